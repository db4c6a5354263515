//! The coarse-to-fine driver (SPEC §7): builds the pyramid, initialises the coarsest level,
//! prolongates deformations and images (and, in the deep model, re-initialises the VGG
//! channels and runs the `J_pre` feature-only sweeps), and runs `J` iPALM sweeps per level,
//! reporting to an [`Observer`] after every sweep.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use burn::tensor::{Device, Tensor};

use crate::deep::DeepFeatures;
use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::io::to_host;
use crate::layout::FeatureLayout;
use crate::optim::ipalm::{
    Ipalm, IpalmConfig, LevelState, SweepKind, SweepReport, initial_lipschitz,
};
use crate::params::EnergyParams;
use crate::resample::{Resize, prolongate_deformation};

/// Settings of a multilevel morph (SPEC §7, §9).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MultilevelConfig {
    /// Number of steps `K` (frames `0..=K`). Default 15.
    pub steps: usize,
    /// Pyramid levels. Default 5. The working size must be divisible by `2^(levels−1)` and
    /// the coarsest level at least 4 × 4.
    pub levels: usize,
    /// Sweeps `J` per level. Default 250.
    pub sweeps: usize,
    /// The energy's parameters.
    pub params: EnergyParams,
    /// The solver's settings.
    pub ipalm: IpalmConfig,
}

