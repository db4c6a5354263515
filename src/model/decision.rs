//! The float64 sums that decide a backtracking test or the safeguard (SPEC §6, "Floating
//! point") as custom Burn ops (Burn 0.22's `#[backend_extension]`).
//!
//! - flex: one pass over the float32 (or float64) buffer, read in place, products and sums
//!   in float64, split over the cores. Composed, the same sum was three passes: the product
//!   or square in float32, a float64 copy of it (twice the memory) and the sum.
//! - ndarray, wgpu: the trait's default bodies, the composed ops, products in float64 too
//!   (wgpu is never asked: it has no float64, and its decisions sum in float32,
//!   [`crate::model::grid::Accumulation`]).
//! - autodiff: not differentiable; the inputs are detached by the caller.
//!
//! With [`crate::model::warp::op`], [`crate::model::separable::op`] and
//! [`crate::model::slopes`], the only numerical code that names backends.

#![allow(deprecated)] // `NdArray` is deprecated upstream in favour of flex; it stays served.

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::{FloatDType, Tensor};

/// The decision sums' primitives, each a `[1]` float64 tensor.
#[backend_extension(
    Flex: cfg(feature = "flex"),
    NdArray: cfg(feature = "ndarray"),
    Cube: cfg(feature = "wgpu"),
    Autodiff
)]
pub trait DecisionOps: Backend {
    /// `Σ a` over every entry.
    fn decision_sum(a: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::float_sum(Self::float_cast(a, FloatDType::F64))
    }
    /// `Σ a·b` over every entry (shapes equal).
    fn decision_dot(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
        let (a, b) = (
            Self::float_cast(a, FloatDType::F64),
            Self::float_cast(b, FloatDType::F64),
        );
        Self::float_sum(Self::float_mul(a, b))
    }
    /// `Σ (a − b)²` over every entry (shapes equal): the difference in the tensors' own
    /// precision, as `a − b` would be, its square and the sum in float64.
    fn decision_distance2(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
        let d = Self::float_cast(Self::float_sub(a, b), FloatDType::F64);
        Self::float_sum(Self::float_mul(d.clone(), d))
    }
}

#[cfg(feature = "ndarray")]
impl DecisionOps for burn::backend::NdArray {}

#[cfg(feature = "wgpu")]
impl DecisionOps for burn::backend::Cube {}

/// `Σ t` over every entry of `t`, accumulated in float64, `[1]`.
pub fn sum<const D: usize>(t: Tensor<D>) -> Tensor<1> {
    Tensor::<1>::from_dispatch(Dispatch::decision_sum(t.detach().into_dispatch()))
}

/// `Σ a·b` over every entry, the products and their sum in float64, `[1]`.
///
/// # Panics
///
/// If the shapes differ.
pub fn dot<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> Tensor<1> {
    assert_eq!(a.dims(), b.dims(), "decision dot: shapes differ");
    Tensor::<1>::from_dispatch(Dispatch::decision_dot(
        a.detach().into_dispatch(),
        b.detach().into_dispatch(),
    ))
}

/// `Σ (a − b)²`, `[1]`: [`sum_squares`] of `a − b` without the difference as a tensor (a
/// fresh frame per backtracking trial), the same value bit for bit.
///
/// # Panics
///
/// If the shapes differ.
pub fn distance2<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> Tensor<1> {
    assert_eq!(a.dims(), b.dims(), "decision distance: shapes differ");
    Tensor::<1>::from_dispatch(Dispatch::decision_distance2(
        a.detach().into_dispatch(),
        b.detach().into_dispatch(),
    ))
}

/// `Σ t²`, `[1]`: [`dot`] of `t` with itself.
pub fn sum_squares<const D: usize>(t: Tensor<D>) -> Tensor<1> {
    dot(t.clone(), t)
}

