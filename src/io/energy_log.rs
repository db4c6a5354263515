//! The energy log of a morph: an observer that records every joint sweep, and its file
//! format, `energy.csv`.

use std::fmt::Write as _;

use std::path::Path;

use crate::error::{Error, Result};
use crate::read::read_bytes;
use crate::solver::ipalm::SweepReport;
use crate::solver::observer::{LevelStop, Observer, Phase, SweepEvent};

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
    /// The streak `m` each deformation search of the sweep started with, `k = 1..K` (SPEC
    /// §6: its first trial was `0.9^(m+1)·L_φ,k` of the previous sweep; the CSV's `m_phi`;
    /// empty for sweep 0 and in logs of earlier versions).
    pub streak_phi: Vec<u32>,
    /// Seconds since the start.
    pub seconds: f64,
    /// Deformation steps of the sweep whose inertia the safeguard restarted (SPEC §6).
    pub restarts: usize,
    /// Deformation steps of the sweep that were dropped (`φ_k` kept).
    pub drops_phi: usize,
    /// Feature blocks of the sweep whose backtracking gave up (values kept).
    pub drops_f: usize,
    /// On a level's last sweep: why the level stopped there.
    pub stop: Option<LevelStop>,
    /// SPEC §11's landmark term `E_lm` (the CSV's `E_lm`; 0 without landmarks and in logs
    /// of earlier versions).
    pub landmarks: f64,
    /// Backtracking trials of the sweep's deformation searches (the CSV's `trials_phi`; `K`
    /// where every search accepted its first; 0 for sweep 0 and in logs of earlier
    /// versions): what the accelerating shrink of SPEC §6 trades against smaller steps.
    pub trials_phi: usize,
    /// Backtracking trials of the sweep's feature searches, every block (`trials_f`).
    pub trials_f: usize,
}

/// Collects an [`EnergyRecord`] per sweep.
#[derive(Clone, Debug, Default)]
pub struct EnergyLog {
    /// The records so far.
    pub records: Vec<EnergyRecord>,
}

impl EnergyLog {
    /// Reads an `energy.csv` (at most 1 GiB).
    ///
    /// # Errors
    ///
    /// [`Error::Io`] or [`Error::Format`] naming the file.
    pub fn read(path: &Path) -> Result<Self> {
        let bytes = read_bytes(path, 1 << 30, "energy log")?;
        Self::from_csv(&String::from_utf8_lossy(&bytes)).map_err(|detail| Error::Format {
            path: path.to_path_buf(),
            detail,
        })
    }

    /// The log as CSV, with a header line. Lipschitz constants are `;`-separated lists.
    pub fn to_csv(&self) -> String {
        let mut out = String::from(
            "level,height,width,sweep,E,sum_R,sum_D,L_phi,L_f,seconds,restarts,drops_phi,drops_f,stop,m_phi,E_lm,trials_phi,trials_f\n",
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
                "{},{},{},{},{:.9e},{:.9e},{:.9e},{},{},{:.3},{},{},{},{},{},{:.9e},{},{}",
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
                r.drops_f,
                r.stop.map_or("", LevelStop::name),
                r.streak_phi
                    .iter()
                    .map(u32::to_string)
                    .collect::<Vec<_>>()
                    .join(";"),
                r.landmarks,
                r.trials_phi,
                r.trials_f
            );
        }
        out
    }

    /// Parses what [`to_csv`](Self::to_csv) wrote (also the 10-, 14-, 15- and 16-column files
    /// of earlier versions, without the restart and drop counts and the stop reasons, without
    /// the streaks, without `E_lm`, or without the trial counts).
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
                if ![10, 14, 15, 16, 18].contains(&cols.len()) {
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
                    stop: match cols.get(13).copied().unwrap_or("") {
                        "" => None,
                        "sweeps" => Some(LevelStop::Sweeps),
                        "converged" => Some(LevelStop::Converged),
                        "interrupted" => Some(LevelStop::Interrupted),
                        "non_finite" => Some(LevelStop::NonFinite),
                        _ => return Err(bad()),
                    },
                    streak_phi: cols
                        .get(14)
                        .map_or(Ok(Vec::new()), |c| {
                            c.split(';')
                                .filter(|v| !v.is_empty())
                                .map(str::parse)
                                .collect::<std::result::Result<_, _>>()
                        })
                        .map_err(|_| bad())?,
                    landmarks: cols.get(15).map_or(Ok(0.0), |c| num(c))?,
                    trials_phi: cols.get(16).map_or(Ok(0), |c| int(c))?,
                    trials_f: cols.get(17).map_or(Ok(0), |c| int(c))?,
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
        let (lipschitz_phi, lipschitz_f, streak_phi) = match e.report {
            Some(r) => (
                r.deformation.iter().map(|s| s.lipschitz).collect(),
                r.features
                    .iter()
                    .flat_map(|s| s.lipschitz.clone())
                    .collect(),
                r.deformation.iter().map(|s| s.streak).collect(),
            ),
            None => (Vec::new(), Vec::new(), Vec::new()),
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
            streak_phi,
            seconds: e.seconds,
            restarts: e.report.map_or(0, |r| r.restarts()),
            drops_phi: e.report.map_or(0, |r| r.deformation_drops()),
            drops_f: e.report.map_or(0, |r| r.feature_drops()),
            stop: e.stop,
            landmarks: e.landmarks,
            trials_phi: e.report.map_or(0, SweepReport::deformation_trials),
            trials_f: e.report.map_or(0, SweepReport::feature_trials),
        });
    }
}
