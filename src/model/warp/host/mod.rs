//! The cubic B-spline prefilter and warp of SPEC §1 as plain loops over host slices: the
//! native CPU kernels behind the fused warp op ([`super::op`]), threaded with rayon over
//! pixels (channels inner) and over lines.
//!
//! Every function here is a linear map or the derivative of one, written with its adjoint:
//!
//! - [`prefilter()`]: `c = P f` per channel (or `Pᵀ g`), the exact interpolating prefilter
//!   with whole-sample mirror boundary, as a tridiagonal solve along each axis: O(n) per line
//!   instead of a dense `n × n` matmul.
//! - [`sample`]: `T = B(φ) c`, the 4 × 4 B-spline evaluation at clamped points.
//! - [`sample_adjoint`]: `B(φ)ᵀ g`, a scatter-add (the gradient w.r.t. the coefficients).
//! - [`sample_position_grad`]: `Σ_c g_c ∂T_c/∂p` (the gradient w.r.t. `φ`), zero along an
//!   axis where the point lies outside the clamp range.
//!
//! Layouts are row-major and contiguous: coefficients `[N, C, H, W]`, deformations
//! `[N, 2, H', W']`, warped maps `[N, C, H', W']`. Many channels ([`reads_channels_last`])
//! are read channels-last; [`prefilter_channels_last`] writes coefficients so, and
//! [`sample_from_table`] / [`position_grad_from_table`] read such a table in place, a block
//! of its channels too ([`Layout`]), where the planar entry points transpose per call. Three
//! or four channels are evaluated and scattered through per-call quad tables ([`quad`]).
//!
//! The files, by operation: [`prefilter`](mod@prefilter), [`points`] (the evaluation's setup),
//! [`evaluate`], [`adjoint`], [`layout`] (channels-last tables), [`quad`]. What the kernels
//! share with the other custom ops' kernels (the element types, the AVX2 dispatch) is
//! `crate::model::cpu`.

use std::borrow::Cow;
use std::mem::MaybeUninit;

use rayon::prelude::*;

pub(crate) use crate::model::cpu::{
    PIXELS_PER_TASK, Real, Shared, channels_last_into, has_avx2, pixels_per_task, simd_dispatch,
    transpose_pixels, zeros,
};

pub mod adjoint;
pub mod evaluate;
pub mod layout;
pub mod points;
pub mod prefilter;
pub mod quad;
#[cfg(test)]
mod tests;

pub use adjoint::*;
pub use evaluate::*;
pub use layout::*;
pub use points::*;
pub use prefilter::*;

/// The element types of the spline kernels: `Real` (`crate::model::cpu`) with the hooks of the quad-table
/// kernels ([`quad`]), where float32 on AVX2 has faster ones.
pub trait SplineReal: Real {
    /// The stencils of the first `n` points of a block over a quad table ([`quad`]), where a
    /// type has a faster kernel for them: written to `block[l]` for the lanes of the mask it
    /// returns (none by default; float32 on AVX2 does those whose columns are contiguous).
    #[inline(always)]
    fn quad_block(
        table: &[Self],
        w: usize,
        rows: quad::BlockAxis<'_, Self>,
        cols: quad::BlockAxis<'_, Self>,
        n: usize,
        block: &mut [[Self; 4]; LANES],
    ) -> u32 {
        let _ = (table, w, rows, cols, n, block);
        0
    }
    /// Adds the values of the lanes `lanes` of a block into a quad table (the adjoint of
    /// [`quad_block`](Self::quad_block)), in lane order, as far as the type has a faster
    /// kernel for them; returns the first lane not done (by default `lanes.start`: none;
    /// float32 on AVX2 stops at the first lane whose columns the mirror folded).
    #[inline(always)]
    fn quad_scatter(
        table: &mut [Self],
        w: usize,
        rows: quad::BlockAxis<'_, Self>,
        cols: quad::BlockAxis<'_, Self>,
        lanes: std::ops::Range<usize>,
        values: &[[Self; 4]; LANES],
    ) -> usize {
        let _ = (table, w, rows, cols, values);
        lanes.start
    }
}

impl SplineReal for f32 {
    #[inline(always)]
    fn quad_block(
        table: &[Self],
        w: usize,
        rows: quad::BlockAxis<'_, Self>,
        cols: quad::BlockAxis<'_, Self>,
        n: usize,
        block: &mut [[Self; 4]; LANES],
    ) -> u32 {
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            // SAFETY: the CPU has AVX2.
            return unsafe { quad::block_avx(table, w, rows, cols, n, block) };
        }
        let _ = (table, w, rows, cols, n, block);
        0
    }
    #[inline(always)]
    fn quad_scatter(
        table: &mut [Self],
        w: usize,
        rows: quad::BlockAxis<'_, Self>,
        cols: quad::BlockAxis<'_, Self>,
        lanes: std::ops::Range<usize>,
        values: &[[Self; 4]; LANES],
    ) -> usize {
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            // SAFETY: the CPU has AVX2.
            return unsafe { quad::scatter_avx(table, w, rows, cols, lanes, values) };
        }
        let _ = (table, w, rows, cols, values);
        lanes.start
    }
}

impl SplineReal for f64 {}
