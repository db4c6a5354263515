//! The coarse-to-fine driver (SPEC §7): builds the pyramid, initialises the coarsest level,
//! prolongates deformations and images (and, in the deep model, re-initialises the VGG
//! channels and runs the `J_pre` feature-only sweeps), and runs `J` iPALM sweeps per level,
//! reporting to an [`Observer`] after every sweep.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use burn::tensor::{Device, Tensor};

use crate::error::{Error, Result};
use crate::model::alignment::GlobalMap;
use crate::model::deformation::admissible_each;
use crate::model::energy::landmarks::{LandmarkTerm, Landmarks};
use crate::model::feature_model::FeatureModel;
use crate::model::grid::{Grid, to_host};
use crate::model::layout::FeatureLayout;
use crate::model::params::EnergyParams;
use crate::model::resample::Resize;
use crate::solver::initial::initial_state;
use crate::solver::ipalm::{Ipalm, IpalmConfig, LevelState, PartialSweep, initial_lipschitz};
use crate::solver::level_run::{LevelRun, LevelStart, NonFinite, Outcome, prolongate};
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
    /// time for the same endpoint error and 0.04 % more energy (docs/quality.md, "The solver at
    /// work").
    pub tolerance: f64,
    /// The energy's parameters.
    pub params: EnergyParams,
    /// The solver's settings.
    pub ipalm: IpalmConfig,
    /// SPEC §11's landmark weight `γ` (`--landmark-weight`), used only with landmarks
    /// ([`Multilevel::with_landmarks`]). Default [`DEFAULT_LANDMARK_WEIGHT`].
    #[serde(default = "default_landmark_weight")]
    pub landmark_weight: f64,
}

/// The default landmark weight `γ` (SPEC §11), measured: on hand-placed landmarks
/// (`docs/examples/points/`, six pairs on faces and on cat_dog, default 256² RGB morphs) the
/// smallest of 1, 3, 10 that meets every point to within a working pixel (max 0.71 and
/// 0.26 px; γ = 3 leaves 1.15 and 2.54 px) with no step folding (docs/results.md).
pub const DEFAULT_LANDMARK_WEIGHT: f64 = 10.0;

