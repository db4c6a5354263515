//! # deepmorph
//!
//! Image morphing as a time-discrete geodesic path in the metamorphosis model, after
//! Effland, Kobler, Pock, Rajković and Rumpf, "Image Morphing in Deep Feature Spaces"
//! (Section 5). The exact discrete model is fixed by `SPEC.md`; module docs cite its
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
//! - [`stencil`], [`separable`]: the mirror-boundary linear operators (SPEC §0).
//! - [`warp`]: the cubic B-spline warp `T[f, φ]` (SPEC §1).
//! - [`deformation`]: Jacobian and admissibility (SPEC §2).
//! - [`energy`]: `W`, `R`, the anisotropy `a`, `D` and the path energy `E` (SPEC §2–§5).
//! - [`sobel`]: the Sobel derivative of the data-term linearisation (SPEC §6).
//! - [`resample`]: bilinear resizing and prolongation (SPEC §7).
//! - [`vgg`], [`deep`]: VGG19 imported from ONNX by burn-import, its run-time weights, and
//!   the deep model's feature vectors `(η·u, τ·F/rms)` per level (SPEC §4).
//! - [`metrics`], [`truth`], [`eval`], [`synthetic`]: quality numbers of a finished morph
//!   (composed map, `det J`, energy split, warp consistency, endpoint error against ground
//!   truth) and synthetic pairs with a known deformation.
#![warn(missing_docs)]

pub mod backend;
pub mod deep;
pub mod deformation;
pub mod demo;
pub mod energy;
pub mod error;
pub mod eval;
pub mod grid;
pub mod io;
pub mod layout;
pub mod memory;
pub mod metrics;
pub mod multilevel;
pub mod observe;
pub mod optim;
pub mod output;
pub mod params;
pub mod resample;
pub mod separable;
pub mod sobel;
pub mod stencil;
pub mod synthetic;
pub mod truth;
pub mod vgg;
pub mod warp;

pub use backend::{Backend, Precision};
pub use error::{Error, Result};
pub use grid::Grid;
pub use params::EnergyParams;
