//! SPEC §11's landmark term: `N` point pairs `(p_i, q_i)` that travel on straight lines,
//! `p_i^k = (1 − k/K) p_i + (k/K) q_i`, and the energy
//!
//! ```text
//! E_lm = K · Σ_{k=1..K} γ/(2N) · Σ_i ‖φ_k(p_i^{k−1}) − p_i^k‖² / s²,   s = max(H, W) − 1,
//! ```
//!
//! with `φ_k` between grid nodes by bilinear interpolation of its grid values. Evaluated as
//! differentiable tensor ops (one `gather` of the four nodes around every point and a
//! weighted sum), so its gradient comes from autodiff like the rest of the smooth part;
//! [`LandmarkTerm::gradient_host`] is the hand-derived sparse form the tests check it against.
//!
//! Points are `[row, col]` in pixel units of the grid they are given on. [`Landmarks`] holds
//! them on the working grid (validated); [`Landmarks::on_grid`] maps them to a level by
//! SPEC §7's align-corners rule.

use burn::tensor::{Int, Tensor, TensorData};

use crate::error::{Error, Result};
use crate::model::grid::Grid;

/// Landmark pairs on one grid: `p_i` in A, `q_i` the same point in B, `[row, col]` each.
#[derive(Clone, Debug, PartialEq)]
pub struct Landmarks {
    a: Vec<[f64; 2]>,
    b: Vec<[f64; 2]>,
    size: (usize, usize),
}

impl Landmarks {
    /// The pairs `(a[i], b[i])` on a grid of `height × width` pixels.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] for no pair, different counts, a coordinate that is not
    /// finite, a point outside the grid or within one pixel of its border (`φ = Id` there:
    /// such a point cannot be moved, SPEC §11), or one point of A given two partners in B.
    pub fn new(
        a: Vec<[f64; 2]>,
        b: Vec<[f64; 2]>,
        (height, width): (usize, usize),
    ) -> Result<Self> {
        if a.is_empty() {
            return Err(Error::invalid("landmarks", 0, "at least 1 pair"));
        }
        if a.len() != b.len() {
            return Err(Error::invalid(
                "landmarks",
                format!("{} points in A and {} in B", a.len(), b.len()),
                "one point in B for each point in A",
            ));
        }
        let (rows, cols) = (height as f64 - 2.0, width as f64 - 2.0);
        for (side, points) in [("A", &a), ("B", &b)] {
            for (i, &[r, c]) in points.iter().enumerate() {
                if !(r.is_finite() && c.is_finite()) {
                    return Err(Error::invalid(
                        "landmarks",
                        format!("point {} of {side} = ({r}, {c}) (row, col)", i + 1),
                        "finite coordinates",
                    ));
                }
                if !((1.0..=rows).contains(&r) && (1.0..=cols).contains(&c)) {
                    return Err(Error::invalid(
                        "landmarks",
                        format!("point {} of {side} = ({r}, {c}) (row, col)", i + 1),
                        format!(
                            "rows in [1, {rows}] and columns in [1, {cols}]: at least one \
                             pixel inside the {height}x{width} grid, where the deformations \
                             can move it"
                        ),
                    ));
                }
            }
        }
        for i in 0..a.len() {
            for j in 0..i {
                if a[i] == a[j] && b[i] != b[j] {
                    return Err(Error::invalid(
                        "landmarks",
                        format!(
                            "points {} and {} of A are both ({}, {}) with different partners",
                            j + 1,
                            i + 1,
                            a[i][0],
                            a[i][1]
                        ),
                        "one partner in B for each point of A",
                    ));
                }
            }
        }
        Ok(Self {
            a,
            b,
            size: (height, width),
        })
    }

    /// The points of A and of B, `[row, col]` each, on the grid they were given on.
    pub fn pairs(&self) -> (&[[f64; 2]], &[[f64; 2]]) {
        (&self.a, &self.b)
    }

