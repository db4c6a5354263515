//! The pixel grid a level of the model lives on.

use std::ops::Range;
use std::sync::{Arc, OnceLock};

use burn::tensor::{Bool, DType, Device, Tensor, TensorData};

use crate::backend::{Capabilities, Gather};
use crate::error::{Error, Result};
use crate::model::decision;
use crate::model::stencil::Matrix;

/// Largest side a working size may have (a 16384² deep morph would need terabytes); saved
/// fields with larger sides are refused as malformed.
pub const MAX_SIDE: usize = 8192;

/// An `H × W` pixel grid (SPEC §0: `H` rows, `W` columns, both at least 4) on a device, in
/// one precision. Every tensor the library creates for the grid gets this device and dtype,
/// so the same code runs in float32 on any backend and in float64 for gradient checks.
#[derive(Clone, Debug)]
pub struct Grid {
    height: usize,
    width: usize,
    device: Device,
    dtype: DType,
    capabilities: Capabilities,
    /// Made on first use and shared by the grid's clones: built from host values per call,
    /// `Id` and the boundary mask cost a prox as much as its arithmetic (a host loop in
    /// float64 and an upload of `2·H·W` values each).
    constants: Arc<Constants>,
}

/// The grid's constant tensors, on its device and in its dtype.
#[derive(Default)]
struct Constants {
    /// `Id`, `[1, 2, H, W]`.
    identity: OnceLock<Tensor<4>>,
    /// 1 on the first and last row and column, 0 inside, `[1, 1, H, W]`.
    boundary: OnceLock<Tensor<4>>,
    /// Where [`Constants::boundary`] is 1, in both components: `[1, 2, H, W]`.
    on_boundary: OnceLock<Tensor<4, Bool>>,
}

impl std::fmt::Debug for Constants {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // The values follow from the grid's size; printing them would print images.
        f.write_str("Constants")
    }
}

/// How [`Grid::decision_sum`] adds up the values whose sums decide a backtracking test
/// (SPEC §6, "Floating point").
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Accumulation {
    /// float32 summands cast to float64 and added in float64: the backend computes in
    /// float64 (flex, ndarray). The tests need no slack.
    Float64,
    /// Everything in float32 (Burn's tree reductions, i.e. pairwise partial sums): the
    /// backend has no float64 (wgpu). The tests allow a relative slack.
    Float32,
}

impl Grid {
    /// A grid of `height × width` pixels.
    ///
    /// # Errors
    ///
    /// If either side is below 4 (the mirror boundary and the cubic stencil need 4 samples).
    pub fn new(height: usize, width: usize, device: &Device, dtype: DType) -> Result<Self> {
        for (name, n) in [("height", height), ("width", width)] {
            if n < 4 {
                return Err(Error::invalid(name, n, "at least 4 pixels"));
            }
        }
        Ok(Self {
            height,
            width,
            device: device.clone(),
            dtype,
            capabilities: Capabilities::of(device),
            constants: Arc::default(),
        })
    }

    /// How decision sums are accumulated on this grid's backend.
    pub fn accumulation(&self) -> Accumulation {
        if self.dtype == DType::F64 || self.capabilities.float64 {
            Accumulation::Float64
        } else {
            Accumulation::Float32
        }
    }

    /// [`decision_sum`](Self::decision_sum) of each item of a batch: `[N]`.
    ///
    /// # Shapes
    /// - `t`: `[N, …, L]` (rank ≥ 2)
    pub fn decision_sum_each<const D: usize>(&self, t: Tensor<D>) -> Tensor<1> {
        let dims = t.dims();
        let n = dims[0];
        if n == 1 {
            // One item is [`decision_sum`](Self::decision_sum) itself: a step of one `k`
            // sums exactly as it did before the schedules shared their steps.
            return self.decision_sum(t);
        }
        let rest = dims.iter().product::<usize>() / n.max(1);
        let t = t.detach().reshape([n, rest]);
        match self.accumulation() {
            // Item by item through the decision op: each item's value is then bit for bit
            // what `decision_sum` gives for it alone (the sequential schedule's), and on flex
            // it is one in-place pass. A float64 copy reduced by `sum_dim` was a third of a
            // deep batched sweep at 96 × 64.
            Accumulation::Float64 => Tensor::cat(
                (0..n)
                    .map(|i| decision::sum(t.clone().narrow(0, i, 1)))
                    .collect(),
                0,
            ),
            Accumulation::Float32 => t.sum_dim(1).reshape([n]),
        }
    }

