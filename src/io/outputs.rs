//! What a morph leaves in its output directory (SPEC §8): frames, an animated GIF and a
//! lossless animated PNG, a contact sheet, the deformations (reloadable), and the colour code of displacements.
//!
//! Every file is written atomically ([`crate::io::images::write_atomically`]).

use std::path::Path;

use burn::tensor::Tensor;
use image::{Rgb, RgbImage as Rgb8};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::io::images::{RgbImage, to_byte, write_atomically, write_png};
use crate::model::grid::host_values;
use crate::read::read_bytes;

/// The name of frame `k` of `0..=k_max`: `frame_00.png`, or wider when `K ≥ 100`.
pub fn frame_name(k: usize, k_max: usize) -> String {
    let digits = k_max.to_string().len().max(2);
    format!("frame_{k:0digits$}.png")
}

/// Every file name a morph of `k` steps writes into its output directory.
pub fn output_names(k: usize) -> Vec<String> {
    let mut names: Vec<String> = (0..=k).map(|i| frame_name(i, k)).collect();
    names.extend(
        [
            "morph.gif",
            "morph.apng",
            "morph.mp4",
            "sheet.png",
            DEFORMATIONS_HEADER,
            DEFORMATIONS_DATA,
            COMPOSED_HEADER,
            COMPOSED_DATA,
            "energy.csv",
            CONFIG,
            METRICS,
        ]
        .map(String::from),
    );
    names
}

/// The file a temporary file of [`crate::io::images::write_atomically`] (`.NAME.tmp-PID`)
/// stands for, or `name` itself.
pub fn written_name(name: &str) -> &str {
    match name.strip_prefix('.').and_then(|n| n.rsplit_once(".tmp-")) {
        Some((file, pid)) if !pid.is_empty() && pid.bytes().all(|b| b.is_ascii_digit()) => file,
        _ => name,
    }
}

/// Whether `name` is a file a morph writes into its output folder (for any `K`), or a
/// temporary one of those left by a killed writer ([`crate::io::images::write_atomically`]).
pub fn is_morph_output(name: &str) -> bool {
    let name = written_name(name);
    let frame = name
        .strip_prefix("frame_")
        .and_then(|n| n.strip_suffix(".png"))
        .is_some_and(|k| k.len() >= 2 && k.bytes().all(|b| b.is_ascii_digit()));
    let checkpoint = [
        crate::io::checkpoint::CHECKPOINT_HEADER,
        crate::io::checkpoint::CHECKPOINT_DATA,
    ]
    .contains(&name);
    frame || checkpoint || output_names(0).iter().skip(1).any(|n| n == name)
}

/// File name of the run's record (`deepmorph::app::config::RunRecord`).
pub const CONFIG: &str = "config.json";
/// File name of the quality numbers ([`crate::eval::metrics::Metrics`]).
pub const METRICS: &str = "metrics.json";

/// Writes `frame_00.png … frame_K.png`.
///
/// # Errors
///
/// If a file cannot be written.
pub fn write_frames(dir: &Path, frames: &[RgbImage]) -> Result<()> {
    let k = frames.len() - 1;
    for (i, frame) in frames.iter().enumerate() {
        write_png(&dir.join(frame_name(i, k)), &frame.to_rgb8())?;
    }
    Ok(())
}

/// The colour of a displacement `(d_row, d_col)` scaled by `max`: hue = direction (right =
/// red, down = yellow-green, left = cyan, up = violet), brightness ∝ magnitude, saturated.
pub fn displacement_colour(d_row: f64, d_col: f64, max: f64) -> [u8; 3] {
    let magnitude = (d_row * d_row + d_col * d_col).sqrt();
    let value = if max > 0.0 {
        (magnitude / max).min(1.0)
    } else {
        0.0
    };
    let hue = d_row.atan2(d_col).rem_euclid(std::f64::consts::TAU) / std::f64::consts::TAU;
    hsv_to_rgb(hue, 1.0, value)
}

/// HSV in `[0, 1]³` to 8-bit RGB.
fn hsv_to_rgb(h: f64, s: f64, v: f64) -> [u8; 3] {
    let h6 = (h * 6.0).rem_euclid(6.0);
    let c = v * s;
    let x = c * (1.0 - ((h6 % 2.0) - 1.0).abs());
    let (r, g, b) = match h6 as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [r, g, b].map(|t| to_byte((t + m) as f32))
}

