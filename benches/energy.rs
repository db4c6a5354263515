//! Baseline costs of the discrete model on each compiled backend, float32:
//!
//! - `warp/BACKEND/C{c}/{n}`: `T[f, φ]` (prefilter + cubic interpolation) of one
//!   `[1, C, n, n]` frame, the way the backend computes it; on a backend with the fused
//!   spline op also `warp/BACKEND-composed/...`, the composed tensor ops it replaced (dense
//!   prefilter matmuls and row gathers), for the comparison;
//! - `step/BACKEND/C{c}/{n}`: value and autodiff gradient of one step of `E`,
//!   `R[φ_k, a_k] + D[f_{k−1}, f_k, φ_k]`, w.r.t. `φ_k`, `f_{k−1}` and `f_k`;
//! - `anisotropy/BACKEND/{n}`: `a[u]` of one RGB frame (SPEC §3), as each deformation step
//!   computes it;
//! - `prefilter/{what}/C{c}x{frames}/{n}`: the native CPU prefilter (the flex backend's
//!   kernel) of the 15 frames of a `K = 15` sweep at once (the batched schedule), or of one
//!   frame (the sequential schedule's steps): `channels-last` is `P f` of the deep model's
//!   67 channels as the warp reads them, `adjoint` `Pᵀ g` of 67 planar channels (the warp's
//!   backward), `planar` `P f` of RGB;
//! - `slope-moments/C{c}x{frames}/{n}`: the deformation step's linearisation moments (the
//!   flex kernel) at each level of a default deep morph.
//!
//! `C = 3` is the RGB model, `C = 67` the deep model's finest level (relu1_2 + η RGB). The
//! deformation is a smooth admissible one with displacements of a few pixels, so the gathers
//! read scattered memory as in a real sweep. Every timed iteration ends with `device.sync()`.
//!
//! ```text
//! cargo bench --features ndarray,flex --bench energy                 # everything
//! cargo bench --features ndarray,flex --bench energy -- 'step/flex'  # a subset
//! ```
//!
//! Peak memory of one configuration: run the bench binary on it alone under
//! `/usr/bin/time -v` (see the README).

use std::time::Duration;

use burn::tensor::{Device, Tensor};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};
use deepmorph::backend::Gather;
use deepmorph::model::energy::path::PathEnergy;
use deepmorph::model::warp::BSpline;
use deepmorph::{Backend, EnergyParams, Grid, Precision};

/// The CLI's allocator (see `src/bin/deepmorph/main.rs`), so the figures are the program's.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

const SIZES: [usize; 4] = [64, 128, 256, 512];
const CHANNELS: [usize; 2] = [3, 67];

/// `c` smooth maps on an `n × n` grid, `[1, c, n, n]`.
fn image(grid: &Grid, c: usize, seed: f64) -> Tensor<4> {
    let n = grid.height();
    let values = (0..c * n * n)
        .map(|p| {
            let (ch, i, j) = (p / (n * n), (p / n) % n, p % n);
            let (x, y) = (i as f64 / n as f64, j as f64 / n as f64);
            0.5 + 0.4 * (6.0 * x + 4.0 * y + ch as f64 + seed).sin() * (5.0 * y - 3.0 * x).cos()
        })
        .collect();
    grid.tensor(values, [1, c, n, n])
}

/// `Id` plus a smooth displacement of up to `0.02 n` pixels that vanishes on the boundary.
fn deformation(grid: &Grid) -> Tensor<4> {
    let n = grid.height();
    let amplitude = 0.02 * n as f64;
    let pi = std::f64::consts::PI;
    let values = (0..2 * n * n)
        .map(|p| {
            let (axis, i, j) = (p / (n * n), (p / n) % n, p % n);
            let (x, y) = (i as f64 / (n - 1) as f64, j as f64 / (n - 1) as f64);
            let bump = (pi * x).sin() * (pi * y).sin();
            let id = if axis == 0 { i } else { j } as f64;
            let swirl = if axis == 0 {
                (2.0 * pi * y).sin()
            } else {
                (2.0 * pi * x).cos()
            };
            id + amplitude * bump * bump * swirl
        })
        .collect();
    grid.tensor(values, [1, 2, n, n])
}

fn sync(device: &Device) {
    device.sync().expect("device sync");
}