impl Default for MultilevelConfig {
    fn default() -> Self {
        Self {
            steps: 15,
            levels: 5,
            sweeps: 250,
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
        if self.levels < 1 {
            return Err(Error::invalid("levels", self.levels, "at least 1"));
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

/// The working size of a `height × width` input on `levels` levels (`levels ≥ 1`): scaled,
/// never up, so that the longer side is at most `max_side`, then each side rounded to a
/// multiple of `2^(levels−1)` and at least 4 of those (SPEC §7 needs both; bringing the
/// inputs to this size is outside the model).
pub fn fit_size(height: usize, width: usize, max_side: usize, levels: usize) -> (usize, usize) {
    let factor = 1usize << (levels - 1);
    let scale = (max_side as f64 / height.max(width) as f64).min(1.0);
    let round = |v: usize| ((v as f64 * scale / factor as f64).round() as usize).max(4) * factor;
    (round(height), round(width))
}

/// Which model's feature vectors a morph uses (SPEC §4).
#[derive(Clone, Debug)]
pub enum FeatureModel {
    /// `f = u`.
    Rgb,
    /// `f = (η·u, τ·F/rms)` with the VGG taps of the inputs.
    Deep(DeepFeatures),
}

impl FeatureModel {
    /// The channel layout of the level whose grid is `1/2^downsampling` of the input.
    ///
    /// # Errors
    ///
    /// In the deep model, if no VGG tap has that size.
    pub fn layout(&self, downsampling: usize) -> Result<FeatureLayout> {
        match self {
            Self::Rgb => Ok(FeatureLayout::rgb()),
            Self::Deep(deep) => deep.layout(downsampling),
        }
    }

    /// Feature-only sweeps after a prolongation (`J_pre`; 0 in the RGB model).
    pub fn pre_sweeps(&self) -> usize {
        match self {
            Self::Rgb => 0,
            Self::Deep(deep) => deep.config().pre_sweeps,
        }
    }
}

/// Which sweeps an event belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Phase {
    /// The deep model's feature-only sweeps after a prolongation (SPEC §7).
    Features,
    /// The joint sweeps (`J` per level).
    Joint,
}

/// What an observer sees after each sweep.
#[derive(Debug)]
pub struct SweepEvent<'a> {
    /// Level index, 0 = coarsest.
    pub level: usize,
    /// Number of levels.
    pub levels: usize,
    /// The level's grid.
    pub grid: &'a Grid,
    /// Which sweeps: the joint ones or the deep model's feature-only ones before them.
    pub phase: Phase,
    /// Sweep index in this phase on this level, 1-based (0 = the state the phase starts
    /// from; for [`Phase::Joint`] that is after any feature-only sweeps).
    pub sweep: usize,
    /// Sweeps of this phase per level.
    pub sweeps: usize,
    /// `E` after the sweep (with `a_k` recomputed, SPEC §10).
    pub energy: f64,
    /// `Σ_k R_k` of that evaluation (times `K`, as in `E`).
    pub regularizer: f64,
    /// `Σ_k D_k / δ` of that evaluation (times `K`, as in `E`).
    pub data: f64,
    /// What the sweep did (`None` for the initial state).
    pub report: Option<&'a SweepReport>,
    /// The state after the sweep.
    pub state: &'a LevelState,
    /// Seconds since the morph started.
    pub seconds: f64,
}

/// Receives progress from the driver; everything outside the numerics (progress bars,
/// energy logs, frame capture) is an observer.
pub trait Observer {
    /// After the initial state of a level (sweep 0) and after every sweep.
    fn sweep(&mut self, event: &SweepEvent<'_>);
}

/// An observer that does nothing.
impl Observer for () {
    fn sweep(&mut self, _: &SweepEvent<'_>) {}
}

impl<T: Observer + ?Sized> Observer for &mut T {
    fn sweep(&mut self, event: &SweepEvent<'_>) {
        (**self).sweep(event);
    }
}

/// Two observers, called in order.
impl<A: Observer, B: Observer> Observer for (A, B) {
    fn sweep(&mut self, event: &SweepEvent<'_>) {
        self.0.sweep(event);
        self.1.sweep(event);
    }
}

/// Why the driver stopped.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Termination {
    /// Every level ran its `J` sweeps.
    Completed,
    /// The interrupt flag was raised; the state is the one after the last full sweep.
    Interrupted {
        /// Level at which it stopped.
        level: usize,
        /// Sweeps done on that level.
        sweep: usize,
    },
    /// A NaN or infinity appeared in sweep `sweep` of level `level` (or in the energy after
    /// it); the state is the last finite iterate, the one before that sweep.
    NonFinite {
        /// Level at which it happened.
        level: usize,
        /// The sweep in which it happened (0: the level's initial state), counted in the
        /// phase `phase`.
        sweep: usize,
        /// The joint sweeps or the deep model's feature-only ones.
        phase: Phase,
        /// Which quantity, and at which step `k`.
        what: String,
    },
}

impl std::fmt::Display for Termination {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Completed => f.write_str("completed"),
            Self::Interrupted { level, sweep } => {
                write!(f, "interrupted at level {level}, sweep {sweep}")
            }
            Self::NonFinite {
                level,
                sweep,
                phase,
                what,
            } => {
                let kind = match phase {
                    Phase::Joint => "",
                    Phase::Features => "feature-only ",
                };
                write!(
                    f,
                    "stopped by a non-finite value at level {level}, {kind}sweep {sweep} ({what}); \
                     the state is the last finite iterate, before that sweep"
                )
            }
        }
    }
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

/// The multilevel driver.
#[derive(Clone, Debug)]
pub struct Multilevel {
    config: MultilevelConfig,
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
            inject_nonfinite: None,
        })
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
    /// [`DeepFeatures`] must have been computed from the same `u_a`, `u_b`).
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
        for (level, &(lh, lw)) in sizes.iter().enumerate() {
            let downsampling = sizes.len() - 1 - level;
            let layout = model.layout(downsampling)?;
            let grid = Grid::new(lh, lw, device, dtype)?;
            let resize = Resize::new(&full, &grid);
            let (u_a_level, u_b_level) = (resize.apply(u_a.clone()), resize.apply(u_b.clone()));
            let (f_a, f_b) = match model {
                FeatureModel::Rgb => (u_a_level, u_b_level),
                FeatureModel::Deep(deep) => {
                    let (tap_a, tap_b) = deep.tap(downsampling)?;
                    (deep.stack(u_a_level, tap_a), deep.stack(u_b_level, tap_b))
                }
            };
            let prolongated = previous.is_some();
            let mut state = match previous.take() {
                None => LevelState::initial(&grid, &layout, f_a, f_b, k, cfg.params.delta)?,
                Some((coarse, coarse_state, coarse_layout)) => {
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

            let evaluate = |state: &LevelState| -> std::result::Result<[f64; 3], String> {
                let value = ipalm.energy(state);
                let parts = to_host(Tensor::cat(
                    vec![
                        value.total,
                        value.regularizer.clone().mul_scalar(k as f64),
                        value.data.clone().mul_scalar(k as f64 / cfg.params.delta),
                    ],
                    0,
                ));
                let (total, per_step) = (parts[0], &parts[1..]);
                if total.is_finite() {
                    let sum = |v: &[f64]| v.iter().sum::<f64>();
                    return Ok([total, sum(&per_step[..k]), sum(&per_step[k..])]);
                }
                let bad = (0..k)
                    .find(|&i| !(per_step[i].is_finite() && per_step[k + i].is_finite()))
                    .map_or(String::new(), |i| {
                        format!(
                            " (step k = {}: K·R = {}, (K/δ)·D = {})",
                            i + 1,
                            per_step[i],
                            per_step[k + i]
                        )
                    });
                Err(format!("the path energy is {total}{bad}"))
            };
            let mut report_sweep =
                |phase: Phase, sweep: usize, report: Option<&SweepReport>, state: &LevelState, numbers: [f64; 3]| {
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
                    });
                };
            // SPEC §7: after a prolongation the deep model first fits the features to the
            // prolongated deformations (pointless on the first level, where the convex
            // combination is already optimal for φ = Id).
            let pre = if prolongated { model.pre_sweeps() } else { 0 };
            let phases = [(Phase::Features, pre, SweepKind::FeaturesOnly), (Phase::Joint, cfg.sweeps, SweepKind::Joint)];
            let mut stopped = None;
            'phases: for (phase, sweeps, kind) in phases {
                if sweeps == 0 && phase == Phase::Features {
                    continue;
                }
                match evaluate(&state) {
                    Ok(numbers) => report_sweep(phase, 0, None, &state, numbers),
                    Err(what) => {
                        stopped = Some(Termination::NonFinite { level, sweep: 0, phase, what });
                        break 'phases;
                    }
                }
                for sweep in 1..=sweeps {
                    // The last finite iterate: cheap to keep, these handles are the tensors
                    // the sweep moves into `f_prev` and `phi_prev` anyway.
                    let before = (state.f.clone(), state.phi.clone());
                    let outcome = match ipalm.sweep(&mut state, kind) {
                        Ok(report) => Ok(report),
                        Err(Error::NonFinite { what }) => Err(what),
                        Err(other) => return Err(other),
                    };
                    if self.inject_nonfinite == Some((level, sweep)) {
                        state.f[1] = state.f[1].clone().mul_scalar(f64::NAN);
                    }
                    match outcome.and_then(|report| evaluate(&state).map(|n| (report, n))) {
                        Ok((report, numbers)) => {
                            report_sweep(phase, sweep, Some(&report), &state, numbers);
                        }
                        Err(what) => {
                            let (f, phi) = before;
                            state.f_prev = f.clone();
                            state.phi_prev = phi.clone();
                            state.f = f;
                            state.phi = phi;
                            stopped = Some(Termination::NonFinite { level, sweep, phase, what });
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
            if stopped.is_some() || level + 1 == sizes.len() {
                let anisotropy = ipalm.anisotropies(&state);
                return Ok(Morph {
                    grid,
                    state,
                    anisotropy,
                    layout,
                    termination: stopped.unwrap_or(Termination::Completed),
                });
            }
            previous = Some((grid, state, layout));
        }
        unreachable!("the last level returns")
    }
}
