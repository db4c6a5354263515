//! The anisotropic regulariser `R[φ, a] = mean(a · W(J(φ)))` (SPEC §2).

use burn::tensor::Tensor;

use crate::backend::Capabilities;
use crate::model::deformation::jacobian;
use crate::model::energy::density::density;
use crate::model::energy::density_op;

/// `R[φ_n, a_n]` for each deformation of the batch; `+∞` where `φ_n` folds.
///
/// # Shapes
/// - `phi`: `[N, 2, H, W]`
/// - `a`: `[N, H, W]`
/// - output: `[N]`
pub fn regularizer(phi: Tensor<4>, a: Tensor<3>, lambda: f64, mu: f64) -> Tensor<1> {
    mean_density(weighted_density(phi, a, lambda, mu))
}

/// [`regularizer`] from its summand [`weighted_density`], for a caller that also sums the
/// summand otherwise (the solver's decisions): the density is then evaluated once.
///
/// # Shapes
/// - `density`: `[N, H, W]`
/// - output: `[N]`
pub fn mean_density(density: Tensor<3>) -> Tensor<1> {
    let [n, h, w] = density.dims();
    density.reshape([n, h * w]).mean_dim(1).reshape([n])
}

/// `a · W(J(φ))` at every pixel: the summand of [`regularizer`], for sums accumulated
/// elsewhere (the solver's decisions add it up in float64).
///
/// On a backend with the fused density ([`crate::backend::Capabilities::fused_density`]) one
/// custom op with a hand-written backward; composed from tensor ops otherwise. Both are SPEC
/// §2's formula.
///
/// # Shapes
/// - `phi`: `[N, 2, H, W]`
/// - `a`: `[N, H, W]`
/// - output: `[N, H, W]`
pub fn weighted_density(phi: Tensor<4>, a: Tensor<3>, lambda: f64, mu: f64) -> Tensor<3> {
    if Capabilities::of(&phi.device()).fused_density {
        return density_op::weighted_density(phi, a, lambda, mu);
    }
    a * density(&jacobian(phi), lambda, mu)
}
