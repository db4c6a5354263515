//! One level of the iPALM solver (SPEC §6, the paper's Algorithm 1).
//!
//! [`Ipalm`] holds the level's operators and the configuration and performs one sweep
//! ([`Ipalm::sweep`]) on a [`LevelState`]; the loop over sweeps, termination, progress and
//! interruption belong to the caller (the multilevel driver), as in argmin's split between
//! solver and executor.
//!
//! Every accept/reject decision compares scalars summed by [`Grid::decision_sum`]: in
//! float64 on the CPU backends (no slack), in float32 with the relative slack
//! [`Backtracking::float32_slack`] on wgpu. Each trial reads its scalars back in one
//! transfer.

use burn::tensor::Tensor;

use crate::error::{Error, Result};
use crate::model::energy::landmarks::LandmarkTerm;
use crate::model::energy::path::{EnergyValue, PathEnergy, StepEnergies};
use crate::model::energy::regularizer::weighted_density;
use crate::model::grid::to_host;
use crate::model::grid::{Accumulation, Grid};
use crate::model::layout::FeatureLayout;
use crate::model::params::EnergyParams;
use crate::model::sobel::Sobel;
use crate::solver::backtracking::Backtracking;
use crate::solver::steps::{FeatureSteps, FrameProducts};

/// The solver's settings beyond the energy (SPEC §6, §9).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IpalmConfig {
    /// Inertial extrapolation `β`, in `[0, 1)`. Default `1/√2`.
    pub beta: f64,
    /// The safeguard of SPEC §6: after a deformation step is accepted, compare the true
    /// local energy with its value at the current `φ_k`; on a rise restart the inertia of
    /// that `k`, then double `L` while it still rises. Default on; off is the paper's plain
    /// algorithm (and the golden sweeps).
    pub safeguard: bool,
    /// Doublings of the safeguard before the step is dropped (`φ_k` kept). Default 30.
    pub safeguard_max: usize,
    /// The backtracking rule of both steps.
    pub backtracking: Backtracking,
    /// The order of the blocks in a sweep. Default [`Schedule::Sequential`].
    pub schedule: Schedule,
}

impl Default for IpalmConfig {
    fn default() -> Self {
        Self {
            beta: std::f64::consts::FRAC_1_SQRT_2,
            safeguard: true,
            safeguard_max: 30,
            backtracking: Backtracking::default(),
            schedule: Schedule::Sequential,
        }
    }
}

/// The order in which a sweep updates the blocks. Both are iPALM with the same energy, the
/// same steps (SPEC §6 step 2 and 3 for each `k`) and the same admissibility guarantee; they
/// differ in which values each block sees.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Schedule {
    /// The paper's Algorithm 1: `k = 1..K` in order, `φ_k` then `f_k`, each step seeing the
    /// already-updated blocks before it: `2K − 1` blocks per sweep.
    Sequential,
    /// Three blocks per sweep: every `φ_k` at once (given the frames they are independent),
    /// then every odd `f_k`, then every even `f_k` (given the deformations and the other
    /// parity, those are independent too). Each block is one operation on stacked
    /// `[n, C, H, W]` tensors, with a Lipschitz estimate, backtracking and safeguard per `k`.
    Batched,
}

impl IpalmConfig {
    /// Checks the ranges.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] naming the bad field.
    pub fn validate(&self) -> Result<()> {
        if !(0.0..1.0).contains(&self.beta) {
            return Err(Error::invalid("beta", self.beta, "in [0, 1)"));
        }
        if self.safeguard_max > 1000 {
            return Err(Error::invalid(
                "safeguard_max",
                self.safeguard_max,
                "in 0..=1000 (L doubles per step)",
            ));
        }
        self.backtracking.validate()
    }
}

/// The iterate of one level: frames, deformations, their values of the previous sweep, and
/// the stored Lipschitz estimates.
#[derive(Clone, Debug)]
pub struct LevelState {
    /// `f_0..f_K`, each `[1, C_tot, H, W]`; `f_0` and `f_K` never change.
    pub f: Vec<Tensor<4>>,
    /// `f_k` of the previous sweep.
    pub f_prev: Vec<Tensor<4>>,
    /// `φ_1..φ_K` (index `k − 1`), each `[1, 2, H, W]`.
    pub phi: Vec<Tensor<4>>,
    /// `φ_k` of the previous sweep.
    pub phi_prev: Vec<Tensor<4>>,
    /// Stored `L_φ,k`, `k = 1..K`.
    pub l_phi: Vec<f64>,
    /// Stored `L_f,k` per block, `k = 1..K−1`.
    pub l_f: Vec<Vec<f64>>,
    /// The streak `m` of each deformation search, `k = 1..K` (SPEC §6, "Where a search
    /// starts"): the sweeps in a row on this level whose search for `φ_k` accepted its first
    /// trial with no safeguard restart. The next search starts from `0.9^(m+1)·L_φ,k`. Zero
    /// in a new state (a new level).
    pub phi_streak: Vec<u32>,
}

