//! A morph from a [`MorphConfig`] to a result folder, in three calls:
//! [`MorphJob::prepare`] checks the settings, reads the inputs, picks the working size and
//! refuses what would not fit in memory; [`MorphJob::run`] morphs; [`MorphResult::write`]
//! writes every output and returns the quality numbers.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use burn::tensor::Tensor;
use image::RgbImage as Rgb8;

use crate::app::config::{AlignmentRecord, Inputs, MorphConfig, Outcome, RunRecord};
use crate::app::demo::demo_pair;
use crate::app::evaluate::landmark_residuals;
use crate::app::memory;
use crate::backend::Precision;
use crate::error::{Error, Result};
use crate::eval::folder::MorphFolder;
use crate::eval::metrics::Metrics;
use crate::eval::perceptual::feature_path;
use crate::features::deep::deep_features;
use crate::features::vgg::Vgg19;
use crate::features::vgg::architecture::tap_channels;
use crate::features::vgg::weights::Vgg19Weights;
use crate::io::checkpoint::{inputs_digest, load_checkpoint, save_checkpoint};
use crate::io::energy_log::EnergyLog;
use crate::io::images::{RgbImage, write_atomically, write_png};
use crate::io::output_folder::OutputFolder;
use crate::io::outputs::{
    CONFIG, METRICS, contact_sheet, is_morph_output, save_composed, save_deformations, write_frames,
};
use crate::io::points::{landmarks_on_working_grid, pairs_of, split_by_segment};
use crate::model::alignment::{
    AlignKind, GlobalMap, GreyImage, SearchRanges, estimate_from_images,
};
use crate::model::energy::landmarks::Landmarks;
use crate::model::feature_model::FeatureModel;
use crate::model::grid::{Grid, host_values};
use crate::model::inbetween::Clip;
use crate::read::is_regular_file;
use crate::solver::estimate::TimeEstimate;
use crate::solver::ipalm::Schedule;
use crate::solver::multilevel::{Draft, Morph, Multilevel};
use crate::solver::observer::{Observer, Termination};

/// A morph ready to run: checked settings, the inputs at the working size.
#[derive(Clone, Debug)]
pub struct MorphJob {
    config: MorphConfig,
    inputs: Inputs,
    images: (RgbImage, RgbImage),
    notes: Vec<String>,
    estimate: u64,
    /// SPEC §11's landmarks on the working grid, from [`MorphConfig::points`].
    landmarks: Option<Landmarks>,
    /// SPEC §11's global map on the working grid, from [`MorphConfig::align`].
    alignment: Option<(GlobalMap, AlignmentRecord)>,
    estimate_time: bool,
    resume: Option<PathBuf>,
    /// A fault for the tests (feature `check`): `None` in every other build.
    #[cfg_attr(not(feature = "check"), allow(dead_code))]
    inject_nonfinite: Option<(usize, usize)>,
    stop_within: Option<(usize, usize, usize)>,
}

/// What a morph computed.
#[derive(Debug)]
pub struct MorphResult {
    /// The solver's result: the last level's grid and state, `a_1..a_K`, the termination.
    pub morph: Morph,
    /// `u_0..u_K` on the host (SPEC §8: RGB part, divided by `η` in the deep model).
    pub frames: Vec<RgbImage>,
    /// `E` and its parts after every joint sweep.
    pub energy: EnergyLog,
    /// Wall-clock seconds of the solver (not of reading the inputs).
    pub seconds: f64,
    /// The deep model: RMS of each VGG tap of the inputs before scaling.
    pub tap_rms: Option<Vec<f64>>,
    /// The time predicted before the solve, when the job was asked for it
    /// ([`MorphJob::estimate_time`]).
    pub estimate: Option<TimeEstimate>,
    /// VGG19's weights when their file is a pipe, which can be read only once: the
    /// feature-space metric needs them again after the solve. A regular file is read again
    /// instead (the weights are not held through the solve, for memory).
    pipe_weights: Option<Vgg19Weights>,
}

