//! The integration tests, built as one binary: each file below was its own test crate, and
//! every one of them was linked against Burn with all three backends; one link instead of
//! eleven is a large part of what keeps CI's build short. Filter as before by path, e.g.
//! `cargo test golden_solver::` or `cargo test wgpu::`.

#[macro_use]
mod common;

mod cli;
mod deep;
mod golden;
mod golden_solver;
mod gradcheck;
mod layers;
mod properties;
mod quality;
mod reliability;
mod solver;
mod solver_rules;
mod vgg;
