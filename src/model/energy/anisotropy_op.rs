//! The edge-stopping anisotropy `a[u] = exp(−|∇u|²/ξ₁) + ξ₂` of SPEC §3 from the images, as
//! one custom Burn op (Burn 0.22's `#[backend_extension]`).
//!
//! Composed, it is two separable operators (each two passes, each writing a frame-sized
//! intermediate), then six passes for the weight: the two squares, their sum, the sum over
//! the colour channels, the scaling and the exponential (flex's elementwise ops run one at a
//! time on the calling thread; its `exp` is libm's, one value at a time). Fused, each output
//! row's derivatives are computed and weighted while in cache, split over the cores, the
//! exponential eight lanes at a time (`crate::model::cpu::elementary`).
//!
//! - flex: the host kernel below.
//! - autodiff: a constant. The anisotropy is a fixed weight of every derivative the model
//!   takes, so its input is detached ([`super::anisotropy::Anisotropy::compute`]).
//! - ndarray and wgpu compose it from tensor ops (not served here).

// With no backend that serves these ops compiled (a build without them), the generated
// dispatch leaves the ops' scalar arguments unused.
#![cfg_attr(not(feature = "flex"), allow(unused_variables))]

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::Tensor;

use std::mem::MaybeUninit;

use crate::model::cpu::Real;
use crate::model::separable::host::{Band, apply_row};

/// The anisotropy's primitive (flex only: the other backends compose it).
#[backend_extension(Flex: cfg(feature = "flex"), Autodiff)]
pub trait AnisotropyOps: Backend {
    /// The whole anisotropy `a[u]` from the images: [`anisotropy`]'s primitive.
    #[allow(clippy::too_many_arguments)]
    fn anisotropy(
        u: FloatTensor<Self>,
        rows0: FloatTensor<Self>,
        cols0_t: FloatTensor<Self>,
        rows1: FloatTensor<Self>,
        cols1_t: FloatTensor<Self>,
        xi1: f64,
        xi2: f64,
    ) -> FloatTensor<Self>;
}

/// `a[u] = exp(−Σ_c (d0_c² + d1_c²) / ξ₁) + ξ₂` with `d0 = R₀ u C₀ᵀ`, `d1 = R₁ u C₁ᵀ` (the
/// two separable operators of SPEC §3, `along_rows` and `along_cols`), in one op: each
/// output row's derivatives are computed, squared and summed while in cache. Composed, the
/// two operators wrote four frame-sized intermediates (each pass of each operator) that the
/// weight read back: at 512² and `K = 15` a sweep's anisotropies moved about half a
/// gigabyte. The same values as the weight of the two operators' outputs, bit for bit.
/// Not differentiable (a constant). Only on a backend that serves it (flex).
///
/// # Shapes
/// - `u`: `[N, C, H, W]`; the operators' `R` `[1, 1, H, H]` and `Cᵀ` `[1, 1, W, W]`
/// - output: `[N, H, W]`
pub fn anisotropy(
    u: Tensor<4>,
    along_rows: (Tensor<4>, Tensor<4>),
    along_cols: (Tensor<4>, Tensor<4>),
    xi1: f64,
    xi2: f64,
) -> Tensor<3> {
    Tensor::from_dispatch(Dispatch::anisotropy(
        u.detach().into_dispatch(),
        along_rows.0.into_dispatch(),
        along_rows.1.into_dispatch(),
        along_cols.0.into_dispatch(),
        along_cols.1.into_dispatch(),
        xi1,
        xi2,
    ))
}

/// Pixels per task: enough that a task outweighs rayon's overhead.
const PIXELS_PER_TASK: usize = 4096;

/// The weight from given derivatives `d0`, `d1` `[N, C, H·W]` into `out` `[N, H·W]`: what
/// [`anisotropy`] computes row by row, here whole frames at a time: its tests' reference.
/// The same operations as the composed weight: the squares summed per pixel over the channels in
/// order, scaled by `−1/ξ₁` rounded once, the exponential, `+ ξ₂`.
#[cfg(test)]
fn host_edge_weight<T: Real>(
    d0: &[T],
    d1: &[T],
    [n, c, plane]: [usize; 3],
    xi1: f64,
    xi2: f64,
    out: &mut [T],
) {
    use rayon::prelude::*;
    assert!(
        d0.len() == n * c * plane && d1.len() == d0.len() && out.len() == n * plane,
        "edge weight: derivatives of {} and {} values, weights of {}, for [{n}, {c}, {plane}]",
        d0.len(),
        d1.len(),
        out.len()
    );
    let (scale, offset) = (T::from_f64(-1.0 / xi1), T::from_f64(xi2));
    out.par_chunks_mut(plane)
        .enumerate()
        .for_each(|(b, image)| {
            let norm2 = |p: usize| {
                let mut sum = T::default();
                for channel in 0..c {
                    let at = (b * c + channel) * plane + p;
                    sum += d0[at] * d0[at] + d1[at] * d1[at];
                }
                sum * scale
            };
            image
                .par_chunks_mut(PIXELS_PER_TASK)
                .enumerate()
                .for_each(|(task, out)| {
                    let mut p = task * PIXELS_PER_TASK;
                    let mut runs = out.chunks_exact_mut(8);
                    for run in &mut runs {
                        let weights = T::exp8(std::array::from_fn(|l| norm2(p + l)));
                        for (o, w) in run.iter_mut().zip(weights) {
                            *o = w + offset;
                        }
                        p += 8;
                    }
                    for o in runs.into_remainder() {
                        *o = norm2(p).exp() + offset;
                        p += 1;
                    }
                });
        });
}