impl MorphJob {
    /// Checks `config`, reads the inputs, resolves the working size and refuses a morph whose
    /// estimated peak memory would not fit, before anything large is allocated.
    ///
    /// # Errors
    ///
    /// A bad setting, an unreadable input, a working size that does not fit the pyramid, or
    /// not enough memory.
    pub fn prepare(config: MorphConfig, inputs: Inputs) -> Result<Self> {
        check_settings(&config, &inputs)?;
        match inputs {
            Inputs::Files { a, b } => {
                let ((image_a, warning_a), (image_b, warning_b)) =
                    (RgbImage::read(&a)?, RgbImage::read(&b)?);
                let sizes = (image_a.size(), image_b.size());
                let absolute = |p: PathBuf| p.canonicalize().unwrap_or(p);
                let inputs = Inputs::Files {
                    a: absolute(a),
                    b: absolute(b),
                };
                let mut job = Self::prepare_images(config, inputs, (image_a, image_b), sizes)?;
                let warnings = [warning_a, warning_b].into_iter().flatten();
                job.notes.splice(0..0, warnings);
                Ok(job)
            }
            Inputs::Demo => {
                let side = match config.size {
                    crate::app::config::WorkingSize::Fit { max_side } => max_side,
                    crate::app::config::WorkingSize::Exact { height, width } => height.max(width),
                };
                let (h, w) = config.size.resolve(side, side, config.size_multiple())?;
                let (a, b) = demo_pair(h.max(w));
                // The demo's points are in the pair's own (square) pixels.
                let sizes = (a.size(), b.size());
                let images = (a.resized(h, w), b.resized(h, w));
                Self::prepare_images(config, Inputs::Demo, images, sizes)
            }
            Inputs::Arrays { .. } => Err(Error::invalid(
                "inputs",
                "arrays",
                "image files: this run's inputs were handed over in memory (the Python \
                 module) and cannot be read again; give the images A and B",
            )),
        }
    }

    /// As [`prepare`](Self::prepare), for two images already in memory (the Python module's
    /// arrays); `config.json` records their sizes ([`Inputs::Arrays`]).
    ///
    /// # Errors
    ///
    /// As [`prepare`](Self::prepare), but for reading the inputs.
    pub fn from_images(config: MorphConfig, a: RgbImage, b: RgbImage) -> Result<Self> {
        check_settings(&config, &Inputs::Demo)?;
        let sizes = (a.size(), b.size());
        let inputs = Inputs::Arrays {
            a: [sizes.0.0, sizes.0.1],
            b: [sizes.1.0, sizes.1.1],
        };
        Self::prepare_images(config, inputs, (a, b), sizes)
    }

    /// [`prepare`](Self::prepare) once the inputs are read: the working size, the memory
    /// check, the landmarks and the alignment.
    /// `sizes` are the inputs' own sizes, in which the landmarks are given.
    fn prepare_images(
        config: MorphConfig,
        inputs: Inputs,
        (image_a, image_b): (RgbImage, RgbImage),
        sizes: ((usize, usize), (usize, usize)),
    ) -> Result<Self> {
        let multiple = config.size_multiple();
        let deep = config.deep.is_some();
        let channels = if deep { 3 + tap_channels()[0] } else { 3 };
        let plan = |height: usize, width: usize| memory::Plan {
            height,
            width,
            steps: config.solver.steps,
            channels,
            deep,
            batched: config.solver.ipalm.schedule == Schedule::Batched,
        };
        let (h, w) = config
            .size
            .resolve(image_a.height(), image_a.width(), multiple)?;
        let estimate = memory::check(
            &plan(h, w),
            config.max_memory_gib,
            config.backend != crate::Backend::Wgpu,
        )?;
        let mut notes = Vec::new();
        let mut resize = |img: RgbImage, name: &str| {
            if (img.height(), img.width()) == (h, w) {
                return img;
            }
            notes.push(format!(
                "{name}: {}x{} resized to the working size {w}x{h}",
                img.width(),
                img.height()
            ));
            img.resized(h, w)
        };
        let images = (resize(image_a, "A"), resize(image_b, "B"));
        if let Some(dir) = &config.init {
            check_draft(dir, &config, images.0.height(), images.0.width())?;
        }
        let working = (images.0.height(), images.0.width());
        check_video_size(&config, working)?;
        let landmarks = match &config.points {
            Some(points) => {
                let pairs = split_by_segment(points, 1)?.remove(0).unwrap_or_default();
                let landmarks = landmarks_on_working_grid(&pairs, sizes.0, sizes.1, working)?;
                for (i, j) in landmarks.crossings() {
                    notes.push(format!(
                        "warning: the straight paths of landmark pairs {} and {} meet: a \
                         diffeomorphic path cannot follow both exactly",
                        i + 1,
                        j + 1
                    ));
                }
                Some(landmarks)
            }
            None => None,
        };
        let alignment = match config.align {
            AlignKind::None => None,
            kind => {
                let aligned = estimate_alignment(&config, kind, &images, landmarks.as_ref())?;
                notes.push(aligned.1.describe());
                Some(aligned)
            }
        };
        Ok(Self {
            config,
            inputs,
            images,
            notes,
            estimate,
            landmarks,
            alignment,
            estimate_time: false,
            resume: None,
            inject_nonfinite: None,
            stop_within: None,
        })
    }

