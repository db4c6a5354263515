//! Quality numbers of a finished morph: the composed deformation, Jacobian statistics, the
//! split of the path energy, warp consistency and (with a ground truth) endpoint error.
//!
//! Everything here reads a morph's results; nothing feeds back into the solver.

use burn::tensor::Tensor;
use serde::{Deserialize, Serialize};

use crate::error::Result;
use crate::io::energy_log::EnergyRecord;
use crate::io::images::to_byte;
use crate::io::truth::{Correspondence, EndpointError};
use crate::model::deformation::jacobian;
use crate::model::grid::Grid;
use crate::model::grid::host_values;
use crate::model::warp::BSpline;

/// The composed map `Φ = φ_N ∘ … ∘ φ_1`, i.e. `Φ(x) = φ_N(…φ_1(x))`: with
/// `u_{k−1} ≈ u_k ∘ φ_k` (SPEC §5), `u_0 ≈ u_N ∘ Φ`.
///
/// Each `φ_k` is evaluated off the grid by cubic B-spline interpolation of its displacement
/// `φ_k − Id` (SPEC §1, the warp's interpolation with its mirror boundary and clamping):
/// the displacement vanishes on the boundary, so its mirror extension is smooth, which the
/// identity part's would not be.
///
/// # Shapes
/// - `phi`: `[N, 2, H, W]`, pixel units
/// - output: `[1, 2, H, W]`
pub fn compose(grid: &Grid, phi: Tensor<4>) -> Tensor<4> {
    let n = phi.dims()[0];
    let bspline = BSpline::new(grid);
    let displacement = phi.clone() - grid.identity(n);
    (1..n).fold(phi.narrow(0, 0, 1), |composed, k| {
        let v = displacement.clone().narrow(0, k, 1);
        composed.clone() + bspline.warp(v, composed)
    })
}

/// Statistics of `det J` (SPEC §2's forward-difference Jacobian) of one deformation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JacobianStats {
    /// Smallest `det J`.
    pub min_det: f64,
    /// Largest `det J`.
    pub max_det: f64,
    /// Share of pixels with `det J ≤ 0` (a fold; 0 for every admissible deformation).
    pub folded_share: f64,
    /// Standard deviation of `log det J` over the unfolded pixels: how unevenly the map
    /// compresses and expands area (0 for a rigid motion).
    pub log_det_std: f64,
}

impl JacobianStats {
    /// The statistics of one map of `det J` values.
    pub fn of(det: &[f64]) -> Self {
        let min_det = det.iter().copied().fold(f64::INFINITY, f64::min);
        let max_det = det.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let logs: Vec<f64> = det.iter().filter(|&&d| d > 0.0).map(|d| d.ln()).collect();
        let folded_share = 1.0 - logs.len() as f64 / det.len() as f64;
        let log_det_std = if logs.is_empty() {
            f64::NAN
        } else {
            let mean = logs.iter().sum::<f64>() / logs.len() as f64;
            (logs.iter().map(|l| (l - mean).powi(2)).sum::<f64>() / logs.len() as f64).sqrt()
        };
        Self {
            min_det,
            max_det,
            folded_share,
            log_det_std,
        }
    }

    /// The statistics of each deformation of a batch `[N, 2, H, W]`.
    ///
    /// # Errors
    ///
    /// If a value is NaN.
    pub fn each(phi: Tensor<4>) -> Result<Vec<Self>> {
        let [_, _, h, w] = phi.dims();
        let det = host_values(jacobian(phi).det())?;
        Ok(det.chunks_exact(h * w).map(Self::of).collect())
    }
}

/// Size of a displacement field.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct DisplacementStats {
    /// Mean length of `Φ − Id`, pixels.
    pub mean: f64,
    /// Largest length of `Φ − Id`, pixels.
    pub max: f64,
}

