//! Image files ↔ host images ↔ tensors, and crash-safe file writing.

use std::fs;
use std::io::Write;
use std::path::{Path, PathBuf};

use burn::tensor::Tensor;
use image::ImageDecoder;
use image::imageops::FilterType;

use crate::error::{Error, Result};
use crate::model::grid::{Grid, host_values};
use crate::read::read_bytes;

/// An RGB image on the host: values in `[0, 1]`, channel-major `[3, H, W]`.
#[derive(Clone, Debug, PartialEq)]
pub struct RgbImage {
    height: usize,
    width: usize,
    data: Vec<f32>,
}

impl RgbImage {
    /// An image from channel-major values (`3 · height · width` of them).
    ///
    /// # Errors
    ///
    /// If the length does not fit the size or a value is not finite.
    pub fn new(height: usize, width: usize, data: Vec<f32>) -> Result<Self> {
        if data.len() != 3 * height * width {
            return Err(Error::Shape {
                op: "RgbImage::new",
                detail: format!("{} values for a 3x{height}x{width} image", data.len()),
            });
        }
        if let Some(bad) = data.iter().find(|v| !v.is_finite()) {
            return Err(Error::NonFinite {
                what: format!("image value {bad}"),
            });
        }
        Ok(Self {
            height,
            width,
            data,
        })
    }

    /// Reads any format the `image` crate decodes here (PNG, JPEG, GIF, BMP, TIFF, WebP,
    /// PNM, TGA, QOI). Alpha is dropped, grey is expanded to RGB, 16-bit is scaled to
    /// `[0, 1]`.
    ///
    /// # Errors
    ///
    /// [`Error::Image`] naming the file if it cannot be read or decoded.
    pub fn load(path: &Path) -> Result<Self> {
        Ok(Self::read(path)?.0)
    }

    /// As [`load`](Self::load), with what the file's decoding should tell a person: a JPEG
    /// whose data stops before its end marker is decoded with its missing rows grey by the
    /// decoder, which says nothing (issue 43 #9).
    ///
    /// # Errors
    ///
    /// As [`load`](Self::load).
    pub fn read(path: &Path) -> Result<(Self, Option<String>)> {
        let (image, warning) = decode_image_noting(path)?;
        Ok((Self::from_dynamic(&image), warning))
    }

    /// An 8-bit image as [`load`](Self::load) reads it from a PNG file.
    pub fn from_rgb8(img: &image::RgbImage) -> Self {
        Self::from_dynamic(&image::DynamicImage::ImageRgb8(img.clone()))
    }

    fn from_dynamic(img: &image::DynamicImage) -> Self {
        let (w, h) = (img.width() as usize, img.height() as usize);
        let mut data = vec![0.0f32; 3 * h * w];
        // Converted a band of rows at a time: a float copy of the whole image would add 12
        // bytes a pixel to the peak (3.2 GB for a 16384² input). Per pixel, so the same.
        const BAND: u32 = 64;
        for top in (0..img.height()).step_by(BAND as usize) {
            let rows = BAND.min(img.height() - top);
            let band = img.crop_imm(0, top, img.width(), rows).to_rgb32f();
            for (x, y, p) in band.enumerate_pixels() {
                let at = (top + y) as usize * w + x as usize;
                for c in 0..3 {
                    data[c * h * w + at] = p[c].clamp(0.0, 1.0);
                }
            }
        }
        Self {
            height: h,
            width: w,
            data,
        }
    }

    /// `(rows, columns)`.
    pub fn size(&self) -> (usize, usize) {
        (self.height, self.width)
    }

    /// Rows.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Columns.
    pub fn width(&self) -> usize {
        self.width
    }

    /// The channel-major values.
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// Resampled to `height × width` with a Lanczos-3 filter (bringing inputs to the
    /// working size is outside the model, SPEC §7, so any good resampling will do).
    pub fn resized(&self, height: usize, width: usize) -> Self {
        if (height, width) == (self.height, self.width) {
            return self.clone();
        }
        let resized = image::imageops::resize(
            &self.to_rgb32f(),
            width as u32,
            height as u32,
            FilterType::Lanczos3,
        );
        Self::from_dynamic(&image::DynamicImage::ImageRgb32F(resized))
    }

    fn to_rgb32f(&self) -> image::Rgb32FImage {
        let (h, w) = (self.height, self.width);
        image::Rgb32FImage::from_fn(w as u32, h as u32, |x, y| {
            let at = y as usize * w + x as usize;
            image::Rgb([0, 1, 2].map(|c| self.data[c * h * w + at]))
        })
    }

    /// 8-bit RGB, values clamped to `[0, 1]` (SPEC §8).
    pub fn to_rgb8(&self) -> image::RgbImage {
        let (h, w) = (self.height, self.width);
        image::RgbImage::from_fn(w as u32, h as u32, |x, y| {
            let at = y as usize * w + x as usize;
            image::Rgb([0, 1, 2].map(|c| to_byte(self.data[c * h * w + at])))
        })
    }