impl LevelState {
    /// A state with `prev = current`.
    ///
    /// # Errors
    ///
    /// If the counts do not fit (`K + 1` frames, `K` deformations, `K` and `K − 1` estimates).
    pub fn new(
        f: Vec<Tensor<4>>,
        phi: Vec<Tensor<4>>,
        l_phi: Vec<f64>,
        l_f: Vec<Vec<f64>>,
    ) -> Result<Self> {
        let k = phi.len();
        if k == 0 || f.len() != k + 1 || l_phi.len() != k || l_f.len() != k - 1 {
            return Err(Error::Shape {
                op: "LevelState::new",
                detail: format!(
                    "{} frames, {} deformations, {} L_phi, {} L_f: expected K+1, K, K, K-1",
                    f.len(),
                    k,
                    l_phi.len(),
                    l_f.len()
                ),
            });
        }
        Ok(Self {
            f_prev: f.clone(),
            phi_prev: phi.clone(),
            f,
            phi,
            l_phi,
            l_f,
            phi_streak: vec![0; k],
        })
    }

    /// Takes the deformation step of `k` (`1..=K`): `φ_k^prev ← φ_k`, `φ_k ← φ_new`, the
    /// stored `L_φ,k` and the streak of SPEC §6. Both schedules apply their steps here, so
    /// the rule of where the next search starts is written once.
    ///
    /// `φ_k^prev ← φ_k` also after a restart: the next sweep then extrapolates along the
    /// restarted step, not the rejected direction (SPEC §6).
    pub(super) fn apply_deformation(
        &mut self,
        k: usize,
        phi_new: Tensor<4>,
        step: &DeformationStep,
    ) {
        let i = k - 1;
        self.l_phi[i] = step.lipschitz;
        self.phi_streak[i] = if step.accepted_first_trial() {
            step.streak + 1
        } else {
            0
        };
        self.phi_prev[i] = std::mem::replace(&mut self.phi[i], phi_new);
    }

    /// The initial state of SPEC §6/§7: `φ_k = Id`, `f_k = (1 − k/K) f_A + (k/K) f_B`, prev
    /// = current, and the initial Lipschitz estimates of [`initial_lipschitz`].
    ///
    /// # Shapes
    /// - `f_a`, `f_b`: `[1, C_tot, H, W]`
    pub fn initial(
        grid: &Grid,
        layout: &FeatureLayout,
        f_a: Tensor<4>,
        f_b: Tensor<4>,
        k: usize,
        delta: f64,
    ) -> Result<Self> {
        let f = (0..=k)
            .map(|step| {
                let t = step as f64 / k as f64;
                match step {
                    0 => f_a.clone(),
                    s if s == k => f_b.clone(),
                    _ => f_a.clone().mul_scalar(1.0 - t) + f_b.clone().mul_scalar(t),
                }
            })
            .collect();
        let phi = vec![grid.identity(1); k];
        let (l_phi, l_f) = initial_lipschitz(grid, layout, k, delta);
        Self::new(f, phi, l_phi, l_f)
    }

    /// `K`.
    pub fn steps(&self) -> usize {
        self.phi.len()
    }

    /// `f_0..f_K` as one `[K+1, C_tot, H, W]` tensor.
    pub fn frames(&self) -> Tensor<4> {
        Tensor::cat(self.f.clone(), 0)
    }

    /// `φ_1..φ_K` as one `[K, 2, H, W]` tensor.
    pub fn deformations(&self) -> Tensor<4> {
        Tensor::cat(self.phi.clone(), 0)
    }
}

/// The initial estimates of SPEC §6 on a level: `L_φ,k = 1/(H·W)` and, for every feature
/// block, `L_f,k = 2K/(δ·C_tot·H·W)`, the curvature of `(K/δ)(D_k + D_{k+1})` in `f_k` with
/// `‖T‖ ≈ 1`, whatever the block's scale.
pub fn initial_lipschitz(
    grid: &Grid,
    layout: &FeatureLayout,
    k: usize,
    delta: f64,
) -> (Vec<f64>, Vec<Vec<f64>>) {
    let pixels = grid.pixels() as f64;
    let l_f = 2.0 * k as f64 / (delta * layout.channels() as f64 * pixels);
    (
        vec![1.0 / pixels; k],
        vec![vec![l_f; layout.blocks().len()]; k.saturating_sub(1)],
    )
}