impl DisplacementStats {
    /// The statistics of a displacement given row-major as `[2, H, W]`.
    pub fn of(displacement: &[f64]) -> Self {
        let n = displacement.len() / 2;
        let lengths = (0..n).map(|p| displacement[p].hypot(displacement[n + p]));
        let (sum, max) = lengths.fold((0.0, 0.0f64), |(s, m), l| (s + l, m.max(l)));
        Self {
            mean: sum / n as f64,
            max,
        }
    }
}

/// The path energy of one level at its last sweep, split into its parts (SPEC §5):
/// `E = K Σ_k R_k + K Σ_k D_k / δ`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LevelEnergy {
    /// Level, 0 = coarsest.
    pub level: usize,
    /// Grid `[H, W]`.
    pub size: [usize; 2],
    /// Sweeps run on the level.
    pub sweeps: usize,
    /// `E`.
    pub energy: f64,
    /// The regulariser's part `K Σ_k R_k` (transport cost).
    pub regularizer: f64,
    /// The data part `K Σ_k D_k / δ` (intensity change along the path).
    pub data: f64,
    /// `data / E`: how much of the morph is cross-fading rather than transport.
    pub data_share: f64,
    /// SPEC §11's landmark term `E_lm` (0 without landmarks).
    #[serde(default)]
    pub landmarks: f64,
    /// `E_lm / E`.
    #[serde(default)]
    pub landmark_share: f64,
}

/// The last record of every level of an energy log (whose parts already carry the factors
/// `K` and `1/δ`), split as in [`LevelEnergy`].
pub fn level_energies(records: &[EnergyRecord]) -> Vec<LevelEnergy> {
    let mut out: Vec<LevelEnergy> = Vec::new();
    for r in records {
        let entry = LevelEnergy {
            level: r.level,
            size: [r.height, r.width],
            sweeps: r.sweep,
            energy: r.energy,
            regularizer: r.regularizer,
            data: r.data,
            data_share: if r.energy > 0.0 {
                r.data / r.energy
            } else {
                0.0
            },
            landmarks: r.landmarks,
            landmark_share: if r.energy > 0.0 {
                r.landmarks / r.energy
            } else {
                0.0
            },
        };
        match out.last_mut() {
            Some(last) if last.level == r.level => *last = entry,
            _ => out.push(entry),
        }
    }
    out
}

/// How well the last frame, pulled back by the composed map, reproduces the first.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WarpConsistency {
    /// `mean |u_K ∘ Φ − u_0|` over pixels and channels (values in `[0, 1]`).
    pub mean_abs_error: f64,
    /// PSNR of `u_K ∘ Φ` against `u_0` in dB (peak value 1).
    pub psnr_db: f64,
}

impl WarpConsistency {
    /// Compares `T[u_last, Φ]` with `u_first`.
    ///
    /// # Shapes
    /// - `u_first`, `u_last`: `[1, C, H, W]`; `composed`: `[1, 2, H, W]`
    ///
    /// # Errors
    ///
    /// If a value is NaN.
    pub fn of(
        grid: &Grid,
        u_first: Tensor<4>,
        u_last: Tensor<4>,
        composed: Tensor<4>,
    ) -> Result<Self> {
        let pulled_back = BSpline::new(grid).warp(u_last, composed);
        let diff = host_values(pulled_back - u_first)?;
        let n = diff.len() as f64;
        let mean_abs_error = diff.iter().map(|d| d.abs()).sum::<f64>() / n;
        let mse = diff.iter().map(|d| d * d).sum::<f64>() / n;
        Ok(Self {
            mean_abs_error,
            psnr_db: -10.0 * mse.log10(),
        })
    }
}

