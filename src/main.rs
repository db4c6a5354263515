//! `deepmorph`: morph one image into another along a time-discrete geodesic.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use deepmorph::deep::{DeepConfig, DeepFeatures};
use deepmorph::eval::MorphFolder;
use deepmorph::io::{RgbImage, write_atomically, write_png};
use deepmorph::memory;
use deepmorph::metrics::Metrics;
use deepmorph::multilevel::{FeatureModel, Multilevel, MultilevelConfig, Termination, fit_size};
use deepmorph::observe::{EnergyLog, Progress, Verbosity};
use deepmorph::optim::ipalm::IpalmConfig;
use deepmorph::output::{
    CONFIG, DeepRecord, METRICS, RunRecord, contact_sheet, output_names, save_composed,
    save_deformations, write_frames, write_gif,
};
use deepmorph::synthetic::{Field, warped_pair};
use deepmorph::truth::Correspondence;
use deepmorph::vgg::Vgg19;
use deepmorph::{Backend, EnergyParams, Grid, Precision};

/// The solver allocates and frees tensors of megabytes many times per sweep. glibc's malloc
/// hands such blocks back to the kernel each time, and the next allocation page-faults them in
/// again: a third of a deep sweep's time at 128² went to page faults. mimalloc keeps them.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
#[command(
    name = "deepmorph",
    version,
    about = "Image morphing as a time-discrete geodesic in the metamorphosis model"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Morph image A into image B.
    Morph {
        /// The first image (any common format; alpha dropped, grey expanded to RGB).
        a: PathBuf,
        /// The last image (resized to A's working size if it differs).
        b: PathBuf,
        /// Working size WxH (each a multiple of 2^(levels-1)); default: A's size scaled to --max-side.
        #[arg(long, value_parser = parse_size, conflicts_with = "max_side")]
        size: Option<(usize, usize)>,
        /// Longest side of the working size when --size is not given.
        #[arg(long, default_value_t = 256)]
        max_side: usize,
        #[command(flatten)]
        run: RunArgs,
    },
    /// Morph a built-in synthetic pair (shapes that move, turn and change colour); about a minute on 2 CPU cores.
    Demo {
        /// Side of the square demo images.
        #[arg(long, default_value_t = 96)]
        size: usize,
        #[command(flatten)]
        run: RunArgs,
    },
    /// Quality numbers of a finished morph (composed map, det J, energy split, warp
    /// consistency, endpoint error against a ground truth); writes DIR/metrics.json.
    Eval {
        /// A morph's output directory.
        dir: PathBuf,
        /// Ground truth for the first image: a Middlebury disparity PNG (16-bit, d x 256,
        /// 0 = unknown) or a Middlebury .flo flow file, at the input image's size.
        #[arg(long)]
        truth: Option<PathBuf>,
        /// Compute backend (flex, ndarray or wgpu, as compiled in).
        #[arg(long)]
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
        #[arg(long, default_value = "smooth")]
        field: Field,
        /// Size of the deformation (see --field).
        #[arg(long, allow_negative_numbers = true)]
        amount: f64,
        /// Output directory (created if needed).
        #[arg(short, long)]
        output: PathBuf,
        /// Compute backend (flex, ndarray or wgpu, as compiled in).
        #[arg(long)]
        backend: Option<Backend>,
    },
}