    /// The grid they were given on, `(H, W)`.
    pub fn size(&self) -> (usize, usize) {
        self.size
    }

    /// `N`.
    pub fn len(&self) -> usize {
        self.a.len()
    }

    /// Never: [`new`](Self::new) refuses an empty set.
    pub fn is_empty(&self) -> bool {
        self.a.is_empty()
    }

    /// The points `p_i^k` of step `k` of `steps` (`k = 0`: the points of A, `k = K`: those of
    /// B), on the straight lines between them.
    pub fn at_step(&self, k: usize, steps: usize) -> Vec<[f64; 2]> {
        let t = k as f64 / steps as f64;
        self.a
            .iter()
            .zip(&self.b)
            .map(|(p, q)| [(1.0 - t) * p[0] + t * q[0], (1.0 - t) * p[1] + t * q[1]])
            .collect()
    }

    /// Pairs `(p, q, p′, q′)` whose straight paths meet (at the same step, within 1/100 of
    /// a pixel): a diffeomorphic path cannot follow both exactly. Indices from 0.
    pub fn crossings(&self) -> Vec<(usize, usize)> {
        let mut out = Vec::new();
        for i in 0..self.len() {
            for j in 0..i {
                // p_i(t) − p_j(t) = d0 + t·(d1 − d0) with d0 = a_i − a_j, d1 = b_i − b_j:
                // its smallest length over t in [0, 1].
                let d0 = [self.a[i][0] - self.a[j][0], self.a[i][1] - self.a[j][1]];
                let d1 = [self.b[i][0] - self.b[j][0], self.b[i][1] - self.b[j][1]];
                let v = [d1[0] - d0[0], d1[1] - d0[1]];
                let vv = v[0] * v[0] + v[1] * v[1];
                let t = if vv > 0.0 {
                    (-(d0[0] * v[0] + d0[1] * v[1]) / vv).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                let gap = (d0[0] + t * v[0]).hypot(d0[1] + t * v[1]);
                if gap < 1e-2 {
                    out.push((j, i));
                }
            }
        }
        out
    }

    /// The same landmarks on a grid of `height × width`, by SPEC §7's align-corners rule:
    /// `row_ℓ = row · (H_ℓ − 1)/(H − 1)`, `col_ℓ = col · (W_ℓ − 1)/(W − 1)`. Not validated
    /// again: a point one pixel inside the working grid may lie closer to a coarse level's
    /// border, where the term still pulls it as far as the deformations can move it.
    pub fn on_grid(&self, (height, width): (usize, usize)) -> Self {
        let (h, w) = self.size;
        let scale = |p: &[f64; 2]| {
            [
                p[0] * (height as f64 - 1.0) / (h as f64 - 1.0),
                p[1] * (width as f64 - 1.0) / (w as f64 - 1.0),
            ]
        };
        Self {
            a: self.a.iter().map(scale).collect(),
            b: self.b.iter().map(scale).collect(),
            size: (height, width),
        }
    }
}

/// The bilinear stencil of a point on an `h × w` grid: the flat indices of its four nodes
/// and their weights, the point clamped into the domain.
fn bilinear(&[r, c]: &[f64; 2], h: usize, w: usize) -> ([usize; 4], [f64; 4]) {
    let axis = |x: f64, n: usize| {
        let x = x.clamp(0.0, (n - 1) as f64);
        let i = (x.floor() as usize).min(n.saturating_sub(2));
        (i, x - i as f64)
    };
    let ((i, t), (j, u)) = (axis(r, h), axis(c, w));
    (
        [
            i * w + j,
            i * w + j + 1,
            (i + 1) * w + j,
            (i + 1) * w + j + 1,
        ],
        [(1.0 - t) * (1.0 - u), (1.0 - t) * u, t * (1.0 - u), t * u],
    )
}

/// SPEC §11's landmark term on one level: for each step `k` the stencils of the points
/// `p_i^{k−1}` and the targets `p_i^k`.
#[derive(Clone, Debug)]
pub struct LandmarkTerm {
    steps: usize,
    count: usize,
    /// `K·γ/(2N·s²)`.
    scale: f64,
    /// Host copies, `[K][N]`: the stencils and the targets (for the hand-derived gradient).
    stencils: Vec<Vec<([usize; 4], [f64; 4])>>,
    targets: Vec<Vec<[f64; 2]>>,
    /// `[K, 2, 4N]` flat node indices (the same for both axes), `[K, 1, 4N]` weights and
    /// `[K, 2, N]` targets, on the grid's device.
    index: Tensor<3, Int>,
    weight: Tensor<3>,
    target: Tensor<3>,
}

impl LandmarkTerm {
    /// The term of `landmarks` (given on `grid`) with weight `gamma` for a path of `steps`
    /// steps.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] for a weight that is negative or not finite.
    pub fn new(grid: &Grid, landmarks: &Landmarks, steps: usize, gamma: f64) -> Result<Self> {
        if !(gamma.is_finite() && gamma >= 0.0) {
            return Err(Error::invalid(
                "landmark_weight",
                gamma,
                "finite and at least 0",
            ));
        }
        let (h, w) = (grid.height(), grid.width());
        let n = landmarks.len();
        let s = (h.max(w) - 1) as f64;
        let stencils: Vec<Vec<_>> = (1..=steps)
            .map(|k| {
                landmarks
                    .at_step(k - 1, steps)
                    .iter()
                    .map(|p| bilinear(p, h, w))
                    .collect()
            })
            .collect();
        let targets: Vec<Vec<[f64; 2]>> =
            (1..=steps).map(|k| landmarks.at_step(k, steps)).collect();
        let flat_index: Vec<i64> = stencils
            .iter()
            .flat_map(|step| {
                let row: Vec<i64> = step
                    .iter()
                    .flat_map(|(nodes, _)| nodes.map(|i| i as i64))
                    .collect();
                [row.clone(), row].concat()
            })
            .collect();
        let flat_weight: Vec<f64> = stencils
            .iter()
            .flat_map(|step| step.iter().flat_map(|(_, weights)| *weights))
            .collect();
        let flat_target: Vec<f64> = targets
            .iter()
            .flat_map(|step| (0..2).flat_map(move |axis| step.iter().map(move |p| p[axis])))
            .collect();
        Ok(Self {
            steps,
            count: n,
            scale: steps as f64 * gamma / (2.0 * n as f64 * s * s),
            index: Tensor::from_data(
                TensorData::new(flat_index, [steps, 2, 4 * n]),
                grid.device(),
            ),
            weight: grid.tensor(flat_weight, [steps, 1, 4 * n]),
            target: grid.tensor(flat_target, [steps, 2, n]),
            stencils,
            targets,
        })
    }

