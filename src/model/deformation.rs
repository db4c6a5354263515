//! Deformations: the forward-difference Jacobian and admissibility (SPEC §0, §2).

use burn::tensor::Tensor;

use crate::backend::Capabilities;
use crate::model::energy::density_op;
use crate::model::grid::Grid;
use crate::model::grid::to_host;

/// The Jacobian `J = I + ∇v` of a batch of deformations, one `[N, H, W]` map per entry:
/// `J[a][b] = δ_ab + ∂_b v_a` with forward differences and a Neumann boundary (the
/// difference is 0 on the last row for `∂₀` and on the last column for `∂₁`).
#[derive(Clone, Debug)]
pub struct Jacobian {
    /// `J₀₀ = 1 + ∂₀ v₀`.
    pub j00: Tensor<3>,
    /// `J₀₁ = ∂₁ v₀`.
    pub j01: Tensor<3>,
    /// `J₁₀ = ∂₀ v₁`.
    pub j10: Tensor<3>,
    /// `J₁₁ = 1 + ∂₁ v₁`.
    pub j11: Tensor<3>,
}

impl Jacobian {
    /// `det J`, `[N, H, W]`.
    pub fn det(&self) -> Tensor<3> {
        self.j00.clone() * self.j11.clone() - self.j01.clone() * self.j10.clone()
    }
}

/// The smallest `det J` of each deformation of the batch, detached, `[N]`: one fused pass on
/// a backend with the fused density ([`crate::backend::Capabilities::fused_density`]; the
/// same values), the composed Jacobian otherwise.
///
/// # Shapes
/// - `phi`: `[N, 2, H, W]`
pub fn min_det_each(phi: Tensor<4>) -> Tensor<1> {
    if Capabilities::of(&phi.device()).fused_density {
        return density_op::min_det(phi);
    }
    let [n, _, h, w] = phi.dims();
    jacobian(phi.detach())
        .det()
        .reshape([n, h * w])
        .min_dim(1)
        .reshape([n])
}

/// Forward difference along `dim` (1 = rows, 2 = columns) of `[N, H, W]` maps, with `fill`
/// in the last row/column where the difference leaves the grid.
fn forward_difference(x: Tensor<3>, dim: usize, fill: f64) -> Tensor<3> {
    let n = x.dims()[dim];
    let ahead = x.clone().narrow(dim, 1, n - 1);
    let here = x.narrow(dim, 0, n - 1);
    let diff = ahead - here;
    let mut edge_shape = diff.dims();
    edge_shape[dim] = 1;
    let edge = Tensor::full(edge_shape, fill, (&diff.device(), diff.dtype()));
    Tensor::cat(vec![diff, edge], dim)
}

/// The Jacobian of `phi` (SPEC §2). Pixel units for `φ` and the grid make it dimensionless;
/// `J(Id) = I`.
///
/// # Shapes
/// - `phi`: `[N, 2, H, W]`
/// - output: four `[N, H, W]` maps
pub fn jacobian(phi: Tensor<4>) -> Jacobian {
    let [n, _, h, w] = phi.dims();
    let phi0 = phi.clone().narrow(1, 0, 1).reshape([n, h, w]);
    let phi1 = phi.narrow(1, 1, 1).reshape([n, h, w]);
    // ∂₀ φ₀ = 1 + ∂₀ v₀ inside, and J₀₀ = 1 on the last row where ∂₀ v = 0; likewise J₁₁.
    // The off-diagonal entries see no identity part (Id₀ is constant along columns).
    Jacobian {
        j00: forward_difference(phi0.clone(), 1, 1.0),
        j01: forward_difference(phi0, 2, 0.0),
        j10: forward_difference(phi1.clone(), 1, 0.0),
        j11: forward_difference(phi1, 2, 1.0),
    }
}

/// Whether each deformation of the batch is admissible (SPEC §0): `φ = Id` on the boundary
/// rows and columns, and `det J > 0` at every pixel. Reads `2N` numbers back from the
/// device.
///
/// # Shapes
/// - `phi`: `[N, 2, H, W]`
pub fn admissible_each(grid: &Grid, phi: Tensor<4>) -> Vec<bool> {
    let phi = phi.detach();
    let [n, _, h, w] = phi.dims();
    let boundary_move = (phi.clone() - grid.identity(n)).abs() * boundary_indicator(grid, n);
    let boundary_max = boundary_move
        .reshape([n, 2 * h * w])
        .max_dim(1)
        .reshape([n]);
    let min_det = min_det_each(phi);
    let values = to_host(Tensor::cat(vec![boundary_max, min_det], 0));
    // A NaN anywhere fails both comparisons, so it is never admissible.
    (0..n)
        .map(|k| values[k] == 0.0 && values[n + k] > 0.0)
        .collect()
}

/// Whether every deformation of the batch is admissible; see [`admissible_each`].
pub fn is_admissible(grid: &Grid, phi: Tensor<4>) -> bool {
    admissible_each(grid, phi).into_iter().all(|ok| ok)
}

/// `φ` with its boundary rows and columns set to the identity, exactly (SPEC §6, §7).
///
/// # Shapes
/// - `phi`: `[N, 2, H, W]`
/// - output: `[N, 2, H, W]`
pub fn with_identity_boundary(grid: &Grid, phi: Tensor<4>) -> Tensor<4> {
    let n = phi.dims()[0];
    if n == 1 {
        return phi.mask_where(grid.on_boundary(), grid.identity(1));
    }
    let shape = [n, 2, grid.height(), grid.width()];
    phi.mask_where(
        grid.on_boundary().expand(shape),
        grid.identity(1).expand(shape),
    )
}

/// 1 on the first and last row and column, 0 inside, `[N, 2, H, W]`.
fn boundary_indicator(grid: &Grid, n: usize) -> Tensor<4> {
    grid.boundary().expand([n, 2, grid.height(), grid.width()])
}
