//! A deformation step's trial (SPEC §6 step 2) as one custom Burn op: the gradient step
//! `y = φ̃ − g/L`, the pointwise 2 × 2 solve of the prox ([`super::prox::LinearisedData`])
//! and the identity on the boundary, per pixel in one pass.
//!
//! Composed, a trial's prox is about twenty elementwise tensor ops on `H × W` planes (scale,
//! shift, products, the determinant, two divisions, a `cat` and the boundary's
//! `mask_where`), each a pass over memory into a fresh output, and flex runs elementwise ops
//! on one core; the backtracking runs two or three trials per step. Fused, every value takes
//! the same float operations in the same order as the composed chain: the trials, and so
//! the morph, are the same bit for bit (a test compares them).
//!
//! - flex: the host kernel below, split over the cores by rows.
//! - autodiff: not differentiable (a trial is a constant of the search: its inputs are
//!   detached).
//! - ndarray and wgpu compose it ([`super::prox::LinearisedData::prox`]); the op is called
//!   only with the fused slope moments, which only flex has.

// With no backend that serves these ops compiled (a build without them), the generated
// dispatch leaves the ops' scalar arguments unused.
#![cfg_attr(not(feature = "flex"), allow(unused_variables))]

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::Tensor;

use crate::model::cpu::{Real, Shared, simd_dispatch};

/// The fused trial's primitive (flex only: the other backends compose it).
#[backend_extension(Flex: cfg(feature = "flex"), Autodiff)]
pub trait ProxOps: Backend {
    /// Shapes and scalars as in [`prox_step`].
    fn prox_step(
        point: FloatTensor<Self>,
        gradient: FloatTensor<Self>,
        moments: FloatTensor<Self>,
        inv_l: f64,
        t: f64,
    ) -> FloatTensor<Self>;
}

/// `x = (I + t Σ Λ Λᵀ)⁻¹ (y + t Σ Λ (Λᵀ φ̃ − r))` with `y = φ̃ − g · inv_l` at every pixel,
/// `Id` on the boundary; `t = κ/L`, `inv_l = 1/L` (each rounded to the tensors' precision
/// once, as a tensor op's scalar is).
///
/// # Shapes
/// - `point` (`φ̃`), `gradient` (`g`): `[N, 2, H, W]`
/// - `moments`: `[N, 5, H, W]`, [`crate::model::slopes::moments`] at `φ̃`
/// - output: `[N, 2, H, W]`
pub fn prox_step(
    point: Tensor<4>,
    gradient: Tensor<4>,
    moments: Tensor<4>,
    inv_l: f64,
    t: f64,
) -> Tensor<4> {
    Tensor::from_dispatch(Dispatch::prox_step(
        point.detach().into_dispatch(),
        gradient.detach().into_dispatch(),
        moments.detach().into_dispatch(),
        inv_l,
        t,
    ))
}

/// Rows per task: enough work per task at 64², every core busy at 512².
const ROWS_PER_TASK: usize = 16;

/// The host kernel of [`prox_step`] on row-major slices: `point`, `gradient` and `out`
/// `[N, 2, H, W]`, `moments` `[N, 5, H, W]`.
pub fn host_prox_step<T: Real>(
    point: &[T],
    gradient: &[T],
    moments: &[T],
    [n, h, w]: [usize; 3],
    (inv_l, t): (f64, f64),
    out: &mut [T],
) {
    use rayon::prelude::*;
    let plane = h * w;
    assert_eq!(point.len(), n * 2 * plane, "linearisation point");
    assert_eq!(gradient.len(), n * 2 * plane, "gradient");
    assert_eq!(moments.len(), n * 5 * plane, "moments");
    assert_eq!(out.len(), n * 2 * plane, "prox");
    let factors = (T::from_f64(inv_l), T::from_f64(t));
    let blocks = h.div_ceil(ROWS_PER_TASK);
    let target = Shared(out.as_mut_ptr());
    (0..n * blocks).into_par_iter().for_each(|task| {
        let (b, block) = (task / blocks, task % blocks);
        let (p, g) = (&point[b * 2 * plane..], &gradient[b * 2 * plane..]);
        let m = &moments[b * 5 * plane..];
        for i in block * ROWS_PER_TASK..((block + 1) * ROWS_PER_TASK).min(h) {
            // SAFETY: row i of image b is this task's alone, in both components.
            let (r0, r1) = unsafe {
                (
                    std::slice::from_raw_parts_mut(target.get(b * 2 * plane + i * w), w),
                    std::slice::from_raw_parts_mut(target.get(b * 2 * plane + plane + i * w), w),
                )
            };
            prox_row_simd(p, g, m, [plane, h, w], i, factors, r0, r1);
        }
    });
}