fn default_landmark_weight() -> f64 {
    DEFAULT_LANDMARK_WEIGHT
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
            landmark_weight: DEFAULT_LANDMARK_WEIGHT,
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
        if !(self.landmark_weight.is_finite() && (0.0..=1e9).contains(&self.landmark_weight)) {
            return Err(Error::invalid(
                "landmark-weight",
                self.landmark_weight,
                "in [0, 1e9]",
            ));
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
        if !height.is_multiple_of(factor)
            || !width.is_multiple_of(factor)
            || height / factor < 4
            || width / factor < 4
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
    /// An interrupted morph's: the blocks of the joint sweep after its last full one that
    /// ran before the interrupt ([`PartialSweep`]; `state` holds them).
    pub partial: Option<PartialSweep>,
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

impl Draft {
    /// The draft as the state of a coarser level (RGB, fresh Lipschitz estimates), to be
    /// prolongated like one.
    fn state(&self, k: usize, delta: f64) -> Result<(Grid, LevelState, FeatureLayout)> {
        let layout = FeatureLayout::rgb();
        let (l_phi, l_f) = initial_lipschitz(&self.grid, &layout, k, delta);
        let phi = (0..k)
            .map(|i| self.deformations.clone().narrow(0, i, 1))
            .collect();
        let state = LevelState::new(self.frames.clone(), phi, l_phi, l_f)?;
        Ok((self.grid.clone(), state, layout))
    }
}

/// What the executor of a level needs to know beyond the level's own run.
struct LevelContext {
    level: usize,
    levels: usize,
    pre_sweeps: usize,
    started: Instant,
}

/// Where an interrupted morph stopped, to continue exactly from there (`--resume`): the
/// whole iPALM state of its last level, after its last full sweep and the blocks of the next
/// one that ran.
#[derive(Clone, Debug)]
pub struct Resume {
    /// The level it stopped on.
    pub level: usize,
    /// Joint sweeps done on that level (0 and no `partial`: stopped during the deep model's
    /// feature-only sweeps, which then run again from the state reached).
    pub sweeps: usize,
    /// The blocks of joint sweep `sweeps + 1` that ran.
    pub partial: Option<PartialSweep>,
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
    /// A stop within a sweep to make for testing `--resume` (see
    /// [`stop_within`](Self::stop_within)).
    stop_within: Option<(usize, usize, usize)>,
    /// SPEC §11's landmarks on the working grid.
    landmarks: Option<Landmarks>,
    /// SPEC §11's global map on the working grid (A's coordinates to B's).
    alignment: Option<GlobalMap>,
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
            stop_within: None,
            landmarks: None,
            alignment: None,
        })
    }

    /// Steers the path by SPEC §11's landmark term with weight
    /// [`MultilevelConfig::landmark_weight`]: `landmarks` are given on the working grid
    /// (the size of the inputs of [`run`](Self::run)) and mapped to each level by the
    /// align-corners rule of SPEC §7.
    pub fn with_landmarks(mut self, landmarks: Landmarks) -> Self {
        self.landmarks = Some(landmarks);
        self
    }

    /// Starts the coarsest level from SPEC §11's initial path for the global map `map`
    /// (given on the working grid, A's pixel coordinates to B's; see
    /// [`crate::solver::initial`]) instead of `φ = Id` and the cross-fade. With landmarks
    /// ([`with_landmarks`](Self::with_landmarks)) and `γ > 0` the coarsest level starts from
    /// that path even without a map (then `G = Id`), carrying each landmark along its line.
    pub fn with_alignment(mut self, map: GlobalMap) -> Self {
        self.alignment = Some(map);
        self
    }

    /// Starts from `draft` instead of the coarsest level: the levels no larger than the
    /// draft (in pixels) are skipped, except the finest, which always runs.
    ///
    /// # Errors
    ///
    /// If the draft's `K` is not this morph's, a deformation of it is not admissible (SPEC
    /// §0), or a frame is not finite.
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
        // A draft is a file a user can edit: one whose steps are not admissible (folded,
        // moved on the border, not finite) would be prolongated into a path the solver cannot
        // start from (issue 43 #13: it silently restarted from the identity).
        let bad: Vec<usize> = admissible_each(&draft.grid, draft.deformations.clone())
            .into_iter()
            .enumerate()
            .filter_map(|(i, ok)| (!ok).then_some(i + 1))
            .collect();
        if let Some(&first) = bad.first() {
            return Err(Error::invalid(
                "init",
                format!(
                    "a draft whose deformation {first} (of {} not admissible) folds, moves the \
                     border or is not finite",
                    bad.len()
                ),
                "a finished morph's deformations: finite, the identity on the border, det ∇φ > 0",
            ));
        }
        for (i, frame) in draft.frames.iter().enumerate() {
            let finite = to_host(frame.clone().abs().max())[0].is_finite();
            if !finite {
                return Err(Error::invalid(
                    "init",
                    format!("a draft whose frame {i} is not finite"),
                    "a finished morph's frames",
                ));
            }
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
    #[cfg(feature = "check")]
    pub fn inject_nonfinite(mut self, level: usize, sweep: usize) -> Self {
        self.inject_nonfinite = Some((level, sweep));
        self
    }

    /// For tests of an interrupt within a sweep: joint sweep `sweep` of level `level` stops
    /// after `blocks` of its blocks ([`Ipalm::sweep_until`]) as if the interrupt had been
    /// raised then, and the morph ends [`Termination::Interrupted`] with the
    /// [`Morph::partial`] sweep.
    #[doc(hidden)]
    pub fn stop_within(mut self, level: usize, sweep: usize, blocks: usize) -> Self {
        self.stop_within = Some((level, sweep, blocks));
        self
    }

    /// The landmarks when they steer the path: with `γ = 0` they are only measured (the
    /// term is 0, and the coarsest level does not start from them).
    fn steering_landmarks(&self) -> Option<&Landmarks> {
        self.landmarks
            .as_ref()
            .filter(|_| self.config.landmark_weight > 0.0)
    }

    /// The settings.
    pub fn config(&self) -> &MultilevelConfig {
        &self.config
    }

    /// Morphs `u_a` into `u_b` (RGB in `[0, 1]`, `[1, 3, H, W]`, on `device`, which must have
    /// autodiff enabled). Stops after the current step (a block of a sweep) when `interrupt`
    /// is raised.
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
        if let Some(landmarks) = &self.landmarks
            && landmarks.size() != (h, w)
        {
            return Err(Error::Shape {
                op: "landmarks",
                detail: format!(
                    "given on a {:?} grid for inputs of {h}x{w} (rows x columns)",
                    landmarks.size()
                ),
            });
        }
        let dtype = u_a.dtype();
        let full = Grid::new(h, w, device, dtype)?;
        let started = Instant::now();
        let k = cfg.steps;

        let (mut coarser, mut first) = match &self.draft {
            Some(draft) => {
                let pixels = draft.grid.height() * draft.grid.width();
                let first = sizes
                    .iter()
                    .position(|&(lh, lw)| lh * lw > pixels)
                    .unwrap_or(sizes.len() - 1);
                (Some(draft.state(k, cfg.params.delta)?), first)
            }
            None => (None, 0),
        };
        let mut summaries = Vec::with_capacity(sizes.len());
        if let Some(resume) = &self.resume {
            first = resume.level.min(sizes.len() - 1);
            summaries = resume.levels.clone();
        }
        for (level, &(lh, lw)) in sizes.iter().enumerate().skip(first) {
            let downsampling = sizes.len() - 1 - level;
            let grid = Grid::new(lh, lw, device, dtype)?;
            let (layout, f_a, f_b) =
                level_endpoints(model, &full, &grid, &u_a, &u_b, downsampling)?;
            let (start, state) = match (
                self.resume.as_ref().filter(|r| r.level == level),
                coarser.take(),
            ) {
                (Some(resume), _) => (
                    LevelStart::Resumed {
                        sweeps: resume.sweeps,
                        partial: resume.partial.clone(),
                        history: resume.history.clone(),
                        prolongated: level > 0,
                    },
                    resume.state.clone(),
                ),
                (None, None) if self.alignment.is_some() || self.steering_landmarks().is_some() => {
                    let map = self
                        .alignment
                        .unwrap_or_else(GlobalMap::identity)
                        .on_grid((h, w), (lh, lw));
                    let landmarks = self.steering_landmarks().map(|l| l.on_grid((lh, lw)));
                    let (state, initialisation) = initial_state(
                        &grid,
                        &layout,
                        f_a,
                        f_b,
                        k,
                        cfg.params.delta,
                        &map,
                        landmarks.as_ref(),
                    )?;
                    observer.initialised(&initialisation);
                    (LevelStart::Fresh, state)
                }
                (None, None) => (
                    LevelStart::Fresh,
                    LevelState::initial(&grid, &layout, f_a, f_b, k, cfg.params.delta)?,
                ),
                (None, Some((coarse, coarse_state, coarse_layout))) => (
                    LevelStart::Prolongated,
                    prolongate(
                        model,
                        (&coarse, &coarse_state, &coarse_layout),
                        &grid,
                        &layout,
                        f_a,
                        f_b,
                        cfg.params.delta,
                    )?,
                ),
            };
            let mut ipalm = Ipalm::new(&grid, cfg.params, layout.clone(), cfg.ipalm)?;
            if let Some(landmarks) = &self.landmarks {
                ipalm = ipalm.with_landmarks(LandmarkTerm::new(
                    &grid,
                    &landmarks.on_grid((lh, lw)),
                    k,
                    cfg.landmark_weight,
                )?);
            }
            let mut run = LevelRun::init(
                ipalm,
                grid,
                layout,
                state,
                &start,
                model.pre_sweeps(),
                cfg.sweeps,
            )
            .with_fault_after(
                self.inject_nonfinite
                    .and_then(|(l, sweep)| (l == level).then_some(sweep)),
            )
            .with_stop_within(
                self.stop_within
                    .and_then(|(l, sweep, blocks)| (l == level).then_some((sweep, blocks))),
            );
            let history = match start {
                LevelStart::Resumed {
                    sweeps,
                    partial,
                    history,
                    ..
                } if sweeps > 0 || partial.is_some() => history,
                _ => Vec::new(),
            };
            let context = LevelContext {
                level,
                levels: sizes.len(),
                pre_sweeps: model.pre_sweeps(),
                started,
            };
            let Executed {
                summary,
                history,
                stopped,
                partial,
            } = self.execute(&mut run, &context, history, observer, interrupt)?;
            summaries.push(summary);
            if stopped.is_some() || level + 1 == sizes.len() {
                let (grid, state, layout, anisotropy) = run.terminate();
                return Ok(Morph {
                    grid,
                    state,
                    anisotropy,
                    layout,
                    termination: stopped.unwrap_or(Termination::Completed),
                    levels: summaries,
                    history,
                    partial,
                });
            }
            coarser = Some(run.into_coarse());
        }
        unreachable!("the last level returns")
    }

    /// The executor of one level: drives `run` sweep by sweep, owns the tolerance (over
    /// `history`, `E` after each joint sweep) and the interrupt (asked between the blocks of
    /// a sweep too: a signal is acted on within a step, not a sweep of `K` steps), and tells
    /// `observer` after every sweep.
    ///
    /// # Errors
    ///
    /// A failure other than a non-finite value (which ends the morph with
    /// [`Termination::NonFinite`] and the last finite iterate).
    fn execute(
        &self,
        run: &mut LevelRun,
        context: &LevelContext,
        mut history: Vec<f64>,
        observer: &mut dyn Observer,
        interrupt: &AtomicBool,
    ) -> Result<Executed> {
        let cfg = &self.config;
        let level = context.level;
        let (height, width) = (run.grid().height(), run.grid().width());
        let mut joint_sweeps = run.joint_sweeps_done();
        let mut level_stop = LevelStop::Sweeps;
        let mut stopped = None;
        let mut partial = None;
        let interrupted = || interrupt.load(Ordering::Relaxed);
        let level_started = Instant::now();
        while let Some(outcome) = run.next_sweep(&interrupted)? {
            let swept = match outcome {
                Outcome::Swept(swept) => swept,
                Outcome::Stopped {
                    phase,
                    sweep,
                    partial: blocks,
                } => {
                    stopped = Some(Termination::Interrupted {
                        level,
                        sweep: match phase {
                            Phase::Joint => sweep - 1,
                            Phase::Features => 0,
                        },
                    });
                    partial = blocks;
                    break;
                }
                Outcome::NonFinite(NonFinite { phase, sweep, what }) => {
                    stopped = Some(Termination::NonFinite {
                        level,
                        sweep,
                        phase,
                        what,
                    });
                    break;
                }
            };
            let mut stop = None;
            if swept.phase == Phase::Joint {
                joint_sweeps = swept.sweep;
                history.push(swept.energy.total);
                if swept.sweep > 0 {
                    if converged(&history, cfg.tolerance) {
                        stop = Some(LevelStop::Converged);
                    } else if swept.sweep == cfg.sweeps {
                        stop = Some(LevelStop::Sweeps);
                    }
                }
            }
            observer.sweep(&SweepEvent {
                level,
                levels: context.levels,
                grid: run.grid(),
                phase: swept.phase,
                sweep: swept.sweep,
                sweeps: match swept.phase {
                    Phase::Features => context.pre_sweeps,
                    Phase::Joint => cfg.sweeps,
                },
                energy: swept.energy.total,
                regularizer: swept.energy.regularizer,
                data: swept.energy.data,
                landmarks: swept.energy.landmarks,
                report: swept.report.as_ref(),
                state: run.state(),
                seconds: context.started.elapsed().as_secs_f64(),
                stop,
            });
            if stop == Some(LevelStop::Converged) {
                level_stop = LevelStop::Converged;
                break;
            }
            if swept.sweep > 0 && interrupted() {
                stopped = Some(Termination::Interrupted {
                    level,
                    sweep: if swept.phase == Phase::Joint {
                        swept.sweep
                    } else {
                        0
                    },
                });
                break;
            }
        }
        let summary = LevelSummary {
            level,
            size: [height, width],
            sweeps: joint_sweeps,
            stop: match &stopped {
                Some(Termination::Interrupted { .. }) => LevelStop::Interrupted,
                Some(Termination::NonFinite { .. }) => LevelStop::NonFinite,
                _ => level_stop,
            },
            seconds: level_started.elapsed().as_secs_f64(),
        };
        Ok(Executed {
            summary,
            history,
            stopped,
            partial,
        })
    }
}

/// What the executor of a level leaves.
struct Executed {
    /// The level's summary.
    summary: LevelSummary,
    /// `E` after each of its joint sweeps.
    history: Vec<f64>,
    /// Why the morph stops here (`None`: the level ran out of sweeps or converged, and the
    /// next one may follow).
    stopped: Option<Termination>,
    /// The blocks of the joint sweep an interrupt stopped.
    partial: Option<PartialSweep>,
}
