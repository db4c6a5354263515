//! The squared distance `Σ_{c,y,x} (a − b)²` of each pair of a batch, the sum under the
//! data term (SPEC §5), as a differentiable custom Burn op (Burn 0.22's
//! `#[backend_extension]`).
//!
//! Composed, the data term of a feature step's block was the difference, its square (a
//! `mul` of the difference with itself), a sum over the last three axes, and in the backward
//! the sum's expansion, two products with the upstream gradient and their sum, and the
//! difference's negation for `b`: eight passes over the frame block, each one on the
//! solver's thread alone (flex's elementwise ops and reductions are single-threaded). A
//! profile of deep 128² joint sweeps had the value at 12 % of the solver thread's samples
//! and the backward's elementwise ops at 17 %. Fused, the value is one pass and the
//! gradient of each tracked input one, both split over the cores.
//!
//! - flex: the host kernels below. The value's squares and sums are float64 (its partial
//!   sums then add in a fixed order, whatever the thread count), returned in the tensors'
//!   precision; the gradient `2g·(a − b)` takes the difference in the tensors' precision,
//!   as composed, and is the same bits as the composed backward's `g·d + g·d`.
//! - ndarray, wgpu: the trait's default bodies, the composed ops.
//! - autodiff: `∂/∂a = 2g·(a − b)`, `∂/∂b = 2g·(b − a)` (the negation is exact).
//!
//! The custom ops and the backends they have kernels for are listed in one place,
//! `docs/architecture.md` ("Custom ops"): they are the only numerical code that names backends.

#![allow(deprecated)] // `NdArray` is deprecated upstream in favour of flex; it stays served.

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, TensorMetadata, backend_extension};
use burn::tensor::{Shape, Tensor};

/// The squared distance's primitives.
#[backend_extension(
    Flex: cfg(feature = "flex"),
    NdArray: cfg(feature = "ndarray"),
    Cube: cfg(feature = "wgpu"),
    Autodiff
)]
pub trait DistanceOps: Backend {
    /// `Σ (a_n − b_n)²` of each item `n` over its other axes, `[N]`; shapes as in
    /// [`distance2_each`].
    fn distance2_each(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
        let shape = a.shape();
        let n = shape[0];
        let per_item = shape.num_elements() / n.max(1);
        let d = Self::float_sub(a, b);
        let squares = Self::float_reshape(Self::float_mul(d.clone(), d), Shape::new([n, per_item]));
        Self::float_reshape(Self::float_sum_dim(squares, 1), Shape::new([n]))
    }
    /// [`distance2_each`](DistanceOps::distance2_each) whose value the caller has summed
    /// already (`value`, `[N]`, in any float dtype): returned in `a`'s dtype without a pass
    /// over `a` and `b`; differentiated as the distance.
    fn distance2_each_given(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        value: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let _ = b;
        Self::float_cast(value, a.dtype().into())
    }
    /// `s_n · (a_n − b_n)` for each item `n`: `a`, `b` and the output `[N, …]`, `s` `[N]`.
    /// The backward of [`distance2_each`] (with `s = 2g`); not differentiable itself.
    fn scaled_difference(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        s: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let shape = a.shape();
        let mut s_shape = vec![1; shape.num_dims()];
        s_shape[0] = shape[0];
        let s = Self::float_reshape(s, Shape::from(s_shape));
        Self::float_mul(Self::float_sub(a, b), s)
    }
}

#[cfg(feature = "ndarray")]
impl DistanceOps for burn::backend::NdArray {}

#[cfg(feature = "wgpu")]
impl DistanceOps for burn::backend::Cube {}

/// `Σ (a_n − b_n)²` over the channels and pixels of each pair `n`, differentiable in both.
///
/// # Shapes
/// - `a`, `b`: `[N, C, H, W]`
/// - output: `[N]`
///
/// # Panics
///
/// If the shapes differ.
pub fn distance2_each(a: Tensor<4>, b: Tensor<4>) -> Tensor<1> {
    assert_eq!(a.dims(), b.dims(), "squared distance: shapes differ");
    Tensor::from_dispatch(Dispatch::distance2_each(
        a.into_dispatch(),
        b.into_dispatch(),
    ))
}

