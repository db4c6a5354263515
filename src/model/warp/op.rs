//! The cubic B-spline prefilter and evaluation as one custom Burn op each (Burn 0.22's
//! `#[backend_extension]`): native kernels per backend and a hand-written backward
//! registered with autodiff, so the solver still takes its gradients from `backward()`.
//!
//! - flex: the host kernels of [`super::host`] on the tensors' own buffers. The forward
//!   prefilter of many channels returns its coefficients channels-last (a permuted view of
//!   an `[N, H, W, C]` buffer), which the evaluation and the position gradient read in place;
//!   any other op sees an ordinary `[N, C, H, W]` tensor.
//! - wgpu: CubeCL kernels (`super::cube`).
//! - autodiff: the prefilter's backward is `Pᵀ`; the evaluation's backward is the adjoint
//!   scatter `B(φ)ᵀ g` for the coefficients and `Σ_c g_c ∂T_c/∂p` for `φ` (SPEC §1's `β'`,
//!   zero outside the clamp range).
//!
//! ndarray is not served: it keeps the composed tensor ops ([`crate::backend::Gather`]).
//! This module and `super::cube` hold what is backend-specific by nature, a kernel per
//! backend. The custom ops and the backends they have kernels for are listed in one place,
//! `docs/architecture.md` ("Custom ops"): they are the only numerical code that names backends.

// With no backend that serves these ops compiled (a build without them), the generated
// dispatch leaves the ops' scalar arguments unused.
#![cfg_attr(not(any(feature = "flex", feature = "wgpu")), allow(unused_variables))]

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::Tensor;

/// The spline's primitives. Shapes as in [`prefilter`], [`sample`], [`sample_adjoint`] and
/// [`sample_position_grad`].
#[backend_extension(Flex: cfg(feature = "flex"), Cube: cfg(feature = "wgpu"), Autodiff)]
pub trait SplineOps: Backend {
    /// `P x` (or `Pᵀ x`) of every plane.
    fn spline_prefilter(x: FloatTensor<Self>, transpose: bool) -> FloatTensor<Self>;
    /// `B(φ) c`.
    fn spline_sample(coeffs: FloatTensor<Self>, phi: FloatTensor<Self>) -> FloatTensor<Self>;
    /// `B(φ)ᵀ g` on a `height × width` coefficient grid.
    fn spline_sample_adjoint(
        grad: FloatTensor<Self>,
        phi: FloatTensor<Self>,
        height: usize,
        width: usize,
    ) -> FloatTensor<Self>;
    /// `Σ_c g_c ∂(B(φ) c)_c/∂φ`.
    fn spline_sample_position_grad(
        coeffs: FloatTensor<Self>,
        phi: FloatTensor<Self>,
        grad: FloatTensor<Self>,
    ) -> FloatTensor<Self>;
}

/// The interpolating prefilter `P` of SPEC §1 applied to every plane (or its adjoint `Pᵀ`
/// with `transpose`), exact, O(n) per line.
///
/// # Shapes
/// - `x`: `[N, C, H, W]`, output alike
pub fn prefilter(x: Tensor<4>, transpose: bool) -> Tensor<4> {
    Tensor::from_dispatch(Dispatch::spline_prefilter(x.into_dispatch(), transpose))
}

/// `T = B(φ) c`: the spline with coefficients `coeffs` at the clamped points `phi`.
///
/// # Shapes
/// - `coeffs`: `[N, C, H, W]`; `phi`: `[N, 2, H', W']`; output `[N, C, H', W']`
pub fn sample(coeffs: Tensor<4>, phi: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(Dispatch::spline_sample(
        coeffs.into_dispatch(),
        phi.into_dispatch(),
    ))
}

/// `B(φ)ᵀ g`, the adjoint of [`sample`] in the coefficients (not differentiable itself).
///
/// # Shapes
/// - `grad`: `[N, C, H', W']`; `phi`: `[N, 2, H', W']`; output `[N, C, height, width]`
pub fn sample_adjoint(grad: Tensor<4>, phi: Tensor<4>, height: usize, width: usize) -> Tensor<4> {
    Tensor::from_dispatch(Dispatch::spline_sample_adjoint(
        grad.into_dispatch(),
        phi.into_dispatch(),
        height,
        width,
    ))
}

