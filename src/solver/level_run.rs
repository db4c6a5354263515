//! One level of a morph as a state machine (SPEC §6, §7), in argmin's split between solver
//! and executor: a [`LevelRun`] is set up by [`LevelRun::init`] from how its state began
//! ([`LevelStart`]), advances one sweep per [`LevelRun::next_sweep`], and says when its
//! phases are over; the executor ([`Multilevel`](super::multilevel::Multilevel)) decides
//! when to stop (the tolerance, the interrupt) and tells the observers. Prolongation of a
//! coarser level's state is [`prolongate`], on its own.

use burn::tensor::Tensor;

use crate::error::{Error, Result};
use crate::model::feature_model::FeatureModel;
use crate::model::grid::Grid;
use crate::model::layout::FeatureLayout;
use crate::model::resample::{Resize, prolongate_deformation};
use crate::solver::ipalm::{
    Ipalm, LevelState, PartialSweep, SweepCarry, SweepEnd, SweepKind, SweepReport,
    initial_lipschitz,
};
use crate::solver::observer::Phase;

/// The energy of a state as the driver logs it (SPEC §5): `E = K Σ_k R_k + (K/δ) Σ_k D_k`,
/// summed in float64.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SweepEnergy {
    /// `E`.
    pub total: f64,
    /// `K Σ_k R_k`.
    pub regularizer: f64,
    /// `(K/δ) Σ_k D_k`.
    pub data: f64,
    /// SPEC §11's `E_lm` (0 without landmarks).
    pub landmarks: f64,
}

/// How a level's state began.
#[derive(Clone, Debug)]
pub enum LevelStart {
    /// SPEC §6's initial state on the coarsest level: nothing to fit the features to.
    Fresh,
    /// Prolongated from a coarser level or a draft (SPEC §7): the deep model first fits the
    /// features to the prolongated deformations.
    Prolongated,
    /// The state an interrupted run left after `sweeps` joint sweeps and the blocks
    /// `partial` of the next one, with `E` after each of them (the tolerance's window);
    /// `prolongated` if the level was not the first one run.
    Resumed {
        /// Joint sweeps done (0 and no `partial`: stopped during the feature-only sweeps,
        /// which run again).
        sweeps: usize,
        /// The blocks of joint sweep `sweeps + 1` run before the interrupt.
        partial: Option<PartialSweep>,
        /// `E` after the joint sweeps `0..=sweeps`.
        history: Vec<f64>,
        /// Whether the level's state came from a coarser one.
        prolongated: bool,
    },
}

/// What one call of [`LevelRun::next_sweep`] did.
#[derive(Debug)]
pub struct Swept {
    /// The phase the sweep belongs to.
    pub phase: Phase,
    /// The sweep in the phase (0: the state the phase starts from, nothing run).
    pub sweep: usize,
    /// What the sweep did (`None` for sweep 0).
    pub report: Option<SweepReport>,
    /// `E` after it.
    pub energy: SweepEnergy,
}

/// What one call of [`LevelRun::next_sweep`] came to.
#[derive(Debug)]
pub enum Outcome {
    /// A sweep ran (or a phase's sweep 0 was evaluated).
    Swept(Swept),
    /// Sweep `sweep` of `phase` was stopped between two blocks: the state holds the blocks
    /// it ran, and `partial` (joint sweeps only) what they did, to finish it on `--resume`.
    /// A features-only sweep is not continued: the deep model's feature-only sweeps run
    /// again on a resumed level.
    Stopped {
        /// The phase it belongs to.
        phase: Phase,
        /// The sweep stopped.
        sweep: usize,
        /// The blocks it ran, in a joint sweep.
        partial: Option<PartialSweep>,
    },
    /// A value turned non-finite; the state is the last finite iterate.
    NonFinite(NonFinite),
}

/// A non-finite value met by [`LevelRun::next_sweep`]: the state is the last finite
/// iterate, and the level cannot go on.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NonFinite {
    /// The phase it happened in.
    pub phase: Phase,
    /// The sweep (0: the phase's initial state).
    pub sweep: usize,
    /// What was not finite.
    pub what: String,
}

/// One level in progress.
pub struct LevelRun {
    grid: Grid,
    layout: FeatureLayout,
    ipalm: Ipalm,
    state: LevelState,
    /// What each sweep leaves for the next on this level's state.
    carry: SweepCarry,
    /// The phase running now, and its sweeps: done (`None`: sweep 0 not yet evaluated) and
    /// in all.
    phase: Phase,
    done: Option<usize>,
    sweeps: usize,
    /// Joint sweeps of the level.
    joint_sweeps: usize,
    /// The last feature-only sweep's energy: the joint phase's sweep 0.
    handed_on: Option<SweepEnergy>,
    /// For tests of the non-finite path: after this sweep of either phase `f_1` turns NaN.
    fault_after: Option<usize>,
    /// The blocks of the next joint sweep that a resumed run had already run.
    partial: Option<PartialSweep>,
    /// For tests of an interrupt within a sweep: joint sweep `.0` stops after `.1` blocks.
    stop_within: Option<(usize, usize)>,
}