/// Which steps a sweep runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SweepKind {
    /// Anisotropy, deformation and feature steps for every `k` (SPEC §6).
    Joint,
    /// Only the feature steps, deformations fixed (the deep model's `J_pre` sweeps, SPEC §7).
    FeaturesOnly,
}

/// What the deformation step of one `k` did.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DeformationStep {
    /// The streak `m` the search started with: its first trial was `0.9^(m+1)` times the
    /// stored `L_φ,k` (SPEC §6, "Where a search starts").
    pub streak: u32,
    /// The `L_φ,k` stored for the next sweep: the one the backtracking accepted (not the
    /// safeguard's doubled value), or the one the step started from if it was dropped.
    pub lipschitz: f64,
    /// Trial values of `L` of the backtracking (1 = the first trial was accepted), counting
    /// both searches when the inertia was restarted.
    pub trials: usize,
    /// How many of those trials gave an inadmissible `φ_new`.
    pub inadmissible_trials: usize,
    /// Whether the safeguard restarted the inertia (SPEC §6: `φ̃ = φ_k`).
    pub restarted: bool,
    /// Doublings of `L` by the safeguard after acceptance.
    pub safeguard_doublings: usize,
    /// Whether the step was dropped (`φ_k` kept): backtracking or safeguard exhausted.
    pub dropped: bool,
    /// `‖T[f_k, φ] − f_{k−1}‖²` (summed for decisions) at the `φ` the step returned, from the
    /// safeguard's last local energy; `None` where the step did not evaluate it (safeguard
    /// off, or dropped before the safeguard ran).
    pub residual_norm2: Option<f64>,
}

impl DeformationStep {
    /// Whether the search accepted its first trial with no safeguard restart and the step
    /// was taken: what extends the streak of SPEC §6 (anything else resets it).
    pub fn accepted_first_trial(&self) -> bool {
        self.trials == 1 && !self.restarted && !self.dropped
    }
}

/// What the feature step of one `k` did, per block.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FeatureStep {
    /// The `L_f,k` stored for each block: accepted, or the starting one if it gave up.
    pub lipschitz: Vec<f64>,
    /// Trials of each block until acceptance.
    pub trials: Vec<usize>,
    /// Whether each block's search gave up (its values kept).
    pub dropped: Vec<bool>,
    /// The squared residual norms of the accepted `f_new`, summed over the blocks for
    /// decisions: `‖T[f_new, φ_k] − f_{k−1}‖²` and `‖T[f_{k+1}, φ_{k+1}] − f_new‖²`; `None` if
    /// a block kept its values (its residuals at `f_k` were never evaluated).
    pub residual_norm2: Option<(f64, f64)>,
}

/// The record of one sweep.
#[derive(Clone, Debug)]
pub struct SweepReport {
    /// The anisotropies `a_1..a_K` of step 1, `[1, H, W]` each (empty for a features-only
    /// sweep; a sweep continued from a [`PartialSweep`] has those of the steps it ran).
    pub anisotropy: Vec<Tensor<3>>,
    /// Deformation steps, `k = 1..K` (empty for a features-only sweep).
    pub deformation: Vec<DeformationStep>,
    /// Feature steps, `k = 1..K−1`.
    pub features: Vec<FeatureStep>,
    /// `‖T[f_k, φ_k] − f_{k−1}‖²`, `k = 1..K`, of the state the sweep leaves behind, summed for
    /// decisions by the last step of the sweep that changed `f_{k−1}`, `f_k` or `φ_k` (or by
    /// an earlier one if none did); `None` where that step did not evaluate it. What
    /// [`Ipalm::energy_after`] reuses instead of warping every frame again.
    pub residual_norm2: Vec<Option<f64>>,
}

impl SweepReport {
    /// A report of a sweep of `K` steps with nothing recorded yet.
    pub(super) fn empty(k: usize) -> Self {
        Self {
            anisotropy: Vec::new(),
            deformation: Vec::new(),
            features: Vec::new(),
            residual_norm2: vec![None; k],
        }
    }

