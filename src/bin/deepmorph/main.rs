//! `deepmorph`: morph one image into another along a time-discrete geodesic.
//!
//! The library does the work ([`deepmorph::app`]); this program parses arguments, shows
//! progress, turns Ctrl-C, SIGTERM and SIGHUP into a clean stop, and maps outcomes to exit codes.

mod args;
mod progress;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use anyhow::{Context, Result};
use clap::Parser;
use deepmorph::app::chain::ChainJob;
use deepmorph::app::config::{Inputs, MorphConfig};
use deepmorph::app::evaluate::evaluate;
use deepmorph::app::job::{MorphJob, write_metrics};
use deepmorph::app::memory;
use deepmorph::eval::synthetic::{Field, warped_pair};
use deepmorph::io::images::{RgbImage, write_png};
use deepmorph::io::output_folder::OutputFolder;
use deepmorph::io::outputs::save_composed;
use deepmorph::solver::observer::{Observer, Phase, SweepEvent, Termination};
use deepmorph::{Backend, Precision};

use args::{Cli, Command, RunArgs, working_size};
use progress::{Progress, Verbosity};

/// The solver allocates and frees tensors of megabytes many times per sweep. glibc's malloc
/// hands such blocks back to the kernel each time, and the next allocation page-faults them in
/// again: a third of a deep sweep's time at 128² went to page faults. mimalloc keeps them.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Held while a morph's outputs are written: the signal handler's abort waits for no one and
/// must not remove the staging folder under the writer.
static WRITING: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Exit status of an error: bad input, unreadable or unwritable files, no backend.
const EXIT_ERROR: i32 = 1;
/// Exit status of a morph stopped by a NaN or infinity in the optimisation; its outputs were
/// written from the last finite iterate. (clap's usage errors exit with 2.)
const EXIT_NONFINITE: i32 = 3;
/// Exit status of a morph stopped by Ctrl-C or SIGTERM; its outputs were written.
const EXIT_INTERRUPTED: i32 = 130;

fn main() {
    let cli = Cli::parse();
    let code = deepmorph::backend::on_a_worker(|| run(cli)).unwrap_or_else(|e| {
        eprintln!("Error: {e:#}");
        EXIT_ERROR
    });
    std::process::exit(code);
}

fn run(cli: Cli) -> Result<i32> {
    let (config, inputs, run) = match cli.command {
        Command::Eval {
            dir,
            truth,
            resample_truth,
            vgg19,
            write,
            backend,
            quiet,
        } => {
            let device = backend_or_default(backend).device_for(Precision::F32)?;
            let evaluation = evaluate(
                &dir,
                truth.as_deref(),
                resample_truth,
                vgg19.as_deref(),
                &device,
            )?;
            if !quiet {
                print!("{}", evaluation.metrics);
            }
            if write {
                save_composed(&dir, evaluation.composed)?;
                write_metrics(&dir, &evaluation.metrics)?;
            }
            return Ok(0);
        }
        Command::Warp {
            image,
            field,
            amount,
            output,
            force,
            backend,
        } => {
            return warp(&image, field, amount, &output, force, backend);
        }
        Command::Morph {
            mut images,
            size,
            max_side,
            run,
        } => {
            let (mut config, recorded) = run.resolve(MorphConfig::default())?;
            config.size = working_size(size, max_side, config.size);
            if run.resume.is_some() && !images.is_empty() {
                anyhow::bail!("--resume continues the recorded morph: give no images");
            }
            let inputs = match (images.len(), recorded) {
                (0, Some(recorded)) => recorded,
                (2, _) => {
                    let b = images.pop().expect("two images");
                    let a = images.pop().expect("two images");
                    Inputs::Files { a, b }
                }
                (3.., _) => return chain(config, images, &run),
                _ => anyhow::bail!(
                    "morph needs two images A and B, more for a chain, or --config with a \
                     run's config.json"
                ),
            };
            (config, inputs, run)
        }
        Command::Demo { size, run } => {
            let (mut config, _) = run.resolve(MorphConfig::demo())?;
            if let Some(side) = size {
                config.size = deepmorph::app::config::WorkingSize::Exact {
                    height: side,
                    width: side,
                };
            }
            (config, Inputs::Demo, run)
        }
    };
    morph(config, inputs, &run)
}

