//! The steps of SPEC §6 for any set of `k` at once: step 2 (the deformations `φ_k`) and
//! step 3 (the features `f_k`). Both schedules take their steps from here, so a rule or a
//! term is written once: the sequential schedule calls them for one `k` at a time, the
//! batched one for every `k` (deformations) and for every `k` of one parity (features).
//!
//! A call for the steps `ks` stacks what they read into `[n, …]` tensors, item `j` for step
//! `ks[j]`. Each item keeps its own Lipschitz estimate, backtracking search, safeguard and
//! inertia restart; the searches run in lockstep (one stacked trial and one read-back per
//! round, [`Lockstep`]), and a round, a restart and a safeguard doubling evaluate only the
//! items still undecided: recomputing every `k` for the one still searching made a deep
//! batched sweep several times the work of a sequential one. With one item every operation
//! is the one a step of one `k` needs, with no stacking around it.
//!
//! Every accept/reject decision compares scalars summed by the grid's decision sums
//! ([`crate::model::grid::Grid::decision_sum`]), each item's bit for bit what it gives
//! alone, and each trial reads its scalars back in one transfer.

use std::ops::Range;

use burn::tensor::Tensor;

use crate::error::{Error, Result};
use crate::model::deformation::{admissible_each, min_det_each};
use crate::model::energy::data::data_term_given;
use crate::model::energy::regularizer::{mean_density, weighted_density};
use crate::solver::backtracking::{Lockstep, Search, SearchRun, Trial};
use crate::solver::ipalm::{DeformationStep, FeatureStep, Ipalm, LevelState, read_groups};
use crate::solver::prox::{LinearisedData, pick};
use crate::solver::update_op::{descend_distance2, extrapolate, extrapolate_distance2};

/// Item `i` of a stacked tensor, `[1, …]` (the tensor itself if it holds one item).
fn item<const D: usize>(t: &Tensor<D>, i: usize) -> Tensor<D> {
    if t.dims()[0] == 1 {
        return t.clone();
    }
    t.clone().narrow(0, i, 1)
}

/// Items stacked along dimension 0 (the item itself if there is one).
fn stack(mut items: Vec<Tensor<4>>) -> Tensor<4> {
    if items.len() == 1 {
        return items.pop().expect("one item");
    }
    Tensor::cat(items, 0)
}

/// The indices `i < n` where `keep(i)`.
fn indices(n: usize, keep: impl Fn(usize) -> bool) -> Vec<usize> {
    (0..n).filter(|&i| keep(i)).collect()
}

/// `v[k + offset]` for every `k` of `ks`, stacked.
fn take(v: &[Tensor<4>], ks: &[usize], offset: isize) -> Tensor<4> {
    stack(
        ks.iter()
            .map(|&k| v[k.checked_add_signed(offset).expect("an index in range")].clone())
            .collect(),
    )
}

/// `P f_k` and `T[f_k, φ_k]` (`[n, C_tot, H, W]` each) as a step computed them: the feature
/// step of `k − 1` computes them and the deformation step of `k` starts from them (neither
/// changes in between), and the accepted trials of `f_k`'s step leave them for the next
/// sweep's feature step of `k − 1` ([`super::ipalm::SweepCarry`]).
#[derive(Clone, Debug)]
pub(super) struct FrameProducts {
    pub(super) coeffs: Tensor<4>,
    pub(super) warped: Tensor<4>,
}

/// What the feature steps of `ks` did, item `j` for step `ks[j]`.
pub(super) struct FeatureSteps {
    /// `f_new` of each step, `[1, C_tot, H, W]`.
    pub(super) frames: Vec<Tensor<4>>,
    /// The record of each step.
    pub(super) steps: Vec<FeatureStep>,
    /// `P f_{k+1}` and `T[f_{k+1}, φ_{k+1}]` of every step, stacked: what the deformation
    /// steps of `k + 1` start from if nothing changes them first.
    pub(super) next: FrameProducts,
    /// `P f_new` and `T[f_new, φ_k]` as the accepted trials computed them, `None` where a
    /// block gave up.
    pub(super) own: Vec<Option<FrameProducts>>,
}

/// The deformation steps of `ks`: the pieces of `K·R[·, a_k]` and `e_k(·)` (SPEC §6 step 2).
struct Deformations<'a> {
    ipalm: &'a Ipalm,
    /// The steps, in `1..=K`; item `j` is step `ks[j]`.
    ks: Vec<usize>,
    /// `a_k`, `[n, H, W]`.
    a: Tensor<3>,
    /// `P f_k`, `[n, C, H, W]`.
    coeffs: Tensor<4>,
    /// `f_{k−1}`, `[n, C, H, W]`.
    before: Tensor<4>,
    /// `K`.
    steps: f64,
}

