//! The command line: its subcommands, the morph options and how they become a [`MorphConfig`]: the library's defaults (or an
//! earlier run's `config.json`), overridden by the flags given. Every default shown in
//! `--help` is read from the library, never written here.

use std::fmt::Display;
use std::path::PathBuf;

use anyhow::{Result, bail};
use clap::{Args, Parser, Subcommand};
use deepmorph::app::config::{
    DeepModel, Inputs, Model, MorphConfig, Quality, RunRecord, WorkingSize,
};
use deepmorph::eval::synthetic::Field;
use deepmorph::io::animation::{DEFAULT_QUALITY, VideoFormat};
use deepmorph::io::points::{PointPair, read_points};
use deepmorph::model::feature_model::DeepConfig;
use deepmorph::{Backend, EnergyParams};

/// `text [default: value]`.
fn default<T: Display>(text: &str, value: T) -> String {
    format!("{text} [default: {value}]")
}

/// `text [default: rgb; deep model: deep]`.
fn per_model<T: Display>(text: &str, rgb: T, deep: T) -> String {
    format!("{text} [default: {rgb}; deep model: {deep}]")
}

/// `text [default: paper; demo: demo]`.
fn per_command<T: Display>(text: &str, paper: T, demo: T) -> String {
    format!("{text} [default: {paper}; demo: {demo}]")
}

fn rgb() -> MorphConfig {
    MorphConfig::default()
}

fn deep() -> DeepConfig {
    DeepConfig::default()
}

