//! Ground-truth correspondences and the endpoint error of a composed deformation.
//!
//! A correspondence assigns to a pixel `(i, j)` of the first image `A` the point `(y, x)` of
//! the last image `B` that shows the same thing, or nothing where that is unknown. A morph's
//! composed map `Φ = φ_K ∘ … ∘ φ_1` claims exactly such a correspondence (`u_0 ≈ u_K ∘ Φ`,
//! SPEC §5), so the endpoint error `|Φ(i, j) − (y, x)|` measures how right it is.
//!
//! Two file formats are read:
//! - **Middlebury disparity PNG** (16-bit grey, value = disparity × 256, 0 = unknown): the
//!   left pixel `(i, j)` matches the right pixel `(i, j − d)`.
//! - **Middlebury `.flo`** (the optical-flow format of Baker et al.): the bytes `PIEH`
//!   (the float32 202021.25), width and height as little-endian int32, then per pixel,
//!   row-major, the float32 pair `(u, v)` = (column, row) displacement; a component above
//!   1e9 in magnitude marks an unknown pixel. [`Correspondence::write_flo`] writes it.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::io::images::{MAX_IMAGE_SIDE, decode_image, write_atomically};
use crate::read::{read_bytes, read_prefix};

/// The `.flo` tag: the float32 202021.25, whose little-endian bytes spell `PIEH`.
const FLO_TAG: &[u8; 4] = b"PIEH";
/// Flow components above this magnitude mark unknown pixels in `.flo` files.
const FLO_UNKNOWN: f32 = 1e9;

/// A ground-truth correspondence on an `H × W` grid: per pixel the displacement
/// `(Δrow, Δcolumn)` in pixels to the matching point, or `None` where unknown.
#[derive(Clone, Debug, PartialEq)]
pub struct Correspondence {
    height: usize,
    width: usize,
    displacement: Vec<Option<[f64; 2]>>,
}

/// Endpoint error of a deformation against a [`Correspondence`], over the pixels with
/// known truth, in pixels of the grid they were compared on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EndpointError {
    /// Pixels with known truth.
    pub pixels: usize,
    /// Mean endpoint error.
    pub mean: f64,
    /// Median endpoint error.
    pub median: f64,
    /// Share of known pixels with an error below 1 pixel.
    pub under_1px: f64,
    /// Share of known pixels with an error below 3 pixels.
    pub under_3px: f64,
    /// Mean error of the identity map, i.e. the mean true displacement: what "no
    /// correspondence at all" scores.
    pub identity_mean: f64,
}

impl Correspondence {
    /// A correspondence from per-pixel displacements, row-major.
    ///
    /// # Errors
    ///
    /// If the length does not fit the size or a known displacement is not finite.
    pub fn new(height: usize, width: usize, displacement: Vec<Option<[f64; 2]>>) -> Result<Self> {
        if displacement.len() != height * width {
            return Err(Error::Shape {
                op: "Correspondence::new",
                detail: format!(
                    "{} displacements for a {height}x{width} grid",
                    displacement.len()
                ),
            });
        }
        if displacement
            .iter()
            .flatten()
            .flatten()
            .any(|v| !v.is_finite())
        {
            return Err(Error::NonFinite {
                what: "a known ground-truth displacement".into(),
            });
        }
        Ok(Self {
            height,
            width,
            displacement,
        })
    }

    /// Rows.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Columns.
    pub fn width(&self) -> usize {
        self.width
    }

    /// The displacement at `(i, j)`, if known.
    pub fn at(&self, i: usize, j: usize) -> Option<[f64; 2]> {
        self.displacement[i * self.width + j]
    }

    /// Reads a truth file: `.flo` by its extension, anything else as a disparity PNG.
    ///
    /// # Errors
    ///
    /// [`Error::Io`] or [`Error::Format`] naming the file and what is wrong with it.
    pub fn load(path: &Path) -> Result<Self> {
        let is_flo = path
            .extension()
            .is_some_and(|e| e.eq_ignore_ascii_case("flo"));
        if is_flo {
            Self::read_flo(path)
        } else {
            Self::read_disparity(path)
        }
    }