    /// `φ_k(p_i^{k−1}) − p_i^k` of the steps `k0 + 1 ..= k0 + n` (in pixels), differentiable
    /// in `phi`.
    ///
    /// # Shapes
    /// - `phi`: `[n, 2, H, W]`, `φ_{k0+1} … φ_{k0+n}`
    /// - output: `[n, 2, N]`
    fn residuals_from(&self, k0: usize, phi: Tensor<4>) -> Tensor<3> {
        let [n, _, h, w] = phi.dims();
        let index = self.index.clone().narrow(0, k0, n);
        let weight = self.weight.clone().narrow(0, k0, n);
        let at = phi.reshape([n, 2, h * w]).gather(2, index) * weight;
        let at: Tensor<3> = at
            .reshape([n, 2 * self.count, 4])
            .sum_dim(2)
            .reshape([n, 2, self.count]);
        at - self.target.clone().narrow(0, k0, n)
    }

    /// The residuals `φ_k(p_i^{k−1}) − p_i^k`, `k = 1..K`, in pixels.
    ///
    /// # Shapes
    /// - `phi`: `[K, 2, H, W]`
    /// - output: `[K, N, 2]` (step, point, row/col)
    pub fn residuals(&self, phi: Tensor<4>) -> Tensor<3> {
        self.residuals_from(0, phi).swap_dims(1, 2)
    }