impl LevelRun {
    /// A level about to run `pre_sweeps` feature-only sweeps (SPEC §7: only after a
    /// prolongation, and only when a resumed level had not yet begun its joint sweeps) and
    /// `joint_sweeps` joint ones, from `state`.
    pub fn init(
        ipalm: Ipalm,
        grid: Grid,
        layout: FeatureLayout,
        state: LevelState,
        start: &LevelStart,
        pre_sweeps: usize,
        joint_sweeps: usize,
    ) -> Self {
        let (prolongated, resumed, partial) = match start {
            LevelStart::Fresh => (false, 0, None),
            LevelStart::Prolongated => (true, 0, None),
            LevelStart::Resumed {
                sweeps,
                partial,
                prolongated,
                ..
            } => (*prolongated, *sweeps, partial.clone()),
        };
        let joint_begun = resumed > 0 || partial.is_some();
        let pre = if prolongated && !joint_begun {
            pre_sweeps
        } else {
            0
        };
        let (phase, done, sweeps) = if pre > 0 {
            (Phase::Features, None, pre)
        } else {
            // A resumed level continues after its last sweep; its sweep 0 was reported.
            (Phase::Joint, joint_begun.then_some(resumed), joint_sweeps)
        };
        Self {
            grid,
            layout,
            ipalm,
            state,
            carry: SweepCarry::default(),
            phase,
            done,
            sweeps,
            joint_sweeps,
            handed_on: None,
            fault_after: None,
            partial,
            stop_within: None,
        }
    }

    /// Makes `f_1` NaN after sweep `sweep` of whichever phase runs it, as a numerical
    /// failure would: for tests of the non-finite path only.
    pub(super) fn with_fault_after(mut self, sweep: Option<usize>) -> Self {
        self.fault_after = sweep;
        self
    }

    /// Stops joint sweep `sweep` after `blocks` of its blocks as an interrupt would: for
    /// tests of `--resume` within a sweep only.
    pub(super) fn with_stop_within(mut self, at: Option<(usize, usize)>) -> Self {
        self.stop_within = at;
        self
    }

    /// The grid.
    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    /// The state as it stands.
    pub fn state(&self) -> &LevelState {
        &self.state
    }

    /// Joint sweeps run so far (a resumed level starts with those of the interrupted run).
    pub fn joint_sweeps_done(&self) -> usize {
        match self.phase {
            Phase::Joint => self.done.unwrap_or(0),
            Phase::Features => 0,
        }
    }

    /// Runs the next sweep (or evaluates a phase's sweep 0), `None` once both phases are
    /// done; `stop` is asked between the sweep's blocks ([`Ipalm::sweep_until`]).
    ///
    /// # Errors
    ///
    /// [`Outcome::NonFinite`] when a value turned non-finite (the state is then the last
    /// finite iterate); `Err` for any other failure.
    pub fn next_sweep(&mut self, stop: &dyn Fn() -> bool) -> Result<Option<Outcome>> {
        if self.done.is_some_and(|d| d >= self.sweeps) {
            if self.phase == Phase::Joint {
                return Ok(None);
            }
            (self.phase, self.done, self.sweeps) = (Phase::Joint, None, self.joint_sweeps);
        }
        let phase = self.phase;
        let Some(done) = self.done else {
            self.done = Some(0);
            // The joint phase starts where the feature-only sweeps left the state: their
            // last energy is its sweep 0.
            let energy = match self.handed_on.take() {
                Some(energy) => Ok(energy),
                None => self.evaluate(None),
            };
            return Ok(Some(match energy {
                Ok(energy) => Outcome::Swept(Swept {
                    phase,
                    sweep: 0,
                    report: None,
                    energy,
                }),
                Err(what) => Outcome::NonFinite(NonFinite {
                    phase,
                    sweep: 0,
                    what,
                }),
            }));
        };
        let sweep = done + 1;
        self.done = Some(sweep);
        let kind = match phase {
            Phase::Features => SweepKind::FeaturesOnly,
            Phase::Joint => SweepKind::Joint,
        };
        // The last finite iterate: cheap to keep, these handles are the tensors the sweep
        // moves into `f_prev` and `phi_prev` anyway.
        let before = (self.state.f.clone(), self.state.phi.clone());
        let from = self.partial.take().filter(|_| phase == Phase::Joint);
        // The test hook: `stop` is asked before each block after the first one run.
        let asked = std::cell::Cell::new(from.as_ref().map_or(0, |p| p.blocks));
        let hooked = self
            .stop_within
            .filter(|&(at, _)| phase == Phase::Joint && at == sweep)
            .map(|(_, blocks)| blocks);
        let stop = || {
            asked.set(asked.get() + 1);
            stop() || hooked.is_some_and(|blocks| asked.get() >= blocks)
        };
        let outcome =
            match self
                .ipalm
                .sweep_until(&mut self.state, kind, &mut self.carry, from, &stop)
            {
                Ok(SweepEnd::Done(report)) => Ok(report),
                Ok(SweepEnd::Stopped(partial)) => {
                    return Ok(Some(Outcome::Stopped {
                        phase,
                        sweep,
                        partial: (phase == Phase::Joint).then_some(partial),
                    }));
                }
                Err(Error::NonFinite { what }) => Err(what),
                Err(other) => return Err(other),
            };
        let faulted = self.fault_after == Some(sweep);
        if faulted {
            self.state.f[1] = self.state.f[1].clone().mul_scalar(f64::NAN);
            self.carry.clear();
        }
        let swept = outcome.and_then(|report| {
            // A fault injected after the sweep is not in its report.
            self.evaluate((!faulted).then_some(&report))
                .map(|energy| (report, energy))
        });
        Ok(Some(match swept {
            Ok((report, energy)) => {
                if phase == Phase::Features {
                    self.handed_on = Some(energy);
                }
                Outcome::Swept(Swept {
                    phase,
                    sweep,
                    report: Some(report),
                    energy,
                })
            }
            Err(what) => {
                self.carry.clear();
                let (f, phi) = before;
                self.state.f_prev = f.clone();
                self.state.phi_prev = phi.clone();
                self.state.f = f;
                self.state.phi = phi;
                Outcome::NonFinite(NonFinite { phase, sweep, what })
            }
        }))
    }

