//! SPEC §11's initial path of the coarsest level when the user steers it: a global map `G`
//! shared equally among the steps, landmarks met along their straight lines, and interior
//! frames carried along these deformations instead of the plain cross-fade.
//!
//! Step `k` starts from
//!
//! ```text
//! φ_k(x) = x + χ(x) · (G_{1/K}(x) − x + ρ_k(x)),
//! ```
//!
//! - `χ(x) = σ(d_row(x)/w) · σ(d_col(x)/w)`, `d` the distance to the nearest boundary row
//!   (column) in pixels, `σ(t) = 3t² − 2t³` on `[0, 1]` (1 beyond): 1 inside, 0 on `∂Ω`,
//!   continuously differentiable. Its width `w` is `min(H, W)/8` pixels, widened to three
//!   times the step's largest unwindowed displacement `D` (so that the window's slope,
//!   at most `1.5/w`, cannot fold the step: `1.5 D/w ≤ 1/2`), within `[2, (min(H, W) − 1)/2]`;
//! - `ρ_k` the Gaussian radial-basis interpolant (width `min(H, W)/5` pixels) of what the
//!   landmarks still need at the points `p_i^{k−1}`: `p_i^k − G_{1/K}(p_i^{k−1})`, so that
//!   where `χ = 1` the initial path carries each landmark exactly along its straight line
//!   and `E_lm` starts at 0 (0 without landmarks).
//!
//! A `φ_k` that is not admissible has its displacement halved until it is (at most 10
//! times, then `Id`). The interior frames are A carried forward and B carried backward
//! along the deformations, blended `1 − k/K : k/K`: `b_K = f_B`, `b_{k−1} = T[b_k, φ_k]`;
//! `a_0 = f_A`, `a_k = T[a_{k−1}, φ_k^{−1}]` with the inverse by the fixed-point iteration
//! `ψ ← y − d_k(ψ)` (`d_k` the displacement, a contraction for an admissible step);
//! `f_k = (1 − k/K) a_k + (k/K) b_k`.

use burn::tensor::Tensor;

use crate::error::Result;
use crate::model::alignment::GlobalMap;
use crate::model::deformation::admissible_each;
use crate::model::energy::landmarks::Landmarks;
use crate::model::grid::Grid;
use crate::model::layout::FeatureLayout;
use crate::model::warp::BSpline;
use crate::solver::ipalm::{LevelState, initial_lipschitz};
use crate::solver::observer::Initialisation;

/// The most halvings of a step's displacement before it starts at `Id`.
pub const MAX_HALVINGS: u32 = 10;

/// The initial state of the coarsest level on `grid` for the map `map` and the landmarks
/// (both on this grid): the deformations, the frames consistent with them, and how each
/// step was made admissible.
///
/// # Shapes
/// - `f_a`, `f_b`: `[1, C_tot, H, W]`
///
/// # Errors
///
/// If `G` has no principal `K`-th root (a half turn).
#[allow(clippy::too_many_arguments)]
pub(crate) fn initial_state(
    grid: &Grid,
    layout: &FeatureLayout,
    f_a: Tensor<4>,
    f_b: Tensor<4>,
    steps: usize,
    delta: f64,
    map: &GlobalMap,
    landmarks: Option<&Landmarks>,
) -> Result<(LevelState, Initialisation)> {
    let field = InitialField::new(grid.height(), grid.width(), map, steps)?;
    let (h, w) = (grid.height(), grid.width());
    let mut phi = Vec::with_capacity(steps);
    let mut inverse = Vec::with_capacity(steps);
    let mut halvings = Vec::with_capacity(steps);
    for k in 1..=steps {
        let rbf = landmarks.map(|l| field.correction(l, k));
        let step = field.step(rbf);
        let full = step.displacement();
        let mut scale = 1.0;
        let mut halved = 0;
        let accepted = loop {
            let candidate = grid.tensor(step.positions(&full, scale), [1, 2, h, w]);
            if admissible_each(grid, candidate.clone())[0] {
                break Some(candidate);
            }
            if halved == MAX_HALVINGS {
                break None;
            }
            halved += 1;
            scale *= 0.5;
        };
        match accepted {
            Some(candidate) => {
                phi.push(candidate);
                inverse.push(grid.tensor(step.inverse(&full, scale), [1, 2, h, w]));
                halvings.push(halved);
            }
            None => {
                phi.push(grid.identity(1));
                inverse.push(grid.identity(1));
                halvings.push(MAX_HALVINGS + 1);
            }
        }
    }
    let spline = BSpline::new(grid);
    let mut backward = vec![f_b.clone(); steps + 1];
    for k in (1..=steps).rev() {
        backward[k - 1] = spline.warp(backward[k].clone(), phi[k - 1].clone());
    }
    let mut forward = f_a.clone();
    let mut f = Vec::with_capacity(steps + 1);
    f.push(f_a);
    for k in 1..steps {
        forward = spline.warp(forward, inverse[k - 1].clone());
        let t = k as f64 / steps as f64;
        f.push(forward.clone().mul_scalar(1.0 - t) + backward[k].clone().mul_scalar(t));
    }
    f.push(f_b);
    let f = f.into_iter().map(|t| t.detach()).collect();
    let (l_phi, l_f) = initial_lipschitz(grid, layout, steps, delta);
    let state = LevelState::new(f, phi, l_phi, l_f)?;
    Ok((state, Initialisation { halvings }))
}