    /// For tests of the non-finite path: see [`Multilevel::inject_nonfinite`].
    #[doc(hidden)]
    #[cfg(feature = "check")]
    pub fn inject_nonfinite(mut self, level: usize, sweep: usize) -> Self {
        self.inject_nonfinite = Some((level, sweep));
        self
    }

    /// For tests of an interrupt within a sweep: see [`Multilevel::stop_within`].
    #[doc(hidden)]
    pub fn stop_within(mut self, level: usize, sweep: usize, blocks: usize) -> Self {
        self.stop_within = Some((level, sweep, blocks));
        self
    }

    /// Before the morph, time a few sweeps on two of its levels and report the predicted
    /// time to the observer ([`Observer::estimate`]; see [`crate::solver::estimate`]).
    pub fn estimate_time(mut self, yes: bool) -> Self {
        self.estimate_time = yes;
        self
    }

    /// Continue the interrupted morph whose folder is `dir` from its checkpoint
    /// ([`crate::io::checkpoint`]); its energy log is continued too. A folder without a
    /// checkpoint (a morph that was not interrupted) is run from the start.
    pub fn resume_from(mut self, dir: &Path) -> Self {
        self.resume = Some(dir.to_path_buf());
        self
    }

    /// One line for a person before the run: "morph: rgb model, 256x256 (WxH), K = 15, 5
    /// levels x 250 sweeps, flex backend, about 0.2 GiB".
    pub fn describe(&self) -> String {
        let (h, w) = self.working_size();
        let solver = &self.config.solver;
        format!(
            "{}: {} model, {w}x{h} (WxH), K = {}, {} levels x {} sweeps, {} backend, about {:.1} GiB",
            if self.inputs == Inputs::Demo {
                "demo"
            } else {
                "morph"
            },
            format!("{:?}", self.config.model()).to_lowercase(),
            solver.steps,
            solver.levels,
            solver.sweeps,
            self.config.backend,
            memory::gib(self.estimated_peak_bytes())
        )
    }

    /// One line for a person before a segment of a chain runs: "a.png -> b.png, 256x192
    /// (WxH), about 0.2 GiB".
    pub fn describe_segment(&self) -> String {
        let (h, w) = self.working_size();
        let inputs = match &self.inputs {
            Inputs::Files { a, b } => format!("{} -> {}, ", a.display(), b.display()),
            Inputs::Demo => "the demo pair, ".into(),
            Inputs::Arrays { .. } => "two arrays, ".into(),
        };
        format!(
            "{inputs}{w}x{h} (WxH), about {:.1} GiB",
            memory::gib(self.estimated_peak_bytes())
        )
    }

    /// The settings.
    pub fn config(&self) -> &MorphConfig {
        &self.config
    }

    /// The inputs (files as absolute paths).
    pub fn inputs(&self) -> &Inputs {
        &self.inputs
    }

    /// The working size `(H, W)`.
    pub fn working_size(&self) -> (usize, usize) {
        (self.images.0.height(), self.images.0.width())
    }

    /// What preparing did that a user should hear of (inputs resized).
    pub fn notes(&self) -> &[String] {
        &self.notes
    }

    /// [`inputs_digest`] of the inputs at the working size (what a checkpoint records).
    pub fn inputs_digest(&self) -> String {
        inputs_digest([self.images.0.data(), self.images.1.data()])
    }

    /// The estimated peak memory in bytes.
    pub fn estimated_peak_bytes(&self) -> u64 {
        self.estimate
    }

