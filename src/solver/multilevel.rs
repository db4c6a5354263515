//! The coarse-to-fine driver (SPEC §7): builds the pyramid, initialises the coarsest level,
//! prolongates deformations and images (and, in the deep model, re-initialises the VGG
//! channels and runs the `J_pre` feature-only sweeps), and runs `J` iPALM sweeps per level,
//! reporting to an [`Observer`] after every sweep.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use burn::tensor::{Device, Tensor};

use crate::error::{Error, Result};
use crate::model::feature_model::FeatureModel;
use crate::model::grid::Grid;
use crate::model::layout::FeatureLayout;
use crate::model::params::EnergyParams;
use crate::model::resample::{Resize, prolongate_deformation};
use crate::solver::ipalm::{
    Ipalm, IpalmConfig, LevelState, SweepCarry, SweepKind, SweepReport, initial_lipschitz,
};
use crate::solver::observer::{LevelStop, LevelSummary, Observer, Phase, SweepEvent, Termination};

/// Settings of a multilevel morph (SPEC §7, §9).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MultilevelConfig {
    /// Number of steps `K` (frames `0..=K`). Default 15.
    pub steps: usize,
    /// Pyramid levels. Default 5. The working size must be divisible by `2^(levels−1)` and
    /// the coarsest level at least 4 × 4.
    pub levels: usize,
    /// Sweeps `J` per level: the most a level runs. Default 250.
    pub sweeps: usize,
    /// Convergence control: a level stops early once the relative decrease of `E` over the
    /// last [`TOLERANCE_WINDOW`] joint sweeps falls below this; 0 = off (every level runs
    /// its `J` sweeps). Default 1e-4: measured on the motorcycle at `J` = 250, 20 % less
    /// time for the same endpoint error and 0.04 % more energy (README, "The solver at
    /// work").
    pub tolerance: f64,
    /// The energy's parameters.
    pub params: EnergyParams,
    /// The solver's settings.
    pub ipalm: IpalmConfig,
}

/// The number of sweeps over which [`MultilevelConfig::tolerance`] measures the decrease.
pub const TOLERANCE_WINDOW: usize = 10;

impl Default for MultilevelConfig {
    fn default() -> Self {
        Self {
            steps: 15,
            levels: 5,
            sweeps: 250,
            tolerance: 1e-4,
            params: EnergyParams::rgb(),
            ipalm: IpalmConfig::default(),
        }
    }
}

impl MultilevelConfig {
    /// Checks every parameter.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] naming the first bad value.
    pub fn validate(&self) -> Result<()> {
        if self.steps < 1 {
            return Err(Error::invalid("K", self.steps, "at least 1"));
        }
        if !(1..=12).contains(&self.levels) {
            return Err(Error::invalid("levels", self.levels, "in 1..=12"));
        }
        if self.steps > 10_000 {
            return Err(Error::invalid("K", self.steps, "at most 10000"));
        }
        if self.sweeps > 1_000_000 {
            return Err(Error::invalid("sweeps", self.sweeps, "at most 1000000"));
        }
        if !(0.0..1.0).contains(&self.tolerance) {
            return Err(Error::invalid("tol", self.tolerance, "in [0, 1) (0 = off)"));
        }
        self.params.validate()?;
        self.ipalm.validate()
    }

    /// The grid sizes of the levels, coarse to fine, for a working size `height × width`.
    ///
    /// # Errors
    ///
    /// If the size is not divisible by `2^(levels−1)` or the coarsest level is below 4 × 4.
    pub fn level_sizes(&self, height: usize, width: usize) -> Result<Vec<(usize, usize)>> {
        let factor = 1usize << (self.levels - 1);
        if height % factor != 0 || width % factor != 0 || height / factor < 4 || width / factor < 4
        {
            return Err(Error::Shape {
                op: "multilevel pyramid",
                detail: format!(
                    "{height}x{width} with {} levels: both sides must be multiples of {factor} \
                     and at least {}",
                    self.levels,
                    4 * factor
                ),
            });
        }
        Ok((0..self.levels)
            .map(|l| {
                let f = 1usize << (self.levels - 1 - l);
                (height / f, width / f)
            })
            .collect())
    }
}