/// `exp(scaled) + offset` of a row of pixels `first ..` of a plane of `plane` pixels, as
/// the whole-frame weight (`host_edge_weight`, the tests' reference) takes it: eight lanes
/// at a time ([`Real::exp8`]: each lane's value does not depend on the others, so any eight
/// pixels may share a call), except the plane's last `plane mod 8` pixels, one at a time.
fn edge_weight_row<T: Real>(
    scaled: &[T],
    first: usize,
    plane: usize,
    offset: T,
    out: &mut [MaybeUninit<T>],
) {
    let lanes_end = (plane - plane % 8).saturating_sub(first).min(scaled.len());
    let mut j = 0;
    while j < lanes_end {
        let take = (lanes_end - j).min(8);
        let weights = T::exp8(std::array::from_fn(|l| scaled[j + l.min(take - 1)]));
        for (o, w) in out[j..j + take].iter_mut().zip(weights) {
            o.write(w + offset);
        }
        j += take;
    }
    for (o, &v) in out[j..].iter_mut().zip(&scaled[j..]) {
        o.write(v.exp() + offset);
    }
}

/// The host kernel of [`anisotropy`]: `u` `[N, C, H, W]`, `out` `[N, H, W]`; the operators
/// `(R, C)` as bands. A task takes whole output rows: per row, each channel's two
/// derivative rows ([`separable::host::apply_row`]), then the weight.
///
/// [`separable::host::apply_row`]: crate::model::separable::host::apply_row
pub fn host_anisotropy<T: Real>(
    u: &[T],
    [n, c, h, w]: [usize; 4],
    along_rows: (&Band<T>, &Band<T>),
    along_cols: (&Band<T>, &Band<T>),
    xi1: f64,
    xi2: f64,
    out: &mut [MaybeUninit<T>],
) {
    use rayon::prelude::*;
    let operators = [along_rows, along_cols];
    for (r, cols) in operators {
        assert!(
            r.rows() == h && r.cols() == h && cols.rows() == w && cols.cols() == w,
            "anisotropy: operators {}×{} and {}×{} on {h}×{w} images",
            r.rows(),
            r.cols(),
            cols.rows(),
            cols.cols()
        );
    }
    assert!(
        u.len() == n * c * h * w && out.len() == n * h * w,
        "anisotropy: {} values for [{n}, {c}, {h}, {w}], {} weights",
        u.len(),
        out.len()
    );
    let runs = operators.map(|(_, cols)| cols.shifted_runs());
    let (scale, offset, plane) = (T::from_f64(-1.0 / xi1), T::from_f64(xi2), h * w);
    // Scratch per task: a pass's row, each operator's output row, the row's sums.
    let scratch = || {
        (
            vec![MaybeUninit::<T>::uninit(); 3 * w],
            vec![T::default(); w],
        )
    };
    out.par_chunks_mut(w)
        .enumerate()
        .with_min_len((PIXELS_PER_TASK / w).max(1))
        .for_each_init(scratch, |(rows, sum), (row, out)| {
            let (b, i) = (row / h, row % h);
            let (down, derivatives) = rows.split_at_mut(w);
            let (d0, d1) = derivatives.split_at_mut(w);
            sum.fill(T::default());
            for channel in 0..c {
                let x = &u[(b * c + channel) * plane..(b * c + channel + 1) * plane];
                for (d, ((r, cols), runs)) in [&mut *d0, &mut *d1]
                    .into_iter()
                    .zip(operators.iter().zip(&runs))
                {
                    apply_row(x, r, cols, runs, i, down, d);
                }
                // SAFETY: apply_row wrote every value of both rows just now.
                let (d0, d1) = unsafe {
                    (
                        &*(std::ptr::from_ref(&*d0) as *const [T]),
                        &*(std::ptr::from_ref(&*d1) as *const [T]),
                    )
                };
                for ((s, &a), &b) in sum.iter_mut().zip(d0).zip(d1) {
                    *s += a * a + b * b;
                }
            }
            for s in sum.iter_mut() {
                *s = *s * scale;
            }
            edge_weight_row(sum, i * w, plane, offset, out);
        });
}