/// A colour wheel of side `size`: the legend of [`displacement_colour`] (the rim is the
/// largest displacement of the sheet).
pub fn colour_wheel(size: usize) -> Rgb8 {
    let centre = (size as f64 - 1.0) / 2.0;
    Rgb8::from_fn(size as u32, size as u32, |x, y| {
        let (dc, dr) = (x as f64 - centre, y as f64 - centre);
        if (dr * dr + dc * dc).sqrt() > centre {
            Rgb([255, 255, 255])
        } else {
            Rgb(displacement_colour(dr, dc, centre))
        }
    })
}

/// The contact sheet, like the paper's figures: the frames `u_0..u_K` in the first row; the
/// anisotropies `a_k` in grey under frame `k` in the second; the displacements `φ_k − Id`
/// colour-coded under frame `k` in the third, with the colour wheel under `u_0`.
///
/// # Shapes
/// - `anisotropy`: `[K, H, W]`; `displacement`: `[K, 2, H, W]` (pixel units)
///
/// # Errors
///
/// If the counts or sizes do not fit or a value is NaN.
pub fn contact_sheet(
    frames: &[RgbImage],
    anisotropy: Tensor<3>,
    displacement: Tensor<4>,
) -> Result<Rgb8> {
    let k = frames.len() - 1;
    let (h, w) = (frames[0].height(), frames[0].width());
    let [ka, ha, wa] = anisotropy.dims();
    let [kd, two, hd, wd] = displacement.dims();
    if ka != k || kd != k || two != 2 || (ha, wa) != (h, w) || (hd, wd) != (h, w) {
        return Err(Error::Shape {
            op: "contact_sheet",
            detail: format!(
                "{} frames of {h}x{w}, anisotropy {:?}, displacement {:?}",
                frames.len(),
                [ka, ha, wa],
                [kd, two, hd, wd]
            ),
        });
    }
    let a = host_values(anisotropy)?;
    let d = host_values(displacement)?;
    let max = (0..k * h * w)
        .map(|p| {
            let (kk, at) = (p / (h * w), p % (h * w));
            let base = kk * 2 * h * w;
            d[base + at].hypot(d[base + h * w + at])
        })
        .fold(0.0f64, f64::max);

    let gap = 4;
    let sheet_w = (k + 1) * w + k * gap;
    let sheet_h = 3 * h + 2 * gap;
    let mut sheet = Rgb8::from_pixel(sheet_w as u32, sheet_h as u32, Rgb([255, 255, 255]));
    let mut paste = |img: &Rgb8, col: usize, row: usize| {
        let (x0, y0) = (col * (w + gap), row * (h + gap));
        for (x, y, p) in img.enumerate_pixels() {
            sheet.put_pixel(x0 as u32 + x, y0 as u32 + y, *p);
        }
    };
    for (i, frame) in frames.iter().enumerate() {
        paste(&frame.to_rgb8(), i, 0);
    }
    for kk in 0..k {
        let grey = Rgb8::from_fn(w as u32, h as u32, |x, y| {
            let v = to_byte(a[kk * h * w + y as usize * w + x as usize] as f32);
            Rgb([v, v, v])
        });
        paste(&grey, kk + 1, 1);
        let base = kk * 2 * h * w;
        let colour = Rgb8::from_fn(w as u32, h as u32, |x, y| {
            let at = y as usize * w + x as usize;
            Rgb(displacement_colour(d[base + at], d[base + h * w + at], max))
        });
        paste(&colour, kk + 1, 2);
    }
    let wheel = colour_wheel(h.min(w));
    paste(&wheel, 0, 2);
    Ok(sheet)
}

/// File name of the deformations' header.
pub const DEFORMATIONS_HEADER: &str = "deformations.json";
/// File name of the deformations' values.
pub const DEFORMATIONS_DATA: &str = "deformations.f32";

