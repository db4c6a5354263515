//! The weighted hyperelastic density `a · W(J(φ))` of the regulariser (SPEC §2) and its
//! gradients as one custom Burn op (Burn 0.22's `#[backend_extension]`).
//!
//! Composed from tensor ops ([`super::density`], [`crate::model::deformation::jacobian`]) the
//! density is about twenty passes over the grid (four forward differences with their
//! `narrow`/`cat`, the determinant, `log`, `exp`, the strain, the fold mask) and autodiff
//! records each one for the backward: about a tenth of a 256² RGB sweep by the profile. Fused, the value is one pass per pixel and the gradient two
//! (`∂W/∂J` per pixel, then the adjoint of the forward differences).
//!
//! - flex: the host kernels below, split over the cores by rows.
//! - autodiff: the backward in `φ` is the hand-derived `a ∂W/∂J` chained through the adjoint
//!   of the forward differences (`crate::check::regularizer_gradient` writes the same formula
//!   as composed ops; the gradient checks compare the two and finite differences); in the
//!   weight `a` (a constant of every derivative the solver takes, but a library user may
//!   track it) it is `g · W(J(φ))`, the op itself with `g` as the weight.
//! - ndarray and wgpu compose the density from tensor ops (not served here).
//!
//! The custom ops and the backends they have kernels for are listed in one place,
//! `docs/architecture.md` ("Custom ops"): they are the only numerical code that names backends.

// With no backend that serves these ops compiled (a build without them), the generated
// dispatch leaves the ops' scalar arguments unused.
#![cfg_attr(not(feature = "flex"), allow(unused_variables))]

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::Tensor;

use crate::model::cpu::{Real, Shared, simd_dispatch};

/// The density's primitives (flex only: the other backends compose it).
#[backend_extension(Flex: cfg(feature = "flex"), Autodiff)]
pub trait DensityOps: Backend {
    /// `a · W(J(φ))`; shapes as in [`weighted_density`].
    fn weighted_density(
        phi: FloatTensor<Self>,
        a: FloatTensor<Self>,
        lambda: f64,
        mu: f64,
    ) -> FloatTensor<Self>;
    /// `∂/∂φ Σ g · a · W(J(φ))`, `[N, 2, H, W]`, zero where `φ` folds.
    fn weighted_density_grad(
        phi: FloatTensor<Self>,
        a: FloatTensor<Self>,
        grad: FloatTensor<Self>,
        lambda: f64,
        mu: f64,
    ) -> FloatTensor<Self>;
    /// The smallest `det J(φ_n)` of each deformation, `[N]`; NaN where a determinant is.
    fn min_det(phi: FloatTensor<Self>) -> FloatTensor<Self>;
}

/// `a · W(J(φ))` at every pixel by the fused op, differentiable in `φ` and `a`. Only on a
/// backend that serves it (flex).
///
/// # Shapes
/// - `phi`: `[N, 2, H, W]`; `a`: `[N, H, W]`; output `[N, H, W]`
pub fn weighted_density(phi: Tensor<4>, a: Tensor<3>, lambda: f64, mu: f64) -> Tensor<3> {
    Tensor::from_dispatch(Dispatch::weighted_density(
        phi.into_dispatch(),
        a.into_dispatch(),
        lambda,
        mu,
    ))
}

/// The smallest `det J` of each deformation by the fused op (not differentiable: the
/// admissibility test of a trial). Only on a backend that serves it (flex); the composed
/// equivalent is [`crate::model::deformation::min_det_each`].
///
/// # Shapes
/// - `phi`: `[N, 2, H, W]`; output `[N]`
pub fn min_det(phi: Tensor<4>) -> Tensor<1> {
    Tensor::from_dispatch(Dispatch::min_det(phi.detach().into_dispatch()))
}

/// Rows per task: enough work per task at 64², every core busy at 512².
const ROWS_PER_TASK: usize = 8;