#[cfg(feature = "flex")]
mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};

    use super::{AnisotropyOps, host_anisotropy};
    use crate::model::cpu::Real;
    use crate::model::host_view::HostView;
    use crate::model::separable::host::Band;

    fn anisotropy_typed<T: Real + burn::tensor::Element + bytemuck::Pod>(
        u: &HostView,
        operators: [(&HostView, &HostView); 2],
        xi1: f64,
        xi2: f64,
    ) -> TensorData {
        let s = u.shape();
        assert_eq!(s.len(), 4, "anisotropy: images {s:?} are not [N, C, H, W]");
        // `R` row-major, `Cᵀ` stored: `C` column-major.
        let [(r0, c0), (r1, c1)] = operators.map(|(r, c_t)| {
            let (rs, cs) = (r.shape(), c_t.shape());
            assert!(
                rs.len() == 4 && cs.len() == 4,
                "anisotropy: operators {rs:?} and {cs:?} are not [1, 1, n, m]"
            );
            (
                Band::from_row_major(rs[2], rs[3], r.values::<T>()),
                Band::from_column_major(cs[3], cs[2], c_t.values::<T>()),
            )
        });
        let len = s[0] * s[2] * s[3];
        let mut out = Vec::with_capacity(len);
        host_anisotropy(
            u.values::<T>(),
            [s[0], s[1], s[2], s[3]],
            (&r0, &c0),
            (&r1, &c1),
            xi1,
            xi2,
            &mut out.spare_capacity_mut()[..len],
        );
        // SAFETY: host_anisotropy wrote every one of the `len` weights.
        unsafe { out.set_len(len) };
        TensorData::new(out, [s[0], s[2], s[3]])
    }

    impl AnisotropyOps for Flex {
        fn anisotropy(
            u: FlexTensor,
            rows0: FlexTensor,
            cols0_t: FlexTensor,
            rows1: FlexTensor,
            cols1_t: FlexTensor,
            xi1: f64,
            xi2: f64,
        ) -> FlexTensor {
            let u = HostView::new(u);
            let [r0, c0, r1, c1] = [rows0, cols0_t, rows1, cols1_t].map(HostView::new);
            let operators = [(&r0, &c0), (&r1, &c1)];
            FlexTensor::from_data(match u.dtype() {
                DType::F32 => anisotropy_typed::<f32>(&u, operators, xi1, xi2),
                DType::F64 => anisotropy_typed::<f64>(&u, operators, xi1, xi2),
                other => panic!("the anisotropy runs in float32 or float64, not {other:?}"),
            })
        }
    }
}

mod autodiff {
    use burn::backend::Autodiff;
    use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
    use burn::backend::tensor::FloatTensor;

    use super::AnisotropyOps;