#[derive(Args, Clone)]
struct RunArgs {
    /// Output directory (created if needed).
    #[arg(short, long)]
    output: PathBuf,
    /// Number of steps K (K+1 frames) [default: 15; demo: 10].
    #[arg(short = 'K', long = "steps")]
    steps: Option<usize>,
    /// Pyramid levels [default: 5; demo: 3].
    #[arg(long)]
    levels: Option<usize>,
    /// iPALM sweeps J per level [default: 250; demo: 60].
    #[arg(long)]
    sweeps: Option<usize>,
    /// Weight 1/delta of the data term.
    #[arg(long, default_value_t = 1.0, allow_negative_numbers = true)]
    delta: f64,
    /// Volume term weight lambda of W [default: 0.1; deep model: 0.002].
    #[arg(long, allow_negative_numbers = true)]
    lambda: Option<f64>,
    /// Strain term weight mu of W [default: 0.025; deep model: 0.002].
    #[arg(long, allow_negative_numbers = true)]
    mu: Option<f64>,
    /// Edge sensitivity xi1 of the anisotropy.
    #[arg(long, default_value_t = 1000.0, allow_negative_numbers = true)]
    xi1: f64,
    /// Lower bound xi2 of the anisotropy.
    #[arg(long, default_value_t = 1e-6, allow_negative_numbers = true)]
    xi2: f64,
    /// Pre-smoothing sigma of the anisotropy, pixels.
    #[arg(long, default_value_t = 0.5, allow_negative_numbers = true)]
    sigma: f64,
    /// Gradient smoothing rho of the anisotropy, pixels.
    #[arg(long, default_value_t = 2.0, allow_negative_numbers = true)]
    rho: f64,
    /// Inertial extrapolation beta of iPALM, in [0, 1).
    #[arg(long, default_value_t = std::f64::consts::FRAC_1_SQRT_2, allow_negative_numbers = true)]
    beta: f64,
    /// Run the paper's plain iPALM, without the energy safeguard of SPEC §6.
    #[arg(long)]
    no_safeguard: bool,
    /// rgb: images compared by colour; deep: by VGG19 features (needs --vgg19; sizes are
    /// rounded to multiples of 16, at most 5 levels).
    #[arg(long, default_value = "rgb", value_parser = ["rgb", "deep"])]
    model: String,
    /// VGG19 weights for the deep model: an ONNX file (torchvision export or ONNX model zoo)
    /// or a safetensors file with torchvision key names.
    #[arg(long, value_name = "FILE")]
    vgg19: Option<PathBuf>,
    /// Deep model: weight eta of the RGB channels inside the feature vector.
    #[arg(long, default_value_t = 1e-6, allow_negative_numbers = true)]
    eta: f64,
    /// Deep model: RMS tau each level's VGG features are scaled to (SPEC §4).
    #[arg(long, default_value_t = 0.1, allow_negative_numbers = true)]
    feature_rms: f64,
    /// Deep model: feature-only sweeps J_pre after each prolongation.
    #[arg(long, default_value_t = 50)]
    pre_sweeps: usize,
    /// Refuse to start when the estimated peak memory exceeds this many GiB [default: the
    /// memory available now].
    #[arg(long, value_name = "GIB", allow_negative_numbers = true)]
    max_memory: Option<f64>,
    /// Compute backend (flex, ndarray or wgpu, as compiled in).
    #[arg(long)]
    backend: Option<Backend>,
    /// The GIF plays forward and back.
    #[arg(long)]
    pingpong: bool,
    /// Print nothing but errors.
    #[arg(short, long, conflicts_with = "verbose")]
    quiet: bool,
    /// One log line per sweep.
    #[arg(short, long)]
    verbose: bool,
}

/// The paper's K, levels and J (SPEC §9).
const PAPER: (usize, usize, usize) = (15, 5, 250);
/// The demo's K, levels and J: about a minute on 2 CPU cores.
const DEMO: (usize, usize, usize) = (10, 3, 60);

impl RunArgs {
    /// Fills the unset K, levels and J from `defaults`.
    fn with_defaults(mut self, (steps, levels, sweeps): (usize, usize, usize)) -> Self {
        self.steps.get_or_insert(steps);
        self.levels.get_or_insert(levels);
        self.sweeps.get_or_insert(sweeps);
        self
    }

    fn steps(&self) -> usize {
        self.steps.expect("resolved by with_defaults")
    }

    fn levels(&self) -> usize {
        self.levels.expect("resolved by with_defaults")
    }

    fn sweeps(&self) -> usize {
        self.sweeps.expect("resolved by with_defaults")
    }

    /// The model's own checks, before any image is read.
    fn check_model(&self) -> Result<()> {
        if self.deep() {
            if self.vgg19.is_none() {
                bail!(
                    "--model deep needs VGG19 weights: --vgg19 FILE (an ONNX or safetensors \
                     VGG19; see the README for where to get one)"
                );
            }
            if self.levels() > 5 {
                bail!(
                    "--levels {} is out of range for --model deep: at most 5 (VGG19 has taps at \
                     1, 1/2, 1/4, 1/8 and 1/16 of the input size)",
                    self.levels()
                );
            }
        } else if self.vgg19.is_some() {
            bail!("--vgg19 is used only by --model deep");
        }
        Ok(())
    }

