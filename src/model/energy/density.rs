//! The hyperelastic energy density `W(J)` (SPEC §2).

use crate::model::deformation::Jacobian;

/// `W(J) = λ/2 (exp((log det J)²) − 1) + μ |sym J − I|²_F` where `det J > 0`, `+∞` elsewhere.
///
/// Where `exp((log d)²)` overflows (in float32 for `d ≲ 8e-5` or `d ≳ 1e4`) the result is
/// `+∞` too, which the solver treats like a fold. At non-positive determinants the log is
/// taken of a clamped value and then replaced, so autodiff sees no NaN (its gradient there
/// is 0; the energy is infinite and never differentiated by the solver).
///
/// # Shapes
/// - `j`: four `[N, H, W]` maps
/// - output: `[N, H, W]`
pub fn density(j: &Jacobian, lambda: f64, mu: f64) -> burn::tensor::Tensor<3> {
    let det = j.det();
    let folded = det.clone().lower_equal_elem(0.0);
    let log_det = det.clamp_min(f64::from(f32::MIN_POSITIVE)).log();
    let volume = log_det
        .square()
        .exp()
        .sub_scalar(1.0)
        .mul_scalar(lambda / 2.0);
    let strain = (j.j00.clone().sub_scalar(1.0).square()
        + j.j11.clone().sub_scalar(1.0).square()
        + (j.j01.clone() + j.j10.clone()).square().mul_scalar(0.5))
    .mul_scalar(mu);
    (volume + strain).mask_fill(folded, f64::INFINITY)
}