    /// `E_lm` of the whole path, differentiable in `phi`.
    ///
    /// # Shapes
    /// - `phi`: `[K, 2, H, W]`
    /// - output: `[1]`
    pub fn energy(&self, phi: Tensor<4>) -> Tensor<1> {
        self.residuals_from(0, phi)
            .square()
            .sum()
            .mul_scalar(self.scale)
    }

    /// The part of `E_lm` that step `k` (`1..=K`) contributes, differentiable in `phi_k`:
    /// what joins the smooth part `S` of the deformation step of `k` (SPEC §11).
    ///
    /// # Shapes
    /// - `phi_k`: `[1, 2, H, W]`
    /// - output: `[1]`
    pub fn step_energy(&self, k: usize, phi_k: Tensor<4>) -> Tensor<1> {
        self.residuals_from(k - 1, phi_k)
            .square()
            .sum()
            .mul_scalar(self.scale)
    }

    /// The parts of `E_lm` that the steps `ks` (each in `1..=K`) contribute, one per step,
    /// differentiable in `phi`: what joins the smooth parts `S_k` of a stack of deformation
    /// steps (SPEC §11).
    ///
    /// # Shapes
    /// - `phi`: `[ks.len(), 2, H, W]`, `φ_k` for each `k` of `ks`
    /// - output: `[ks.len()]`
    pub fn step_energies(&self, ks: &[usize], phi: Tensor<4>) -> Tensor<1> {
        let n = ks.len();
        if let Some(run) = ks.windows(2).all(|p| p[1] == p[0] + 1).then_some(ks[0]) {
            return self.parts(self.residuals_from(run - 1, phi));
        }
        let [_, _, h, w] = phi.dims();
        let rows = |t: &Tensor<3>| ks.iter().map(|&k| t.clone().narrow(0, k - 1, 1)).collect();
        let index = Tensor::cat(
            ks.iter()
                .map(|&k| self.index.clone().narrow(0, k - 1, 1))
                .collect(),
            0,
        );
        let at = phi.reshape([n, 2, h * w]).gather(2, index) * Tensor::cat(rows(&self.weight), 0);
        let at: Tensor<3> = at
            .reshape([n, 2 * self.count, 4])
            .sum_dim(2)
            .reshape([n, 2, self.count]);
        self.parts(at - Tensor::cat(rows(&self.target), 0))
    }

    /// `scale · ‖r_k‖²` of each step of a stack of residuals `[n, 2, N]`: `[n]`.
    fn parts(&self, residuals: Tensor<3>) -> Tensor<1> {
        let n = residuals.dims()[0];
        residuals
            .square()
            .reshape([n, 2 * self.count])
            .sum_dim(1)
            .reshape([n])
            .mul_scalar(self.scale)
    }