    impl<B: AnisotropyOps, C: CheckpointStrategy> AnisotropyOps for Autodiff<B, C> {
        /// A constant: no gradient flows through it (its input is detached, the operators
        /// are the model's constants).
        fn anisotropy(
            u: FloatTensor<Self>,
            rows0: FloatTensor<Self>,
            cols0_t: FloatTensor<Self>,
            rows1: FloatTensor<Self>,
            cols1_t: FloatTensor<Self>,
            xi1: f64,
            xi2: f64,
        ) -> FloatTensor<Self> {
            let [u, rows0, cols0_t, rows1, cols1_t] =
                [u, rows0, cols0_t, rows1, cols1_t].map(|t| t.into_parts().0);
            FloatTensor::<Self>::new(B::anisotropy(u, rows0, cols0_t, rows1, cols1_t, xi1, xi2))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::{host_anisotropy, host_edge_weight};

    /// Derivatives of `n` images of `c` channels and `plane` pixels, spread over the weight's
    /// whole range (`|∇u|²/ξ₁` from 0 to about 30).
    fn derivatives(n: usize, c: usize, plane: usize) -> (Vec<f64>, Vec<f64>) {
        let value = |i: usize, k: usize| (((i * k) % 97) as f64 - 48.0) / 300.0;
        let len = n * c * plane;
        (
            (0..len).map(|i| value(i, 31)).collect(),
            (0..len).map(|i| value(i, 53)).collect(),
        )
    }

    /// The weight one pixel at a time, in the composed order.
    fn reference<T: crate::model::cpu::Real>(
        d0: &[T],
        d1: &[T],
        [n, c, plane]: [usize; 3],
        xi1: f64,
        xi2: f64,
    ) -> Vec<T> {
        let (scale, offset) = (T::from_f64(-1.0 / xi1), T::from_f64(xi2));
        (0..n * plane)
            .map(|at| {
                let (b, p) = (at / plane, at % plane);
                let mut sum = T::default();
                for channel in 0..c {
                    let i = (b * c + channel) * plane + p;
                    sum += d0[i] * d0[i] + d1[i] * d1[i];
                }
                (sum * scale).exp() + offset
            })
            .collect()
    }

    /// The whole-anisotropy kernel gives the two separable operators' outputs weighted by
    /// [`host_edge_weight`], bit for bit: float32 and float64, a plane that is not whole
    /// lanes, lines shorter than the stencils and lines with a long interior.
    #[test]
    fn the_fused_anisotropy_is_the_operators_then_the_weight() {
        use crate::model::separable::host::{Band, apply};
        use crate::model::stencil::{Matrix, central_difference_domain, gaussian};
        use std::mem::MaybeUninit;

        fn check<T: crate::model::cpu::Real + PartialEq + std::fmt::Debug>(
            [n, c, h, w]: [usize; 4],
        ) {
            let band = |m: &Matrix| {
                let data: Vec<T> = m.data.iter().map(|&v| T::from_f64(v)).collect();
                Band::from_row_major(m.rows, m.cols, &data)
            };
            let smooth = |n| gaussian(n, 2.0).matmul(&gaussian(n, 0.5));
            let derivative = |n| {
                gaussian(n, 2.0).matmul(&central_difference_domain(n).matmul(&gaussian(n, 0.5)))
            };
            let rows = (band(&derivative(h)), band(&smooth(w)));
            let cols = (band(&smooth(h)), band(&derivative(w)));
            let u: Vec<T> = (0..n * c * h * w)
                .map(|i| T::from_f64(((i * 7919) % 1013) as f64 / 1013.0))
                .collect();
            let (xi1, xi2) = (1e-3, 1e-6);
            let d0 = apply(&u, &rows.0, &rows.1);
            let d1 = apply(&u, &cols.0, &cols.1);
            let mut want = vec![T::default(); n * h * w];
            host_edge_weight(&d0, &d1, [n, c, h * w], xi1, xi2, &mut want);
            let mut got = vec![MaybeUninit::uninit(); n * h * w];
            host_anisotropy(
                &u,
                [n, c, h, w],
                (&rows.0, &rows.1),
                (&cols.0, &cols.1),
                xi1,
                xi2,
                &mut got,
            );
            // SAFETY: the kernel wrote every weight.
            let got: Vec<T> = got
                .into_iter()
                .map(|v| unsafe { v.assume_init() })
                .collect();
            assert!(
                got.iter()
                    .zip(&want)
                    .all(|(g, e)| g.to_f64().to_bits() == e.to_f64().to_bits()),
                "[{n}, {c}, {h}, {w}]: the fused anisotropy differs"
            );
        }
        for dims in [[2, 3, 13, 29], [1, 3, 70, 75], [3, 1, 5, 6], [1, 3, 40, 64]] {
            check::<f32>(dims);
            check::<f64>(dims);
        }
    }

    #[test]
    fn the_fused_weight_is_the_composed_formula() {
        // Planes longer than a task and not a multiple of the eight lanes.
        let dims = [2, 3, 4096 + 13];
        let (xi1, xi2) = (0.01, 0.1);
        let (d0, d1) = derivatives(dims[0], dims[1], dims[2]);
        let mut out = vec![0.0; dims[0] * dims[2]];
        host_edge_weight(&d0, &d1, dims, xi1, xi2, &mut out);
        // float64: libm's exp in both, the same bits.
        assert_eq!(out, reference(&d0, &d1, dims, xi1, xi2));

        let (d0, d1): (Vec<f32>, Vec<f32>) = (
            d0.iter().map(|&v| v as f32).collect(),
            d1.iter().map(|&v| v as f32).collect(),
        );
        let mut out = vec![0.0f32; dims[0] * dims[2]];
        host_edge_weight(&d0, &d1, dims, xi1, xi2, &mut out);
        // float32: the vectorised exponential against libm's, to an ulp of the exponential.
        for (got, want) in out.iter().zip(reference(&d0, &d1, dims, xi1, xi2)) {
            assert!((got - want).abs() <= 1.2e-7 * want, "{got} against {want}");
        }
    }
}
