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
use burn::tensor::{Scalar, Shape, Slice, Tensor, TensorData};

use crate::model::grid::{Accumulation, Grid};

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
    /// [`descend`](UpdateOps::descend), and the float64 `Σ (r − out)²` of each item's
    /// channel blocks `0..split` and `split..C` (one block where `split = C`), `[N · B]`;
    /// shapes as in [`descend_distance2`].
    fn descend_distance2(
        x: FloatTensor<Self>,
        g: FloatTensor<Self>,
        s: FloatTensor<Self>,
        r: FloatTensor<Self>,
        split: usize,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let out = Self::descend(x, g, s);
        let sums = composed_block_distances::<Self>(r, out.clone(), split);
        (out, sums)
    }
    /// [`extrapolate`](UpdateOps::extrapolate), and the sums of
    /// [`descend_distance2`](UpdateOps::descend_distance2).
    fn extrapolate_distance2(
        x: FloatTensor<Self>,
        previous: FloatTensor<Self>,
        beta: f64,
        r: FloatTensor<Self>,
        split: usize,
    ) -> (FloatTensor<Self>, FloatTensor<Self>) {
        let out = Self::extrapolate(x, previous, beta);
        let sums = composed_block_distances::<Self>(r, out.clone(), split);
        (out, sums)
    }
}

/// The channel ranges of the blocks `0..split`, `split..c` (the second only if not empty).
fn split_blocks(c: usize, split: usize) -> Vec<Range<usize>> {
    assert!(
        (1..=c).contains(&split),
        "update: block split {split} of {c} channels"
    );
    [0..split, split..c]
        .into_iter()
        .filter(|block| !block.is_empty())
        .collect()
}

/// The sums of [`UpdateOps::descend_distance2`] of the backends without a kernel: each item's
/// block through [`crate::model::decision::composed_distance2`] on its own, the values
/// [`crate::model::grid::Grid::decision_distance2_blocks`] gives there, bit for bit.
fn composed_block_distances<B: Backend>(
    r: FloatTensor<B>,
    out: FloatTensor<B>,
    split: usize,
) -> FloatTensor<B> {
    let shape = out.shape();
    let [n, c, h, w] = [shape[0], shape[1], shape[2], shape[3]];
    let sums = (0..n)
        .flat_map(|i| {
            split_blocks(c, split)
                .into_iter()
                .map(move |block| (i, block))
        })
        .map(|(i, block)| {
            let part = |t: &FloatTensor<B>| {
                B::float_slice(
                    t.clone(),
                    &[
                        Slice::from(i..i + 1),
                        Slice::from(block.clone()),
                        Slice::from(0..h),
                        Slice::from(0..w),
                    ],
                )
            };
            crate::model::decision::composed_distance2::<B>(part(&r), part(&out))
        })
        .collect();
    B::float_cat(sums, 0)
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
    let s = step_factors(&x, g.dims(), lipschitz, blocks);
    Tensor::from_dispatch(Dispatch::descend(
        x.detach().into_dispatch(),
        g.detach().into_dispatch(),
        s.into_dispatch(),
    ))
}

/// The factors `1/L` of each item's channels, `[N · C]`, for [`descend`]'s `x` and the shape
/// of `g` (checked as [`descend`] says).
fn step_factors(
    x: &Tensor<4>,
    g: [usize; 4],
    lipschitz: &[f64],
    blocks: &[Range<usize>],
) -> Tensor<1> {
    assert_eq!(x.dims(), g, "gradient step: shapes differ");
    let [n, c, _, _] = g;
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
    Tensor::<1>::from_data(TensorData::new(inverse, [n * c]), (&x.device(), x.dtype()))
}

