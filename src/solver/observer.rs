//! What the driver reports after each sweep, to whom, and why it stopped. Everything outside
//! the numerics (progress bars, energy logs, frame capture) is an [`Observer`]: the loop
//! never prints.

use crate::model::grid::Grid;
use crate::solver::estimate::TimeEstimate;
use crate::solver::ipalm::{LevelState, SweepReport};

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
    /// SPEC §11's landmark term `E_lm` of that evaluation (0 without landmarks).
    pub landmarks: f64,
    /// What the sweep did (`None` for the initial state).
    pub report: Option<&'a SweepReport>,
    /// The state after the sweep.
    pub state: &'a LevelState,
    /// Seconds since the morph started.
    pub seconds: f64,
    /// On the level's last joint sweep: why the level stops there.
    pub stop: Option<LevelStop>,
}

/// Why a level stopped.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LevelStop {
    /// It ran its `J` sweeps.
    Sweeps,
    /// `E` decreased by less than the tolerance over the last sweeps.
    Converged,
    /// The interrupt flag was raised.
    Interrupted,
    /// A non-finite value stopped the morph.
    NonFinite,
}

impl LevelStop {
    /// The word `energy.csv` and `config.json` use.
    pub fn name(self) -> &'static str {
        match self {
            LevelStop::Sweeps => "sweeps",
            LevelStop::Converged => "converged",
            LevelStop::Interrupted => "interrupted",
            LevelStop::NonFinite => "non_finite",
        }
    }
}

/// What one level did.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LevelSummary {
    /// Level index, 0 = coarsest.
    pub level: usize,
    /// `[H, W]`.
    pub size: [usize; 2],
    /// Joint sweeps run.
    pub sweeps: usize,
    /// Why it stopped.
    pub stop: LevelStop,
    /// Wall-clock seconds of its sweeps (feature-only and joint; not the level's set-up):
    /// in a resumed morph, those of this run only. 0 in checkpoints written before this
    /// was recorded.
    #[serde(default)]
    pub seconds: f64,
}

/// Receives progress from the driver; everything outside the numerics (progress bars,
/// energy logs, frame capture) is an observer.
pub trait Observer {
    /// After the initial state of a level (sweep 0) and after every sweep.
    fn sweep(&mut self, event: &SweepEvent<'_>);

    /// Before the first level, when the run was asked to estimate its time.
    fn estimate(&mut self, _estimate: &TimeEstimate) {}

    /// After SPEC §11's initial path of the coarsest level was built (with `--align` or
    /// landmarks only).
    fn initialised(&mut self, _initialisation: &Initialisation) {}
}

/// How SPEC §11's initial path of the coarsest level came out.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Initialisation {
    /// For each step `k = 1..K`: how often its displacement was halved to make it
    /// admissible; [`MAX_HALVINGS`](crate::solver::initial::MAX_HALVINGS) + 1 means it
    /// never was, and the step starts at `Id`.
    pub halvings: Vec<u32>,
}

impl Initialisation {
    /// A warning for the user when a step could not take its full share, `None` otherwise.
    pub fn warning(&self) -> Option<String> {
        let limit = crate::solver::initial::MAX_HALVINGS;
        let halved = self
            .halvings
            .iter()
            .filter(|&&h| h > 0 && h <= limit)
            .count();
        let identity = self.halvings.iter().filter(|&&h| h > limit).count();
        if halved == 0 && identity == 0 {
            return None;
        }
        let most = self
            .halvings
            .iter()
            .copied()
            .filter(|&h| h <= limit)
            .max()
            .unwrap_or(0);
        Some(format!(
            "warning: the initial path's deformations folded: {halved} of {} steps start \
             with their displacement halved (up to {most} times){}",
            self.halvings.len(),
            if identity > 0 {
                format!(", {identity} at the identity")
            } else {
                String::new()
            }
        ))
    }
}

/// An observer that does nothing.
impl Observer for () {
    fn sweep(&mut self, _: &SweepEvent<'_>) {}
}

impl<T: Observer + ?Sized> Observer for &mut T {
    fn sweep(&mut self, event: &SweepEvent<'_>) {
        (**self).sweep(event);
    }

    fn estimate(&mut self, estimate: &TimeEstimate) {
        (**self).estimate(estimate);
    }

    fn initialised(&mut self, initialisation: &Initialisation) {
        (**self).initialised(initialisation);
    }
}

/// Two observers, called in order.
impl<A: Observer, B: Observer> Observer for (A, B) {
    fn sweep(&mut self, event: &SweepEvent<'_>) {
        self.0.sweep(event);
        self.1.sweep(event);
    }

    fn initialised(&mut self, initialisation: &Initialisation) {
        self.0.initialised(initialisation);
        self.1.initialised(initialisation);
    }

    fn estimate(&mut self, estimate: &TimeEstimate) {
        self.0.estimate(estimate);
        self.1.estimate(estimate);
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