    fn deep(&self) -> bool {
        self.model == "deep"
    }

    /// The SPEC §9 energy parameters of the chosen model, overridden by the flags given.
    fn params(&self) -> EnergyParams {
        let defaults = if self.deep() {
            EnergyParams::deep()
        } else {
            EnergyParams::rgb()
        };
        EnergyParams {
            lambda: self.lambda.unwrap_or(defaults.lambda),
            mu: self.mu.unwrap_or(defaults.mu),
            delta: self.delta,
            sigma: self.sigma,
            rho: self.rho,
            xi1: self.xi1,
            xi2: self.xi2,
        }
    }

    /// The side multiple of the working size: `2^(levels−1)`, and 16 in the deep model
    /// (VGG19's four max-pools must halve exactly).
    fn size_levels(&self) -> usize {
        if self.deep() {
            self.levels().max(5)
        } else {
            self.levels()
        }
    }
}

fn parse_size(s: &str) -> std::result::Result<(usize, usize), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("`{s}` is not WxH (e.g. 256x192)"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<usize>()
            .map_err(|_| format!("`{s}` is not WxH (e.g. 256x192)"))
    };
    Ok((parse(h)?, parse(w)?))
}

/// Exit status of a morph stopped by a NaN or infinity in the optimisation; its outputs were
/// written from the last finite iterate.
const EXIT_NONFINITE: i32 = 3;
/// Exit status of a morph stopped by Ctrl-C; its outputs were written.
const EXIT_INTERRUPTED: i32 = 130;

/// `DEEPMORPH_INJECT_NONFINITE=LEVEL:SWEEP` makes the solver meet a NaN after that sweep: the
/// tests' way to check the non-finite path end to end (outputs written, exit status 3).
fn injected_fault() -> Result<Option<(usize, usize)>> {
    let Some(value) = std::env::var_os("DEEPMORPH_INJECT_NONFINITE") else {
        return Ok(None);
    };
    let value = value.to_string_lossy();
    let parsed = value
        .split_once(':')
        .and_then(|(l, s)| Some((l.trim().parse().ok()?, s.trim().parse().ok()?)));
    match parsed {
        Some(fault) => Ok(Some(fault)),
        None => bail!("DEEPMORPH_INJECT_NONFINITE={value} is not LEVEL:SWEEP"),
    }
}

fn main() {
    if let Err(e) = run(Cli::parse()) {
        eprintln!("Error: {e:#}");
        std::process::exit(1);
    }
}

fn run(cli: Cli) -> Result<()> {
    let (inputs, pair, args, command) = match cli.command {
        Command::Eval {
            dir,
            truth,
            backend,
            quiet,
        } => return eval(&dir, truth.as_deref(), backend, quiet),
        Command::Warp {
            image,
            field,
            amount,
            output,
            backend,
        } => return warp(&image, field, amount, &output, backend),
        Command::Morph {
            a,
            b,
            size,
            max_side,
            run,
        } => {
            let run = run.with_defaults(PAPER);
            let image_a = RgbImage::load(&a)?;
            let image_b = RgbImage::load(&b)?;
            run.check_model()?;
            let (h, w) = working_size(&image_a, size, max_side, run.size_levels())?;
            let resize = |img: &RgbImage, name: &str| {
                if (img.height(), img.width()) != (h, w) {
                    if !run.quiet {
                        eprintln!(
                            "{name}: {}x{} resized to the working size {w}x{h}",
                            img.width(),
                            img.height()
                        );
                    }
                    img.resized(h, w)
                } else {
                    img.clone()
                }
            };
            let pair = (resize(&image_a, "A"), resize(&image_b, "B"));
            (vec![a, b], pair, run, "morph")
        }
        Command::Demo { size, run } => {
            let run = run.with_defaults(DEMO);
            run.check_model()?;
            working_size_fits(size, size, run.size_levels())?;
            (Vec::new(), deepmorph::demo::demo_pair(size), run, "demo")
        }
    };
    morph(command, &inputs, pair, &args)
}