/// The options every morph takes (`morph` and `demo`).
#[derive(Args, Clone, Debug)]
pub struct RunArgs {
    /// Output folder: new, empty, or (with --force) holding an earlier morph. It appears
    /// complete when the run ends; until then the files are in a hidden sibling folder.
    #[arg(short, long, required_unless_present = "resume")]
    output: Option<PathBuf>,
    /// Replace the morph in an existing output folder (atomically, once the new one is
    /// complete). A folder holding files deepmorph does not write is never replaced.
    #[arg(long)]
    pub force: bool,
    /// Continue the interrupted morph in DIR (Ctrl-C, SIGTERM, SIGHUP) from the checkpoint it
    /// left there, with its recorded settings and inputs, replacing it when done (a morph
    /// that was not interrupted is run again from the start).
    #[arg(long, value_name = "DIR", conflicts_with_all = ["config", "output"])]
    pub resume: Option<PathBuf>,
    /// Start from the settings (and, for `morph` without images, the inputs) of an earlier
    /// run's config.json; the flags given override them.
    #[arg(long, value_name = "FILE")]
    pub config: Option<PathBuf>,
    /// Preset of working size, levels, sweeps, feature-only sweeps and tolerance: draft (at
    /// most 128 px, 3 levels x 60 sweeps), standard (the defaults), paper (SPEC §9 at 512 px,
    /// every sweep run). Flags given beside it override its values.
    #[arg(long, value_enum)]
    quality: Option<Quality>,
    #[arg(short = 'K', long = "steps", help = per_command("Number of steps K (K+1 frames)", rgb().solver.steps, MorphConfig::demo().solver.steps))]
    steps: Option<usize>,
    #[arg(long, help = per_command("Pyramid levels", rgb().solver.levels, MorphConfig::demo().solver.levels))]
    levels: Option<usize>,
    #[arg(long, help = per_command("iPALM sweeps J per level", rgb().solver.sweeps, MorphConfig::demo().solver.sweeps))]
    sweeps: Option<usize>,
    #[arg(long, allow_negative_numbers = true, help = default("Weight 1/delta of the data term", EnergyParams::rgb().delta))]
    delta: Option<f64>,
    #[arg(long, allow_negative_numbers = true, help = per_model("Volume term weight lambda of W", EnergyParams::rgb().lambda, EnergyParams::deep().lambda))]
    lambda: Option<f64>,
    #[arg(long, allow_negative_numbers = true, help = per_model("Strain term weight mu of W", EnergyParams::rgb().mu, EnergyParams::deep().mu))]
    mu: Option<f64>,
    #[arg(long, allow_negative_numbers = true, help = default("Edge sensitivity xi1 of the anisotropy", EnergyParams::rgb().xi1))]
    xi1: Option<f64>,
    #[arg(long, allow_negative_numbers = true, help = default("Lower bound xi2 of the anisotropy", EnergyParams::rgb().xi2))]
    xi2: Option<f64>,
    #[arg(long, allow_negative_numbers = true, help = default("Pre-smoothing sigma of the anisotropy, pixels", EnergyParams::rgb().sigma))]
    sigma: Option<f64>,
    #[arg(long, allow_negative_numbers = true, help = default("Gradient smoothing rho of the anisotropy, pixels", EnergyParams::rgb().rho))]
    rho: Option<f64>,
    #[arg(long, allow_negative_numbers = true, help = default("Inertial extrapolation beta of iPALM, in [0, 1)", rgb().solver.ipalm.beta))]
    beta: Option<f64>,
    /// Run the paper's plain iPALM, without the energy safeguard of SPEC §6.
    #[arg(long)]
    no_safeguard: bool,
    #[arg(long, value_enum, help = default("Block order of a sweep: sequential (the paper's Algorithm 1) or batched (all deformations, then odd, then even frames, each as one stacked operation)", format!("{:?}", rgb().solver.ipalm.schedule).to_lowercase()))]
    schedule: Option<deepmorph::solver::ipalm::Schedule>,
    /// Landmark pairs that steer the path (SPEC §11): a CSV with the header x_a,y_a,x_b,y_b
    /// (one pair a line) or a JSON array of {"a": [x, y], "b": [x, y]}; x is the column and
    /// y the row in each image's own pixels, origin at the centre of the top-left pixel. A
    /// chain takes a `segment` column (1 = the first two images) or one --points per
    /// segment, in order.
    #[arg(long, value_name = "FILE", action = clap::ArgAction::Append)]
    points: Vec<PathBuf>,
    #[arg(long, value_name = "GAMMA", allow_negative_numbers = true, help = default("Weight gamma of the landmark term (SPEC §11; used with --points; 0 measures the points in metrics.json without steering)", rgb().solver.landmark_weight))]
    landmark_weight: Option<f64>,
    /// Start the coarsest level from a global map of A onto B (SPEC §11): from the --points
    /// by least squares when given (similarity: 2 pairs or more, affine: 3), otherwise
    /// found in the images (shifts up to 30% of each side, turns up to 30 degrees, scales
    /// 0.71-1.41, then refined). Default none.
    #[arg(long, value_enum, value_name = "MAP")]
    align: Option<deepmorph::model::alignment::AlignKind>,
    #[arg(long, value_name = "X", allow_negative_numbers = true, help = default("Stop a level once E decreased by less than X (relative) over the last 10 sweeps; 0 = run all J sweeps", rgb().solver.tolerance))]
    tol: Option<f64>,
    #[arg(long, value_enum, help = default("rgb: images compared by colour; deep: by VGG19 features (needs --vgg19; sizes are rounded to multiples of 16, at most 5 levels)", "rgb"))]
    model: Option<Model>,
    /// VGG19 weights for the deep model: an ONNX file (torchvision export or ONNX model zoo)
    /// or a safetensors file with torchvision key names.
    #[arg(long, value_name = "FILE")]
    vgg19: Option<PathBuf>,
    #[arg(long, allow_negative_numbers = true, help = default("Deep model: weight eta of the RGB channels inside the feature vector", deep().eta))]
    eta: Option<f64>,
    #[arg(long, allow_negative_numbers = true, help = default("Deep model: RMS tau each level's VGG features are scaled to (SPEC §4)", deep().feature_rms))]
    feature_rms: Option<f64>,
    #[arg(long, help = default("Deep model: feature-only sweeps J_pre after each prolongation", deep().pre_sweeps))]
    pre_sweeps: Option<usize>,
    /// Refuse to start when the estimated peak memory exceeds this many GiB [default: the
    /// memory available now].
    #[arg(long, value_name = "GIB", allow_negative_numbers = true)]
    max_memory: Option<f64>,
    #[arg(long, value_enum, help = default("Compute backend, as compiled in", rgb().backend))]
    backend: Option<Backend>,
    /// The animations play forward and back.
    #[arg(long)]
    pingpong: bool,
    #[arg(long, value_enum, value_delimiter = ',', value_name = "FORMATS", help = default("Animations to write, comma-separated: mp4 (H.264), apng (lossless), gif", VideoFormat::defaults().iter().map(|f| f.to_string()).collect::<Vec<_>>().join(",")))]
    video: Option<Vec<VideoFormat>>,
    /// Frames per second of the animations [default: as many as make the animation last 3 s].
    #[arg(long, value_name = "F")]
    fps: Option<f64>,
    #[arg(long, value_name = "Q", help = default("Quality of morph.mp4: H.264's quantiser, 0 (best) to 51 (smallest); 18 looks lossless", DEFAULT_QUALITY))]
    crf: Option<u8>,
    /// Frames of the animations (morph.mp4, morph.apng, morph.gif): N >= K + 1 frames evenly along the
    /// path, with frames rendered between the computed ones [default: K + 1].
    #[arg(long, value_name = "N")]
    frames: Option<usize>,
    /// Start from a finished morph's folder (a draft) instead of the coarsest level: its
    /// frames and deformations are prolongated to the first level larger than it, and the
    /// levels up to its size are not run. Same K; at most the working size.
    #[arg(long, value_name = "DIR")]
    init: Option<PathBuf>,
    /// Print nothing but errors.
    #[arg(short, long, conflicts_with = "verbose")]
    pub quiet: bool,
    /// One log line per sweep.
    #[arg(short, long)]
    pub verbose: bool,
}

