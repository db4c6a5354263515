//! How long a morph will take, measured before it starts: a few sweeps on two levels of the
//! real problem, timed on the backend that will run it, and a cost model fitted to them.
//!
//! A sweep's time is a fixed part (launching ops, the autodiff graph, small allocations:
//! what dominates at 16²–32²) plus a part proportional to its work `K · C · H · W` (the
//! warps, convolutions and elementwise passes, all linear in it). Timing the coarsest level
//! alone would read mostly the fixed part and, scaled by pixels to the finest level,
//! overestimate a 256² morph about twice; so the calibration times the coarsest level and
//! the first level above it of at least [`CALIBRATION_PIXELS`] (RGB:
//! [`RGB_CALIBRATION_PIXELS`]) pixels (or the finest), and fits
//! both parts. The deep
//! model's feature-only sweeps are timed on the second level too, as a fraction of a joint
//! sweep.
//!
//! The estimate assumes every level runs all its `J` sweeps: with a tolerance, levels
//! usually stop sooner. It is an estimate, not a bound: sweeps from the initial state are
//! not quite the sweeps of a running level. In the deep model they are cheaper, by a
//! measured factor the estimate applies ([`DEEP_RUNNING_LEVEL`]); docs/benchmarks.md
//! compares estimates with measured runs. The progress report rescales the remaining time
//! by how fast the run actually goes.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use burn::tensor::{Device, Tensor};

use crate::error::Result;
use crate::model::feature_model::FeatureModel;
use crate::model::grid::Grid;
use crate::solver::ipalm::{Ipalm, LevelState, SweepCarry, SweepKind};
use crate::solver::multilevel::{Multilevel, level_endpoints};
use crate::solver::observer::Phase;

/// The second calibration level is the first with at least this many pixels (64²), where a
/// sweep's time is mostly work, not overhead (or the finest, if smaller).
pub const CALIBRATION_PIXELS: usize = 64 * 64;

/// The RGB model's second calibration level: the first with at least this many pixels
/// (128²). An RGB sweep at 64² is still mostly overhead per value (3 channels), so the line
/// through 16² (or 32²) and 64² overestimated the finer levels' sweeps, and one timed sweep
/// a level left the line to the machine's noise: measured 2026-12-07 (Intel Xeon), the
/// 256² sweeps of default morphs 1.6–2.7× their estimate (`faces`: 2 min 38 s estimated
/// for all 250 sweeps a level, about 67 s measured; `cars`: 1 min 44 s for 73 s), and
/// `--quality paper` `faces` at 512² estimated 5 min 54 s … 9 min 28 s for 3 min 54 s.
/// Through 128², each point the median of three timed sweeps: `faces` 59–62 s, `cars`
/// 62–77 s, the paper morph 3 min 53 s … 4 min 48 s (−15 … +23 %), for about 0.2 s more
/// calibration (each point now the median of the sweeps of a third of a second,
/// three at least).
pub const RGB_CALIBRATION_PIXELS: usize = 128 * 128;

/// The most steps a calibration path has: the default `K` = 15 is timed whole, and a path
/// of thousands of steps is timed on a part (its first sweep would otherwise take as long
/// as a sweep of the morph, tens of seconds before the morph even starts).
pub const CALIBRATION_STEPS: usize = 16;

/// How much more a joint sweep of a running level of the deep model costs than the
/// calibration's sweep from the level's initial state. SPEC §6's safeguard restarts a step's
/// inertia (a second linearisation and search) more often as a level converges, and the
/// searches take more trials: in a default deep morph (`faces`, 256², 2026-12-06) the
/// finest level restarted 0.65 steps a sweep in its first 60 sweeps and 3.0 after, the 128²
/// level 1.5 and 6.2, and each level's mean joint sweep took 1.38–1.44 times the calibrated
/// one on the three finest levels (1.46 over the whole solve for the sweeps it ran). Without
/// the factor that morph's estimate was 27 % short (a run of the session before: 20 %).
/// With 1.4 two later default morphs (2026-12-07, 256²) came out 10 % short (`faces`) and
/// 17 % short (`cars`, whose 32²–256² levels ran 1.13–1.57 times their calibrated sweeps):
/// 1.55 puts both within 10 % (≈ −1 % and ≈ −9 %; docs/benchmarks.md).
/// The RGB model's sweeps have no such drift measured; its factor is 1.
pub const DEEP_RUNNING_LEVEL: f64 = 1.55;