/// The working size: `--size`, or A's size scaled so its longest side is at most `max_side`,
/// rounded to multiples of `2^(levels−1)`.
fn working_size(
    a: &RgbImage,
    size: Option<(usize, usize)>,
    max_side: usize,
    levels: usize,
) -> Result<(usize, usize)> {
    check_levels(levels)?;
    let factor = 1usize << (levels - 1);
    if let Some((h, w)) = size {
        working_size_fits(h, w, levels)?;
        return Ok((h, w));
    }
    if max_side < 4 * factor {
        bail!(
            "--max-side {max_side} is too small for --levels {levels}: must be at least {}",
            4 * factor
        );
    }
    Ok(fit_size(a.height(), a.width(), max_side, levels))
}

fn check_levels(levels: usize) -> Result<()> {
    if levels == 0 || levels > 12 {
        bail!("--levels {levels} is out of range: must be in 1..=12");
    }
    Ok(())
}

/// Checks that an explicit working size suits the pyramid.
fn working_size_fits(h: usize, w: usize, levels: usize) -> Result<()> {
    check_levels(levels)?;
    let factor = 1usize << (levels - 1);
    if h % factor != 0 || w % factor != 0 || h < 4 * factor || w < 4 * factor {
        bail!(
            "--size {w}x{h} does not fit the pyramid: both sides must be multiples of {factor} \
             (2^(levels-1), and 16 for the deep model) and at least {}",
            4 * factor
        );
    }
    Ok(())
}

fn backend_or_default(backend: Option<Backend>) -> Result<Backend> {
    match backend {
        Some(b) => Ok(b),
        None => Backend::default_compiled().context("no backend compiled into this build"),
    }
}

/// `deepmorph eval`: reads a morph's folder, prints its metrics and writes `metrics.json`.
fn eval(dir: &Path, truth: Option<&Path>, backend: Option<Backend>, quiet: bool) -> Result<()> {
    let device = backend_or_default(backend)?.device_for(Precision::F32)?;
    let folder = MorphFolder::read(dir, &device)?;
    let truth = truth
        .map(|path| Correspondence::load(path).map(|t| (t, path.display().to_string())))
        .transpose()?;
    let composed = folder.composed();
    save_composed(dir, composed.clone())?;
    let metrics = folder.metrics(composed, truth.as_ref().map(|(t, name)| (t, name.as_str())))?;
    write_metrics(dir, &metrics)?;
    if !quiet {
        print!("{metrics}");
    }
    Ok(())
}

fn write_metrics(dir: &Path, metrics: &Metrics) -> Result<()> {
    let json = serde_json::to_vec_pretty(metrics)?;
    write_atomically(&dir.join(METRICS), |w| w.write_all(&json))?;
    Ok(())
}

/// `deepmorph warp`: a synthetic pair with a known correspondence.
fn warp(
    image: &Path,
    field: Field,
    amount: f64,
    out: &Path,
    backend: Option<Backend>,
) -> Result<()> {
    let input = RgbImage::load(image)?;
    let device = backend_or_default(backend)?.device_for(Precision::F32)?;
    let (warped, truth) = warped_pair(&input, field, amount, &device)?;
    let out = prepare_output(
        out,
        &[image.to_path_buf()],
        &["a.png", "b.png", "truth.flo"],
    )?;
    write_png(&out.join("a.png"), &warped.to_rgb8())?;
    write_png(&out.join("b.png"), &input.to_rgb8())?;
    truth.write_flo(&out.join("truth.flo"))?;
    eprintln!(
        "wrote a.png ({field} {amount} applied to {}), b.png and truth.flo ({}x{}) to {}",
        image.display(),
        input.width(),
        input.height(),
        out.display()
    );
    Ok(())
}

