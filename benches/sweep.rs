//! One full iPALM sweep (all `k`, SPEC §6) of the RGB model with `K = 15` at 64², 128² and
//! 256² on each compiled backend (wgpu too with `--features wgpu`), float32, safeguard on
//! (the CLI default).
//!
//! The state is a mid-run one: the demo pair after a few sweeps at the benchmarked size, so
//! the deformations are non-trivial and backtracking behaves as in a real run. Each timed
//! iteration sweeps a fresh copy of that state and ends with `device.sync()`.
//!
//! ```text
//! cargo bench --features ndarray,flex --bench sweep
//! ```

use std::sync::atomic::AtomicBool;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use deepmorph::demo::demo_pair;
use deepmorph::layout::FeatureLayout;
use deepmorph::multilevel::{Multilevel, MultilevelConfig};
use deepmorph::optim::ipalm::{Ipalm, IpalmConfig, SweepKind};
use deepmorph::{Backend, EnergyParams, Grid, Precision};

const SIZES: [usize; 3] = [64, 128, 256];
const STEPS: usize = 15;

fn benches(c: &mut Criterion) {
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
                    let mut state = warm.state.clone();
                    let report = ipalm.sweep(&mut state, SweepKind::Joint).unwrap();
                    device.sync().expect("device sync");
                    report
                })
            });
        }
    }
    group.finish();
}

criterion_group!(sweep, benches);
criterion_main!(sweep);
