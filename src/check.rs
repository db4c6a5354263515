//! Reference paths for the tests and benchmarks, compiled only with the `check` feature
//! (which the crate's own tests and benches switch on through a dev-dependency on itself):
//! the hand-derived adjoints and gradients of SPEC §1–§5 that the gradient checks compare
//! with autodiff and with finite differences, and the reference forms of operators the
//! model composes differently (the truncated 25-tap prefilter, the anisotropy's separate
//! smoothing and differencing). The solver never calls any of this: it takes its gradients
//! from autodiff.

use burn::tensor::{IndexingUpdateOp, Tensor};

use crate::model::deformation::Jacobian;
use crate::model::deformation::jacobian;
use crate::model::energy::anisotropy::Anisotropy;
use crate::model::energy::path::PathEnergy;
use crate::model::grid::Grid;
use crate::model::separable::Separable;
use crate::model::stencil::{BSPLINE_POLE, Matrix, central_difference_domain, gaussian};
use crate::model::warp::BSpline;

// ---- the warp (SPEC §1) ----------------------------------------------------------------

/// Adjoint of [`BSpline::coefficients`]: `Pᵀ` applied per channel.
///
/// Always the dense `Pᵀ` (built here when the spline is fused), so a hand gradient never
/// shares a kernel with the autodiff gradient it checks.
pub fn coefficients_adjoint(bspline: &BSpline, g: Tensor<4>) -> Tensor<4> {
    match bspline.prefilter() {
        Some(dense) => separable_adjoint(dense, g),
        None => {
            let grid = bspline.grid();
            let dense = Separable::new(
                grid,
                &crate::model::stencil::bspline_prefilter(grid.height()),
                &crate::model::stencil::bspline_prefilter(grid.width()),
            );
            separable_adjoint(&dense, g)
        }
    }
}

/// The adjoint of [`BSpline::interpolate`] in its coefficients, by scatter-add: `Bᵀ y` with
/// `B` the (φ-dependent) evaluation matrix.
///
/// # Shapes
/// - `y`: `[N, C, H', W']`
/// - `phi`: `[N, 2, H', W']`
/// - output: `[N, C, H, W]`
pub fn interpolate_adjoint(bspline: &BSpline, y: Tensor<4>, phi: Tensor<4>) -> Tensor<4> {
    let [n, c, ho, wo] = y.dims();
    let (h, w) = (bspline.grid().height(), bspline.grid().width());
    let st = bspline.stencil(phi);
    let y = y.reshape([n, c, ho * wo]);
    let mut acc = Tensor::<3>::zeros([n, c, h * w], (&y.device(), y.dtype()));
    for a in 0..4 {
        for b in 0..4 {
            let idx = st.flat[4 * a + b].clone().expand([n, c, ho * wo]);
            let values = y.clone() * (st.w0[a].clone() * st.w1[b].clone());
            acc = acc.scatter(2, idx, values, IndexingUpdateOp::Add);
        }
    }
    acc.reshape([n, c, h, w])
}

/// The derivative of the interpolant with respect to the sample position, via `β'`:
/// `∂T/∂p₀` and `∂T/∂p₁` per channel, zero on an axis where the point lies outside the
/// clamp range (the clamped function is constant there).
///
/// # Shapes
/// - `coeffs`: `[N, C, H, W]`
/// - `phi`: `[N, 2, H', W']`
/// - output: (`[N, C, H', W']`, `[N, C, H', W']`)
pub fn interpolate_position_derivative(
    bspline: &BSpline,
    coeffs: Tensor<4>,
    phi: Tensor<4>,
) -> (Tensor<4>, Tensor<4>) {
    let [n, c, h, w] = coeffs.dims();
    let [_, _, ho, wo] = phi.dims();
    let st = bspline.stencil(phi);
    let dw0 = bspline_weight_derivatives(st.t0.clone());
    let dw1 = bspline_weight_derivatives(st.t1.clone());
    let coeffs = coeffs.reshape([n, c, h * w]);
    let zeros = Tensor::<3>::zeros([n, c, ho * wo], (&coeffs.device(), coeffs.dtype()));
    let (mut d0, mut d1) = (zeros.clone(), zeros);
    for a in 0..4 {
        for b in 0..4 {
            let idx = st.flat[4 * a + b].clone().expand([n, c, ho * wo]);
            let g = coeffs.clone().gather(2, idx);
            d0 = d0 + g.clone() * (dw0[a].clone() * st.w1[b].clone());
            d1 = d1 + g * (st.w0[a].clone() * dw1[b].clone());
        }
    }
    let d0 = (d0 * st.inside0).reshape([n, c, ho, wo]);
    let d1 = (d1 * st.inside1).reshape([n, c, ho, wo]);
    (d0, d1)
}