fn morph(
    command: &str,
    inputs: &[PathBuf],
    (a, b): (RgbImage, RgbImage),
    args: &RunArgs,
) -> Result<()> {
    let backend = backend_or_default(args.backend)?;
    let params = args.params();
    let config = MultilevelConfig {
        steps: args.steps(),
        levels: args.levels(),
        sweeps: args.sweeps(),
        params,
        ipalm: IpalmConfig {
            beta: args.beta,
            safeguard: !args.no_safeguard,
            ..IpalmConfig::default()
        },
        ..MultilevelConfig::default()
    };
    let mut driver = Multilevel::new(config).map_err(|e| anyhow::anyhow!("{e}"))?;
    if let Some((level, sweep)) = injected_fault()? {
        driver = driver.inject_nonfinite(level, sweep);
    }
    let estimate = check_memory(args, backend, a.height(), a.width())?;
    let out = prepare_output(&args.output, inputs, &output_names(args.steps()))?;

    let precision = Precision::F32;
    let device = backend.device_for(precision)?.autodiff();
    let grid = Grid::new(a.height(), a.width(), &device, precision.dtype())?;
    let (u_a, u_b) = (a.to_tensor(&grid)?, b.to_tensor(&grid)?);
    let deep_config = DeepConfig {
        eta: args.eta,
        feature_rms: args.feature_rms,
        pre_sweeps: args.pre_sweeps,
    };
    let model = match &args.vgg19 {
        Some(path) if args.deep() => {
            deep_config.validate().map_err(|e| anyhow::anyhow!("{e}"))?;
            let vgg = Vgg19::load(path, &device)?;
            FeatureModel::Deep(DeepFeatures::new(
                &vgg,
                u_a.clone(),
                u_b.clone(),
                deep_config,
            )?)
        }
        _ => FeatureModel::Rgb,
    };

    let interrupt = Arc::new(AtomicBool::new(false));
    {
        let flag = Arc::clone(&interrupt);
        ctrlc::set_handler(move || {
            if flag.swap(true, Ordering::SeqCst) {
                std::process::exit(130); // a second Ctrl-C does not wait
            }
            eprintln!("\ninterrupted: stopping after this sweep and writing the outputs (Ctrl-C again to abort)");
        })
        .context("installing the Ctrl-C handler")?;
    }
    let verbosity = if args.quiet {
        Verbosity::Quiet
    } else if args.verbose {
        Verbosity::Verbose
    } else {
        Verbosity::Normal
    };
    if !args.quiet {
        eprintln!(
            "{command}: {} model, {}x{} (WxH), K = {}, {} levels x {} sweeps, {} backend, about {:.1} GiB",
            args.model,
            a.width(),
            a.height(),
            args.steps(),
            args.levels(),
            args.sweeps(),
            backend,
            memory::gib(estimate)
        );
    }
    let started = Instant::now();
    let mut progress = Progress::new(verbosity);
    let mut log = EnergyLog::default();
    let mut observers = (&mut progress, &mut log);
    let morph = driver.run_with(&device, u_a, u_b, &model, &mut observers, &interrupt)?;
    drop(progress);
    let seconds = started.elapsed().as_secs_f64();

    let frames = morph
        .images()
        .into_iter()
        .map(RgbImage::from_tensor)
        .collect::<deepmorph::Result<Vec<_>>>()?;
    write_frames(&out, &frames)?;
    write_gif(&out.join("morph.gif"), &frames, args.pingpong, 3.0)?;
    let k = args.steps();
    let displacement = morph.state.deformations() - morph.grid.identity(k);
    let sheet = contact_sheet(&frames, morph.anisotropy.clone(), displacement)?;
    write_png(&out.join("sheet.png"), &sheet)?;
    save_deformations(&out, morph.state.deformations())?;
    let csv = log.to_csv();
    write_atomically(&out.join("energy.csv"), |w| w.write_all(csv.as_bytes()))?;
    let termination = morph.termination.to_string();
    let record = RunRecord {
        program: "deepmorph".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        command: command.into(),
        inputs: inputs.iter().map(|p| p.display().to_string()).collect(),
        working_size: [a.height(), a.width()],
        model: args.model.clone(),
        backend: backend.to_string(),
        precision: "f32".into(),
        steps: k,
        levels: args.levels(),
        sweeps: args.sweeps(),
        delta: args.delta,
        lambda: params.lambda,
        mu: params.mu,
        sigma: args.sigma,
        rho: args.rho,
        xi1: args.xi1,
        xi2: args.xi2,
        beta: args.beta,
        safeguard: !args.no_safeguard,
        pingpong: args.pingpong,
        deep: match (&model, &args.vgg19) {
            (FeatureModel::Deep(deep), Some(path)) => Some(DeepRecord {
                vgg19: path.display().to_string(),
                eta: deep_config.eta,
                feature_rms: deep_config.feature_rms,
                pre_sweeps: deep_config.pre_sweeps,
                tap_rms: deep.rms().to_vec(),
            }),
            _ => None,
        },
        termination: termination.clone(),
        seconds,
    };
    let json = serde_json::to_vec_pretty(&record)?;
    write_atomically(&out.join(CONFIG), |w| w.write_all(&json))?;
    // The same numbers `deepmorph eval` computes, from the files just written.
    let folder = MorphFolder::read(&out, &backend.device_for(precision)?)?;
    let composed = folder.composed();
    save_composed(&out, composed.clone())?;
    let metrics = folder.metrics(composed, None)?;
    write_metrics(&out, &metrics)?;
    if let Termination::NonFinite { .. } = morph.termination {
        eprintln!(
            "Error: {termination}; wrote every output from that iterate to {}",
            out.display()
        );
        std::process::exit(EXIT_NONFINITE);
    }
    if !args.quiet {
        let last = log.records.last().map_or(f64::NAN, |r| r.energy);
        eprintln!(
            "{termination} in {seconds:.1} s, final E = {last:.6e}; wrote {} frames, morph.gif, sheet.png, deformations, composed map, energy.csv, config.json, metrics.json to {}",
            k + 1,
            out.display()
        );
        if args.verbose {
            eprint!("{metrics}");
        }
    }
    if matches!(morph.termination, Termination::Interrupted { .. }) {
        std::process::exit(EXIT_INTERRUPTED);
    }
    Ok(())
}

