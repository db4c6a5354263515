//! The batched schedule ([`Schedule::Batched`](super::ipalm::Schedule::Batched)): the steps of
//! SPEC §6 for every `k`, grouped into three blocks per sweep, each one operation on stacked
//! `[n, C, H, W]` tensors.
//!
//! 1. All deformations `φ_1..φ_K`: given the frames they are independent. Each `k` keeps its
//!    own `L_φ,k`, backtracking search, safeguard and inertia restart; the searches run in
//!    lockstep (one batched trial and one read-back per round, until every `k` is decided).
//!    A round, a restart and a safeguard doubling evaluate only the steps still undecided:
//!    recomputing every `k` for the one still searching made a deep batched sweep several
//!    times the work of a sequential one.
//! 2. All odd frames, then 3. all even frames: given the deformations and the frames of the
//!    other parity, `f_k` only meets `f_{k±1}`, so the frames of one parity are independent.
//!
//! This is iPALM with three blocks instead of `2K − 1`: the same energy and the same
//! admissibility guarantee, another block order (every `φ_k` sees the frames of the previous
//! sweep, every `f_k` the new deformations).

use burn::tensor::Tensor;

use crate::error::{Error, Result};
use crate::model::deformation::{admissible_each, min_det_each};
use crate::model::energy::data::data_term_from_warped;
use crate::model::energy::regularizer::{regularizer, weighted_density};
use crate::solver::backtracking::{Lockstep, Search, SearchRun, Trial};
use crate::solver::ipalm::{
    DeformationStep, FeatureStep, Ipalm, LevelState, SweepKind, SweepReport, read_groups,
    read_scalars,
};
use crate::solver::prox::{LinearisedData, pick};

/// Item `i` of a stacked tensor, `[1, …]`.
fn item(t: &Tensor<4>, i: usize) -> Tensor<4> {
    t.clone().narrow(0, i, 1)
}

/// A stack built item by item from `item_at(i)`.
fn stack(n: usize, item_at: impl Fn(usize) -> Tensor<4>) -> Tensor<4> {
    Tensor::cat((0..n).map(item_at).collect(), 0)
}

/// The indices `i < n` where `keep(i)`.
fn indices(n: usize, keep: impl Fn(usize) -> bool) -> Vec<usize> {
    (0..n).filter(|&i| keep(i)).collect()
}

/// All deformation steps of a sweep: the stacked form of `DeformationProblem`.
struct Deformations<'a> {
    ipalm: &'a Ipalm,
    /// `a_1..a_K`, `[K, H, W]`.
    a: Tensor<3>,
    /// `P f_1..P f_K`, `[K, C, H, W]`.
    coeffs: Tensor<4>,
    /// `f_0..f_{K−1}`, `[K, C, H, W]`.
    before: Tensor<4>,
    steps: f64,
}

/// The stacked linearisation of the steps `steps` (indices into `0..K`) around their points
/// `φ̃_k`; item `j` belongs to step `steps[j]`.
struct Linearised {
    steps: Vec<usize>,
    point: Tensor<4>,
    /// `S_k(φ̃_k)` of each item.
    smooth: Vec<f64>,
    gradient: Tensor<4>,
    data: LinearisedData,
}

impl Linearised {
    /// The items `items` of this linearisation.
    fn select(&self, items: &[usize]) -> Self {
        Self {
            steps: items.iter().map(|&j| self.steps[j]).collect(),
            point: pick(&self.point, items),
            smooth: items.iter().map(|&j| self.smooth[j]).collect(),
            gradient: pick(&self.gradient, items),
            data: self.data.select(items),
        }
    }

    /// The item of step `k`.
    fn item_of(&self, k: usize) -> usize {
        self.steps
            .iter()
            .position(|&s| s == k)
            .expect("the step is linearised here")
    }

    fn candidates(&self, l: &[f64]) -> Tensor<4> {
        let inverse: Tensor<4> = self.data_grid_tensor(l);
        self.data
            .prox_each(self.point.clone() - self.gradient.clone() * inverse, l)
    }

    /// `1/L_k` as a `[K, 1, 1, 1]` tensor.
    fn data_grid_tensor(&self, l: &[f64]) -> Tensor<4> {
        let like = &self.point;
        Tensor::from_data(
            burn::tensor::TensorData::new(
                l.iter().map(|l| 1.0 / l).collect::<Vec<f64>>(),
                [l.len(), 1, 1, 1],
            ),
            (&like.device(), like.dtype()),
        )
    }
}