/// The safeguard's `e_k(φ)` and the squared residual norm in its data term.
#[derive(Clone, Copy, Debug)]
struct LocalEnergy {
    value: f64,
    residual_norm2: f64,
}

/// Deformation steps linearised around their points `φ̃_k` (the extrapolated points, or
/// `φ_k` after a restart): `S_k(φ̃_k)` summed for decisions, `g_k = ∇S_k(φ̃_k)`, and the
/// prox of the linearised data terms. Entry `j` belongs to item `items[j]`.
struct Linearised {
    items: Vec<usize>,
    point: Tensor<4>,
    smooth: Vec<f64>,
    gradient: Tensor<4>,
    data: LinearisedData,
}

impl Linearised {
    /// The entries `entries` of this linearisation, in that order.
    fn select(&self, entries: &[usize]) -> Self {
        Self {
            items: entries.iter().map(|&j| self.items[j]).collect(),
            point: pick(&self.point, entries),
            smooth: entries.iter().map(|&j| self.smooth[j]).collect(),
            gradient: pick(&self.gradient, entries),
            data: self.data.select(entries),
        }
    }

    /// The entry of item `i`.
    fn entry_of(&self, i: usize) -> usize {
        self.items
            .iter()
            .position(|&s| s == i)
            .expect("the item is linearised here")
    }

    /// `φ_new` of every entry for its trial `L`: the prox at `y = φ̃ − g/L`.
    fn candidates(&self, l: &[f64]) -> Tensor<4> {
        if let [l] = l {
            // One entry: the fused trial where the linearisation was fused.
            return self
                .data
                .candidate(self.point.clone(), self.gradient.clone(), *l);
        }
        let like = &self.point;
        let inverse: Tensor<4> = Tensor::from_data(
            burn::tensor::TensorData::new(
                l.iter().map(|l| 1.0 / l).collect::<Vec<f64>>(),
                [l.len(), 1, 1, 1],
            ),
            (&like.device(), like.dtype()),
        );
        self.data
            .prox_each(self.point.clone() - self.gradient.clone() * inverse, l)
    }
}