    /// The energy after a sweep, reusing the data terms the sweep evaluated (its report)
    /// and leaving the anisotropies it computed for the next sweep.
    fn evaluate(
        &mut self,
        report: Option<&SweepReport>,
    ) -> std::result::Result<SweepEnergy, String> {
        let energy = self
            .ipalm
            .energy_after_carrying(&self.state, report, &mut self.carry);
        let total = energy.total();
        if total.is_finite() {
            return Ok(SweepEnergy {
                total,
                regularizer: energy.regularizer_part(),
                data: energy.data_part(),
                landmarks: energy.landmarks,
            });
        }
        let bad = energy.first_nonfinite().map_or(String::new(), |(k, r, d)| {
            format!(" (step k = {k}: K·R = {r}, (K/δ)·D = {d})")
        });
        Err(format!("the path energy is {total}{bad}"))
    }

    /// Ends the level: its grid, state, layout and the anisotropies `a_1..a_K` of its final
    /// frames (`[K, H, W]`).
    pub fn terminate(self) -> (Grid, LevelState, FeatureLayout, Tensor<3>) {
        let anisotropy = self.ipalm.anisotropies(&self.state);
        (self.grid, self.state, self.layout, anisotropy)
    }

    /// Ends the level, handing its state on to the next one (no anisotropies computed).
    pub fn into_coarse(self) -> (Grid, LevelState, FeatureLayout) {
        (self.grid, self.state, self.layout)
    }
}

/// The state of the level on `grid` prolongated from a coarser level's (SPEC §7):
/// deformations by bilinear interpolation in domain coordinates, interior images likewise;
/// in the deep model the VGG channels from the convex combination of the endpoint features
/// `f_a`, `f_b` (`[1, C_tot, H, W]`) and the η-scaled RGB channels from the prolongated
/// images. The Lipschitz estimates start afresh (SPEC §6).
///
/// # Errors
///
/// If the counts of the coarse state do not fit.
#[allow(clippy::too_many_arguments)]
pub fn prolongate(
    model: &FeatureModel,
    (coarse, coarse_state, coarse_layout): (&Grid, &LevelState, &FeatureLayout),
    grid: &Grid,
    layout: &FeatureLayout,
    f_a: Tensor<4>,
    f_b: Tensor<4>,
    delta: f64,
) -> Result<LevelState> {
    let k = coarse_state.steps();
    let up = Resize::new(coarse, grid);
    let mut f = Vec::with_capacity(k + 1);
    f.push(f_a.clone());
    for (step, frame) in coarse_state.f[1..k].iter().enumerate() {
        let u = up.apply(coarse_layout.rgb_part(frame.clone()));
        f.push(match model {
            FeatureModel::Rgb => u,
            // SPEC §7: VGG channels from the convex combination of the endpoints, η-scaled
            // RGB from the prolongated images.
            FeatureModel::Deep(deep) => {
                let t = (step + 1) as f64 / k as f64;
                let features = f_a
                    .clone()
                    .narrow(1, 3, layout.channels() - 3)
                    .mul_scalar(1.0 - t)
                    + f_b
                        .clone()
                        .narrow(1, 3, layout.channels() - 3)
                        .mul_scalar(t);
                deep.stack(u, features)
            }
        });
    }
    f.push(f_b);
    let phi = prolongate_deformation(coarse, grid, coarse_state.deformations());
    let phi = (0..k).map(|i| phi.clone().narrow(0, i, 1)).collect();
    let (l_phi, l_f) = initial_lipschitz(grid, layout, k, delta);
    LevelState::new(f, phi, l_phi, l_f)
}