fn benches(c: &mut Criterion) {
    // The program's pages (`host_memory::prefer_small_pages`); `MIMALLOC_ALLOW_THP=1` for huge.
    deepmorph::host_memory::prefer_small_pages();
    for backend in Backend::compiled() {
        let Ok(plain) = backend.device_for(Precision::F32) else {
            continue;
        };
        let autodiff = plain.clone().autodiff();
        for channels in CHANNELS {
            for n in SIZES {
                let id = format!("{backend}/C{channels}");

                let grid = Grid::new(n, n, &plain, Precision::F32.dtype()).unwrap();
                let (f, phi) = (image(&grid, channels, 0.0), deformation(&grid));
                let mut variants = vec![(id.clone(), BSpline::new(&grid))];
                if backend.has_fused_warp() {
                    let composed = BSpline::with_gather(&grid, Gather::RowsFrom(32));
                    variants.push((format!("{backend}-composed/C{channels}"), composed));
                }
                let mut group = c.benchmark_group("warp");
                group.sample_size(10).warm_up_time(Duration::from_secs(1));
                for (label, bspline) in &variants {
                    group.bench_with_input(BenchmarkId::new(label, n), &n, |b, _| {
                        b.iter(|| {
                            let out = bspline.warp(f.clone(), phi.clone());
                            sync(&plain);
                            out
                        })
                    });
                }
                group.finish();

                let grid = grid.with_device(&autodiff);
                let energy = PathEnergy::new(&grid, EnergyParams::rgb(), channels).unwrap();
                let frames = Tensor::cat(
                    vec![image(&grid, channels, 0.0), image(&grid, channels, 1.0)],
                    0,
                );
                let phi = deformation(&grid);
                let rgb = image(&grid, 3, 1.0);
                let a = energy.anisotropy().compute(rgb.clone());
                if channels == 3 {
                    // One image, and a sweep's worth: the energy after a sweep takes the
                    // anisotropies of all `K` frames at once (frames beyond the caches).
                    let frames = Tensor::cat(vec![rgb.clone(); FRAMES], 0);
                    let mut group = c.benchmark_group("anisotropy");
                    group.sample_size(10).warm_up_time(Duration::from_secs(1));
                    for (label, u) in [
                        (backend.name().to_string(), &rgb),
                        (format!("{}/K{FRAMES}", backend.name()), &frames),
                    ] {
                        group.bench_with_input(BenchmarkId::new(label, n), &n, |b, _| {
                            b.iter(|| {
                                let out = energy.anisotropy().compute(u.clone());
                                sync(&autodiff);
                                out
                            })
                        });
                    }
                    group.finish();
                }
                let mut group = c.benchmark_group("step");
                group.sample_size(10).warm_up_time(Duration::from_secs(1));
                group.bench_with_input(BenchmarkId::new(&id, n), &n, |b, _| {
                    b.iter(|| {
                        let f = frames.clone().require_grad();
                        let phi = phi.clone().require_grad();
                        let value = energy.value(f.clone(), phi.clone(), a.clone());
                        let grads = value.total.backward();
                        let out = (f.grad(&grads), phi.grad(&grads));
                        sync(&autodiff);
                        out
                    })
                });
                group.finish();
            }
        }
    }
}

/// Frames a `K = 15` sweep prefilters at once.
const FRAMES: usize = 15;

fn prefilter_benches(c: &mut Criterion) {
    use deepmorph::model::warp::host;
    let mut group = c.benchmark_group("prefilter");
    group.sample_size(10).warm_up_time(Duration::from_secs(1));
    for n in [128, 256] {
        for frames in [FRAMES, 1] {
            for (what, channels) in [("channels-last", 67), ("adjoint", 67), ("planar", 3)] {
                let len = frames * channels * n * n;
                let source: Vec<f32> = (0..len)
                    .map(|i| ((i as f64 * 0.618).fract() - 0.5) as f32)
                    .collect();
                let mut out = vec![0.0f32; len];
                let id = BenchmarkId::new(format!("{what}/C{channels}x{frames}"), n);
                group.bench_with_input(id, &n, |b, _| {
                    b.iter(|| match what {
                        "channels-last" => host::prefilter_channels_last(
                            &source,
                            &mut out,
                            (frames, channels, n, n),
                        ),
                        _ => host::prefilter_into(&source, &mut out, n, n, what == "adjoint"),
                    })
                });
            }
        }
    }
    group.finish();
}

fn adjoint_benches(c: &mut Criterion) {
    use deepmorph::model::warp::host;
    let mut group = c.benchmark_group("adjoint");
    group.sample_size(20).warm_up_time(Duration::from_secs(1));
    for (channels, n) in [(67, 256), (131, 128), (259, 64), (515, 32), (515, 16)] {
        let plane = n * n;
        let grad: Vec<f32> = (0..channels * plane)
            .map(|i| ((i as f64 * 0.618).fract() - 0.5) as f32)
            .collect();
        // A smooth deformation of a few pixels, in sample coordinates (row plane, column
        // plane), so neighbouring points scatter into neighbouring coefficients.
        let phi: Vec<f32> = (0..2 * plane)
            .map(|i| {
                let (axis, p) = (i / plane, i % plane);
                let (y, x) = ((p / n) as f64, (p % n) as f64);
                let s = (n as f64 / 64.0).max(1.0);
                let v = if axis == 0 {
                    y + 1.5 * s * (x * 0.05).sin()
                } else {
                    x + 1.5 * s * (y * 0.07).cos()
                };
                v.clamp(0.0, (n - 1) as f64) as f32
            })
            .collect();
        let d = host::Dims {
            n: 1,
            c: channels,
            h: n,
            w: n,
            ho: n,
            wo: n,
        };
        let mut out = vec![0.0f32; channels * plane];
        group.bench_with_input(BenchmarkId::new(format!("C{channels}"), n), &n, |b, _| {
            b.iter(|| host::sample_adjoint(&grad, &phi, &mut out, d))
        });
    }
    group.finish();
}