/// A morph's predicted time, level by level; `config.json` records it (`outcome.estimate`)
/// beside what each level took (`outcome.levels[l].seconds`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TimeEstimate {
    /// Predicted seconds of one joint sweep on each level, coarse to fine (in the deep model
    /// with [`DEEP_RUNNING_LEVEL`]).
    #[serde(rename = "joint_sweep_seconds")]
    pub joint: Vec<f64>,
    /// Predicted seconds of one feature-only sweep on each level (deep model; 0 for RGB).
    #[serde(rename = "features_only_sweep_seconds")]
    pub features_only: Vec<f64>,
    /// `J`.
    pub sweeps: usize,
    /// Feature-only sweeps before the joint ones on every level after the first.
    pub pre_sweeps: usize,
    /// Whether a tolerance may stop levels before their `J` sweeps (the estimate is then an
    /// upper bound).
    pub early_stops: bool,
    /// What the calibration itself took, seconds.
    pub calibration_seconds: f64,
    /// Predicted seconds of the work after the solve that is not writing files: the deep
    /// model's feature-space path metric, `2K` VGG19 forwards at the working size, timed by
    /// the caller on the inputs' forwards (0: none, the RGB model).
    #[serde(rename = "after_solve_seconds")]
    pub after_solve: f64,
}

impl TimeEstimate {
    /// Seconds of the sweeps still to run after sweep `sweep` of `phase` on `level` (0:
    /// none of that phase done yet), every level running all its sweeps.
    pub fn remaining_after(&self, level: usize, phase: Phase, sweep: usize) -> f64 {
        let mut total = 0.0;
        for l in level..self.joint.len() {
            let pre = if l == 0 { 0 } else { self.pre_sweeps };
            let (pre_done, joint_done) = match (l == level, phase) {
                (false, _) => (0, 0),
                (true, Phase::Features) => (sweep.min(pre), 0),
                (true, Phase::Joint) => (pre, sweep.min(self.sweeps)),
            };
            total += (pre - pre_done) as f64 * self.features_only[l]
                + (self.sweeps - joint_done) as f64 * self.joint[l];
        }
        total
    }

    /// Seconds of level `level`'s sweeps, all of them run.
    pub fn level(&self, level: usize) -> f64 {
        self.remaining_after(level, Phase::Features, 0)
            - self.remaining_after(level + 1, Phase::Features, 0)
    }

    /// Seconds of the whole morph, every level running all its sweeps, and what follows the
    /// solve ([`after_solve`](Self::after_solve)).
    pub fn total(&self) -> f64 {
        self.remaining_after(0, Phase::Features, 0) + self.after_solve
    }
}

/// How many sweeps a calibration level times: at least `sweeps`, and more until they add up
/// to `seconds` (at most [`MOST_TIMED_SWEEPS`]).
#[derive(Clone, Copy, Debug)]
struct Timing {
    sweeps: usize,
    seconds: f64,
}

/// The most sweeps [`Timing`] times on one level.
const MOST_TIMED_SWEEPS: usize = 40;

impl Timing {
    /// Whether the sweeps timed so far, `seconds` each, are enough.
    fn done(&self, seconds: &[f64]) -> bool {
        seconds.len() >= MOST_TIMED_SWEEPS
            || (seconds.len() >= self.sweeps && seconds.iter().sum::<f64>() >= self.seconds)
    }
}

/// The RGB model's calibration on each level: sweeps until a third of a second. Three
/// sweeps of 128² (about 25 ms each on the 2-core AMD EPYC of docs/benchmarks.md) left the
/// line to the machine's noise: 14 starts of the same `--quality paper` 512² morph
/// estimated 1 min 52 s … 3 min 34 s (2026-12-07; the run took 2 min 23 s and 2 min 49 s),
/// and the 512² sweep is 16 times the 128² one. Timed so, 19 starts gave 2 min 00 s … 3 min
/// 48 s, 16 of them 2 min 00 s … 2 min 29 s (of 14 starts before, 6 in that range): what
/// remains is the machine itself running a whole second slower (the one outlier whose sweeps
/// were logged took 38–46 ms for each 128² sweep, the others 25–37 ms).
const RGB_TIMING: Timing = Timing {
    sweeps: 3,
    seconds: 0.3,
};

/// The deep model's: one sweep (a 64² deep sweep is already a tenth of a second or more,
/// and its running factor, [`DEEP_RUNNING_LEVEL`], was fitted to one).
const DEEP_TIMING: Timing = Timing {
    sweeps: 1,
    seconds: 0.0,
};

