//! The separable operator `x ↦ R · x · Cᵀ` as a custom Burn op (Burn 0.22's
//! `#[backend_extension]`), so that flex applies only the nonzero band of `R` and `C`.
//!
//! - flex: the banded host kernel of [`super::host`], `taps` multiply-adds per value.
//! - ndarray, wgpu: the trait's default body, two dense matmuls (a GPU runs them at full
//!   speed; ndarray is the deprecated reference backend).
//! - autodiff: the backward is the adjoint `Rᵀ · g · C`, the same op on the transposed
//!   matrices. The matrices are constants of the model and never take a gradient.
//!
//! The custom ops and the backends they have kernels for are listed in one place,
//! `docs/architecture.md` ("Custom ops"): they are the only numerical code that names backends.

#![allow(deprecated)] // `NdArray` is deprecated upstream in favour of flex; it stays served.

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::Tensor;

/// The separable operator's primitive.
#[backend_extension(
    Flex: cfg(feature = "flex"),
    NdArray: cfg(feature = "ndarray"),
    Cube: cfg(feature = "wgpu"),
    Autodiff
)]
pub trait SeparableOps: Backend {
    /// `rows · x · cols_t` on every plane; shapes as in [`apply`].
    fn separable_apply(
        x: FloatTensor<Self>,
        rows: FloatTensor<Self>,
        cols_t: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        Self::float_matmul(Self::float_matmul(rows, x), cols_t)
    }
}

#[cfg(feature = "ndarray")]
impl SeparableOps for burn::backend::NdArray {}

#[cfg(feature = "wgpu")]
impl SeparableOps for burn::backend::Cube {}

/// `R · x · Cᵀ` of every plane, `R = rows`, `Cᵀ = cols_t`.
///
/// # Shapes
/// - `x`: `[N, C, H, W]`; `rows`: `[1, 1, H', H]`; `cols_t`: `[1, 1, W, W']`
/// - output: `[N, C, H', W']`
pub fn apply(x: Tensor<4>, rows: Tensor<4>, cols_t: Tensor<4>) -> Tensor<4> {
    Tensor::from_dispatch(Dispatch::separable_apply(
        x.into_dispatch(),
        rows.into_dispatch(),
        cols_t.into_dispatch(),
    ))
}

#[cfg(feature = "flex")]
mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};

    use super::super::host::{self, Band};
    use super::SeparableOps;
    use crate::model::cpu::Real;
    use crate::model::host_view::HostView;

    fn apply_typed<T: Real + burn::tensor::Element + bytemuck::Pod>(
        x: HostView,
        rows: HostView,
        cols_t: HostView,
    ) -> TensorData {
        let (s, r, c) = (x.shape(), rows.shape(), cols_t.shape());
        assert!(
            s.len() == 4 && r.len() == 4 && c.len() == 4 && r[3] == s[2] && c[2] == s[3],
            "separable: operators {r:?} and {c:?} do not fit the maps {s:?}"
        );
        let (ho, h, w, wo) = (r[2], r[3], c[2], c[3]);
        // Read in place: the operators are the model's constants, shared buffers that
        // `into_data` copied on every call.
        let (r, c) = (rows.values::<T>(), cols_t.values::<T>());
        let rows = Band::from_row_major(ho, h, r);
        // `Cᵀ` is stored: `C` column-major.
        let cols = Band::from_column_major(wo, w, c);
        let out = host::apply(x.values::<T>(), &rows, &cols);
        TensorData::new(out, [s[0], s[1], ho, wo])
    }

    impl SeparableOps for Flex {
        fn separable_apply(x: FlexTensor, rows: FlexTensor, cols_t: FlexTensor) -> FlexTensor {
            let (x, rows, cols_t) = (HostView::new(x), HostView::new(rows), HostView::new(cols_t));
            let out = match x.dtype() {
                DType::F32 => apply_typed::<f32>(x, rows, cols_t),
                DType::F64 => apply_typed::<f64>(x, rows, cols_t),
                other => panic!("the separable kernel runs in float32 or float64, not {other:?}"),
            };
            FlexTensor::from_data(out)
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

    use super::SeparableOps;

    #[derive(Debug)]
    struct Apply;

    impl<B: SeparableOps> Backward<B, 1> for Apply {
        /// `R` and `Cᵀ`.
        type State = (FloatTensor<B>, FloatTensor<B>);

        fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
            let [parent] = ops.parents;
            let (rows, cols_t) = ops.state;
            let grad = grads.consume::<B>(&ops.node);
            if let Some(node) = parent {
                // (R · g · Cᵀ)ᵀ-adjoint: Rᵀ · g · C.
                let adjoint =
                    B::separable_apply(grad, B::float_transpose(rows), B::float_transpose(cols_t));
                grads.register::<B>(node.id, adjoint);
            }
        }
    }

    impl<B: SeparableOps, C: CheckpointStrategy> SeparableOps for Autodiff<B, C> {
        fn separable_apply(
            x: FloatTensor<Self>,
            rows: FloatTensor<Self>,
            cols_t: FloatTensor<Self>,
        ) -> FloatTensor<Self> {
            assert!(
                !rows.is_tracked() && !cols_t.is_tracked(),
                "a separable operator's matrices are constants of the model"
            );
            let (x, node) = x.into_parts();
            let (rows, _) = rows.into_parts();
            let (cols_t, _) = cols_t.into_parts();
            match Apply.prepare::<C>([node]).compute_bound().stateful() {
                OpsKind::Tracked(prep) => {
                    let out = B::separable_apply(x, rows.clone(), cols_t.clone());
                    prep.finish((rows, cols_t), out)
                }
                OpsKind::UnTracked(prep) => prep.finish(B::separable_apply(x, rows, cols_t)),
            }
        }
    }
}
