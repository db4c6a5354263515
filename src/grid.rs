//! The pixel grid a level of the model lives on.

use burn::tensor::{DType, Device, FloatDType, Tensor, TensorData};

use crate::error::{Error, Result};
use crate::stencil::Matrix;

/// An `H × W` pixel grid (SPEC §0: `H` rows, `W` columns, both at least 4) on a device, in
/// one precision. Every tensor the library creates for the grid gets this device and dtype,
/// so the same code runs in float32 on any backend and in float64 for gradient checks.
#[derive(Clone, Debug)]
pub struct Grid {
    height: usize,
    width: usize,
    device: Device,
    dtype: DType,
    accumulation: Accumulation,
}

/// How [`Grid::decision_sum`] adds up the values whose sums decide a backtracking test
/// (SPEC §6, "Floating point").
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Accumulation {
    /// Partial sums along the last axis in the working precision, added in float64: the
    /// backend computes in float64 (flex, ndarray). The tests need no slack.
    Float64,
    /// Everything in float32 (Burn's tree reductions, i.e. pairwise partial sums): the
    /// backend has no float64 (wgpu). The tests allow a relative slack.
    Float32,
}

impl Accumulation {
    fn of(device: &Device, dtype: DType) -> Self {
        let float64 = dtype == DType::F64
            || crate::Backend::of(device).is_some_and(|b| b.supports(crate::Precision::F64));
        if float64 { Self::Float64 } else { Self::Float32 }
    }
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
            accumulation: Accumulation::of(device, dtype),
        })
    }

    /// How decision sums are accumulated on this grid's backend.
    pub fn accumulation(&self) -> Accumulation {
        self.accumulation
    }

    /// The sum of every entry of `t`, detached, as a `[1]` tensor in float64 where the backend
    /// has it (SPEC §6: the scalars a decrease test or the safeguard compares). Each line
    /// along the last axis (at most a few hundred values) is summed in the working precision,
    /// the partial sums in float64: a float32 sum of `67·256²` values is off by ~6e-6
    /// relative, enough to turn accept/reject near convergence into noise.
    pub fn decision_sum<const D: usize>(&self, t: Tensor<D>) -> Tensor<1> {
        let t = t.detach();
        match self.accumulation {
            Accumulation::Float64 if D >= 2 => t.sum_dim(D - 1).cast(FloatDType::F64).sum(),
            Accumulation::Float64 => t.cast(FloatDType::F64).sum(),
            Accumulation::Float32 => t.sum(),
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
            accumulation: Accumulation::of(device, self.dtype),
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
        let (h, w) = (self.height, self.width);
        let mut values = Vec::with_capacity(2 * h * w);
        values.extend((0..h).flat_map(|i| std::iter::repeat_n(i as f64, w)));
        values.extend((0..h).flat_map(|_| (0..w).map(|j| j as f64)));
        let id: Tensor<4> = self.tensor(values, [1, 2, h, w]);
        if n == 1 { id } else { id.repeat_dim(0, n) }
    }

    /// Checks that `t` has spatial size `H × W` (its last two dimensions).
    pub fn check_spatial<const D: usize>(&self, op: &'static str, t: &Tensor<D>) -> Result<()> {
        let dims = t.dims();
        if D < 2 || dims[D - 2] != self.height || dims[D - 1] != self.width {
            return Err(Error::Shape {
                op,
                detail: format!(
                    "expected spatial size {}x{}, got shape {:?}",
                    self.height, self.width, dims
                ),
            });
        }
        Ok(())
    }
}