    /// The image as a `[1, 3, H, W]` tensor on `grid`'s device and dtype.
    ///
    /// # Errors
    ///
    /// If the grid's size differs from the image's.
    pub fn to_tensor(&self, grid: &Grid) -> Result<Tensor<4>> {
        if (grid.height(), grid.width()) != (self.height, self.width) {
            return Err(Error::Shape {
                op: "RgbImage::to_tensor",
                detail: format!(
                    "image is {}x{}, grid is {}x{}",
                    self.height,
                    self.width,
                    grid.height(),
                    grid.width()
                ),
            });
        }
        let values = self.data.iter().map(|&v| f64::from(v)).collect();
        Ok(grid.tensor(values, [1, 3, self.height, self.width]))
    }

    /// The image of a `[1, 3, H, W]` (or `[3, H, W]`-sized) tensor, clamped to `[0, 1]`.
    ///
    /// # Errors
    ///
    /// If the tensor does not hold 3 channels or holds a NaN.
    pub fn from_tensor(t: Tensor<4>) -> Result<Self> {
        let [n, c, h, w] = t.dims();
        if n != 1 || c != 3 {
            return Err(Error::Shape {
                op: "RgbImage::from_tensor",
                detail: format!("expected [1, 3, H, W], got {:?}", t.dims()),
            });
        }
        let data = host_values(t)?
            .into_iter()
            .map(|v| v.clamp(0.0, 1.0) as f32)
            .collect();
        Self::new(h, w, data)
    }
}

/// The largest side of an input image in pixels (the working size's limit is smaller:
/// [`crate::model::grid::MAX_SIDE`]); a larger one is refused from its header, before decoding.
pub const MAX_IMAGE_SIDE: u32 = 16384;
/// The largest image file read.
pub const MAX_IMAGE_FILE_BYTES: u64 = 1 << 30;

/// Reads and decodes an image file in any format the `image` crate decodes here, guessing
/// the format from the contents. The file is read whole first (so pipes work too), and the
/// size in its header is checked against [`MAX_IMAGE_SIDE`] before anything is decoded.
///
/// # Errors
///
/// [`Error::Io`], [`Error::Format`] (too large) or [`Error::Image`] naming the file.
pub fn decode_image(path: &Path) -> Result<image::DynamicImage> {
    Ok(decode_image_noting(path)?.0)
}

/// [`decode_image`] with a warning for a file that decodes but is damaged.
fn decode_image_noting(path: &Path) -> Result<(image::DynamicImage, Option<String>)> {
    let bytes = read_bytes(path, MAX_IMAGE_FILE_BYTES, "image file")?;
    let image_error = |cause| Error::Image {
        path: path.to_path_buf(),
        cause,
    };
    // By content, else by extension: TGA has no signature to recognise it by.
    let format = image::guess_format(&bytes)
        .ok()
        .or_else(|| image::ImageFormat::from_path(path).ok());
    let reader = || {
        let mut reader = image::ImageReader::new(std::io::Cursor::new(&bytes[..]));
        if let Some(format) = format {
            reader.set_format(format);
        }
        reader
    };
    let (w, h) = reader().into_dimensions().map_err(image_error)?;
    if w.max(h) > MAX_IMAGE_SIDE {
        return Err(Error::Format {
            path: path.to_path_buf(),
            detail: format!(
                "a {w}x{h} image: at most {MAX_IMAGE_SIDE} pixels per side are read (the \
                 working size is at most {} anyway)",
                crate::model::grid::MAX_SIDE
            ),
        });
    }
    // Decoded, converted to float and resized, an image takes its decoded bytes plus 24 a
    // pixel at the peak: refused before decoding if that does not fit the memory this
    // process may take (issue 43 #6: a 783 kB PNG of 16384² zeros took 7.1 GB, and under
    // `ulimit -v` the allocation failed with a panic).
    let decoded = reader().into_decoder().map_err(image_error)?.total_bytes();
    let needed = decoded.saturating_add(24 * u64::from(w) * u64::from(h));
    if let Some((room, limit)) = crate::host_memory::host_limit()
        && needed > room
    {
        return Err(Error::Format {
            path: path.to_path_buf(),
            detail: format!(
                "a {w}x{h} image needs about {:.1} GiB to read and resize, more than {limit} \
                 ({:.1} GiB): give a smaller image",
                needed as f64 / f64::from(1u32 << 30),
                room as f64 / f64::from(1u32 << 30),
            ),
        });
    }
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_IMAGE_SIDE);
    limits.max_image_height = Some(MAX_IMAGE_SIDE);
    // The decoder may allocate what the header says the image holds, and its own buffers.
    limits.max_alloc = Some(decoded.saturating_add(64 << 20));
    let mut reader = reader();
    reader.limits(limits);
    let image = reader.decode().map_err(image_error)?;
    let warning = (format == Some(image::ImageFormat::Jpeg) && !jpeg_has_end(&bytes)).then(|| {
        format!(
            "warning: {}: the JPEG data ends before its end marker (a truncated file?); the \
             decoder filled what is missing",
            path.display()
        )
    });
    Ok((image, warning))
}