/// [`descend`] and `grid.`[`decision_distance2_blocks`](Grid::decision_distance2_blocks)`(r,
/// x_new, blocks)`, `[N · B]` item-major. Where the grid's decision sums are float64 and the
/// blocks are `0..s`, `s..C` (or `0..C`), one pass (on flex each chunk of the new frame is
/// folded while it is in cache), the same bits; otherwise the two calls.
///
/// # Shapes
/// - `x`, `g`, `r`, the new frame: `[N, C, H, W]`; `lipschitz` as in [`descend`]
///
/// # Panics
///
/// As [`descend`]; if `r`'s shape differs.
pub fn descend_distance2(
    grid: &Grid,
    x: Tensor<4>,
    g: Tensor<4>,
    lipschitz: &[f64],
    blocks: &[Range<usize>],
    r: Tensor<4>,
) -> (Tensor<4>, Tensor<1>) {
    assert_eq!(x.dims(), r.dims(), "gradient step: shapes differ");
    let Some(split) = fused_split(grid, blocks) else {
        let stepped = descend(x, g, lipschitz, blocks);
        let sums = grid.decision_distance2_blocks(r, stepped.clone(), blocks);
        return (stepped, sums);
    };
    let s = step_factors(&x, g.dims(), lipschitz, blocks);
    let (out, sums) = Dispatch::descend_distance2(
        x.detach().into_dispatch(),
        g.detach().into_dispatch(),
        s.into_dispatch(),
        r.detach().into_dispatch(),
        split,
    );
    (Tensor::from_dispatch(out), Tensor::from_dispatch(sums))
}

/// [`extrapolate`] and the sums of [`descend_distance2`]: bit for bit [`extrapolate`] then
/// `grid.`[`decision_distance2_blocks`](Grid::decision_distance2_blocks)`(r, x̃, blocks)`, in
/// one pass where [`descend_distance2`] is one.
///
/// # Shapes
/// - `x`, `previous`, `r`, `x̃`: `[N, C, H, W]`
///
/// # Panics
///
/// If the shapes differ, or the blocks do not end at `C`.
pub fn extrapolate_distance2(
    grid: &Grid,
    x: Tensor<4>,
    previous: Tensor<4>,
    beta: f64,
    blocks: &[Range<usize>],
    r: Tensor<4>,
) -> (Tensor<4>, Tensor<1>) {
    assert!(
        x.dims() == previous.dims() && x.dims() == r.dims(),
        "extrapolation: shapes differ"
    );
    assert_eq!(
        blocks.last().map(|b| b.end),
        Some(x.dims()[1]),
        "extrapolation: blocks {blocks:?}"
    );
    let Some(split) = fused_split(grid, blocks) else {
        let extrapolated = extrapolate(x, previous, beta);
        let sums = grid.decision_distance2_blocks(r, extrapolated.clone(), blocks);
        return (extrapolated, sums);
    };
    let (out, sums) = Dispatch::extrapolate_distance2(
        x.detach().into_dispatch(),
        previous.detach().into_dispatch(),
        beta,
        r.detach().into_dispatch(),
        split,
    );
    (Tensor::from_dispatch(out), Tensor::from_dispatch(sums))
}

/// The channel where the fused sums' second block starts (`C` for one block), where the
/// fused updates apply: float64 decision sums (the fused kernels fold in float64, as
/// [`Grid::decision_distance2_blocks`] does only then) and blocks `0..s, s..C` or `0..C`.
fn fused_split(grid: &Grid, blocks: &[Range<usize>]) -> Option<usize> {
    let contiguous = blocks.windows(2).all(|w| w[0].end == w[1].start);
    (grid.accumulation() == Accumulation::Float64
        && matches!(blocks.len(), 1 | 2)
        && blocks[0].start == 0
        && contiguous)
        .then(|| blocks[0].end)
}