/// `d/dt` of the four cubic B-spline weights `β(t+1), β(t), β(t−1), β(t−2)`: `β'`.
fn bspline_weight_derivatives(t: Tensor<3>) -> [Tensor<3>; 4] {
    let s = t.clone().neg().add_scalar(1.0);
    let t2 = t.clone().square();
    let s2 = s.clone().square();
    [
        s2.clone().mul_scalar(-0.5),
        t2.clone().mul_scalar(1.5) - t.mul_scalar(2.0),
        s.mul_scalar(2.0) - s2.mul_scalar(1.5),
        t2.mul_scalar(0.5),
    ]
}

/// The 25 taps `h[n] = √3 · z^|n|`, `|n| ≤ 12`, of the truncated prefilter SPEC §1 allows.
pub fn bspline_prefilter_taps25() -> Vec<f64> {
    (-12i32..=12)
        .map(|k| 3f64.sqrt() * BSPLINE_POLE.powi(k.abs()))
        .collect()
}

// ---- separable operators and the anisotropy (SPEC §0, §3) --------------------------------

/// The adjoint `y ↦ Rᵀ · y · C` of a [`Separable`] operator `x ↦ R · x · Cᵀ`.
///
/// # Shapes
/// - `y`: `[N, C, H', W']`
/// - output: `[N, C, H, W]`
pub fn separable_adjoint(op: &Separable, y: Tensor<4>) -> Tensor<4> {
    let (rows, cols_t) = op.matrices();
    rows.swap_dims(2, 3)
        .matmul(y)
        .matmul(cols_t.swap_dims(2, 3))
}

