//! The RGB model on the Middlebury 2014 motorcycle stereo pair, scored against its
//! ground-truth disparity: the endpoint error of the composed map `Φ = φ_K ∘ … ∘ φ_1`.
//!
//! ```sh
//! cargo run --release --example motorcycle -- --max-side 128 -K 8 --levels 4 --sweeps 60
//! ```
//!
//! Reads `../shared/data/images/pairs/motorcycle/{a.png, b.png, disparity_a.png}` (the
//! team's test data; the example says so and exits when they are absent). The same
//! numbers come from the command line:
//! `deepmorph morph a.png b.png -o out …` then `deepmorph eval out --truth disparity_a.png`.

use std::path::Path;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::Result;
use clap::Parser;
use deepmorph::io::RgbImage;
use deepmorph::metrics::{Metrics, compose};
use deepmorph::multilevel::{Multilevel, MultilevelConfig, fit_size};
use deepmorph::observe::EnergyLog;
use deepmorph::truth::Correspondence;
use deepmorph::{Backend, Grid, Precision};

/// The CLI's allocator (see `src/main.rs`), so the figures are the program's.
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
}

fn main() -> Result<()> {
    let args = Args::parse();
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/images/pairs/motorcycle");
    if !dir.join("disparity_a.png").is_file() {
        println!(
            "skipped: {} is absent (the team's test data)",
            dir.display()
        );
        return Ok(());
    }
    let (a, b) = (
        RgbImage::load(&dir.join("a.png"))?,
        RgbImage::load(&dir.join("b.png"))?,
    );
    let truth = Correspondence::load(&dir.join("disparity_a.png"))?;

    let (h, w) = fit_size(a.height(), a.width(), args.max_side, args.levels);

    let backend = Backend::default_compiled().expect("a backend is compiled in");
    let device = backend.device_for(Precision::F32)?.autodiff();
    let grid = Grid::new(h, w, &device, Precision::F32.dtype())?;
    let (u_a, u_b) = (
        a.resized(h, w).to_tensor(&grid)?,
        b.resized(h, w).to_tensor(&grid)?,
    );
    let config = MultilevelConfig {
        steps: args.steps,
        levels: args.levels,
        sweeps: args.sweeps,
        params: deepmorph::EnergyParams {
            delta: args.delta,
            ..deepmorph::EnergyParams::rgb()
        },
        ..MultilevelConfig::default()
    };
    println!(
        "motorcycle {}x{} -> {w}x{h}, K = {}, {} levels x {} sweeps, delta = {}, {backend}",
        a.width(),
        a.height(),
        args.steps,
        args.levels,
        args.sweeps,
        args.delta
    );
    let started = Instant::now();
    let mut log = EnergyLog::default();
    let morph =
        Multilevel::new(config)?.run(&device, u_a, u_b, &mut log, &AtomicBool::new(false))?;
    let seconds = started.elapsed().as_secs_f64();

    let frames = morph.state.frames();
    let k = args.steps;
    let endpoints = (frames.clone().narrow(0, 0, 1), frames.narrow(0, k, 1));
    let deformations = morph.state.deformations();
    let composed = compose(&morph.grid, deformations.clone());
    let metrics = Metrics::compute(
        &morph.grid,
        deformations,
        composed,
        endpoints,
        &log.records,
        Some((&truth, "disparity_a.png")),
    )?;
    print!("{metrics}");
    println!("solver time {seconds:.1} s");
    Ok(())
}