/// The Jacobian of SPEC §2 at pixel `(i, j)` from the two planes of `φ`: forward differences,
/// `J₀₀ = 1` and `J₁₀ = 0` on the last row, `J₀₁ = 0` and `J₁₁ = 1` on the last column.
#[inline(always)]
fn jacobian_at<T: Real>(p0: &[T], p1: &[T], i: usize, j: usize, h: usize, w: usize) -> [T; 4] {
    let at = i * w + j;
    let (zero, one) = (T::default(), T::from_f64(1.0));
    let (j00, j10) = if i + 1 < h {
        (p0[at + w] - p0[at], p1[at + w] - p1[at])
    } else {
        (one, zero)
    };
    let (j01, j11) = if j + 1 < w {
        (p0[at + 1] - p0[at], p1[at + 1] - p1[at])
    } else {
        (zero, one)
    };
    [j00, j01, j10, j11]
}

/// `W(J)` (SPEC §2), in the order of the composed [`super::density::density`]; `+∞` where
/// `det J ≤ 0`.
#[inline(always)]
fn density_at<T: Real>([j00, j01, j10, j11]: [T; 4], half_lambda: T, mu: T) -> T {
    let (one, half) = (T::from_f64(1.0), T::from_f64(0.5));
    let det = j00 * j11 - j01 * j10;
    if det <= T::default() {
        return T::from_f64(f64::INFINITY);
    }
    let log_det = det.ln();
    let volume = ((log_det * log_det).exp() - one) * half_lambda;
    let (d00, d11, shear) = (j00 - one, j11 - one, j01 + j10);
    let strain = (d00 * d00 + d11 * d11 + shear * shear * half) * mu;
    volume + strain
}

/// `∂W/∂J` (SPEC §2): `λ exp((log d)²) log d · d J⁻ᵀ / d + 2μ (sym J − I)`; zero where
/// `det J ≤ 0` (the composed density's gradient there, which the solver never follows).
#[inline(always)]
fn density_grad_at<T: Real>([j00, j01, j10, j11]: [T; 4], lambda: T, mu: T) -> [T; 4] {
    let (zero, one, two) = (T::default(), T::from_f64(1.0), T::from_f64(2.0));
    let det = j00 * j11 - j01 * j10;
    if !(det > zero) {
        return [zero; 4];
    }
    let log_det = det.ln();
    let factor = (log_det * log_det).exp() * log_det * lambda * (one / det);
    let shear = (j01 + j10) * mu;
    [
        factor * j11 + (j00 - one) * two * mu,
        shear - factor * j10,
        shear - factor * j01,
        factor * j00 + (j11 - one) * two * mu,
    ]
}

/// Pixels per vectorised group: eight float32 lanes of AVX2.
const LANES: usize = 8;

/// [`jacobian_at`] of the eight pixels `(i, j + l)`, `l < 8`, of an interior run (`i + 1 < h`,
/// `j + 8 < w`: no boundary rule applies); `at = i·w + j`. Entries first, lanes second.
#[inline(always)]
fn jacobians8<T: Real>(p0: &[T], p1: &[T], at: usize, w: usize) -> [[T; LANES]; 4] {
    let (p0, p1) = (&p0[at..at + w + LANES], &p1[at..at + w + LANES]);
    [
        std::array::from_fn(|l| p0[l + w] - p0[l]),
        std::array::from_fn(|l| p0[l + 1] - p0[l]),
        std::array::from_fn(|l| p1[l + w] - p1[l]),
        std::array::from_fn(|l| p1[l + 1] - p1[l]),
    ]
}

/// `det J`, `log det J` and `exp((log det J)²)` of eight Jacobians, by the type's
/// vectorisable [`Real::ln8`] and [`Real::exp8`] (lanes where `det J ≤ 0` hold garbage the
/// callers replace).
#[inline(always)]
fn volume_terms8<T: Real>([j00, j01, j10, j11]: &[[T; LANES]; 4]) -> [[T; LANES]; 3] {
    let det: [T; LANES] = std::array::from_fn(|l| j00[l] * j11[l] - j01[l] * j10[l]);
    let log_det = T::ln8(det);
    let growth = T::exp8(std::array::from_fn(|l| log_det[l] * log_det[l]));
    [det, log_det, growth]
}

/// [`density_at`] of eight Jacobians, the same operations lane by lane.
#[inline(always)]
fn density8<T: Real>(j: [[T; LANES]; 4], half_lambda: T, mu: T) -> [T; LANES] {
    let (one, half) = (T::from_f64(1.0), T::from_f64(0.5));
    let [det, _, growth] = volume_terms8(&j);
    let [j00, j01, j10, j11] = j;
    std::array::from_fn(|l| {
        let volume = (growth[l] - one) * half_lambda;
        let (d00, d11, shear) = (j00[l] - one, j11[l] - one, j01[l] + j10[l]);
        let strain = (d00 * d00 + d11 * d11 + shear * shear * half) * mu;
        if det[l] <= T::default() {
            T::from_f64(f64::INFINITY)
        } else {
            volume + strain
        }
    })
}

