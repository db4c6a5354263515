//! How the channels of a feature vector are laid out (SPEC §4, §6).

use std::ops::Range;

use burn::tensor::Tensor;

use crate::error::{Error, Result};

/// A group of channels with its own Lipschitz estimate and backtracking in the feature step
/// (SPEC §6): the deep model's η-scaled RGB and VGG channels have gradients that differ in
/// size by `η`, so one shared step would be decided by the VGG block alone.
#[derive(Clone, Debug, PartialEq)]
pub struct ChannelBlock {
    /// The block's channels.
    pub channels: Range<usize>,
}

/// The channel layout of the feature vectors `f_k` of one model: `C_tot` channels, the
/// first three of which are the RGB image times `rgb_scale`, grouped into blocks.
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureLayout {
    channels: usize,
    rgb_scale: f64,
    blocks: Vec<ChannelBlock>,
}

impl FeatureLayout {
    /// The RGB model: `f = u`, one block.
    pub fn rgb() -> Self {
        Self {
            channels: 3,
            rgb_scale: 1.0,
            blocks: vec![ChannelBlock { channels: 0..3 }],
        }
    }

    /// The deep model: `f = (η u, F)` with `features` VGG channels, two blocks.
    ///
    /// # Errors
    ///
    /// If `η` is not a finite positive number or `features` is 0.
    pub fn deep(eta: f64, features: usize) -> Result<Self> {
        crate::model::params::positive("eta", eta)?;
        if features == 0 {
            return Err(Error::invalid("features", "0", "at least 1 channel"));
        }
        Ok(Self {
            channels: 3 + features,
            rgb_scale: eta,
            blocks: vec![
                ChannelBlock { channels: 0..3 },
                ChannelBlock {
                    channels: 3..3 + features,
                },
            ],
        })
    }

    /// `C_tot`.
    pub fn channels(&self) -> usize {
        self.channels
    }

    /// The blocks of the feature step.
    pub fn blocks(&self) -> &[ChannelBlock] {
        &self.blocks
    }

    /// The RGB image `u` in `[0, 1]` inside feature vectors (SPEC §5: `u_k` is the RGB part
    /// of `f_k`, unscaled).
    ///
    /// # Shapes
    /// - `f`: `[N, C_tot, H, W]`
    /// - output: `[N, 3, H, W]`
    pub fn rgb_part(&self, f: Tensor<4>) -> Tensor<4> {
        self.unscaled(f.narrow(1, 0, 3))
    }

    /// The RGB images of several frames, stacked: [`rgb_part`](Self::rgb_part) of their
    /// concatenation, but each frame is narrowed to its 3 channels before the copy (the deep
    /// model's frames have 67: stacking them whole to keep 3 copied and page-faulted 280 MB
    /// per energy evaluation at 256², K 15, the largest copy in a profile of the solver
    /// thread; the peak fell by ~150 MB, the sweep time within noise).
    ///
    /// # Shapes
    /// - `frames`: `[1, C_tot, H, W]` each
    /// - output: `[frames.len(), 3, H, W]`
    pub fn rgb_parts(&self, frames: &[Tensor<4>]) -> Tensor<4> {
        let rgb = frames.iter().map(|f| f.clone().narrow(1, 0, 3)).collect();
        self.unscaled(Tensor::cat(rgb, 0))
    }

    fn unscaled(&self, rgb: Tensor<4>) -> Tensor<4> {
        if self.rgb_scale == 1.0 {
            rgb
        } else {
            rgb.mul_scalar(1.0 / self.rgb_scale)
        }
    }
}
