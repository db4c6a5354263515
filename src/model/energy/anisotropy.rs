//! The edge-stopping anisotropy `a[u]` that weights the regulariser (SPEC §3).

use burn::tensor::Tensor;

use crate::backend::Capabilities;
use crate::error::Result;
use crate::model::energy::anisotropy_op::anisotropy;
use crate::model::grid::Grid;
use crate::model::params::positive;
use crate::model::separable::Separable;
use crate::model::stencil::{central_difference_domain, gaussian};

/// `a[u] = exp(−|G_ρ ∗ D(G_σ ∗ u)|² / ξ₁) + ξ₂` on one grid.
///
/// Smoothing, differencing and smoothing again are linear and separable, so each of the two
/// derivative directions is a single [`Separable`] operator whose 1-D matrices are the
/// products `G_ρ D G_σ` (along the derivative's axis) and `G_ρ G_σ` (along the other),
/// each factor with its own mirror boundary: four matmuls per channel instead of five
/// filtering passes.
#[derive(Clone, Debug)]
pub struct Anisotropy {
    along_rows: Separable,
    along_cols: Separable,
    xi1: f64,
    xi2: f64,
}

impl Anisotropy {
    /// The anisotropy operator with smoothing widths `σ`, `ρ` and constants `ξ₁`, `ξ₂`.
    ///
    /// # Errors
    ///
    /// If a parameter is not a finite positive number.
    pub fn new(grid: &Grid, sigma: f64, rho: f64, xi1: f64, xi2: f64) -> Result<Self> {
        positive("sigma", sigma)?;
        positive("rho", rho)?;
        positive("xi1", xi1)?;
        positive("xi2", xi2)?;
        let smooth = |n| gaussian(n, rho).matmul(&gaussian(n, sigma));
        let differentiate =
            |n| gaussian(n, rho).matmul(&central_difference_domain(n).matmul(&gaussian(n, sigma)));
        let (h, w) = (grid.height(), grid.width());
        Ok(Self {
            along_rows: Separable::new(grid, &differentiate(h), &smooth(w)),
            along_cols: Separable::new(grid, &smooth(h), &differentiate(w)),
            xi1,
            xi2,
        })
    }

    /// The two separable operators `G_ρ D G_σ` (derivative along rows, then along columns).
    #[cfg(feature = "check")]
    pub(crate) fn operators(&self) -> (&Separable, &Separable) {
        (&self.along_rows, &self.along_cols)
    }

    /// `a[u]` for each image of the batch. The anisotropy is a fixed weight in every
    /// derivative the model takes, so the input is detached.
    ///
    /// # Shapes
    /// - `u`: `[N, 3, H, W]`, RGB in `[0, 1]` (never the η-scaled copy)
    /// - output: `[N, H, W]`
    pub fn compute(&self, u: Tensor<4>) -> Tensor<3> {
        let [n, _, h, w] = u.dims();
        let u = u.detach();
        if Capabilities::of(&u.device()).fused_anisotropy {
            return anisotropy(
                u,
                self.along_rows.matrices(),
                self.along_cols.matrices(),
                self.xi1,
                self.xi2,
            );
        }
        let d0 = self.along_rows.apply(u.clone());
        let d1 = self.along_cols.apply(u);
        let norm2 = (d0.square() + d1.square()).sum_dim(1).reshape([n, h, w]);
        norm2.mul_scalar(-1.0 / self.xi1).exp().add_scalar(self.xi2)
    }
}