    /// Records the deformation step of `k`: only `D_k` depends on `φ_k`, and a dropped step
    /// that did not evaluate it left it as it was.
    pub(super) fn record_deformation(&mut self, k: usize, step: DeformationStep) {
        if !(step.dropped && step.residual_norm2.is_none()) {
            self.residual_norm2[k - 1] = step.residual_norm2;
        }
        self.deformation.push(step);
    }

    /// Records the feature step of `k`: `f_k` enters `D_k` and `D_{k+1}`.
    fn record_features(&mut self, k: usize, step: FeatureStep) {
        self.record_residuals(k, step.residual_norm2);
        self.features.push(step);
    }

    /// Records the squared residual norms a feature step of `k` left: those of `D_k` and
    /// `D_{k+1}`, or neither.
    pub(super) fn record_residuals(&mut self, k: usize, norms: Option<(f64, f64)>) {
        self.residual_norm2[k - 1] = norms.map(|(moved, _)| moved);
        self.residual_norm2[k] = norms.map(|(_, fixed)| fixed);
    }

    /// Deformation steps whose inertia the safeguard restarted.
    pub fn restarts(&self) -> usize {
        self.deformation.iter().filter(|s| s.restarted).count()
    }

    /// Deformation steps dropped (`φ_k` kept).
    pub fn deformation_drops(&self) -> usize {
        self.deformation.iter().filter(|s| s.dropped).count()
    }

    /// Trials of the sweep's deformation searches, both searches of a restarted step
    /// counted (`K` where every search accepted its first trial).
    pub fn deformation_trials(&self) -> usize {
        self.deformation.iter().map(|s| s.trials).sum()
    }

    /// Trials of the sweep's feature searches, over every block of every `k`.
    pub fn feature_trials(&self) -> usize {
        self.features.iter().flat_map(|s| &s.trials).sum()
    }

    /// Feature blocks whose search gave up.
    pub fn feature_drops(&self) -> usize {
        self.features
            .iter()
            .map(|s| s.dropped.iter().filter(|&&d| d).count())
            .sum()
    }
}

/// The blocks of a sweep that ran before it was stopped ([`Ipalm::sweep_until`]), and what
/// they did: with the state they left, enough to finish the sweep later exactly as it would
/// have run (`--resume` after an interrupt within a sweep, issue 43 #10).
///
/// The blocks are counted in the schedule's order: sequential `φ_1, f_1, φ_2, …, f_{K−1},
/// φ_K` (a features-only sweep: `f_1 … f_{K−1}`), batched all `φ`, the odd `f`, the even
/// `f`.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PartialSweep {
    /// Blocks run.
    pub blocks: usize,
    /// [`SweepReport::deformation`] so far.
    pub deformation: Vec<DeformationStep>,
    /// [`SweepReport::features`] so far (batched: the odd `k` in order).
    pub features: Vec<FeatureStep>,
    /// [`SweepReport::residual_norm2`] so far.
    pub residual_norm2: Vec<Option<f64>>,
}

impl PartialSweep {
    /// The first `blocks` blocks of the sweep that `report` records.
    pub(super) fn of(report: SweepReport, blocks: usize) -> Self {
        Self {
            blocks,
            deformation: report.deformation,
            features: report.features,
            residual_norm2: report.residual_norm2,
        }
    }

    /// The report to go on with (no anisotropies: those of the blocks run are not kept).
    fn into_report(self) -> SweepReport {
        SweepReport {
            anisotropy: Vec::new(),
            deformation: self.deformation,
            features: self.features,
            residual_norm2: self.residual_norm2,
        }
    }

    /// The cursor over the blocks of a sweep going on from `from` (from its first block when
    /// `None`), asking `stop` as [`Ipalm::sweep_until`] says, and the report so far; `k` steps
    /// if nothing ran yet.
    pub(super) fn start<'s>(
        from: Option<Self>,
        k: usize,
        stop: &'s dyn Fn() -> bool,
    ) -> (Blocks<'s>, SweepReport) {
        let (first, report) = match from {
            Some(partial) => (partial.blocks, partial.into_report()),
            None => (0, SweepReport::empty(k)),
        };
        let blocks = Blocks {
            next: 0,
            first,
            stop,
        };
        (blocks, report)
    }
}

/// The blocks of one call of [`Ipalm::sweep_until`], taken in the schedule's order: the rule
/// of which ran in an earlier call, which runs now, and before which the sweep stops, kept in
/// one place for both schedules.
pub(super) struct Blocks<'s> {
    /// The index of the block [`next`](Self::next) hands out.
    next: usize,
    /// The first block this call runs: the blocks before it ran in the call that stopped.
    first: usize,
    stop: &'s dyn Fn() -> bool,
}