/// `Σ_c g_c ∂T_c/∂φ`, the gradient of `⟨g, sample(coeffs, φ)⟩` w.r.t. `φ` (not
/// differentiable itself).
///
/// # Shapes
/// - `coeffs`: `[N, C, H, W]`; `phi`: `[N, 2, H', W']`; `grad`: `[N, C, H', W']`; output
///   `[N, 2, H', W']`
pub fn sample_position_grad(coeffs: Tensor<4>, phi: Tensor<4>, grad: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(Dispatch::spline_sample_position_grad(
        coeffs.into_dispatch(),
        phi.into_dispatch(),
        grad.into_dispatch(),
    ))
}

/// The shapes of an evaluation, checked.
#[cfg(feature = "flex")]
fn dims(coeffs: &[usize], phi: &[usize]) -> super::host::Dims {
    assert!(
        coeffs.len() == 4 && phi.len() == 4 && phi[1] == 2 && coeffs[0] == phi[0],
        "spline sample: coefficients {coeffs:?} and deformation {phi:?} do not fit [N, C, H, W] \
         and [N, 2, H', W']"
    );
    super::host::Dims {
        n: coeffs[0],
        c: coeffs[1],
        h: coeffs[2],
        w: coeffs[3],
        ho: phi[2],
        wo: phi[3],
    }
}