#[cfg(feature = "flex")]
mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};

    use super::UpdateOps;
    use crate::model::cpu::{Real, combine, combine_distance2};
    use crate::model::decision::flex::Value;
    use crate::model::host_view::HostView;

    trait Kernel: Real + Value + Send + burn::tensor::Element + bytemuck::Pod {}
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

    /// The lengths of the fused sums' regions: each item's blocks `0..split`, `split..C`.
    fn regions(shape: &[usize], split: usize) -> Vec<usize> {
        let [n, c, h, w] = [shape[0], shape[1], shape[2], shape[3]];
        let blocks = super::split_blocks(c, split);
        (0..n)
            .flat_map(|_| blocks.iter().map(|block| block.len() * h * w))
            .collect()
    }

    /// The new frame and its sums as flex tensors.
    fn with_sums(
        out: Vec<impl Kernel>,
        sums: Vec<f64>,
        shape: Vec<usize>,
    ) -> (FlexTensor, FlexTensor) {
        let count = sums.len();
        (
            FlexTensor::from_data(TensorData::new(out, shape)),
            FlexTensor::from_data(TensorData::new(sums, [count])),
        )
    }

    fn descend_distance2_typed<T: Kernel>(
        x: &HostView,
        g: &HostView,
        s: &HostView,
        r: &HostView,
        split: usize,
    ) -> (FlexTensor, FlexTensor) {
        let (out, sums) = combine_distance2(
            x.values::<T>(),
            g.values::<T>(),
            s.values::<T>(),
            r.values::<T>(),
            &regions(&x.shape(), split),
            |x, g, s| x - g * s,
        );
        with_sums(out, sums, x.shape())
    }

    fn extrapolate_distance2_typed<T: Kernel>(
        x: &HostView,
        previous: &HostView,
        beta: f64,
        r: &HostView,
        split: usize,
    ) -> (FlexTensor, FlexTensor) {
        let (out, sums) = combine_distance2(
            x.values::<T>(),
            previous.values::<T>(),
            &[T::from_f64(beta)],
            r.values::<T>(),
            &regions(&x.shape(), split),
            |x, p, beta| x + (x - p) * beta,
        );
        with_sums(out, sums, x.shape())
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

        fn descend_distance2(
            x: FlexTensor,
            g: FlexTensor,
            s: FlexTensor,
            r: FlexTensor,
            split: usize,
        ) -> (FlexTensor, FlexTensor) {
            let (x, g) = HostView::pair(x, g, "gradient step");
            let (s, r) = (HostView::new(s), HostView::new(r));
            assert!(
                s.dtype() == x.dtype() && s.shape() == [x.shape()[0] * x.shape()[1]],
                "gradient step: factors {:?} {:?} for {:?} {:?}",
                s.shape(),
                s.dtype(),
                x.shape(),
                x.dtype()
            );
            assert!(
                r.shape() == x.shape() && r.dtype() == x.dtype(),
                "gradient step: distances to {:?} {:?}",
                r.shape(),
                r.dtype()
            );
            typed!(x.dtype(), descend_distance2_typed(&x, &g, &s, &r, split))
        }

        fn extrapolate_distance2(
            x: FlexTensor,
            previous: FlexTensor,
            beta: f64,
            r: FlexTensor,
            split: usize,
        ) -> (FlexTensor, FlexTensor) {
            let (x, previous) = HostView::pair(x, previous, "extrapolation");
            let r = HostView::new(r);
            assert!(
                r.shape() == x.shape() && r.dtype() == x.dtype(),
                "extrapolation: distances to {:?} {:?}",
                r.shape(),
                r.dtype()
            );
            typed!(
                x.dtype(),
                extrapolate_distance2_typed(&x, &previous, beta, &r, split)
            )
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

        fn descend_distance2(
            x: FloatTensor<Self>,
            g: FloatTensor<Self>,
            s: FloatTensor<Self>,
            r: FloatTensor<Self>,
            split: usize,
        ) -> (FloatTensor<Self>, FloatTensor<Self>) {
            let (x, _) = x.into_parts();
            let (g, _) = g.into_parts();
            let (s, _) = s.into_parts();
            let (r, _) = r.into_parts();
            constants::<B, C>(B::descend_distance2(x, g, s, r, split))
        }

        fn extrapolate_distance2(
            x: FloatTensor<Self>,
            previous: FloatTensor<Self>,
            beta: f64,
            r: FloatTensor<Self>,
            split: usize,
        ) -> (FloatTensor<Self>, FloatTensor<Self>) {
            let (x, _) = x.into_parts();
            let (previous, _) = previous.into_parts();
            let (r, _) = r.into_parts();
            constants::<B, C>(B::extrapolate_distance2(x, previous, beta, r, split))
        }
    }

    /// A fused update's frame and its sums.
    type Fused<B> = (FloatTensor<B>, FloatTensor<B>);

    /// A fused update's frame and sums as untracked tensors.
    fn constants<B: UpdateOps, C: CheckpointStrategy>(
        (out, sums): Fused<B>,
    ) -> Fused<Autodiff<B, C>> {
        (
            FloatTensor::<Autodiff<B, C>>::new(out),
            FloatTensor::<Autodiff<B, C>>::new(sums),
        )
    }
}