/// [`distance2_each`] of `a` and `b` whose value `value` the caller has already summed:
/// `Σ (a_n − b_n)²` of each item, as the decision sums of SPEC §6 give it
/// (`Grid::decision_distance2_each`, float64 on the CPU). The forward returns it in the
/// tensors' dtype instead of summing again; the gradients are [`distance2_each`]'s. A feature
/// step needs both the decision sums of its residuals and their gradient: this is one pass
/// over each residual's two sides where the pair of ops made two. Debug builds check `value`
/// against a sum of their own.
///
/// # Shapes
/// - `a`, `b`: `[N, C, H, W]`
/// - `value`, output: `[N]`
///
/// # Panics
///
/// If the shapes differ.
pub fn distance2_each_given(a: Tensor<4>, b: Tensor<4>, value: Tensor<1>) -> Tensor<1> {
    assert_eq!(a.dims(), b.dims(), "squared distance: shapes differ");
    assert_eq!(
        value.dims(),
        [a.dims()[0]],
        "squared distance: one value per item"
    );
    let value = value.detach();
    #[cfg(debug_assertions)]
    {
        let summed = distance2_each(a.clone().detach(), b.clone().detach()).into_data();
        let given = value.clone().into_data();
        let (summed, given) = (
            summed
                .convert::<f64>()
                .into_vec::<f64>()
                .expect("float values"),
            given
                .convert::<f64>()
                .into_vec::<f64>()
                .expect("float values"),
        );
        for (s, g) in summed.iter().zip(&given) {
            assert!(
                // A float32 sum (wgpu, ndarray's composed value) rounds apart from the
                // float64 one by far less; a wrong value (another pair, unscaled) by far more.
                (s - g).abs() <= 1e-3 * s.abs().max(f64::MIN_POSITIVE),
                "squared distance: given {g}, summed {s}"
            );
        }
    }
    Tensor::from_dispatch(Dispatch::distance2_each_given(
        a.into_dispatch(),
        b.into_dispatch(),
        value.into_dispatch(),
    ))
}