impl RunArgs {
    /// The output folder: `-o`, or the folder `--resume` continues.
    pub fn output(&self) -> &std::path::Path {
        self.output
            .as_deref()
            .or(self.resume.as_deref())
            .expect("clap requires -o unless --resume")
    }

    /// The base settings and inputs: `--config`'s (or `--resume`'s folder's), or the
    /// library's defaults for `base`.
    fn base(&self, base: MorphConfig) -> Result<(MorphConfig, Option<Inputs>)> {
        if let Some(dir) = &self.resume
            && !dir.join("config.json").exists()
            && dir.join("segment_01").is_dir()
        {
            // A chain's folder records its segments, each a morph of its own.
            bail!(
                "{} holds a chain of morphs, which --resume cannot continue as a whole: \
                 --resume its interrupted segment's folder (segment_NN) to finish that morph, \
                 or run the chain again",
                dir.display()
            );
        }
        let recorded = self
            .config
            .clone()
            .or_else(|| self.resume.as_ref().map(|dir| dir.join("config.json")));
        Ok(match &recorded {
            Some(path) => {
                let record = RunRecord::read(path)?;
                (record.config, Some(record.inputs))
            }
            None => (base, None),
        })
    }

    /// Refuses settings that would change what a `--resume`d run computes (issue 43 #3: `-K`
    /// or `--sweeps` with `--resume` dropped the checkpoint and mixed two plans in
    /// `energy.csv`). How the outputs are written (videos, frames, backend) may change.
    fn check_resume(&self, config: &MorphConfig) -> Result<()> {
        let Some(dir) = &self.resume else {
            return Ok(());
        };
        let (recorded, _) = self.base(config.clone())?;
        let differs = [
            (
                "the solver's settings (-K, --levels, --sweeps, the energy's parameters, --tol, \
              --schedule, --landmark-weight)",
                config.solver != recorded.solver,
            ),
            (
                "the model (--model, --vgg19, --eta, --feature-rms, --pre-sweeps)",
                config.deep != recorded.deep,
            ),
            (
                "the working size (--size, --max-side, --quality)",
                config.size != recorded.size,
            ),
            ("the landmarks (--points)", config.points != recorded.points),
            ("the alignment (--align)", config.align != recorded.align),
            ("the draft (--init)", config.init != recorded.init),
        ];
        if let Some((what, _)) = differs.iter().find(|(_, changed)| *changed) {
            bail!(
                "--resume continues the run recorded in {} with its own settings, but {what} \
                 differ: give no such option, or start a new morph",
                dir.display()
            );
        }
        Ok(())
    }

