//! The discrete path energy `E` (SPEC §5) on one grid.

use burn::tensor::Tensor;

use crate::error::{Error, Result};
use crate::model::energy::anisotropy::Anisotropy;
use crate::model::energy::data::data_term;
use crate::model::energy::regularizer::regularizer;
use crate::model::grid::Grid;
use crate::model::params::EnergyParams;
use crate::model::warp::BSpline;

/// Largest number of feature values one batched warp may touch before the path energy is
/// evaluated in chunks of frames. A row-gather warp ([`crate::model::warp::Gather`]) holds 16 values
/// per feature value while it runs, so this bounds that buffer to about 256 MiB: with the deep
/// model's 67 channels, 3 frames at a time at 128² and one at 256² and above (with 2²⁴, a
/// whole K = 8 path at 128² went through at once and doubled the morph's peak memory).
const CHUNK_ELEMENTS: usize = 1 << 22;

/// The path energy of one level: parameters, the grid's operators, and the channel count
/// `C_tot` of the feature vectors (3 for the RGB model, `3 + C` for the deep one).
#[derive(Clone, Debug)]
pub struct PathEnergy {
    params: EnergyParams,
    channels: usize,
    bspline: BSpline,
    anisotropy: Anisotropy,
}

/// The value of `E` and its parts.
#[derive(Clone, Debug)]
pub struct EnergyValue {
    /// `E = K Σ_k (R_k + D_k / δ)`, `[1]`.
    pub total: Tensor<1>,
    /// `R_k = R[φ_k, a_k]`, `[K]`.
    pub regularizer: Tensor<1>,
    /// `D_k = D[f_{k−1}, f_k, φ_k]`, `[K]`.
    pub data: Tensor<1>,
}

/// `E` by steps on the host, in float64: `R_k` and `D_k` summed for decisions (SPEC §6), what
/// a level's driver logs and tests for convergence.
#[derive(Clone, Debug, PartialEq)]
pub struct StepEnergies {
    /// `R_k = R[φ_k, a_k]`, `k = 1..K`.
    pub regularizer: Vec<f64>,
    /// `D_k = D[f_{k−1}, f_k, φ_k]`, `k = 1..K`.
    pub data: Vec<f64>,
    /// `δ`.
    pub delta: f64,
    /// SPEC §11's landmark term `E_lm` of the whole path (its factor `K` included); 0 without
    /// landmarks.
    pub landmarks: f64,
}

impl StepEnergies {
    /// `K`.
    pub fn steps(&self) -> usize {
        self.regularizer.len()
    }

    /// `E = K Σ_k (R_k + D_k / δ)`, plus `E_lm` with landmarks (SPEC §11).
    pub fn total(&self) -> f64 {
        self.regularizer_part() + self.data_part() + self.landmarks
    }

    /// `K Σ_k R_k`.
    pub fn regularizer_part(&self) -> f64 {
        self.steps() as f64 * self.regularizer.iter().sum::<f64>()
    }

    /// `(K/δ) Σ_k D_k`.
    pub fn data_part(&self) -> f64 {
        self.steps() as f64 / self.delta * self.data.iter().sum::<f64>()
    }

    /// The first step `k` (1-based) whose `K·R_k` or `(K/δ)·D_k` is not finite, with both.
    pub fn first_nonfinite(&self) -> Option<(usize, f64, f64)> {
        let k = self.steps() as f64;
        (0..self.steps())
            .map(|i| {
                (
                    i + 1,
                    k * self.regularizer[i],
                    k / self.delta * self.data[i],
                )
            })
            .find(|(_, r, d)| !(r.is_finite() && d.is_finite()))
    }
}

impl PathEnergy {
    /// The path energy on `grid` for features with `channels` channels.
    ///
    /// # Errors
    ///
    /// If a parameter is out of range or `channels` is 0.
    pub fn new(grid: &Grid, params: EnergyParams, channels: usize) -> Result<Self> {
        params.validate()?;
        if channels == 0 {
            return Err(Error::invalid("channels", "0", "at least 1"));
        }
        Ok(Self {
            params,
            channels,
            bspline: BSpline::new(grid),
            anisotropy: Anisotropy::new(grid, params.sigma, params.rho, params.xi1, params.xi2)?,
        })
    }