#[cfg(feature = "flex")]
pub(super) mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};

    use super::super::host::{self, Dims, SplineReal};
    use super::{SplineOps, dims};
    use crate::model::cpu::zeros;
    use crate::model::host_view::HostView;

    /// The tensor's values as contiguous host data.
    fn data(t: FlexTensor) -> TensorData {
        t.into_data()
    }

    fn shape(t: &TensorData) -> Vec<usize> {
        t.shape().to_vec()
    }

    /// Runs `f` with the element type of `dtype` (the model computes in float32 and checks
    /// gradients in float64).
    macro_rules! typed {
        ($dtype:expr, $f:ident ( $($arg:expr),* )) => {
            match $dtype {
                DType::F32 => $f::<f32>($($arg),*),
                DType::F64 => $f::<f64>($($arg),*),
                other => panic!("the spline kernels run in float32 or float64, not {other:?}"),
            }
        };
    }

    fn prefilter_typed<T: SplineReal + burn::tensor::Element>(
        mut x: TensorData,
        transpose: bool,
    ) -> TensorData {
        let s = shape(&x);
        let (h, w) = (s[s.len() - 2], s[s.len() - 1]);
        host::prefilter(
            x.as_mut_slice::<T>().expect("dtype checked"),
            h,
            w,
            transpose,
        );
        x
    }

    /// [`prefilter_typed`] of a buffer others share: into a new one.
    fn prefilter_shared<T: Kernel>(x: &HostView, transpose: bool) -> TensorData {
        let s = x.shape();
        let (h, w) = (s[s.len() - 2], s[s.len() - 1]);
        let source = x.values::<T>();
        let mut out = zeros(source.len());
        host::prefilter_into(source, &mut out, h, w, transpose);
        TensorData::new(out, s)
    }

    /// The element types the kernels take: read in place from flex buffers.
    trait Kernel: SplineReal + burn::tensor::Element + bytemuck::Pod {}
    impl Kernel for f32 {}
    impl Kernel for f64 {}

    fn sample_typed<T: Kernel>(coeffs: &Coefficients, phi: &HostView, d: Dims) -> TensorData {
        let len = d.n * d.c * d.ho * d.wo;
        let mut out = Vec::with_capacity(len);
        let spare = &mut out.spare_capacity_mut()[..len];
        match coeffs {
            Coefficients::Planar(c) => host::sample_uninit(c.values(), phi.values(), spare, d),
            Coefficients::ChannelsLast { tensor, stride } => {
                let start = tensor.layout().start_offset();
                let values = &tensor.storage::<T>()[start..];
                host::sample_from_table_uninit(values, *stride, phi.values(), spare, d);
            }
        }
        // SAFETY: the sampling kernels write every one of the `len` values.
        unsafe { out.set_len(len) };
        TensorData::new(out, [d.n, d.c, d.ho, d.wo])
    }

    fn adjoint_typed<T: Kernel>(grad: &HostView, phi: &HostView, d: Dims) -> TensorData {
        let len = d.n * d.c * d.h * d.w;
        let mut out = Vec::<T>::with_capacity(len);
        let spare = &mut out.spare_capacity_mut()[..len];
        host::sample_adjoint_uninit(grad.values(), phi.values(), spare, d);
        // SAFETY: the adjoint writes every one of the `len` values.
        unsafe { out.set_len(len) };
        TensorData::new(out, [d.n, d.c, d.h, d.w])
    }

    fn position_typed<T: Kernel>(
        coeffs: &Coefficients,
        phi: &HostView,
        grad: &HostView,
        d: Dims,
    ) -> TensorData {
        let mut out = zeros(d.n * 2 * d.ho * d.wo);
        let (phi, grad) = (phi.values(), grad.values());
        match coeffs {
            Coefficients::Planar(c) => {
                host::sample_position_grad(c.values(), phi, grad, &mut out, d);
            }
            Coefficients::ChannelsLast { tensor, stride } => {
                let start = tensor.layout().start_offset();
                let values = &tensor.storage::<T>()[start..];
                host::position_grad_from_table(values, *stride, phi, grad, &mut out, d);
            }
        }
        TensorData::new(out, [d.n, 2, d.ho, d.wo])
    }

    /// [`host::prefilter_channels_last`] of planar `x`, as a `[N, C, H, W]` tensor whose
    /// buffer is channels-last (a permuted view).
    fn prefilter_channels_last<T: Kernel>(x: &HostView) -> FlexTensor {
        let s = x.shape();
        let (n, c, h, w) = (s[0], s[1], s[2], s[3]);
        let len = n * c * h * w;
        let mut out = Vec::with_capacity(len);
        let spare = &mut out.spare_capacity_mut()[..len];
        host::prefilter_channels_last_uninit(x.values::<T>(), spare, (n, c, h, w));
        // SAFETY: the prefilter writes every one of the `len` values.
        unsafe { out.set_len(len) };
        FlexTensor::from_data(TensorData::new(out, [n, h, w, c])).permute(&[0, 3, 1, 2])
    }

    /// Coefficients as the kernels read them: in place when they lie planar or
    /// channels-last (a block of channels of a channels-last table included), else copied
    /// planar.
    enum Coefficients {
        Planar(HostView),
        ChannelsLast { tensor: FlexTensor, stride: usize },
    }

    impl Coefficients {
        fn new(t: FlexTensor) -> Self {
            match channels_last_stride(&t) {
                Some(stride) => Self::ChannelsLast { tensor: t, stride },
                None => Self::Planar(HostView::new(t)),
            }
        }

        fn shape(&self) -> Vec<usize> {
            match self {
                Self::Planar(v) => v.shape(),
                Self::ChannelsLast { tensor, .. } => tensor.layout().shape().to_vec(),
            }
        }

        fn dtype(&self) -> DType {
            match self {
                Self::Planar(v) => v.dtype(),
                Self::ChannelsLast { tensor, .. } => tensor.dtype(),
            }
        }
    }

    /// The pixel stride of a `[N, C, H, W]` tensor whose values lie channels-last in its
    /// buffer (strides `[H·W·s, 1, W·s, s]`, `s ≥ C`), with enough channels that the kernels
    /// read them so; `None` otherwise.
    pub(super) fn channels_last_stride(t: &FlexTensor) -> Option<usize> {
        let layout = t.layout();
        let (shape, strides) = (layout.shape(), layout.strides());
        if shape.num_dims() != 4 || !host::reads_channels_last(shape[1]) {
            return None;
        }
        let (n, c, h, w) = (shape[0], shape[1], shape[2], shape[3]);
        let s = usize::try_from(strides[3]).ok()?;
        let fits = strides[1] == 1
            && s >= c
            && strides[2] == (w * s) as isize
            && (n == 1 || strides[0] == (h * w * s) as isize);
        fits.then_some(s)
    }

    impl SplineOps for Flex {
        fn spline_prefilter(x: FlexTensor, transpose: bool) -> FlexTensor {
            let s = x.layout().shape().to_vec();
            if !transpose && s.len() == 4 && host::reads_channels_last(s[1]) {
                let x = HostView::new(x);
                return typed!(x.dtype(), prefilter_channels_last(&x));
            }
            if x.is_unique() {
                // In place: nobody else holds the buffer.
                let x = data(x);
                return FlexTensor::from_data(typed!(x.dtype(), prefilter_typed(x, transpose)));
            }
            let x = HostView::new(x);
            FlexTensor::from_data(typed!(x.dtype(), prefilter_shared(&x, transpose)))
        }

        fn spline_sample(coeffs: FlexTensor, phi: FlexTensor) -> FlexTensor {
            let (coeffs, phi) = (Coefficients::new(coeffs), HostView::new(phi));
            let d = dims(&coeffs.shape(), &phi.shape());
            FlexTensor::from_data(typed!(coeffs.dtype(), sample_typed(&coeffs, &phi, d)))
        }

        fn spline_sample_adjoint(
            grad: FlexTensor,
            phi: FlexTensor,
            height: usize,
            width: usize,
        ) -> FlexTensor {
            let (grad, phi) = (HostView::new(grad), HostView::new(phi));
            let g = grad.shape();
            let d = dims(&[g[0], g[1], height, width], &phi.shape());
            FlexTensor::from_data(typed!(grad.dtype(), adjoint_typed(&grad, &phi, d)))
        }

        fn spline_sample_position_grad(
            coeffs: FlexTensor,
            phi: FlexTensor,
            grad: FlexTensor,
        ) -> FlexTensor {
            let (coeffs, phi, grad) = (
                Coefficients::new(coeffs),
                HostView::new(phi),
                HostView::new(grad),
            );
            let d = dims(&coeffs.shape(), &phi.shape());
            FlexTensor::from_data(typed!(
                coeffs.dtype(),
                position_typed(&coeffs, &phi, &grad, d)
            ))
        }
    }
}