/// What to do with a sweep's next block.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Block {
    /// It ran before this call: take its results from the report.
    Ran,
    /// Run it.
    Run,
    /// Stop the sweep before it; `blocks` ran ([`PartialSweep::blocks`]).
    Stop { blocks: usize },
}

impl Blocks<'_> {
    /// The next block: `stop` is asked before every block after the first this call runs,
    /// except one with no work (`empty`, a pass over no frame), which never stops a sweep.
    pub(super) fn next(&mut self, empty: bool) -> Block {
        let block = self.next;
        self.next += 1;
        if block < self.first {
            Block::Ran
        } else if block > self.first && !empty && (self.stop)() {
            Block::Stop { blocks: block }
        } else {
            Block::Run
        }
    }
}

/// How a call of [`Ipalm::sweep_until`] ended.
#[derive(Clone, Debug)]
pub enum SweepEnd {
    /// The sweep ran to its end.
    Done(SweepReport),
    /// It was stopped between two blocks; the state holds the blocks run.
    Stopped(PartialSweep),
}

/// The iPALM solver on one level.
#[derive(Clone, Debug)]
pub struct Ipalm {
    pub(super) grid: Grid,
    pub(super) energy: PathEnergy,
    pub(super) layout: FeatureLayout,
    pub(super) sobel: Sobel,
    pub(super) config: IpalmConfig,
    /// SPEC §11's landmark term on this level, part of every `S_k` and `E`.
    pub(super) landmarks: Option<LandmarkTerm>,
}

/// Several `[1]` tensors read back from the device in one transfer, as float64 where the
/// backend has it (decision sums already are).
pub(super) fn read_scalars(grid: &Grid, parts: Vec<Tensor<1>>) -> Vec<f64> {
    let dtype = match grid.accumulation() {
        Accumulation::Float64 => burn::tensor::FloatDType::F64,
        Accumulation::Float32 => burn::tensor::FloatDType::F32,
    };
    to_host(Tensor::cat(
        parts.into_iter().map(|t| t.detach().cast(dtype)).collect(),
        0,
    ))
}

/// `P` groups of scalars (`[n_p]` tensors, e.g. one value per batch item) read back in one
/// transfer, as [`read_scalars`] does, and handed back group by group, so that a caller
/// names what it reads (`let [min_det, smooth, inner, norm2] = …`) instead of indexing one
/// flat vector by position.
pub(super) fn read_groups<const P: usize>(grid: &Grid, parts: [Tensor<1>; P]) -> [Vec<f64>; P] {
    let lengths = parts.each_ref().map(|t| t.dims()[0]);
    let values = read_scalars(grid, parts.into());
    let mut at = 0;
    lengths.map(|n| {
        at += n;
        values[at - n..at].to_vec()
    })
}

/// The one result of a step run for one `k`.
fn one_step<T>(results: Vec<T>) -> [T; 1] {
    let n = results.len();
    results
        .try_into()
        .unwrap_or_else(|_| unreachable!("a step of one k gave {n} results"))
}

impl Ipalm {
    /// The solver on `grid` (whose device must have autodiff enabled: the steps take
    /// gradients) for features laid out as `layout`.
    ///
    /// # Errors
    ///
    /// If a parameter is out of range.
    pub fn new(
        grid: &Grid,
        params: EnergyParams,
        layout: FeatureLayout,
        config: IpalmConfig,
    ) -> Result<Self> {
        config.validate()?;
        Ok(Self {
            grid: grid.clone(),
            energy: PathEnergy::new(grid, params, layout.channels())?,
            sobel: Sobel::new(grid),
            layout,
            config,
            landmarks: None,
        })
    }

    /// The solver with SPEC §11's landmark term `term` (on this level's grid, for its `K`)
    /// in the smooth part of every deformation step and in `E`.
    pub fn with_landmarks(mut self, term: LandmarkTerm) -> Self {
        self.landmarks = Some(term);
        self
    }

    /// The landmark term, if any.
    pub fn landmarks(&self) -> Option<&LandmarkTerm> {
        self.landmarks.as_ref()
    }

    /// The path energy of this level.
    pub fn path_energy(&self) -> &PathEnergy {
        &self.energy
    }

    /// The configuration.
    pub fn config(&self) -> &IpalmConfig {
        &self.config
    }

