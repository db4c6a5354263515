//! The elementwise updates of SPEC §6's steps as custom Burn ops (Burn 0.22's
//! `#[backend_extension]`): the inertial extrapolation `x + β(x − x_prev)` (`f̃` and `φ̃`) and
//! a feature trial's gradient step `x̃ − ∇Q/L`, one `L` per channel block.
//!
//! Composed, the extrapolation is three elementwise ops (difference, scale, sum) and the
//! gradient step two, each a pass over the frame into a fresh output on one core (flex runs
//! its elementwise ops single-threaded). At 256² a deep frame is 17.6 MB: timed in a deep
//! morph's feature steps, the extrapolation took 7 % of their time and the trials' gradient
//! steps 5 %. Fused, each is one pass split over the cores, every value the composed chain's
//! operations in its order: the same bits.
//!
//! - flex: the host kernel below.
//! - ndarray, wgpu: the trait's default bodies, the composed ops.
//! - autodiff: not differentiable (both are constants of a step: their inputs are the
//!   state and a gradient already taken).
//!
//! The custom ops and the backends they have kernels for are listed in one place,
//! `docs/architecture.md` ("Custom ops"): they are the only numerical code that names backends.

#![allow(deprecated)] // `NdArray` is deprecated upstream in favour of flex; it stays served.

use std::ops::Range;

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, TensorMetadata, backend_extension};
use burn::tensor::{Scalar, Shape, Tensor, TensorData};

/// The updates' primitives.
#[backend_extension(
    Flex: cfg(feature = "flex"),
    NdArray: cfg(feature = "ndarray"),
    Cube: cfg(feature = "wgpu"),
    Autodiff
)]
pub trait UpdateOps: Backend {
    /// `x + (x − previous)·β`; shapes as in [`extrapolate`].
    fn extrapolate(
        x: FloatTensor<Self>,
        previous: FloatTensor<Self>,
        beta: f64,
    ) -> FloatTensor<Self> {
        let step =
            Self::float_mul_scalar(Self::float_sub(x.clone(), previous), Scalar::Float(beta));
        Self::float_add(x, step)
    }
    /// `x_nc − g_nc·s_nc` for each item `n` and channel `c`: `x`, `g` and the output
    /// `[N, C, H, W]`, `s` `[N·C]` in their dtype.
    fn descend(
        x: FloatTensor<Self>,
        g: FloatTensor<Self>,
        s: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let shape = x.shape();
        let s = Self::float_reshape(s, Shape::new([shape[0], shape[1], 1, 1]));
        Self::float_sub(x, Self::float_mul(g, s))
    }
}

#[cfg(feature = "ndarray")]
impl UpdateOps for burn::backend::NdArray {}

#[cfg(feature = "wgpu")]
impl UpdateOps for burn::backend::Cube {}

/// The inertial extrapolation `x + β(x − x_prev)` of SPEC §6 (`f̃`, `φ̃`): as the composed
/// `x + (x − x_prev)·β` with `β` rounded to the tensors' precision, bit for bit.
///
/// # Shapes
/// - `x`, `previous`, output: `[N, C, H, W]`
///
/// # Panics
///
/// If the shapes differ.
pub fn extrapolate(x: Tensor<4>, previous: Tensor<4>, beta: f64) -> Tensor<4> {
    assert_eq!(x.dims(), previous.dims(), "extrapolation: shapes differ");
    Tensor::from_dispatch(Dispatch::extrapolate(
        x.detach().into_dispatch(),
        previous.detach().into_dispatch(),
        beta,
    ))
}

