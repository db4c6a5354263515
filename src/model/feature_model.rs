//! The feature vectors of each pyramid level (SPEC §4): the RGB model's `f = u`, or the deep
//! model's `f = (η·u, τ·F/rms)` with `F` the deep feature map whose size is the level's grid.
//!
//! This is what the solver needs of the features: per level the channel layout, the two
//! endpoints' maps and how to stack a frame. Computing the maps from a network is
//! the business of the `features` module, a layer above this one.

use burn::tensor::Tensor;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::model::layout::FeatureLayout;
use crate::model::params::positive;

/// Settings of the deep model (SPEC §4, §7, §9).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeepConfig {
    /// `η`, the weight of the RGB channels inside the feature vector. Default 1e-6.
    pub eta: f64,
    /// `τ`, the RMS every level's deep feature map is scaled to (`--feature-rms`, SPEC §4).
    /// Default 0.1, calibrated on the motorcycle stereo pair (docs/quality.md, "The deep model and its
    /// feature scale").
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
        positive("eta", self.eta)?;
        positive("feature-rms", self.feature_rms)?;
        if self.pre_sweeps > 1_000_000 {
            return Err(Error::invalid(
                "pre-sweeps",
                self.pre_sweeps,
                "at most 1000000",
            ));
        }
        Ok(())
    }
}

/// The deep model's feature maps of both inputs, one per pyramid level, each scaled to RMS
/// `τ` (SPEC §4: one constant per level, from both images' maps together).
#[derive(Clone, Debug)]
pub struct DeepFeatures {
    config: DeepConfig,
    /// Per downsampling `s`: `(F_A, F_B)`, each `[1, C_s, H/2^s, W/2^s]`, scaled.
    maps: Vec<(Tensor<4>, Tensor<4>)>,
    /// Per downsampling: the RMS before scaling.
    rms: Vec<f64>,
}

impl DeepFeatures {
    /// Feature maps `maps[s] = (F_A, F_B)` at `1/2^s` of the input size, already scaled, with
    /// the RMS each had before scaling.
    ///
    /// # Errors
    ///
    /// Invalid settings, or maps and RMS values that do not pair up.
    pub fn new(
        config: DeepConfig,
        maps: Vec<(Tensor<4>, Tensor<4>)>,
        rms: Vec<f64>,
    ) -> Result<Self> {
        config.validate()?;
        if maps.is_empty() || maps.len() != rms.len() {
            return Err(Error::Shape {
                op: "DeepFeatures::new",
                detail: format!("{} feature maps and {} RMS values", maps.len(), rms.len()),
            });
        }
        Ok(Self { config, maps, rms })
    }

    /// The settings.
    pub fn config(&self) -> &DeepConfig {
        &self.config
    }

    /// RMS of each level's map before scaling, finest first.
    pub fn rms(&self) -> &[f64] {
        &self.rms
    }

    /// How many pyramid levels the maps can serve.
    pub fn levels(&self) -> usize {
        self.maps.len()
    }

    fn level(&self, downsampling: usize) -> Result<&(Tensor<4>, Tensor<4>)> {
        self.maps.get(downsampling).ok_or_else(|| {
            Error::invalid(
                "levels",
                downsampling + 1,
                format!(
                    "at most {} for the deep model: one level per feature map (VGG19 has taps \
                     at 1, 1/2, 1/4, 1/8 and 1/16 of the input size)",
                    self.maps.len()
                ),
            )
        })
    }

    /// The layout of the level whose grid is `1/2^downsampling` of the input.
    ///
    /// # Errors
    ///
    /// If there is no feature map of that size.
    pub fn layout(&self, downsampling: usize) -> Result<FeatureLayout> {
        let channels = self.level(downsampling)?.0.dims()[1];
        FeatureLayout::deep(self.config.eta, channels)
    }

    /// `(F_A, F_B)` of the level whose grid is `1/2^downsampling` of the input, scaled.
    ///
    /// # Errors
    ///
    /// If there is no feature map of that size.
    pub fn maps(&self, downsampling: usize) -> Result<(Tensor<4>, Tensor<4>)> {
        self.level(downsampling).cloned()
    }

    /// `f = (η·u, F)` (SPEC §4).
    ///
    /// # Shapes
    /// - `u`: `[N, 3, h, w]`; `features`: `[N, C, h, w]`; output `[N, 3 + C, h, w]`
    pub fn stack(&self, u: Tensor<4>, features: Tensor<4>) -> Tensor<4> {
        Tensor::cat(vec![u.mul_scalar(self.config.eta), features], 1)
    }
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