impl Deformations<'_> {
    /// `a_k · W(J(φ_k))` per pixel of the items `items`, differentiable where `φ` is: the
    /// summand of `S_k` and of its decision sum.
    fn density(&self, phi: Tensor<4>, items: &[usize]) -> Tensor<3> {
        let p = self.ipalm.energy.params();
        weighted_density(phi, pick(&self.a, items), p.lambda, p.mu)
    }

    /// SPEC §11's landmark part of `S_k` of each item, `[n]`, differentiable in `phi`;
    /// `None` without landmarks.
    fn landmarks(&self, phi: Tensor<4>, items: &[usize]) -> Option<Tensor<1>> {
        let ks: Vec<usize> = items.iter().map(|&i| self.ks[i]).collect();
        self.ipalm
            .landmarks
            .as_ref()
            .map(|term| term.step_energies(&ks, phi))
    }

    /// `S_k(φ_k) = K·R[φ_k, a_k] (+ the landmark part)` of each item summed for decisions,
    /// `[n]`, from [`density`](Self::density) and [`landmarks`](Self::landmarks). The
    /// landmark part is a sum of `N` squares, cast, not a float64 sum of its summands: its
    /// rounding is that of `N` float32 values, not of `H·W`.
    fn smooth_decision(&self, density: Tensor<3>, landmarks: Option<Tensor<1>>) -> Tensor<1> {
        let grid = &self.ipalm.grid;
        let smooth = grid
            .decision_sum_each(density)
            .mul_scalar(self.steps / grid.pixels() as f64);
        match landmarks {
            Some(part) => {
                let dtype = burn::tensor::FloatDType::from(smooth.dtype());
                smooth + part.detach().cast(dtype)
            }
            None => smooth,
        }
    }

    /// [`smooth_decision`](Self::smooth_decision) at `phi`.
    fn smooth_at(&self, phi: Tensor<4>, items: &[usize]) -> Tensor<1> {
        self.smooth_decision(self.density(phi.clone(), items), self.landmarks(phi, items))
    }

    /// `(K/δ) / (2·C_tot·H·W)`: the data part of `e_k` per unit of squared residual norm.
    fn data_scale(&self) -> f64 {
        let ipalm = self.ipalm;
        self.steps
            / (ipalm.energy.params().delta
                * 2.0
                * ipalm.layout.channels() as f64
                * ipalm.grid.pixels() as f64)
    }

    /// The true local energies `e_k(φ) = K·R[φ, a_k] + (K/δ)·D[f_{k−1}, f_k, φ]` of the
    /// items `items`, summed for decisions (the safeguard's); `smooth`, when given, holds
    /// `S_k(φ)` of each as a trial summed it. Also returns `T[f_k, φ]` of each,
    /// `[items.len(), C, H, W]`.
    ///
    /// # Shapes
    /// - `phi`: `[items.len(), 2, H, W]`
    fn local_energies(
        &self,
        phi: Tensor<4>,
        items: &[usize],
        smooth: Option<Vec<f64>>,
    ) -> (Vec<LocalEnergy>, Tensor<4>) {
        let warped = self
            .ipalm
            .energy
            .bspline()
            .interpolate(pick(&self.coeffs, items), phi.clone());
        (
            self.local_energies_of(phi, warped.clone(), items, smooth),
            warped,
        )
    }

    /// [`local_energies`](Self::local_energies) with `T[f_k, φ]` already computed.
    fn local_energies_of(
        &self,
        phi: Tensor<4>,
        warped: Tensor<4>,
        items: &[usize],
        smooth: Option<Vec<f64>>,
    ) -> Vec<LocalEnergy> {
        let grid = &self.ipalm.grid;
        let distance = grid.decision_distance2_each(warped, pick(&self.before, items));
        let (smooth, residual_norm2) = match smooth {
            Some(smooth) => {
                let [residual] = read_groups(grid, [distance]);
                (smooth, residual)
            }
            None => {
                let [smooth, residual] = read_groups(grid, [self.smooth_at(phi, items), distance]);
                (smooth, residual)
            }
        };
        let scale = self.data_scale();
        smooth
            .iter()
            .zip(residual_norm2)
            .map(|(smooth, residual_norm2)| LocalEnergy {
                value: smooth + residual_norm2 * scale,
                residual_norm2,
            })
            .collect()
    }

    /// Linearises the steps of `items` around `point` (SPEC §6 step 2); `warped`, when
    /// given, is `T[f_k, point]` of each item, already evaluated.
    ///
    /// # Errors
    ///
    /// [`Error::NonFinite`] if some `S_k(φ̃_k)` or its gradient is not finite.
    ///
    /// # Shapes
    /// - `point`: `[items.len(), 2, H, W]`; `warped`: `[items.len(), C, H, W]`
    fn linearise_at(
        &self,
        point: Tensor<4>,
        items: &[usize],
        warped: Option<Tensor<4>>,
    ) -> Result<Linearised> {
        let ipalm = self.ipalm;
        let grid = &ipalm.grid;
        let leaf = point.clone().detach().require_grad();
        // One density for the gradient and the decision sums: the same values either way.
        // The S_k are independent: the gradient of their sum is each one's gradient.
        let density = self.density(leaf.clone(), items);
        let landmarks = self.landmarks(leaf.clone(), items);
        let mut smooth = mean_density(density.clone()).sum().mul_scalar(self.steps);
        if let Some(part) = &landmarks {
            smooth = smooth + part.clone().sum();
        }
        let grads = smooth.backward();
        let gradient = leaf
            .grad(&grads)
            .expect("the regulariser depends on phi")
            .autodiff();
        let [smooth, grad_norm2] = read_groups(
            grid,
            [
                self.smooth_decision(density, landmarks),
                grid.decision_norm2_each(gradient.clone()),
            ],
        );
        let bad = (0..items.len()).find(|&j| !(smooth[j].is_finite() && grad_norm2[j].is_finite()));
        if let Some(j) = bad {
            return Err(Error::NonFinite {
                what: format!(
                    "step k = {}: K·R at the linearisation point is {}, |grad|^2 = {}",
                    self.ks[items[j]], smooth[j], grad_norm2[j]
                ),
            });
        }
        let p = ipalm.energy.params();
        let kappa = self.steps / (p.delta * ipalm.layout.channels() as f64 * grid.pixels() as f64);
        let data = LinearisedData::around(
            grid,
            ipalm.energy.bspline(),
            &ipalm.sobel,
            pick(&self.coeffs, items),
            pick(&self.before, items),
            point.clone(),
            kappa,
            warped,
        );
        Ok(Linearised {
            items: items.to_vec(),
            point,
            smooth,
            gradient,
            data,
        })
    }

    /// The backtracking searches of SPEC §6 step 2 around `lin`, in lockstep from the
    /// stored `L_φ,k` and the streaks `m_k` of its items (first trial `0.9^(m+1)·L`): every
    /// round evaluates one trial `L` per undecided entry as one stacked prox of those only
    /// and reads back `min det J`, `S`, `⟨g, d⟩` and `‖d‖²` of all of them at once. Entry `j`
    /// of the result accepts `(φ_new, S_k(φ_new))`, the latter as the test summed it.
    fn search(
        &self,
        lin: &Linearised,
        stored: &[f64],
        streak: &[u32],
    ) -> Result<Vec<Search<(Tensor<4>, f64)>>> {
        let ipalm = self.ipalm;
        let grid = &ipalm.grid;
        let bt = ipalm.config.backtracking;
        let slack = ipalm.slack();
        let mut searches = Lockstep::new(
            lin.items
                .iter()
                .map(|&i| Some(SearchRun::from_streak(&bt, stored[i], streak[i])))
                .collect(),
        );
        while let Some(trial) = searches.round() {
            let entries = indices(lin.items.len(), |j| trial[j].is_some());
            let l: Vec<f64> = entries.iter().filter_map(|&j| trial[j]).collect();
            let sub = lin.select(&entries);
            let candidates = sub.candidates(&l);
            let d = candidates.clone() - sub.point.clone();
            let [min_det, smooth, inner, norm2] = read_groups(
                grid,
                [
                    min_det_each(candidates.clone()),
                    self.smooth_at(candidates.clone(), &sub.items),
                    grid.decision_dot_each(sub.gradient.clone(), d.clone()),
                    grid.decision_norm2_each(d),
                ],
            );
            for (e, (&j, &l)) in entries.iter().zip(&l).enumerate() {
                // The prox fixes the boundary exactly, so admissibility is det J > 0 (a NaN
                // fails it too).
                let outcome = if !(min_det[e] > 0.0) {
                    Trial::Inadmissible
                } else if bt.accepts(smooth[e], sub.smooth[e], inner[e], norm2[e], l, slack) {
                    Trial::Accepted((item(&candidates, e), smooth[e]))
                } else {
                    Trial::Rejected
                };
                searches.record(j, outcome);
            }
        }
        Ok(searches
            .finish()
            .into_iter()
            .map(|s| s.expect("every entry searches"))
            .collect())
    }
}