impl Deformations<'_> {
    /// `S_k(φ_k)` of the steps `idx`, summed for decisions, `[idx.len()]`.
    fn smooth_decision(&self, phi: Tensor<4>, idx: &[usize]) -> Tensor<1> {
        let p = self.ipalm.energy.params();
        let grid = &self.ipalm.grid;
        grid.decision_sum_each(weighted_density(phi, pick(&self.a, idx), p.lambda, p.mu))
            .mul_scalar(self.steps / grid.pixels() as f64)
    }

    /// The safeguard's local energies `e_k(φ_k)` of the steps `idx`, summed for decisions.
    ///
    /// # Shapes
    /// - `phi`: `[idx.len(), 2, H, W]`
    fn local_energies(&self, phi: Tensor<4>, idx: &[usize]) -> Vec<f64> {
        let ipalm = self.ipalm;
        let grid = &ipalm.grid;
        let residual = ipalm
            .energy
            .bspline()
            .interpolate(pick(&self.coeffs, idx), phi.clone())
            - pick(&self.before, idx);
        let data_scale = self.steps
            / (ipalm.energy.params().delta
                * 2.0
                * ipalm.layout.channels() as f64
                * grid.pixels() as f64);
        let e = self.smooth_decision(phi, idx)
            + grid
                .decision_sum_each(residual.square())
                .mul_scalar(data_scale);
        read_scalars(grid, vec![e])
    }

    /// The linearisation of the steps `steps` around `point`, `[steps.len(), 2, H, W]`.
    fn linearise_at(&self, point: Tensor<4>, steps: &[usize]) -> Result<Linearised> {
        let ipalm = self.ipalm;
        let grid = &ipalm.grid;
        let p = ipalm.energy.params();
        let leaf = point.clone().detach().require_grad();
        // The S_k are independent: the gradient of their sum is each one's gradient.
        let smooth = regularizer(leaf.clone(), pick(&self.a, steps), p.lambda, p.mu)
            .sum()
            .mul_scalar(self.steps);
        let grads = smooth.backward();
        let gradient = leaf
            .grad(&grads)
            .expect("the regulariser depends on phi")
            .autodiff();
        let k = point.dims()[0];
        let [smooth, grad_norm2] = read_groups(
            grid,
            [
                self.smooth_decision(point.clone(), steps),
                grid.decision_sum_each(gradient.clone().square()),
            ],
        );
        if let Some(bad) = (0..k).find(|&i| !(smooth[i].is_finite() && grad_norm2[i].is_finite())) {
            return Err(Error::NonFinite {
                what: format!(
                    "step k = {}: K·R at the linearisation point is {}, |grad|^2 = {}",
                    steps[bad] + 1,
                    smooth[bad],
                    grad_norm2[bad]
                ),
            });
        }
        let kappa = self.steps / (p.delta * ipalm.layout.channels() as f64 * grid.pixels() as f64);
        Ok(Linearised {
            data: LinearisedData::around(
                grid,
                ipalm.energy.bspline(),
                &ipalm.sobel,
                pick(&self.coeffs, steps),
                pick(&self.before, steps),
                point.clone(),
                kappa,
            ),
            steps: steps.to_vec(),
            point,
            smooth,
            gradient,
        })
    }

    /// The searches of the steps `lin` linearises, in lockstep from the stored `L_φ,k` and
    /// streaks `m_k` (SPEC §6): every round evaluates one trial `L` per undecided step as one
    /// batched prox of those steps only and reads back `min det J`, `S`, `⟨g, d⟩` and `‖d‖²`
    /// of all of them at once. Item `j` of the result is step `lin.steps[j]`'s.
    fn search(
        &self,
        lin: &Linearised,
        stored: &[f64],
        streak: &[u32],
    ) -> Result<Vec<Search<Tensor<4>>>> {
        let ipalm = self.ipalm;
        let grid = &ipalm.grid;
        let bt = ipalm.config.backtracking;
        let slack = ipalm.slack();
        let k = lin.steps.len();
        let mut searches = Lockstep::new(
            lin.steps
                .iter()
                .map(|&s| Some(SearchRun::from_streak(&bt, stored[s], streak[s])))
                .collect(),
        );
        while let Some(trial) = searches.round() {
            let idx = indices(k, |j| trial[j].is_some());
            let l: Vec<f64> = idx.iter().filter_map(|&j| trial[j]).collect();
            let sub = lin.select(&idx);
            let candidates = sub.candidates(&l);
            let d = candidates.clone() - sub.point.clone();
            let [min_det, smooth, inner, norm2] = read_groups(
                grid,
                [
                    min_det_each(candidates.clone()),
                    self.smooth_decision(candidates.clone(), &sub.steps),
                    grid.decision_sum_each(sub.gradient.clone() * d.clone()),
                    grid.decision_sum_each(d.square()),
                ],
            );
            for (j, (&i, &l)) in idx.iter().zip(&l).enumerate() {
                let outcome = if !(min_det[j] > 0.0) {
                    Trial::Inadmissible
                } else if bt.accepts(smooth[j], sub.smooth[j], inner[j], norm2[j], l, slack) {
                    Trial::Accepted(item(&candidates, j))
                } else {
                    Trial::Rejected
                };
                searches.record(i, outcome);
            }
        }
        Ok(searches
            .finish()
            .into_iter()
            .map(|s| s.expect("every step searches"))
            .collect())
    }
}

