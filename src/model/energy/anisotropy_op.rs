//! The edge-stopping weight `exp(−|∇u|²/ξ₁) + ξ₂` of the anisotropy (SPEC §3) from its two
//! smoothed derivatives, as one custom Burn op (Burn 0.22's `#[backend_extension]`).
//!
//! Composed, the weight after the two separable operators is six passes over the frames:
//! the two squares, their sum, the sum over the colour channels, the scaling and the
//! exponential (flex's elementwise ops run one at a time on the calling thread; its `exp` is
//! libm's, one value at a time). A profile of a 256² RGB sweep had those at about a sixth of
//! the anisotropy's samples. Fused, it is one pass split over the cores, its exponential
//! eight lanes at a time (`crate::model::cpu::elementary`).
//!
//! - flex: the host kernel below.
//! - autodiff: a constant. The anisotropy is a fixed weight of every derivative the model
//!   takes, so its input is detached ([`super::anisotropy::Anisotropy::compute`]).
//! - ndarray and wgpu compose the weight from tensor ops (not served here).

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::Tensor;

use crate::model::cpu::Real;

/// The weight's primitive (flex only: the other backends compose it).
#[backend_extension(Flex: cfg(feature = "flex"), Autodiff)]
pub trait AnisotropyOps: Backend {
    /// `exp(−Σ_c (d0_c² + d1_c²) / ξ₁) + ξ₂`; shapes as in [`edge_weight`].
    fn edge_weight(
        d0: FloatTensor<Self>,
        d1: FloatTensor<Self>,
        xi1: f64,
        xi2: f64,
    ) -> FloatTensor<Self>;
}

/// `exp(−Σ_c (d0_c² + d1_c²) / ξ₁) + ξ₂` at every pixel by the fused op: the anisotropy of
/// SPEC §3 from the smoothed derivatives along rows (`d0`) and columns (`d1`). Not
/// differentiable (a constant, as the anisotropy is). Only on a backend that serves it (flex).
///
/// # Shapes
/// - `d0`, `d1`: `[N, C, H, W]`; output `[N, H, W]`
pub fn edge_weight(d0: Tensor<4>, d1: Tensor<4>, xi1: f64, xi2: f64) -> Tensor<3> {
    assert_eq!(
        d0.dims(),
        d1.dims(),
        "edge weight: the derivatives' shapes differ"
    );
    Tensor::from_dispatch(Dispatch::edge_weight(
        d0.detach().into_dispatch(),
        d1.detach().into_dispatch(),
        xi1,
        xi2,
    ))
}

/// Pixels per task: enough that a task outweighs rayon's overhead.
const PIXELS_PER_TASK: usize = 4096;

/// The host kernel of [`edge_weight`]: `d0`, `d1` `[N, C, H·W]`, `out` `[N, H·W]`. The same
/// operations as the composed weight: the squares summed per pixel over the channels in
/// order, scaled by `−1/ξ₁` rounded once, the exponential, `+ ξ₂`.
pub fn host_edge_weight<T: Real>(
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

#[cfg(feature = "flex")]
mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};

    use super::{AnisotropyOps, host_edge_weight};
    use crate::model::cpu::Real;
    use crate::model::host_view::HostView;

    fn weight_typed<T: Real + burn::tensor::Element + bytemuck::Pod>(
        d0: &HostView,
        d1: &HostView,
        xi1: f64,
        xi2: f64,
    ) -> TensorData {
        let s = d0.shape();
        assert!(
            s.len() == 4 && d1.shape() == s,
            "edge weight: derivatives {s:?} and {:?} are not one [N, C, H, W]",
            d1.shape()
        );
        let mut out = vec![T::default(); s[0] * s[2] * s[3]];
        host_edge_weight(
            d0.values(),
            d1.values(),
            [s[0], s[1], s[2] * s[3]],
            xi1,
            xi2,
            &mut out,
        );
        TensorData::new(out, [s[0], s[2], s[3]])
    }

    impl AnisotropyOps for Flex {
        fn edge_weight(d0: FlexTensor, d1: FlexTensor, xi1: f64, xi2: f64) -> FlexTensor {
            let (d0, d1) = (HostView::new(d0), HostView::new(d1));
            assert_eq!(d0.dtype(), d1.dtype(), "edge weight: dtypes differ");
            FlexTensor::from_data(match d0.dtype() {
                DType::F32 => weight_typed::<f32>(&d0, &d1, xi1, xi2),
                DType::F64 => weight_typed::<f64>(&d0, &d1, xi1, xi2),
                other => panic!("the edge weight runs in float32 or float64, not {other:?}"),
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
        /// A constant: no gradient flows through it (its inputs are detached).
        fn edge_weight(
            d0: FloatTensor<Self>,
            d1: FloatTensor<Self>,
            xi1: f64,
            xi2: f64,
        ) -> FloatTensor<Self> {
            let ((d0, _), (d1, _)) = (d0.into_parts(), d1.into_parts());
            FloatTensor::<Self>::new(B::edge_weight(d0, d1, xi1, xi2))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::host_edge_weight;

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