#[cfg(feature = "flex")]
mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};

    use super::DistanceOps;
    use crate::model::cpu::{Real, combine};
    use crate::model::decision::flex::{Term, Value, reduce};
    use crate::model::host_view::HostView;

    trait Kernel: Real + burn::tensor::Element + bytemuck::Pod + Value {}
    impl Kernel for f32 {}
    impl Kernel for f64 {}

    /// The host kernel of [`super::distance2_each`] on row-major slices of `n` items: each
    /// item's sum as the decision sums add it ([`reduce`]: the difference in `T`, squares
    /// and sums in float64, in chunks whose partial sums add in a fixed order).
    fn host_distance2_each<T: Kernel>(a: &[T], b: &[T], n: usize) -> Vec<f64> {
        assert_eq!(a.len(), b.len(), "squared distance: lengths differ");
        let per_item = a.len() / n.max(1);
        (0..n)
            .map(|item| {
                let range = item * per_item..(item + 1) * per_item;
                reduce(&a[range.clone()], &b[range], Term::SquaredDifference)
            })
            .collect()
    }

    /// The host kernel of [`DistanceOps::scaled_difference`]: `s[item] · (a − b)`.
    fn host_scaled_difference<T: Kernel>(a: &[T], b: &[T], s: &[T]) -> Vec<T> {
        combine(a, b, s, |x, y, factor| (x - y) * factor)
    }

    macro_rules! typed {
        ($dtype:expr, $f:ident($($arg:expr),*)) => {
            match $dtype {
                DType::F32 => $f::<f32>($($arg),*),
                DType::F64 => $f::<f64>($($arg),*),
                other => panic!("the distance kernels run in float32 or float64, not {other:?}"),
            }
        };
    }

    fn distance2_typed<T: Kernel>(a: &HostView, b: &HostView) -> TensorData {
        let n = a.shape()[0];
        let sums = host_distance2_each(a.values::<T>(), b.values::<T>(), n);
        TensorData::new(sums.into_iter().map(T::from_f64).collect(), [n])
    }

    fn scaled_typed<T: Kernel>(a: &HostView, b: &HostView, s: &HostView) -> TensorData {
        let out = host_scaled_difference(a.values::<T>(), b.values::<T>(), s.values::<T>());
        TensorData::new(out, a.shape())
    }

    impl DistanceOps for Flex {
        fn distance2_each(a: FlexTensor, b: FlexTensor) -> FlexTensor {
            let (a, b) = HostView::pair(a, b, "squared distance");
            FlexTensor::from_data(typed!(a.dtype(), distance2_typed(&a, &b)))
        }

        fn scaled_difference(a: FlexTensor, b: FlexTensor, s: FlexTensor) -> FlexTensor {
            let (a, b) = HostView::pair(a, b, "scaled difference");
            let s = HostView::new(s);
            assert_eq!(s.dtype(), a.dtype(), "scaled difference: factors' dtype");
            FlexTensor::from_data(typed!(a.dtype(), scaled_typed(&a, &b, &s)))
        }
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn the_sums_do_not_depend_on_the_thread_count() {
            let len = 3 * (1 << 14) + 17;
            let a: Vec<f32> = (0..2 * len)
                .map(|i| ((i * 37) % 101) as f32 * 0.013)
                .collect();
            let b: Vec<f32> = (0..2 * len)
                .map(|i| ((i * 11) % 89) as f32 * 0.021)
                .collect();
            let in_pool = |threads: usize| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap()
                    .install(|| host_distance2_each(&a, &b, 2))
            };
            let one = in_pool(1);
            assert_eq!(one, in_pool(3));
            assert_eq!(one, in_pool(16));
            for (item, &sum) in one.iter().enumerate() {
                let exact: f64 = (item * len..(item + 1) * len)
                    .map(|i| f64::from(a[i] - b[i]).powi(2))
                    .sum();
                assert!(
                    (sum - exact).abs() <= 1e-12 * exact,
                    "{sum} against {exact}"
                );
            }
        }

        #[test]
        fn the_scaled_difference_writes_every_value() {
            // Items longer than `combine`'s chunks of 2^14 values.
            let len = 2 * (1 << 14) + 5;
            let a: Vec<f32> = (0..3 * len).map(|i| (i % 7) as f32).collect();
            let b: Vec<f32> = (0..3 * len).map(|i| (i % 5) as f32 * 0.5).collect();
            let s = [2.0f32, -0.25, 3.0];
            let out = host_scaled_difference(&a, &b, &s);
            assert_eq!(out.len(), a.len());
            for (i, &v) in out.iter().enumerate() {
                assert_eq!(v, (a[i] - b[i]) * s[i / len], "value {i}");
            }
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
    use burn::tensor::Scalar;

    use super::DistanceOps;

    #[derive(Debug)]
    struct Distance2;

    impl<B: DistanceOps> Backward<B, 2> for Distance2 {
        /// `a` and `b`.
        type State = (FloatTensor<B>, FloatTensor<B>);

        fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
            let [a_node, b_node] = ops.parents;
            let (a, b) = ops.state;
            let grad = grads.consume::<B>(&ops.node);
            // 2g is exact: the gradient 2g·(a − b) is then the composed backward's g·d + g·d.
            let twice = B::float_mul_scalar(grad, Scalar::Float(2.0));
            if let Some(node) = a_node {
                let g = B::scaled_difference(a.clone(), b.clone(), twice.clone());
                grads.register::<B>(node.id, g);
            }
            if let Some(node) = b_node {
                grads.register::<B>(node.id, B::scaled_difference(b, a, twice));
            }
        }
    }

    /// The backward's kernel is not differentiated again (first-order autodiff only).
    #[derive(Debug)]
    struct NotDifferentiable;

    impl<B: DistanceOps> Backward<B, 3> for NotDifferentiable {
        type State = ();

        fn backward(self, _: Ops<(), 3>, _: &mut Gradients, _: &mut Checkpointer) {
            unreachable!("prepared only for untracked inputs")
        }
    }

    /// The squared distance of `a` and `b` on the inner backend by `forward`, recorded with
    /// its backward ([`Distance2`]) where either input is tracked.
    fn tracked<B: DistanceOps, C: CheckpointStrategy>(
        a: FloatTensor<Autodiff<B, C>>,
        b: FloatTensor<Autodiff<B, C>>,
        forward: impl FnOnce(FloatTensor<B>, FloatTensor<B>) -> FloatTensor<B>,
    ) -> FloatTensor<Autodiff<B, C>> {
        let (a, a_node) = a.into_parts();
        let (b, b_node) = b.into_parts();
        match Distance2
            .prepare::<C>([a_node, b_node])
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let out = forward(a.clone(), b.clone());
                prep.finish((a, b), out)
            }
            OpsKind::UnTracked(prep) => prep.finish(forward(a, b)),
        }
    }

    impl<B: DistanceOps, C: CheckpointStrategy> DistanceOps for Autodiff<B, C> {
        fn distance2_each(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
            tracked::<B, C>(a, b, B::distance2_each)
        }

        fn distance2_each_given(
            a: FloatTensor<Self>,
            b: FloatTensor<Self>,
            value: FloatTensor<Self>,
        ) -> FloatTensor<Self> {
            let (value, _) = value.into_parts();
            tracked::<B, C>(a, b, |a, b| B::distance2_each_given(a, b, value))
        }

        fn scaled_difference(
            a: FloatTensor<Self>,
            b: FloatTensor<Self>,
            s: FloatTensor<Self>,
        ) -> FloatTensor<Self> {
            let (a, a_node) = a.into_parts();
            let (b, b_node) = b.into_parts();
            let (s, s_node) = s.into_parts();
            match NotDifferentiable
                .prepare::<C>([a_node, b_node, s_node])
                .compute_bound()
                .stateful()
            {
                OpsKind::UnTracked(prep) => prep.finish(B::scaled_difference(a, b, s)),
                OpsKind::Tracked(_) => {
                    panic!("the squared distance's backward kernel is not differentiable")
                }
            }
        }
    }
}
