//! VGG19 deep features (SPEC §4): the network imported from `onnx/` by burn-import at build
//! time ([`model`], generated, included untouched), its weights read at run time from the
//! user's file ([`weights`]), the ImageNet normalisation in front of it, and the table that
//! says which tap feeds which pyramid level.

pub mod architecture;
pub mod model;
mod proto;
pub mod weights;

use std::path::Path;

use burn::tensor::{Device, Tensor};
use burn_store::ModuleSnapshot;

use crate::error::{Error, Result};
pub use weights::Vgg19Weights;

/// The names of the five taps of SPEC §4, finest first: `TAPS[s]` has `1/2^s` of the
/// input's size.
pub const TAPS: [&str; 5] = [
    architecture::TAPS[0].0,
    architecture::TAPS[1].0,
    architecture::TAPS[2].0,
    architecture::TAPS[3].0,
    architecture::TAPS[4].0,
];

/// ImageNet mean and standard deviation per RGB channel (SPEC §4).
pub const IMAGENET_MEAN: [f64; 3] = [0.485, 0.456, 0.406];
/// See [`IMAGENET_MEAN`].
pub const IMAGENET_STD: [f64; 3] = [0.229, 0.224, 0.225];

/// VGG19's convolutional part with real weights, on one device.
#[derive(Debug)]
pub struct Vgg19 {
    model: model::Model,
    device: Device,
}

impl Vgg19 {
    /// Loads the weights in `path` (ONNX or safetensors, see [`Vgg19Weights::read`]) into the
    /// imported network on `device` (the network itself never records gradients).
    ///
    /// # Errors
    ///
    /// The file cannot be read or does not hold VGG19's convolutions.
    pub fn load(path: &Path, device: &Device) -> Result<Self> {
        Self::from_weights(Vgg19Weights::read(path)?, device)
    }

    /// The network with the given weights.
    ///
    /// # Errors
    ///
    /// If Burn refuses a tensor (cannot happen for weights that passed [`Vgg19Weights::read`]'s
    /// checks; reported instead of ignored).
    pub fn from_weights(weights: Vgg19Weights, device: &Device) -> Result<Self> {
        let device = device.clone().without_autodiff();
        let mut model = model::Model::new(&device);
        let mut tensors = Vec::with_capacity(32);
        for (i, conv) in weights.convs.into_iter().enumerate() {
            let (w, b) = conv.into_data();
            let name = format!("conv2d{}", i + 1);
            tensors.push(burn_store::bridge::from_data(
                w,
                format!("{name}.weight"),
                None,
            ));
            tensors.push(burn_store::bridge::from_data(
                b,
                format!("{name}.bias"),
                None,
            ));
        }
        let result = model.apply(tensors, None, None, false);
        if !result.missing.is_empty() || !result.errors.is_empty() || !result.unused.is_empty() {
            return Err(Error::Shape {
                op: "VGG19 weights",
                detail: format!(
                    "the imported network did not take the weights: missing {:?}, unused {:?}, errors {:?}",
                    result.missing, result.unused, result.errors
                ),
            });
        }
        Ok(Self { model, device })
    }

    /// The five taps of `u` (RGB in `[0, 1]`), after ImageNet normalisation, on `u`'s device.
    /// Sides should be multiples of 16 so that every max-pool halves exactly.
    ///
    /// # Shapes
    /// - `u`: `[N, 3, H, W]`
    /// - output `s`: `[N, architecture::tap_channels()[s], H/2^s, W/2^s]` (floor)
    pub fn taps(&self, u: Tensor<4>) -> [Tensor<4>; 5] {
        let target = u.device();
        let u = u.without_autodiff().to_device(&self.device);
        let mean = Tensor::<1>::from_floats(IMAGENET_MEAN.map(|v| v as f32), &self.device)
            .cast(u.dtype())
            .reshape([1, 3, 1, 1]);
        let inv_std =
            Tensor::<1>::from_floats(IMAGENET_STD.map(|v| (1.0 / v) as f32), &self.device)
                .cast(u.dtype())
                .reshape([1, 3, 1, 1]);
        let x = (u - mean) * inv_std;
        let (t1, t2, t3, t4, t5) = self.model.forward(x);
        [t1, t2, t3, t4, t5].map(|t| {
            let t = t.to_device(&target.clone().without_autodiff());
            if target.is_autodiff() {
                t.autodiff()
            } else {
                t
            }
        })
    }
}