/// Whether a JPEG file holds its end-of-image marker (`FF D9`) near its end. Entropy-coded
/// data never holds `FF D9` (a data byte `FF` is followed by `00`), so a file cut anywhere in
/// its scan lacks it; a few kB of trailing bytes after it are tolerated, as decoders do.
fn jpeg_has_end(bytes: &[u8]) -> bool {
    let tail = &bytes[bytes.len().saturating_sub(4096)..];
    tail.windows(2).any(|w| w == [0xFF, 0xD9])
}

/// `[0, 1]` → `0..=255`, rounded.
pub fn to_byte(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Writes a file so that a crash never leaves half of it: the bytes go to a temporary file
/// beside the target, which is then renamed over it.
///
/// # Errors
///
/// [`Error::Io`] naming the file.
pub fn write_atomically(
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> std::io::Result<()>,
) -> Result<()> {
    let io_error = |source| Error::Io {
        path: path.to_path_buf(),
        cause: source,
    };
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let temporary: PathBuf = path.with_file_name(format!(".{name}.tmp-{}", std::process::id()));
    let result = (|| {
        let mut file = std::io::BufWriter::new(fs::File::create(&temporary)?);
        write(&mut file)?;
        file.into_inner().map_err(|e| e.into_error())?.sync_all()?;
        fs::rename(&temporary, path)
    })();
    if result.is_err() {
        let _ = fs::remove_file(&temporary);
    }
    result.map_err(io_error)
}

/// Encodes `img` as PNG and writes it atomically.
///
/// # Errors
///
/// [`Error::Io`] or [`Error::Image`] naming the file.
pub fn write_png(path: &Path, img: &image::RgbImage) -> Result<()> {
    let mut bytes = Vec::new();
    img.write_to(
        &mut std::io::Cursor::new(&mut bytes),
        image::ImageFormat::Png,
    )
    .map_err(|e| Error::Image {
        path: path.to_path_buf(),
        cause: e,
    })?;
    write_atomically(path, |w| w.write_all(&bytes))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn png_round_trip_and_grey_expansion() {
        let dir = std::env::temp_dir().join(format!("deepmorph-io-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let img = RgbImage::new(2, 3, (0..18).map(|i| i as f32 / 17.0).collect()).unwrap();
        let path = dir.join("a.png");
        write_png(&path, &img.to_rgb8()).unwrap();
        let back = RgbImage::load(&path).unwrap();
        assert_eq!((back.height(), back.width()), (2, 3));
        for (a, b) in img.data().iter().zip(back.data()) {
            assert!((a - b).abs() <= 0.5 / 255.0 + 1e-6);
        }
        let grey = image::GrayImage::from_fn(3, 2, |x, _| image::Luma([(x * 100) as u8]));
        let path = dir.join("g.png");
        grey.save(&path).unwrap();
        let back = RgbImage::load(&path).unwrap();
        assert_eq!(back.data()[1], back.data()[6 + 1]);
        assert_eq!(back.data()[1], back.data()[12 + 1]);
        let err = RgbImage::load(&dir.join("missing.png"))
            .unwrap_err()
            .to_string();
        assert!(err.contains("missing.png"), "{err}");
        fs::remove_dir_all(&dir).unwrap();
    }

    /// A JPEG cut in its scan data decodes (the decoder fills the rest) and is reported; the
    /// whole file is not (issue 43 #9).
    #[test]
    fn a_truncated_jpeg_is_reported() {
        let dir = std::env::temp_dir().join(format!("deepmorph-jpeg-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let img = image::RgbImage::from_fn(64, 48, |x, y| {
            image::Rgb([(x * 4) as u8, (y * 5) as u8, ((x * y) % 256) as u8])
        });
        let whole = dir.join("whole.jpg");
        img.save(&whole).unwrap();
        let (_, warning) = RgbImage::read(&whole).unwrap();
        assert_eq!(warning, None);
        let bytes = std::fs::read(&whole).unwrap();
        let cut = dir.join("cut.jpg");
        std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
        let (image, warning) = RgbImage::read(&cut).unwrap();
        assert_eq!(image.size(), (48, 64));
        let warning = warning.expect("a warning for the truncated file");
        assert!(
            warning.contains("cut.jpg") && warning.contains("end marker"),
            "{warning}"
        );
        std::fs::remove_dir_all(&dir).ok();
    }

    /// TGA has no signature: it is read by its extension (README lists it among the inputs).
    #[test]
    fn tga_is_read_by_its_extension() {
        let dir = std::env::temp_dir().join(format!("deepmorph-tga-{}", std::process::id()));
        fs::create_dir_all(&dir).unwrap();
        let path = dir.join("a.tga");
        let img =
            image::RgbImage::from_fn(5, 4, |x, y| image::Rgb([(40 * x) as u8, (60 * y) as u8, 7]));
        img.save(&path).unwrap();
        let back = RgbImage::load(&path).unwrap();
        assert_eq!((back.height(), back.width()), (4, 5));
        assert_eq!(back.to_rgb8(), img);
        fs::remove_dir_all(&dir).unwrap();
    }
}
