//! Frames between the frames of a geodesic: a clip of any length from the `K + 1` frames the
//! model computes.
//!
//! Step `k` carries `u_{k−1}` to `u_k` by `u_{k−1} ≈ u_k ∘ φ_k` plus a small intensity change:
//! the content at `y` in `u_{k−1}` sits at `φ_k(y) = y + d(y)` in `u_k`, `d = φ_k − Id`. At a
//! fraction `s ∈ [0, 1]` of the step it sits at `y + s·d(y)`, and its colour is blended
//! linearly; pulling each end frame to that position (to first order in the displacement,
//! `d(y) ≈ d(x)` over one step) gives
//!
//! `v_s(x) = (1 − s) · u_{k−1}(x − s·d(x)) + s · u_k(x + (1 − s)·d(x))`,
//!
//! both terms warped with the model's cubic B-spline (SPEC §1). `v_0 = u_{k−1}` and
//! `v_1 = u_k` exactly (the frames themselves are used there), and a uniformly translated
//! picture moves linearly in `s`.

use burn::tensor::Tensor;

use crate::error::{Error, Result};
use crate::model::grid::Grid;
use crate::model::warp::BSpline;

/// Where frame `j` of `count` falls on a path of `steps` steps: the step `k ∈ 1..=steps`
/// and the fraction `s ∈ [0, 1]` of it, evenly spaced in `k − 1 + s` from 0 to `steps`.
pub fn position(j: usize, count: usize, steps: usize) -> (usize, f64) {
    let t = j as f64 * steps as f64 / (count - 1) as f64;
    let k = (t.floor() as usize).min(steps - 1) + 1;
    (k, t - (k - 1) as f64)
}

/// The most frames a clip may have (20 s at 30 frames per second).
pub const MAX_FRAMES: usize = 600;

/// Checks that a clip of `count` frames fits a path of `steps` steps: `K + 1 ≤ count ≤`
/// [`MAX_FRAMES`] (or `K + 1` when that is more).
///
/// # Errors
///
/// [`Error::InvalidParameter`] naming `frames` and the range.
pub fn check_count(steps: usize, count: usize) -> Result<()> {
    let (least, most) = (steps + 1, MAX_FRAMES.max(steps + 1));
    if (least..=most).contains(&count) {
        Ok(())
    } else {
        Err(Error::invalid(
            "frames",
            count,
            format!("at least K + 1 = {least} (the frames the model computes) and at most {most}"),
        ))
    }
}

/// A clip of `count` frames evenly spaced along the path of `frames` and `deformations`
/// (see the module's formula), rendered one frame at a time.
#[derive(Clone, Debug)]
pub struct Clip {
    bspline: BSpline,
    identity: Tensor<4>,
    frames: Tensor<4>,
    deformations: Tensor<4>,
    count: usize,
}

impl Clip {
    /// The clip of `count` frames.
    ///
    /// # Shapes
    /// - `frames`: `[K + 1, C, H, W]`; `deformations`: `[K, 2, H, W]` (pixel units), on `grid`
    ///
    /// # Errors
    ///
    /// As [`check_count`].
    pub fn new(
        grid: &Grid,
        frames: Tensor<4>,
        deformations: Tensor<4>,
        count: usize,
    ) -> Result<Self> {
        check_count(deformations.dims()[0], count)?;
        Ok(Self {
            bspline: BSpline::new(grid),
            identity: grid.identity(1),
            frames,
            deformations,
            count,
        })
    }

    /// The number of frames.
    pub fn len(&self) -> usize {
        self.count
    }

    /// Whether the clip has no frames (never: it has at least `K + 1 ≥ 2`).
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Frame `j < len()`, `[1, C, H, W]`.
    pub fn frame(&self, j: usize) -> Tensor<4> {
        let steps = self.deformations.dims()[0];
        let (k, s) = position(j, self.count, steps);
        let frame = |i: usize| self.frames.clone().narrow(0, i, 1);
        if s == 0.0 {
            return frame(k - 1);
        }
        if s == 1.0 {
            return frame(k);
        }
        let id = &self.identity;
        let d = self.deformations.clone().narrow(0, k - 1, 1) - id.clone();
        let from = self
            .bspline
            .warp(frame(k - 1), id.clone() - d.clone().mul_scalar(s));
        let to = self
            .bspline
            .warp(frame(k), id.clone() + d.mul_scalar(1.0 - s));
        from.mul_scalar(1.0 - s) + to.mul_scalar(s)
    }
}

/// All frames of a [`Clip`] of `count` frames at once.
///
/// # Shapes
/// - as [`Clip::new`]; output `[count, C, H, W]`
///
/// # Errors
///
/// As [`Clip::new`].
pub fn inbetween(
    grid: &Grid,
    frames: Tensor<4>,
    deformations: Tensor<4>,
    count: usize,
) -> Result<Tensor<4>> {
    let clip = Clip::new(grid, frames, deformations, count)?;
    Ok(Tensor::cat((0..count).map(|j| clip.frame(j)).collect(), 0))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn positions_are_even_and_hit_every_frame() {
        assert_eq!(position(0, 5, 4), (1, 0.0));
        assert_eq!(position(4, 5, 4), (4, 1.0));
        assert_eq!(position(2, 5, 4), (3, 0.0));
        // 9 frames on 4 steps: halves.
        assert_eq!(position(3, 9, 4), (2, 0.5));
        assert_eq!(position(8, 9, 4), (4, 1.0));
    }
}
