//! The application layer: a morph from a [`config::MorphConfig`] to a folder of results,
//! as a library call. The command line (`src/bin/deepmorph`) only parses arguments, shows
//! progress, handles Ctrl-C and maps outcomes to exit codes.
//!
//! - [`chain`]: morphing through more than two images, one morph per consecutive pair.
//! - [`config`]: the settings of a whole morph, serialisable; `config.json`'s record.
//! - [`evaluate`]: a finished morph's folder checked and measured (`deepmorph eval`).
//! - [`hooks`]: the command line's test hooks (a NaN or an interrupt at a chosen sweep).
//! - [`job`]: prepare (check, read, size, memory), run, write the outputs.
//! - [`memory`]: the peak-memory estimate and the refusal of what would not fit.
//! - [`demo`]: the built-in synthetic pair.
//! - [`warp`]: a synthetic pair with a known correspondence, written (`deepmorph warp`).

pub mod chain;
pub mod config;
pub mod demo;
pub mod evaluate;
pub mod hooks;
pub mod job;
pub mod memory;
pub mod warp;