/// Where one deformation step stands during its safeguard.
struct Pending {
    step: DeformationStep,
    /// The accepted `φ_new` and `S_k(φ_new)` as its trial summed it (`None` where the last
    /// candidate came from a doubling), `None` once dropped.
    candidate: Option<(Tensor<4>, Option<f64>)>,
    /// The `L` the backtracking accepted.
    accepted: f64,
    /// The `L` of the safeguard's doublings.
    doubled: f64,
    /// `e_k(φ_k)`, once the safeguard evaluated it.
    current: Option<LocalEnergy>,
    /// `e_k` of the candidate, once the safeguard evaluated it.
    energy: Option<LocalEnergy>,
    /// `T[f_k, φ_k]` and `T[f_k, ·]` of the candidate where the safeguard evaluated them
    /// and the caller keeps them ([`Ipalm::deformation_steps`]'s `keep`).
    current_warp: Option<Tensor<4>>,
    candidate_warp: Option<Tensor<4>>,
}

impl Pending {
    /// Takes what a search found: the first one, or the search after an inertia restart.
    fn found(&mut self, search: Search<(Tensor<4>, f64)>) {
        self.step.trials += search.trials;
        self.step.inadmissible_trials += search.inadmissible;
        self.candidate = search.accepted.map(|(phi, smooth)| (phi, Some(smooth)));
        self.candidate_warp = None;
        self.accepted = search.lipschitz;
        self.doubled = search.lipschitz;
    }

    /// Whether `e_k` of the candidate lies above `e_k(φ_k)` by more than `slack` relative
    /// (written so that a NaN energy counts as a rise).
    fn rises(&self, slack: f64) -> bool {
        let (Some(current), Some(energy)) = (self.current, self.energy) else {
            return false;
        };
        let tolerance = slack * current.value.abs();
        !(energy.value <= current.value + tolerance)
    }
}