    /// [`decision_dot`](Self::decision_dot) of each item of a batch: `[N]`.
    ///
    /// # Shapes
    /// - `a`, `b`: `[N, …]`
    pub fn decision_dot_each<const D: usize>(&self, a: Tensor<D>, b: Tensor<D>) -> Tensor<1> {
        self.each_pair(a, b, |a, b| self.decision_dot(a, b), |a, b| a * b)
    }

    /// [`decision_distance2`](Self::decision_distance2) of each item of a batch: `[N]`.
    ///
    /// # Shapes
    /// - `a`, `b`: `[N, …]`
    pub fn decision_distance2_each<const D: usize>(&self, a: Tensor<D>, b: Tensor<D>) -> Tensor<1> {
        self.each_pair(
            a,
            b,
            |a, b| self.decision_distance2(a, b),
            |a, b| (a - b).square(),
        )
    }

    /// [`decision_norm2`](Self::decision_norm2) of each item of a batch: `[N]`.
    ///
    /// # Shapes
    /// - `t`: `[N, …]`
    pub fn decision_norm2_each<const D: usize>(&self, t: Tensor<D>) -> Tensor<1> {
        self.each_pair(
            t.clone(),
            t,
            |t, _| self.decision_norm2(t),
            |t, _| t.square(),
        )
    }

    /// [`decision_distance2`](Self::decision_distance2) of each item and channel block of a
    /// batch: `[N · B]`, item-major (entry `i·B + b` for item `i`, block `b`). Each entry is
    /// what the item's block alone gives, bit for bit (a feature step decides each block on
    /// its own, SPEC §6 step 3); with one block, [`decision_distance2_each`](Self::decision_distance2_each).
    ///
    /// # Shapes
    /// - `a`, `b`: `[N, C, H, W]`; `blocks`: ranges of channels
    pub fn decision_distance2_blocks(
        &self,
        a: Tensor<4>,
        b: Tensor<4>,
        blocks: &[Range<usize>],
    ) -> Tensor<1> {
        self.each_block(
            a,
            b,
            blocks,
            |a, b| self.decision_distance2(a, b),
            |a, b| (a - b).square(),
        )
    }

    /// [`decision_distance2_blocks`](Self::decision_distance2_blocks) of `a` with `b` and of
    /// `a` with `c`, each bit for bit what that call gives; where the sums are float64 each
    /// item's block is one pass reading `a` once (a feature trial compares its warp with
    /// `f_{k−1}` and with the extrapolated point's warp: 1 frame read fewer per trial).
    ///
    /// # Shapes
    /// - `a`, `b`, `c`: `[N, C, H, W]`; `blocks`: ranges of channels; each output `[N · B]`
    pub fn decision_distance2_blocks_pair(
        &self,
        a: Tensor<4>,
        b: Tensor<4>,
        c: Tensor<4>,
        blocks: &[Range<usize>],
    ) -> [Tensor<1>; 2] {
        if self.accumulation() == Accumulation::Float32 {
            return [
                self.decision_distance2_blocks(a.clone(), b, blocks),
                self.decision_distance2_blocks(a, c, blocks),
            ];
        }
        let n = a.dims()[0];
        let pairs = per_item_block(n, blocks, |part| {
            decision::distance2_pair(part(&a), part(&b), part(&c))
        })
        .reshape([n * blocks.len(), 2]);
        [0, 1].map(|j| pairs.clone().narrow(1, j, 1).reshape([n * blocks.len()]))
    }

    /// [`decision_norm2`](Self::decision_norm2) of each item and channel block: `[N · B]`, as
    /// [`decision_distance2_blocks`](Self::decision_distance2_blocks).
    pub fn decision_norm2_blocks(&self, t: Tensor<4>, blocks: &[Range<usize>]) -> Tensor<1> {
        self.each_block(
            t.clone(),
            t,
            blocks,
            |t, _| self.decision_norm2(t),
            |t, _| t.square(),
        )
    }

    /// [`each_pair`](Self::each_pair) of every channel block: where the sums are float64,
    /// each item's block through `whole` on its own (a block of one item is contiguous, read
    /// in place); in float32, `summand` reduced per item and block.
    fn each_block(
        &self,
        a: Tensor<4>,
        b: Tensor<4>,
        blocks: &[Range<usize>],
        whole: impl Fn(Tensor<4>, Tensor<4>) -> Tensor<1>,
        summand: impl Fn(Tensor<4>, Tensor<4>) -> Tensor<4>,
    ) -> Tensor<1> {
        if let [block] = blocks
            && block.len() == a.dims()[1]
        {
            return self.each_pair(a, b, whole, summand);
        }
        let [n, c, h, w] = a.dims();
        match self.accumulation() {
            Accumulation::Float64 => per_item_block(n, blocks, |part| whole(part(&a), part(&b))),
            Accumulation::Float32 => {
                let t = summand(a.detach(), b.detach()).reshape([n, c, h * w]);
                let sums = blocks
                    .iter()
                    .map(|block| {
                        t.clone()
                            .narrow(1, block.start, block.len())
                            .sum_dim(2)
                            .sum_dim(1)
                            .reshape([n, 1])
                    })
                    .collect();
                Tensor::cat(sums, 1).reshape([n * blocks.len()])
            }
        }
    }

