//! Separable linear operators on images, applied as two matrix products.

use burn::tensor::Tensor;

use crate::model::grid::Grid;
use crate::model::stencil::Matrix;

/// A separable linear map `x ↦ R · x · Cᵀ` acting on the last two axes of a batch of maps:
/// `R` (`H' × H`) on rows and `C` (`W' × W`) on columns.
///
/// The 1-D matrices come from [`crate::model::stencil`] with the mirror boundary folded in. Two
/// dense matmuls are exact for any stencil width, differentiate under autodiff as matmuls
/// do, and run on every backend. They cost `2·C·H·W·(H + W)` flops against a banded
/// stencil's `C·H·W·taps` (the `warp` benchmark includes the prefilter's share).
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
        self.rows.clone().matmul(x).matmul(self.cols_t.clone())
    }

    /// `R` and `Cᵀ`, `[1, 1, H', H]` and `[1, 1, W, W']`.
    #[cfg(feature = "check")]
    pub(crate) fn matrices(&self) -> (Tensor<4>, Tensor<4>) {
        (self.rows.clone(), self.cols_t.clone())
    }
}