/// [`density_grad_at`] of eight Jacobians, the same operations lane by lane.
#[inline(always)]
fn density_grad8<T: Real>(j: [[T; LANES]; 4], lambda: T, mu: T) -> [[T; LANES]; 4] {
    let (zero, one, two) = (T::default(), T::from_f64(1.0), T::from_f64(2.0));
    let [det, log_det, growth] = volume_terms8(&j);
    let [j00, j01, j10, j11] = j;
    let factor: [T; LANES] =
        std::array::from_fn(|l| growth[l] * log_det[l] * lambda * (one / det[l]));
    let shear: [T; LANES] = std::array::from_fn(|l| (j01[l] + j10[l]) * mu);
    let admissible = |l: usize, v: T| if det[l] > zero { v } else { zero };
    [
        std::array::from_fn(|l| admissible(l, factor[l] * j11[l] + (j00[l] - one) * two * mu)),
        std::array::from_fn(|l| admissible(l, shear[l] - factor[l] * j10[l])),
        std::array::from_fn(|l| admissible(l, shear[l] - factor[l] * j01[l])),
        std::array::from_fn(|l| admissible(l, factor[l] * j00[l] + (j11[l] - one) * two * mu)),
    ]
}

/// How many runs of eight interior pixels start row `i` (`[h, w]` the image's size), at
/// columns `0, 8, …`: none on the last row, and the pixels from the last run's end on go
/// one at a time, where the boundary rule of [`jacobian_at`] applies. (Loops rather than a
/// visitor closure: the closure was not inlined into the AVX2 copy of its caller.)
#[inline(always)]
fn runs(i: usize, [h, w]: [usize; 2]) -> usize {
    if i + 1 < h { (w - 1) / LANES } else { 0 }
}

/// [`host_density`]'s rows `rows` of one image: `p0`, `p1`, `a` that image's planes, `out`
/// its rows `rows`.
#[inline(always)]
fn density_rows<T: Real>(
    p0: &[T],
    p1: &[T],
    a: &[T],
    rows: std::ops::Range<usize>,
    [h, w]: [usize; 2],
    [half_lambda, mu]: [T; 2],
    out: &mut [T],
) {
    let first = rows.start * w;
    for i in rows {
        let interior = runs(i, [h, w]) * LANES;
        for j in (0..interior).step_by(LANES) {
            let at = i * w + j;
            let v = density8(jacobians8(p0, p1, at, w), half_lambda, mu);
            let out = &mut out[at - first..at - first + LANES];
            for ((o, v), a) in out.iter_mut().zip(v).zip(&a[at..at + LANES]) {
                *o = *a * v;
            }
        }
        for j in interior..w {
            let at = i * w + j;
            out[at - first] = a[at] * density_at(jacobian_at(p0, p1, i, j, h, w), half_lambda, mu);
        }
    }
}

/// The first pass of [`host_density_grad`] on rows `rows` of one image: `g a ∂W/∂J` into
/// `entries`, rows `rows` of the image's four entry planes; `p0`, `p1`, `a`, `g` that
/// image's planes.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn density_grad_rows<T: Real>(
    p0: &[T],
    p1: &[T],
    a: &[T],
    g: &[T],
    rows: std::ops::Range<usize>,
    [h, w]: [usize; 2],
    [lambda, mu]: [T; 2],
    mut entries: [&mut [T]; 4],
) {
    let first = rows.start * w;
    for i in rows {
        let interior = runs(i, [h, w]) * LANES;
        for j in (0..interior).step_by(LANES) {
            let at = i * w + j;
            let d = density_grad8(jacobians8(p0, p1, at, w), lambda, mu);
            for (d, plane) in d.into_iter().zip(entries.iter_mut()) {
                let out = &mut plane[at - first..at - first + LANES];
                for (l, (o, v)) in out.iter_mut().zip(d).enumerate() {
                    *o = g[at + l] * a[at + l] * v;
                }
            }
        }
        for j in interior..w {
            let at = i * w + j;
            let d = density_grad_at(jacobian_at(p0, p1, i, j, h, w), lambda, mu);
            for (v, plane) in d.into_iter().zip(entries.iter_mut()) {
                plane[at - first] = g[at] * a[at] * v;
            }
        }
    }
}

