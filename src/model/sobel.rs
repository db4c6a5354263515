//! The Sobel derivative used to linearise the data term (SPEC §6).

use burn::tensor::Tensor;

use crate::model::grid::Grid;
use crate::model::separable::Separable;
use crate::model::stencil::{sobel_difference, sobel_smoothing};

/// The Sobel gradient in pixel units with mirror boundary:
/// `∂₀ g(i,j) = Σ_s w_s (g(i+1, j+s) − g(i−1, j+s)) / 8`, `w = (1, 2, 1)`, and likewise `∂₁`.
/// It is exact on linear ramps.
#[derive(Clone, Debug)]
pub struct Sobel {
    along_rows: Separable,
    along_cols: Separable,
}

impl Sobel {
    /// The Sobel operator of `grid`.
    pub fn new(grid: &Grid) -> Self {
        let (h, w) = (grid.height(), grid.width());
        Self {
            along_rows: Separable::new(grid, &sobel_difference(h), &sobel_smoothing(w)),
            along_cols: Separable::new(grid, &sobel_smoothing(h), &sobel_difference(w)),
        }
    }

    /// Both derivatives of every map.
    ///
    /// # Shapes
    /// - `g`: `[N, C, H, W]`
    /// - output: `[N, C, 2, H, W]` (`[:, :, 0]` along rows, `[:, :, 1]` along columns)
    pub fn gradient(&self, g: Tensor<4>) -> Tensor<5> {
        let d0 = self.along_rows.apply(g.clone());
        let d1 = self.along_cols.apply(g);
        Tensor::stack(vec![d0, d1], 2)
    }
}