    /// The relative slack of the decision tests on this grid: none where the sums are
    /// accumulated in float64 (SPEC §6, "Floating point").
    pub(super) fn slack(&self) -> f64 {
        match self.grid.accumulation() {
            Accumulation::Float64 => 0.0,
            Accumulation::Float32 => self.config.backtracking.float32_slack,
        }
    }

    /// `a_k = a[u_k]` for the frames `f_1..f_K` of `state`, `[K, H, W]`.
    pub fn anisotropies(&self, state: &LevelState) -> Tensor<3> {
        let k = state.steps();
        self.energy
            .anisotropy()
            .compute(self.layout.rgb_parts(&state.f[1..=k]))
    }

    /// `E` of `state` with every `a_k` recomputed from its `f_k` (SPEC §10: the energy after
    /// a sweep), as the float32 tensors of [`PathEnergy::value`]. Their sums are float32 too:
    /// on a deep 256² path (67 channels) this read 0.23 % below the float64 sum of the same
    /// residuals; the driver logs [`energy_after`](Self::energy_after).
    pub fn energy(&self, state: &LevelState) -> EnergyValue {
        let mut value = self.energy.value(
            state.frames(),
            state.deformations(),
            self.anisotropies(state),
        );
        if let Some(term) = &self.landmarks {
            value.total = value.total + term.energy(state.deformations());
        }
        value
    }

    /// `E` of `state` after a sweep by steps, in float64 (SPEC §10: every `a_k` recomputed
    /// from its `f_k`): the value [`energy`](Self::energy) gives up to its float32 rounding.
    ///
    /// With the `report` of the sweep that left `state`, each `D_k` the sweep already
    /// evaluated at the final iterate ([`SweepReport::residual_norm2`]: every one in a
    /// sequential sweep without a dropped block or a deformation step the safeguard did not
    /// check) is taken from it instead of warping `f_k` again: in the deep model those warps
    /// of every channel were a quarter of a sweep's time at 256². The rest, and all of them
    /// without a report, are evaluated here.
    pub fn energy_after(&self, state: &LevelState, report: Option<&SweepReport>) -> StepEnergies {
        self.energy_after_carrying(state, report, &mut SweepCarry::default())
    }

    /// [`energy_after`](Self::energy_after), leaving the anisotropies it computed in `carry`
    /// for the next sweep of `state` ([`SweepCarry`]); `carry` must be the one that sweep
    /// will be given, and `state` must not change in between.
    pub fn energy_after_carrying(
        &self,
        state: &LevelState,
        report: Option<&SweepReport>,
        carry: &mut SweepCarry,
    ) -> StepEnergies {
        let k = state.steps();
        let grid = &self.grid;
        let p = self.energy.params();
        let known = report.map_or_else(|| vec![None; k], |r| r.residual_norm2.clone());
        let missing: Vec<usize> = (0..k).filter(|&i| known[i].is_none()).collect();
        let anisotropy = self.anisotropies(state);
        carry.anisotropy = Some(anisotropy.clone());
        let mut parts = vec![grid.decision_sum_each(weighted_density(
            state.deformations(),
            anisotropy,
            p.lambda,
            p.mu,
        ))];
        if !missing.is_empty() {
            parts.extend(
                self.energy
                    .residual_norms(grid, &state.f, &state.phi, &missing),
            );
        }
        if let Some(term) = &self.landmarks {
            parts.push(term.energy(state.deformations()));
        }
        let v = read_scalars(grid, parts);
        let landmarks = match self.landmarks {
            Some(_) => v[v.len() - 1],
            None => 0.0,
        };
        let pixels = grid.pixels() as f64;
        let mut evaluated = v[k..].iter();
        let data_scale = 1.0 / (2.0 * self.layout.channels() as f64 * pixels);
        StepEnergies {
            regularizer: v[..k].iter().map(|r| r / pixels).collect(),
            data: known
                .iter()
                .map(|n| {
                    n.unwrap_or_else(|| *evaluated.next().expect("one value per missing D_k"))
                        * data_scale
                })
                .collect(),
            delta: p.delta,
            landmarks,
        }
    }

    /// One sweep over `k = 1..K` (SPEC §6), updating `state` in place.
    ///
    /// # Errors
    ///
    /// [`Error::NonFinite`] if a NaN or infinity shows up in an energy or gradient of the
    /// state. Every step is applied only once it is known to be finite, so `state` is then a
    /// finite iterate: the steps `1..k−1` of this sweep done, the rest as before.
    pub fn sweep(&self, state: &mut LevelState, kind: SweepKind) -> Result<SweepReport> {
        self.sweep_carrying(state, kind, &mut SweepCarry::default())
    }

