//! Quality numbers of a finished morph and pairs with a known answer.
//!
//! - [`metrics`]: the composed map, `det J` statistics, the energy split, warp consistency
//!   and the endpoint error against ground truth.
//! - [`folder`]: a morph's output folder read back, evaluated as `deepmorph eval` does.
//! - [`perceptual`]: the path's adjacent-frame distances in VGG19 feature space.
//! - [`synthetic`]: an image warped by a known deformation, with its truth.

pub mod folder;
pub mod metrics;
pub mod perceptual;
pub mod synthetic;