/// Where one deformation step stands during the batched safeguard.
struct Pending {
    step: DeformationStep,
    /// The accepted `φ_new`, `None` once dropped.
    candidate: Option<Tensor<4>>,
    /// The `L` the backtracking accepted.
    accepted: f64,
    /// The `L` of the safeguard's doublings.
    doubled: f64,
    /// Whether the candidate comes from the restarted linearisation.
    restarted: bool,
}

impl Ipalm {
    /// One sweep of the batched schedule; `anisotropy`, when given, holds `a_1..a_K` of
    /// `state` (`[K, H, W]`, [`super::ipalm::SweepCarry`]).
    pub(super) fn sweep_batched(
        &self,
        state: &mut LevelState,
        kind: SweepKind,
        anisotropy: Option<Tensor<3>>,
    ) -> Result<SweepReport> {
        let k = state.steps();
        let mut report = SweepReport::empty(k);
        if kind == SweepKind::Joint {
            let a = anisotropy.unwrap_or_else(|| self.anisotropies(state));
            let (phi_new, steps) = self.deformation_steps(state, a.clone())?;
            for (i, (phi, step)) in phi_new.into_iter().zip(steps).enumerate() {
                state.apply_deformation(i + 1, phi, &step);
                report.deformation.push(step);
            }
            report.anisotropy = (0..k).map(|i| a.clone().narrow(0, i, 1)).collect();
        }
        let mut features: Vec<Option<FeatureStep>> = vec![None; k.saturating_sub(1)];
        for parity in [1, 0] {
            let ks: Vec<usize> = (1..k).filter(|j| j % 2 == parity).collect();
            if ks.is_empty() {
                continue;
            }
            let (frames, steps) = self.feature_steps(state, &ks)?;
            // Recorded in the order the passes run: every `D_k` next to an even frame is final
            // only after the even pass, `D_1` and (for even `K`) `D_K` after the odd one.
            for ((&j, f), step) in ks.iter().zip(frames).zip(steps) {
                report.record_residuals(j, step.residual_norm2);
                state.l_f[j - 1] = step.lipschitz.clone();
                state.f_prev[j] = std::mem::replace(&mut state.f[j], f);
                features[j - 1] = Some(step);
            }
        }
        report.features = features
            .into_iter()
            .map(|s| s.expect("every k < K has a feature step"))
            .collect();
        Ok(report)
    }