    /// The settings of this morph and the inputs of `--config`, if any: `base` (the
    /// library's defaults of the command) or the `--config` file's, overridden by every flag
    /// given.
    pub fn resolve(&self, base: MorphConfig) -> Result<(MorphConfig, Option<Inputs>)> {
        let (mut config, inputs) = self.base(base)?;
        let model = self.model.unwrap_or(config.model());
        match (model, &self.vgg19) {
            (Model::Rgb, Some(_)) => bail!("--vgg19 is used only by --model deep"),
            (Model::Rgb, None) if config.deep.is_some() => {
                config.deep = None;
                config.solver.params.lambda = EnergyParams::rgb().lambda;
                config.solver.params.mu = EnergyParams::rgb().mu;
            }
            (Model::Deep, vgg19) => {
                let Some(vgg19) = vgg19
                    .clone()
                    .or_else(|| config.deep.as_ref().map(|d| d.vgg19.clone()))
                else {
                    bail!(
                        "--model deep needs VGG19 weights: --vgg19 FILE (an ONNX or safetensors \
                         VGG19; see the README for where to get one)"
                    );
                };
                if config.deep.is_none() {
                    config.solver.params.lambda = EnergyParams::deep().lambda;
                    config.solver.params.mu = EnergyParams::deep().mu;
                }
                let features = config.deep.map_or_else(DeepConfig::default, |d| d.features);
                config.deep = Some(DeepModel { vgg19, features });
            }
            (Model::Rgb, None) => {}
        }
        if let Some(quality) = self.quality {
            quality.apply(&mut config);
        }
        let solver = &mut config.solver;
        let set = |target: &mut usize, value: Option<usize>| {
            if let Some(v) = value {
                *target = v;
            }
        };
        set(&mut solver.steps, self.steps);
        set(&mut solver.levels, self.levels);
        set(&mut solver.sweeps, self.sweeps);
        let params = &mut solver.params;
        for (target, value) in [
            (&mut params.delta, self.delta),
            (&mut params.lambda, self.lambda),
            (&mut params.mu, self.mu),
            (&mut params.xi1, self.xi1),
            (&mut params.xi2, self.xi2),
            (&mut params.sigma, self.sigma),
            (&mut params.rho, self.rho),
            (&mut solver.ipalm.beta, self.beta),
        ] {
            if let Some(v) = value {
                *target = v;
            }
        }
        if self.no_safeguard {
            solver.ipalm.safeguard = false;
        }
        solver.ipalm.schedule = self.schedule.unwrap_or(solver.ipalm.schedule);
        solver.tolerance = self.tol.unwrap_or(solver.tolerance);
        solver.landmark_weight = self.landmark_weight.unwrap_or(solver.landmark_weight);
        config.align = self.align.unwrap_or(config.align);
        config.points = match self.points.as_slice() {
            [] => config.points,
            [one] => Some(read_points(one)?),
            files => {
                let mut all = Vec::new();
                for (i, path) in files.iter().enumerate() {
                    let pairs = read_points(path)?;
                    if pairs.iter().any(|p| p.segment.is_some()) {
                        bail!(
                            "{}: a file of one segment (one --points per segment) takes no \
                             segment column",
                            path.display()
                        );
                    }
                    all.extend(pairs.into_iter().map(|p| PointPair {
                        segment: Some(i + 1),
                        ..p
                    }));
                }
                Some(all)
            }
        };
        if let Some(deep) = &mut config.deep {
            let f = &mut deep.features;
            f.eta = self.eta.unwrap_or(f.eta);
            f.feature_rms = self.feature_rms.unwrap_or(f.feature_rms);
            f.pre_sweeps = self.pre_sweeps.unwrap_or(f.pre_sweeps);
        } else if self.eta.is_some() || self.feature_rms.is_some() || self.pre_sweeps.is_some() {
            bail!("--eta, --feature-rms and --pre-sweeps are used only by --model deep");
        }
        if let Some(gib) = self.max_memory {
            if !(gib.is_finite() && gib > 0.0) {
                bail!("invalid --max-memory {gib}: must be a number of GiB > 0");
            }
            config.max_memory_gib = Some(gib);
        }
        config.backend = self.backend.unwrap_or(config.backend);
        config.pingpong |= self.pingpong;
        if let Some(formats) = &self.video {
            let mut formats = formats.clone();
            formats.sort();
            formats.dedup();
            config.video = formats;
        }
        config.fps = self.fps.or(config.fps);
        config.crf = self.crf.unwrap_or(config.crf);
        config.animation_frames = self.frames.or(config.animation_frames);
        config.init = self.init.clone().or(config.init);
        Ok((config, inputs))
    }
}