    /// The parameters.
    pub fn params(&self) -> &EnergyParams {
        &self.params
    }

    /// `C_tot`.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// The grid's B-spline interpolator.
    pub fn bspline(&self) -> &BSpline {
        &self.bspline
    }

    /// The grid's anisotropy operator.
    pub fn anisotropy(&self) -> &Anisotropy {
        &self.anisotropy
    }

    /// `E[f_0..f_K, φ_1..φ_K, a_1..a_K]` and its parts (SPEC §5).
    ///
    /// # Shapes
    /// - `f`: `[K+1, C, H, W]`, `phi`: `[K, 2, H, W]`, `a`: `[K, H, W]`
    pub fn value(&self, f: Tensor<4>, phi: Tensor<4>, a: Tensor<3>) -> EnergyValue {
        let [k, _, _, _] = phi.dims();
        let regularizer = regularizer(phi.clone(), a, self.params.lambda, self.params.mu);
        let data = self.data_terms(f, phi);
        let per_step = regularizer.clone() + data.clone().mul_scalar(1.0 / self.params.delta);
        EnergyValue {
            total: per_step.sum().mul_scalar(k as f64),
            regularizer,
            data,
        }
    }

    /// `‖T[f_k, φ_k] − f_{k−1}‖²` summed for decisions (SPEC §6) for the steps `k = i + 1`,
    /// `i ∈ which` (ascending), in that order; runs of consecutive steps are batched in chunks
    /// of at most `CHUNK_ELEMENTS` values.
    ///
    /// # Shapes
    /// - `f`: `K + 1` tensors `[1, C, H, W]`, `phi`: `K` tensors `[1, 2, H, W]`
    /// - output: `which.len()` tensors `[1]`
    pub fn residual_norms(
        &self,
        grid: &Grid,
        f: &[Tensor<4>],
        phi: &[Tensor<4>],
        which: &[usize],
    ) -> Vec<Tensor<1>> {
        let [_, c, h, w] = f[0].dims();
        let chunk = (CHUNK_ELEMENTS / (c * h * w)).max(1);
        let mut runs: Vec<Vec<usize>> = Vec::new();
        for &i in which {
            match runs.last_mut() {
                Some(run) if run.len() < chunk && run.last().map(|l| l + 1) == Some(i) => {
                    run.push(i)
                }
                _ => runs.push(vec![i]),
            }
        }
        let stack = |parts: &[Tensor<4>], run: &[usize], offset: usize| -> Tensor<4> {
            match run {
                [i] => parts[i + offset].clone(),
                _ => Tensor::cat(
                    parts[run[0] + offset..=run[run.len() - 1] + offset].to_vec(),
                    0,
                ),
            }
        };
        runs.iter()
            .flat_map(|run| {
                let warped = self.bspline.interpolate(
                    self.bspline.coefficients(stack(f, run, 1)),
                    stack(phi, run, 0),
                );
                let residual = warped - stack(f, run, 0);
                // Item by item: the decision norm squares in float64 as the steps' do.
                (0..run.len())
                    .map(|i| grid.decision_norm2(residual.clone().narrow(0, i, 1)))
                    .collect::<Vec<_>>()
            })
            .collect()
    }

    /// `D_k` for `k = 1..K`, batched over frames in chunks of at most [`CHUNK_ELEMENTS`].
    fn data_terms(&self, f: Tensor<4>, phi: Tensor<4>) -> Tensor<1> {
        let [k, _, h, w] = phi.dims();
        let c = f.dims()[1];
        let chunk = (CHUNK_ELEMENTS / (c * h * w)).clamp(1, k);
        let parts: Vec<Tensor<1>> = (0..k)
            .step_by(chunk)
            .map(|start| {
                let len = chunk.min(k - start);
                data_term(
                    &self.bspline,
                    f.clone().narrow(0, start, len),
                    f.clone().narrow(0, start + 1, len),
                    phi.clone().narrow(0, start, len),
                    self.channels,
                )
            })
            .collect();
        Tensor::cat(parts, 0)
    }
}
