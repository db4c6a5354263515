//! The per-pixel moments of the data term's slopes over the channels, fused: what a
//! deformation step's prox needs of its linearisation (SPEC §6), in one pass over `T` and
//! `f_{k−1}`.
//!
//! With `s_c = T_c + f_{k−1,c}`, `Λ_c = ½ ∇s_c` (the Sobel derivative in pixel units, mirror
//! boundary: `∂₀` the central difference along rows smoothed `(1, 2, 1)/4` along columns,
//! `∂₁` the transpose), `r_c = T_c − f_{k−1,c}` and `q_c = Λ_cᵀ φ̃ − r_c`:
//! `Σ_c Λ_c Λ_cᵀ` (three entries) and `Σ_c Λ_c q_c` (two), `[N, 5, H, W]`.
//!
//! Composed from tensor ops (`crate::solver::prox`, every backend) this is two separable
//! operators and about twenty passes over `C` channels with `2C`-channel intermediates; on
//! flex a host kernel does it per row block with the channels inner. Not differentiable:
//! the linearisation is a constant of its step. The custom ops and the backends they have kernels for are listed in one place,
//! `docs/architecture.md` ("Custom ops"): they are the only numerical code that names backends.

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::Tensor;

use crate::model::cpu::{Real, Shared, simd_dispatch};