    /// A decision reduction `whole` of two tensors, item by item along dimension 0: where
    /// the sums are float64, each item through `whole` on its own (so that its value is bit
    /// for bit what one item alone gives: the sequential schedule's); in float32, `summand`
    /// reduced per item in one pass.
    fn each_pair<const D: usize>(
        &self,
        a: Tensor<D>,
        b: Tensor<D>,
        whole: impl Fn(Tensor<D>, Tensor<D>) -> Tensor<1>,
        summand: impl Fn(Tensor<D>, Tensor<D>) -> Tensor<D>,
    ) -> Tensor<1> {
        let n = a.dims()[0];
        if n == 1 {
            return whole(a, b);
        }
        match self.accumulation() {
            Accumulation::Float64 => Tensor::cat(
                (0..n)
                    .map(|i| whole(a.clone().narrow(0, i, 1), b.clone().narrow(0, i, 1)))
                    .collect(),
                0,
            ),
            Accumulation::Float32 => {
                let t = summand(a.detach(), b.detach());
                let rest = t.dims().iter().product::<usize>() / n;
                t.reshape([n, rest]).sum_dim(1).reshape([n])
            }
        }
    }

    /// Whether this grid's backend reduces a linearisation with the fused kernel
    /// ([`crate::model::slopes`]).
    pub fn fused_linearisation(&self) -> bool {
        self.capabilities.fused_linearisation
    }

    /// Whether this grid's backend keeps many-channel spline coefficients channels-last
    /// ([`crate::backend::Capabilities::channels_last_coefficients`]).
    pub fn channels_last_coefficients(&self) -> bool {
        self.capabilities.channels_last_coefficients
    }

    /// How the warp reads spline coefficients on this grid's backend.
    pub fn gather(&self) -> Gather {
        self.capabilities.gather
    }

    /// The sum of every entry of `t`, detached, as a `[1]` tensor in float64 where the backend
    /// has it (SPEC §6: the scalars a decrease test or the safeguard compares). The float32
    /// summands are cast first: a float32 sum of `67·256²` values is off by ~6e-6 relative,
    /// and partial sums in float32 keep a systematic rounding bias of the same order (seen
    /// with 256-value lines: 2.4e-6), enough to turn accept/reject near convergence into noise.
    pub fn decision_sum<const D: usize>(&self, t: Tensor<D>) -> Tensor<1> {
        match self.accumulation() {
            Accumulation::Float64 => decision::sum(t),
            Accumulation::Float32 => t.detach().sum(),
        }
    }

    /// [`decision_sum`](Self::decision_sum) of `a · b` (entrywise), the products taken in
    /// float64 where the sum is.
    pub fn decision_dot<const D: usize>(&self, a: Tensor<D>, b: Tensor<D>) -> Tensor<1> {
        match self.accumulation() {
            Accumulation::Float64 => decision::dot(a, b),
            Accumulation::Float32 => (a.detach() * b.detach()).sum(),
        }
    }

    /// [`decision_norm2`](Self::decision_norm2) of `a − b`, without `a − b` as a tensor.
    pub fn decision_distance2<const D: usize>(&self, a: Tensor<D>, b: Tensor<D>) -> Tensor<1> {
        match self.accumulation() {
            Accumulation::Float64 => decision::distance2(a, b),
            Accumulation::Float32 => (a.detach() - b.detach()).square().sum(),
        }
    }

    /// [`decision_sum`](Self::decision_sum) of `t²`: `‖t‖²`.
    pub fn decision_norm2<const D: usize>(&self, t: Tensor<D>) -> Tensor<1> {
        match self.accumulation() {
            Accumulation::Float64 => decision::sum_squares(t),
            Accumulation::Float32 => t.detach().square().sum(),
        }
    }

    /// Rows `H`.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Columns `W`.
    pub fn width(&self) -> usize {
        self.width
    }

    /// `H · W`, the divisor of every `mean` in the SPEC.
    pub fn pixels(&self) -> usize {
        self.height * self.width
    }