/// The gradient step `x − g / L` of each item and channel block (SPEC §6 step 3's trial,
/// every block of a frame in one pass): as the composed `x − g·(1/L)` of each block with
/// `1/L` rounded to the tensors' precision, bit for bit. `L = ∞` leaves a block at `x`.
///
/// # Shapes
/// - `x`, `g`, output: `[N, C, H, W]`; `blocks`: ranges of channels covering `0..C`;
///   `lipschitz`: `N · blocks.len()` values, item-major
///
/// # Panics
///
/// If the shapes differ, the blocks do not cover the channels, or `lipschitz` does not hold
/// one value per item and block.
pub fn descend(
    x: Tensor<4>,
    g: Tensor<4>,
    lipschitz: &[f64],
    blocks: &[Range<usize>],
) -> Tensor<4> {
    assert_eq!(x.dims(), g.dims(), "gradient step: shapes differ");
    let [n, c, _, _] = x.dims();
    assert!(
        blocks.first().is_some_and(|b| b.start == 0)
            && blocks.last().is_some_and(|b| b.end == c)
            && blocks.windows(2).all(|w| w[0].end == w[1].start),
        "gradient step: blocks {blocks:?} do not cover {c} channels"
    );
    assert_eq!(
        lipschitz.len(),
        n * blocks.len(),
        "gradient step: one L per item and block"
    );
    let inverse: Vec<f64> = lipschitz
        .chunks(blocks.len())
        .flat_map(|per_block| {
            per_block
                .iter()
                .zip(blocks)
                .flat_map(|(l, block)| std::iter::repeat_n(1.0 / l, block.len()))
        })
        .collect();
    let s = Tensor::<1>::from_data(TensorData::new(inverse, [n * c]), (&x.device(), x.dtype()));
    Tensor::from_dispatch(Dispatch::descend(
        x.detach().into_dispatch(),
        g.detach().into_dispatch(),
        s.into_dispatch(),
    ))
}

#[cfg(feature = "flex")]
mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};

    use super::UpdateOps;
    use crate::model::cpu::{Real, combine};
    use crate::model::host_view::HostView;

    trait Kernel: Real + burn::tensor::Element + bytemuck::Pod {}
    impl Kernel for f32 {}
    impl Kernel for f64 {}

    fn extrapolate_typed<T: Kernel>(x: &HostView, previous: &HostView, beta: f64) -> TensorData {
        let out = combine(
            x.values::<T>(),
            previous.values::<T>(),
            &[T::from_f64(beta)],
            |x, p, beta| x + (x - p) * beta,
        );
        TensorData::new(out, x.shape())
    }

    fn descend_typed<T: Kernel>(x: &HostView, g: &HostView, s: &HostView) -> TensorData {
        let out = combine(
            x.values::<T>(),
            g.values::<T>(),
            s.values::<T>(),
            |x, g, s| x - g * s,
        );
        TensorData::new(out, x.shape())
    }

    macro_rules! typed {
        ($dtype:expr, $f:ident($($arg:expr),*)) => {
            match $dtype {
                DType::F32 => $f::<f32>($($arg),*),
                DType::F64 => $f::<f64>($($arg),*),
                other => panic!("the updates run in float32 or float64, not {other:?}"),
            }
        };
    }

    impl UpdateOps for Flex {
        fn extrapolate(x: FlexTensor, previous: FlexTensor, beta: f64) -> FlexTensor {
            let (x, previous) = HostView::pair(x, previous, "extrapolation");
            FlexTensor::from_data(typed!(x.dtype(), extrapolate_typed(&x, &previous, beta)))
        }

        fn descend(x: FlexTensor, g: FlexTensor, s: FlexTensor) -> FlexTensor {
            let (x, g) = HostView::pair(x, g, "gradient step");
            let s = HostView::new(s);
            assert!(
                s.dtype() == x.dtype() && s.shape() == [x.shape()[0] * x.shape()[1]],
                "gradient step: factors {:?} {:?} for {:?} {:?}",
                s.shape(),
                s.dtype(),
                x.shape(),
                x.dtype()
            );
            FlexTensor::from_data(typed!(x.dtype(), descend_typed(&x, &g, &s)))
        }
    }
}

mod autodiff {
    use burn::backend::Autodiff;
    use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
    use burn::backend::tensor::FloatTensor;

    use super::UpdateOps;

    /// An update is a constant of its step: no gradient flows through it (its inputs are
    /// detached by the public functions).
    impl<B: UpdateOps, C: CheckpointStrategy> UpdateOps for Autodiff<B, C> {
        fn extrapolate(
            x: FloatTensor<Self>,
            previous: FloatTensor<Self>,
            beta: f64,
        ) -> FloatTensor<Self> {
            let (x, _) = x.into_parts();
            let (previous, _) = previous.into_parts();
            FloatTensor::<Self>::new(B::extrapolate(x, previous, beta))
        }

        fn descend(
            x: FloatTensor<Self>,
            g: FloatTensor<Self>,
            s: FloatTensor<Self>,
        ) -> FloatTensor<Self> {
            let (x, _) = x.into_parts();
            let (g, _) = g.into_parts();
            let (s, _) = s.into_parts();
            FloatTensor::<Self>::new(B::descend(x, g, s))
        }
    }
}