/// Refuses a morph whose estimated peak memory exceeds `--max-memory`, or on a CPU backend
/// the memory available now, before anything large is allocated.
fn check_memory(args: &RunArgs, backend: Backend, h: usize, w: usize) -> Result<u64> {
    let channels = if args.deep() { 3 + 64 } else { 3 };
    let estimate = memory::estimate_peak_bytes(h, w, args.steps(), channels, args.deep());
    let limit = match args.max_memory {
        Some(gib) if gib.is_finite() && gib > 0.0 => {
            Some(((gib * (1u64 << 30) as f64) as u64, "--max-memory"))
        }
        Some(gib) => bail!("invalid --max-memory {gib}: must be a number of GiB > 0"),
        // On wgpu the tensors live in GPU memory, which the host cannot see.
        None if backend != Backend::Wgpu => {
            memory::available_bytes().map(|b| (b, "available memory"))
        }
        None => None,
    };
    if let Some((limit, what)) = limit
        && estimate > limit
    {
        bail!(
            "this morph needs about {:.1} GiB ({w}x{h}, K = {}, {} model) but the {what} is {:.1} GiB: \
             use a smaller --size or --max-side, fewer steps -K, or raise --max-memory",
            memory::gib(estimate),
            args.steps(),
            args.model,
            memory::gib(limit)
        );
    }
    Ok(estimate)
}

/// Creates the output directory and refuses one whose outputs would overwrite an input.
fn prepare_output(out: &Path, inputs: &[PathBuf], names: &[impl AsRef<str>]) -> Result<PathBuf> {
    std::fs::create_dir_all(out)
        .with_context(|| format!("cannot create the output directory {}", out.display()))?;
    let out_dir = out
        .canonicalize()
        .with_context(|| format!("cannot resolve {}", out.display()))?;
    for input in inputs {
        let Ok(input_path) = input.canonicalize() else {
            continue;
        };
        let name = input_path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned());
        if input_path.parent() == Some(out_dir.as_path())
            && name
                .as_ref()
                .is_some_and(|n| names.iter().any(|m| m.as_ref() == n))
        {
            bail!(
                "the output directory {} would overwrite the input {}: choose another -o",
                out.display(),
                input.display()
            );
        }
    }
    Ok(out_dir)
}