/// How far and how evenly a sequence of frames moves: the distance between adjacent frames,
/// its sum (the path's length) and its spread.
///
/// Distances are RMS differences over pixels and channels, `‖u_k − u_{k−1}‖₂ / √(3·H·W)`,
/// in the frames' `[0, 1]` colour units: a perceptual-path-length-like number in pixel
/// space. (The PPL/PDV of the morphing literature use LPIPS, a learned distance whose network
/// we do not download.)
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PathStats {
    /// The distance of each step, `k = 1..K`.
    pub adjacent: Vec<f64>,
    /// `Σ_k` of the distances.
    pub length: f64,
    /// Population variance of the distances (0 for a path at constant speed).
    pub variance: f64,
    /// Standard deviation over mean of the distances: the variance without the scale
    /// (0 when every step moves as far; 0 for a path that does not move).
    pub relative_std: f64,
}

impl PathStats {
    /// The statistics of `frames` (each `3·H·W` values, all the same length).
    ///
    /// # Panics
    ///
    /// If there are fewer than 2 frames or their lengths differ.
    pub fn of(frames: &[&[f32]]) -> Self {
        assert!(frames.len() >= 2, "a path needs 2 frames or more");
        Self::from_adjacent(
            frames
                .windows(2)
                .map(|pair| {
                    assert_eq!(pair[0].len(), pair[1].len(), "frames of different sizes");
                    let sum: f64 = pair[0]
                        .iter()
                        .zip(pair[1])
                        .map(|(&a, &b)| (f64::from(b) - f64::from(a)).powi(2))
                        .sum();
                    (sum / pair[0].len() as f64).sqrt()
                })
                .collect(),
        )
    }

    /// The statistics of the distances `adjacent` of a path's steps (at least one).
    ///
    /// # Panics
    ///
    /// If `adjacent` is empty.
    pub fn from_adjacent(adjacent: Vec<f64>) -> Self {
        assert!(!adjacent.is_empty(), "a path needs 1 step or more");
        let n = adjacent.len() as f64;
        let length: f64 = adjacent.iter().sum();
        let mean = length / n;
        let variance = adjacent.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / n;
        let relative_std = if mean > 0.0 {
            variance.sqrt() / mean
        } else {
            0.0
        };
        Self {
            adjacent,
            length,
            variance,
            relative_std,
        }
    }
}

/// The morph's path in pixel space ([`PathStats`]) beside the plain cross-fade
/// `(1 − k/K) u_0 + (k/K) u_K` of its endpoints in the same number of steps, rounded to 8 bits
/// as the written frames are.
///
/// In pixel space the cross-fade is the straight line, so its length is the least any path
/// between the two endpoints can have and its steps are even (up to 8-bit rounding): a morph
/// is longer by what its transport adds, and `relative_std` says how evenly it spends it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PathSmoothness {
    /// The morph's frames `u_0..u_K`.
    pub morph: PathStats,
    /// The cross-fade of `u_0` and `u_K`.
    pub crossfade: PathStats,
}

impl PathSmoothness {
    /// The statistics of `frames` and of the cross-fade of its ends.
    ///
    /// # Panics
    ///
    /// As [`PathStats::of`].
    pub fn of(frames: &[&[f32]]) -> Self {
        let (first, last) = (frames[0], frames[frames.len() - 1]);
        let steps = frames.len() - 1;
        let crossfade: Vec<Vec<f32>> = (0..=steps)
            .map(|k| {
                let t = k as f32 / steps as f32;
                first
                    .iter()
                    .zip(last)
                    .map(|(&a, &b)| f32::from(to_byte((1.0 - t) * a + t * b)) / 255.0)
                    .collect()
            })
            .collect();
        let crossfade: Vec<&[f32]> = crossfade.iter().map(Vec::as_slice).collect();
        Self {
            morph: PathStats::of(frames),
            crossfade: PathStats::of(&crossfade),
        }
    }
}