    /// SPEC §6 step 2 for every `k` at once.
    fn deformation_steps(
        &self,
        state: &LevelState,
        a: Tensor<3>,
    ) -> Result<(Vec<Tensor<4>>, Vec<DeformationStep>)> {
        let k = state.steps();
        let bspline = self.energy.bspline();
        let problem = Deformations {
            ipalm: self,
            a,
            coeffs: bspline.coefficients(Tensor::cat(state.f[1..=k].to_vec(), 0)),
            before: Tensor::cat(state.f[..k].to_vec(), 0),
            steps: k as f64,
        };
        let phi = state.deformations();
        let stored = state.l_phi.clone();
        let streak = state.phi_streak.clone();
        let (point, extrapolated) = if self.config.beta > 0.0 {
            let prev = Tensor::cat(state.phi_prev.clone(), 0);
            let e = phi.clone() + (phi.clone() - prev).mul_scalar(self.config.beta);
            let ok = admissible_each(&self.grid, e.clone());
            let point = stack(k, |i| if ok[i] { item(&e, i) } else { item(&phi, i) });
            (point, ok)
        } else {
            (phi.clone(), vec![false; k])
        };
        let all = indices(k, |_| true);
        let lin = problem.linearise_at(point, &all)?;
        let found = problem.search(&lin, &stored, &streak)?;
        let mut pending: Vec<Pending> = found
            .into_iter()
            .zip(&streak)
            .map(|(search, &streak)| {
                let accepted = search.lipschitz;
                Pending {
                    step: DeformationStep {
                        streak,
                        lipschitz: accepted,
                        trials: search.trials,
                        inadmissible_trials: search.inadmissible,
                        restarted: false,
                        safeguard_doublings: 0,
                        dropped: search.accepted.is_none(),
                        residual_norm2: None,
                    },
                    candidate: search.accepted,
                    accepted,
                    doubled: accepted,
                    restarted: false,
                }
            })
            .collect();

        if self.config.safeguard {
            let current = problem.local_energies(phi.clone(), &all);
            let tolerance: Vec<f64> = current.iter().map(|e| self.slack() * e.abs()).collect();
            let rises = |i: usize, e: f64| !(e <= current[i] + tolerance[i]);
            // The candidates of the steps `idx` (`φ_k` where dropped).
            let candidates = |pending: &[Pending], idx: &[usize]| {
                stack(idx.len(), |j| {
                    pending[idx[j]]
                        .candidate
                        .clone()
                        .unwrap_or_else(|| item(&phi, idx[j]))
                })
            };
            let mut energy = problem.local_energies(candidates(&pending, &all), &all);
            // Restart the inertia of every k whose extrapolated step raised e.
            let restart = indices(k, |i| {
                pending[i].candidate.is_some() && rises(i, energy[i]) && extrapolated[i]
            });
            let mut restarted_lin = None;
            if !restart.is_empty() {
                let lin = problem.linearise_at(pick(&phi, &restart), &restart)?;
                let found = problem.search(&lin, &stored, &streak)?;
                for (&i, search) in restart.iter().zip(found) {
                    let p = &mut pending[i];
                    p.step.restarted = true;
                    p.restarted = true;
                    p.step.trials += search.trials;
                    p.step.inadmissible_trials += search.inadmissible;
                    p.candidate = search.accepted;
                    p.accepted = search.lipschitz;
                    p.doubled = search.lipschitz;
                }
                let e = problem.local_energies(candidates(&pending, &restart), &restart);
                for (&i, e) in restart.iter().zip(e) {
                    energy[i] = e;
                }
                restarted_lin = Some(lin);
            }
            // Double L while e still rises, each k on its own linearisation.
            let mut doubling: Vec<bool> = (0..k)
                .map(|i| pending[i].candidate.is_some() && rises(i, energy[i]))
                .collect();
            loop {
                for (i, p) in pending.iter_mut().enumerate() {
                    if !doubling[i] {
                        continue;
                    }
                    if p.step.safeguard_doublings == self.config.safeguard_max {
                        p.candidate = None;
                        doubling[i] = false;
                        continue;
                    }
                    p.step.safeguard_doublings += 1;
                    p.doubled *= 2.0;
                }
                let idx = indices(k, |i| doubling[i]);
                if idx.is_empty() {
                    break;
                }
                let (again, fresh): (Vec<usize>, Vec<usize>) =
                    idx.iter().partition(|&&i| pending[i].restarted);
                for (around, ks) in [(Some(&lin), fresh), (restarted_lin.as_ref(), again)] {
                    if ks.is_empty() {
                        continue;
                    }
                    let around = around.expect("a restarted step has its linearisation");
                    let items: Vec<usize> = ks.iter().map(|&i| around.item_of(i)).collect();
                    let l: Vec<f64> = ks.iter().map(|&i| pending[i].doubled).collect();
                    let from = around.select(&items).candidates(&l);
                    for (j, &i) in ks.iter().enumerate() {
                        pending[i].candidate = Some(item(&from, j));
                    }
                }
                let e = problem.local_energies(candidates(&pending, &idx), &idx);
                for (&i, e) in idx.iter().zip(e) {
                    doubling[i] = rises(i, e);
                }
            }
        }

        let mut frames = Vec::with_capacity(k);
        let mut steps = Vec::with_capacity(k);
        for (i, mut p) in pending.into_iter().enumerate() {
            match p.candidate {
                Some(candidate) => {
                    p.step.lipschitz = p.accepted;
                    frames.push(candidate);
                }
                None => {
                    // SPEC §6, *Giving up*: keep φ_k and the L the step started from.
                    p.step.dropped = true;
                    p.step.lipschitz = stored[i];
                    frames.push(item(&phi, i));
                }
            }
            steps.push(p.step);
        }
        Ok((frames, steps))
    }

