//! One full iPALM sweep (all `k`, SPEC §6) on each compiled backend (wgpu too with
//! `--features wgpu`), float32, safeguard on (the CLI default):
//!
//! - `sweep_K15/BACKEND/n`: the RGB model, `K = 15`, at 64², 128² and 256²;
//! - `sweep_deep_K4/BACKEND/n`: the deep model's finest level (η-RGB + 64 feature channels,
//!   two blocks, deep defaults), `K = 4`, at 64² and 128². The 64 channels are smooth
//!   functions of the demo images' colours scaled to RMS τ = 0.5 (not VGG: the bench must
//!   not need a weights file), so they move with the images as relu1_2 does.
//!
//! The state is a mid-run one: the demo pair after a few sweeps at the benchmarked size, so
//! the deformations are non-trivial and backtracking behaves as in a real run. Each timed
//! iteration sweeps a fresh copy of that state and ends with `device.sync()`, on a worker of
//! the solver's pool as the CLI runs it ([`deepmorph::backend::on_a_worker`]).
//!
//! ```text
//! cargo bench --features ndarray,flex --bench sweep
//! cargo bench --features flex --bench sweep -- sweep_deep
//! ```

use std::sync::atomic::AtomicBool;
use std::time::Duration;

use burn::tensor::Tensor;
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use deepmorph::app::demo::demo_pair;
use deepmorph::model::feature_model::DeepConfig;
use deepmorph::model::layout::FeatureLayout;
use deepmorph::solver::ipalm::{Ipalm, IpalmConfig, LevelState, SweepKind};
use deepmorph::solver::multilevel::{Multilevel, MultilevelConfig};
use deepmorph::{Backend, EnergyParams, Grid, Precision};

/// The CLI's allocator (see `src/bin/deepmorph/main.rs`), so the figures are the program's.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

const SIZES: [usize; 3] = [64, 128, 256];
const STEPS: usize = 15;
const DEEP_SIZES: [usize; 2] = [64, 128];
const DEEP_STEPS: usize = 4;
const DEEP_CHANNELS: usize = 64;

/// `(η·u, F)` for an RGB image `u`, `[1, 3 + 64, n, n]`: channel `j` of `F` is
/// `sin(a_j·u + b_j)` for fixed pseudo-random `a_j`, `b_j`, scaled to RMS 0.5.
fn deep_features(u: Tensor<4>, eta: f64) -> Tensor<4> {
    let features: Vec<Tensor<4>> = (0..DEEP_CHANNELS)
        .map(|j| {
            let x = (j as f64 + 1.0) * 0.618_034;
            let mix = [(7.0 * x).sin(), (11.0 * x).cos(), (13.0 * x).sin()];
            let [r, g, b] = [0, 1, 2].map(|c| u.clone().narrow(1, c, 1));
            (r.mul_scalar(3.0 * mix[0]) + g.mul_scalar(3.0 * mix[1]) + b.mul_scalar(3.0 * mix[2]))
                .add_scalar(5.0 * x)
                .sin()
                .mul_scalar(0.5 * std::f64::consts::SQRT_2)
        })
        .collect();
    Tensor::cat(vec![u.mul_scalar(eta), Tensor::cat(features, 1)], 1)
}

fn deep_benches(c: &mut Criterion) {
    deepmorph::host_memory::prefer_small_pages();
    let mut group = c.benchmark_group(format!("sweep_deep_K{DEEP_STEPS}"));
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(30));
    let eta = DeepConfig::default().eta;
    let layout = FeatureLayout::deep(eta, DEEP_CHANNELS).unwrap();
    for backend in Backend::compiled() {
        let Ok(device) = backend.device_for(Precision::F32) else {
            continue;
        };
        let device = device.autodiff();
        for n in DEEP_SIZES {
            let grid = Grid::new(n, n, &device, Precision::F32.dtype()).unwrap();
            let (a, b) = demo_pair(n);
            let [f_a, f_b] = [a, b].map(|u| deep_features(u.to_tensor(&grid).unwrap(), eta));
            let ipalm = Ipalm::new(
                &grid,
                EnergyParams::deep(),
                layout.clone(),
                IpalmConfig::default(),
            )
            .unwrap();
            let mut warm = LevelState::initial(&grid, &layout, f_a, f_b, DEEP_STEPS, 1.0).unwrap();
            for _ in 0..3 {
                ipalm.sweep(&mut warm, SweepKind::Joint).unwrap();
            }
            group.bench_with_input(BenchmarkId::new(backend.name(), n), &n, |bench, _| {
                bench.iter(|| {
                    on_pool(|| {
                        let mut state = warm.clone();
                        let report = ipalm.sweep(&mut state, SweepKind::Joint).unwrap();
                        device.sync().expect("device sync");
                        report
                    })
                })
            });
        }
    }
    group.finish();
}

fn benches(c: &mut Criterion) {
    // The program's pages (`host_memory::prefer_small_pages`); `MIMALLOC_ALLOW_THP=1` for huge.
    deepmorph::host_memory::prefer_small_pages();
    let mut group = c.benchmark_group("sweep_K15");
    group
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(20));
    for backend in Backend::compiled() {
        let Ok(device) = backend.device_for(Precision::F32) else {
            continue;
        };
        let device = device.autodiff();
        for n in SIZES {
            let grid = Grid::new(n, n, &device, Precision::F32.dtype()).unwrap();
            let (a, b) = demo_pair(n);
            let config = MultilevelConfig {
                steps: STEPS,
                levels: 1,
                sweeps: 3,
                ..MultilevelConfig::default()
            };
            let warm = Multilevel::new(config)
                .unwrap()
                .run(
                    &device,
                    a.to_tensor(&grid).unwrap(),
                    b.to_tensor(&grid).unwrap(),
                    &mut (),
                    &AtomicBool::new(false),
                )
                .unwrap();
            let ipalm = Ipalm::new(
                &grid,
                EnergyParams::rgb(),
                FeatureLayout::rgb(),
                IpalmConfig::default(),
            )
            .unwrap();
            group.bench_with_input(BenchmarkId::new(backend.name(), n), &n, |bench, _| {
                bench.iter(|| {
                    on_pool(|| {
                        let mut state = warm.state.clone();
                        let report = ipalm.sweep(&mut state, SweepKind::Joint).unwrap();
                        device.sync().expect("device sync");
                        report
                    })
                })
            });
        }
    }
    group.finish();
}

/// Runs a timed sweep on a worker of one pool, as the CLI runs its solver
/// ([`deepmorph::backend::on_a_worker`]); the pool is built once.
fn on_pool<R: Send>(sweep: impl FnOnce() -> R + Send) -> R {
    static POOL: std::sync::OnceLock<Option<rayon::ThreadPool>> = std::sync::OnceLock::new();
    match POOL.get_or_init(deepmorph::backend::solver_pool) {
        Some(pool) => pool.install(sweep),
        None => sweep(),
    }
}

criterion_group!(sweep, benches, deep_benches);
criterion_main!(sweep);
