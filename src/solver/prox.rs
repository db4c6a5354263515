//! The linearised data term of a deformation step and its closed-form pointwise prox
//! (SPEC §6).

use burn::tensor::Tensor;

use crate::model::deformation::with_identity_boundary;
use crate::model::grid::Grid;
use crate::model::slopes;
use crate::model::sobel::Sobel;
use crate::model::warp::BSpline;
use crate::solver::prox_op;

/// The data term `D[f_{k−1}, f_k, φ]` linearised around `φ̃`, reduced to what the prox
/// needs at each pixel: with `r_c = T[f_{k,c}, φ̃] − f_{k−1,c}` and
/// `Λ_c = ½ (∇T[f_{k,c}, φ̃] + ∇f_{k−1,c})` (Sobel, pixel units),
/// the matrix `Σ_c Λ_c Λ_cᵀ` and the vector `Σ_c Λ_c (Λ_cᵀ φ̃ − r_c)`.
///
/// Neither depends on the trial `L`, so a backtracking sequence builds this once and calls
/// [`prox`](Self::prox) per trial.
#[derive(Clone, Debug)]
pub struct LinearisedData {
    grid: Grid,
    kappa: f64,
    /// `Σ_c Λ_c Λ_cᵀ` entries `(0,0)`, `(0,1)`, `(1,1)`, `[1, 1, H, W]` each.
    a00: Tensor<4>,
    a01: Tensor<4>,
    a11: Tensor<4>,
    /// `Σ_c Λ_c (Λ_cᵀ φ̃ − r_c)`, `[1, 2, H, W]`.
    v: Tensor<4>,
    /// The five planes above as the fused kernel left them, `[1, 5, H, W]` (flex): the
    /// fused trial ([`super::prox_op`]) reads them.
    moments: Option<Tensor<4>>,
}

/// Items `items` of a stacked tensor (dimension 0), in that order; the tensor itself when
/// `items` is all of it in order.
pub(crate) fn pick<const D: usize>(t: &Tensor<D>, items: &[usize]) -> Tensor<D> {
    if items.len() == t.dims()[0] && items.iter().enumerate().all(|(j, &i)| i == j) {
        return t.clone();
    }
    Tensor::cat(
        items.iter().map(|&i| t.clone().narrow(0, i, 1)).collect(),
        0,
    )
}

/// The residual and slopes of the linearisation, for inspection and tests.
#[derive(Clone, Debug)]
pub struct Linearisation {
    /// `r_c = T[f_{k,c}, φ̃] − f_{k−1,c}`, `[1, C, H, W]`.
    pub residual: Tensor<4>,
    /// `Λ_c`, `[1, C, 2, H, W]`.
    pub slopes: Tensor<5>,
}

/// `r` and `Λ` of the linearisation around `phi_tilde` (SPEC §6).
///
/// # Shapes
/// - `coeffs_k`: `P f_k`, `[1, C, H, W]`; `f_km1`: `[1, C, H, W]`; `phi_tilde`: `[1, 2, H, W]`
pub fn linearise(
    bspline: &BSpline,
    sobel: &Sobel,
    coeffs_k: Tensor<4>,
    f_km1: Tensor<4>,
    phi_tilde: Tensor<4>,
) -> Linearisation {
    let warped = bspline.interpolate(coeffs_k, phi_tilde);
    // ½ (∇T + ∇f_{k−1}) = ½ ∇(T + f_{k−1}): the Sobel operator is linear.
    let slopes = sobel
        .gradient(warped.clone() + f_km1.clone())
        .mul_scalar(0.5);
    Linearisation {
        residual: warped - f_km1,
        slopes,
    }
}

impl LinearisedData {
    /// Reduces a [`Linearisation`] around `phi_tilde` for the prox with weight
    /// `κ = K / (δ · C_tot · H · W)`.
    ///
    /// # Shapes
    /// - `phi_tilde`: `[1, 2, H, W]`
    pub fn new(grid: &Grid, lin: Linearisation, phi_tilde: Tensor<4>, kappa: f64) -> Self {
        let [n, c, _, h, w] = lin.slopes.dims();
        let l0 = lin.slopes.clone().narrow(2, 0, 1).reshape([n, c, h, w]);
        let l1 = lin.slopes.narrow(2, 1, 1).reshape([n, c, h, w]);
        let p0 = phi_tilde.clone().narrow(1, 0, 1);
        let p1 = phi_tilde.narrow(1, 1, 1);
        let q = l0.clone() * p0 + l1.clone() * p1 - lin.residual;
        let channel_sum = |t: Tensor<4>| t.sum_dim(1);
        Self {
            grid: grid.clone(),
            kappa,
            a00: channel_sum(l0.clone().square()),
            a01: channel_sum(l0.clone() * l1.clone()),
            a11: channel_sum(l1.clone().square()),
            v: Tensor::cat(vec![channel_sum(l0 * q.clone()), channel_sum(l1 * q)], 1),
            moments: None,
        }
    }