/// The fused moments' primitive (flex only: the other backends compose them).
#[backend_extension(Flex: cfg(feature = "flex"), Autodiff)]
pub trait SlopeOps: Backend {
    /// Shapes as in [`moments`].
    fn slope_moments(
        warped: FloatTensor<Self>,
        prev: FloatTensor<Self>,
        phi: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// `(Σ Λ₀², Σ Λ₀Λ₁, Σ Λ₁², Σ Λ₀ q, Σ Λ₁ q)` at every pixel (module docs). Only on a grid
/// whose capabilities say `fused_linearisation`.
///
/// # Shapes
/// - `warped` (`T[f_k, φ̃]`), `prev` (`f_{k−1}`): `[N, C, H, W]`; `phi` (`φ̃`): `[N, 2, H, W]`
/// - output: `[N, 5, H, W]`
pub fn moments(warped: Tensor<4>, prev: Tensor<4>, phi: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(Dispatch::slope_moments(
        warped.detach().into_dispatch(),
        prev.detach().into_dispatch(),
        phi.detach().into_dispatch(),
    ))
}

/// Rows per task of [`host_moments`]: the task's five accumulator rows and the three input
/// rows it reads per channel stay in cache.
const ROWS_PER_TASK: usize = 4;

/// The host kernel of [`moments`] on row-major slices; `out` is `[N, 5, H, W]`.
pub fn host_moments<T: Real>(
    warped: &[T],
    prev: &[T],
    phi: &[T],
    [n, c, h, w]: [usize; 4],
    out: &mut [T],
) {
    use rayon::prelude::*;
    let plane = h * w;
    assert!(h >= 2 && w >= 2, "the Sobel derivative needs 2 × 2 pixels");
    assert_eq!(warped.len(), n * c * plane, "warped maps");
    assert_eq!(prev.len(), n * c * plane, "previous frame");
    assert_eq!(phi.len(), n * 2 * plane, "deformation");
    assert_eq!(out.len(), n * 5 * plane, "moments");
    let blocks = h.div_ceil(ROWS_PER_TASK);
    let out_ptr = Shared(out.as_mut_ptr());
    (0..n * blocks).into_par_iter().for_each(|task| {
        let (b, block) = (task / blocks, task % blocks);
        let rows = block * ROWS_PER_TASK..((block + 1) * ROWS_PER_TASK).min(h);
        let count = rows.len();
        // The task's rows of the five moments (`[row, moment, W]`), summed over the channels.
        let mut acc = vec![T::default(); count * 5 * w];
        let mut scratch = vec![T::default(); (count + 2) * w + 2 * (w + 2)];
        let phi0 = &phi[b * 2 * plane + rows.start * w..b * 2 * plane + rows.end * w];
        let phi1 =
            &phi[b * 2 * plane + plane + rows.start * w..b * 2 * plane + plane + rows.end * w];
        for ch in 0..c {
            let at = (b * c + ch) * plane;
            moments_rows_simd(
                &warped[at..at + plane],
                &prev[at..at + plane],
                phi0,
                phi1,
                rows.clone(),
                w,
                &mut scratch,
                &mut acc,
            );
        }
        for m in 0..5 {
            for (r, i) in rows.clone().enumerate() {
                let first = (b * 5 + m) * plane + i * w;
                // SAFETY: rows `rows` of image b are this task's alone, in each moment's plane.
                let dst = unsafe { std::slice::from_raw_parts_mut(out_ptr.get(first), w) };
                dst.copy_from_slice(&acc[(r * 5 + m) * w..(r * 5 + m + 1) * w]);
            }
        }
    });
}

/// The index `i` of a line of `len` samples reflected at both ends (whole-sample mirror).
fn mirror(i: isize, len: usize) -> usize {
    let last = len as isize - 1;
    (last - (i.abs() - last).abs()) as usize
}

/// Adds one channel's `Λ Λᵀ` and `Λ q` at the rows `rows` into `acc` (`[rows, 5, W]`), from
/// the channel's planes `t` (`T`) and `f` (`f_{k−1}`), `[H, W]`, and `φ̃`'s two planes at
/// those rows, `p0` and `p1` (`[rows, W]` each). `scratch` holds `(rows + 2)·W + 2·(W + 2)`
/// values.
///
/// Each line of `s = T + f_{k−1}` the rows need (theirs and one either side, mirrored) is
/// summed once (per row, three lines were summed again each time); each row's two passes
/// along it (the central difference and the smoothing) are written with a mirrored value at
/// either end, so that the columns run over the whole row in `add_row`'s vector blocks (with
/// the two edge columns apart, a 32-column row left at least 8 of its columns to scalar
/// code, a 16-column row at least half: at the 32² level of a deep morph, 515 channels, the moments were a
/// fifth of the level's time). Every value takes the same operations in the same order as
/// SPEC §6's formula at the edges and inside.
#[inline(always)]
fn moments_rows<T: Real>(
    t: &[T],
    f: &[T],
    p0: &[T],
    p1: &[T],
    rows: std::ops::Range<usize>,
    w: usize,
    scratch: &mut [T],
    acc: &mut [T],
) {
    let (h, count) = (t.len() / w, rows.len());
    let (quarter, two) = (T::from_f64(0.25), T::from_f64(2.0));
    let (s, rest) = scratch[..(count + 2) * w + 2 * (w + 2)].split_at_mut((count + 2) * w);
    let (vd, vs) = rest.split_at_mut(w + 2);
    for (l, line) in s.chunks_exact_mut(w).enumerate() {
        let i = mirror(rows.start as isize + l as isize - 1, h);
        for ((x, &a), &b) in line.iter_mut().zip(&t[i * w..][..w]).zip(&f[i * w..][..w]) {
            *x = a + b;
        }
    }
    for (r, i) in rows.enumerate() {
        // Along rows first: the central difference (halved below) and the (1, 2, 1)
        // smoothing of the three lines, at columns 1..=W, mirrored into 0 and W + 1.
        // Every slice cut to the row's length `[..w]` up front, so the loops have no bounds
        // checks left to stop them vectorising.
        let (s0, s1, s2) = (
            &s[r * w..][..w],
            &s[(r + 1) * w..][..w],
            &s[(r + 2) * w..][..w],
        );
        {
            let (d, m) = (&mut vd[1..][..w], &mut vs[1..][..w]);
            for j in 0..w {
                d[j] = s2[j] - s0[j];
                m[j] = (s0[j] + two * s1[j] + s2[j]) * quarter;
            }
        }
        (vd[0], vd[w + 1]) = (vd[2], vd[w - 1]);
        (vs[0], vs[w + 1]) = (vs[2], vs[w - 1]);
        add_row(
            vd,
            vs,
            &t[i * w..][..w],
            &f[i * w..][..w],
            &p0[r * w..][..w],
            &p1[r * w..][..w],
            &mut acc[r * 5 * w..][..5 * w],
        );
    }
}

/// Adds one row's `Λ Λᵀ` and `Λ q` into `acc` (`[5, W]`), from the row's two passes `vd`,
/// `vs` (`W + 2` values: columns at 1..=W, mirrored ends) and its `T`, `f_{k−1}` and `φ̃`.
///
/// Eight columns at a time through fixed-size arrays: the slopes of all eight first, then
/// each moment's eight sums. Written as one loop over the columns, the compiler kept it
/// scalar here (it could not tell the five outputs from the inputs); blocks of arrays are
/// straight-line code it vectorises without that. Per value the same operations in the
/// same order.
#[inline(always)]
fn add_row<T: Real>(vd: &[T], vs: &[T], t: &[T], f: &[T], p0: &[T], p1: &[T], acc: &mut [T]) {
    const L: usize = 8;
    let w = t.len();
    let (a0, rest) = acc.split_at_mut(w);
    let (a1, rest) = rest.split_at_mut(w);
    let (a2, rest) = rest.split_at_mut(w);
    let (a3, a4) = rest.split_at_mut(w);
    let column = |j: usize| {
        slopes_at(
            [vd[j], vd[j + 1], vd[j + 2]],
            [vs[j], vs[j + 2]],
            [p0[j], p1[j]],
            t[j] - f[j],
        )
    };
    let whole = w - w % L;
    for j0 in (0..whole).step_by(L) {
        let block = |x: &[T]| -> [T; L] { x[j0..j0 + L].try_into().expect("a block") };
        let (dm, dc, dp) = (block(&vd[..w]), block(&vd[1..]), block(&vd[2..]));
        let (sm, sp) = (block(&vs[..w]), block(&vs[2..]));
        let (q0, q1, tc, fc) = (block(p0), block(p1), block(t), block(f));
        let mut slopes = [[T::default(); L]; 3];
        for l in 0..L {
            let [l0, l1, q] = slopes_at(
                [dm[l], dc[l], dp[l]],
                [sm[l], sp[l]],
                [q0[l], q1[l]],
                tc[l] - fc[l],
            );
            (slopes[0][l], slopes[1][l], slopes[2][l]) = (l0, l1, q);
        }
        let [l0, l1, q] = slopes;
        let add = |a: &mut [T], x: [T; L], y: [T; L]| {
            let a: &mut [T; L] = (&mut a[j0..j0 + L]).try_into().expect("a block");
            for l in 0..L {
                a[l] += x[l] * y[l];
            }
        };
        add(a0, l0, l0);
        add(a1, l0, l1);
        add(a2, l1, l1);
        add(a3, l0, q);
        add(a4, l1, q);
    }
    for j in whole..w {
        let [l0, l1, q] = column(j);
        a0[j] += l0 * l0;
        a1[j] += l0 * l1;
        a2[j] += l1 * l1;
        a3[j] += l0 * q;
        a4[j] += l1 * q;
    }
}

/// `[Λ₀, Λ₁, q]` at a column from `vd` at `j − 1, j, j + 1`, `vs` at `j − 1, j + 1`, `φ̃`
/// and the residual `T − f_{k−1}`: Λ = ½ ∇s, ∂₀ = (vd[j−1] + 2 vd[j] + vd[j+1]) / 8 (vd is
/// twice the central difference), ∂₁ = (vs[j+1] − vs[j−1]) / 2.
#[inline(always)]
fn slopes_at<T: Real>(vd: [T; 3], vs: [T; 2], phi: [T; 2], residual: T) -> [T; 3] {
    let (half, eighth, two) = (T::from_f64(0.5), T::from_f64(0.125), T::from_f64(2.0));
    let l0 = half * ((vd[0] + two * vd[1] + vd[2]) * eighth);
    let l1 = half * ((vs[1] - vs[0]) * half);
    [l0, l1, l0 * phi[0] + l1 * phi[1] - residual]
}

simd_dispatch!(fn moments_rows_simd<T: Real>(
    t: &[T], f: &[T], p0: &[T], p1: &[T], rows: std::ops::Range<usize>, w: usize,
    scratch: &mut [T], acc: &mut [T]
) => moments_rows);

#[cfg(feature = "flex")]
mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};