/// Seconds of a sweep of `kind` (followed by the energy evaluation the driver runs after
/// every sweep): the median of the sweeps `timing` asks for, after one untimed sweep that
/// warms the allocator and caches.
fn time_sweeps(
    ipalm: &Ipalm,
    state: &mut LevelState,
    kind: SweepKind,
    timing: Timing,
    interrupt: &AtomicBool,
) -> Result<Option<f64>> {
    // As the driver runs them: each sweep starts from what the previous one carried.
    let mut carry = SweepCarry::default();
    let mut sweep = |state: &mut LevelState| -> Result<()> {
        let report = ipalm.sweep_carrying(state, kind, &mut carry)?;
        // Reading the energy back synchronises the backend, as the driver does.
        ipalm.energy_after_carrying(state, Some(&report), &mut carry);
        Ok(())
    };
    sweep(state)?;
    let mut seconds: Vec<f64> = Vec::with_capacity(timing.sweeps);
    while !timing.done(&seconds) {
        if interrupt.load(Ordering::Relaxed) {
            return Ok(None);
        }
        let started = Instant::now();
        sweep(state)?;
        seconds.push(started.elapsed().as_secs_f64());
    }
    // The median: one sweep slowed by the machine does not move it.
    seconds.sort_by(f64::total_cmp);
    Ok(Some(seconds[seconds.len() / 2]))
}