    /// Reads a Middlebury disparity map: 16-bit grey, disparity × 256, 0 = unknown. The
    /// left pixel `(i, j)` matches the right pixel `(i, j − d)`.
    ///
    /// # Errors
    ///
    /// If the file is unreadable or not a 16-bit grey image.
    pub fn read_disparity(path: &Path) -> Result<Self> {
        let decoded = decode_image(path)?;
        let grey = decoded.as_luma16().ok_or_else(|| Error::Format {
            path: path.to_path_buf(),
            detail: format!(
                "a disparity map must be 16-bit grey (value = disparity x 256), this is {:?}",
                decoded.color()
            ),
        })?;
        let (w, h) = (grey.width() as usize, grey.height() as usize);
        let displacement = grey
            .pixels()
            .map(|p| (p[0] > 0).then(|| [0.0, -f64::from(p[0]) / 256.0]))
            .collect();
        Self::new(h, w, displacement)
    }

    /// Reads a Middlebury `.flo` file (see the module docs).
    ///
    /// # Errors
    ///
    /// If the file is unreadable, has no `PIEH` tag, an implausible size, or is truncated.
    pub fn read_flo(path: &Path) -> Result<Self> {
        let bad = |detail: String| Error::Format {
            path: path.to_path_buf(),
            detail,
        };
        // The header says how much follows: read that much and one byte more, never more.
        let size = flo_size(&read_prefix(path, 12, "flow file")?).map_err(bad)?;
        let bytes = read_bytes(path, flo_bytes(size) as u64, "flow file of that size")?;
        Self::from_flo_bytes(&bytes).map_err(bad)
    }

    /// A `.flo` file's contents (see [`Correspondence::read_flo`]).
    fn from_flo_bytes(bytes: &[u8]) -> std::result::Result<Self, String> {
        let (h, w) = flo_size(bytes)?;
        let expected = flo_bytes((h, w));
        if bytes.len() != expected {
            return Err(format!(
                "{} bytes, a flow of this size needs {expected} (truncated or trailing data)",
                bytes.len()
            ));
        }
        let displacement = bytes[12..]
            .chunks_exact(8)
            .map(|p| {
                let u = f32::from_le_bytes(p[..4].try_into().expect("4 bytes"));
                let v = f32::from_le_bytes(p[4..].try_into().expect("4 bytes"));
                let known = u.is_finite()
                    && v.is_finite()
                    && u.abs() <= FLO_UNKNOWN
                    && v.abs() <= FLO_UNKNOWN;
                known.then(|| [f64::from(v), f64::from(u)])
            })
            .collect();
        Self::new(h, w, displacement).map_err(|e| e.to_string())
    }

    /// Writes the correspondence as a `.flo` file (unknown pixels as 1e10), atomically.
    ///
    /// # Errors
    ///
    /// [`Error::Io`] naming the file.
    pub fn write_flo(&self, path: &Path) -> Result<()> {
        let mut bytes = Vec::with_capacity(12 + 8 * self.displacement.len());
        bytes.extend_from_slice(FLO_TAG);
        bytes.extend_from_slice(&(self.width as i32).to_le_bytes());
        bytes.extend_from_slice(&(self.height as i32).to_le_bytes());
        for d in &self.displacement {
            let [v, u] = d.map_or([1e10f32; 2], |[r, c]| [r as f32, c as f32]);
            bytes.extend_from_slice(&u.to_le_bytes());
            bytes.extend_from_slice(&v.to_le_bytes());
        }
        write_atomically(path, |w| w.write_all(&bytes))
    }

    /// The correspondence on an `h × w` grid that covers the same image (the morph's working
    /// size), with displacements in that grid's pixels.
    ///
    /// Pixel centres are matched as the image resizer does (`(i + ½)·s − ½`, `s` the size
    /// ratio per axis); the nearest source pixel supplies the truth, so an unknown pixel or a
    /// depth edge is never blended into a made-up displacement.
    pub fn resampled(&self, h: usize, w: usize) -> Self {
        let (sy, sx) = (self.height as f64 / h as f64, self.width as f64 / w as f64);
        let nearest = |i: usize, s: f64, n: usize| {
            (((i as f64 + 0.5) * s - 0.5).round().max(0.0) as usize).min(n - 1)
        };
        let displacement = (0..h)
            .flat_map(|i| (0..w).map(move |j| (i, j)))
            .map(|(i, j)| {
                self.at(nearest(i, sy, self.height), nearest(j, sx, self.width))
                    .map(|[dy, dx]| [dy / sy, dx / sx])
            })
            .collect();
        Self {
            height: h,
            width: w,
            displacement,
        }
    }