    use super::{SlopeOps, host_moments};
    use crate::model::cpu::Real;
    use crate::model::host_view::HostView;

    fn typed<T: Real + burn::tensor::Element + bytemuck::Pod>(
        warped: &HostView,
        prev: &HostView,
        phi: &HostView,
    ) -> TensorData {
        let s = warped.shape();
        assert!(
            s.len() == 4 && prev.shape() == s && phi.shape() == [s[0], 2, s[2], s[3]],
            "slope moments: maps {s:?}, previous frame {:?} and deformation {:?} do not fit",
            prev.shape(),
            phi.shape()
        );
        let dims = [s[0], s[1], s[2], s[3]];
        let mut out = crate::model::cpu::zeros::<T>(s[0] * 5 * s[2] * s[3]);
        host_moments(warped.values(), prev.values(), phi.values(), dims, &mut out);
        TensorData::new(out, [s[0], 5, s[2], s[3]])
    }

    impl SlopeOps for Flex {
        fn slope_moments(warped: FlexTensor, prev: FlexTensor, phi: FlexTensor) -> FlexTensor {
            let (warped, prev, phi) = (
                HostView::new(warped),
                HostView::new(prev),
                HostView::new(phi),
            );
            assert!(
                warped.dtype() == prev.dtype() && warped.dtype() == phi.dtype(),
                "slope moments: dtypes differ"
            );
            FlexTensor::from_data(match warped.dtype() {
                DType::F32 => typed::<f32>(&warped, &prev, &phi),
                DType::F64 => typed::<f64>(&warped, &prev, &phi),
                other => panic!("the slope moments run in float32 or float64, not {other:?}"),
            })
        }
    }
}

