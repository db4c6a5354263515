//! Evaluating a finished morph from its output directory: what `deepmorph eval` runs and
//! what every morph writes as `metrics.json`.
//!
//! It reads only files (the deformations, the frames, `energy.csv`; the run's
//! `config.json` must be there), so a morph evaluated at its end and the same folder
//! evaluated later give the same numbers. The frames are the written 8-bit PNGs: the warp-consistency figures
//! are those of what the user sees (8-bit rounding alone caps the PSNR near 59 dB).

use std::path::Path;

use burn::tensor::{Device, Tensor};

use crate::backend::Precision;
use crate::error::{Error, Result};
use crate::eval::metrics::{Metrics, compose};
use crate::io::energy_log::EnergyLog;
use crate::io::images::RgbImage;
use crate::io::outputs::{CONFIG, DEFORMATIONS_HEADER, frame_name, load_deformations};
use crate::io::truth::Correspondence;
use crate::model::grid::Grid;

/// A morph's output directory, read back.
pub struct MorphFolder {
    /// `K`.
    pub steps: usize,
    /// `φ_1..φ_K`, `[K, 2, H, W]` on the evaluation device.
    pub deformations: Tensor<4>,
    /// `u_0` and `u_K`, `[1, 3, H, W]`.
    pub endpoints: (Tensor<4>, Tensor<4>),
    /// Every written frame `u_0..u_K`.
    pub frames: Vec<RgbImage>,
    /// `energy.csv`.
    pub energy: EnergyLog,
    /// The working grid.
    pub grid: Grid,
}

impl MorphFolder {
    /// Reads `dir` onto `device` (float32).
    ///
    /// # Errors
    ///
    /// [`Error::Io`] or [`Error::Format`] naming the missing or malformed file, or a
    /// mismatch between the files (sizes, number of steps).
    pub fn read(dir: &Path, device: &Device) -> Result<Self> {
        let format = |name: &str, detail: String| Error::Format {
            path: dir.join(name),
            detail,
        };
        if !dir.join(CONFIG).is_file() {
            return Err(format(
                CONFIG,
                "not found: not the output folder of a morph (`deepmorph morph` writes \
                 config.json beside the deformations, frames and energy.csv)"
                    .into(),
            ));
        }
        // The deformations' grid, not necessarily the working size: an interrupted morph
        // writes the level it reached.
        let (shape, phi) = load_deformations(dir)?;
        let [k, two, h, w] = shape;
        if two != 2 || k == 0 {
            return Err(format(
                DEFORMATIONS_HEADER,
                format!("shape {shape:?}: expected [K, 2, H, W] with K >= 1"),
            ));
        }
        let grid = Grid::new(h, w, device, Precision::F32.dtype())?;
        let deformations = grid.tensor(phi.into_iter().map(f64::from).collect(), shape);

        let frame = |i: usize| -> Result<RgbImage> {
            let name = frame_name(i, k);
            let image = RgbImage::load(&dir.join(&name))?;
            if (image.height(), image.width()) != (h, w) {
                return Err(format(
                    &name,
                    format!(
                        "{}x{}, but the deformations are {w}x{h}",
                        image.width(),
                        image.height()
                    ),
                ));
            }
            Ok(image)
        };
        let frames = (0..=k).map(frame).collect::<Result<Vec<_>>>()?;
        let energy = EnergyLog::read(&dir.join("energy.csv"))?;
        Self::from_parts(grid, deformations, frames, energy)
    }

    /// A folder's contents from their parts: `deformations` `[K, 2, H, W]` on `grid`, the
    /// `K + 1` frames at its size, the energy log.
    ///
    /// # Errors
    ///
    /// [`Error::Shape`] if the frames do not fit the deformations.
    pub fn from_parts(
        grid: Grid,
        deformations: Tensor<4>,
        frames: Vec<RgbImage>,
        energy: EnergyLog,
    ) -> Result<Self> {
        let [k, _, h, w] = deformations.dims();
        if frames.len() != k + 1 || frames.iter().any(|f| f.size() != (h, w)) {
            return Err(Error::Shape {
                op: "MorphFolder::from_parts",
                detail: format!("{} frames for {k} deformations of {w}x{h}", frames.len()),
            });
        }
        let endpoints = (frames[0].to_tensor(&grid)?, frames[k].to_tensor(&grid)?);
        Ok(Self {
            steps: k,
            deformations,
            endpoints,
            frames,
            energy,
            grid,
        })
    }

    /// The composed map `Φ`, `[1, 2, H, W]`.
    pub fn composed(&self) -> Tensor<4> {
        compose(&self.grid, self.deformations.clone())
    }

    /// Every quality number of the folder's morph, `composed` being its [`composed`](Self::composed)
    /// map; with `truth` (and its name), also the endpoint error of `Φ` against it.
    ///
    /// # Errors
    ///
    /// If a value is NaN.
    pub fn metrics(
        &self,
        composed: Tensor<4>,
        truth: Option<(&Correspondence, &str)>,
    ) -> Result<Metrics> {
        Metrics::compute(
            &self.grid,
            self.deformations.clone(),
            composed,
            self.endpoints.clone(),
            &self.frames.iter().map(RgbImage::data).collect::<Vec<_>>(),
            &self.energy.records,
            truth,
        )
    }
}