/// The parts of the initial displacement on one grid shared by the steps: the map's root.
struct InitialField {
    rows: usize,
    cols: usize,
    root: GlobalMap,
    steps: usize,
    rbf_width: f64,
}

/// One step's displacement: the root, the landmarks' correction and the window.
struct StepField<'a> {
    field: &'a InitialField,
    rbf: Option<Rbf>,
    window: f64,
}

/// A Gaussian radial-basis interpolant: `ρ(x) = Σ_j w_j exp(−|x − c_j|²/(2σ²))`.
struct Rbf {
    centres: Vec<[f64; 2]>,
    weights: Vec<[f64; 2]>,
    width: f64,
}

impl Rbf {
    /// The interpolant of `values` at `centres` (repeated centres kept once), with a ridge of
    /// 1e-4 so that points that meet mid-path (crossing trajectories) give a large but
    /// finite correction, which the halving then tames.
    fn new(centres: &[[f64; 2]], values: &[[f64; 2]], width: f64) -> Self {
        let mut kept: Vec<([f64; 2], [f64; 2])> = Vec::with_capacity(centres.len());
        for (&c, &v) in centres.iter().zip(values) {
            if !kept.iter().any(|(k, _)| *k == c) {
                kept.push((c, v));
            }
        }
        let n = kept.len();
        let kernel = |a: [f64; 2], b: [f64; 2]| {
            (-((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2)) / (2.0 * width * width)).exp()
        };
        // [K + λI | v] by Gaussian elimination with partial pivoting (N is small).
        let mut m: Vec<Vec<f64>> = (0..n)
            .map(|i| {
                let mut row: Vec<f64> = (0..n).map(|j| kernel(kept[i].0, kept[j].0)).collect();
                row[i] += 1e-4;
                row.extend_from_slice(&kept[i].1);
                row
            })
            .collect();
        for col in 0..n {
            let pivot = (col..n)
                .max_by(|&a, &b| m[a][col].abs().total_cmp(&m[b][col].abs()))
                .unwrap_or(col);
            m.swap(col, pivot);
            for row in 0..n {
                if row != col {
                    let factor = m[row][col] / m[col][col];
                    for j in col..n + 2 {
                        m[row][j] -= factor * m[col][j];
                    }
                }
            }
        }
        let weights = (0..n)
            .map(|i| [m[i][n] / m[i][i], m[i][n + 1] / m[i][i]])
            .collect();
        Self {
            centres: kept.into_iter().map(|(c, _)| c).collect(),
            weights,
            width,
        }
    }

