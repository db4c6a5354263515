//! `deepmorph warp`: a synthetic pair with a known correspondence, written as a folder
//! (`a.png`, `b.png`, `truth.flo`) that `deepmorph morph` and `deepmorph eval --truth` read.

use std::path::{Path, PathBuf};

use burn::tensor::Device;

use crate::error::Result;
use crate::eval::synthetic::{Field, warped_pair};
use crate::io::images::{RgbImage, write_png};
use crate::io::output_folder::OutputFolder;

/// The files `deepmorph warp` writes.
pub const WARP_OUTPUTS: [&str; 3] = ["a.png", "b.png", "truth.flo"];

/// What [`write_warped_pair`] wrote.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WarpedPair {
    /// The folder, in place.
    pub folder: PathBuf,
    /// The image's width and height in pixels (that of both files and of the truth).
    pub size: (usize, usize),
}

/// Reads `image`, warps it by `field` of size `amount` (computed on `device`) and writes
/// the warped image as `a.png`, the image itself as `b.png` and the correspondence from A
/// to B as `truth.flo` into `out`, as one transaction ([`OutputFolder`]: a folder with
/// files of ours is replaced only with `force`, one with other files never).
///
/// # Errors
///
/// An unreadable image, an `amount` that folds the field, or a folder that cannot be
/// written or must not be replaced.
pub fn write_warped_pair(
    image: &Path,
    field: Field,
    amount: f64,
    out: &Path,
    force: bool,
    device: &Device,
) -> Result<WarpedPair> {
    let input = RgbImage::load(image)?;
    let (warped, truth) = warped_pair(&input, field, amount, device)?;
    let folder = OutputFolder::begin(out, &[image], |name| WARP_OUTPUTS.contains(&name), force)?;
    let staging = folder.path();
    write_png(&staging.join("a.png"), &warped.to_rgb8())?;
    write_png(&staging.join("b.png"), &input.to_rgb8())?;
    truth.write_flo(&staging.join("truth.flo"))?;
    Ok(WarpedPair {
        folder: folder.commit()?,
        size: (input.width(), input.height()),
    })
}