fn morph(config: MorphConfig, inputs: Inputs, args: &RunArgs) -> Result<i32> {
    let mut job = MorphJob::prepare(config, inputs)?.estimate_time(!args.quiet);
    if let Some((level, sweep)) = level_and_sweep("DEEPMORPH_INJECT_NONFINITE")? {
        job = job.inject_nonfinite(level, sweep);
    }
    if let Some(dir) = &args.resume {
        job = job.resume_from(dir);
    }
    let folder = job.output_folder(args.output(), args.force || args.resume.is_some())?;
    let interrupt = stop_on_signals(folder.path().to_path_buf())?;
    let mut interrupt_at = InterruptAt {
        at: level_and_sweep("DEEPMORPH_INTERRUPT_AT")?,
        flag: Arc::clone(&interrupt),
    };
    let verbosity = verbosity(args);
    let config = job.config();
    let (h, w) = job.working_size();
    if !args.quiet {
        job.notes().iter().for_each(|note| eprintln!("{note}"));
        let model = format!("{:?}", config.model()).to_lowercase();
        let solver = &config.solver;
        eprintln!(
            "{}: {model} model, {w}x{h} (WxH), K = {}, {} levels x {} sweeps, {} backend, about {:.1} GiB",
            if job.inputs() == &Inputs::Demo {
                "demo"
            } else {
                "morph"
            },
            solver.steps,
            solver.levels,
            solver.sweeps,
            config.backend,
            memory::gib(job.estimated_peak_bytes())
        );
    }
    let mut progress = Progress::new(verbosity);
    let result = job.run(&mut (&mut progress, &mut interrupt_at), &interrupt)?;
    drop(progress);
    let writing = WRITING
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let (metrics, out) = result.write(&job, folder)?;
    drop(writing);
    let termination = &result.morph.termination;
    if let Termination::NonFinite { .. } = termination {
        eprintln!(
            "Error: {termination}; wrote every output from that iterate to {}",
            out.display()
        );
        return Ok(EXIT_NONFINITE);
    }
    if !args.quiet {
        let last = result.energy.records.last().map_or(f64::NAN, |r| r.energy);
        eprintln!(
            "{termination} in {:.1} s, final E = {last:.6e}; wrote {} frames, {}, sheet.png, deformations, composed map, energy.csv, config.json, metrics.json to {}",
            result.seconds,
            config.solver.steps + 1,
            config
                .video
                .iter()
                .map(|f| f.file_name())
                .collect::<Vec<_>>()
                .join(", "),
            out.display()
        );
        if args.verbose {
            eprint!("{metrics}");
        }
    }
    Ok(match termination {
        Termination::Interrupted { .. } => EXIT_INTERRUPTED,
        _ => 0,
    })
}

/// Turns SIGINT, SIGTERM and SIGHUP (ctrlc's `termination` feature) into a raised flag: the
/// solver stops after the current sweep and the outputs are written. A second signal aborts,
/// removing `staging` and leaving the previous output as it was, unless the outputs are being
/// written (a second or so): those are finished first, so the staging folder is never
/// removed under the writer.
fn stop_on_signals(staging: PathBuf) -> Result<Arc<AtomicBool>> {
    let interrupt = Arc::new(AtomicBool::new(false));
    let flag = Arc::clone(&interrupt);
    ctrlc::set_handler(move || {
        if flag.swap(true, Ordering::SeqCst) {
            // A second signal aborts, leaving the previous output as it was, unless the
            // outputs are being written (a second or so): those are finished first, so the
            // staging folder is never removed under the writer.
            if let Ok(_not_writing) = WRITING.try_lock() {
                let _ = std::fs::remove_dir_all(&staging);
                std::process::exit(EXIT_INTERRUPTED);
            }
            eprintln!("\nthe outputs are being written; they will be complete in a moment");
            return;
        }
        eprintln!("\ninterrupted: stopping after this sweep and writing the outputs (signal again to abort)");
    })
    .context("installing the signal handler")?;
    Ok(interrupt)
}

fn verbosity(args: &RunArgs) -> Verbosity {
    match (args.quiet, args.verbose) {
        (true, _) => Verbosity::Quiet,
        (_, true) => Verbosity::Verbose,
        _ => Verbosity::Normal,
    }
}

