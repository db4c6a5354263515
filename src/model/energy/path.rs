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