/// Whether the relative decrease of `E` over the last [`TOLERANCE_WINDOW`] sweeps is below
/// `tolerance` (never with `tolerance = 0`).
fn converged(history: &[f64], tolerance: f64) -> bool {
    if tolerance <= 0.0 || history.len() <= TOLERANCE_WINDOW {
        return false;
    }
    let (then, now) = (
        history[history.len() - 1 - TOLERANCE_WINDOW],
        history[history.len() - 1],
    );
    (then - now) < tolerance * then.abs()
}

/// The result of a morph.
#[derive(Debug)]
pub struct Morph {
    /// The last level's grid.
    pub grid: Grid,
    /// The last level's state: `f_0..f_K`, `φ_1..φ_K`.
    pub state: LevelState,
    /// `a_1..a_K` of the final frames, `[K, H, W]`.
    pub anisotropy: Tensor<3>,
    /// The channel layout of `state.f` (the RGB part of a frame is `layout.rgb_part(f)`).
    pub layout: FeatureLayout,
    /// Why it stopped.
    pub termination: Termination,
    /// What each level did, coarse to fine (only the levels reached).
    pub levels: Vec<LevelSummary>,
    /// `E` after each joint sweep of the last level, from its sweep 0 (what a resumed run
    /// needs for the tolerance's window).
    pub history: Vec<f64>,
}

impl Morph {
    /// The frames `u_0..u_K` as RGB images (SPEC §8: the RGB part, divided by `η` in the
    /// deep model), each `[1, 3, H, W]`.
    pub fn images(&self) -> Vec<Tensor<4>> {
        self.state
            .f
            .iter()
            .map(|f| self.layout.rgb_part(f.clone()))
            .collect()
    }
}

/// The channel layout and the endpoint feature vectors `f_A`, `f_B` of the level on `grid`,
/// `1/2^downsampling` of the working grid `full` (SPEC §4, §7).
///
/// # Errors
///
/// In the deep model, if no VGG tap has that size.
pub(crate) fn level_endpoints(
    model: &FeatureModel,
    full: &Grid,
    grid: &Grid,
    u_a: &Tensor<4>,
    u_b: &Tensor<4>,
    downsampling: usize,
) -> Result<(FeatureLayout, Tensor<4>, Tensor<4>)> {
    let layout = model.layout(downsampling)?;
    let resize = Resize::new(full, grid);
    let (u_a, u_b) = (resize.apply(u_a.clone()), resize.apply(u_b.clone()));
    let (f_a, f_b) = match model {
        FeatureModel::Rgb => (u_a, u_b),
        FeatureModel::Deep(deep) => {
            let (tap_a, tap_b) = deep.maps(downsampling)?;
            (deep.stack(u_a, tap_a), deep.stack(u_b, tap_b))
        }
    };
    Ok((layout, f_a, f_b))
}

/// A finished morph to start from instead of the coarsest level (`--init`): its frames and
/// deformations are prolongated to the first level larger than it, as a coarser level's
/// would be (SPEC §7), and the levels up to its size are not run.
#[derive(Clone, Debug)]
pub struct Draft {
    /// The draft's grid (on the device of the run).
    pub grid: Grid,
    /// `u_0..u_K`, RGB, each `[1, 3, h, w]`.
    pub frames: Vec<Tensor<4>>,
    /// `φ_1..φ_K`, `[K, 2, h, w]`.
    pub deformations: Tensor<4>,
}

/// Where an interrupted morph stopped, to continue exactly from there (`--resume`): the
/// whole iPALM state of its last level after its last full sweep.
#[derive(Clone, Debug)]
pub struct Resume {
    /// The level it stopped on.
    pub level: usize,
    /// Joint sweeps done on that level (0: stopped during the deep model's feature-only
    /// sweeps, which then run again from the state reached).
    pub sweeps: usize,
    /// `f`, `f_prev`, `φ`, `φ_prev` and the stored Lipschitz estimates.
    pub state: LevelState,
    /// `E` after the level's joint sweeps `0..=sweeps` (the tolerance's window).
    pub history: Vec<f64>,
    /// What the levels before it did.
    pub levels: Vec<LevelSummary>,
}

/// The multilevel driver.
#[derive(Clone, Debug)]
pub struct Multilevel {
    config: MultilevelConfig,
    /// Where to start instead of the coarsest level.
    draft: Option<Draft>,
    /// Where an interrupted run stopped.
    resume: Option<Resume>,
    /// A fault to inject for testing the non-finite path (see
    /// [`inject_nonfinite`](Self::inject_nonfinite)).
    inject_nonfinite: Option<(usize, usize)>,
}