/// Row `i` of [`host_prox_step`] into its two components' rows `r0`, `r1`: the boundary
/// pixels keep the identity, the interior ones solve their system, in a loop without a
/// branch per pixel (with the boundary test per pixel the loop stayed scalar baseline code,
/// its two divisions one lane at a time).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn prox_row<T: Real>(
    p: &[T],
    g: &[T],
    m: &[T],
    [plane, h, w]: [usize; 3],
    i: usize,
    (inv_l, t): (T, T),
    r0: &mut [T],
    r1: &mut [T],
) {
    let identity = |r0: &mut [T], r1: &mut [T], j: usize| {
        r0[j] = T::from_i32(i as i32);
        r1[j] = T::from_i32(j as i32);
    };
    if i == 0 || i + 1 == h || w < 3 {
        for j in 0..w {
            identity(r0, r1, j);
        }
        return;
    }
    identity(r0, r1, 0);
    identity(r0, r1, w - 1);
    let one = T::from_f64(1.0);
    let row = |k: usize| &m[k * plane + i * w + 1..k * plane + (i + 1) * w - 1];
    let (m0, m1, m2, m3, m4) = (row(0), row(1), row(2), row(3), row(4));
    let (p0, p1) = (
        &p[i * w + 1..(i + 1) * w - 1],
        &p[plane + i * w + 1..plane + (i + 1) * w - 1],
    );
    let (g0, g1) = (
        &g[i * w + 1..(i + 1) * w - 1],
        &g[plane + i * w + 1..plane + (i + 1) * w - 1],
    );
    let (o0, o1) = (&mut r0[1..w - 1], &mut r1[1..w - 1]);
    for j in 0..w - 2 {
        // The composed chain's operations, in its order (`LinearisedData::solve`).
        let y0 = p0[j] - g0[j] * inv_l;
        let y1 = p1[j] - g1[j] * inv_l;
        let m00 = m0[j] * t + one;
        let m01 = m1[j] * t;
        let m11 = m2[j] * t + one;
        let b0 = y0 + m3[j] * t;
        let b1 = y1 + m4[j] * t;
        let det = m00 * m11 - m01 * m01;
        o0[j] = (m11 * b0 - m01 * b1) / det;
        o1[j] = (m00 * b1 - m01 * b0) / det;
    }
}

simd_dispatch!(fn prox_row_simd<T: Real>(
    p: &[T], g: &[T], m: &[T], dims: [usize; 3], i: usize, factors: (T, T), r0: &mut [T],
    r1: &mut [T]
) => prox_row);

#[cfg(feature = "flex")]
mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};

    use super::{ProxOps, host_prox_step};
    use crate::model::cpu::Real;
    use crate::model::host_view::HostView;

    fn typed<T: Real + burn::tensor::Element + bytemuck::Pod>(
        point: &HostView,
        gradient: &HostView,
        moments: &HostView,
        scalars: (f64, f64),
    ) -> TensorData {
        let s = point.shape();
        assert!(
            s.len() == 4
                && s[1] == 2
                && gradient.shape() == s
                && moments.shape() == [s[0], 5, s[2], s[3]],
            "prox step: point {s:?}, gradient {:?} and moments {:?} do not fit",
            gradient.shape(),
            moments.shape()
        );
        let mut out = vec![T::default(); s.iter().product()];
        host_prox_step(
            point.values(),
            gradient.values(),
            moments.values(),
            [s[0], s[2], s[3]],
            scalars,
            &mut out,
        );
        TensorData::new(out, s)
    }

    impl ProxOps for Flex {
        fn prox_step(
            point: FlexTensor,
            gradient: FlexTensor,
            moments: FlexTensor,
            inv_l: f64,
            t: f64,
        ) -> FlexTensor {
            let (point, gradient, moments) = (
                HostView::new(point),
                HostView::new(gradient),
                HostView::new(moments),
            );
            assert!(
                point.dtype() == gradient.dtype() && point.dtype() == moments.dtype(),
                "prox step: dtypes differ"
            );
            let scalars = (inv_l, t);
            FlexTensor::from_data(match point.dtype() {
                DType::F32 => typed::<f32>(&point, &gradient, &moments, scalars),
                DType::F64 => typed::<f64>(&point, &gradient, &moments, scalars),
                other => panic!("the prox runs in float32 or float64, not {other:?}"),
            })
        }
    }
}