/// `deepmorph morph A B C ...`: one morph per consecutive pair, in one output folder.
fn chain(config: MorphConfig, images: Vec<PathBuf>, args: &RunArgs) -> Result<i32> {
    let job = ChainJob::prepare(config, images)?.estimate_time(!args.quiet);
    let folder = job.output_folder(args.output(), args.force)?;
    let interrupt = stop_on_signals(folder.path().to_path_buf())?;
    let count = job.segments().len();
    let mut progress = Progress::new(verbosity(args));
    let quiet = args.quiet;
    let outcome = job.run(
        folder,
        &mut progress,
        &interrupt,
        |i, segment| {
            if !quiet {
                segment.notes().iter().for_each(|note| eprintln!("{note}"));
                let (h, w) = segment.working_size();
                if let Inputs::Files { a, b } = segment.inputs() {
                    eprintln!(
                        "segment {}/{count}: {} -> {}, {w}x{h} (WxH), about {:.1} GiB",
                        i + 1,
                        a.display(),
                        b.display(),
                        memory::gib(segment.estimated_peak_bytes())
                    );
                }
            }
        },
        &WRITING,
    )?;
    drop(progress);
    let last = outcome.segments.last().map(|(t, _)| t.clone());
    if !quiet {
        eprintln!(
            "chain of {count} segments: {} run, {}; wrote them to {}{}",
            outcome.segments.len(),
            last.as_ref().map_or("none".into(), ToString::to_string),
            outcome.folder.display(),
            if outcome.animation {
                ", with the whole chain's animations"
            } else {
                " (no chain animation: not every segment completed)"
            }
        );
    }
    Ok(match last {
        Some(Termination::NonFinite { .. }) => EXIT_NONFINITE,
        Some(Termination::Interrupted { .. }) => EXIT_INTERRUPTED,
        _ if outcome.segments.len() < count => EXIT_INTERRUPTED,
        _ => 0,
    })
}

/// `LEVEL:SWEEP` from the environment variable `name`, for the tests' hooks:
/// `DEEPMORPH_INJECT_NONFINITE` makes the solver meet a NaN after that sweep (the non-finite
/// path end to end: outputs written, exit status 3); `DEEPMORPH_INTERRUPT_AT` raises the
/// interrupt flag after that joint sweep, as a signal would (`--resume` end to end).
fn level_and_sweep(name: &str) -> Result<Option<(usize, usize)>> {
    let Some(value) = std::env::var_os(name) else {
        return Ok(None);
    };
    let value = value.to_string_lossy();
    let parsed = value
        .split_once(':')
        .and_then(|(l, s)| Some((l.trim().parse().ok()?, s.trim().parse().ok()?)));
    parsed
        .map(Some)
        .with_context(|| format!("{name}={value} is not LEVEL:SWEEP"))
}

/// Raises the interrupt flag after joint sweep `at` (level, sweep): see [`level_and_sweep`].
struct InterruptAt {
    at: Option<(usize, usize)>,
    flag: Arc<AtomicBool>,
}

impl Observer for InterruptAt {
    fn sweep(&mut self, e: &SweepEvent<'_>) {
        if e.phase == Phase::Joint && self.at == Some((e.level, e.sweep)) {
            self.flag.store(true, Ordering::SeqCst);
        }
    }
}

/// The files `deepmorph warp` writes.
fn is_warp_output(name: &str) -> bool {
    ["a.png", "b.png", "truth.flo"].contains(&name)
}

fn backend_or_default(backend: Option<Backend>) -> Backend {
    backend.unwrap_or(MorphConfig::default().backend)
}

/// `deepmorph warp`: a synthetic pair with a known correspondence.
fn warp(
    image: &Path,
    field: Field,
    amount: f64,
    out: &Path,
    force: bool,
    backend: Option<Backend>,
) -> Result<i32> {
    let input = RgbImage::load(image)?;
    let device = backend_or_default(backend).device_for(Precision::F32)?;
    let (warped, truth) = warped_pair(&input, field, amount, &device)?;
    let folder = OutputFolder::begin(out, &[image], is_warp_output, force)?;
    let staging = folder.path();
    write_png(&staging.join("a.png"), &warped.to_rgb8())?;
    write_png(&staging.join("b.png"), &input.to_rgb8())?;
    truth.write_flo(&staging.join("truth.flo"))?;
    let out = folder.commit()?;
    eprintln!(
        "wrote a.png ({field} {amount} applied to {}), b.png and truth.flo ({}x{}) to {}",
        image.display(),
        input.width(),
        input.height(),
        out.display()
    );
    Ok(0)
}