/// The deformation step's linearisation moments (`slopes::host_moments`, the flex kernel) of
/// one frame at each level of a default deep morph (`C` channels at `n²`, `N` frames: 15 in
/// the batched schedule, 1 in a restart's or the sequential schedule's step).
fn slope_moment_benches(c: &mut Criterion) {
    use deepmorph::model::slopes::host_moments;
    let mut group = c.benchmark_group("slope-moments");
    group.sample_size(20).warm_up_time(Duration::from_secs(1));
    for (channels, n, frames) in [
        (67, 256, 1),
        (131, 128, 1),
        (259, 64, 1),
        (515, 32, 1),
        (515, 32, FRAMES),
        (515, 16, FRAMES),
    ] {
        let len = frames * channels * n * n;
        let wave = |seed: f64| -> Vec<f32> {
            (0..len)
                .map(|i| ((i as f64 * 0.618 + seed).fract() - 0.5) as f32)
                .collect()
        };
        let (warped, prev) = (wave(0.1), wave(0.4));
        let phi: Vec<f32> = (0..frames * 2 * n * n)
            .map(|i| ((i as f64 * 0.377).sin() * 2.0) as f32)
            .collect();
        let mut out = vec![0.0f32; frames * 5 * n * n];
        let id = BenchmarkId::new(format!("C{channels}x{frames}"), n);
        group.bench_with_input(id, &n, |b, _| {
            b.iter(|| {
                host_moments(&warped, &prev, &phi, [frames, channels, n, n], &mut out);
            })
        });
    }
    group.finish();
}

/// A feature trial's frame passes besides its warp (SPEC §6 step 3), deep model, float64
/// decision sums on flex: the gradient step `x̃ − ∇Q/L` of both channel blocks and the three
/// decision folds of its test, `‖T[f_{k+1}, φ_{k+1}] − x_new‖²`, `‖T[x_new, φ_k] − f_{k−1}‖²`
/// and `‖T[x_new, φ_k] − T[x̃, φ_k]‖²` per block, done `separately` (a pass per fold) and
/// `fused` as the solver runs them (the first fold while the step writes the frame, the other
/// two in one pass over the trial's warp).
fn trial_fold_benches(c: &mut Criterion) {
    use deepmorph::solver::update_op::{descend, descend_distance2};
    let Ok(device) = Backend::Flex.device_for(Precision::F32) else {
        return;
    };
    let mut group = c.benchmark_group("trial-folds");
    group.sample_size(10).warm_up_time(Duration::from_secs(1));
    for (channels, n, frames) in [(67, 256, FRAMES), (67, 256, 1), (131, 128, FRAMES)] {
        let grid = Grid::new(n, n, &device, Precision::F32.dtype()).unwrap();
        let blocks = [0..3, 3..channels];
        let stack = |seed: f64| {
            Tensor::cat(
                (0..frames)
                    .map(|i| image(&grid, channels, seed + i as f64))
                    .collect(),
                0,
            )
        };
        let (x, g, next, warped, before, tilde) = (
            stack(0.0),
            stack(1.0),
            stack(2.0),
            stack(3.0),
            stack(4.0),
            stack(5.0),
        );
        let lipschitz: Vec<f64> = (0..frames * 2).map(|e| 2.0 + e as f64).collect();
        for variant in ["separate", "fused"] {
            let id = BenchmarkId::new(format!("{variant}/C{channels}x{frames}"), n);
            group.bench_with_input(id, &n, |b, _| {
                b.iter(|| {
                    let sums = if variant == "fused" {
                        let (_, to_next) = descend_distance2(
                            &grid,
                            x.clone(),
                            g.clone(),
                            &lipschitz,
                            &blocks,
                            next.clone(),
                        );
                        let [to_prev, moved] = grid.decision_distance2_blocks_pair(
                            warped.clone(),
                            before.clone(),
                            tilde.clone(),
                            &blocks,
                        );
                        [to_next, to_prev, moved]
                    } else {
                        let candidate = descend(x.clone(), g.clone(), &lipschitz, &blocks);
                        [
                            grid.decision_distance2_blocks(next.clone(), candidate, &blocks),
                            grid.decision_distance2_blocks(warped.clone(), before.clone(), &blocks),
                            grid.decision_distance2_blocks(warped.clone(), tilde.clone(), &blocks),
                        ]
                    };
                    sums.map(|t| t.into_data())
                })
            });
        }
    }
    group.finish();
}

criterion_group!(
    energy,
    benches,
    prefilter_benches,
    adjoint_benches,
    slope_moment_benches,
    trial_fold_benches
);
criterion_main!(energy);