    /// [`sweep`](Self::sweep), starting from what the previous sweep of the same state left
    /// in `carry` and leaving there what the next one can start from (sequential schedule;
    /// the batched one empties it). The iterate is the same, bit for bit, as without it.
    ///
    /// `carry` must have come from sweeps of this `state` only, with nothing else changing
    /// it in between: a new level, a resumed or edited state starts from an empty one.
    ///
    /// # Errors
    ///
    /// As [`sweep`](Self::sweep); `carry` is then empty.
    pub fn sweep_carrying(
        &self,
        state: &mut LevelState,
        kind: SweepKind,
        carry: &mut SweepCarry,
    ) -> Result<SweepReport> {
        match self.sweep_until(state, kind, carry, None, &|| false)? {
            SweepEnd::Done(report) => Ok(report),
            SweepEnd::Stopped(_) => unreachable!("a sweep that is never asked to stop ends"),
        }
    }

    /// [`sweep_carrying`](Self::sweep_carrying), asking `stop` between blocks and stopping
    /// there when it says so ([`SweepEnd::Stopped`]: the state then holds the blocks run, a
    /// valid iterate), and going on from `from`, the blocks a stopped sweep of this `state`
    /// ran: the iterate and the report are then the ones of the sweep run without a stop, bit
    /// for bit (those anisotropies aside). At least one block runs per call, and after the
    /// last block the sweep ends whatever `stop` says.
    ///
    /// # Errors
    ///
    /// As [`sweep`](Self::sweep); `carry` is then empty.
    pub fn sweep_until(
        &self,
        state: &mut LevelState,
        kind: SweepKind,
        carry: &mut SweepCarry,
        from: Option<PartialSweep>,
        stop: &dyn Fn() -> bool,
    ) -> Result<SweepEnd> {
        if self.config.schedule == Schedule::Batched {
            let anisotropy = carry.anisotropy.take();
            carry.clear();
            return self.sweep_batched(state, kind, anisotropy, from, stop);
        }
        if from.is_some() {
            // What a sweep carries is for one that starts at its first block.
            carry.clear();
        }
        let result = self.sweep_sequential(state, kind, carry, from, stop);
        if result.is_err() {
            carry.clear();
        }
        result
    }

    /// The sequential schedule's sweep (SPEC §6, Algorithm 1).
    fn sweep_sequential(
        &self,
        state: &mut LevelState,
        kind: SweepKind,
        carry: &mut SweepCarry,
        from: Option<PartialSweep>,
        stop: &dyn Fn() -> bool,
    ) -> Result<SweepEnd> {
        let k_steps = state.steps();
        let (mut cursor, mut report) = PartialSweep::start(from, k_steps, stop);
        carry.fit(k_steps);
        // What the feature step of k computed that the deformation step of k + 1 needs; for
        // k = 1, what the previous sweep's feature step of 1 left (φ_1 and f_1 unchanged).
        let mut carried: Option<FrameProducts> = carry.take(1);
        // Every a_k at once: step k reads f_k before its feature step changes it, so these are
        // the values a computation at step k would give (a frame's anisotropy does not depend
        // on the batch it is computed in). A continued sweep's f_k of the steps to come are
        // unchanged too.
        let anisotropy = carry.anisotropy.take();
        let anisotropy = (kind == SweepKind::Joint)
            .then(|| anisotropy.unwrap_or_else(|| self.anisotropies(state)));
        for k in 1..=k_steps {
            if let Some(anisotropy) = &anisotropy {
                match cursor.next(false) {
                    Block::Stop { blocks } => {
                        return Ok(SweepEnd::Stopped(PartialSweep::of(report, blocks)));
                    }
                    Block::Ran => {}
                    Block::Run => {
                        let a = anisotropy.clone().narrow(0, k - 1, 1);
                        let [(phi_new, step, products)] = one_step(self.deformation_steps(
                            state,
                            &[k],
                            a.clone(),
                            carried.take(),
                            k == k_steps,
                        )?);
                        if k == k_steps {
                            carry.put(k, products);
                        }
                        state.apply_deformation(k, phi_new, &step);
                        report.anisotropy.push(a);
                        report.record_deformation(k, step);
                    }
                }
            }
            if k < k_steps {
                match cursor.next(false) {
                    Block::Stop { blocks } => {
                        return Ok(SweepEnd::Stopped(PartialSweep::of(report, blocks)));
                    }
                    Block::Ran => {}
                    Block::Run => {
                        let FeatureSteps {
                            frames,
                            steps,
                            next,
                            own,
                        } = self.feature_steps(state, &[k], carry.take(k + 1))?;
                        let ([f_new], [step], [own]) =
                            (one_step(frames), one_step(steps), one_step(own));
                        carried = Some(next);
                        carry.put(k, own);
                        state.l_f[k - 1] = step.lipschitz.clone();
                        state.f_prev[k] = std::mem::replace(&mut state.f[k], f_new);
                        report.record_features(k, step);
                    }
                }
            }
        }
        if let Some(products) = carried {
            // The deformation step of K did not run (a feature sweep): P f_K and
            // T[f_K, φ_K] still hold for the next sweep's feature step of K − 1.
            carry.put(k_steps, Some(products));
        }
        Ok(SweepEnd::Done(report))
    }
}