/// The header of a saved set of deformations: `deformations.f32` holds `φ_1..φ_K` as
/// little-endian float32, row-major `[K, 2, H, W]`, pixel units. `u_{k−1} ≈ u_k ∘ φ_k`
/// (SPEC §5): `φ_k(i, j)` is the point of frame `k` (`[0]` row, `[1]` column) that matches
/// pixel `(i, j)` of frame `k − 1`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DeformationsHeader {
    /// Always `"deepmorph-deformations"`.
    pub format: String,
    /// Format version, 1.
    pub version: u32,
    /// `[K, 2, H, W]`.
    pub shape: [usize; 4],
    /// `"f32le"`.
    pub dtype: String,
    /// `"pixels"`.
    pub units: String,
    /// The values' file, relative to the header.
    pub data: String,
}

/// Saves deformations `[K, 2, H, W]` as [`DEFORMATIONS_HEADER`] + [`DEFORMATIONS_DATA`].
///
/// # Errors
///
/// If a file cannot be written or a value is NaN.
pub fn save_deformations(dir: &Path, phi: Tensor<4>) -> Result<()> {
    save_field(dir, DEFORMATIONS_HEADER, DEFORMATIONS_DATA, phi)
}

/// File name of the composed map's header (same format as the deformations, `K = 1`).
pub const COMPOSED_HEADER: &str = "composed.json";
/// File name of the composed map's values.
pub const COMPOSED_DATA: &str = "composed.f32";

/// Saves the composed map `Φ` `[1, 2, H, W]` as [`COMPOSED_HEADER`] + [`COMPOSED_DATA`], in
/// the deformations' format ([`load_field`] reads it).
///
/// # Errors
///
/// If a file cannot be written or a value is NaN.
pub fn save_composed(dir: &Path, phi: Tensor<4>) -> Result<()> {
    save_field(dir, COMPOSED_HEADER, COMPOSED_DATA, phi)
}

fn save_field(dir: &Path, header_name: &str, data_name: &str, phi: Tensor<4>) -> Result<()> {
    let shape = phi.dims();
    let values = host_values(phi)?;
    let header = DeformationsHeader {
        format: "deepmorph-deformations".into(),
        version: 1,
        shape,
        dtype: "f32le".into(),
        units: "pixels".into(),
        data: data_name.into(),
    };
    let bytes: Vec<u8> = values
        .iter()
        .flat_map(|&v| (v as f32).to_le_bytes())
        .collect();
    write_atomically(&dir.join(data_name), |w| w.write_all(&bytes))?;
    let json = serde_json::to_vec_pretty(&header).expect("header serialises");
    write_atomically(&dir.join(header_name), |w| w.write_all(&json))
}

/// Loads what [`save_deformations`] wrote: the shape `[K, 2, H, W]` and the values.
///
/// # Errors
///
/// If a file is missing or malformed.
pub fn load_deformations(dir: &Path) -> Result<([usize; 4], Vec<f32>)> {
    load_field(&dir.join(DEFORMATIONS_HEADER))
}

/// Loads a field in the deformations' format from its header file: the shape
/// `[N, 2, H, W]` and the values.
///
/// # Errors
///
/// If a file is missing or malformed.
pub fn load_field(header_path: &Path) -> Result<([usize; 4], Vec<f32>)> {
    let dir = header_path.parent().unwrap_or(Path::new("."));
    let malformed = |path: &Path, detail: String| Error::Format {
        path: path.to_path_buf(),
        detail,
    };
    let bytes = read_bytes(header_path, 1 << 20, "deformation header")?;
    let header: DeformationsHeader = serde_json::from_slice(&bytes)
        .map_err(|e| malformed(header_path, format!("not a deformation header: {e}")))?;
    if header.format != "deepmorph-deformations" || header.version != 1 || header.dtype != "f32le" {
        return Err(malformed(
            header_path,
            format!(
                "unsupported format {:?} v{} {}",
                header.format, header.version, header.dtype
            ),
        ));
    }
    // The values live beside the header: a path elsewhere is not followed.
    let plain = Path::new(&header.data)
        .file_name()
        .is_some_and(|n| n == header.data.as_str());
    if !plain || header.data.starts_with('.') {
        return Err(malformed(
            header_path,
            format!(
                "data = {:?}: must name a file in the same folder",
                header.data
            ),
        ));
    }
    let [n, two, h, w] = header.shape;
    let max_side = crate::model::grid::MAX_SIDE;
    if !(1..=MAX_FIELDS).contains(&n)
        || two != 2
        || !(1..=max_side).contains(&h)
        || !(1..=max_side).contains(&w)
    {
        return Err(malformed(
            header_path,
            format!(
                "shape {:?}: expected [N, 2, H, W] with 1 <= N <= {MAX_FIELDS} and sides from 1 \
                 to {max_side}",
                header.shape
            ),
        ));
    }
    let data_path = dir.join(&header.data);
    let expected = 4 * n * two * h * w;
    let bytes = read_bytes(
        &data_path,
        expected as u64,
        "deformation file of that shape",
    )?;
    if bytes.len() != expected {
        return Err(malformed(
            &data_path,
            format!(
                "{} bytes, shape {:?} needs {expected} (truncated)",
                bytes.len(),
                header.shape
            ),
        ));
    }
    let values: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    if let Some(at) = values.iter().position(|v| !v.is_finite()) {
        return Err(malformed(
            &data_path,
            format!("value {at} is {}: not a deformation", values[at]),
        ));
    }
    Ok((header.shape, values))
}