impl Multilevel {
    /// A driver with validated settings.
    ///
    /// # Errors
    ///
    /// If a setting is out of range.
    pub fn new(config: MultilevelConfig) -> Result<Self> {
        config.validate()?;
        Ok(Self {
            config,
            draft: None,
            resume: None,
            inject_nonfinite: None,
        })
    }

    /// Starts from `draft` instead of the coarsest level: the levels no larger than the
    /// draft (in pixels) are skipped, except the finest, which always runs.
    ///
    /// # Errors
    ///
    /// If the draft's `K` is not this morph's.
    pub fn with_draft(mut self, draft: Draft) -> Result<Self> {
        let k = draft.deformations.dims()[0];
        if k != self.config.steps || draft.frames.len() != k + 1 {
            return Err(Error::invalid(
                "K",
                self.config.steps,
                format!(
                    "the draft's K = {k} ({} frames): a morph refined from a draft keeps its K",
                    draft.frames.len()
                ),
            ));
        }
        self.draft = Some(draft);
        Ok(self)
    }

    /// Continues an interrupted morph from where it stopped ([`Resume`]): the levels before
    /// are not run again, and with the same settings on a deterministic backend the result
    /// is the one the uninterrupted run would have given.
    pub fn with_resume(mut self, resume: Resume) -> Self {
        self.resume = Some(resume);
        self
    }

    /// For tests of what happens when the optimisation meets a NaN: after sweep `sweep` of
    /// level `level` (of whichever phase runs it) the interior frame `f_1` is made NaN, as a
    /// numerical failure would. The driver must then stop with [`Termination::NonFinite`]
    /// and the last finite iterate.
    #[doc(hidden)]
    pub fn inject_nonfinite(mut self, level: usize, sweep: usize) -> Self {
        self.inject_nonfinite = Some((level, sweep));
        self
    }

    /// The settings.
    pub fn config(&self) -> &MultilevelConfig {
        &self.config
    }

    /// Morphs `u_a` into `u_b` (RGB in `[0, 1]`, `[1, 3, H, W]`, on `device`, which must have
    /// autodiff enabled). Stops after the current sweep when `interrupt` is raised.
    ///
    /// # Errors
    ///
    /// Mismatched or unsuitable sizes, or a non-finite value in the optimisation (naming the
    /// level and sweep).
    pub fn run(
        &self,
        device: &Device,
        u_a: Tensor<4>,
        u_b: Tensor<4>,
        observer: &mut dyn Observer,
        interrupt: &AtomicBool,
    ) -> Result<Morph> {
        self.run_with(device, u_a, u_b, &FeatureModel::Rgb, observer, interrupt)
    }

