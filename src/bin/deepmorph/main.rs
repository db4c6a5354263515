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
use deepmorph::app::hooks::TestHooks;
use deepmorph::app::job::MorphJob;
use deepmorph::app::warp::write_warped_pair;
use deepmorph::eval::synthetic::Field;
use deepmorph::solver::observer::Termination;
use deepmorph::{Backend, Precision};

use args::{Cli, Command, Request, RunArgs, demo_request, morph_request};
use progress::{Progress, Verbosity};

/// The solver allocates and frees tensors of megabytes many times per sweep. glibc's malloc
/// hands such blocks back to the kernel each time, and the next allocation page-faults them in
/// again: a third of a deep sweep's time at 128² went to page faults. mimalloc keeps them.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Held while a morph's outputs are written: the signal handler's abort waits for no one and
/// must not remove the staging folder under the writer.
static WRITING: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Raised when the solver has reported its first event (the time estimate, the landmark
/// start or a sweep). Before that nothing worth writing exists, and the work may be blocked
/// where no flag is looked at (opening a pipe that has no writer yet, reading the weights,
/// VGG19's forward passes): a signal then ends the run at once.
static SOLVING: AtomicBool = AtomicBool::new(false);

/// The observer that raises [`SOLVING`].
struct SolveStarted;

impl deepmorph::solver::observer::Observer for SolveStarted {
    fn sweep(&mut self, _: &deepmorph::solver::observer::SweepEvent<'_>) {
        SOLVING.store(true, Ordering::SeqCst);
    }

    fn estimate(&mut self, _: &deepmorph::solver::estimate::TimeEstimate) {
        SOLVING.store(true, Ordering::SeqCst);
    }

    fn initialised(&mut self, _: &deepmorph::solver::observer::Initialisation) {
        SOLVING.store(true, Ordering::SeqCst);
    }
}

/// Exit status of an error: bad input, unreadable or unwritable files, no backend.
const EXIT_ERROR: i32 = 1;
/// Exit status of a morph stopped by a NaN or infinity in the optimisation; its outputs were
/// written from the last finite iterate. (clap's usage errors exit with 2.)
const EXIT_NONFINITE: i32 = 3;
/// Exit status of a morph stopped by Ctrl-C or SIGTERM; its outputs were written.
const EXIT_INTERRUPTED: i32 = 130;

fn main() {
    deepmorph::host_memory::prefer_small_pages();
    let cli = Cli::parse();
    let code = deepmorph::backend::on_a_worker(|| run(cli)).unwrap_or_else(|e| {
        eprintln!("Error: {e:#}");
        EXIT_ERROR
    });
    std::process::exit(code);
}

fn run(cli: Cli) -> Result<i32> {
    let request = match cli.command {
        Command::Eval {
            dir,
            truth,
            resample_truth,
            vgg19,
            points,
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
                points.as_deref(),
                &device,
            )?;
            if !quiet {
                print!("{}", evaluation.metrics);
            }
            if write {
                evaluation.write(&dir)?;
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
            images,
            size,
            max_side,
            run,
        } => morph_request(images, size, max_side, run)?,
        Command::Demo { size, run } => demo_request(size, run)?,
    };
    match request {
        Request::Single(config, inputs, run) => morph(config, inputs, &run),
        Request::Chain(config, images, run) => chain(config, images, &run),
    }
}

fn morph(config: MorphConfig, inputs: Inputs, args: &RunArgs) -> Result<i32> {
    let hooks = TestHooks::from_env()?;
    let mut job = hooks.apply(MorphJob::prepare(config, inputs)?.estimate_time(!args.quiet))?;
    if let Some(dir) = &args.resume {
        job = job.resume_from(dir);
    }
    let folder = job.output_folder(args.output(), args.force || args.resume.is_some())?;
    let interrupt = stop_on_signals(folder.path().to_path_buf())?;
    let mut interrupt_at = hooks.interrupter(Arc::clone(&interrupt));
    if !args.quiet {
        job.notes().iter().for_each(|note| eprintln!("{note}"));
        eprintln!("{}", job.describe());
    }
    let mut progress = Progress::new(verbosity(args));
    let result = job.run(
        &mut (&mut progress, (&mut interrupt_at, SolveStarted)),
        &interrupt,
    )?;
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
            "{termination} in {:.1} s, final E = {last:.6e}; wrote {} to {}",
            result.seconds,
            result.outputs_written(&job),
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
/// solver stops after the current step (one block of a sweep) and the outputs are written,
/// with a checkpoint for `--resume`. A signal before the solve began ([`SOLVING`]), or a
/// second signal, aborts at once, removing `staging` and leaving the previous output as it
/// was, unless the outputs are being written (a second or so): those are finished first, so
/// the staging folder is never removed under the writer.
fn stop_on_signals(staging: PathBuf) -> Result<Arc<AtomicBool>> {
    let interrupt = Arc::new(AtomicBool::new(false));
    let flag = Arc::clone(&interrupt);
    ctrlc::set_handler(move || {
        let again = flag.swap(true, Ordering::SeqCst);
        let solving = SOLVING.load(Ordering::SeqCst);
        if !again && solving {
            eprintln!(
                "\ninterrupted: stopping after this step and writing the outputs (signal again to abort)"
            );
            return;
        }
        if let Ok(_not_writing) = WRITING.try_lock() {
            let _ = std::fs::remove_dir_all(&staging);
            if !solving {
                eprintln!("\ninterrupted before the solve began: nothing written");
            }
            std::process::exit(EXIT_INTERRUPTED);
        }
        eprintln!("\nthe outputs are being written; they will be complete in a moment");
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
        &mut (&mut progress, SolveStarted),
        &interrupt,
        |i, segment| {
            if !quiet {
                segment.notes().iter().for_each(|note| eprintln!("{note}"));
                eprintln!("segment {}/{count}: {}", i + 1, segment.describe_segment());
            }
        },
        &WRITING,
    )?;
    drop(progress);
    let last = outcome.segments.last().map(|(t, _)| t.clone());
    if !quiet {
        eprintln!("{}", outcome.summary(count));
    }
    Ok(match last {
        Some(Termination::NonFinite { .. }) => EXIT_NONFINITE,
        Some(Termination::Interrupted { .. }) => EXIT_INTERRUPTED,
        _ if outcome.segments.len() < count => EXIT_INTERRUPTED,
        _ => 0,
    })
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
    let device = backend_or_default(backend).device_for(Precision::F32)?;
    let pair = write_warped_pair(image, field, amount, out, force, &device)?;
    eprintln!(
        "wrote a.png ({field} {amount} applied to {}), b.png and truth.flo ({}x{}) to {}",
        image.display(),
        pair.size.0,
        pair.size.1,
        pair.folder.display()
    );
    Ok(0)
}