/// Every quality number of a morph (what `deepmorph eval` prints and `metrics.json` holds).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// Working size `[H, W]`.
    pub size: [usize; 2],
    /// `det J` statistics of each `φ_k`, `k = 1..K`.
    pub deformations: Vec<JacobianStats>,
    /// `det J` statistics of the composed map `Φ`.
    pub composed: JacobianStats,
    /// Size of `Φ − Id`.
    pub composed_displacement: DisplacementStats,
    /// The energy split at the end of each level.
    pub levels: Vec<LevelEnergy>,
    /// `u_K ∘ Φ` against `u_0`.
    pub warp_consistency: WarpConsistency,
    /// The frames' path against the cross-fade.
    pub path: PathSmoothness,
    /// The same in VGG19 feature space ([`crate::eval::perceptual`]): deep morphs, and
    /// `deepmorph eval --vgg19`.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub feature_path: Option<PathSmoothness>,
    /// Endpoint error of `Φ` against a ground truth, in working-size pixels.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub endpoint_error: Option<EndpointError>,
    /// The ground-truth file the endpoint error was measured against.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub truth: Option<String>,
    /// How far `Φ` carries each landmark of A from its partner in B (SPEC §11): morphs with
    /// `--points`.
    #[serde(skip_serializing_if = "Option::is_none", default)]
    pub landmarks: Option<LandmarkResiduals>,
}

/// `|Φ(p_i) − q_i|` over the landmark pairs, in working pixels (SPEC §11).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LandmarkResiduals {
    /// `N`.
    pub count: usize,
    /// Mean residual.
    pub mean: f64,
    /// Largest residual.
    pub max: f64,
    /// Each pair's residual, in the order given.
    pub each: Vec<f64>,
}

impl LandmarkResiduals {
    /// The residuals of the pairs `(p_i, q_i)` (`[row, col]` on the grid of `phi`) under the
    /// map `phi` (`[2, H, W]` row-major host values, pixel units), evaluated between nodes
    /// by bilinear interpolation as SPEC §11 evaluates `φ_k`.
    pub fn of(phi: &[f64], (h, w): (usize, usize), pairs: &[([f64; 2], [f64; 2])]) -> Self {
        let each: Vec<f64> = pairs
            .iter()
            .map(|(p, q)| {
                let r = p[0].clamp(0.0, (h - 1) as f64);
                let c = p[1].clamp(0.0, (w - 1) as f64);
                let (r0, c0) = (
                    (r.floor() as usize).min(h.saturating_sub(2)),
                    (c.floor() as usize).min(w.saturating_sub(2)),
                );
                let (fr, fc) = (r - r0 as f64, c - c0 as f64);
                let at = |axis: usize| {
                    let v = |i: usize, j: usize| phi[axis * h * w + i * w + j];
                    let (r1, c1) = ((r0 + 1).min(h - 1), (c0 + 1).min(w - 1));
                    (1.0 - fr) * ((1.0 - fc) * v(r0, c0) + fc * v(r0, c1))
                        + fr * ((1.0 - fc) * v(r1, c0) + fc * v(r1, c1))
                };
                (at(0) - q[0]).hypot(at(1) - q[1])
            })
            .collect();
        Self {
            count: each.len(),
            mean: each.iter().sum::<f64>() / each.len().max(1) as f64,
            max: each.iter().copied().fold(0.0, f64::max),
            each,
        }
    }
}

