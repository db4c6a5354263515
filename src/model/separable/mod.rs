//! Separable linear operators on images: `x ↦ R · x · Cᵀ` with 1-D matrices `R` and `C`.

pub mod host;
pub mod op;

use burn::tensor::Tensor;

use crate::model::grid::Grid;
use crate::model::stencil::Matrix;

/// A separable linear map `x ↦ R · x · Cᵀ` acting on the last two axes of a batch of maps:
/// `R` (`H' × H`) on rows and `C` (`W' × W`) on columns.
///
/// The 1-D matrices come from [`crate::model::stencil`] with the mirror boundary folded in, so
/// any stencil width is exact (a 13-tap Gaussian on 10 rows reflects twice). They are kept
/// dense on the device; the op ([`op`]) applies them as two matmuls where that is the
/// backend's strength (wgpu, ndarray) and as their nonzero bands on flex, `C·H·W·taps`
/// multiply-adds instead of the dense `2·C·H·W·(H + W)` flops. Autodiff differentiates it
/// through its adjoint `Rᵀ · g · C`.
#[derive(Clone, Debug)]
pub struct Separable {
    rows: Tensor<4>,
    cols_t: Tensor<4>,
}

impl Separable {
    /// The operator `x ↦ rows · x · colsᵀ` on `grid`'s device and dtype.
    pub fn new(grid: &Grid, rows: &Matrix, cols: &Matrix) -> Self {
        Self {
            rows: grid.matrix(rows),
            cols_t: grid.matrix(&cols.transpose()),
        }
    }

    /// Applies the operator.
    ///
    /// # Shapes
    /// - `x`: `[N, C, H, W]`
    /// - output: `[N, C, H', W']`
    pub fn apply(&self, x: Tensor<4>) -> Tensor<4> {
        op::apply(x, self.rows.clone(), self.cols_t.clone())
    }

    /// `R` and `Cᵀ`, `[1, 1, H', H]` and `[1, 1, W, W']`.
    pub(crate) fn matrices(&self) -> (Tensor<4>, Tensor<4>) {
        (self.rows.clone(), self.cols_t.clone())
    }
}
