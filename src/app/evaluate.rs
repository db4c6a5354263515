//! `deepmorph eval` as a library call: a morph's output folder read back, checked against its
//! own record, and measured, optionally against a ground-truth correspondence.

use std::path::Path;

use burn::tensor::{Device, Tensor};

use crate::app::config::{Inputs, RunRecord};
use crate::error::{Error, Result};
use crate::eval::folder::MorphFolder;
use crate::eval::metrics::{LandmarkResiduals, Metrics};
use crate::eval::perceptual::feature_path;
use crate::features::vgg::Vgg19;
use crate::io::outputs::CONFIG;
use crate::io::points::{landmarks_on_working_grid, pairs_of, read_points};
use crate::io::truth::Correspondence;
use crate::model::grid::host_values;

/// What [`evaluate`] measured.
pub struct Evaluation {
    /// The quality numbers (with the endpoint error when a truth was given).
    pub metrics: Metrics,
    /// The composed map `Φ`, `[1, 2, H, W]`.
    pub composed: Tensor<4>,
}

impl Evaluation {
    /// Writes the composed map and `metrics.json` into the morph's folder `dir`
    /// (`deepmorph eval --write`).
    ///
    /// # Errors
    ///
    /// A file cannot be written.
    pub fn write(&self, dir: &Path) -> Result<()> {
        crate::io::outputs::save_composed(dir, self.composed.clone())?;
        crate::app::job::write_metrics(dir, &self.metrics)
    }
}

/// How far the aspect ratio of a ground truth may be from the morph's when the input's own
/// size is unknown (the working size rounds each side to a multiple of up to 16 pixels).
const ASPECT_TOLERANCE: f64 = 0.05;

/// Reads the morph in `dir`, checks that its `config.json` describes the files beside it,
/// and measures it; with `truth`, also its endpoint error against that file; with `vgg19`
/// (weights as for the deep model), also its path in VGG19 feature space. A truth must be
/// at the size of the morph's first input (or, where that input cannot be read, of the same
/// aspect as the working size); another size is refused unless `resample_truth`. With
/// `points` (a points file as for `--points`, in the inputs' own pixels), the landmark
/// residuals are measured on those pairs instead of the run's own (held-out points, or a
/// run made without any).
///
/// # Errors
///
/// A missing or malformed file, a record that disagrees with the files, a truth of another
/// size, unreadable weights, points that do not fit the inputs.
pub fn evaluate(
    dir: &Path,
    truth: Option<&Path>,
    resample_truth: bool,
    vgg19: Option<&Path>,
    points: Option<&Path>,
    device: &Device,
) -> Result<Evaluation> {
    let folder = MorphFolder::read(dir, device)?;
    let mut record = RunRecord::read(&dir.join(CONFIG))?;
    if let Some(path) = points {
        let pairs = read_points(path)?;
        let working = (record.working_size[0], record.working_size[1]);
        let (size_a, size_b) = match &record.inputs {
            Inputs::Files { a, b } => (input_size(a)?, input_size(b)?),
            Inputs::Demo => (working, working),
            Inputs::Arrays { a, b } => ((a[0], a[1]), (b[0], b[1])),
        };
        let landmarks = landmarks_on_working_grid(&pairs, size_a, size_b, working)?;
        record.landmarks = Some(pairs_of(&landmarks));
    }
    let (h, w) = (folder.grid.height(), folder.grid.width());
    let disagree = |detail: String| Error::Format {
        path: dir.join(CONFIG),
        detail: format!("{detail}: the folder mixes files of different runs"),
    };
    if record.config.solver.steps != folder.steps {
        return Err(disagree(format!(
            "records K = {} but the deformations hold {} steps",
            record.config.solver.steps, folder.steps
        )));
    }
    if record.outcome.grid != [h, w] {
        return Err(disagree(format!(
            "records a {}x{} grid but the deformations are {w}x{h}",
            record.outcome.grid[1], record.outcome.grid[0]
        )));
    }
    let truth = truth
        .map(|path| -> Result<_> {
            let correspondence = Correspondence::load(path)?;
            check_truth_size(&correspondence, path, &record, resample_truth)?;
            Ok((correspondence, path.display().to_string()))
        })
        .transpose()?;
    let composed = folder.composed();
    let mut metrics = folder.metrics(
        composed.clone(),
        truth.as_ref().map(|(t, name)| (t, name.as_str())),
    )?;
    metrics.landmarks = landmark_residuals(&record, composed.clone(), (h, w))?;
    if let Some(weights) = vgg19 {
        let vgg = Vgg19::load(weights, device)?;
        metrics.feature_path = Some(feature_path(&vgg, &folder.grid, &folder.frames)?);
    }
    Ok(Evaluation { metrics, composed })
}

