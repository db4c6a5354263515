//! The pixel grid a level of the model lives on.

use burn::tensor::{DType, Device, Tensor, TensorData};

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
        })
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