/// What a `morph` or `demo` command asks for, its settings resolved.
pub(crate) enum Request {
    /// One morph of two images (or the demo's, or the recorded ones).
    Single(MorphConfig, Inputs, RunArgs),
    /// A chain through three images or more.
    Chain(MorphConfig, Vec<PathBuf>, RunArgs),
}

/// The request of `deepmorph morph IMAGES…` with its options.
pub(crate) fn morph_request(
    mut images: Vec<PathBuf>,
    size: Option<(usize, usize)>,
    max_side: Option<usize>,
    run: RunArgs,
) -> Result<Request> {
    let (mut config, recorded) = run.resolve(MorphConfig::default())?;
    config.size = working_size(size, max_side, config.size);
    if run.resume.is_some() && !images.is_empty() {
        bail!("--resume continues the recorded morph: give no images");
    }
    run.check_resume(&config)?;
    if run.points.len() > 1 && run.points.len() + 1 != images.len() {
        bail!(
            "{} --points files for {} images: give one per consecutive pair of images ({} \
             here), or one file with a segment column",
            run.points.len(),
            images.len(),
            images.len().saturating_sub(1)
        );
    }
    let inputs = match (images.len(), recorded) {
        (0, Some(recorded)) => recorded,
        (2, _) => {
            let b = images.pop().expect("two images");
            let a = images.pop().expect("two images");
            Inputs::Files { a, b }
        }
        (3.., _) => return Ok(Request::Chain(config, images, run)),
        _ => bail!(
            "morph needs two images A and B, more for a chain, or --config with a run's \
             config.json"
        ),
    };
    Ok(Request::Single(config, inputs, run))
}

/// The request of `deepmorph demo` with its options.
pub(crate) fn demo_request(size: Option<usize>, run: RunArgs) -> Result<Request> {
    let (mut config, _) = run.resolve(MorphConfig::demo())?;
    if let Some(side) = size {
        config.size = WorkingSize::Exact {
            height: side,
            width: side,
        };
    }
    run.check_resume(&config)?;
    Ok(Request::Single(config, Inputs::Demo, run))
}

/// `WxH` → `(H, W)`.
pub fn parse_size(s: &str) -> std::result::Result<(usize, usize), String> {
    let bad = || format!("`{s}` is not WxH (e.g. 256x192)");
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let parse = |v: &str| v.trim().parse::<usize>().map_err(|_| bad());
    Ok((parse(h)?, parse(w)?))
}

/// The working size of `morph`: `--size`, else `--max-side`, else the base config's.
pub fn working_size(
    size: Option<(usize, usize)>,
    max_side: Option<usize>,
    base: WorkingSize,
) -> WorkingSize {
    match (size, max_side) {
        (Some((height, width)), _) => WorkingSize::Exact { height, width },
        (None, Some(max_side)) => WorkingSize::Fit { max_side },
        (None, None) => base,
    }
}