impl Ipalm {
    /// SPEC §6 step 2 for the steps `ks` (in `1..=K`) at once: `φ_new` of each and what
    /// happened.
    ///
    /// `carried`, when given, holds `P f_k` and `T[f_k, φ_k]` of every step (from the
    /// feature step of `k − 1` in this sweep; neither changed since): the steps start from
    /// them instead of computing them again, with the same values.
    ///
    /// With `keep`, each step also returns `P f_k` and `T[f_k, φ_new]` where its safeguard
    /// evaluated them (the warp of `e_k` at the accepted candidate, or at `φ_k` for a dropped
    /// step): for `k = K`, whose `f_K` never changes, they are what the next sweep's feature
    /// step of `K − 1` reads.
    ///
    /// # Shapes
    /// - `a`: `[ks.len(), H, W]`, the anisotropies `a_k`
    pub(super) fn deformation_steps(
        &self,
        state: &LevelState,
        ks: &[usize],
        a: Tensor<3>,
        carried: Option<FrameProducts>,
        keep: bool,
    ) -> Result<Vec<(Tensor<4>, DeformationStep, Option<FrameProducts>)>> {
        let n = ks.len();
        let bspline = self.energy.bspline();
        let (coeffs, reference_warp) = match carried {
            Some(FrameProducts { coeffs, warped }) => (coeffs, Some(warped)),
            None => (bspline.coefficients(take(&state.f, ks, 0)), None),
        };
        let problem = Deformations {
            ipalm: self,
            ks: ks.to_vec(),
            a,
            coeffs,
            before: take(&state.f, ks, -1),
            steps: state.steps() as f64,
        };
        let phi = take(&state.phi, ks, -1);
        let stored: Vec<f64> = ks.iter().map(|&k| state.l_phi[k - 1]).collect();
        let streak: Vec<u32> = ks.iter().map(|&k| state.phi_streak[k - 1]).collect();
        let (point, extrapolated) = if self.config.beta > 0.0 {
            let e = extrapolate(phi.clone(), take(&state.phi_prev, ks, -1), self.config.beta);
            let ok = admissible_each(&self.grid, e.clone());
            let point = if ok.iter().all(|&ok| ok) {
                e
            } else if !ok.iter().any(|&ok| ok) {
                phi.clone()
            } else {
                stack(
                    (0..n)
                        .map(|i| if ok[i] { item(&e, i) } else { item(&phi, i) })
                        .collect(),
                )
            };
            (point, ok)
        } else {
            (phi.clone(), vec![false; n])
        };
        let all = indices(n, |_| true);
        let lin = problem.linearise_at(point, &all, None)?;
        let mut pending: Vec<Pending> = streak
            .iter()
            .map(|&streak| Pending {
                step: DeformationStep {
                    streak,
                    lipschitz: 0.0,
                    trials: 0,
                    inadmissible_trials: 0,
                    restarted: false,
                    safeguard_doublings: 0,
                    dropped: false,
                    residual_norm2: None,
                },
                candidate: None,
                accepted: 0.0,
                doubled: 0.0,
                current: None,
                energy: None,
                current_warp: None,
                candidate_warp: None,
            })
            .collect();
        for (p, search) in pending
            .iter_mut()
            .zip(problem.search(&lin, &stored, &streak)?)
        {
            p.found(search);
        }
        if self.config.safeguard {
            self.safeguard(
                &problem,
                &phi,
                reference_warp,
                &lin,
                &extrapolated,
                &stored,
                &streak,
                keep,
                &mut pending,
            )?;
        }
        let coeffs = &problem.coeffs;
        Ok(pending
            .into_iter()
            .enumerate()
            .map(|(i, mut p)| {
                p.step.residual_norm2 = p.energy.or(p.current).map(|e| e.residual_norm2);
                match p.candidate {
                    // The doublings answered a linearisation that misled this step, not the
                    // curvature of S: the next sweep starts from the L the backtracking
                    // accepted.
                    Some((candidate, _)) => {
                        p.step.lipschitz = p.accepted;
                        let products = p.candidate_warp.map(|warped| FrameProducts {
                            coeffs: item(coeffs, i),
                            warped,
                        });
                        (candidate, p.step, products)
                    }
                    None => {
                        // SPEC §6, *Giving up*: keep φ_k and the L the step started from.
                        p.step.dropped = true;
                        p.step.lipschitz = stored[i];
                        let products = p.current_warp.map(|warped| FrameProducts {
                            coeffs: item(coeffs, i),
                            warped,
                        });
                        (item(&phi, i), p.step, products)
                    }
                }
            })
            .collect())
    }