    /// The linearisation around `phi_tilde` reduced for the prox with weight
    /// `κ = K / (δ · C_tot · H · W)`: [`linearise`] then [`new`](Self::new), or on a grid
    /// with the fused kernel, the same moments in one pass ([`crate::model::slopes`]).
    ///
    /// `warped`, where the caller has it, is `T[f_k, φ̃]` (the values
    /// `bspline.interpolate(coeffs_k, phi_tilde)` gives, bit for bit): the fused kernel
    /// reads it instead of evaluating the warp again. A restart of SPEC §6's safeguard
    /// linearises at `φ_k`, whose warp the safeguard has just evaluated for `e_k(φ_k)`.
    ///
    /// # Shapes
    /// - `coeffs_k`: `P f_k`, `[N, C, H, W]`; `f_km1`: `[N, C, H, W]`; `phi_tilde`:
    ///   `[N, 2, H, W]`; `warped`: `[N, C, H, W]`
    #[allow(clippy::too_many_arguments)]
    pub fn around(
        grid: &Grid,
        bspline: &BSpline,
        sobel: &Sobel,
        coeffs_k: Tensor<4>,
        f_km1: Tensor<4>,
        phi_tilde: Tensor<4>,
        kappa: f64,
        warped: Option<Tensor<4>>,
    ) -> Self {
        if !grid.fused_linearisation() {
            let lin = linearise(bspline, sobel, coeffs_k, f_km1, phi_tilde.clone());
            return Self::new(grid, lin, phi_tilde, kappa);
        }
        let warped = warped.unwrap_or_else(|| bspline.interpolate(coeffs_k, phi_tilde.clone()));
        Self::from_moments(grid, slopes::moments(warped, f_km1, phi_tilde), kappa)
    }

    /// The linearisations of the items `items` of a batch, in that order.
    pub fn select(&self, items: &[usize]) -> Self {
        match &self.moments {
            // The planes are views of the moments: one copy, not two.
            Some(m) => Self::from_moments(&self.grid, pick(m, items), self.kappa),
            None => Self {
                grid: self.grid.clone(),
                kappa: self.kappa,
                a00: pick(&self.a00, items),
                a01: pick(&self.a01, items),
                a11: pick(&self.a11, items),
                v: pick(&self.v, items),
                moments: None,
            },
        }
    }

    /// The linearisation held by the fused kernel's moments `[N, 5, H, W]`.
    fn from_moments(grid: &Grid, m: Tensor<4>, kappa: f64) -> Self {
        Self {
            grid: grid.clone(),
            kappa,
            a00: m.clone().narrow(1, 0, 1),
            a01: m.clone().narrow(1, 1, 1),
            a11: m.clone().narrow(1, 2, 1),
            v: m.clone().narrow(1, 3, 2),
            moments: Some(m),
        }
    }

    /// The candidate of the trial `L` around `point` (`φ̃`) with the gradient `g` of the
    /// smooth part: [`prox`](Self::prox) at `y = φ̃ − g/L`, in one fused pass where the
    /// linearisation was fused ([`super::prox_op`]; the same values).
    ///
    /// # Shapes
    /// - `point`, `gradient`, output: `[1, 2, H, W]`
    pub fn candidate(&self, point: Tensor<4>, gradient: Tensor<4>, l: f64) -> Tensor<4> {
        match &self.moments {
            Some(m) => prox_op::prox_step(point, gradient, m.clone(), 1.0 / l, self.kappa / l),
            None => self.composed_candidate(point, gradient, l),
        }
    }

    /// [`candidate`](Self::candidate) composed from tensor ops: what every backend without
    /// the fused moments runs, and what the fused op is compared with.
    pub fn composed_candidate(&self, point: Tensor<4>, gradient: Tensor<4>, l: f64) -> Tensor<4> {
        self.prox(point - gradient.mul_scalar(1.0 / l), l)
    }

    /// The prox for the trial `L` at `y = φ̃ − g / L`:
    /// `(L·I + κ Σ Λ Λᵀ)⁻¹ (L·y + κ Σ Λ (Λᵀ φ̃ − r))` at every pixel (a 2 × 2 solve), then
    /// `Id` on the boundary.
    ///
    /// # Shapes
    /// - `y`: `[1, 2, H, W]`
    /// - output: `[1, 2, H, W]`
    pub fn prox(&self, y: Tensor<4>, l: f64) -> Tensor<4> {
        let t = self.kappa / l;
        self.solve(y, |m| m.mul_scalar(t))
    }

    /// [`prox`](Self::prox) for a batch of linearisations, each with its own trial `L`.
    ///
    /// # Shapes
    /// - `y`: `[N, 2, H, W]`, `l`: `N` values
    /// - output: `[N, 2, H, W]`
    pub fn prox_each(&self, y: Tensor<4>, l: &[f64]) -> Tensor<4> {
        let t: Tensor<4> = self.grid.tensor(
            l.iter().map(|l| self.kappa / l).collect(),
            [l.len(), 1, 1, 1],
        );
        self.solve(y, |m| m * t.clone())
    }

    /// The pointwise 2 × 2 solve with `t = κ/L` applied by `scale`.
    fn solve(&self, y: Tensor<4>, scale: impl Fn(Tensor<4>) -> Tensor<4>) -> Tensor<4> {
        // Divided through by L, the system is (I + t Σ Λ Λᵀ) x = y + t Σ Λ (Λᵀ φ̃ − r) with
        // t = κ / L: the same solution, but no L² that overflows float32 when backtracking
        // has doubled L many times.
        let m00 = scale(self.a00.clone()).add_scalar(1.0);
        let m01 = scale(self.a01.clone());
        let m11 = scale(self.a11.clone()).add_scalar(1.0);
        let b = y + scale(self.v.clone());
        let b0 = b.clone().narrow(1, 0, 1);
        let b1 = b.narrow(1, 1, 1);
        // Σ Λ Λᵀ ⪰ 0, so the determinant is at least 1.
        let det = m00.clone() * m11.clone() - m01.clone().square();
        let x0 = (m11 * b0.clone() - m01.clone() * b1.clone()) / det.clone();
        let x1 = (m00 * b1 - m01 * b0) / det;
        with_identity_boundary(&self.grid, Tensor::cat(vec![x0, x1], 1))
    }
}