    /// SPEC §6 step 3 for the frames `ks` (all of one parity) at once, block by block.
    fn feature_steps(
        &self,
        state: &LevelState,
        ks: &[usize],
    ) -> Result<(Vec<Tensor<4>>, Vec<FeatureStep>)> {
        let n = ks.len();
        let grid = &self.grid;
        let bspline = self.energy.bspline();
        let bt = self.config.backtracking;
        let c_tot = self.layout.channels();
        let delta = self.energy.params().delta;
        let steps = state.steps() as f64;
        let take = |v: &[Tensor<4>], offset: isize| {
            Tensor::cat(
                ks.iter()
                    .map(|&j| v[(j as isize + offset) as usize].clone())
                    .collect(),
                0,
            )
        };
        let f_k = take(&state.f, 0);
        let f_tilde = if self.config.beta > 0.0 {
            f_k.clone() + (f_k.clone() - take(&state.f_prev, 0)).mul_scalar(self.config.beta)
        } else {
            f_k.clone()
        };
        // φ_k is stored at k − 1, φ_{k+1} at k.
        let phis = take(&state.phi, -1);
        let sampler = bspline.sampler(phis.clone());
        let next_warped =
            bspline.interpolate(bspline.coefficients(take(&state.f, 1)), take(&state.phi, 0));
        let before = take(&state.f, -1);
        let scale = steps / (delta * 2.0 * c_tot as f64 * grid.pixels() as f64);

        let mut blocks: Vec<Tensor<4>> = Vec::new();
        let mut records: Vec<FeatureStep> = (0..n)
            .map(|_| FeatureStep {
                lipschitz: Vec::new(),
                trials: Vec::new(),
                dropped: Vec::new(),
                residual_norm2: Some((0.0, 0.0)),
            })
            .collect();
        for (b, block) in self.layout.blocks().iter().enumerate() {
            let (start, len) = (block.channels.start, block.channels.len());
            let prev = before.clone().narrow(1, start, len);
            let next = next_warped.clone().narrow(1, start, len);
            let warp = |x: Tensor<4>| sampler.sample(bspline.coefficients(x));
            // The frames `items` only (the trials of the frames still undecided).
            let warp_items = |x: Tensor<4>, items: &[usize]| {
                if items.len() == n {
                    warp(x)
                } else {
                    bspline
                        .sampler(pick(&phis, items))
                        .sample(bspline.coefficients(x))
                }
            };
            let residuals = |x: Tensor<4>, warped: Tensor<4>, items: &[usize]| {
                (warped - pick(&prev, items), pick(&next, items) - x)
            };
            // The squared norms of each item's two residuals, `[n]` each, summed for decisions;
            // `Q` is their sum times `scale`, taken on the host.
            let norms_each = |(moved, fixed): &(Tensor<4>, Tensor<4>)| {
                [
                    grid.decision_sum_each(moved.clone().square()),
                    grid.decision_sum_each(fixed.clone().square()),
                ]
            };
            // Each item's residual norms of its last trial: the accepted one's once decided.
            let mut norms = vec![(f64::NAN, f64::NAN); n];
            let x_tilde = f_tilde.clone().narrow(1, start, len).detach();
            let leaf = x_tilde.clone().require_grad();
            let warped = warp(leaf.clone());
            // The Q_k are independent: the gradient of their sum is each one's gradient.
            let q = (data_term_from_warped(warped.clone(), prev.clone(), c_tot)
                + data_term_from_warped(next.clone(), leaf.clone(), c_tot))
            .sum()
            .mul_scalar(steps / delta);
            let grads = q.backward();
            let grad = leaf.grad(&grads).expect("Q depends on f_k").autodiff();
            let warped_tilde = warped.detach();
            let all = indices(n, |_| true);
            let [moved, fixed] =
                norms_each(&residuals(x_tilde.clone(), warped_tilde.clone(), &all));
            let [moved, fixed, norm2] = read_groups(
                grid,
                [moved, fixed, grid.decision_sum_each(grad.clone().square())],
            );
            let q_tilde: Vec<f64> = (0..n).map(|i| (moved[i] + fixed[i]) * scale).collect();
            if let Some(i) = (0..n).find(|&i| !(q_tilde[i].is_finite() && norm2[i].is_finite())) {
                return Err(Error::NonFinite {
                    what: format!(
                        "feature step k = {}, block {b}: Q = {}, |grad Q|^2 = {}",
                        ks[i], q_tilde[i], norm2[i]
                    ),
                });
            }
            let slack = self.slack();
            let mut searches = Lockstep::new(
                ks.iter()
                    .map(|&j| Some(SearchRun::new(&bt, state.l_f[j - 1][b])))
                    .collect(),
            );
            while let Some(trial) = searches.round() {
                let idx = indices(n, |i| trial[i].is_some());
                let l: Vec<f64> = idx.iter().filter_map(|&i| trial[i]).collect();
                let m = idx.len();
                let inverse = grid.tensor(l.iter().map(|l| 1.0 / l).collect(), [m, 1, 1, 1]);
                let candidates = pick(&x_tilde, &idx) - pick(&grad, &idx) * inverse;
                let warped = warp_items(candidates.clone(), &idx);
                // ‖T[d, φ_k]‖² = ‖T[x_new, φ_k] − T[x̃, φ_k]‖² of each item: the exact remainder
                // of the quadratic Q (see the sequential feature step).
                let moved =
                    grid.decision_sum_each((warped.clone() - pick(&warped_tilde, &idx)).square());
                let [to_prev, to_next] = norms_each(&residuals(candidates.clone(), warped, &idx));
                let [to_prev, to_next, moved] = read_groups(grid, [to_prev, to_next, moved]);
                for (j, (&i, &l)) in idx.iter().zip(&l).enumerate() {
                    norms[i] = (to_prev[j], to_next[j]);
                    let q_new = (to_prev[j] + to_next[j]) * scale;
                    let (g2, q0) = (norm2[i], q_tilde[i]);
                    // x_new − x̃ = −∇Q/L: ‖x_new − x̃‖² = ‖∇Q‖²/L²; the test on the exact
                    // remainder scale·(‖T[d, φ_k]‖² + ‖d‖²), as the sequential feature step.
                    let d2 = g2 / (l * l);
                    let remainder = scale * (moved[j] + d2);
                    let outcome = if bt.accepts_remainder(q_new, q0, remainder, d2, l, slack) {
                        Trial::Accepted(item(&candidates, j))
                    } else {
                        Trial::Rejected
                    };
                    searches.record(i, outcome);
                }
            }
            let current = f_k.clone().narrow(1, start, len);
            let mut values = Vec::with_capacity(n);
            for (i, search) in searches.finish().into_iter().enumerate() {
                let search = search.expect("every frame searches");
                records[i].dropped.push(search.accepted.is_none());
                records[i].lipschitz.push(search.lipschitz);
                records[i].trials.push(search.trials);
                records[i].residual_norm2 = match (records[i].residual_norm2, &search.accepted) {
                    (Some((moved, fixed)), Some(_)) => {
                        Some((moved + norms[i].0, fixed + norms[i].1))
                    }
                    _ => None,
                };
                values.push(search.accepted.unwrap_or_else(|| item(&current, i)));
            }
            blocks.push(Tensor::cat(values, 0));
        }
        let frames = Tensor::cat(blocks, 1);
        Ok(((0..n).map(|i| item(&frames, i)).collect(), records))
    }
}
