//! The deep model's feature vectors (SPEC §4, §7): `f = (η·u, τ·F/rms)` on each pyramid
//! level, with `F` the VGG19 tap whose size is the level's grid, computed once from the
//! full-resolution inputs.

use burn::tensor::Tensor;

use crate::error::{Error, Result};
use crate::io::to_host;
use crate::layout::FeatureLayout;
use crate::vgg::{TAP_CHANNELS, TAPS, Vgg19, tap_for};

/// Settings of the deep model (SPEC §4, §7, §9).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DeepConfig {
    /// `η`, the weight of the RGB channels inside the feature vector. Default 1e-6.
    pub eta: f64,
    /// `τ`, the RMS every level's VGG tap is scaled to (`--feature-rms`, SPEC §4). Default 0.1,
    /// calibrated on the motorcycle stereo pair (README, "The deep model and its feature scale").
    pub feature_rms: f64,
    /// `J_pre`, feature-only sweeps after each prolongation (SPEC §7). Default 50.
    pub pre_sweeps: usize,
}

impl Default for DeepConfig {
    fn default() -> Self {
        Self {
            eta: 1e-6,
            feature_rms: 0.1,
            pre_sweeps: 50,
        }
    }
}

impl DeepConfig {
    /// Checks the ranges.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] naming the bad value.
    pub fn validate(&self) -> Result<()> {
        crate::params::positive("eta", self.eta)?;
        crate::params::positive("feature-rms", self.feature_rms)
    }
}

/// The VGG taps of both inputs, each scaled to RMS `τ` (SPEC §4: one constant per level,
/// from both images' maps together).
#[derive(Clone, Debug)]
pub struct DeepFeatures {
    config: DeepConfig,
    /// Per tap `s`: `(F_A, F_B)`, each `[1, TAP_CHANNELS[s], H/2^s, W/2^s]`, scaled.
    taps: Vec<(Tensor<4>, Tensor<4>)>,
    /// Per tap: the RMS before scaling.
    rms: Vec<f64>,
}

impl DeepFeatures {
    /// Runs `vgg` on both inputs (one batch) and scales each tap.
    ///
    /// # Shapes
    /// - `u_a`, `u_b`: `[1, 3, H, W]`, RGB in `[0, 1]`, `H` and `W` multiples of 16
    ///
    /// # Errors
    ///
    /// Invalid settings, sizes not divisible by 16, or a tap that is zero everywhere (its
    /// scale would be undefined).
    pub fn new(vgg: &Vgg19, u_a: Tensor<4>, u_b: Tensor<4>, config: DeepConfig) -> Result<Self> {
        config.validate()?;
        let [_, _, h, w] = u_a.dims();
        if h % 16 != 0 || w % 16 != 0 || u_a.dims() != u_b.dims() {
            return Err(Error::Shape {
                op: "deep features",
                detail: format!(
                    "inputs {:?} and {:?}: the deep model needs one size with sides multiples of 16",
                    u_a.dims(),
                    u_b.dims()
                ),
            });
        }
        let both = vgg.taps(Tensor::cat(vec![u_a, u_b], 0));
        let mut taps = Vec::with_capacity(TAPS.len());
        let mut rms = Vec::with_capacity(TAPS.len());
        for (s, t) in both.into_iter().enumerate() {
            let r = to_host(t.clone().powi_scalar(2).mean().sqrt())[0];
            if !(r.is_finite() && r > 0.0) {
                return Err(Error::NonFinite {
                    what: format!(
                        "VGG tap {} of the inputs has RMS {r}: cannot scale it (all-zero or \
                         non-finite activations; wrong weights?)",
                        TAPS[s]
                    ),
                });
            }
            let t = t.mul_scalar(config.feature_rms / r);
            taps.push((t.clone().narrow(0, 0, 1), t.narrow(0, 1, 1)));
            rms.push(r);
        }
        Ok(Self { config, taps, rms })
    }

    /// The settings.
    pub fn config(&self) -> &DeepConfig {
        &self.config
    }

    /// RMS of each tap before scaling, `relu1_2` first.
    pub fn rms(&self) -> &[f64] {
        &self.rms
    }

    /// The layout of the level whose grid is `1/2^downsampling` of the input.
    ///
    /// # Errors
    ///
    /// If there is no VGG tap of that size.
    pub fn layout(&self, downsampling: usize) -> Result<FeatureLayout> {
        FeatureLayout::deep(self.config.eta, TAP_CHANNELS[tap_for(downsampling)?])
    }

    /// `(F_A, F_B)` of the level whose grid is `1/2^downsampling` of the input, scaled.
    ///
    /// # Errors
    ///
    /// If there is no VGG tap of that size.
    pub fn tap(&self, downsampling: usize) -> Result<(Tensor<4>, Tensor<4>)> {
        Ok(self.taps[tap_for(downsampling)?].clone())
    }

    /// `f = (η·u, F)` (SPEC §4).
    ///
    /// # Shapes
    /// - `u`: `[N, 3, h, w]`; `features`: `[N, C, h, w]`; output `[N, 3 + C, h, w]`
    pub fn stack(&self, u: Tensor<4>, features: Tensor<4>) -> Tensor<4> {
        Tensor::cat(vec![u.mul_scalar(self.config.eta), features], 1)
    }
}