#[cfg(all(test, feature = "flex"))]
mod tests {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::backend::ops::FloatTensorOps;
    use burn::tensor::TensorData;

    use super::SplineOps;
    use super::flex::channels_last_stride;

    fn tensor(c: usize) -> FlexTensor {
        let values: Vec<f32> = (0..c * 30).map(|i| (i as f32 * 0.37).sin()).collect();
        FlexTensor::from_data(TensorData::new(values, [1, c, 5, 6]))
    }

    /// The forward prefilter of many channels leaves them channels-last; joined with an RGB
    /// block along the channels of that layout the whole frame stays so, and the kernels
    /// read its many-channel blocks in place (few channels are copied planar).
    #[test]
    fn coefficients_stay_channels_last_through_a_join() {
        let deep = Flex::spline_prefilter(tensor(64), false);
        assert_eq!(channels_last_stride(&deep), Some(64));
        assert_eq!(
            channels_last_stride(&Flex::spline_prefilter(tensor(3), false)),
            None
        );
        assert_eq!(
            channels_last_stride(&Flex::spline_prefilter(tensor(64), true)),
            None
        );
        let last = |t: FlexTensor| t.permute(&[0, 2, 3, 1]);
        let joined = Flex::float_cat(vec![last(tensor(3)), last(deep)], 3).permute(&[0, 3, 1, 2]);
        assert_eq!(channels_last_stride(&joined), Some(67));
        assert_eq!(channels_last_stride(&joined.narrow(1, 3, 64)), Some(67));
        assert_eq!(channels_last_stride(&joined.narrow(1, 0, 3)), None);
    }
}

mod autodiff {
    use burn::backend::Autodiff;
    use burn::backend::TensorMetadata;
    use burn::backend::autodiff::checkpoint::base::Checkpointer;
    use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
    use burn::backend::autodiff::grads::Gradients;
    use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
    use burn::backend::tensor::FloatTensor;

    use super::SplineOps;

    #[derive(Debug)]
    struct Prefilter;

    impl<B: SplineOps> Backward<B, 1> for Prefilter {
        /// Whether the forward applied `Pᵀ`.
        type State = bool;

        fn backward(self, ops: Ops<bool, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
            let [parent] = ops.parents;
            let grad = grads.consume::<B>(&ops.node);
            if let Some(node) = parent {
                grads.register::<B>(node.id, B::spline_prefilter(grad, !ops.state));
            }
        }
    }

    #[derive(Debug)]
    struct Sample;