mod autodiff {
    use burn::backend::Autodiff;
    use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
    use burn::backend::tensor::FloatTensor;

    use super::ProxOps;

    /// A trial is a constant of the search: no gradient flows through it, whatever its
    /// inputs (a detached leaf still counts as tracked here, so this does not assert).
    impl<B: ProxOps, C: CheckpointStrategy> ProxOps for Autodiff<B, C> {
        fn prox_step(
            point: FloatTensor<Self>,
            gradient: FloatTensor<Self>,
            moments: FloatTensor<Self>,
            inv_l: f64,
            t: f64,
        ) -> FloatTensor<Self> {
            let (point, _) = point.into_parts();
            let (gradient, _) = gradient.into_parts();
            let (moments, _) = moments.into_parts();
            FloatTensor::<Self>::new(B::prox_step(point, gradient, moments, inv_l, t))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// With fewer than three rows or columns no pixel is interior: each keeps the identity.
    #[test]
    fn images_of_one_or_two_rows_or_columns_are_all_boundary() {
        for [h, w] in [[1, 4], [2, 2], [2, 5], [5, 2], [3, 1]] {
            let plane = h * w;
            let point = vec![0.5; 2 * plane];
            let (gradient, moments) = (vec![0.25; 2 * plane], vec![1.0; 5 * plane]);
            let mut out = vec![f64::NAN; 2 * plane];
            host_prox_step(&point, &gradient, &moments, [1, h, w], (1.0, 1.0), &mut out);
            let identity: Vec<f64> = (0..2 * plane)
                .map(|at| match at / plane {
                    0 => ((at % plane) / w) as f64,
                    _ => ((at % plane) % w) as f64,
                })
                .collect();
            assert_eq!(out, identity, "{h} × {w}");
        }
    }

    #[test]
    fn the_kernel_solves_each_pixels_system_and_keeps_the_boundary() {
        // Two images, heights across the row blocks, `Σ Λ Λᵀ ⪰ 0` as the moments are.
        let [n, h, w] = [2, 37, 11];
        let plane = h * w;
        let value = |i: usize, seed: f64| (i as f64 * 0.613 + seed).sin();
        let point: Vec<f64> = (0..n * 2 * plane).map(|i| 5.0 * value(i, 0.2)).collect();
        let gradient: Vec<f64> = (0..n * 2 * plane).map(|i| value(i, 1.1)).collect();
        let mut moments = vec![0.0; n * 5 * plane];
        for b in 0..n {
            for p in 0..plane {
                let (l0, l1) = (value(b * plane + p, 2.3), value(b * plane + p, 3.7));
                let q = value(b * plane + p, 4.1);
                let m = [l0 * l0, l0 * l1, l1 * l1, l0 * q, l1 * q];
                for (k, v) in m.into_iter().enumerate() {
                    moments[(b * 5 + k) * plane + p] = v;
                }
            }
        }
        let (inv_l, t) = (0.25, 3.0);
        let mut out = vec![f64::NAN; n * 2 * plane];
        host_prox_step(&point, &gradient, &moments, [n, h, w], (inv_l, t), &mut out);
        for b in 0..n {
            for i in 0..h {
                for j in 0..w {
                    let p = i * w + j;
                    let at = |c: usize| (b * 2 + c) * plane + p;
                    let x = [out[at(0)], out[at(1)]];
                    if i == 0 || j == 0 || i == h - 1 || j == w - 1 {
                        assert_eq!(x, [i as f64, j as f64], "boundary ({b}, {i}, {j})");
                        continue;
                    }
                    let m = |k: usize| moments[(b * 5 + k) * plane + p];
                    // (I + t M) x = φ̃ − g/L + t v
                    let rhs = [
                        point[at(0)] - gradient[at(0)] * inv_l + t * m(3),
                        point[at(1)] - gradient[at(1)] * inv_l + t * m(4),
                    ];
                    let lhs = [
                        (1.0 + t * m(0)) * x[0] + t * m(1) * x[1],
                        t * m(1) * x[0] + (1.0 + t * m(2)) * x[1],
                    ];
                    for c in 0..2 {
                        assert!(
                            (lhs[c] - rhs[c]).abs() <= 1e-12 * (1.0 + rhs[c].abs()),
                            "({b}, {i}, {j}) component {c}: {} vs {}",
                            lhs[c],
                            rhs[c]
                        );
                    }
                }
            }
        }
    }
}