    /// SPEC §6's safeguard on the accepted deformation steps: compare `e_k` of each
    /// candidate with `e_k(φ_k)`; on a rise restart the inertia of that `k` (search again
    /// around `φ_k`), then double its `L` while `e_k` still rises, up to `safeguard_max`
    /// doublings before the step is dropped.
    #[allow(clippy::too_many_arguments)]
    fn safeguard(
        &self,
        problem: &Deformations,
        phi: &Tensor<4>,
        reference_warp: Option<Tensor<4>>,
        lin: &Linearised,
        extrapolated: &[bool],
        stored: &[f64],
        streak: &[u32],
        keep: bool,
        pending: &mut [Pending],
    ) -> Result<()> {
        let n = pending.len();
        let slack = self.slack();
        let live = indices(n, |i| pending[i].candidate.is_some());
        if live.is_empty() {
            return Ok(());
        }
        let reference_warp = match reference_warp {
            Some(warped) => pick(&warped, &live),
            None => self
                .energy
                .bspline()
                .interpolate(pick(&problem.coeffs, &live), pick(phi, &live)),
        };
        let current =
            problem.local_energies_of(pick(phi, &live), reference_warp.clone(), &live, None);
        for (j, (&i, e)) in live.iter().zip(current).enumerate() {
            pending[i].current = Some(e);
            if keep {
                pending[i].current_warp = Some(item(&reference_warp, j));
            }
        }
        // `e_k` of the candidates of the items `items`, each from its trial's `S_k` where it
        // has one.
        let evaluate = |pending: &mut [Pending], items: &[usize]| {
            let (candidates, smooth): (Vec<Tensor<4>>, Vec<Option<f64>>) = items
                .iter()
                .map(|&i| pending[i].candidate.clone().expect("a candidate"))
                .unzip();
            let smooth = smooth.into_iter().collect::<Option<Vec<f64>>>();
            let (energies, warped) = problem.local_energies(stack(candidates), items, smooth);
            for (j, (&i, e)) in items.iter().zip(energies).enumerate() {
                pending[i].energy = Some(e);
                if keep {
                    pending[i].candidate_warp = Some(item(&warped, j));
                }
            }
        };
        evaluate(pending, &live);
        // Restart the inertia of every k whose extrapolated step raised e_k: as L grows the
        // prox tends to φ̃, which for the extrapolated point may lie above e_k(φ_k); around
        // φ_k it tends to φ_k.
        let restart = indices(n, |i| {
            pending[i].candidate.is_some() && pending[i].rises(slack) && extrapolated[i]
        });
        let mut restarted_lin = None;
        if !restart.is_empty() {
            // The restart linearises at φ_k, whose warp e_k(φ_k) has just evaluated.
            let at: Vec<usize> = restart
                .iter()
                .map(|i| live.binary_search(i).expect("a restarted step is live"))
                .collect();
            let lin = problem.linearise_at(
                pick(phi, &restart),
                &restart,
                Some(pick(&reference_warp, &at)),
            )?;
            for (&i, search) in restart.iter().zip(problem.search(&lin, stored, streak)?) {
                pending[i].step.restarted = true;
                pending[i].found(search);
                pending[i].energy = None;
            }
            let again = indices(n, |i| {
                pending[i].step.restarted && pending[i].candidate.is_some()
            });
            if !again.is_empty() {
                evaluate(pending, &again);
            }
            restarted_lin = Some(lin);
        }
        // Double L while e_k still rises, each k on the linearisation of its last search.
        let mut doubling: Vec<bool> = (0..n)
            .map(|i| pending[i].candidate.is_some() && pending[i].rises(slack))
            .collect();
        loop {
            for (i, p) in pending.iter_mut().enumerate() {
                if !doubling[i] {
                    continue;
                }
                if p.step.safeguard_doublings == self.config.safeguard_max {
                    p.candidate = None;
                    p.energy = None;
                    doubling[i] = false;
                    continue;
                }
                p.step.safeguard_doublings += 1;
                p.doubled *= 2.0;
            }
            let items = indices(n, |i| doubling[i]);
            if items.is_empty() {
                return Ok(());
            }
            let (again, fresh): (Vec<usize>, Vec<usize>) =
                items.iter().partition(|&&i| pending[i].step.restarted);
            for (around, group) in [(Some(lin), fresh), (restarted_lin.as_ref(), again)] {
                if group.is_empty() {
                    continue;
                }
                let around = around.expect("a restarted step has its linearisation");
                let entries: Vec<usize> = group.iter().map(|&i| around.entry_of(i)).collect();
                let l: Vec<f64> = group.iter().map(|&i| pending[i].doubled).collect();
                let from = around.select(&entries).candidates(&l);
                for (j, &i) in group.iter().enumerate() {
                    pending[i].candidate = Some((item(&from, j), None));
                }
            }
            evaluate(pending, &items);
            for &i in &items {
                doubling[i] = pending[i].rises(slack);
            }
        }
    }

