//! The edge-stopping anisotropy `a[u]` that weights the regulariser (SPEC §3).

use burn::tensor::Tensor;

use crate::error::Result;
use crate::grid::Grid;
use crate::params::positive;
use crate::separable::Separable;
use crate::stencil::{Matrix, central_difference_domain, gaussian};

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

    /// The smoothed gradient `G_ρ ∗ D(G_σ ∗ u)`: per channel, the derivative along rows then
    /// along columns, in domain units (the domain is `[0, 1]²`).
    ///
    /// # Shapes
    /// - `u`: `[N, C, H, W]`
    /// - output: `[N, C, 2, H, W]`
    pub fn smoothed_gradient(&self, u: Tensor<4>) -> Tensor<5> {
        let d0 = self.along_rows.apply(u.clone());
        let d1 = self.along_cols.apply(u);
        Tensor::stack(vec![d0, d1], 2)
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
        let d0 = self.along_rows.apply(u.clone());
        let d1 = self.along_cols.apply(u);
        let norm2 = (d0.square() + d1.square()).sum_dim(1).reshape([n, h, w]);
        norm2.mul_scalar(-1.0 / self.xi1).exp().add_scalar(self.xi2)
    }
}

/// Gaussian smoothing `G_s ∗` with mirror boundary on both axes (SPEC §3).
pub fn gaussian_smoothing(grid: &Grid, s: f64) -> Separable {
    Separable::new(
        grid,
        &gaussian(grid.height(), s),
        &gaussian(grid.width(), s),
    )
}

/// The central-difference derivative in domain units along rows (`axis = 0`) or columns
/// (`axis = 1`) (SPEC §3's `D`).
pub fn domain_derivative(grid: &Grid, axis: usize) -> Separable {
    let (h, w) = (grid.height(), grid.width());
    match axis {
        0 => Separable::new(grid, &central_difference_domain(h), &Matrix::identity(w)),
        _ => Separable::new(grid, &Matrix::identity(h), &central_difference_domain(w)),
    }
}