/// What a sequential sweep leaves for the next sweep of the same state: for each `k`
/// (`1..K`) whose feature step accepted a trial in every block, `P f_k` and `T[f_k, φ_k]`
/// as that trial computed them. The next sweep's feature step of `k − 1` needs exactly these
/// (`f_k` and `φ_k` change only after it), and its deformation step of `k = 1` too: one
/// prefilter and one warp of all channels fewer per feature step. For `k = K` (`f_K = B`
/// never changes) they are `P f_K` and the warp at the new `φ_K` that the safeguard of the
/// deformation step of `K` evaluated. Costs `2·K` frames of memory (SPEC §6 is unchanged:
/// the values are the ones that would be recomputed).
///
/// The energy evaluated after a sweep ([`Ipalm::energy_after_carrying`]) leaves here the
/// anisotropies `a[f_1] … a[f_K]` of the state it evaluated: the next sweep's deformation
/// steps need exactly these (step `k` reads `f_k` before its feature step changes it), so
/// each frame's anisotropy is computed once per sweep instead of twice.
///
/// See [`Ipalm::sweep_carrying`].
#[derive(Debug, Default)]
pub struct SweepCarry {
    products: Vec<Option<FrameProducts>>,
    /// `a_1..a_K` of the state as it is, `[K, H, W]`.
    anisotropy: Option<Tensor<3>>,
}

impl SweepCarry {
    /// Forgets everything: the next sweep computes what it needs.
    pub fn clear(&mut self) {
        self.products.clear();
        self.anisotropy = None;
    }

    /// Whether anything is held.
    pub fn is_empty(&self) -> bool {
        self.products.iter().all(Option::is_none) && self.anisotropy.is_none()
    }

    /// Room for `k_steps` (a carry of another `K` is forgotten).
    fn fit(&mut self, k_steps: usize) {
        if self.products.len() != k_steps + 1 {
            self.products = vec![None; k_steps + 1];
        }
    }

    /// What is held for `k`, removed.
    fn take(&mut self, k: usize) -> Option<FrameProducts> {
        self.products.get_mut(k).and_then(Option::take)
    }

    /// Holds `products` for `k`.
    fn put(&mut self, k: usize, products: Option<FrameProducts>) {
        self.products[k] = products;
    }
}

#[cfg(test)]
mod tests {
    use std::cell::Cell;

    use super::{Block, PartialSweep};

    #[test]
    fn blocks_skip_what_ran_and_ask_to_stop_only_after_the_first_they_run() {
        let asked = Cell::new(0);
        let stop = || {
            asked.set(asked.get() + 1);
            true
        };
        let ran = PartialSweep {
            blocks: 2,
            deformation: Vec::new(),
            features: Vec::new(),
            residual_norm2: Vec::new(),
        };
        let (mut cursor, _) = PartialSweep::start(Some(ran), 3, &stop);
        assert_eq!(cursor.next(false), Block::Ran);
        assert_eq!(cursor.next(false), Block::Ran);
        // At least one block runs per call, whatever `stop` says.
        assert_eq!(cursor.next(false), Block::Run);
        assert_eq!(asked.get(), 0);
        // A pass over no frame never stops a sweep.
        assert_eq!(cursor.next(true), Block::Run);
        assert_eq!(asked.get(), 0);
        assert_eq!(cursor.next(false), Block::Stop { blocks: 4 });
        assert_eq!(asked.get(), 1);

        let (mut fresh, _) = PartialSweep::start(None, 3, &stop);
        assert_eq!(fresh.next(false), Block::Run);
        assert_eq!(fresh.next(false), Block::Stop { blocks: 1 });
    }
}