    impl<B: SplineOps> Backward<B, 2> for Sample {
        /// The coefficients (kept only when `φ` needs its gradient), `φ`, and the
        /// coefficient grid's `H × W`.
        type State = (Option<FloatTensor<B>>, FloatTensor<B>, [usize; 2]);

        fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
            let [coeffs_node, phi_node] = ops.parents;
            let (coeffs, phi, [h, w]) = ops.state;
            let grad = grads.consume::<B>(&ops.node);
            if let Some(node) = phi_node {
                let coeffs = coeffs.expect("kept when φ is tracked");
                let g = B::spline_sample_position_grad(coeffs, phi.clone(), grad.clone());
                grads.register::<B>(node.id, g);
            }
            if let Some(node) = coeffs_node {
                grads.register::<B>(node.id, B::spline_sample_adjoint(grad, phi, h, w));
            }
        }
    }

    /// The backward passes' own kernels are not differentiated again (first-order autodiff
    /// only): on untracked inputs they run, on tracked ones they refuse.
    #[derive(Debug)]
    struct NotDifferentiable;

    impl<B: SplineOps, const N: usize> Backward<B, N> for NotDifferentiable {
        type State = ();

        fn backward(self, _: Ops<(), N>, _: &mut Gradients, _: &mut Checkpointer) {
            unreachable!("prepared only for untracked inputs")
        }
    }

    fn untracked<B: SplineOps, C: CheckpointStrategy, const N: usize>(
        what: &str,
        prep: OpsKind<NotDifferentiable, B, (), C, N>,
        output: impl FnOnce() -> FloatTensor<B>,
    ) -> FloatTensor<Autodiff<B, C>> {
        match prep {
            OpsKind::UnTracked(prep) => prep.finish(output()),
            OpsKind::Tracked(_) => panic!("{what} is not differentiable (a backward kernel)"),
        }
    }

    impl<B: SplineOps, C: CheckpointStrategy> SplineOps for Autodiff<B, C> {
        fn spline_prefilter(x: FloatTensor<Self>, transpose: bool) -> FloatTensor<Self> {
            let (x, node) = x.into_parts();
            match Prefilter.prepare::<C>([node]).compute_bound().stateful() {
                OpsKind::Tracked(prep) => prep.finish(transpose, B::spline_prefilter(x, transpose)),
                OpsKind::UnTracked(prep) => prep.finish(B::spline_prefilter(x, transpose)),
            }
        }

        fn spline_sample(coeffs: FloatTensor<Self>, phi: FloatTensor<Self>) -> FloatTensor<Self> {
            let phi_tracked = phi.is_tracked();
            let (coeffs, coeffs_node) = coeffs.into_parts();
            let (phi, phi_node) = phi.into_parts();
            let shape = coeffs.shape();
            let hw = [shape[2], shape[3]];
            match Sample
                .prepare::<C>([coeffs_node, phi_node])
                .compute_bound()
                .stateful()
            {
                OpsKind::Tracked(prep) => {
                    let kept = phi_tracked.then(|| coeffs.clone());
                    let out = B::spline_sample(coeffs, phi.clone());
                    prep.finish((kept, phi, hw), out)
                }
                OpsKind::UnTracked(prep) => prep.finish(B::spline_sample(coeffs, phi)),
            }
        }

        fn spline_sample_adjoint(
            grad: FloatTensor<Self>,
            phi: FloatTensor<Self>,
            height: usize,
            width: usize,
        ) -> FloatTensor<Self> {
            let (grad, a) = grad.into_parts();
            let (phi, b) = phi.into_parts();
            let prep = NotDifferentiable
                .prepare::<C>([a, b])
                .compute_bound()
                .stateful();
            untracked("the spline's adjoint", prep, || {
                B::spline_sample_adjoint(grad, phi, height, width)
            })
        }

        fn spline_sample_position_grad(
            coeffs: FloatTensor<Self>,
            phi: FloatTensor<Self>,
            grad: FloatTensor<Self>,
        ) -> FloatTensor<Self> {
            let (coeffs, a) = coeffs.into_parts();
            let (phi, b) = phi.into_parts();
            let (grad, c) = grad.into_parts();
            let prep = NotDifferentiable
                .prepare::<C>([a, b, c])
                .compute_bound()
                .stateful();
            untracked("the spline's position gradient", prep, || {
                B::spline_sample_position_grad(coeffs, phi, grad)
            })
        }
    }
}
