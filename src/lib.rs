//! # deepmorph
//!
//! Image morphing as a time-discrete geodesic path in the metamorphosis model, after
//! Effland, Kobler, Pock, Rajković and Rumpf, "Image Morphing in Deep Feature Spaces"
//! (Section 5). The exact discrete model is fixed by `docs/SPEC.md`; module docs cite its
//! sections.
//!
//! Everything numerical is written once on Burn's backend-erased tensors: the same code runs
//! on the flex or ndarray CPU backends and on wgpu, picked in [`backend`], in float32, or in
//! float64 for the finite-difference checks. Images and features are batches
//! `[N, C, H, W]`, deformations `[N, 2, H, W]` in pixel units (`[:, 0]` = row).
//!
//! Scalars enter as `mul_scalar(1.0 / x)`, never `div_scalar(x)`: Burn 0.22's autodiff
//! backward of `div_scalar` multiplies by `1 / x` rounded to float32, even for float64
//! tensors, which the float64 gradient checks see at 1e-8 relative.
//!
//! The layers, each importing only from those above it in this list:
//!
//! - [`error`]: the library's error type.
//! - [`read`]: reading untrusted files within a size limit.
//! - [`backend`]: which backends were compiled in (beside the custom ops' kernels); turns a
//!   choice into a device and tells the numerics what the device can do.
//! - [`model`]: the discrete model as differentiable tensor ops (SPEC §0–§5, §7).
//! - [`solver`]: iPALM on a level and the multilevel driver (SPEC §6, §7).
//! - [`features`]: VGG19 from ONNX and the deep model's feature maps (SPEC §4).
//! - [`io`]: images, the output folder, ground-truth files.
//! - [`eval`]: quality numbers of a finished morph, synthetic pairs with known truth.
//! - [`app`]: a whole morph from a config to a result folder.
//!
//! A morph as a library call:
//!
//! ```no_run
//! use std::sync::atomic::AtomicBool;
//! use deepmorph::app::config::{Inputs, MorphConfig};
//! use deepmorph::app::job::MorphJob;
//!
//! # fn main() -> deepmorph::Result<()> {
//! let inputs = Inputs::Files { a: "a.png".into(), b: "b.png".into() };
//! let job = MorphJob::prepare(MorphConfig::default(), inputs)?;
//! let out = job.output_folder("out".as_ref(), false)?; // checked before the work
//! let result = job.run(&mut (), &AtomicBool::new(false))?;
//! let (metrics, path) = result.write(&job, out)?;
//! # Ok(()) }
//! ```
#![warn(missing_docs)]

pub mod app;
pub mod backend;
#[cfg(feature = "check")]
pub mod check;
pub mod error;
pub mod eval;
pub mod features;
#[cfg(test)]
mod fuzz;
pub mod host_memory;
pub mod io;
pub mod model;
pub mod read;
pub mod solver;

pub use backend::{Backend, Precision};
pub use error::{Error, Result};
pub use model::grid::Grid;
pub use model::params::EnergyParams;