#[cfg(feature = "flex")]
mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};
    use rayon::prelude::*;

    use super::DecisionOps;
    use crate::model::host_view::HostView;

    /// Values per task: a task's float64 partial sum then adds to the others in a fixed
    /// order, so the result does not depend on the thread count.
    const CHUNK: usize = 1 << 14;

    /// `Σ f(a_i, b_i)` in float64 over chunks, in eight interleaved lanes per chunk.
    fn reduce<T: Copy + Sync>(a: &[T], b: &[T], f: impl Fn(T, T) -> f64 + Sync) -> f64 {
        let partial: Vec<f64> = a
            .par_chunks(CHUNK)
            .zip(b.par_chunks(CHUNK))
            .map(|(a, b)| {
                let mut lanes = [0.0f64; 8];
                let (a8, b8) = (a.chunks_exact(8), b.chunks_exact(8));
                let (a_rest, b_rest) = (a8.remainder(), b8.remainder());
                for (x, y) in a8.zip(b8) {
                    for j in 0..8 {
                        lanes[j] += f(x[j], y[j]);
                    }
                }
                let mut s = ((lanes[0] + lanes[1]) + (lanes[2] + lanes[3]))
                    + ((lanes[4] + lanes[5]) + (lanes[6] + lanes[7]));
                for (&x, &y) in a_rest.iter().zip(b_rest) {
                    s += f(x, y);
                }
                s
            })
            .collect();
        partial.iter().sum()
    }

    fn dot(a: &HostView, b: &HostView) -> f64 {
        match a.dtype() {
            DType::F32 => reduce(a.values::<f32>(), b.values::<f32>(), |x, y| {
                f64::from(x) * f64::from(y)
            }),
            DType::F64 => reduce(a.values::<f64>(), b.values::<f64>(), |x, y| x * y),
            other => panic!("decision sums read float32 or float64, not {other:?}"),
        }
    }

    fn distance2(a: &HostView, b: &HostView) -> f64 {
        match a.dtype() {
            DType::F32 => reduce(a.values::<f32>(), b.values::<f32>(), |x, y| {
                let d = f64::from(x - y);
                d * d
            }),
            DType::F64 => reduce(a.values::<f64>(), b.values::<f64>(), |x, y| {
                let d = x - y;
                d * d
            }),
            other => panic!("decision sums read float32 or float64, not {other:?}"),
        }
    }

    fn scalar(v: f64) -> FlexTensor {
        FlexTensor::from_data(TensorData::new(vec![v], [1]))
    }

    impl DecisionOps for Flex {
        fn decision_sum(a: FlexTensor) -> FlexTensor {
            let a = HostView::new(a);
            let v = match a.dtype() {
                DType::F32 => reduce(a.values::<f32>(), a.values::<f32>(), |x, _| f64::from(x)),
                DType::F64 => reduce(a.values::<f64>(), a.values::<f64>(), |x, _| x),
                other => panic!("decision sums read float32 or float64, not {other:?}"),
            };
            scalar(v)
        }

        fn decision_dot(a: FlexTensor, b: FlexTensor) -> FlexTensor {
            let (a, b) = (HostView::new(a), HostView::new(b));
            assert_eq!(a.dtype(), b.dtype(), "decision dot: dtypes differ");
            scalar(dot(&a, &b))
        }

        fn decision_distance2(a: FlexTensor, b: FlexTensor) -> FlexTensor {
            let (a, b) = (HostView::new(a), HostView::new(b));
            assert_eq!(a.dtype(), b.dtype(), "decision distance: dtypes differ");
            scalar(distance2(&a, &b))
        }
    }
}

mod autodiff {
    use burn::backend::Autodiff;
    use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
    use burn::backend::tensor::FloatTensor;

    use super::DecisionOps;

    /// A decision sum's inputs are detached ([`super::sum`], [`super::dot`]): the op runs on
    /// the inner backend and its result is a constant.
    impl<B: DecisionOps, C: CheckpointStrategy> DecisionOps for Autodiff<B, C> {
        fn decision_sum(a: FloatTensor<Self>) -> FloatTensor<Self> {
            assert!(!a.is_tracked(), "a decision sum is not differentiable");
            let (a, _) = a.into_parts();
            FloatTensor::<Self>::new(B::decision_sum(a))
        }

        fn decision_dot(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
            assert!(
                !a.is_tracked() && !b.is_tracked(),
                "a decision sum is not differentiable"
            );
            let (a, _) = a.into_parts();
            let (b, _) = b.into_parts();
            FloatTensor::<Self>::new(B::decision_dot(a, b))
        }

        fn decision_distance2(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
            assert!(
                !a.is_tracked() && !b.is_tracked(),
                "a decision sum is not differentiable"
            );
            let (a, _) = a.into_parts();
            let (b, _) = b.into_parts();
            FloatTensor::<Self>::new(B::decision_distance2(a, b))
        }
    }
}