    /// SPEC §6 step 3 for the frames `ks` (in `1..K`, no two adjacent) at once:
    /// `Q_k(x) = (K/δ)(D[f_{k−1}, x, φ_k] + D[x, f_{k+1}, φ_{k+1}])`, one gradient step per
    /// trial `L`, each channel block with its own `L` and search (`Q_k` restricted to the
    /// block's channels, still divided by `C_tot`).
    ///
    /// The blocks' searches run in lockstep on whole frames: `Q_k` is a sum over channels,
    /// so one forward and one backward give every block's value and gradient, and a round's
    /// trial is one frame in which each block takes its own trial step (a block already
    /// decided takes its accepted step again, the same values bit for bit). Each block is
    /// decided by its own float64 sums
    /// ([`crate::model::grid::Grid::decision_distance2_blocks`]); the prefilter and the
    /// channels-last evaluation give each channel the same values whatever other channels
    /// the frame holds, so the accepted frame, its `P x` and its `T[x, φ_k]` are those of
    /// the round that accepted its last block, with no joining of blocks. (Searched
    /// block by block, each block was a warp, a backward and a `cat` into the frame of its
    /// own: the `cat`s alone were 7.5 % of a deep sweep's feature steps.)
    ///
    /// `next`, when given, holds `P f_{k+1}` and `T[f_{k+1}, φ_{k+1}]` of every step (the
    /// previous sweep's feature step of `k + 1` computed them; neither has changed since);
    /// otherwise they are computed.
    pub(super) fn feature_steps(
        &self,
        state: &LevelState,
        ks: &[usize],
        next: Option<FrameProducts>,
    ) -> Result<FeatureSteps> {
        let n = ks.len();
        let grid = &self.grid;
        let bspline = self.energy.bspline();
        let bt = self.config.backtracking;
        let slack = self.slack();
        let c_tot = self.layout.channels();
        let blocks: Vec<Range<usize>> = self
            .layout
            .blocks()
            .iter()
            .map(|block| block.channels.clone())
            .collect();
        let nb = blocks.len();
        let delta = self.energy.params().delta;
        let steps = state.steps() as f64;
        let scale = steps / (delta * 2.0 * c_tot as f64 * grid.pixels() as f64);
        let f_k = take(&state.f, ks, 0);
        // φ_k (stored at k − 1) is already this sweep's, φ_{k+1} (at k) still the previous
        // one. Both stay fixed for the whole step: φ_k's stencil serves every trial, and
        // T[f_{k+1}, φ_{k+1}] does not depend on f_k at all.
        let phis = take(&state.phi, ks, -1);
        let sampler = bspline.sampler(phis.clone());
        let next = next.unwrap_or_else(|| {
            let coeffs = bspline.coefficients(take(&state.f, ks, 1));
            let warped = bspline
                .sampler(take(&state.phi, ks, 0))
                .sample(coeffs.clone());
            FrameProducts { coeffs, warped }
        });
        let before = take(&state.f, ks, -1);
        // The extrapolation (and below each trial's gradient step) gives the new frame's
        // distances to T[f_{k+1}, φ_{k+1}] with it: on flex one pass, folded as it is written.
        let (f_tilde, fixed) = if self.config.beta > 0.0 {
            let previous = take(&state.f_prev, ks, 0);
            let (f_tilde, fixed) = extrapolate_distance2(
                grid,
                f_k.clone(),
                previous,
                self.config.beta,
                &blocks,
                next.warped.clone(),
            );
            (f_tilde, Some(fixed))
        } else {
            (f_k.clone(), None)
        };

        let x_tilde = f_tilde.detach();
        let leaf = x_tilde.clone().require_grad();
        let warped = sampler.sample(bspline.coefficients(leaf.clone()));
        let warped_tilde = warped.clone().detach();
        // The squared norms of the residuals T[x̃, φ_k] − f_{k−1} and T[f_{k+1}, φ_{k+1}] − x̃
        // of each block as the decisions sum them, once: summed over the blocks they are also
        // the values of Q's data terms, whose ops then only differentiate (the residuals are
        // never tensors). The Q_k are independent: the gradient of their sum is each one's.
        let moved = grid.decision_distance2_blocks(warped_tilde.clone(), before.clone(), &blocks);
        let fixed = fixed.unwrap_or_else(|| {
            grid.decision_distance2_blocks(next.warped.clone(), x_tilde.clone(), &blocks)
        });
        let per_item = |t: &Tensor<1>| t.clone().reshape([n, nb]).sum_dim(1).reshape([n]);
        let q = (data_term_given(warped, before.clone(), c_tot, per_item(&moved))
            + data_term_given(next.warped.clone(), leaf.clone(), c_tot, per_item(&fixed)))
        .sum()
        .mul_scalar(steps / delta);
        let grads = q.backward();
        let grad = leaf.grad(&grads).expect("Q depends on f_k").autodiff();
        // Entry `i·nb + b`: item i, block b.
        let [moved, fixed, grad_norm2] = read_groups(
            grid,
            [
                moved,
                fixed,
                grid.decision_norm2_blocks(grad.clone(), &blocks),
            ],
        );
        let q_tilde: Vec<f64> = (0..n * nb).map(|e| (moved[e] + fixed[e]) * scale).collect();
        if let Some(e) =
            (0..n * nb).find(|&e| !(q_tilde[e].is_finite() && grad_norm2[e].is_finite()))
        {
            return Err(Error::NonFinite {
                what: format!(
                    "feature step k = {}, block {}: Q = {}, |grad Q|^2 = {}",
                    ks[e / nb],
                    e % nb,
                    q_tilde[e],
                    grad_norm2[e]
                ),
            });
        }

        // Each entry's residual norms of its last trial (the accepted one's once decided) and
        // accepted L; each item's last trial frame and, once every block accepted, that
        // frame with its P x and T[x, φ_k].
        let mut norms = vec![(f64::NAN, f64::NAN); n * nb];
        let mut accepted: Vec<Option<f64>> = vec![None; n * nb];
        let mut last: Vec<Option<Tensor<4>>> = vec![None; n];
        let mut whole: Vec<Option<(Tensor<4>, FrameProducts)>> = vec![None; n];
        let mut searches = Lockstep::new(
            (0..n * nb)
                .map(|e| Some(SearchRun::new(&bt, state.l_f[ks[e / nb] - 1][e % nb])))
                .collect(),
        );
        while let Some(trial) = searches.round() {
            let items = indices(n, |i| (0..nb).any(|b| trial[i * nb + b].is_some()));
            // A block out of trials takes x̃ (L = ∞): its values are replaced below.
            let l: Vec<f64> = items
                .iter()
                .flat_map(|&i| (i * nb..(i + 1) * nb).map(|e| trial[e].or(accepted[e])))
                .map(|l| l.unwrap_or(f64::INFINITY))
                .collect();
            let (candidates, to_next) = descend_distance2(
                grid,
                pick(&x_tilde, &items),
                pick(&grad, &items),
                &l,
                &blocks,
                pick(&next.warped, &items),
            );
            let coeffs = bspline.coefficients(candidates.clone());
            let trial_warped = if items.len() == n {
                sampler.sample(coeffs.clone())
            } else {
                bspline.sampler(pick(&phis, &items)).sample(coeffs.clone())
            };
            let [to_prev, moved] = grid.decision_distance2_blocks_pair(
                trial_warped.clone(),
                pick(&before, &items),
                pick(&warped_tilde, &items),
                &blocks,
            );
            let [to_prev, to_next, moved] = read_groups(grid, [to_prev, to_next, moved]);
            for (j, &i) in items.iter().enumerate() {
                for b in 0..nb {
                    let (e, at) = (i * nb + b, j * nb + b);
                    let Some(l) = trial[e] else { continue };
                    norms[e] = (to_prev[at], to_next[at]);
                    let q_new = (to_prev[at] + to_next[at]) * scale;
                    // x_new − x̃ = d = −∇Q/L: ⟨∇Q, d⟩ = −‖∇Q‖²/L, ‖d‖² = ‖∇Q‖²/L². Q is
                    // quadratic in f_k (T is linear in it), so Q(x̃ + d) − Q(x̃) − ⟨∇Q, d⟩ is
                    // exactly scale·(‖T[d, φ_k]‖² + ‖d‖²), with T[d, φ_k] = T[x_new, φ_k] −
                    // T[x̃, φ_k]. The test on that remainder is SPEC §6's test without the
                    // difference Q(x_new) − Q(x̃): near convergence float32 rounding of the
                    // warps made that difference exceed the decrease −‖∇Q‖²/(2L), every
                    // trial failed, L doubled until the decrease fell below float64's
                    // resolution of Q and the frame's features froze for the rest of the
                    // level (seen at 64², sweep 48).
                    let d2 = grad_norm2[e] / (l * l);
                    let remainder = scale * (moved[at] + d2);
                    let outcome =
                        if bt.accepts_remainder(q_new, q_tilde[e], remainder, d2, l, slack) {
                            accepted[e] = Some(l);
                            Trial::Accepted(())
                        } else {
                            Trial::Rejected
                        };
                    searches.record(e, outcome);
                }
                let candidate = item(&candidates, j);
                if accepted[i * nb..(i + 1) * nb].iter().all(Option::is_some) {
                    let products = FrameProducts {
                        coeffs: item(&coeffs, j),
                        warped: item(&trial_warped, j),
                    };
                    whole[i] = Some((candidate.clone(), products));
                }
                last[i] = Some(candidate);
            }
        }
        let mut searched = searches.finish().into_iter();
        let mut frames = Vec::with_capacity(n);
        let mut records = Vec::with_capacity(n);
        let mut own = Vec::with_capacity(n);
        for i in 0..n {
            let mut record = FeatureStep {
                lipschitz: Vec::new(),
                trials: Vec::new(),
                dropped: Vec::new(),
                residual_norm2: Some((0.0, 0.0)),
            };
            for b in 0..nb {
                let search = searched
                    .next()
                    .flatten()
                    .expect("every block of every frame searches");
                let e = i * nb + b;
                record.dropped.push(search.accepted.is_none());
                record.lipschitz.push(search.lipschitz);
                record.trials.push(search.trials);
                record.residual_norm2 = match (record.residual_norm2, search.accepted) {
                    (Some((moved, fixed)), Some(())) => {
                        Some((moved + norms[e].0, fixed + norms[e].1))
                    }
                    _ => None,
                };
            }
            records.push(record);
            match whole[i].take() {
                Some((frame, products)) => {
                    frames.push(frame);
                    own.push(Some(products));
                }
                None => {
                    // A block whose search gave up keeps its current values: the frame is
                    // joined from the accepted blocks of the last trial and f_k's others.
                    let last = last[i].take().expect("every frame ran a trial");
                    let parts = blocks
                        .iter()
                        .enumerate()
                        .map(|(b, block)| {
                            let from = if accepted[i * nb + b].is_some() {
                                last.clone()
                            } else {
                                item(&f_k, i)
                            };
                            from.narrow(1, block.start, block.len())
                        })
                        .collect();
                    frames.push(Tensor::cat(parts, 1));
                    own.push(None);
                }
            }
        }
        Ok(FeatureSteps {
            frames,
            steps: records,
            next,
            own,
        })
    }
}