    /// Begins the output folder `dir` (see [`OutputFolder::begin`]): before the morph runs,
    /// so a folder that cannot be used or written is refused before any work. `force`
    /// allows replacing a previous morph there.
    ///
    /// # Errors
    ///
    /// The folder holds other files, a previous morph without `force`, an input, or cannot
    /// be written.
    pub fn output_folder(&self, dir: &Path, force: bool) -> Result<OutputFolder> {
        OutputFolder::begin(dir, &self.inputs.files(), is_morph_output, force)
    }

    /// Runs the morph, reporting every sweep to `observer`; stops after the current step
    /// when `interrupt` is raised. A NaN in the optimisation is not an error: the result
    /// then holds the last finite iterate and says so in its termination.
    ///
    /// # Errors
    ///
    /// The backend cannot run, the VGG19 weights cannot be read, or the inputs do not suit
    /// the model.
    pub fn run(&self, observer: &mut dyn Observer, interrupt: &AtomicBool) -> Result<MorphResult> {
        let precision = Precision::F32;
        let device = self.config.backend.device_for(precision)?.autodiff();
        let (h, w) = self.working_size();
        let grid = Grid::new(h, w, &device, precision.dtype())?;
        let (u_a, u_b) = (
            self.images.0.to_tensor(&grid)?,
            self.images.1.to_tensor(&grid)?,
        );
        let mut pipe_weights = None;
        // Seconds of one VGG19 forward at the working size (the deep model).
        let mut forward_seconds = 0.0;
        let model = match &self.config.deep {
            Some(deep) => {
                let weights = Vgg19Weights::read(&deep.vgg19)?;
                if !is_regular_file(&deep.vgg19) {
                    pipe_weights = Some(weights.clone());
                }
                let vgg = Vgg19::from_weights(weights, &device)?;
                let started = Instant::now();
                let features = deep_features(&vgg, u_a.clone(), u_b.clone(), deep.features)?;
                forward_seconds = started.elapsed().as_secs_f64() / 2.0;
                FeatureModel::Deep(features)
            }
            None => FeatureModel::Rgb,
        };
        let mut driver = Multilevel::new(self.config.solver)?;
        if let Some(landmarks) = &self.landmarks {
            driver = driver.with_landmarks(landmarks.clone());
        }
        if let Some((map, _)) = &self.alignment {
            driver = driver.with_alignment(*map);
        }
        if let Some(dir) = &self.config.init {
            let folder = MorphFolder::read(dir, &device)?;
            let frames = folder
                .frames
                .iter()
                .map(|f| f.to_tensor(&folder.grid))
                .collect::<Result<Vec<_>>>()?;
            driver = driver.with_draft(Draft {
                grid: folder.grid,
                frames,
                deformations: folder.deformations,
            })?;
        }
        if let Some((level, sweep, blocks)) = self.stop_within {
            driver = driver.stop_within(level, sweep, blocks);
        }
        #[cfg(feature = "check")]
        if let Some((level, sweep)) = self.inject_nonfinite {
            driver = driver.inject_nonfinite(level, sweep);
        }
        let mut predicted = None;
        if self.estimate_time
            && let Some(mut estimate) =
                driver.estimate_time(&device, &u_a, &u_b, &model, interrupt)?
        {
            // The feature-space path metric after the solve: one forward per frame of the
            // morph and of the cross-fade, their shared ends once (`feature_path`).
            estimate.after_solve = forward_seconds * (2 * self.config.solver.steps) as f64;
            observer.estimate(&estimate);
            predicted = Some(estimate);
        }
        let mut energy = EnergyLog::default();
        if let Some(dir) = &self.resume {
            let sizes = self.config.solver.level_sizes(h, w)?;
            let grid = |level: usize| {
                Grid::new(sizes[level].0, sizes[level].1, &device, precision.dtype())
            };
            if let Some(resume) = load_checkpoint(dir, &self.inputs_digest(), &sizes, grid)? {
                driver = driver.with_resume(resume);
                energy = EnergyLog::read(&dir.join("energy.csv"))?;
            }
        }
        let started = Instant::now();
        let morph = driver.run_with(
            &device,
            u_a,
            u_b,
            &model,
            &mut (&mut energy, observer),
            interrupt,
        )?;
        let seconds = started.elapsed().as_secs_f64();
        let frames = morph
            .images()
            .into_iter()
            .map(RgbImage::from_tensor)
            .collect::<Result<Vec<_>>>()?;
        Ok(MorphResult {
            morph,
            frames,
            energy,
            seconds,
            tap_rms: match model {
                FeatureModel::Deep(deep) => Some(deep.rms().to_vec()),
                FeatureModel::Rgb => None,
            },
            estimate: predicted,
            pipe_weights,
        })
    }
}