    /// The endpoint error of the map `phi` (row-major `[2, H, W]`, pixel units, `[0]` rows)
    /// on this grid.
    ///
    /// # Errors
    ///
    /// If `phi` does not have `2·H·W` values, or no pixel has known truth.
    pub fn endpoint_error(&self, phi: &[f64]) -> Result<EndpointError> {
        let n = self.height * self.width;
        if phi.len() != 2 * n {
            return Err(Error::Shape {
                op: "endpoint_error",
                detail: format!(
                    "{} values for a deformation of a {}x{} grid",
                    phi.len(),
                    self.height,
                    self.width
                ),
            });
        }
        let mut errors = Vec::with_capacity(n);
        let mut identity = 0.0;
        for (p, d) in self.displacement.iter().enumerate() {
            let Some([dy, dx]) = *d else { continue };
            let (i, j) = ((p / self.width) as f64, (p % self.width) as f64);
            let (y, x) = (i + dy, j + dx);
            errors.push((phi[p] - y).hypot(phi[n + p] - x));
            identity += dy.hypot(dx);
        }
        if errors.is_empty() {
            return Err(Error::Shape {
                op: "endpoint_error",
                detail: "the ground truth has no known pixel".into(),
            });
        }
        let count = errors.len() as f64;
        let share = |limit: f64| errors.iter().filter(|&&e| e < limit).count() as f64 / count;
        let (under_1px, under_3px) = (share(1.0), share(3.0));
        let mean = errors.iter().sum::<f64>() / count;
        errors.sort_by(f64::total_cmp);
        let m = errors.len();
        let median = if m % 2 == 1 {
            errors[m / 2]
        } else {
            0.5 * (errors[m / 2 - 1] + errors[m / 2])
        };
        Ok(EndpointError {
            pixels: m,
            mean,
            median,
            under_1px,
            under_3px,
            identity_mean: identity / count,
        })
    }
}

/// The size `(H, W)` a `.flo` header (a file's first 12 bytes) declares.
fn flo_size(header: &[u8]) -> std::result::Result<(usize, usize), String> {
    if header.len() < 12 || &header[..4] != FLO_TAG {
        return Err("not a .flo file (no PIEH tag)".into());
    }
    let int = |at: usize| i32::from_le_bytes(header[at..at + 4].try_into().expect("4 bytes"));
    let (w, h) = (int(4), int(8));
    let side = 1..=MAX_IMAGE_SIDE as i32;
    if !side.contains(&w) || !side.contains(&h) {
        return Err(format!(
            "implausible size {w}x{h} (sides from 1 to {MAX_IMAGE_SIDE})"
        ));
    }
    Ok((h as usize, w as usize))
}