#[derive(Parser)]
#[command(
    name = "deepmorph",
    version,
    about = "Image morphing as a time-discrete geodesic in the metamorphosis model"
)]
pub(crate) struct Cli {
    #[command(subcommand)]
    pub(crate) command: Command,
}

#[derive(Subcommand)]
pub(crate) enum Command {
    /// Morph image A into image B (or through a chain of images).
    Morph {
        /// The images: A and B (any common format; alpha dropped, grey expanded to RGB; B
        /// resized to A's working size if it differs), or more for a chain: each consecutive
        /// pair is morphed into OUT/segment_01, OUT/segment_02, ..., and OUT/morph.mp4 (.apng,
        /// .gif) plays the whole chain. With --config and no images: the recorded ones.
        #[arg(value_name = "IMAGES")]
        images: Vec<PathBuf>,
        /// Working size WxH (each a multiple of 2^(levels-1), and of 16 for the deep model).
        #[arg(long, value_parser = parse_size, conflicts_with = "max_side")]
        size: Option<(usize, usize)>,
        /// Longest side of the working size when --size is not given [default: 256].
        #[arg(long)]
        max_side: Option<usize>,
        #[command(flatten)]
        run: RunArgs,
    },
    /// Morph a built-in synthetic pair (shapes that move, turn and change colour); about a
    /// minute on 2 CPU cores.
    Demo {
        /// Side of the square demo images [default: 96].
        #[arg(long)]
        size: Option<usize>,
        #[command(flatten)]
        run: RunArgs,
    },
    /// Quality numbers of a finished morph (composed map, det J, energy split, warp
    /// consistency, endpoint error against a ground truth); with --write, also into the folder.
    Eval {
        /// A morph's output directory.
        dir: PathBuf,
        /// Ground truth for the first image: a Middlebury disparity PNG (16-bit, d x 256,
        /// 0 = unknown) or a Middlebury .flo flow file, at the input image's size.
        #[arg(long)]
        truth: Option<PathBuf>,
        /// Accept a ground truth of another size than the first input, scaled to the morph.
        #[arg(long)]
        resample_truth: bool,
        /// VGG19 weights (as for --model deep): also measure the path in VGG19 feature space
        /// (deep morphs record it in metrics.json themselves).
        #[arg(long, value_name = "FILE")]
        vgg19: Option<PathBuf>,
        /// Landmark pairs to measure |Phi(p) - q| on (as for --points, in the inputs' own
        /// pixels) instead of the run's own: held-out points, or a run made without any.
        #[arg(long, value_name = "FILE")]
        points: Option<PathBuf>,
        /// Write metrics.json and the composed map (composed.json, composed.f32) into DIR.
        #[arg(long)]
        write: bool,
        /// Compute backend, as compiled in.
        #[arg(long, value_enum)]
        backend: Option<Backend>,
        /// Print only errors.
        #[arg(short, long)]
        quiet: bool,
    },
    /// Make a synthetic pair with a known deformation: OUT/a.png = IMAGE warped,
    /// OUT/b.png = IMAGE, OUT/truth.flo = the correspondence of a to b.
    Warp {
        /// The image to warp.
        image: PathBuf,
        /// smooth: a swirl, AMOUNT = largest displacement in pixels; rotate: AMOUNT degrees
        /// at the centre; shear: AMOUNT columns per row at the centre. All fade out to the
        /// fixed border.
        #[arg(long, value_enum, default_value_t = Field::Smooth)]
        field: Field,
        /// Size of the deformation (see --field).
        #[arg(long, allow_negative_numbers = true)]
        amount: f64,
        /// Output folder: new, empty, or (with --force) holding an earlier pair.
        #[arg(short, long)]
        output: PathBuf,
        /// Replace the pair in an existing output folder.
        #[arg(long)]
        force: bool,
        /// Compute backend, as compiled in.
        #[arg(long, value_enum)]
        backend: Option<Backend>,
    },
}
