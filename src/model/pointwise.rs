//! The two elementwise updates of an iPALM step on whole frames (SPEC §6), as custom Burn
//! ops (Burn 0.22's `#[backend_extension]`): the inertial point `x + β·(x − y)` and the
//! gradient step `x − s·g`.
//!
//! - flex: one pass over the inputs, read in place, split over the cores. flex's own
//!   elementwise ops run on one core and make one pass (and one fresh tensor) per
//!   operation: three for the inertial point, two for the step, on 64-channel frames at
//!   every feature step and trial.
//! - ndarray, wgpu: the trait's default bodies, the composed ops.
//! - autodiff: on untracked inputs (the solver's: frames and gradients are detached) the
//!   inner backend's op; on tracked ones the composed ops, recorded as usual.
//!
//! Each value is computed with the same float operations in the same order as the composed
//! form (`x + (x − y)·β`, `x − g·s`, the scalar rounded to the tensor's precision first),
//! so the results are the same bits.
//!
//! With [`crate::model::decision`], [`crate::model::warp::op`] and the other custom ops,
//! the only numerical code that names backends.

#![allow(deprecated)] // `NdArray` is deprecated upstream in favour of flex; it stays served.

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, TensorMetadata, backend_extension};
use burn::tensor::{Scalar, Tensor};

/// The updates' primitives.
#[backend_extension(
    Flex: cfg(feature = "flex"),
    NdArray: cfg(feature = "ndarray"),
    Cube: cfg(feature = "wgpu"),
    Autodiff
)]
pub trait PointwiseOps: Backend {
    /// `x + (x − y)·β` (shapes equal).
    fn pointwise_extrapolate(
        x: FloatTensor<Self>,
        y: FloatTensor<Self>,
        beta: f64,
    ) -> FloatTensor<Self> {
        composed_extrapolate::<Self>(x, y, beta)
    }
    /// `x − g·s` (shapes equal).
    fn pointwise_descend(x: FloatTensor<Self>, g: FloatTensor<Self>, s: f64) -> FloatTensor<Self> {
        composed_descend::<Self>(x, g, s)
    }
}

fn composed_extrapolate<B: Backend>(
    x: FloatTensor<B>,
    y: FloatTensor<B>,
    beta: f64,
) -> FloatTensor<B> {
    let beta = Scalar::new(beta, &x.dtype());
    B::float_add(x.clone(), B::float_mul_scalar(B::float_sub(x, y), beta))
}

fn composed_descend<B: Backend>(x: FloatTensor<B>, g: FloatTensor<B>, s: f64) -> FloatTensor<B> {
    let s = Scalar::new(s, &g.dtype());
    B::float_sub(x, B::float_mul_scalar(g, s))
}

#[cfg(feature = "ndarray")]
impl PointwiseOps for burn::backend::NdArray {}

#[cfg(feature = "wgpu")]
impl PointwiseOps for burn::backend::Cube {}

/// The inertial point `x + β·(x − y)` (SPEC §6: `x` the current iterate, `y` the previous).
///
/// # Panics
///
/// If the shapes differ.
pub fn extrapolate<const D: usize>(x: Tensor<D>, y: Tensor<D>, beta: f64) -> Tensor<D> {
    assert_eq!(x.dims(), y.dims(), "extrapolate: shapes differ");
    Tensor::from_dispatch(Dispatch::pointwise_extrapolate(
        x.into_dispatch(),
        y.into_dispatch(),
        beta,
    ))
}

/// The gradient step `x − s·g`.
///
/// # Panics
///
/// If the shapes differ.
pub fn descend<const D: usize>(x: Tensor<D>, g: Tensor<D>, s: f64) -> Tensor<D> {
    assert_eq!(x.dims(), g.dims(), "descend: shapes differ");
    Tensor::from_dispatch(Dispatch::pointwise_descend(
        x.into_dispatch(),
        g.into_dispatch(),
        s,
    ))
}

#[cfg(feature = "flex")]
mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};
    use rayon::prelude::*;

    use super::PointwiseOps;
    use crate::model::host_view::HostView;

    /// Values per task.
    const CHUNK: usize = 1 << 15;

    /// `f(a_i, b_i)` for every `i`, in parallel, as a tensor of `a`'s shape.
    fn zip_map<T>(a: &HostView, b: &HostView, f: impl Fn(T, T) -> T + Sync) -> FlexTensor
    where
        T: bytemuck::Pod + burn::tensor::Element + Send + Sync + Default,
    {
        let (x, y) = (a.values::<T>(), b.values::<T>());
        assert_eq!(x.len(), y.len(), "pointwise: lengths differ");
        let mut out = vec![T::default(); x.len()];
        out.par_chunks_mut(CHUNK)
            .zip(x.par_chunks(CHUNK).zip(y.par_chunks(CHUNK)))
            .for_each(|(o, (x, y))| {
                for ((o, &x), &y) in o.iter_mut().zip(x).zip(y) {
                    *o = f(x, y);
                }
            });
        FlexTensor::from_data(TensorData::new(out, a.shape()))
    }

    fn views(x: FlexTensor, y: FlexTensor) -> (HostView, HostView) {
        let (x, y) = (HostView::new(x), HostView::new(y));
        assert_eq!(x.dtype(), y.dtype(), "pointwise: dtypes differ");
        (x, y)
    }

    impl PointwiseOps for Flex {
        fn pointwise_extrapolate(x: FlexTensor, y: FlexTensor, beta: f64) -> FlexTensor {
            let (x, y) = views(x, y);
            match x.dtype() {
                DType::F32 => {
                    let b = beta as f32;
                    zip_map::<f32>(&x, &y, |x, y| x + (x - y) * b)
                }
                DType::F64 => zip_map::<f64>(&x, &y, |x, y| x + (x - y) * beta),
                other => panic!("pointwise ops run in float32 or float64, not {other:?}"),
            }
        }

        fn pointwise_descend(x: FlexTensor, g: FlexTensor, s: f64) -> FlexTensor {
            let (x, g) = views(x, g);
            match x.dtype() {
                DType::F32 => {
                    let s = s as f32;
                    zip_map::<f32>(&x, &g, |x, g| x - g * s)
                }
                DType::F64 => zip_map::<f64>(&x, &g, |x, g| x - g * s),
                other => panic!("pointwise ops run in float32 or float64, not {other:?}"),
            }
        }
    }
}

mod autodiff {
    use burn::backend::Autodiff;
    use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
    use burn::backend::tensor::FloatTensor;

    use super::{PointwiseOps, composed_descend, composed_extrapolate};

    impl<B: PointwiseOps, C: CheckpointStrategy> PointwiseOps for Autodiff<B, C> {
        fn pointwise_extrapolate(
            x: FloatTensor<Self>,
            y: FloatTensor<Self>,
            beta: f64,
        ) -> FloatTensor<Self> {
            if x.is_tracked() || y.is_tracked() {
                return composed_extrapolate::<Self>(x, y, beta);
            }
            let (x, _) = x.into_parts();
            let (y, _) = y.into_parts();
            FloatTensor::<Self>::new(B::pointwise_extrapolate(x, y, beta))
        }

        fn pointwise_descend(
            x: FloatTensor<Self>,
            g: FloatTensor<Self>,
            s: f64,
        ) -> FloatTensor<Self> {
            if x.is_tracked() || g.is_tracked() {
                return composed_descend::<Self>(x, g, s);
            }
            let (x, _) = x.into_parts();
            let (g, _) = g.into_parts();
            FloatTensor::<Self>::new(B::pointwise_descend(x, g, s))
        }
    }
}