simd_dispatch!(fn density_rows_simd<T: Real>(
    p0: &[T], p1: &[T], a: &[T], rows: std::ops::Range<usize>, hw: [usize; 2],
    coefficients: [T; 2], out: &mut [T]
) => density_rows);

simd_dispatch!(fn density_grad_rows_simd<T: Real>(
    p0: &[T], p1: &[T], a: &[T], g: &[T], rows: std::ops::Range<usize>, hw: [usize; 2],
    coefficients: [T; 2], entries: [&mut [T]; 4]
) => density_grad_rows);

/// The two planes `(φ₀, φ₁)` of deformation `b` in `phi` (`[N, 2, H, W]`, `plane = H·W`).
#[inline]
fn planes<T>(phi: &[T], b: usize, plane: usize) -> (&[T], &[T]) {
    phi[b * 2 * plane..(b + 1) * 2 * plane].split_at(plane)
}

/// Checks the lengths of the kernels' slices: `phi` `[N, 2, H, W]`, every map `[N, H, W]`.
fn check_lengths<T>(phi: &[T], maps: &[(&[T], &str)], [n, h, w]: [usize; 3]) {
    assert_eq!(phi.len(), n * 2 * h * w, "deformation");
    for (map, what) in maps {
        assert_eq!(map.len(), n * h * w, "{what}");
    }
}

/// The host kernel of [`weighted_density`] on row-major slices: `phi` `[N, 2, H, W]`, `a`
/// and `out` `[N, H, W]`.
pub fn host_density<T: Real>(
    phi: &[T],
    a: &[T],
    [n, h, w]: [usize; 3],
    lambda: f64,
    mu: f64,
    out: &mut [T],
) {
    use rayon::prelude::*;
    let plane = h * w;
    check_lengths(phi, &[(a, "anisotropy"), (&*out, "density")], [n, h, w]);
    // `λ/2` rounded once, as the composed density's scalar.
    let (lambda, mu) = (T::from_f64(lambda / 2.0), T::from_f64(mu));
    let blocks = h.div_ceil(ROWS_PER_TASK);
    let target = Shared(out.as_mut_ptr());
    (0..n * blocks).into_par_iter().for_each(|task| {
        let (b, block) = (task / blocks, task % blocks);
        let (p0, p1) = planes(phi, b, plane);
        let rows = block * ROWS_PER_TASK..((block + 1) * ROWS_PER_TASK).min(h);
        // SAFETY: rows `rows` of image b are this task's alone.
        let out = unsafe {
            std::slice::from_raw_parts_mut(target.get(b * plane + rows.start * w), rows.len() * w)
        };
        let a = &a[b * plane..(b + 1) * plane];
        density_rows_simd(p0, p1, a, rows, [h, w], [lambda, mu], out);
    });
}

/// The host kernel of [`min_det`]: `phi` `[N, 2, H, W]`, one value per deformation. The
/// determinant is the composed `Jacobian::det`'s product and difference, so the minimum is
/// the same value; a NaN determinant makes the result NaN (an inadmissible trial).
// `det != det` is the NaN test that stays in vector registers (`Real` has no `is_nan`).
#[allow(clippy::eq_op)]
pub fn host_min_det<T: Real>(phi: &[T], [n, h, w]: [usize; 3]) -> Vec<T> {
    use rayon::prelude::*;
    let plane = h * w;
    check_lengths(phi, &[], [n, h, w]);
    let blocks = h.div_ceil(ROWS_PER_TASK);
    (0..n)
        .map(|b| {
            let (p0, p1) = planes(phi, b, plane);
            let (least, nan) = (0..blocks)
                .into_par_iter()
                .map(|block| {
                    let (mut least, mut nan) = (T::from_f64(f64::INFINITY), false);
                    for i in block * ROWS_PER_TASK..((block + 1) * ROWS_PER_TASK).min(h) {
                        for j in 0..w {
                            let [j00, j01, j10, j11] = jacobian_at(p0, p1, i, j, h, w);
                            let det = j00 * j11 - j01 * j10;
                            nan |= det != det;
                            if det < least {
                                least = det;
                            }
                        }
                    }
                    (least, nan)
                })
                .reduce(
                    || (T::from_f64(f64::INFINITY), false),
                    |(a, x), (b, y)| (if b < a { b } else { a }, x || y),
                );
            if nan { T::from_f64(f64::NAN) } else { least }
        })
        .collect()
}