impl Metrics {
    /// Every quality number of the deformations `φ_1..φ_K` `[K, 2, H, W]`, their composition
    /// `composed` (`[1, 2, H, W]`, from [`compose`]) and the frames `(u_0, u_K)`
    /// (`[1, 3, H, W]` each), with the level energies of `records` and the path of `frames`
    /// (`u_0..u_K`, `3·H·W` values each, [`PathSmoothness`]); with `truth` (and its
    /// name), also the endpoint error of `Φ` against it, resampled to the working size
    /// ([`Correspondence::resampled`]).
    ///
    /// # Errors
    ///
    /// If a value is NaN.
    pub fn compute(
        grid: &Grid,
        deformations: Tensor<4>,
        composed: Tensor<4>,
        (u_first, u_last): (Tensor<4>, Tensor<4>),
        frames: &[&[f32]],
        records: &[EnergyRecord],
        truth: Option<(&Correspondence, &str)>,
    ) -> Result<Self> {
        let (h, w) = (grid.height(), grid.width());
        let phi = host_values(composed.clone())?;
        // Id at flat index p of [2, H, W]: the row p / W in the first half, the column p % W.
        let identity = |p: usize| if p < h * w { p / w } else { p % w } as f64;
        let displacement: Vec<f64> = phi
            .iter()
            .enumerate()
            .map(|(p, v)| v - identity(p))
            .collect();
        let endpoint_error = truth
            .map(|(truth, _)| truth.resampled(h, w).endpoint_error(&phi))
            .transpose()?;
        Ok(Self {
            size: [h, w],
            deformations: JacobianStats::each(deformations)?,
            composed: JacobianStats::each(composed.clone())?.remove(0),
            composed_displacement: DisplacementStats::of(&displacement),
            levels: level_energies(records),
            warp_consistency: WarpConsistency::of(grid, u_first, u_last, composed)?,
            path: PathSmoothness::of(frames),
            feature_path: None,
            endpoint_error,
            truth: truth.map(|(_, name)| name.to_string()),
            landmarks: None,
        })
    }
}

