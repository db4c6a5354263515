//! The terms of the path energy, grouped by what they look at: the deformation
//! ([`density`], [`density_op`], [`regularizer`]), the image ([`anisotropy`], [`anisotropy_op`]), an image pair ([`data`]), and
//! the whole path ([`path`]); point pairs the user gives ([`landmarks`], SPEC §11).

pub mod anisotropy;
pub mod anisotropy_op;
pub mod data;
pub mod density;
pub mod density_op;
pub mod distance_op;
pub mod landmarks;
pub mod path;
pub mod regularizer;
