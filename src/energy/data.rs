//! The data term `D[f, f̃, φ] = 1/(2 C_tot) Σ_c mean((T[f̃_c, φ] − f_c)²)` (SPEC §5).

use burn::tensor::Tensor;

use crate::warp::BSpline;

/// `D[f_n, f̃_n, φ_n]` for each triple of the batch.
///
/// `c_tot` is the channel count of the whole feature vector: in the deep model a block of
/// channels is still divided by it (SPEC §6), so it is not read off `f`.
///
/// # Shapes
/// - `f`: `[N, C, H, W]`, `f_tilde`: `[N, C, H, W]`, `phi`: `[N, 2, H, W]`
/// - output: `[N]`
pub fn data_term(
    bspline: &BSpline,
    f: Tensor<4>,
    f_tilde: Tensor<4>,
    phi: Tensor<4>,
    c_tot: usize,
) -> Tensor<1> {
    data_term_from_coefficients(bspline, f, bspline.coefficients(f_tilde), phi, c_tot)
}

/// [`data_term`] with the warped frame given by its spline coefficients `P f̃`, which a
/// sweep computes once per frame and reuses.
///
/// # Shapes
/// - `f`: `[N, C, H, W]`, `coeffs_tilde`: `[N, C, H, W]`, `phi`: `[N, 2, H, W]`
/// - output: `[N]`
pub fn data_term_from_coefficients(
    bspline: &BSpline,
    f: Tensor<4>,
    coeffs_tilde: Tensor<4>,
    phi: Tensor<4>,
    c_tot: usize,
) -> Tensor<1> {
    data_term_from_warped(bspline.interpolate(coeffs_tilde, phi), f, c_tot)
}

/// [`data_term`] with the warped frame `T[f̃, φ]` given: a feature step keeps `φ` and `f̃`
/// fixed for a whole backtracking search.
///
/// # Shapes
/// - `warped`: `[N, C, H, W]`, `f`: `[N, C, H, W]`
/// - output: `[N]`
pub fn data_term_from_warped(warped: Tensor<4>, f: Tensor<4>, c_tot: usize) -> Tensor<1> {
    data_term_from_residual(warped - f, c_tot)
}

/// [`data_term`] from the residual `r = T[f̃, φ] − f`.
///
/// # Shapes
/// - `residual`: `[N, C, H, W]`
/// - output: `[N]`
pub fn data_term_from_residual(residual: Tensor<4>, c_tot: usize) -> Tensor<1> {
    let [n, c, h, w] = residual.dims();
    let scale = 1.0 / (2.0 * c_tot as f64 * (h * w) as f64);
    residual
        .square()
        .reshape([n, c * h * w])
        .sum_dim(1)
        .reshape([n])
        .mul_scalar(scale)
}

/// Hand-derived gradients of [`data_term`] (for the gradient checks).
#[derive(Clone, Debug)]
pub struct DataTermGradient {
    /// `∂D/∂f = −r / (C_tot H W)`, `[N, C, H, W]`.
    pub f: Tensor<4>,
    /// `∂D/∂f̃ = Pᵀ Bᵀ_φ r / (C_tot H W)`, `[N, C, H, W]` (adjoint of the warp).
    pub f_tilde: Tensor<4>,
    /// `∂D/∂φ = Σ_c r_c ∇_p T[f̃_c](φ) / (C_tot H W)` with `β'`, `[N, 2, H, W]`.
    pub phi: Tensor<4>,
}

/// The hand-derived gradient of [`data_term`] with respect to all three arguments, with
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
    let (dp0, dp1) = bspline.interpolate_position_derivative(coeffs, phi.clone());
    let along = |d: Tensor<4>| (d * residual.clone()).sum_dim(1).reshape([n, 1, h, w]);
    let grad_phi = Tensor::cat(vec![along(dp0), along(dp1)], 1);
    let adjoint = bspline.interpolate_adjoint(residual.clone(), phi);
    DataTermGradient {
        f: residual.clone().neg(),
        f_tilde: bspline.coefficients_adjoint(adjoint),
        phi: grad_phi,
    }
}