/// The landmark residuals `|Φ(p_i) − q_i|` of a run whose `record` has landmarks, with
/// `composed` the map `Φ` (`[1, 2, H, W]`) on its `(H, W)` grid: `None` without landmarks.
/// The landmarks are recorded on the working grid; a run stopped on a coarser level maps
/// them there by SPEC §7's align-corners rule.
///
/// # Errors
///
/// If `composed` holds a NaN.
pub(crate) fn landmark_residuals(
    record: &RunRecord,
    composed: Tensor<4>,
    (h, w): (usize, usize),
) -> Result<Option<LandmarkResiduals>> {
    let Some(pairs) = &record.landmarks else {
        return Ok(None);
    };
    let [wh, ww] = record.working_size;
    let scale = |v: f64, to: usize, from: usize| {
        if from > 1 {
            v * (to - 1) as f64 / (from - 1) as f64
        } else {
            v
        }
    };
    let on_grid = |[x, y]: [f64; 2]| [scale(y, h, wh), scale(x, w, ww)];
    let pairs: Vec<_> = pairs.iter().map(|p| (on_grid(p.a), on_grid(p.b))).collect();
    Ok(Some(LandmarkResiduals::of(
        &host_values(composed)?,
        (h, w),
        &pairs,
    )))
}

/// The `(rows, columns)` of an input image, from its header.
fn input_size(path: &Path) -> Result<(usize, usize)> {
    let (w, h) = image::image_dimensions(path).map_err(|e| Error::Format {
        path: path.to_path_buf(),
        detail: format!("cannot read the input's size to place the points: {e}"),
    })?;
    Ok((h as usize, w as usize))
}

/// Refuses a truth whose size is not the first input's (see [`evaluate`]).
fn check_truth_size(
    truth: &Correspondence,
    path: &Path,
    record: &RunRecord,
    resample: bool,
) -> Result<()> {
    if resample {
        return Ok(());
    }
    let (th, tw) = (truth.height(), truth.width());
    let [wh, ww] = record.working_size;
    let input = match &record.inputs {
        Inputs::Files { a, .. } => image::image_dimensions(a)
            .ok()
            .map(|(w, h)| (h as usize, w as usize, a.display().to_string())),
        Inputs::Demo => Some((wh, ww, "demo input".into())),
        Inputs::Arrays { a: [h, w], .. } => Some((*h, *w, "first input array".into())),
    };
    let refuse = |what: String| {
        Err(Error::Format {
            path: path.to_path_buf(),
            detail: format!(
                "a {tw}x{th} ground truth, but {what}: pass --resample-truth to scale it to \
                 the morph (displacements scaled per axis)"
            ),
        })
    };
    match input {
        Some((ih, iw, name)) if (ih, iw) != (th, tw) => {
            refuse(format!("the first input {name} is {iw}x{ih}"))
        }
        Some(_) => Ok(()),
        None => {
            let aspect = |h: usize, w: usize| w as f64 / h as f64;
            if (aspect(th, tw) / aspect(wh, ww) - 1.0).abs() > ASPECT_TOLERANCE {
                refuse(format!(
                    "the morph is {ww}x{wh} (its first input cannot be read to compare sizes)"
                ))
            } else {
                Ok(())
            }
        }
    }
}
