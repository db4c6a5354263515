//! The data term `D[f, f̃, φ] = 1/(2 C_tot) Σ_c mean((T[f̃_c, φ] − f_c)²)` (SPEC §5).

use burn::tensor::Tensor;

use crate::model::energy::distance_op::{distance2_each, distance2_each_given};
use crate::model::warp::BSpline;

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
/// The sum of squares is the fused [`distance2_each`] (one pass for the value, one per
/// tracked input for the gradient, split over the cores on flex), differentiable in both.
///
/// # Shapes
/// - `warped`: `[N, C, H, W]`, `f`: `[N, C, H, W]`
/// - output: `[N]`
pub fn data_term_from_warped(warped: Tensor<4>, f: Tensor<4>, c_tot: usize) -> Tensor<1> {
    let scale = data_scale(&warped, c_tot);
    distance2_each(warped, f).mul_scalar(scale)
}

/// [`data_term_from_warped`] whose squared residual norms `Σ (T[f̃, φ] − f)²` of each item
/// the caller has summed already (a feature step's decision sums): the value is theirs,
/// scaled, with no pass of its own ([`distance2_each_given`]); the gradient is the same.
///
/// # Shapes
/// - `warped`: `[N, C, H, W]`, `f`: `[N, C, H, W]`, `residual_norm2`: `[N]`
/// - output: `[N]`
pub fn data_term_given(
    warped: Tensor<4>,
    f: Tensor<4>,
    c_tot: usize,
    residual_norm2: Tensor<1>,
) -> Tensor<1> {
    let scale = data_scale(&warped, c_tot);
    distance2_each_given(warped, f, residual_norm2).mul_scalar(scale)
}

/// `1 / (2·C_tot·H·W)`, the data term's weight of a squared residual norm (SPEC §5).
fn data_scale(warped: &Tensor<4>, c_tot: usize) -> f64 {
    let [_, _, h, w] = warped.dims();
    1.0 / (2.0 * c_tot as f64 * (h * w) as f64)
}