/// `R` and `Cᵀ` of a [`Separable`] operator, `[1, 1, H', H]` and `[1, 1, W, W']`, for a dense
/// reference product.
pub fn separable_matrices(op: &Separable) -> (Tensor<4>, Tensor<4>) {
    op.matrices()
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

/// The anisotropy's smoothed gradient `G_ρ ∗ D(G_σ ∗ u)`: per channel, the derivative
/// along rows then along columns, in domain units.
///
/// # Shapes
/// - `u`: `[N, C, H, W]`
/// - output: `[N, C, 2, H, W]`
pub fn smoothed_gradient(anisotropy: &Anisotropy, u: Tensor<4>) -> Tensor<5> {
    let (along_rows, along_cols) = anisotropy.operators();
    let d0 = along_rows.apply(u.clone());
    let d1 = along_cols.apply(u);
    Tensor::stack(vec![d0, d1], 2)
}

// ---- deformations and the regulariser (SPEC §2) -------------------------------------------

/// The four entries of a Jacobian stacked as `[N, 2, 2, H, W]` (`[:, a, b]` = `J[a][b]`).
pub fn stacked(j: &Jacobian) -> Tensor<5> {
    let row0 = Tensor::stack::<4>(vec![j.j00.clone(), j.j01.clone()], 1);
    let row1 = Tensor::stack::<4>(vec![j.j10.clone(), j.j11.clone()], 1);
    Tensor::stack(vec![row0, row1], 1)
}

/// Adjoint of the forward difference along `dim` (ignoring the constant fill): for `y`
/// with `n` entries along `dim`, `(Dᵀ y)(i) = y(i−1)·[i ≥ 1] − y(i)·[i ≤ n−2]`. The last
/// row/column of `y` pairs with the constant fill and does not contribute.
pub fn forward_difference_adjoint(y: Tensor<3>, dim: usize) -> Tensor<3> {
    let n = y.dims()[dim];
    let inner = y.narrow(dim, 0, n - 1);
    let mut edge_shape = inner.dims();
    edge_shape[dim] = 1;
    let zero = Tensor::zeros(edge_shape, (&inner.device(), inner.dtype()));
    let shifted = Tensor::cat(vec![zero.clone(), inner.clone()], dim);
    let here = Tensor::cat(vec![inner, zero], dim);
    shifted - here
}

/// The adjoint of [`jacobian`] as a linear map of `v = φ − Id`: given `G = ∂F/∂J` for some
/// `F(J(φ))`, returns `∂F/∂φ`.
///
/// # Shapes
/// - `g`: four `[N, H, W]` maps
/// - output: `[N, 2, H, W]`
pub fn jacobian_adjoint(g: Jacobian) -> Tensor<4> {
    let d0 = forward_difference_adjoint(g.j00, 1) + forward_difference_adjoint(g.j01, 2);
    let d1 = forward_difference_adjoint(g.j10, 1) + forward_difference_adjoint(g.j11, 2);
    Tensor::stack(vec![d0, d1], 1)
}

/// The hand-derived `∂W/∂J = λ exp((log d)²) log d J⁻ᵀ + 2μ (sym J − I)` (SPEC §2). Only
/// meaningful where `det J > 0`.
///
/// # Shapes
/// - `j`: four `[N, H, W]` maps
/// - output: four `[N, H, W]` maps (`∂W/∂J[a][b]` in field `jab`)
pub fn density_gradient(j: &Jacobian, lambda: f64, mu: f64) -> Jacobian {
    let det = j.det();
    let log_det = det.clone().log();
    // λ exp((log d)²) log d / d: the common factor of the cofactor matrix d·J⁻ᵀ.
    let factor = log_det.clone().square().exp() * log_det / det * lambda;
    let shear = (j.j01.clone() + j.j10.clone()).mul_scalar(mu);
    Jacobian {
        j00: factor.clone() * j.j11.clone() + j.j00.clone().sub_scalar(1.0).mul_scalar(2.0 * mu),
        j01: (factor.clone() * j.j10.clone()).neg() + shear.clone(),
        j10: (factor.clone() * j.j01.clone()).neg() + shear,
        j11: factor * j.j00.clone() + j.j11.clone().sub_scalar(1.0).mul_scalar(2.0 * mu),
    }
}

/// The hand-derived `∂R/∂φ`: `a ∂W/∂J / (H·W)` chained through the adjoint of the forward
/// differences. Only meaningful for admissible `φ`.
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

// ---- the data term and the path energy (SPEC §5) ------------------------------------------

/// Hand-derived gradients of [`crate::model::energy::data::data_term`].
#[derive(Clone, Debug)]
pub struct DataTermGradient {
    /// `∂D/∂f = −r / (C_tot H W)`, `[N, C, H, W]`.
    pub f: Tensor<4>,
    /// `∂D/∂f̃ = Pᵀ Bᵀ_φ r / (C_tot H W)`, `[N, C, H, W]` (adjoint of the warp).
    pub f_tilde: Tensor<4>,
    /// `∂D/∂φ = Σ_c r_c ∇_p T[f̃_c](φ) / (C_tot H W)` with `β'`, `[N, 2, H, W]`.
    pub phi: Tensor<4>,
}

/// The hand-derived gradient of `D[f, f̃, φ]` with respect to all three arguments, with
/// `r = T[f̃, φ] − f`.
pub fn data_term_gradient(
    bspline: &BSpline,
    f: Tensor<4>,
    f_tilde: Tensor<4>,
    phi: Tensor<4>,
    c_tot: usize,
) -> DataTermGradient {
    let [n, _, h, w] = f.dims();
    let scale = 1.0 / (c_tot as f64 * (h * w) as f64);
    let coeffs = bspline.coefficients(f_tilde);
    let residual = (bspline.interpolate(coeffs.clone(), phi.clone()) - f).mul_scalar(scale);
    let (dp0, dp1) = interpolate_position_derivative(bspline, coeffs, phi.clone());
    let along = |d: Tensor<4>| (d * residual.clone()).sum_dim(1).reshape([n, 1, h, w]);
    let grad_phi = Tensor::cat(vec![along(dp0), along(dp1)], 1);
    let adjoint = interpolate_adjoint(bspline, residual.clone(), phi);
    DataTermGradient {
        f: residual.clone().neg(),
        f_tilde: coefficients_adjoint(bspline, adjoint),
        phi: grad_phi,
    }
}

/// Hand-derived gradient of `E`.
#[derive(Clone, Debug)]
pub struct EnergyGradient {
    /// `∂E/∂f_k` for the free frames `k = 1..K−1`, `[K−1, C, H, W]` (`a` held fixed).
    pub f_interior: Tensor<4>,
    /// `∂E/∂φ_k`, `k = 1..K`, `[K, 2, H, W]`.
    pub phi: Tensor<4>,
}

/// The hand-derived gradient of [`PathEnergy::value`] with respect to the free frames and
/// the deformations, `a` held fixed.
pub fn path_energy_gradient(
    energy: &PathEnergy,
    f: Tensor<4>,
    phi: Tensor<4>,
    a: Tensor<3>,
) -> EnergyGradient {
    let [k, _, _, _] = phi.dims();
    let p = energy.params();
    let scale = k as f64;
    let d = data_term_gradient(
        energy.bspline(),
        f.clone().narrow(0, 0, k),
        f.narrow(0, 1, k),
        phi.clone(),
        energy.channels(),
    );
    let r = regularizer_gradient(phi, a, p.lambda, p.mu);
    let grad_phi = (r + d.phi.mul_scalar(1.0 / p.delta)).mul_scalar(scale);
    // f_k is the warped frame of D_k and the fixed frame of D_{k+1}.
    let f_interior = if k > 1 {
        (d.f_tilde.narrow(0, 0, k - 1) + d.f.narrow(0, 1, k - 1)).mul_scalar(scale / p.delta)
    } else {
        let [_, c, h, w] = d.f.dims();
        Tensor::zeros([0, c, h, w], (&d.f.device(), d.f.dtype()))
    };
    EnergyGradient {
        f_interior,
        phi: grad_phi,
    }
}