/// Checks the settings and the backend before any file is read, and refuses a path
/// `config.json` could not record as text (one that is not UTF-8 would fail only when the
/// morph is written, after all the work).
fn check_settings(config: &MorphConfig, inputs: &Inputs) -> Result<()> {
    config.validate()?;
    let recorded = inputs
        .files()
        .into_iter()
        .chain(config.init.as_deref())
        .chain(config.deep.as_ref().map(|deep| deep.vgg19.as_path()));
    for path in recorded {
        if path.to_str().is_none() {
            return Err(Error::invalid(
                "path",
                path.display(),
                "a UTF-8 name (config.json records the paths of a run as text): rename the \
                 file or folder",
            ));
        }
    }
    config.backend.device_for(Precision::F32)?;
    Ok(())
}

/// Refuses a working size one of the requested animations cannot encode
/// ([`crate::io::animation::VideoFormat::min_side`]), before any work.
///
/// # Errors
///
/// [`Error::InvalidParameter`] naming the size and what would work.
fn check_video_size(config: &MorphConfig, (h, w): (usize, usize)) -> Result<()> {
    let Some(format) = config
        .video
        .iter()
        .copied()
        .find(|f| h.min(w) < f.min_side())
    else {
        return Ok(());
    };
    Err(Error::invalid(
        "size",
        format!("{w}x{h} (WxH)"),
        format!(
            "at least {} pixels on each side for {} (its encoder's smallest frame): a larger \
             --size, or --video without {format}",
            format.min_side(),
            format.file_name()
        ),
    ))
}

/// SPEC §11's global map for `--align kind`: from the landmarks by least squares when there
/// are any, otherwise from the images on the coarsest level (RGB resampled to its size,
/// blurred grey, [`SearchRanges::default`]).
///
/// # Errors
///
/// Too few or degenerate landmarks, a map that reflects, or images without contrast.
fn estimate_alignment(
    config: &MorphConfig,
    kind: AlignKind,
    (a, b): &(RgbImage, RgbImage),
    landmarks: Option<&Landmarks>,
) -> Result<(GlobalMap, AlignmentRecord)> {
    let (h, w) = (a.height(), a.width());
    let (map, source, ncc) = match landmarks {
        Some(landmarks) => (
            GlobalMap::from_landmarks(landmarks, kind)?,
            "landmarks",
            None,
        ),
        None => {
            let (lh, lw) = config.solver.level_sizes(h, w)?[0];
            let grey = |img: &RgbImage| {
                let small = img.resized(lh, lw);
                let planes: Vec<f64> = small.data().iter().map(|&v| f64::from(v)).collect();
                GreyImage::from_rgb_planes(&planes, lh, lw, 1.0)
            };
            let found = estimate_from_images(&grey(a)?, &grey(b)?, kind, &SearchRanges::default())?;
            (
                found.map.on_grid((lh, lw), (h, w)),
                "images",
                Some([found.ncc, found.ncc_identity]),
            )
        }
    };
    let record = AlignmentRecord {
        kind,
        source: source.into(),
        matrix: map.matrix_xy(),
        summary: map.summary((h, w)),
        ncc,
    };
    Ok((map, record))
}

impl MorphResult {
    /// The run's record, `config.json`.
    pub fn record(&self, job: &MorphJob) -> RunRecord {
        let (h, w) = job.working_size();
        RunRecord {
            program: "deepmorph".into(),
            version: env!("CARGO_PKG_VERSION").into(),
            inputs: job.inputs.clone(),
            working_size: [h, w],
            config: job.config.clone(),
            landmarks: job.landmarks.as_ref().map(pairs_of),
            alignment: job.alignment.as_ref().map(|(_, record)| record.clone()),
            outcome: Outcome {
                termination: self.morph.termination.to_string(),
                grid: [self.morph.grid.height(), self.morph.grid.width()],
                seconds: self.seconds,
                levels: self.morph.levels.clone(),
                tap_rms: self.tap_rms.clone(),
                estimate: self.estimate.clone(),
            },
        }
    }

