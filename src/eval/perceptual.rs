//! The path in VGG19 feature space: how far adjacent frames are apart as the deep model's
//! network sees them, the unlearned cousin of the LPIPS distance behind the perceptual path
//! length (PPL) and path deviation (PDV) of the morphing literature.
//!
//! The distance of two frames `u`, `v` is
//! `d(u, v) = √( (1/5) Σ_s mean((F_s(u) − F_s(v))²) / r_s² )`
//! over VGG19's five taps `F_s` (relu1_2 … relu5_4, the deep model's, SPEC §4), each taken
//! relative to `r_s`, the RMS of that tap on the two endpoints together: every tap weighs
//! the same whatever its scale (as the deep model's `τ`-scaling makes them), and `d` is a
//! pure number, 1 ≈ as far as a tap's typical activation. The frames are the written 8-bit
//! images; the cross-fade baseline is measured the same way. Unlike in pixel space, the
//! cross-fade is not the shortest path here: a morph that transports content can be shorter
//! and more even in feature space than the blend.

use burn::tensor::Tensor;

use crate::error::{Error, Result};
use crate::eval::metrics::{PathSmoothness, PathStats};
use crate::features::vgg::{TAPS, Vgg19};
use crate::io::images::{RgbImage, to_byte};
use crate::model::grid::{Grid, to_host};

/// The smallest side VGG19's five taps exist for (four 2× max-pools).
pub const MIN_SIDE: usize = 16;

/// The feature-space path of `frames` and of the cross-fade of its ends ([`PathSmoothness`],
/// distances as the module says).
///
/// # Errors
///
/// Fewer than 2 frames, a side below [`MIN_SIDE`], or a tap that is zero on both endpoints
/// (its scale would be undefined: wrong weights).
pub fn feature_path(vgg: &Vgg19, grid: &Grid, frames: &[RgbImage]) -> Result<PathSmoothness> {
    let (h, w) = (grid.height(), grid.width());
    if frames.len() < 2 || h.min(w) < MIN_SIDE {
        return Err(Error::Shape {
            op: "feature-space path",
            detail: format!(
                "{} frames of {w}x{h}: needs 2 frames or more, sides of at least {MIN_SIDE} px",
                frames.len()
            ),
        });
    }
    // One network pass per image: the endpoints' taps give the scales and both paths' ends
    // (the cross-fade's ends are the morph's), 2K passes for K + 1 frames.
    let taps =
        |image: &RgbImage| -> Result<[Tensor<4>; 5]> { Ok(vgg.taps(image.to_tensor(grid)?)) };
    let (first, last) = (&frames[0], &frames[frames.len() - 1]);
    let (first_taps, last_taps) = (taps(first)?, taps(last)?);
    let squares: Vec<Tensor<1>> = first_taps
        .iter()
        .zip(&last_taps)
        .map(|(a, b)| {
            // The RMS over both endpoints together: they have the same size.
            (a.clone().powi_scalar(2).mean() + b.clone().powi_scalar(2).mean())
                .div_scalar(2.0)
                .reshape([1])
        })
        .collect();
    let rms: Vec<f64> = to_host(Tensor::cat(squares, 0))
        .into_iter()
        .map(f64::sqrt)
        .collect();
    if let Some(s) = rms.iter().position(|r| !(r.is_finite() && *r > 0.0)) {
        return Err(Error::NonFinite {
            what: format!(
                "VGG tap {} of the morph's endpoints has RMS {}: cannot measure distances \
                 relative to it (wrong weights?)",
                TAPS[s], rms[s]
            ),
        });
    }
    let steps = frames.len() - 1;
    // The interior frames' taps are computed as the distances walk along the path: one
    // frame's at a time, never the whole path's.
    type Taps = Result<[Tensor<4>; 5]>;
    let path = |interior: Box<dyn Iterator<Item = Taps> + '_>| {
        let all = std::iter::once(Ok(first_taps.clone()))
            .chain(interior)
            .chain(std::iter::once(Ok(last_taps.clone())));
        adjacent_distances(&rms, all)
    };
    let morph = path(Box::new(frames[1..steps].iter().map(taps)))?;
    let crossfade = path(Box::new((1..steps).map(|k| {
        let t = k as f32 / steps as f32;
        let data = first
            .data()
            .iter()
            .zip(last.data())
            .map(|(&a, &b)| f32::from(to_byte((1.0 - t) * a + t * b)) / 255.0)
            .collect();
        taps(&RgbImage::new(h, w, data)?)
    })))?;
    Ok(PathSmoothness {
        morph: PathStats::from_adjacent(morph),
        crossfade: PathStats::from_adjacent(crossfade),
    })
}

/// `d(u_{k−1}, u_k)` along a path given by the taps of its frames, one read-back per pair.
fn adjacent_distances(
    rms: &[f64],
    frames: impl Iterator<Item = Result<[Tensor<4>; 5]>>,
) -> Result<Vec<f64>> {
    let mut previous: Option<[Tensor<4>; 5]> = None;
    let mut distances = Vec::new();
    for taps in frames {
        let taps = taps?;
        if let Some(before) = previous {
            let terms: Vec<Tensor<1>> = taps
                .iter()
                .zip(before)
                .zip(rms)
                .map(|((now, then), r)| {
                    (now.clone() - then)
                        .powi_scalar(2)
                        .mean()
                        .div_scalar(r * r)
                        .reshape([1])
                })
                .collect();
            let sum: f64 = to_host(Tensor::cat(terms, 0)).iter().sum();
            distances.push((sum / TAPS.len() as f64).sqrt());
        }
        previous = Some(taps);
    }
    Ok(distances)
}
