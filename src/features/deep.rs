//! The deep model's feature maps (SPEC §4): both inputs through VGG19 once, at full
//! resolution, and each tap scaled to RMS `τ`, one constant per tap from both images' maps.

use burn::tensor::Tensor;

use crate::error::{Error, Result};
use crate::features::vgg::{TAPS, Vgg19};
use crate::model::feature_model::{DeepConfig, DeepFeatures};
use crate::model::grid::to_host;

/// Runs `vgg` on both inputs (one batch) and scales each tap to RMS `config.feature_rms`.
///
/// # Shapes
/// - `u_a`, `u_b`: `[1, 3, H, W]`, RGB in `[0, 1]`, `H` and `W` multiples of 16
///
/// # Errors
///
/// Invalid settings, sizes not divisible by 16, or a tap whose RMS is zero or not finite (its
/// scale would be undefined: wrong weights).
pub fn deep_features(
    vgg: &Vgg19,
    u_a: Tensor<4>,
    u_b: Tensor<4>,
    config: DeepConfig,
) -> Result<DeepFeatures> {
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
    let mut maps = Vec::with_capacity(TAPS.len());
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
        maps.push((t.clone().narrow(0, 0, 1), t.narrow(0, 1, 1)));
        rms.push(r);
    }
    DeepFeatures::new(config, maps, rms)
}