    fn at(&self, x: [f64; 2]) -> [f64; 2] {
        let mut out = [0.0, 0.0];
        for (c, wt) in self.centres.iter().zip(&self.weights) {
            let g = (-((x[0] - c[0]).powi(2) + (x[1] - c[1]).powi(2))
                / (2.0 * self.width * self.width))
                .exp();
            out[0] += wt[0] * g;
            out[1] += wt[1] * g;
        }
        out
    }
}

impl InitialField {
    fn new(rows: usize, cols: usize, map: &GlobalMap, steps: usize) -> Result<Self> {
        let short = rows.min(cols) as f64;
        Ok(Self {
            rows,
            cols,
            root: map.root(steps)?,
            steps,
            rbf_width: short / 5.0,
        })
    }

    /// The step with the correction `rbf`, its window's width chosen from its largest
    /// unwindowed displacement (see the module's documentation).
    fn step(&self, rbf: Option<Rbf>) -> StepField<'_> {
        let mut largest: f64 = 0.0;
        for r in 0..self.rows {
            for c in 0..self.cols {
                let x = [r as f64, c as f64];
                let moved = self.root.apply(x);
                let extra = rbf.as_ref().map_or([0.0, 0.0], |f| f.at(x));
                largest =
                    largest.max((moved[0] - x[0] + extra[0]).hypot(moved[1] - x[1] + extra[1]));
            }
        }
        let short = self.rows.min(self.cols) as f64;
        let window = (short / 8.0)
            .max(3.0 * largest)
            .min((short - 1.0) / 2.0)
            .max(2.0);
        StepField {
            field: self,
            rbf,
            window,
        }
    }

    /// `ρ_k` for the landmarks' step `k`.
    fn correction(&self, landmarks: &Landmarks, k: usize) -> Rbf {
        let from = landmarks.at_step(k - 1, self.steps);
        let to = landmarks.at_step(k, self.steps);
        let values: Vec<[f64; 2]> = from
            .iter()
            .zip(&to)
            .map(|(&p, q)| {
                let moved = self.root.apply(p);
                [q[0] - moved[0], q[1] - moved[1]]
            })
            .collect();
        Rbf::new(&from, &values, self.rbf_width)
    }
}