    /// `K`.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// The hand-derived gradient `∂E_lm/∂φ` in float64 on the host, from the host values of
    /// `φ_1..φ_K` (`[K, 2, H, W]` row-major): `2·scale·r_i` spread onto each point's four
    /// nodes with its bilinear weights, zero elsewhere.
    pub fn gradient_host(&self, phi: &[f64], (h, w): (usize, usize)) -> Vec<f64> {
        let plane = h * w;
        let mut grad = vec![0.0; self.steps * 2 * plane];
        for (k, (stencils, targets)) in self.stencils.iter().zip(&self.targets).enumerate() {
            for ((nodes, weights), target) in stencils.iter().zip(targets) {
                for axis in 0..2 {
                    let base = (k * 2 + axis) * plane;
                    let at: f64 = nodes
                        .iter()
                        .zip(weights)
                        .map(|(&i, &wt)| wt * phi[base + i])
                        .sum();
                    let r = at - target[axis];
                    for (&i, &wt) in nodes.iter().zip(weights) {
                        grad[base + i] += 2.0 * self.scale * r * wt;
                    }
                }
            }
        }
        grad
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SIZE: (usize, usize) = (10, 13);

    fn refused(a: Vec<[f64; 2]>, b: Vec<[f64; 2]>) -> String {
        Landmarks::new(a, b, SIZE).unwrap_err().to_string()
    }

    #[test]
    fn bad_landmarks_are_refused_with_what_is_wrong() {
        assert!(refused(vec![], vec![]).contains("at least 1 pair"));
        assert!(refused(vec![[2.0, 2.0]], vec![]).contains("1 points in A and 0 in B"));
        let nan = refused(vec![[f64::NAN, 2.0]], vec![[2.0, 2.0]]);
        assert!(
            nan.contains("point 1 of A") && nan.contains("finite"),
            "{nan}"
        );
        // Within one pixel of the border (φ = Id there), and outside.
        let edge = refused(vec![[2.0, 2.0]], vec![[0.5, 3.0]]);
        assert!(
            edge.contains("point 1 of B") && edge.contains("rows in [1, 8]"),
            "{edge}"
        );
        assert!(refused(vec![[2.0, 11.5]], vec![[2.0, 2.0]]).contains("columns in [1, 11]"));
        let twice = refused(vec![[2.0, 2.0], [2.0, 2.0]], vec![[3.0, 3.0], [4.0, 4.0]]);
        assert!(twice.contains("points 1 and 2 of A"), "{twice}");
        // The same pair twice is no contradiction.
        Landmarks::new(vec![[2.0, 2.0]; 2], vec![[3.0, 3.0]; 2], SIZE).unwrap();
    }

    #[test]
    fn crossing_paths_are_found() {
        // Two points swapping places meet half way; two moving in parallel never do.
        let swap = Landmarks::new(
            vec![[4.0, 2.0], [4.0, 8.0]],
            vec![[4.0, 8.0], [4.0, 2.0]],
            SIZE,
        );
        assert_eq!(swap.unwrap().crossings(), vec![(0, 1)]);
        let parallel = Landmarks::new(
            vec![[4.0, 2.0], [6.0, 2.0]],
            vec![[4.0, 8.0], [6.0, 8.0]],
            SIZE,
        );
        assert!(parallel.unwrap().crossings().is_empty());
    }

    #[test]
    fn steps_and_levels_move_points_as_the_spec_says() {
        let l = Landmarks::new(vec![[2.0, 3.0]], vec![[5.0, 9.0]], SIZE).unwrap();
        assert_eq!(l.at_step(0, 3), vec![[2.0, 3.0]]);
        assert_eq!(l.at_step(3, 3), vec![[5.0, 9.0]]);
        assert_eq!(l.at_step(1, 3), vec![[3.0, 5.0]]);
        // Align corners: the last row and column map onto each other.
        let coarse = l.on_grid((5, 7));
        assert_eq!(
            coarse.at_step(0, 1),
            vec![[2.0 * 4.0 / 9.0, 3.0 * 6.0 / 12.0]]
        );
    }

    #[test]
    fn the_bilinear_stencil_reproduces_linear_functions() {
        let (h, w) = (6, 7);
        for p in [[0.0, 0.0], [2.25, 3.5], [5.0, 6.0], [4.999, 0.001]] {
            let (nodes, weights) = bilinear(&p, h, w);
            let at = |f: &dyn Fn(usize, usize) -> f64| -> f64 {
                nodes
                    .iter()
                    .zip(weights)
                    .map(|(&n, wt)| wt * f(n / w, n % w))
                    .sum()
            };
            assert!((at(&|i, _| i as f64) - p[0]).abs() < 1e-12, "{p:?}");
            assert!((at(&|_, j| j as f64) - p[1]).abs() < 1e-12, "{p:?}");
        }
    }
}