mod autodiff {
    use burn::backend::Autodiff;
    use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
    use burn::backend::tensor::FloatTensor;

    use super::SlopeOps;

    /// The moments are constants of a step ([`super::moments`] detaches its inputs).
    impl<B: SlopeOps, C: CheckpointStrategy> SlopeOps for Autodiff<B, C> {
        fn slope_moments(
            warped: FloatTensor<Self>,
            prev: FloatTensor<Self>,
            phi: FloatTensor<Self>,
        ) -> FloatTensor<Self> {
            assert!(
                !warped.is_tracked() && !prev.is_tracked() && !phi.is_tracked(),
                "the slope moments are not differentiable"
            );
            let (warped, _) = warped.into_parts();
            let (prev, _) = prev.into_parts();
            let (phi, _) = phi.into_parts();
            FloatTensor::<Self>::new(B::slope_moments(warped, prev, phi))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::stencil::mirror_index;

    /// SPEC §6's Sobel formula, written out per pixel in float64.
    fn naive(warped: &[f64], prev: &[f64], phi: &[f64], [n, c, h, w]: [usize; 4]) -> Vec<f64> {
        let plane = h * w;
        let mut out = vec![0.0; n * 5 * plane];
        let m = |i: isize, len: usize| mirror_index(i as i64, len);
        for b in 0..n {
            for ch in 0..c {
                let s = |i: isize, j: isize| {
                    let at = (b * c + ch) * plane + m(i, h) * w + m(j, w);
                    warped[at] + prev[at]
                };
                for i in 0..h as isize {
                    for j in 0..w as isize {
                        let ws = [1.0, 2.0, 1.0];
                        let (mut d0, mut d1) = (0.0, 0.0);
                        for (t, wt) in (-1..=1).zip(ws) {
                            d0 += wt * (s(i + 1, j + t) - s(i - 1, j + t)) / 8.0;
                            d1 += wt * (s(i + t, j + 1) - s(i + t, j - 1)) / 8.0;
                        }
                        let (l0, l1) = (0.5 * d0, 0.5 * d1);
                        let p = i as usize * w + j as usize;
                        let at = (b * c + ch) * plane + p;
                        let q = l0 * phi[b * 2 * plane + p] + l1 * phi[(b * 2 + 1) * plane + p]
                            - (warped[at] - prev[at]);
                        for (k, v) in [l0 * l0, l0 * l1, l1 * l1, l0 * q, l1 * q]
                            .into_iter()
                            .enumerate()
                        {
                            out[(b * 5 + k) * plane + p] += v;
                        }
                    }
                }
            }
        }
        out
    }

    #[test]
    fn the_fused_moments_are_spec_sobel_slopes_summed_over_channels() {
        // Heights and widths on both sides of the task's row block, including 2; widths
        // with no, one and many (a vector body and its tail) interior columns.
        for dims in [
            [2, 3, 5, 6],
            [1, 4, 9, 2],
            [1, 1, 2, 7],
            [1, 2, 3, 3],
            [1, 3, 6, 41],
        ] {
            let [n, c, h, w] = dims;
            let value = |i: usize, seed: f64| (i as f64 * 0.731 + seed).sin();
            let warped: Vec<f64> = (0..n * c * h * w).map(|i| value(i, 0.3)).collect();
            let prev: Vec<f64> = (0..n * c * h * w).map(|i| value(i, 1.7)).collect();
            let phi: Vec<f64> = (0..n * 2 * h * w).map(|i| 3.0 * value(i, 2.9)).collect();
            let mut got = vec![0.0; n * 5 * h * w];
            host_moments(&warped, &prev, &phi, dims, &mut got);
            let want = naive(&warped, &prev, &phi, dims);
            for (i, (g, e)) in got.iter().zip(&want).enumerate() {
                assert!(
                    (g - e).abs() <= 1e-12 * (1.0 + e.abs()),
                    "{dims:?} at {i}: {g} vs {e}"
                );
            }
        }
    }
}
