//! Files: images in and out, what a morph leaves in its output folder, and ground-truth
//! correspondences.
//!
//! - [`animation`]: the morph as MP4, APNG and GIF, which of them and how fast.
//! - [`checkpoint`]: the state an interrupted morph leaves for `--resume`.
//! - [`energy_log`]: the energy after every sweep, written as `energy.csv`.
//! - [`h264`] (feature `mp4`): frames to H.264 in an MP4 file.
//! - [`images`]: image files ↔ host images ↔ tensors, crash-safe writing.
//! - [`mp4`]: a minimal MP4 writer and reader for one H.264 track.
//! - [`output_folder`]: a run's output folder as one transaction (staged beside it, swapped
//!   in when complete, never mixing two runs).
//! - [`outputs`]: the output folder of a morph (frames, GIF, contact sheet, deformations,
//!   `energy.csv`, `config.json`), written and read back.
//! - [`truth`]: Middlebury disparity PNGs and `.flo` flow files, resampled to a working size.

pub mod animation;
pub mod checkpoint;
pub mod energy_log;
#[cfg(feature = "mp4")]
pub mod h264;
pub mod images;
pub mod mp4;
pub mod output_folder;
pub mod outputs;
pub mod points;
pub mod truth;