/// The host kernel of [`DensityOps::weighted_density_grad`]: `g` and `a` `[N, H, W]`, `out`
/// `[N, 2, H, W]`.
pub fn host_density_grad<T: Real>(
    phi: &[T],
    a: &[T],
    g: &[T],
    [n, h, w]: [usize; 3],
    lambda: f64,
    mu: f64,
    out: &mut [T],
) {
    use rayon::prelude::*;
    let plane = h * w;
    check_lengths(phi, &[(a, "anisotropy"), (g, "output gradient")], [n, h, w]);
    assert_eq!(out.len(), n * 2 * plane, "gradient");
    let (lambda, mu) = (T::from_f64(lambda), T::from_f64(mu));
    // `g a ∂W/∂J`, four planes per image: the adjoint below reads each entry twice.
    let mut dj = crate::model::cpu::zeros(n * 4 * plane);
    dj.par_chunks_mut(4 * plane)
        .enumerate()
        .for_each(|(b, entries)| {
            let (p0, p1) = planes(phi, b, plane);
            let out = Shared(entries.as_mut_ptr());
            let (a, g) = (
                &a[b * plane..(b + 1) * plane],
                &g[b * plane..(b + 1) * plane],
            );
            (0..h.div_ceil(ROWS_PER_TASK))
                .into_par_iter()
                .for_each(|block| {
                    let rows = block * ROWS_PER_TASK..((block + 1) * ROWS_PER_TASK).min(h);
                    let entries = std::array::from_fn(|m| {
                        // SAFETY: rows `rows` of the image's four planes are this task's alone.
                        unsafe {
                            std::slice::from_raw_parts_mut(
                                out.get(m * plane + rows.start * w),
                                rows.len() * w,
                            )
                        }
                    });
                    density_grad_rows_simd(p0, p1, a, g, rows, [h, w], [lambda, mu], entries);
                });
        });
    // The adjoint of the forward differences: `J₀₀`, `J₁₀` difference along rows (none on
    // the last row, where they are constants), `J₀₁`, `J₁₁` along columns.
    let target = Shared(out.as_mut_ptr());
    (0..n * h).into_par_iter().for_each(|task| {
        let (b, i) = (task / h, task % h);
        let planes = &dj[b * 4 * plane..(b + 1) * 4 * plane];
        let entry = |m: usize, i: usize, j: usize| planes[m * plane + i * w + j];
        for (component, (along_rows, along_cols)) in [(0, 1), (2, 3)].into_iter().enumerate() {
            for j in 0..w {
                let mut v = T::default();
                if i + 1 < h {
                    v = v - entry(along_rows, i, j);
                }
                if i >= 1 {
                    v += entry(along_rows, i - 1, j);
                }
                if j + 1 < w {
                    v = v - entry(along_cols, i, j);
                }
                if j >= 1 {
                    v += entry(along_cols, i, j - 1);
                }
                // SAFETY: row i of image b is this task's alone, in both components.
                unsafe { *target.get((b * 2 + component) * plane + i * w + j) = v };
            }
        }
    });
}