/// The bytes of a `.flo` file of `H × W`.
fn flo_bytes((h, w): (usize, usize)) -> usize {
    12 + 8 * h * w
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> std::path::PathBuf {
        let dir =
            std::env::temp_dir().join(format!("deepmorph-truth-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    fn identity(h: usize, w: usize) -> Vec<f64> {
        let rows = (0..h * w).map(|p| (p / w) as f64);
        let cols = (0..h * w).map(|p| (p % w) as f64);
        rows.chain(cols).collect()
    }

    #[test]
    fn flo_round_trip_keeps_unknown_pixels() {
        let truth = Correspondence::new(
            2,
            3,
            vec![
                Some([0.5, -1.25]),
                None,
                Some([2.0, 0.0]),
                Some([-3.5, 4.0]),
                Some([0.0, 0.0]),
                None,
            ],
        )
        .unwrap();
        let dir = scratch("flo");
        let path = dir.join("t.flo");
        truth.write_flo(&path).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(
            f32::from_le_bytes(bytes[..4].try_into().unwrap()),
            202021.25
        );
        assert_eq!(Correspondence::load(&path).unwrap(), truth);

        std::fs::write(&path, &bytes[..bytes.len() - 1]).unwrap();
        let err = Correspondence::load(&path).unwrap_err().to_string();
        assert!(err.contains("truncated"), "{err}");
        std::fs::write(&path, b"PIEX....").unwrap();
        let err = Correspondence::load(&path).unwrap_err().to_string();
        assert!(err.contains("PIEH"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn disparity_png_means_a_leftward_match() {
        let dir = scratch("disparity");
        let path = dir.join("d.png");
        let img =
            image::ImageBuffer::<image::Luma<u16>, _>::from_vec(3, 1, vec![0u16, 256 * 5, 128])
                .unwrap();
        img.save(&path).unwrap();
        let truth = Correspondence::load(&path).unwrap();
        assert_eq!(truth.at(0, 0), None);
        assert_eq!(truth.at(0, 1), Some([0.0, -5.0]));
        assert_eq!(truth.at(0, 2), Some([0.0, -0.5]));

        let rgb = dir.join("rgb.png");
        image::RgbImage::new(2, 2).save(&rgb).unwrap();
        let err = Correspondence::load(&rgb).unwrap_err().to_string();
        assert!(err.contains("16-bit grey"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn resampling_scales_displacements_per_axis() {
        // 4 × 6 with a constant displacement (2, −3): on a 2 × 2 grid rows shrink by 2 and
        // columns by 3, so the displacement becomes (1, −1).
        let truth = Correspondence::new(4, 6, vec![Some([2.0, -3.0]); 24]).unwrap();
        let small = truth.resampled(2, 2);
        assert!((0..2).all(|i| (0..2).all(|j| small.at(i, j) == Some([1.0, -1.0]))));
    }

    #[test]
    fn endpoint_error_is_zero_for_the_truth_and_large_for_a_wrong_map() {
        let (h, w) = (5, 7);
        let shift = [0.5, -2.0];
        let mut known = vec![Some(shift); h * w];
        known[3] = None;
        let truth = Correspondence::new(h, w, known).unwrap();
        let id = identity(h, w);
        let right: Vec<f64> = (0..2 * h * w).map(|p| id[p] + shift[p / (h * w)]).collect();
        let e = truth.endpoint_error(&right).unwrap();
        assert_eq!(e.pixels, h * w - 1);
        assert!(e.mean < 1e-12 && e.median < 1e-12 && e.under_1px == 1.0);
        let norm = shift[0].hypot(shift[1]);
        assert!((e.identity_mean - norm).abs() < 1e-12);

        let wrong = truth.endpoint_error(&id).unwrap();
        assert!(
            (wrong.mean - norm).abs() < 1e-12 && wrong.under_1px == 0.0 && wrong.under_3px == 1.0
        );
        assert!(truth.endpoint_error(&id[1..]).is_err());
    }

    /// A 3×2 `.flo` with one unknown pixel.
    fn seed_flo() -> Vec<u8> {
        let mut bytes = FLO_TAG.to_vec();
        bytes.extend(3i32.to_le_bytes());
        bytes.extend(2i32.to_le_bytes());
        for i in 0..6 {
            let u = if i == 4 { 1e10f32 } else { i as f32 * 0.5 };
            bytes.extend(u.to_le_bytes());
            bytes.extend((-u).to_le_bytes());
        }
        bytes
    }

    #[test]
    fn the_seed_flo_reads() {
        let truth = Correspondence::from_flo_bytes(&seed_flo()).unwrap();
        assert_eq!((truth.height(), truth.width()), (2, 3));
        assert_eq!(truth.at(0, 1), Some([-0.5, 0.5]));
        assert_eq!(truth.at(1, 1), None);
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(crate::fuzz::cases()))]

        #[test]
        fn fuzz_flo(bytes in crate::fuzz::mutated(seed_flo())) {
            crate::fuzz::within_allowance(&bytes, |b| {
                let _ = Correspondence::from_flo_bytes(b);
                let _ = flo_size(b);
            });
        }

        #[test]
        fn fuzz_flo_random(bytes in crate::fuzz::random_bytes()) {
            crate::fuzz::within_allowance(&bytes, |b| {
                let _ = Correspondence::from_flo_bytes(b);
            });
        }
    }
}