/// The most fields a deformation file may hold (`K` is at most 10000).
const MAX_FIELDS: usize = 10_000;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn colour_code_directions() {
        assert_eq!(displacement_colour(0.0, 1.0, 1.0), [255, 0, 0]); // right: red
        assert_eq!(displacement_colour(0.0, -1.0, 1.0), [0, 255, 255]); // left: cyan
        assert_eq!(displacement_colour(0.0, 0.0, 1.0), [0, 0, 0]); // none: black
        assert_eq!(displacement_colour(0.0, 0.5, 1.0), [128, 0, 0]); // half as bright
        assert_eq!(frame_name(3, 15), "frame_03.png");
        assert_eq!(frame_name(7, 120), "frame_007.png");
        for name in output_names(120) {
            assert!(is_morph_output(&name), "{name}");
        }
        assert!(is_morph_output(".frame_054.png.tmp-22172"));
        for name in [
            "frame_1.png",
            "frame_01.jpg",
            "notes.txt",
            ".config.json.tmp-",
            "a.png",
        ] {
            assert!(!is_morph_output(name), "{name}");
        }
    }

    /// A deformation header and its values, `[1, 2, 2, 3]`.
    fn seed_field() -> (Vec<u8>, Vec<u8>) {
        let header = DeformationsHeader {
            format: "deepmorph-deformations".into(),
            version: 1,
            shape: [1, 2, 2, 3],
            dtype: "f32le".into(),
            units: "pixels".into(),
            data: DEFORMATIONS_DATA.into(),
        };
        let values = (0..12).flat_map(|i| (i as f32).to_le_bytes()).collect();
        (serde_json::to_vec(&header).unwrap(), values)
    }

    /// Writes a header and values into a fresh folder and loads them.
    fn load_written(header: &[u8], values: &[u8]) -> Result<([usize; 4], Vec<f32>)> {
        let dir = std::env::temp_dir().join(format!(
            "deepmorph-fuzz-field-{}-{:?}",
            std::process::id(),
            std::thread::current().id()
        ));
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join(DEFORMATIONS_HEADER), header).unwrap();
        std::fs::write(dir.join(DEFORMATIONS_DATA), values).unwrap();
        let loaded = load_deformations(&dir);
        std::fs::remove_dir_all(&dir).unwrap();
        loaded
    }

    #[test]
    fn the_seed_field_loads() {
        let (header, values) = seed_field();
        let (shape, phi) = load_written(&header, &values).unwrap();
        assert_eq!((shape, phi[11]), ([1, 2, 2, 3], 11.0));
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(crate::fuzz::cases() / 3))]

        #[test]
        fn fuzz_field_header(header in crate::fuzz::mutated(seed_field().0)) {
            let values = seed_field().1;
            crate::fuzz::within_allowance(&header, |h| {
                let _ = load_written(h, &values);
            });
        }

        #[test]
        fn fuzz_field_values(values in crate::fuzz::mutated(seed_field().1)) {
            let header = seed_field().0;
            crate::fuzz::within_allowance(&values, |v| {
                let _ = load_written(&header, v);
            });
        }
    }
}
