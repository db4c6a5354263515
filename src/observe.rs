//! Observers of a morph (see [`crate::multilevel::Observer`]): a progress bar, a per-sweep
//! log line, and the energy log written to `energy.csv`. None of them touches the numerics.

use std::fmt::Write as _;
use std::io::IsTerminal;

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::multilevel::{Observer, Phase, SweepEvent};

/// One line of `energy.csv`.
#[derive(Clone, Debug, PartialEq)]
pub struct EnergyRecord {
    /// Level, 0 = coarsest.
    pub level: usize,
    /// Grid rows and columns of the level.
    pub height: usize,
    /// Columns.
    pub width: usize,
    /// Sweep on the level (0 = its initial state).
    pub sweep: usize,
    /// `E` after the sweep.
    pub energy: f64,
    /// `K Σ R_k` (the CSV's `sum_R`).
    pub regularizer: f64,
    /// `(K/δ) Σ D_k` (the CSV's `sum_D`).
    pub data: f64,
    /// Accepted `L_φ,k`, `k = 1..K` (empty for sweep 0).
    pub lipschitz_phi: Vec<f64>,
    /// Accepted `L_f,k` of every block, `k = 1..K−1`.
    pub lipschitz_f: Vec<f64>,
    /// Seconds since the start.
    pub seconds: f64,
    /// Deformation steps of the sweep whose inertia the safeguard restarted (SPEC §6).
    pub restarts: usize,
    /// Deformation steps of the sweep that were dropped (`φ_k` kept).
    pub drops_phi: usize,
    /// Feature blocks of the sweep whose backtracking gave up (values kept).
    pub drops_f: usize,
}

/// Collects an [`EnergyRecord`] per sweep.
#[derive(Clone, Debug, Default)]
pub struct EnergyLog {
    /// The records so far.
    pub records: Vec<EnergyRecord>,
}

impl EnergyLog {
    /// The log as CSV, with a header line. Lipschitz constants are `;`-separated lists.
    pub fn to_csv(&self) -> String {
        let mut out = String::from(
            "level,height,width,sweep,E,sum_R,sum_D,L_phi,L_f,seconds,restarts,drops_phi,drops_f\n",
        );
        let list = |v: &[f64]| {
            v.iter()
                .map(|x| format!("{x:.6e}"))
                .collect::<Vec<_>>()
                .join(";")
        };
        for r in &self.records {
            let _ = writeln!(
                out,
                "{},{},{},{},{:.9e},{:.9e},{:.9e},{},{},{:.3},{},{},{}",
                r.level,
                r.height,
                r.width,
                r.sweep,
                r.energy,
                r.regularizer,
                r.data,
                list(&r.lipschitz_phi),
                list(&r.lipschitz_f),
                r.seconds,
                r.restarts,
                r.drops_phi,
                r.drops_f
            );
        }
        out
    }

    /// Parses what [`to_csv`](Self::to_csv) wrote (also the 10-column files of earlier
    /// versions, without the restart and drop counts).
    ///
    /// # Errors
    ///
    /// A message naming the first line that does not parse.
    pub fn from_csv(text: &str) -> std::result::Result<Self, String> {
        let mut lines = text.lines();
        let header = lines.next().unwrap_or_default();
        if !header.starts_with("level,height,width,sweep,E,sum_R,sum_D") {
            return Err(format!("unexpected header `{header}`"));
        }
        let list = |s: &str| -> std::result::Result<Vec<f64>, std::num::ParseFloatError> {
            s.split(';')
                .filter(|v| !v.is_empty())
                .map(str::parse)
                .collect()
        };
        let records = lines
            .enumerate()
            .map(|(i, line)| {
                let bad = || format!("line {}: cannot parse `{line}`", i + 2);
                let cols: Vec<&str> = line.split(',').collect();
                if cols.len() != 10 && cols.len() != 13 {
                    return Err(bad());
                }
                let int = |c: &str| c.parse::<usize>().map_err(|_| bad());
                let num = |c: &str| c.parse::<f64>().map_err(|_| bad());
                Ok(EnergyRecord {
                    level: int(cols[0])?,
                    height: int(cols[1])?,
                    width: int(cols[2])?,
                    sweep: int(cols[3])?,
                    energy: num(cols[4])?,
                    regularizer: num(cols[5])?,
                    data: num(cols[6])?,
                    lipschitz_phi: list(cols[7]).map_err(|_| bad())?,
                    lipschitz_f: list(cols[8]).map_err(|_| bad())?,
                    seconds: num(cols[9])?,
                    restarts: cols.get(10).map_or(Ok(0), |c| int(c))?,
                    drops_phi: cols.get(11).map_or(Ok(0), |c| int(c))?,
                    drops_f: cols.get(12).map_or(Ok(0), |c| int(c))?,
                })
            })
            .collect::<std::result::Result<_, _>>()?;
        Ok(Self { records })
    }
}

impl Observer for EnergyLog {
    fn sweep(&mut self, e: &SweepEvent<'_>) {
        // One row per joint sweep; the energy after the deep model's feature-only sweeps is
        // the level's sweep-0 row.
        if e.phase == Phase::Features {
            return;
        }
        let (lipschitz_phi, lipschitz_f) = match e.report {
            Some(r) => (
                r.deformation.iter().map(|s| s.lipschitz).collect(),
                r.features
                    .iter()
                    .flat_map(|s| s.lipschitz.clone())
                    .collect(),
            ),
            None => (Vec::new(), Vec::new()),
        };
        self.records.push(EnergyRecord {
            level: e.level,
            height: e.grid.height(),
            width: e.grid.width(),
            sweep: e.sweep,
            energy: e.energy,
            regularizer: e.regularizer,
            data: e.data,
            lipschitz_phi,
            lipschitz_f,
            seconds: e.seconds,
            restarts: e.report.map_or(0, |r| r.restarts()),
            drops_phi: e.report.map_or(0, |r| r.deformation_drops()),
            drops_f: e.report.map_or(0, |r| r.feature_drops()),
        });
    }
}

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

/// The command line's progress report: a bar per level (sweep, energy, speed) or a line per
/// sweep.
pub struct Progress {
    verbosity: Verbosity,
    bar: Option<ProgressBar>,
}

impl Progress {
    /// A reporter at `verbosity`; the bar is hidden when stderr is not a terminal.
    pub fn new(verbosity: Verbosity) -> Self {
        Self {
            verbosity,
            bar: None,
        }
    }

    fn new_bar(&self, e: &SweepEvent<'_>) -> ProgressBar {
        let bar = ProgressBar::new(e.sweeps as u64);
        if self.verbosity != Verbosity::Normal || !std::io::stderr().is_terminal() {
            bar.set_draw_target(ProgressDrawTarget::hidden());
        }
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix} [{bar:30}] {pos}/{len} sweeps  {msg}  {per_sec} eta {eta}",
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
            bar.set_message(format!("E {:.5e}", e.energy));
            if e.sweep == e.sweeps && e.level + 1 == e.levels && e.phase == Phase::Joint {
                bar.finish();
            }
        }
        if self.verbosity == Verbosity::Verbose {
            let (trials, restarts, drops_phi, drops_f) = e.report.map_or((0, 0, 0, 0), |r| {
                (
                    r.deformation.iter().map(|s| s.trials).sum::<usize>(),
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
            if e.phase == Phase::Joint
                && e.sweep == e.sweeps
                && let Some(peak) = crate::memory::peak_resident_bytes()
            {
                eprintln!(
                    "level {} done after {:.1} s; peak memory so far {:.0} MiB",
                    e.level,
                    e.seconds,
                    peak as f64 / (1u64 << 20) as f64
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