    /// Writes every output of SPEC §8 into `folder` and moves it into place (see
    /// [`OutputFolder::commit`]): the frames, the animations (`--video`), the contact sheet, the deformations,
    /// the energy log, `config.json`, the composed map and `metrics.json`, which is computed
    /// from the files just written by the code of `deepmorph eval` (so both give the same
    /// numbers). Returns those metrics and the folder's path.
    ///
    /// # Errors
    ///
    /// A file cannot be written (the folder is then left as it was before the run).
    pub fn write(&self, job: &MorphJob, folder: OutputFolder) -> Result<(Metrics, PathBuf)> {
        let metrics = self.write_files(job, folder.path())?;
        Ok((metrics, folder.commit()?))
    }

    /// The animations' frames, 8-bit: the computed frames, or `--frames N` of them with
    /// in-between frames ([`Clip`]).
    ///
    /// # Errors
    ///
    /// If the backend fails to render an in-between frame.
    pub fn animation(&self, job: &MorphJob) -> Result<Vec<Rgb8>> {
        let Some(count) = job.config.animation_frames else {
            return Ok(self.frames.iter().map(RgbImage::to_rgb8).collect());
        };
        Ok(self
            .inbetween(count)?
            .iter()
            .map(RgbImage::to_rgb8)
            .collect())
    }

    /// `count` frames evenly spaced in time along the path, the computed ones among them
    /// ([`Clip`]: frames between `u_{k−1}` and `u_k` follow `φ_k`).
    ///
    /// # Errors
    ///
    /// A `count` that does not hold the computed frames ([`crate::model::inbetween::check_count`]),
    /// or a backend that fails to render a frame.
    pub fn inbetween(&self, count: usize) -> Result<Vec<RgbImage>> {
        let grid = &self.morph.grid;
        let frames = self
            .frames
            .iter()
            .map(|f| f.to_tensor(grid))
            .collect::<Result<Vec<_>>>()?;
        let clip = Clip::new(
            grid,
            Tensor::cat(frames, 0),
            self.morph.state.deformations(),
            count,
        )?;
        (0..clip.len())
            .map(|j| RgbImage::from_tensor(clip.frame(j)))
            .collect()
    }

    /// Writes every output into the existing folder `dir` (as [`MorphResult::write`] does
    /// into its staging folder) and returns the metrics: for a morph that is part of a
    /// larger output, such as a segment of a chain.
    ///
    /// # Errors
    ///
    /// A file cannot be written.
    pub fn write_files(&self, job: &MorphJob, dir: &Path) -> Result<Metrics> {
        let k = job.config.solver.steps;
        write_frames(dir, &self.frames)?;
        let animation = self.animation(job)?;
        job.config.playback().write(dir, &animation)?;
        let deformations = self.morph.state.deformations();
        let displacement = deformations.clone() - self.morph.grid.identity(k);
        let sheet = contact_sheet(&self.frames, self.morph.anisotropy.clone(), displacement)?;
        write_png(&dir.join("sheet.png"), &sheet)?;
        save_deformations(dir, deformations)?;
        save_checkpoint(dir, &self.morph, || job.inputs_digest())?;
        let csv = self.energy.to_csv();
        write_atomically(&dir.join("energy.csv"), |w| w.write_all(csv.as_bytes()))?;
        let record = self.record(job);
        let json = serde_json::to_vec_pretty(&record).expect("records serialise");
        write_atomically(&dir.join(CONFIG), |w| w.write_all(&json))?;
        let device = job.config.backend.device_for(Precision::F32)?;
        let folder = MorphFolder::read(dir, &device)?;
        let (metrics, composed) = self.measure(job, &folder, &device)?;
        save_composed(dir, composed)?;
        write_metrics(dir, &metrics)?;
        Ok(metrics)
    }