    /// The device tensors are created on.
    pub fn device(&self) -> &Device {
        &self.device
    }

    /// The float dtype tensors are created with.
    pub fn dtype(&self) -> DType {
        self.dtype
    }

    /// The same grid on another device (e.g. with autodiff enabled).
    pub fn with_device(&self, device: &Device) -> Self {
        Self {
            device: device.clone(),
            capabilities: Capabilities::of(device),
            // The constants live on the old device.
            constants: Arc::default(),
            ..self.clone()
        }
    }

    /// A tensor from host values, in this grid's device and dtype.
    pub fn tensor<const D: usize>(&self, values: Vec<f64>, shape: [usize; D]) -> Tensor<D> {
        Tensor::from_data(TensorData::new(values, shape), (&self.device, self.dtype))
    }

    /// A host matrix as a `[1, 1, rows, cols]` tensor, ready to broadcast in a batched matmul.
    pub fn matrix(&self, m: &Matrix) -> Tensor<4> {
        self.tensor(m.data.clone(), [1, 1, m.rows, m.cols])
    }

    /// A tensor filled with `value`.
    pub fn full<const D: usize>(&self, shape: [usize; D], value: f64) -> Tensor<D> {
        Tensor::full(shape, value, (&self.device, self.dtype))
    }

    /// The identity deformation `Id`, `[n, 2, H, W]` in pixel units: `Id[0](i, j) = i`,
    /// `Id[1](i, j) = j` (SPEC §0).
    pub fn identity(&self, n: usize) -> Tensor<4> {
        let id = self
            .constants
            .identity
            .get_or_init(|| {
                let (h, w) = (self.height, self.width);
                let mut values = Vec::with_capacity(2 * h * w);
                values.extend((0..h).flat_map(|i| std::iter::repeat_n(i as f64, w)));
                values.extend((0..h).flat_map(|_| (0..w).map(|j| j as f64)));
                self.tensor(values, [1, 2, h, w])
            })
            .clone();
        if n == 1 { id } else { id.repeat_dim(0, n) }
    }

    /// 1 on the first and last row and column, 0 inside: `[1, 1, H, W]`.
    pub fn boundary(&self) -> Tensor<4> {
        self.constants
            .boundary
            .get_or_init(|| {
                let (h, w) = (self.height, self.width);
                let values: Vec<f64> = (0..h)
                    .flat_map(|i| {
                        (0..w).map(move |j| {
                            let edge = i == 0 || j == 0 || i == h - 1 || j == w - 1;
                            if edge { 1.0 } else { 0.0 }
                        })
                    })
                    .collect();
                self.tensor(values, [1, 1, h, w])
            })
            .clone()
    }

    /// Where [`boundary`](Self::boundary) is 1, for both components of a deformation:
    /// `[1, 2, H, W]`.
    pub fn on_boundary(&self) -> Tensor<4, Bool> {
        self.constants
            .on_boundary
            .get_or_init(|| {
                let (h, w) = (self.height, self.width);
                self.boundary().expand([1, 2, h, w]).equal_elem(1.0)
            })
            .clone()
    }
}

/// All values of a float tensor, read back to the host as `f64` (one synchronisation).
pub fn to_host<const D: usize>(t: Tensor<D>) -> Vec<f64> {
    t.into_data()
        .try_into_vec_as::<f64>()
        .expect("float tensors convert to f64")
}

/// [`to_host`] for values that must not be NaN.
///
/// # Errors
///
/// [`Error::NonFinite`] if a value is NaN (infinities pass: callers decide).
pub fn host_values<const D: usize>(t: Tensor<D>) -> Result<Vec<f64>> {
    let values = to_host(t);
    if values.iter().any(|v| v.is_nan()) {
        return Err(Error::NonFinite {
            what: "NaN in a tensor read back to the host".into(),
        });
    }
    Ok(values)
}

/// `sum` of each item's channel block, item-major, concatenated: `sum` reads its tensors
/// through `part`, which narrows one to the item and block (a contiguous block of one item,
/// read in place by the flex kernels).
fn per_item_block(
    n: usize,
    blocks: &[Range<usize>],
    sum: impl Fn(&dyn Fn(&Tensor<4>) -> Tensor<4>) -> Tensor<1>,
) -> Tensor<1> {
    Tensor::cat(
        (0..n)
            .flat_map(|i| blocks.iter().map(move |block| (i, block)))
            .map(|(i, block)| {
                sum(&|t: &Tensor<4>| {
                    t.clone()
                        .narrow(0, i, 1)
                        .narrow(1, block.start, block.len())
                })
            })
            .collect(),
        0,
    )
}