impl Multilevel {
    /// Times sweeps on two levels of this morph (see the module's documentation) and
    /// predicts each level's sweep time: a fraction of a second to a few seconds, on the
    /// device that will run the morph. The timed paths have at most [`CALIBRATION_STEPS`]
    /// steps (a sweep's cost is linear in `K`), so the calibration stays short at any `K`;
    /// `None` if `interrupt` was raised meanwhile (checked between the timed sweeps).
    ///
    /// # Errors
    ///
    /// As [`Multilevel::run_with`].
    pub fn estimate_time(
        &self,
        device: &Device,
        u_a: &Tensor<4>,
        u_b: &Tensor<4>,
        model: &FeatureModel,
        interrupt: &AtomicBool,
    ) -> Result<Option<TimeEstimate>> {
        let started = Instant::now();
        let cfg = self.config();
        let [_, _, h, w] = u_a.dims();
        let sizes = cfg.level_sizes(h, w)?;
        let full = Grid::new(h, w, device, u_a.dtype())?;
        let k = cfg.steps;
        let timed_steps = k.min(CALIBRATION_STEPS);
        // Two points whenever there are two levels: the coarsest, and the first level above
        // it of at least the model's calibration pixels (else the finest). One point read as all rate
        // would scale the coarsest level's fixed part up with the pixels (measured: a 256²
        // morph whose coarsest level is 64² was estimated 50 % high that way).
        let (threshold, timing) = match model {
            FeatureModel::Deep(_) => (CALIBRATION_PIXELS, DEEP_TIMING),
            FeatureModel::Rgb => (RGB_CALIBRATION_PIXELS, RGB_TIMING),
        };
        let second = sizes
            .iter()
            .skip(1)
            .position(|&(lh, lw)| lh * lw >= threshold)
            .map_or(sizes.len() - 1, |p| p + 1);
        // Work of a timed sweep on each level: K · C · H · W with the timed K.
        let mut work = Vec::with_capacity(sizes.len());
        for (level, &(lh, lw)) in sizes.iter().enumerate() {
            let channels = model.layout(sizes.len() - 1 - level)?.channels();
            work.push((timed_steps * channels * lh * lw) as f64);
        }
        let mut timed = Vec::new();
        let mut features_ratio = 0.0;
        for level in if second == 0 {
            vec![0]
        } else {
            vec![0, second]
        } {
            let (lh, lw) = sizes[level];
            let grid = Grid::new(lh, lw, device, u_a.dtype())?;
            let downsampling = sizes.len() - 1 - level;
            let (layout, f_a, f_b) = level_endpoints(model, &full, &grid, u_a, u_b, downsampling)?;
            let ipalm = Ipalm::new(&grid, cfg.params, layout.clone(), cfg.ipalm)?;
            let mut state =
                LevelState::initial(&grid, &layout, f_a, f_b, timed_steps, cfg.params.delta)?;
            let Some(joint) = time_sweeps(&ipalm, &mut state, SweepKind::Joint, timing, interrupt)?
            else {
                return Ok(None);
            };
            if level == second && model.pre_sweeps() > 0 {
                let Some(features) = time_sweeps(
                    &ipalm,
                    &mut state,
                    SweepKind::FeaturesOnly,
                    DEEP_TIMING,
                    interrupt,
                )?
                else {
                    return Ok(None);
                };
                features_ratio = features / joint;
            }
            timed.push((work[level], joint));
        }
        // seconds = fixed + rate · work, through both points (one point: no fixed part).
        let (fixed, rate) = match timed[..] {
            [(w1, t1), (w2, t2)] if w2 > w1 => {
                let rate = ((t2 - t1) / (w2 - w1)).max(0.0);
                ((t1 - rate * w1).max(0.0), rate)
            }
            [(w1, t1), ..] => (0.0, t1 / w1),
            [] => unreachable!("at least one level is timed"),
        };
        // Nearly all of a sweep is per step (the fixed part too: launches and reductions
        // of each step's warps), so a sweep of `K` steps costs `K / timed` timed sweeps.
        let per_step = k as f64 / timed_steps as f64;
        let calibrated: Vec<f64> = work
            .iter()
            .map(|&wk| per_step * (fixed + rate * wk))
            .collect();
        // Feature-only sweeps run no deformation step, so no safeguard: as calibrated.
        let running = match model {
            FeatureModel::Deep(_) => DEEP_RUNNING_LEVEL,
            FeatureModel::Rgb => 1.0,
        };
        Ok(Some(TimeEstimate {
            features_only: calibrated.iter().map(|t| t * features_ratio).collect(),
            joint: calibrated.iter().map(|t| t * running).collect(),
            sweeps: cfg.sweeps,
            pre_sweeps: model.pre_sweeps(),
            early_stops: cfg.tolerance > 0.0,
            calibration_seconds: started.elapsed().as_secs_f64(),
            after_solve: 0.0,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calibration_times_its_minimum_then_until_its_seconds_then_stops_at_the_cap() {
        // RGB: three sweeps at least, then on until a third of a second.
        assert!(!RGB_TIMING.done(&[0.2, 0.2]));
        assert!(RGB_TIMING.done(&[0.2, 0.2, 0.2]));
        assert!(!RGB_TIMING.done(&[0.026; 3]));
        assert!(!RGB_TIMING.done(&[0.026; 11]));
        assert!(RGB_TIMING.done(&[0.026; 12]));
        // Sweeps of a millisecond stop at the cap, not after 300 of them.
        assert!(!RGB_TIMING.done(&[0.001; MOST_TIMED_SWEEPS - 1]));
        assert!(RGB_TIMING.done(&[0.001; MOST_TIMED_SWEEPS]));
        // Deep: one sweep, however short.
        assert!(!DEEP_TIMING.done(&[]));
        assert!(DEEP_TIMING.done(&[0.001]));
    }

    fn estimate() -> TimeEstimate {
        TimeEstimate {
            joint: vec![1.0, 2.0, 4.0],
            features_only: vec![0.5, 1.0, 2.0],
            sweeps: 10,
            pre_sweeps: 3,
            early_stops: true,
            calibration_seconds: 0.0,
            after_solve: 0.0,
        }
    }

    #[test]
    fn remaining_time_counts_down_to_zero() {
        let e = estimate();
        // Level 0 runs no feature-only sweeps; the others 3 each before their 10.
        let total = 10.0 * 1.0 + (3.0 * 1.0 + 10.0 * 2.0) + (3.0 * 2.0 + 10.0 * 4.0);
        assert_eq!(e.total(), total);
        assert_eq!(e.remaining_after(0, Phase::Joint, 4), total - 4.0);
        assert_eq!(e.remaining_after(1, Phase::Features, 2), 1.0 + 20.0 + 46.0);
        assert_eq!(e.remaining_after(1, Phase::Joint, 0), 20.0 + 46.0);
        assert_eq!(e.remaining_after(2, Phase::Joint, 10), 0.0);
        assert_eq!(
            [e.level(0), e.level(1), e.level(2)],
            [10.0, 3.0 + 20.0, 6.0 + 40.0]
        );
        let measured = TimeEstimate {
            after_solve: 7.5,
            ..e
        };
        assert_eq!(measured.total(), total + 7.5);
        assert_eq!(measured.remaining_after(0, Phase::Joint, 4), total - 4.0);
    }
}