    /// The quality numbers [`write`](Self::write) puts in `metrics.json`, computed in memory
    /// from what it would write (frames rounded to 8 bits, the energy log as `energy.csv`
    /// holds it), without writing anything: for a library caller who keeps the result.
    ///
    /// # Errors
    ///
    /// A NaN in the deformations, or a backend that cannot run.
    pub fn metrics(&self, job: &MorphJob) -> Result<Metrics> {
        let device = job.config.backend.device_for(Precision::F32)?;
        let deformations = self.morph.state.deformations();
        let shape = deformations.dims();
        let grid = Grid::new(shape[2], shape[3], &device, Precision::F32.dtype())?;
        let deformations = grid.tensor(host_values(deformations)?, shape);
        let frames = self
            .frames
            .iter()
            .map(|f| RgbImage::from_rgb8(&f.to_rgb8()))
            .collect();
        let energy =
            EnergyLog::from_csv(&self.energy.to_csv()).map_err(|detail| Error::Format {
                path: "energy.csv".into(),
                detail,
            })?;
        let folder = MorphFolder::from_parts(grid, deformations, frames, energy)?;
        Ok(self.measure(job, &folder, &device)?.0)
    }

    /// The metrics of `folder` (this morph, read back or in memory) and its composed map.
    fn measure(
        &self,
        job: &MorphJob,
        folder: &MorphFolder,
        device: &burn::tensor::Device,
    ) -> Result<(Metrics, Tensor<4>)> {
        let composed = folder.composed();
        let mut metrics = folder.metrics(composed.clone(), None)?;
        let grid = (folder.grid.height(), folder.grid.width());
        metrics.landmarks = landmark_residuals(&self.record(job), composed.clone(), grid)?;
        // The deep model's network again (it is not kept through the solve, for memory);
        // should its file have gone meanwhile, the morph is still measured, without these.
        if let Some(deep) = &job.config.deep {
            let vgg = match &self.pipe_weights {
                Some(weights) => Vgg19::from_weights(weights.clone(), device),
                None => Vgg19::load(&deep.vgg19, device),
            };
            metrics.feature_path = vgg
                .and_then(|vgg| feature_path(&vgg, &folder.grid, &folder.frames))
                .ok();
        }
        Ok((metrics, composed))
    }

    /// What [`write`](Self::write) writes, for a person: "16 frames, morph.mp4, …,
    /// metrics.json".
    pub fn outputs_written(&self, job: &MorphJob) -> String {
        let mut names = vec![format!("{} frames", self.frames.len())];
        names.extend(job.config.video.iter().map(|f| f.file_name().to_string()));
        names.extend(
            [
                "sheet.png",
                "deformations",
                "composed map",
                "energy.csv",
                "config.json",
                "metrics.json",
            ]
            .map(String::from),
        );
        names.join(", ")
    }

    /// Whether the morph ran to its end.
    pub fn completed(&self) -> bool {
        self.morph.termination == Termination::Completed
    }
}

/// Refuses a draft (`--init`) that cannot start this morph, before any work: not a morph's
/// folder, another `K`, larger than the working size's limit, or of another aspect ratio.
fn check_draft(dir: &Path, config: &MorphConfig, height: usize, width: usize) -> Result<()> {
    let record = RunRecord::read(&dir.join(CONFIG))?;
    let bad = |detail: String| Error::Format {
        path: dir.join(CONFIG),
        detail: format!("cannot start this morph from this draft: {detail}"),
    };
    if record.config.solver.steps != config.solver.steps {
        return Err(bad(format!(
            "its K is {}, this morph's {} (a refined morph keeps the draft's K)",
            record.config.solver.steps, config.solver.steps
        )));
    }
    let [h, w] = record.outcome.grid;
    if h > height || w > width {
        return Err(bad(format!(
            "it is {w}x{h}, larger than the working size {width}x{height}"
        )));
    }
    let aspect = |h: usize, w: usize| w as f64 / h as f64;
    if (aspect(h, w) / aspect(height, width) - 1.0).abs() > 0.05 {
        return Err(bad(format!(
            "it is {w}x{h}, another aspect ratio than the working size {width}x{height}"
        )));
    }
    Ok(())
}

/// Writes `metrics.json` into `dir`.
///
/// # Errors
///
/// The file cannot be written.
pub fn write_metrics(dir: &Path, metrics: &Metrics) -> Result<()> {
    let json = serde_json::to_vec_pretty(metrics).expect("metrics serialise");
    write_atomically(&dir.join(METRICS), |w| w.write_all(&json))
}
