//! The command line's progress report: a bar per level on a terminal, or a line per sweep.

use std::io::IsTerminal;

use deepmorph::solver::estimate::TimeEstimate;
use deepmorph::solver::observer::{Initialisation, Observer, Phase, SweepEvent};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

/// How much the command line prints while a morph runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verbosity {
    /// Nothing.
    Quiet,
    /// A progress bar per level, only when stderr is a terminal.
    Normal,
    /// One line per sweep on stderr.
    Verbose,
}

/// The command line's progress report: a bar per level (sweep, energy, speed, the whole
/// morph's time left) or a line per sweep.
pub struct Progress {
    verbosity: Verbosity,
    bar: Option<ProgressBar>,
    estimate: Option<TimeEstimate>,
}

/// `seconds` for people: `12.3 s`, `4 min 05 s`, `2 h 07 min`.
pub fn duration(seconds: f64) -> String {
    let s = seconds.max(0.0).round() as u64;
    match s {
        _ if seconds < 60.0 => format!("{seconds:.1} s"),
        0..3600 => format!("{} min {:02} s", s / 60, s % 60),
        _ => format!("{} h {:02} min", s / 3600, (s % 3600) / 60),
    }
}

impl Progress {
    /// A reporter at `verbosity`; the bar is hidden when stderr is not a terminal.
    pub fn new(verbosity: Verbosity) -> Self {
        Self {
            verbosity,
            bar: None,
            estimate: None,
        }
    }

    /// The whole morph's time left after the sweep of `e`: the estimate's remaining sweeps,
    /// scaled by how the run's time so far compares with the estimate's for the same sweeps
    /// (levels the tolerance stopped early count as done, which shortens it); with a
    /// tolerance, levels still to come may stop sooner too.
    fn time_left(&self, e: &SweepEvent<'_>) -> Option<f64> {
        let estimate = self.estimate.as_ref()?;
        let remaining = estimate.remaining_after(e.level, e.phase, e.sweep);
        let predicted_so_far = estimate.total() - remaining;
        let scale = if predicted_so_far > 1.0 && e.seconds > 1.0 {
            e.seconds / predicted_so_far
        } else {
            1.0
        };
        Some(remaining * scale)
    }

    fn new_bar(&self, e: &SweepEvent<'_>) -> ProgressBar {
        let bar = ProgressBar::new(e.sweeps as u64);
        if self.verbosity != Verbosity::Normal || !std::io::stderr().is_terminal() {
            bar.set_draw_target(ProgressDrawTarget::hidden());
        }
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix} [{bar:30}] {pos}/{len} sweeps  {per_sec}  {msg}",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        bar.set_prefix(format!(
            "level {}/{} {}x{}{}",
            e.level + 1,
            e.levels,
            e.grid.height(),
            e.grid.width(),
            if e.phase == Phase::Features {
                " features only"
            } else {
                ""
            }
        ));
        bar
    }
}

impl Observer for Progress {
    fn initialised(&mut self, initialisation: &Initialisation) {
        // A warning, so also when quiet.
        if let Some(warning) = initialisation.warning() {
            eprintln!("{warning}");
        }
    }

    fn estimate(&mut self, estimate: &TimeEstimate) {
        if self.verbosity != Verbosity::Quiet {
            let total = duration(estimate.total());
            let mut timed = format!(
                "sweeps timed on this machine in {:.1} s",
                estimate.calibration_seconds
            );
            if estimate.after_solve > 0.0 {
                timed.push_str(&format!(
                    "; {} of it measures the path in VGG19 feature space after the solve",
                    duration(estimate.after_solve)
                ));
            }
            if estimate.early_stops {
                eprintln!(
                    "estimated time: about {total} if every level runs all its {} sweeps (the \
                     tolerance usually stops levels sooner; {timed})",
                    estimate.sweeps
                );
            } else {
                eprintln!("estimated time: about {total} ({timed})");
            }
        }
        self.estimate = Some(estimate.clone());
    }

    fn sweep(&mut self, e: &SweepEvent<'_>) {
        if self.verbosity == Verbosity::Quiet {
            return;
        }
        if e.sweep == 0 {
            if let Some(done) = self.bar.take() {
                done.finish();
            }
            self.bar = Some(self.new_bar(e));
        }
        if let Some(bar) = &self.bar {
            bar.set_position(e.sweep as u64);
            let left = self
                .time_left(e)
                .map_or(String::new(), |t| format!("  morph: {} left", duration(t)));
            bar.set_message(format!("E {:.5e}{left}", e.energy));
            if e.sweep == e.sweeps && e.level + 1 == e.levels && e.phase == Phase::Joint {
                bar.finish();
            }
        }
        if self.verbosity == Verbosity::Verbose {
            let (trials, restarts, drops_phi, drops_f) = e.report.map_or((0, 0, 0, 0), |r| {
                (
                    r.deformation_trials(),
                    r.restarts(),
                    r.deformation_drops(),
                    r.feature_drops(),
                )
            });
            eprintln!(
                "level {} ({}x{}) {}sweep {:>4}/{}: E = {:.6e} (R {:.4e}, D {:.4e}), phi trials {trials}, restarts {restarts}, dropped phi {drops_phi} f {drops_f}, {:.1} s",
                e.level,
                e.grid.height(),
                e.grid.width(),
                if e.phase == Phase::Features {
                    "feature-only "
                } else {
                    ""
                },
                e.sweep,
                e.sweeps,
                e.energy,
                e.regularizer,
                e.data,
                e.seconds
            );
            if let Some(stop) = e.stop {
                let peak =
                    deepmorph::app::memory::peak_resident_bytes().map_or(String::new(), |p| {
                        format!(
                            "; peak memory so far {:.0} MiB",
                            p as f64 / (1u64 << 20) as f64
                        )
                    });
                let left = self
                    .time_left(e)
                    .map_or(String::new(), |t| format!("; about {} left", duration(t)));
                eprintln!(
                    "level {} done after {} sweeps ({}) at {:.1} s{peak}{left}",
                    e.level,
                    e.sweep,
                    stop.name(),
                    e.seconds
                );
            }
        }
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.abandon();
        }
    }
}