#[cfg(feature = "flex")]
mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};

    use super::{DensityOps, host_density, host_density_grad, host_min_det};
    use crate::model::cpu::{Real, zeros};
    use crate::model::host_view::HostView;

    trait Kernel: Real + burn::tensor::Element + bytemuck::Pod {}
    impl Kernel for f32 {}
    impl Kernel for f64 {}

    /// `[N, H, W]` of a deformation `[N, 2, H, W]` and a map that must be `[N, H, W]`.
    fn dims(phi: &HostView, map: &HostView, what: &str) -> [usize; 3] {
        let (s, m) = (phi.shape(), map.shape());
        assert!(
            s.len() == 4 && s[1] == 2 && m == [s[0], s[2], s[3]],
            "weighted density: deformation {s:?} and {what} {m:?} do not fit [N, 2, H, W] and \
             [N, H, W]"
        );
        [s[0], s[2], s[3]]
    }

    fn density_typed<T: Kernel>(phi: &HostView, a: &HostView, lambda: f64, mu: f64) -> TensorData {
        let d = dims(phi, a, "weight");
        let mut out = zeros::<T>(d.iter().product());
        host_density(phi.values(), a.values(), d, lambda, mu, &mut out);
        TensorData::new(out, d)
    }

    fn grad_typed<T: Kernel>(
        phi: &HostView,
        a: &HostView,
        g: &HostView,
        lambda: f64,
        mu: f64,
    ) -> TensorData {
        let d = dims(phi, a, "weight");
        assert_eq!(dims(phi, g, "output gradient"), d);
        let mut out = zeros::<T>(2 * d.iter().product::<usize>());
        host_density_grad(
            phi.values(),
            a.values(),
            g.values(),
            d,
            lambda,
            mu,
            &mut out,
        );
        TensorData::new(out, [d[0], 2, d[1], d[2]])
    }

    macro_rules! typed {
        ($dtype:expr, $f:ident ( $($arg:expr),* )) => {
            match $dtype {
                DType::F32 => $f::<f32>($($arg),*),
                DType::F64 => $f::<f64>($($arg),*),
                other => panic!("the density runs in float32 or float64, not {other:?}"),
            }
        };
    }

    fn min_det_typed<T: Kernel>(phi: &HostView) -> TensorData {
        let s = phi.shape();
        assert!(
            s.len() == 4 && s[1] == 2,
            "min det J: deformation {s:?} is not [N, 2, H, W]"
        );
        TensorData::new(host_min_det::<T>(phi.values(), [s[0], s[2], s[3]]), [s[0]])
    }

    impl DensityOps for Flex {
        fn min_det(phi: FlexTensor) -> FlexTensor {
            let phi = HostView::new(phi);
            FlexTensor::from_data(typed!(phi.dtype(), min_det_typed(&phi)))
        }

        fn weighted_density(phi: FlexTensor, a: FlexTensor, lambda: f64, mu: f64) -> FlexTensor {
            let (phi, a) = (HostView::new(phi), HostView::new(a));
            assert_eq!(phi.dtype(), a.dtype(), "weighted density: dtypes differ");
            FlexTensor::from_data(typed!(phi.dtype(), density_typed(&phi, &a, lambda, mu)))
        }

        fn weighted_density_grad(
            phi: FlexTensor,
            a: FlexTensor,
            grad: FlexTensor,
            lambda: f64,
            mu: f64,
        ) -> FlexTensor {
            let (phi, a, grad) = (HostView::new(phi), HostView::new(a), HostView::new(grad));
            assert!(
                phi.dtype() == a.dtype() && phi.dtype() == grad.dtype(),
                "weighted density gradient: dtypes differ"
            );
            FlexTensor::from_data(typed!(phi.dtype(), grad_typed(&phi, &a, &grad, lambda, mu)))
        }
    }
}

mod autodiff {
    use burn::backend::Autodiff;
    use burn::backend::autodiff::checkpoint::base::Checkpointer;
    use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
    use burn::backend::autodiff::grads::Gradients;
    use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
    use burn::backend::tensor::FloatTensor;

    use super::DensityOps;

    #[derive(Debug)]
    struct Density;

    impl<B: DensityOps> Backward<B, 2> for Density {
        /// `φ`, `a`, `λ`, `μ`.
        type State = (FloatTensor<B>, FloatTensor<B>, f64, f64);

        fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
            let [phi_node, a_node] = ops.parents;
            let (phi, a, lambda, mu) = ops.state;
            let grad = grads.consume::<B>(&ops.node);
            if let Some(node) = a_node {
                // ∂(a W)/∂a · g = g W: the density weighted by g.
                let g = B::weighted_density(phi.clone(), grad.clone(), lambda, mu);
                grads.register::<B>(node.id, g);
            }
            if let Some(node) = phi_node {
                grads.register::<B>(node.id, B::weighted_density_grad(phi, a, grad, lambda, mu));
            }
        }
    }

    impl<B: DensityOps, C: CheckpointStrategy> DensityOps for Autodiff<B, C> {
        /// A constant: no gradient flows through it, whatever its input (a detached leaf
        /// still counts as tracked here, so this does not assert like the gradient kernel).
        fn min_det(phi: FloatTensor<Self>) -> FloatTensor<Self> {
            let (phi, _) = phi.into_parts();
            FloatTensor::<Self>::new(B::min_det(phi))
        }

        fn weighted_density(
            phi: FloatTensor<Self>,
            a: FloatTensor<Self>,
            lambda: f64,
            mu: f64,
        ) -> FloatTensor<Self> {
            let (phi, phi_node) = phi.into_parts();
            let (a, a_node) = a.into_parts();
            match Density
                .prepare::<C>([phi_node, a_node])
                .compute_bound()
                .stateful()
            {
                OpsKind::Tracked(prep) => {
                    let out = B::weighted_density(phi.clone(), a.clone(), lambda, mu);
                    prep.finish((phi, a, lambda, mu), out)
                }
                OpsKind::UnTracked(prep) => prep.finish(B::weighted_density(phi, a, lambda, mu)),
            }
        }

        fn weighted_density_grad(
            phi: FloatTensor<Self>,
            a: FloatTensor<Self>,
            grad: FloatTensor<Self>,
            lambda: f64,
            mu: f64,
        ) -> FloatTensor<Self> {
            assert!(
                !phi.is_tracked() && !a.is_tracked() && !grad.is_tracked(),
                "the density's gradient kernel is not differentiable"
            );
            let (phi, _) = phi.into_parts();
            let (a, _) = a.into_parts();
            let (grad, _) = grad.into_parts();
            FloatTensor::<Self>::new(B::weighted_density_grad(phi, a, grad, lambda, mu))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `Id` plus a smooth displacement of about `amplitude` pixels, `[n, 2, h, w]`.
    fn deformation(n: usize, h: usize, w: usize, amplitude: f64) -> Vec<f64> {
        (0..n * 2 * h * w)
            .map(|at| {
                let (b, axis, i, j) = (at / (2 * h * w), (at / (h * w)) % 2, (at / w) % h, at % w);
                let id = if axis == 0 { i } else { j } as f64;
                let x = (i * 7 + j * 3 + axis * 5 + b * 11) as f64;
                id + amplitude * (0.37 * x).sin()
            })
            .collect()
    }

    /// SPEC §2 per pixel in float64: forward differences, `W(J)`, `+∞` where `det J ≤ 0`.
    fn naive(phi: &[f64], a: &[f64], [n, h, w]: [usize; 3], lambda: f64, mu: f64) -> Vec<f64> {
        let plane = h * w;
        let mut out = vec![0.0; n * plane];
        for b in 0..n {
            let v = |axis: usize, i: usize, j: usize| phi[(b * 2 + axis) * plane + i * w + j];
            for i in 0..h {
                for j in 0..w {
                    let d0 = |axis| {
                        if i + 1 < h {
                            Some(v(axis, i + 1, j) - v(axis, i, j))
                        } else {
                            None
                        }
                    };
                    let d1 = |axis| {
                        if j + 1 < w {
                            Some(v(axis, i, j + 1) - v(axis, i, j))
                        } else {
                            None
                        }
                    };
                    let (j00, j10) = (d0(0).unwrap_or(1.0), d0(1).unwrap_or(0.0));
                    let (j01, j11) = (d1(0).unwrap_or(0.0), d1(1).unwrap_or(1.0));
                    let det = j00 * j11 - j01 * j10;
                    let wj = if det <= 0.0 {
                        f64::INFINITY
                    } else {
                        lambda / 2.0 * (det.ln().powi(2).exp() - 1.0)
                            + mu * ((j00 - 1.0).powi(2)
                                + (j11 - 1.0).powi(2)
                                + 0.5 * (j01 + j10).powi(2))
                    };
                    out[b * plane + i * w + j] = a[b * plane + i * w + j] * wj;
                }
            }
        }
        out
    }

    #[test]
    fn the_fused_density_is_specs_formula_per_pixel_and_infinite_where_folded() {
        let (lambda, mu) = (0.1, 0.025);
        // Row counts below, at and beyond one task's rows; two images.
        for dims in [[2, 5, 6], [1, 8, 4], [2, 11, 7]] {
            let [n, h, w] = dims;
            let mut phi = deformation(n, h, w, 0.2);
            // A fold in the last image: one row overtakes the next.
            let (b, i, j) = (n - 1, h / 2, w / 2);
            phi[(b * 2) * h * w + i * w + j] += 1.5;
            let a: Vec<f64> = (0..n * h * w)
                .map(|p| 0.5 + 0.4 * (p as f64).cos())
                .collect();
            let mut got = vec![0.0; n * h * w];
            host_density(&phi, &a, dims, lambda, mu, &mut got);
            let want = naive(&phi, &a, dims, lambda, mu);
            assert!(want.iter().any(|v| v.is_infinite()), "the fold shows");
            for (k, (g, e)) in got.iter().zip(&want).enumerate() {
                assert!(
                    g == e || (g - e).abs() <= 1e-13 * e.abs(),
                    "{dims:?} at {k}: {g} vs {e}"
                );
            }
        }
    }

    #[test]
    fn the_smallest_determinant_is_specs_and_nan_wins() {
        // SPEC §2's determinant per pixel: the naive density is infinite exactly where it is
        // not positive, and its formula's determinant is recomputed here.
        for (dims, amplitude) in [([2, 5, 6], 0.1), ([1, 19, 7], 0.3), ([3, 8, 9], 2.0)] {
            let [n, h, w] = dims;
            let phi = deformation(n, h, w, amplitude);
            let got = host_min_det(&phi, dims);
            for b in 0..n {
                let plane = h * w;
                let v = |axis: usize, i: usize, j: usize| phi[(b * 2 + axis) * plane + i * w + j];
                let mut least = f64::INFINITY;
                for i in 0..h {
                    for j in 0..w {
                        let d0 = |a| {
                            if i + 1 < h {
                                v(a, i + 1, j) - v(a, i, j)
                            } else {
                                f64::from(u8::from(a == 0))
                            }
                        };
                        let d1 = |a| {
                            if j + 1 < w {
                                v(a, i, j + 1) - v(a, i, j)
                            } else {
                                f64::from(u8::from(a == 1))
                            }
                        };
                        least = least.min(d0(0) * d1(1) - d1(0) * d0(1));
                    }
                }
                assert_eq!(got[b], least, "{dims:?} image {b}");
            }
            // The large displacement folds somewhere.
            if amplitude > 1.0 {
                assert!(got.iter().any(|&d| d <= 0.0), "{dims:?}: {got:?}");
            }
        }
        let [n, h, w] = [2, 20, 5];
        let mut phi = deformation(n, h, w, 0.1);
        phi[2 * h * w + 17 * w + 3] = f64::NAN;
        let got = host_min_det(&phi, [n, h, w]);
        assert!(got[0].is_finite() && got[1].is_nan(), "{got:?}");
    }

    #[test]
    fn the_fused_gradient_is_the_derivative_of_the_weighted_sum() {
        let (lambda, mu) = (0.1, 0.025);
        for dims in [[2, 5, 6], [1, 11, 9]] {
            let [n, h, w] = dims;
            let phi = deformation(n, h, w, 0.15);
            let a: Vec<f64> = (0..n * h * w)
                .map(|p| 0.5 + 0.4 * (p as f64).cos())
                .collect();
            let g: Vec<f64> = (0..n * h * w)
                .map(|p| 1.0 + 0.3 * (0.7 * p as f64).sin())
                .collect();
            let total = |phi: &[f64]| {
                let mut d = vec![0.0; n * h * w];
                host_density(phi, &a, dims, lambda, mu, &mut d);
                d.iter().zip(&g).map(|(d, g)| d * g).sum::<f64>()
            };
            let mut got = vec![0.0; n * 2 * h * w];
            host_density_grad(&phi, &a, &g, dims, lambda, mu, &mut got);
            let step = 1e-6;
            for k in 0..phi.len() {
                let (mut up, mut down) = (phi.clone(), phi.clone());
                up[k] += step;
                down[k] -= step;
                let fd = (total(&up) - total(&down)) / (2.0 * step);
                assert!(
                    (got[k] - fd).abs() <= 1e-7 * (1.0 + fd.abs()),
                    "{dims:?} entry {k}: {} vs finite difference {fd}",
                    got[k]
                );
            }
        }
    }
}
