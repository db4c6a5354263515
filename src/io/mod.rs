//! Files: images in and out, what a morph leaves in its output folder, and ground-truth
//! correspondences.
//!
//! - [`energy_log`]: the energy after every sweep, written as `energy.csv`.
//! - [`images`]: image files ↔ host images ↔ tensors, crash-safe writing.
//! - [`output_folder`]: a run's output folder as one transaction (staged beside it, swapped
//!   in when complete, never mixing two runs).
//! - [`outputs`]: the output folder of a morph (frames, GIF, contact sheet, deformations,
//!   `energy.csv`, `config.json`), written and read back.
//! - [`truth`]: Middlebury disparity PNGs and `.flo` flow files, resampled to a working size.

pub mod energy_log;
pub mod images;
pub mod output_folder;
pub mod outputs;
pub mod truth;
