//! The Middlebury 2014 motorcycle stereo pair morphed with the library's one-call API, and
//! scored against its ground-truth disparity: the endpoint error of the composed map
//! `Φ = φ_K ∘ … ∘ φ_1`.
//!
//! ```sh
//! cargo run --release --example motorcycle -- --max-side 128 -K 8 --levels 4 --sweeps 60
//! cargo run --release --example motorcycle -- --max-side 128 --model deep \
//!     --vgg19 ../shared/data/vgg19/vgg19_hed_stand_in.onnx
//! ```
//!
//! Reads `../shared/data/images/pairs/motorcycle/{a.png, b.png, disparity_a.png}` (the
//! team's test data; the example says so and exits when they are absent) and writes the
//! morph to `--output`. The same numbers come from the command line:
//! `deepmorph morph a.png b.png -o out …` then `deepmorph eval out --truth disparity_a.png`.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

use anyhow::Result;
use clap::Parser;
use deepmorph::Precision;
use deepmorph::app::config::{Inputs, MorphConfig, WorkingSize};
use deepmorph::app::job::MorphJob;
use deepmorph::eval::folder::MorphFolder;
use deepmorph::io::truth::Correspondence;

/// The CLI's allocator (see `src/bin/deepmorph/main.rs`), so the figures are the program's.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[derive(Parser)]
struct Args {
    /// Longest side of the working size.
    #[arg(long, default_value_t = 128)]
    max_side: usize,
    /// Steps K.
    #[arg(short = 'K', default_value_t = 8)]
    steps: usize,
    /// Pyramid levels.
    #[arg(long, default_value_t = 4)]
    levels: usize,
    /// Sweeps per level.
    #[arg(long, default_value_t = 60)]
    sweeps: usize,
    /// Data-term weight 1/δ (SPEC §9: 1).
    #[arg(long, default_value_t = 1.0)]
    delta: f64,
    /// VGG19 weights: morph with the deep model.
    #[arg(long)]
    vgg19: Option<PathBuf>,
    /// Where the morph is written.
    #[arg(short, long, default_value = "target/motorcycle")]
    output: PathBuf,
}

fn main() -> Result<()> {
    // Small pages and the solver's thread on a worker of the kernels' pool, as the CLI runs.
    deepmorph::host_memory::prefer_small_pages();
    deepmorph::backend::on_a_worker(run)
}

fn run() -> Result<()> {
    let args = Args::parse();
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/images/pairs/motorcycle");
    if !dir.join("disparity_a.png").is_file() {
        println!(
            "skipped: {} is absent (the team's test data)",
            dir.display()
        );
        return Ok(());
    }
    let mut config = match &args.vgg19 {
        Some(weights) => MorphConfig::deep(weights),
        None => MorphConfig::default(),
    };
    config.size = WorkingSize::Fit {
        max_side: args.max_side,
    };
    config.solver.steps = args.steps;
    config.solver.levels = args.levels;
    config.solver.sweeps = args.sweeps;
    config.solver.params.delta = args.delta;
    let inputs = Inputs::Files {
        a: dir.join("a.png"),
        b: dir.join("b.png"),
    };
    let job = MorphJob::prepare(config, inputs)?;
    let (h, w) = job.working_size();
    println!(
        "motorcycle -> {w}x{h}, K = {}, {} levels x {} sweeps, delta = {}, {:?} model, {}",
        args.steps,
        args.levels,
        args.sweeps,
        args.delta,
        job.config().model(),
        job.config().backend
    );
    // A previous run of this example is replaced: it is this example's own folder.
    let folder = job.output_folder(&args.output, true)?;
    let result = job.run(&mut (), &AtomicBool::new(false))?;
    let (_, out) = result.write(&job, folder)?;

    let truth = Correspondence::load(&dir.join("disparity_a.png"))?;
    let folder = MorphFolder::read(&out, &job.config().backend.device_for(Precision::F32)?)?;
    let metrics = folder.metrics(folder.composed(), Some((&truth, "disparity_a.png")))?;
    print!("{metrics}");
    println!(
        "solver time {:.1} s; morph in {}",
        result.seconds,
        out.display()
    );
    Ok(())
}
