//! The discrete model of SPEC §0–§5 and §7 as differentiable tensor operations: the grid a
//! level lives on, the mirror-boundary stencils, the cubic B-spline warp, deformations and
//! their Jacobian, the energy terms, resampling between levels, and what a feature vector
//! holds. Nothing here iterates, reads files or knows which backend runs it.
//!
//! - [`decision`]: the float64 sums that decide backtracking tests (SPEC §6).
//! - [`grid`]: the pixel grid of a level, its device, dtype and backend capabilities, and
//!   the host read-back.
//! - [`stencil`], [`separable`]: the 1-D mirror-boundary operators (SPEC §0) and their
//!   separable application to images.
//! - [`warp`]: the cubic B-spline warp `T[f, φ]` (SPEC §1).
//! - [`deformation`]: Jacobian and admissibility (SPEC §0, §2).
//! - [`energy`]: `W`, `R`, the anisotropy `a`, `D` and the path energy `E` (SPEC §2–§5).
//! - `cpu`: what the custom ops' native CPU kernels share (element types, AVX2 dispatch,
//!   vectorisable `ln` and `exp`); the kernels import from it, never from each other.
//! - [`params`]: the energy's parameters with SPEC §9's defaults.
//! - [`sobel`]: the Sobel derivative of the data-term linearisation (SPEC §6); [`slopes`]:
//!   the linearisation's per-pixel moments over the channels, fused.
//! - [`resample`]: bilinear resizing and prolongation between levels (SPEC §7).
//! - [`inbetween`]: frames between the computed ones, for a smooth clip.
//! - [`layout`], [`feature_model`]: the channels of a feature vector and the RGB or deep
//!   feature vectors of each level (SPEC §4).

pub mod alignment;
pub(crate) mod cpu;
pub mod decision;
pub mod deformation;
pub mod energy;
pub mod feature_model;
pub mod grid;
#[cfg(feature = "flex")]
pub(crate) mod host_view;
pub mod inbetween;
pub mod layout;
pub mod params;
pub mod resample;
pub mod separable;
pub mod slopes;
pub mod sobel;
pub mod stencil;
pub mod warp;
