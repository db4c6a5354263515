//! The anisotropic regulariser `R[φ, a] = mean(a · W(J(φ)))` (SPEC §2).

use burn::tensor::Tensor;

use crate::deformation::{Jacobian, jacobian, jacobian_adjoint};
use crate::energy::density::{density, density_gradient};

/// `R[φ_n, a_n]` for each deformation of the batch; `+∞` where `φ_n` folds.
///
/// # Shapes
/// - `phi`: `[N, 2, H, W]`
/// - `a`: `[N, H, W]`
/// - output: `[N]`
pub fn regularizer(phi: Tensor<4>, a: Tensor<3>, lambda: f64, mu: f64) -> Tensor<1> {
    let [n, _, h, w] = phi.dims();
    weighted_density(phi, a, lambda, mu)
        .reshape([n, h * w])
        .mean_dim(1)
        .reshape([n])
}

/// `a · W(J(φ))` at every pixel: the summand of [`regularizer`], for sums accumulated
/// elsewhere (the solver's decisions add it up in float64).
///
/// # Shapes
/// - `phi`: `[N, 2, H, W]`
/// - `a`: `[N, H, W]`
/// - output: `[N, H, W]`
pub fn weighted_density(phi: Tensor<4>, a: Tensor<3>, lambda: f64, mu: f64) -> Tensor<3> {
    a * density(&jacobian(phi), lambda, mu)
}

/// The hand-derived `∂R/∂φ`: `a ∂W/∂J / (H·W)` chained through the adjoint of the forward
/// differences (for the gradient checks). Only meaningful for admissible `φ`.
///
/// # Shapes
/// - `phi`: `[N, 2, H, W]`
/// - `a`: `[N, H, W]`
/// - output: `[N, 2, H, W]`
pub fn regularizer_gradient(phi: Tensor<4>, a: Tensor<3>, lambda: f64, mu: f64) -> Tensor<4> {
    let [_, _, h, w] = phi.dims();
    let g = density_gradient(&jacobian(phi), lambda, mu);
    let scale = a.mul_scalar(1.0 / (h * w) as f64);
    jacobian_adjoint(Jacobian {
        j00: g.j00 * scale.clone(),
        j01: g.j01 * scale.clone(),
        j10: g.j10 * scale.clone(),
        j11: g.j11 * scale,
    })
}