impl std::fmt::Display for Metrics {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let [h, w] = self.size;
        writeln!(f, "working size {w}x{h}, K = {}", self.deformations.len())?;
        let min = self
            .deformations
            .iter()
            .map(|s| s.min_det)
            .fold(f64::INFINITY, f64::min);
        let max = self
            .deformations
            .iter()
            .map(|s| s.max_det)
            .fold(f64::NEG_INFINITY, f64::max);
        let folded = self
            .deformations
            .iter()
            .map(|s| s.folded_share)
            .fold(0.0, f64::max);
        writeln!(
            f,
            "steps phi_k:    det J in [{min:.4}, {max:.4}], folded share {folded:.2e} (worst step)"
        )?;
        let c = &self.composed;
        writeln!(
            f,
            "composed Phi:   det J in [{:.4}, {:.4}], folded share {:.2e}, std log det J {:.4}",
            c.min_det, c.max_det, c.folded_share, c.log_det_std
        )?;
        writeln!(
            f,
            "                displacement mean {:.3} px, max {:.3} px",
            self.composed_displacement.mean, self.composed_displacement.max
        )?;
        for l in &self.levels {
            writeln!(
                f,
                "level {} ({}x{}, {} sweeps): E = {:.6e} = R {:.4e} + D {:.4e}, data share {:.1} %",
                l.level,
                l.size[1],
                l.size[0],
                l.sweeps,
                l.energy,
                l.regularizer,
                l.data,
                100.0 * l.data_share
            )?;
        }
        writeln!(
            f,
            "u_K o Phi vs u_0: mean |diff| {:.4}, PSNR {:.2} dB",
            self.warp_consistency.mean_abs_error, self.warp_consistency.psnr_db
        )?;
        let (m, c) = (&self.path.morph, &self.path.crossfade);
        writeln!(
            f,
            "path (RMS colour distance of adjacent frames): length {:.4}, variance {:.3e}, \
             relative std {:.3} (cross-fade: length {:.4}, relative std {:.3})",
            m.length, m.variance, m.relative_std, c.length, c.relative_std
        )?;
        if let Some(p) = &self.feature_path {
            let (m, c) = (&p.morph, &p.crossfade);
            writeln!(
                f,
                "path in VGG19 feature space: length {:.4}, variance {:.3e}, relative std \
                 {:.3} (cross-fade: length {:.4}, relative std {:.3})",
                m.length, m.variance, m.relative_std, c.length, c.relative_std
            )?;
        }
        if let Some(l) = &self.landmarks {
            writeln!(
                f,
                "landmarks |Phi(p) - q|: mean {:.3} px, max {:.3} px over {} pairs",
                l.mean, l.max, l.count
            )?;
        }
        if let Some(e) = &self.endpoint_error {
            writeln!(
                f,
                "endpoint error vs {} ({} px known): mean {:.3} px, median {:.3} px, < 1 px {:.1} %, < 3 px {:.1} % (identity: mean {:.3} px)",
                self.truth.as_deref().unwrap_or("truth"),
                e.pixels,
                e.mean,
                e.median,
                100.0 * e.under_1px,
                100.0 * e.under_3px,
                e.identity_mean
            )?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jacobian_stats_of_a_map() {
        let s = JacobianStats::of(&[1.0, std::f64::consts::E, -0.5, 1.0]);
        assert_eq!(
            (s.min_det, s.max_det, s.folded_share),
            (-0.5, std::f64::consts::E, 0.25)
        );
        // log det = 0, 1, 0 → std = sqrt(2/9).
        assert!((s.log_det_std - (2.0f64 / 9.0).sqrt()).abs() < 1e-15);
    }

    /// A blob moving at constant speed has even steps; the cross-fade of its ends is the
    /// shortest path (its length is the endpoint distance) with even steps too.
    #[test]
    fn path_statistics_of_a_moving_blob_and_its_crossfade() {
        let (h, w, steps) = (8, 16, 4);
        let frame = |k: usize| -> Vec<f32> {
            (0..3 * h * w)
                .map(|i| {
                    let col = i % w;
                    if (2 * k..2 * k + 4).contains(&col) {
                        1.0
                    } else {
                        0.0
                    }
                })
                .collect()
        };
        let frames: Vec<Vec<f32>> = (0..=steps).map(frame).collect();
        let views: Vec<&[f32]> = frames.iter().map(Vec::as_slice).collect();
        let p = PathSmoothness::of(&views);
        // Each step changes 2 + 2 columns of 16: RMS = sqrt(4/16) = 0.5.
        assert_eq!(p.morph.adjacent, vec![0.5; steps]);
        assert_eq!(
            (p.morph.length, p.morph.variance, p.morph.relative_std),
            (2.0, 0.0, 0.0)
        );
        // The ends differ in 8 of 16 columns by 1: distance sqrt(1/2); each cross-fade step
        // a quarter of it (up to the 8-bit rounding of 0.25 and 0.75).
        let end = 0.5f64.sqrt();
        assert!(
            (p.crossfade.length - end).abs() < 2e-3 * end,
            "{}",
            p.crossfade.length
        );
        assert!(
            p.crossfade.relative_std < 1e-2,
            "{}",
            p.crossfade.relative_std
        );
        assert!(p.morph.length > p.crossfade.length);
        // A path that stands still.
        let still = PathStats::of(&[views[0], views[0]]);
        assert_eq!((still.length, still.relative_std), (0.0, 0.0));
    }

    #[test]
    fn level_energies_take_each_levels_last_sweep() {
        let record = |level, sweep, energy, regularizer, data| EnergyRecord {
            level,
            height: 4 << level,
            width: 4 << level,
            sweep,
            energy,
            regularizer,
            data,
            lipschitz_phi: Vec::new(),
            lipschitz_f: Vec::new(),
            streak_phi: Vec::new(),
            seconds: 0.0,
            restarts: 0,
            drops_phi: 0,
            drops_f: 0,
            stop: None,
            landmarks: 0.0,
            trials_phi: 0,
            trials_f: 0,
        };
        let records = [
            record(0, 0, 9.0, 4.0, 5.0),
            record(0, 1, 6.0, 4.0, 2.0),
            record(1, 0, 8.0, 6.0, 2.0),
        ];
        let levels = level_energies(&records);
        assert_eq!(levels.len(), 2);
        assert_eq!(
            (levels[0].sweeps, levels[0].regularizer, levels[0].data),
            (1, 4.0, 2.0)
        );
        assert!((levels[0].data_share - 2.0 / 6.0).abs() < 1e-15);
        assert_eq!(
            (levels[1].level, levels[1].size, levels[1].data_share),
            (1, [8, 8], 0.25)
        );
    }
}