    /// Like [`run`](Self::run), with the feature vectors of `model` (the deep model's
    /// feature maps must have been computed from the same `u_a`, `u_b`).
    ///
    /// # Errors
    ///
    /// As [`run`](Self::run); in the deep model also more than 5 levels (VGG19 has 5 taps).
    pub fn run_with(
        &self,
        device: &Device,
        u_a: Tensor<4>,
        u_b: Tensor<4>,
        model: &FeatureModel,
        observer: &mut dyn Observer,
        interrupt: &AtomicBool,
    ) -> Result<Morph> {
        let cfg = &self.config;
        let [_, ca, h, w] = u_a.dims();
        if u_a.dims() != u_b.dims() || ca != 3 {
            return Err(Error::Shape {
                op: "morph inputs",
                detail: format!(
                    "A is {:?} and B is {:?}: expected two [1, 3, H, W] RGB images of one size",
                    u_a.dims(),
                    u_b.dims()
                ),
            });
        }
        let sizes = cfg.level_sizes(h, w)?;
        let dtype = u_a.dtype();
        let full = Grid::new(h, w, device, dtype)?;
        let started = Instant::now();
        let k = cfg.steps;

        let mut previous: Option<(Grid, LevelState, FeatureLayout)> = None;
        let mut first = 0;
        if let Some(draft) = &self.draft {
            let pixels = draft.grid.height() * draft.grid.width();
            first = sizes
                .iter()
                .position(|&(lh, lw)| lh * lw > pixels)
                .unwrap_or(sizes.len() - 1);
            let layout = FeatureLayout::rgb();
            let (l_phi, l_f) = initial_lipschitz(&draft.grid, &layout, k, cfg.params.delta);
            let phi = (0..k)
                .map(|i| draft.deformations.clone().narrow(0, i, 1))
                .collect();
            let state = LevelState::new(draft.frames.clone(), phi, l_phi, l_f)?;
            previous = Some((draft.grid.clone(), state, layout));
        }
        let mut summaries = Vec::with_capacity(sizes.len());
        if let Some(resume) = &self.resume {
            first = resume.level.min(sizes.len() - 1);
            summaries = resume.levels.clone();
        }
        for (level, &(lh, lw)) in sizes.iter().enumerate().skip(first) {
            let resume_here = self.resume.as_ref().filter(|r| r.level == level);
            let downsampling = sizes.len() - 1 - level;
            let grid = Grid::new(lh, lw, device, dtype)?;
            let (layout, f_a, f_b) =
                level_endpoints(model, &full, &grid, &u_a, &u_b, downsampling)?;
            let prolongated = previous.is_some() || (resume_here.is_some() && level > 0);
            let mut state = match (resume_here, previous.take()) {
                (Some(resume), _) => resume.state.clone(),
                (None, None) => LevelState::initial(&grid, &layout, f_a, f_b, k, cfg.params.delta)?,
                (None, Some((coarse, coarse_state, coarse_layout))) => {
                    let up = Resize::new(&coarse, &grid);
                    let mut f = Vec::with_capacity(k + 1);
                    f.push(f_a.clone());
                    for (step, frame) in coarse_state.f[1..k].iter().enumerate() {
                        let u = up.apply(coarse_layout.rgb_part(frame.clone()));
                        f.push(match model {
                            FeatureModel::Rgb => u,
                            // SPEC §7: VGG channels from the convex combination of the
                            // endpoints, η-scaled RGB from the prolongated images.
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
                    let phi = prolongate_deformation(&coarse, &grid, coarse_state.deformations());
                    let phi = (0..k).map(|i| phi.clone().narrow(0, i, 1)).collect();
                    let (l_phi, l_f) = initial_lipschitz(&grid, &layout, k, cfg.params.delta);
                    LevelState::new(f, phi, l_phi, l_f)?
                }
            };
            let ipalm = Ipalm::new(&grid, cfg.params, layout.clone(), cfg.ipalm)?;

            // The energy after a sweep, reusing the data terms the sweep evaluated (its report)
            // and leaving the anisotropies it computed for the next sweep (`carry`).
            let evaluate = |state: &LevelState,
                            report: Option<&SweepReport>,
                            carry: &mut SweepCarry|
             -> std::result::Result<[f64; 3], String> {
                let energy = ipalm.energy_after_carrying(state, report, carry);
                let total = energy.total();
                if total.is_finite() {
                    return Ok([total, energy.regularizer_part(), energy.data_part()]);
                }
                let bad = energy.first_nonfinite().map_or(String::new(), |(k, r, d)| {
                    format!(" (step k = {k}: K·R = {r}, (K/δ)·D = {d})")
                });
                Err(format!("the path energy is {total}{bad}"))
            };
            let mut report_sweep = |phase: Phase,
                                    sweep: usize,
                                    report: Option<&SweepReport>,
                                    state: &LevelState,
                                    numbers: [f64; 3],
                                    stop: Option<LevelStop>| {
                observer.sweep(&SweepEvent {
                    level,
                    levels: sizes.len(),
                    grid: &grid,
                    phase,
                    sweep,
                    sweeps: match phase {
                        Phase::Features => model.pre_sweeps(),
                        Phase::Joint => cfg.sweeps,
                    },
                    energy: numbers[0],
                    regularizer: numbers[1],
                    data: numbers[2],
                    report,
                    state,
                    seconds: started.elapsed().as_secs_f64(),
                    stop,
                });
            };
            // SPEC §7: after a prolongation the deep model first fits the features to the
            // prolongated deformations (pointless on the first level, where the convex
            // combination is already optimal for φ = Id).
            let resumed_sweeps = resume_here.map_or(0, |r| r.sweeps);
            let pre = if prolongated && resumed_sweeps == 0 {
                model.pre_sweeps()
            } else {
                0
            };
            let phases = [
                (Phase::Features, pre, SweepKind::FeaturesOnly),
                (Phase::Joint, cfg.sweeps, SweepKind::Joint),
            ];
            let mut stopped = None;
            let mut history: Vec<f64> = match resume_here {
                Some(r) if r.sweeps > 0 => r.history.clone(),
                _ => Vec::new(),
            };
            let mut level_stop = LevelStop::Sweeps;
            let mut joint_sweeps = resumed_sweeps;
            let mut last_numbers: Option<[f64; 3]> = None;
            // What each sweep leaves for the next on this level's state.
            let mut carry = SweepCarry::default();
            'phases: for (phase, sweeps, kind) in phases {
                if sweeps == 0 && phase == Phase::Features {
                    continue;
                }
                // A resumed level continues after its last sweep; its sweep 0 was reported.
                let start = if phase == Phase::Joint {
                    resumed_sweeps
                } else {
                    0
                };
                // The joint phase starts where the feature-only sweeps left the state: their
                // last energy is its sweep 0.
                let initial = (start == 0).then(|| {
                    last_numbers
                        .take()
                        .map_or_else(|| evaluate(&state, None, &mut carry), Ok)
                });
                match initial {
                    None => {}
                    Some(Ok(numbers)) => {
                        if phase == Phase::Joint {
                            history.push(numbers[0]);
                        }
                        report_sweep(phase, 0, None, &state, numbers, None)
                    }
                    Some(Err(what)) => {
                        stopped = Some(Termination::NonFinite {
                            level,
                            sweep: 0,
                            phase,
                            what,
                        });
                        break 'phases;
                    }
                }
                for sweep in start + 1..=sweeps {
                    // The last finite iterate: cheap to keep, these handles are the tensors
                    // the sweep moves into `f_prev` and `phi_prev` anyway.
                    let before = (state.f.clone(), state.phi.clone());
                    let outcome = match ipalm.sweep_carrying(&mut state, kind, &mut carry) {
                        Ok(report) => Ok(report),
                        Err(Error::NonFinite { what }) => Err(what),
                        Err(other) => return Err(other),
                    };
                    let injected = self.inject_nonfinite == Some((level, sweep));
                    if injected {
                        state.f[1] = state.f[1].clone().mul_scalar(f64::NAN);
                        carry.clear();
                    }
                    match outcome.and_then(|report| {
                        // A fault injected after the sweep is not in its report.
                        evaluate(&state, (!injected).then_some(&report), &mut carry)
                            .map(|n| (report, n))
                    }) {
                        Ok((report, numbers)) => {
                            last_numbers = Some(numbers);
                            let mut stop = None;
                            if phase == Phase::Joint {
                                joint_sweeps = sweep;
                                history.push(numbers[0]);
                                if converged(&history, cfg.tolerance) {
                                    stop = Some(LevelStop::Converged);
                                } else if sweep == sweeps {
                                    stop = Some(LevelStop::Sweeps);
                                }
                            }
                            report_sweep(phase, sweep, Some(&report), &state, numbers, stop);
                            if stop == Some(LevelStop::Converged) {
                                level_stop = LevelStop::Converged;
                                break 'phases;
                            }
                        }
                        Err(what) => {
                            carry.clear();
                            let (f, phi) = before;
                            state.f_prev = f.clone();
                            state.phi_prev = phi.clone();
                            state.f = f;
                            state.phi = phi;
                            stopped = Some(Termination::NonFinite {
                                level,
                                sweep,
                                phase,
                                what,
                            });
                            break 'phases;
                        }
                    }
                    if interrupt.load(Ordering::Relaxed) {
                        stopped = Some(Termination::Interrupted {
                            level,
                            sweep: if phase == Phase::Joint { sweep } else { 0 },
                        });
                        break 'phases;
                    }
                }
            }
            summaries.push(LevelSummary {
                level,
                size: [lh, lw],
                sweeps: joint_sweeps,
                stop: match &stopped {
                    Some(Termination::Interrupted { .. }) => LevelStop::Interrupted,
                    Some(Termination::NonFinite { .. }) => LevelStop::NonFinite,
                    _ => level_stop,
                },
            });
            if stopped.is_some() || level + 1 == sizes.len() {
                let anisotropy = ipalm.anisotropies(&state);
                return Ok(Morph {
                    grid,
                    state,
                    anisotropy,
                    layout,
                    termination: stopped.unwrap_or(Termination::Completed),
                    levels: summaries,
                    history,
                });
            }
            previous = Some((grid, state, layout));
        }
        unreachable!("the last level returns")
    }
}