impl StepField<'_> {
    /// `χ(x)`: 1 inside, 0 on the boundary rows and columns.
    fn window(&self, [r, c]: [f64; 2]) -> f64 {
        let ramp = |d: f64| {
            let t = (d / self.window).clamp(0.0, 1.0);
            t * t * (3.0 - 2.0 * t)
        };
        let (hr, hc) = ((self.field.rows - 1) as f64, (self.field.cols - 1) as f64);
        ramp(r.min(hr - r)) * ramp(c.min(hc - c))
    }

    /// The displacement `d(x) = χ(x) (G_{1/K}(x) − x + ρ(x))` at any point.
    fn displacement_at(&self, x: [f64; 2]) -> [f64; 2] {
        let chi = self.window(x);
        if chi == 0.0 {
            return [0.0, 0.0];
        }
        let moved = self.field.root.apply(x);
        let extra = self.rbf.as_ref().map_or([0.0, 0.0], |r| r.at(x));
        [
            chi * (moved[0] - x[0] + extra[0]),
            chi * (moved[1] - x[1] + extra[1]),
        ]
    }

    /// The displacement on the grid, planes `[2, H, W]` flattened.
    fn displacement(&self) -> Vec<f64> {
        let (rows, cols) = (self.field.rows, self.field.cols);
        let n = rows * cols;
        let mut out = vec![0.0; 2 * n];
        for r in 0..rows {
            for c in 0..cols {
                let d = self.displacement_at([r as f64, c as f64]);
                out[r * cols + c] = d[0];
                out[n + r * cols + c] = d[1];
            }
        }
        out
    }

    /// `x + scale · d(x)` on the grid.
    fn positions(&self, displacement: &[f64], scale: f64) -> Vec<f64> {
        let (rows, cols) = (self.field.rows, self.field.cols);
        let n = rows * cols;
        let mut out = displacement.iter().map(|d| scale * d).collect::<Vec<_>>();
        for r in 0..rows {
            for c in 0..cols {
                out[r * cols + c] += r as f64;
                out[n + r * cols + c] += c as f64;
            }
        }
        out
    }

    /// `φ^{−1}(y)` on the grid for `φ = Id + scale · d`, by `ψ ← y − scale · d(ψ)`
    /// (clamped into the domain), 30 rounds.
    fn inverse(&self, displacement: &[f64], scale: f64) -> Vec<f64> {
        let (rows, cols) = (self.field.rows, self.field.cols);
        let n = rows * cols;
        let (hr, hc) = ((rows - 1) as f64, (cols - 1) as f64);
        let mut out = vec![0.0; 2 * n];
        for r in 0..rows {
            for c in 0..cols {
                let i = r * cols + c;
                let y = [r as f64, c as f64];
                let mut psi = [
                    y[0] - scale * displacement[i],
                    y[1] - scale * displacement[n + i],
                ];
                for _ in 0..30 {
                    let d = self.displacement_at(psi);
                    psi = [
                        (y[0] - scale * d[0]).clamp(0.0, hr),
                        (y[1] - scale * d[1]).clamp(0.0, hc),
                    ];
                }
                out[i] = psi[0];
                out[n + i] = psi[1];
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn field(map: GlobalMap) -> InitialField {
        InitialField::new(24, 32, &map, 6).unwrap()
    }

    #[test]
    fn the_window_is_zero_on_the_boundary_and_one_inside() {
        let field = field(GlobalMap::identity());
        let f = field.step(None);
        for c in 0..32 {
            assert_eq!(f.window([0.0, c as f64]), 0.0);
            assert_eq!(f.window([23.0, c as f64]), 0.0);
        }
        assert_eq!(f.window([12.0, 16.0]), 1.0);
        assert!(f.window([1.0, 16.0]) > 0.0 && f.window([1.0, 16.0]) < 1.0);
    }

    /// The inverse composes with the step back to the identity inside the window.
    #[test]
    fn the_fixed_point_inverse_inverts_the_step() {
        let map = GlobalMap::similarity([11.5, 15.5], 20.0, 1.2, [4.0, -3.0]);
        let field = field(map);
        let f = field.step(None);
        let d = f.displacement();
        let inv = f.inverse(&d, 1.0);
        let n = 24 * 32;
        for r in 3..21 {
            for c in 3..29 {
                let i = r * 32 + c;
                let psi = [inv[i], inv[n + i]];
                let back = f.displacement_at(psi);
                let y = [psi[0] + back[0], psi[1] + back[1]];
                assert!(
                    (y[0] - r as f64).abs() < 1e-9 && (y[1] - c as f64).abs() < 1e-9,
                    "({r}, {c}) -> {y:?}"
                );
            }
        }
    }

    /// With landmarks, each step carries every landmark from `p_i^{k−1}` to `p_i^k`.
    #[test]
    fn the_correction_carries_the_landmarks_along_their_lines() {
        let map = GlobalMap::similarity([11.5, 15.5], 5.0, 1.0, [1.0, 0.0]);
        let field = field(map);
        let landmarks = Landmarks::new(
            vec![[8.0, 9.0], [15.0, 20.0], [12.0, 25.0]],
            vec![[10.0, 12.0], [14.0, 17.0], [9.0, 24.0]],
            (24, 32),
        )
        .unwrap();
        for k in 1..=6 {
            let f = field.step(Some(field.correction(&landmarks, k)));
            for (p, q) in landmarks
                .at_step(k - 1, 6)
                .iter()
                .zip(landmarks.at_step(k, 6))
            {
                let d = f.displacement_at(*p);
                let moved = [p[0] + d[0], p[1] + d[1]];
                // The ridge of 1e-4 leaves a residual of that order.
                assert!(
                    (moved[0] - q[0]).abs() < 1e-3 && (moved[1] - q[1]).abs() < 1e-3,
                    "k={k}: {moved:?} vs {q:?}"
                );
            }
        }
    }
}
