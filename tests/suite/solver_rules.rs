//! The solver's rules of SPEC §6 that decide what happens at the edges of a step: the
//! inertia restart of the safeguard, giving up without freezing a frame, decisions summed in
//! float64, the feature blocks' initial estimate, and a NaN that must not lose the run.

use crate::common;

use std::sync::atomic::AtomicBool;

use burn::tensor::Tensor;
use common::{device, values};
use deepmorph::model::energy::data::data_term;
use deepmorph::model::energy::regularizer::regularizer;
use deepmorph::model::grid::Accumulation;
use deepmorph::model::layout::FeatureLayout;
use deepmorph::model::sobel::Sobel;
use deepmorph::model::warp::BSpline;
use deepmorph::solver::backtracking::Backtracking;
use deepmorph::solver::ipalm::{Ipalm, IpalmConfig, LevelState, SweepKind, initial_lipschitz};
use deepmorph::solver::multilevel::{Multilevel, MultilevelConfig};
use deepmorph::solver::observer::{Phase, Termination};
use deepmorph::solver::prox::LinearisedData;
use deepmorph::{Backend, EnergyParams, Grid, Precision};

/// A soft blob centred at `(cy, cx)` on an `n × n` grid, `[1, 3, n, n]`.
fn blob(grid: &Grid, cy: f64, cx: f64) -> Tensor<4> {
    let n = grid.height();
    let values = (0..3 * n * n)
        .map(|p| {
            let (c, i, j) = (p / (n * n), (p / n) % n, p % n);
            let r2 = (i as f64 - cy).powi(2) + (j as f64 - cx).powi(2);
            0.2 + (0.5 + 0.1 * c as f64) * (-r2 / 18.0).exp()
        })
        .collect();
    grid.tensor(values, [1, 3, n, n])
}

/// A deep-model frame of [`blob`]: η-scaled RGB and four feature channels that move with
/// the blob, `[1, 7, n, n]`.
fn deep_frame(grid: &Grid, eta: f64, cy: f64, cx: f64) -> Tensor<4> {
    deep_frame_of(grid, eta, cy, cx, 4)
}

/// [`deep_frame`] with `channels` feature channels.
fn deep_frame_of(grid: &Grid, eta: f64, cy: f64, cx: f64, channels: usize) -> Tensor<4> {
    let features: Vec<Tensor<4>> = (0..channels)
        .map(|c| {
            blob(grid, cy + (c % 7) as f64 * 0.5, cx - (c % 5) as f64 * 0.3).narrow(1, c % 3, 1)
        })
        .collect();
    Tensor::cat(
        vec![blob(grid, cy, cx).mul_scalar(eta), Tensor::cat(features, 1)],
        1,
    )
}

/// `Id + amplitude · bump` with a smooth bump that vanishes on the boundary, `[1, 2, n, n]`.
fn bumped(grid: &Grid, amplitude: f64) -> Tensor<4> {
    let n = grid.height();
    let pi = std::f64::consts::PI;
    let bump: Vec<f64> = (0..2 * n * n)
        .map(|p| {
            let (axis, i, j) = (p / (n * n), (p / n) % n, p % n);
            let (x, y) = (i as f64 / (n - 1) as f64, j as f64 / (n - 1) as f64);
            let edge = i == 0 || j == 0 || i == n - 1 || j == n - 1;
            let s = if edge {
                0.0
            } else {
                (pi * x).sin() * (pi * y).sin()
            };
            if axis == 0 { s } else { 0.5 * s }
        })
        .collect();
    grid.identity(1) + grid.tensor(bump, [1, 2, n, n]).mul_scalar(amplitude)
}

/// The safeguard's local energy `e(φ) = K·R[φ, a] + (K/δ)·D[f_0, f_1, φ]` for `K = 1`.
fn local_energy(grid: &Grid, params: &EnergyParams, f: &[Tensor<4>], phi: Tensor<4>) -> f64 {
    let ipalm = Ipalm::new(grid, *params, FeatureLayout::rgb(), IpalmConfig::default()).unwrap();
    let a = ipalm
        .path_energy()
        .anisotropy()
        .compute(f[1].clone())
        .reshape([1, grid.height(), grid.width()]);
    let r = regularizer(phi.clone(), a, params.lambda, params.mu);
    let d = data_term(&BSpline::new(grid), f[0].clone(), f[1].clone(), phi, 3);
    values(r + d.mul_scalar(1.0 / params.delta))[0]
}

/// SPEC §6, safeguard step 1. `φ_1 = Id` with a previous iterate far on the other side, so
/// that the extrapolated point `φ̃ = Id − β·bump` has a higher local energy than `φ_1`; a
/// large stored `L` keeps the accepted step next to `φ̃`. Doubling `L` only brings the prox
/// closer to `φ̃`: before the restart rule all 30 doublings failed and the step was dropped.
/// Restarted at `φ_1`, the step is accepted and does not raise the local energy.
fn an_overshooting_extrapolation_is_restarted_not_dropped(backend: Backend) {
    let device = device(backend, Precision::F64, true);
    let grid = Grid::new(16, 16, &device, Precision::F64.dtype()).unwrap();
    let params = EnergyParams::rgb();
    let f = vec![blob(&grid, 7.0, 7.0), blob(&grid, 7.0, 8.0)];
    let id = grid.identity(1);
    let mut state = LevelState::new(f.clone(), vec![id.clone()], vec![1e3], vec![]).unwrap();
    state.phi_prev = vec![bumped(&grid, 0.8)];
    let beta = IpalmConfig::default().beta;
    let extrapolated = id.clone() - (bumped(&grid, 0.8) - id.clone()).mul_scalar(beta);
    let (e_current, e_extrapolated) = (
        local_energy(&grid, &params, &f, id.clone()),
        local_energy(&grid, &params, &f, extrapolated),
    );
    assert!(
        e_extrapolated > 1.5 * e_current,
        "the case needs e(φ̃) = {e_extrapolated} well above e(φ_1) = {e_current}"
    );

    let ipalm = Ipalm::new(&grid, params, FeatureLayout::rgb(), IpalmConfig::default()).unwrap();
    let report = ipalm.sweep(&mut state, SweepKind::Joint).unwrap();
    let step = &report.deformation[0];
    assert!(step.restarted, "{step:?}");
    assert!(!step.dropped, "the restart must rescue the step: {step:?}");
    let e_new = local_energy(&grid, &params, &f, state.phi[0].clone());
    assert!(
        e_new <= e_current,
        "the restarted step raised e from {e_current} to {e_new}"
    );
    let moved = values(state.phi[0].clone() - id)
        .iter()
        .fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(moved > 0.0, "the step did not move");
    // The stored L is the one the backtracking accepted, not a safeguard doubling of it.
    let ratio = step.lipschitz / (0.9 * 1e3);
    assert!(
        (ratio.log2() - ratio.log2().round()).abs() < 1e-9
            && ratio <= 2f64.powi(step.trials as i32),
        "stored L {} is not a backtracking trial value",
        step.lipschitz
    );
    assert_eq!(step.safeguard_doublings, 0, "{step:?}");
    // φ_prev ← φ_1: the next sweep extrapolates along the restarted step.
    assert_eq!(values(state.phi_prev[0].clone()), values(grid.identity(1)));
}

/// SPEC §6, *Giving up*: a step whose backtracking runs out of trials keeps `φ_k` and the `L`
/// it started from, so the next sweep starts from `0.9·L` again instead of `0.9·L·2^trials`.
fn an_exhausted_step_keeps_the_estimate_it_started_from(backend: Backend) {
    let device = device(backend, Precision::F64, true);
    let grid = Grid::new(16, 16, &device, Precision::F64.dtype()).unwrap();
    let f = vec![
        blob(&grid, 7.0, 7.0),
        blob(&grid, 7.0, 8.5),
        blob(&grid, 7.5, 9.0),
    ];
    let id = grid.identity(1);
    // Tiny estimates: the first trial's step is huge (inadmissible, or rejected by the
    // decrease test), and one trial is all the rule allows.
    let (l_phi, l_f) = (1e-9, 1e-12);
    let mut state = LevelState::new(
        f.clone(),
        vec![id.clone(), id.clone()],
        vec![l_phi; 2],
        vec![vec![l_f]],
    )
    .unwrap();
    let config = IpalmConfig {
        backtracking: Backtracking {
            max_trials: 1,
            ..Backtracking::default()
        },
        ..IpalmConfig::default()
    };
    let ipalm = Ipalm::new(&grid, EnergyParams::rgb(), FeatureLayout::rgb(), config).unwrap();
    let report = ipalm.sweep(&mut state, SweepKind::Joint).unwrap();
    assert!(report.deformation.iter().all(|s| s.dropped), "{report:?}");
    assert_eq!(report.deformation_drops(), 2);
    assert_eq!(report.feature_drops(), 1);
    assert_eq!(state.l_phi, vec![l_phi; 2]);
    assert_eq!(state.l_f, vec![vec![l_f]]);
    for phi in &state.phi {
        assert_eq!(values(phi.clone()), values(id.clone()), "a dropped φ moved");
    }
    assert_eq!(
        values(state.f[1].clone()),
        values(f[1].clone()),
        "a dropped f moved"
    );
}

/// SPEC §6, "Floating point": decisions between float32 sums that rounding flips, and the
/// float64 accumulation of [`Grid::decision_sum`] gets right. Two sums that are equal in
/// exact arithmetic: `n` copies of 0.1 and `n/2` copies of 0.2 (exactly twice 0.1 in
/// float32), one summand of one of them lowered by one unit in the last place, so exactly
/// that one is the smaller. Summed in float32 the totals are off by up to 4e-2 relative,
/// each in its own way: whichever of the two is lowered, one backend or the other decides
/// "smaller ≤ larger" wrongly; in float64 both are exact.
fn float64_accumulation_decides_what_float32_rounding_flips(backend: Backend) {
    let device = device(backend, Precision::F32, false);
    let grid = Grid::new(256, 256, &device, Precision::F32.dtype()).unwrap();
    assert_eq!(grid.accumulation(), Accumulation::Float64);
    let n = 67 * 256 * 256;
    let (tenth, fifth) = (0.1f32, 0.2f32);
    let rule = Backtracking::default();
    let mut flipped = 0;
    for lower_the_tenths in [true, false] {
        let mut tenths = vec![f64::from(tenth); n];
        let mut fifths = vec![f64::from(fifth); n / 2];
        let exact = n as f64 * f64::from(tenth);
        let (smaller, larger, exact_smaller) = if lower_the_tenths {
            let lowered = f32::from_bits(tenth.to_bits() - 1);
            tenths[12345] = f64::from(lowered);
            (tenths, fifths, exact - f64::from(tenth - lowered))
        } else {
            let lowered = f32::from_bits(fifth.to_bits() - 1);
            fifths[12345] = f64::from(lowered);
            (fifths, tenths, exact - f64::from(fifth - lowered))
        };
        let tensor = |v: Vec<f64>| -> Tensor<2> {
            let len = v.len();
            grid.tensor(v, [len / 256, 256])
        };
        let (smaller, larger) = (tensor(smaller), tensor(larger));
        let sum64 = |t: Tensor<2>| values(grid.decision_sum(t))[0];
        let (s64, l64) = (sum64(smaller.clone()), sum64(larger.clone()));
        assert!(
            (s64 - exact_smaller).abs() <= 1e-12 * exact && (l64 - exact).abs() <= 1e-12 * exact,
            "float64 accumulation: {s64} vs {exact_smaller}, {l64} vs {exact}"
        );
        assert!(rule.accepts(s64, l64, 0.0, 0.0, 1.0, 0.0), "{s64} vs {l64}");
        assert!(
            !rule.accepts(l64, s64, 0.0, 0.0, 1.0, 0.0),
            "{l64} vs {s64}"
        );
        let sum32 = |t: Tensor<2>| values(t.sum())[0];
        let (s32, l32) = (sum32(smaller), sum32(larger));
        let error = (s32 - exact_smaller).abs().max((l32 - exact).abs()) / exact;
        assert!(
            error > 1e-5,
            "float32 sums were accurate here ({error:e} relative)"
        );
        if !rule.accepts(s32, l32, 0.0, 0.0, 1.0, 0.0) {
            flipped += 1;
        }
    }
    assert!(
        flipped >= 1,
        "float32 sums decided both cases rightly on this backend"
    );
}

/// SPEC §6: every feature block starts from `L_f = 2K/(δ·C_tot·H·W)` (the η-scaled RGB block
/// used to start at `η²/(H·W)`, ~40 doublings too low).
fn feature_blocks_start_from_the_data_curvature(backend: Backend) {
    let device = device(backend, Precision::F32, false);
    let grid = Grid::new(32, 48, &device, Precision::F32.dtype()).unwrap();
    let layout = FeatureLayout::deep(1e-6, 64).unwrap();
    let (k, delta) = (8, 0.5);
    let (l_phi, l_f) = initial_lipschitz(&grid, &layout, k, delta);
    let pixels = (32 * 48) as f64;
    assert_eq!(l_phi, vec![1.0 / pixels; k]);
    let want = 2.0 * k as f64 / (delta * 67.0 * pixels);
    assert_eq!(l_f, vec![vec![want, want]; k - 1]);
}

/// The anisotropies' RGB images, narrowed frame by frame before stacking, are exactly the
/// RGB part of the stacked frames (the deep layout's η scaling included).
fn stacked_rgb_parts_equal_the_rgb_part_of_the_stack(backend: Backend) {
    let device = device(backend, Precision::F32, false);
    let layout = FeatureLayout::deep(1e-3, 5).unwrap();
    let frames: Vec<Tensor<4>> = (0..4)
        .map(|i| {
            let data: Vec<f32> = (0..8 * 8 * 12)
                .map(|j| ((i * 97 + j) % 31) as f32 * 1e-3)
                .collect();
            Tensor::from_data(
                burn::tensor::TensorData::new(data, [1, 8, 8, 12]),
                (&device, burn::tensor::DType::F32),
            )
        })
        .collect();
    let stacked = layout.rgb_part(Tensor::cat(frames.clone(), 0));
    let parts = layout.rgb_parts(&frames);
    assert_eq!(parts.dims(), [4, 3, 8, 12]);
    assert_eq!(values(parts), values(stacked));
}

/// A NaN in the optimisation stops the morph with [`Termination::NonFinite`] naming level and
/// sweep, and the state is the last finite iterate (the one after the sweep before).
fn a_nan_stops_with_the_last_finite_iterate(backend: Backend) {
    let device = device(backend, Precision::F32, true);
    let grid = Grid::new(16, 16, &device, Precision::F32.dtype()).unwrap();
    let (a, b) = (blob(&grid, 7.0, 6.0), blob(&grid, 8.0, 9.0));
    let config = MultilevelConfig {
        steps: 3,
        levels: 2,
        sweeps: 4,
        ..MultilevelConfig::default()
    };
    let run = |driver: Multilevel| {
        driver
            .run(
                &device,
                a.clone(),
                b.clone(),
                &mut (),
                &AtomicBool::new(false),
            )
            .unwrap()
    };
    let failed = run(Multilevel::new(config).unwrap().inject_nonfinite(1, 3));
    match &failed.termination {
        Termination::NonFinite {
            level: 1,
            sweep: 3,
            phase: Phase::Joint,
            what,
        } => assert!(what.contains("NaN"), "{what}"),
        other => panic!("expected a non-finite stop at level 1, sweep 3, got {other:?}"),
    }
    let frames = values(failed.state.frames());
    assert!(frames.iter().all(|v| v.is_finite()));
    // The iterate kept is the one after sweep 2 of level 1: the same run interrupted there.
    struct StopAfter<'a>(&'a AtomicBool);
    impl deepmorph::solver::observer::Observer for StopAfter<'_> {
        fn sweep(&mut self, e: &deepmorph::solver::observer::SweepEvent<'_>) {
            if e.level == 1 && e.sweep == 2 {
                self.0.store(true, std::sync::atomic::Ordering::Relaxed);
            }
        }
    }
    let interrupt = AtomicBool::new(false);
    let stopped_early = Multilevel::new(config)
        .unwrap()
        .run(
            &device,
            a.clone(),
            b.clone(),
            &mut StopAfter(&interrupt),
            &interrupt,
        )
        .unwrap();
    assert_eq!(
        stopped_early.termination,
        Termination::Interrupted { level: 1, sweep: 2 }
    );
    let same = |what: &str, got: Tensor<4>, want: Tensor<4>| {
        common::assert_close(what, &values(got), &values(want), 1e-6, 1e-6)
    };
    same(
        "frames",
        failed.state.frames(),
        stopped_early.state.frames(),
    );
    same(
        "deformations",
        failed.state.deformations(),
        stopped_early.state.deformations(),
    );
}

/// Convergence control: with a tolerance a level stops once `E` decreased by less than that
/// over the last 10 sweeps, and says so; with 0 every level runs its `J` sweeps.
fn a_level_stops_when_the_energy_stalls(backend: Backend) {
    use deepmorph::solver::observer::LevelStop;
    let device = device(backend, Precision::F32, true);
    let grid = Grid::new(16, 16, &device, Precision::F32.dtype()).unwrap();
    let (a, b) = (blob(&grid, 7.0, 6.0), blob(&grid, 8.0, 9.0));
    let run = |tolerance: f64| {
        let config = MultilevelConfig {
            steps: 3,
            levels: 2,
            sweeps: 200,
            tolerance,
            ..MultilevelConfig::default()
        };
        Multilevel::new(config)
            .unwrap()
            .run(
                &device,
                a.clone(),
                b.clone(),
                &mut (),
                &AtomicBool::new(false),
            )
            .unwrap()
    };
    let full = run(0.0);
    assert!(
        full.levels
            .iter()
            .all(|l| l.sweeps == 200 && l.stop == LevelStop::Sweeps)
    );
    let early = run(1e-3);
    assert_eq!(early.termination, Termination::Completed);
    assert_eq!(early.levels.len(), 2);
    for level in &early.levels {
        assert_eq!(level.stop, LevelStop::Converged, "{level:?}");
        assert!((11..200).contains(&level.sweeps), "{level:?}");
    }
}

/// The decision sums' own kernels (one pass, products in float64 on flex; composed on
/// ndarray) against the same sums on the host: a plain tensor, a channel block narrowed out
/// of a larger one (a view into a shared buffer) and the product of two of them.
fn decision_sums_are_float64_sums_of_the_float32_values(backend: Backend) {
    let device = device(backend, Precision::F32, true);
    let grid = Grid::new(16, 24, &device, Precision::F32.dtype()).unwrap();
    let host = |seed: f64, n: usize| -> Vec<f64> {
        // Values that float32 holds exactly, so the host sums see what the tensor holds.
        (0..n)
            .map(|i| f64::from(((i as f64 * 0.618 + seed).sin() * 3.0) as f32))
            .collect()
    };
    let (a, b) = (host(0.2, 5 * 16 * 24), host(1.3, 5 * 16 * 24));
    let wide: Tensor<4> = grid.tensor(a.clone(), [1, 5, 16, 24]);
    let other: Tensor<4> = grid.tensor(b.clone(), [1, 5, 16, 24]);
    // Channels 1..4 of both: views with an offset into buffers the full tensors still hold.
    let block = |t: &Tensor<4>| t.clone().narrow(1, 1, 3);
    let plane = 16 * 24;
    let (a_block, b_block) = (&a[plane..4 * plane], &b[plane..4 * plane]);
    let read = |t: Tensor<1>| deepmorph::model::grid::to_host(t)[0];
    // The distance is the norm of the float32 difference, bit for bit: the kernel forms
    // `a − b` in float32 as the tensor op would.
    let distance = read(grid.decision_distance2(block(&wide), block(&other)));
    let of_difference = read(grid.decision_norm2(block(&wide) - block(&other)));
    assert_eq!(
        distance.to_bits(),
        of_difference.to_bits(),
        "{backend:?} distance: {distance} vs {of_difference}"
    );
    let cases = [
        (
            "sum",
            read(grid.decision_sum(wide.clone())),
            a.iter().sum::<f64>(),
        ),
        (
            "norm2 of a block",
            read(grid.decision_norm2(block(&wide))),
            a_block.iter().map(|x| x * x).sum(),
        ),
        (
            "dot of blocks",
            read(grid.decision_dot(block(&wide), block(&other))),
            a_block.iter().zip(b_block).map(|(x, y)| x * y).sum(),
        ),
        (
            "distance of blocks",
            distance,
            a_block
                .iter()
                .zip(b_block)
                .map(|(x, y)| f64::from((x - y) as f32).powi(2))
                .sum(),
        ),
    ];
    for (what, got, want) in cases {
        // float64 sums in another order: equal to a few units of float64 rounding, far below
        // float32's 6e-8.
        assert!(
            (got - want).abs() <= 1e-12 * want.abs().max(1.0),
            "{backend:?} {what}: {got} vs {want}"
        );
    }
}

/// The energy after a sweep reuses the squared residuals the sweep's last steps evaluated
/// (SPEC §10's value, `a_k` from the new frames): equal to evaluating every `D_k` again, which
/// is a float64 sum of the float32 residuals, and to the float32 path energy up to its rounding;
/// in the batched schedule too, whose odd and even passes finish different `D_k`.
fn the_energy_after_a_sweep_reuses_the_sweeps_residuals(backend: Backend) {
    use deepmorph::solver::ipalm::Schedule;
    let device = device(backend, Precision::F32, true);
    let grid = Grid::new(16, 16, &device, Precision::F32.dtype()).unwrap();
    let eta = 1e-3;
    let layout = FeatureLayout::deep(eta, 4).unwrap();
    let frame = |cy: f64, cx: f64| deep_frame(&grid, eta, cy, cx);
    let params = EnergyParams::deep();
    let bspline = BSpline::new(&grid);
    let host_data_terms = |state: &LevelState| -> Vec<f64> {
        (0..state.steps())
            .map(|i| {
                let warped = bspline.interpolate(
                    bspline.coefficients(state.f[i + 1].clone()),
                    state.phi[i].clone(),
                );
                let residual = values(warped)
                    .iter()
                    .zip(values(state.f[i].clone()))
                    // The residual as the tensor holds it: a float32 difference.
                    .map(|(w, f)| f64::from(*w as f32 - f as f32).powi(2))
                    .sum::<f64>();
                residual / (2.0 * 7.0 * 256.0)
            })
            .collect()
    };
    for schedule in [Schedule::Sequential, Schedule::Batched] {
        let config = IpalmConfig {
            schedule,
            ..IpalmConfig::default()
        };
        let ipalm = Ipalm::new(&grid, params, layout.clone(), config).unwrap();
        let mut state = LevelState::initial(
            &grid,
            &layout,
            frame(7.0, 6.0),
            frame(8.0, 9.0),
            3,
            params.delta,
        )
        .unwrap();
        let kinds = [SweepKind::FeaturesOnly, SweepKind::Joint, SweepKind::Joint];
        for (sweep, kind) in kinds.into_iter().enumerate() {
            let report = ipalm.sweep(&mut state, kind).unwrap();
            let what = format!("{backend:?} {schedule:?} sweep {sweep} ({kind:?})");
            let recorded = report.residual_norm2.iter().filter(|n| n.is_some()).count();
            // Every D_k is final after the step that last touched it, in both schedules.
            assert_eq!(recorded, 3, "{what}");
            let reused = ipalm.energy_after(&state, Some(&report));
            let evaluated = ipalm.energy_after(&state, None);
            assert_eq!(reused.regularizer, evaluated.regularizer, "{what}");
            // A value the sweep did not record (a dropped block) is evaluated in its place.
            let mut partial = report.clone();
            partial.residual_norm2[1] = None;
            let mixed = ipalm.energy_after(&state, Some(&partial));
            assert_eq!(mixed.data[0], reused.data[0], "{what}");
            assert_eq!(mixed.data[1], evaluated.data[1], "{what}");
            assert_eq!(mixed.data[2], reused.data[2], "{what}");
            // Two missing values apart: evaluated one at a time, not as one batch of frames.
            let mut apart = report.clone();
            apart.residual_norm2[0] = None;
            apart.residual_norm2[2] = None;
            let apart = ipalm.energy_after(&state, Some(&apart));
            assert_eq!(apart.data[0], evaluated.data[0], "{what}");
            assert_eq!(apart.data[1], reused.data[1], "{what}");
            assert_eq!(apart.data[2], evaluated.data[2], "{what}");
            let host = host_data_terms(&state);
            for k in 0..3 {
                let (r, e, h) = (reused.data[k], evaluated.data[k], host[k]);
                // The steps warp each channel block on its own: float32 rounding apart.
                assert!((r - e).abs() <= 1e-6 * e, "{what} D_{}: {r} vs {e}", k + 1);
                // Both float64 sums of the same float32 residuals.
                assert!((e - h).abs() <= 1e-12 * h, "{what} D_{}: {e} vs {h}", k + 1);
            }
            let float32 = values(ipalm.energy(&state).total)[0];
            let total = reused.total();
            assert!(
                (total - float32).abs() <= 1e-5 * total,
                "{what}: E {total} vs {float32} in float32"
            );
        }
    }
}

/// A sweep that starts from what the previous one carried (`P f_k` and `T[f_k, φ_k]` of
/// the accepted feature trials, and of `f_K` at the `φ_K` of the last deformation step of
/// `K`) leaves the same iterate, bit for bit, with the same decisions, as one that computes
/// everything again: over feature-only and joint sweeps, with `K = 4` so that the feature
/// steps' `f_{k+1}` (`f_K` included) and the first deformation step take carried values,
/// and with few and many feature channels. The batched schedule carries nothing.
fn a_carried_sweep_equals_a_fresh_one(backend: Backend) {
    // 4 feature channels, and 64 and 128 as VGG19's taps have, where the warps read the
    // coefficients channels-last instead of planar.
    for channels in [4, 64, 128] {
        carried_and_fresh_sweeps(backend, channels);
    }
}

fn carried_and_fresh_sweeps(backend: Backend, channels: usize) {
    use deepmorph::solver::ipalm::{Schedule, SweepCarry};
    let device = device(backend, Precision::F32, true);
    let grid = Grid::new(16, 16, &device, Precision::F32.dtype()).unwrap();
    let eta = 1e-3;
    let layout = FeatureLayout::deep(eta, channels).unwrap();
    let params = EnergyParams::deep();
    let ipalm = Ipalm::new(&grid, params, layout.clone(), IpalmConfig::default()).unwrap();
    let initial = LevelState::initial(
        &grid,
        &layout,
        deep_frame_of(&grid, eta, 7.0, 6.0, channels),
        deep_frame_of(&grid, eta, 8.5, 9.0, channels),
        4,
        params.delta,
    )
    .unwrap();
    let (mut fresh, mut carried) = (initial.clone(), initial.clone());
    let mut carry = SweepCarry::default();
    let kinds = [
        SweepKind::FeaturesOnly,
        SweepKind::FeaturesOnly,
        SweepKind::Joint,
        SweepKind::Joint,
        SweepKind::Joint,
    ];
    for (sweep, kind) in kinds.into_iter().enumerate() {
        let what = format!("{backend:?} C {channels}, sweep {sweep} ({kind:?})");
        let a = ipalm.sweep(&mut fresh, kind).unwrap();
        let b = ipalm
            .sweep_carrying(&mut carried, kind, &mut carry)
            .unwrap();
        assert!(!carry.is_empty(), "{what}: nothing carried");
        // As the driver runs it: the energy after the sweep leaves the anisotropies for the
        // next one.
        let evaluated = ipalm.energy_after(&fresh, Some(&a));
        let left = ipalm.energy_after_carrying(&carried, Some(&b), &mut carry);
        assert_eq!(
            format!("{evaluated:?}"),
            format!("{left:?}"),
            "{what}: energy"
        );
        // What makes the carried anisotropies right: a frame's own, bit for bit, whether
        // computed alone (as at step k) or with the others.
        let all = ipalm.anisotropies(&carried);
        for k in 1..=carried.steps() {
            let alone = ipalm
                .path_energy()
                .anisotropy()
                .compute(layout.rgb_part(carried.f[k].clone()));
            assert_eq!(
                values(all.clone().narrow(0, k - 1, 1)),
                values(alone),
                "{what}: a_{k}"
            );
        }
        assert_eq!(a.residual_norm2, b.residual_norm2, "{what}");
        assert_eq!(format!("{a:?}"), format!("{b:?}"), "{what}: decisions");
        assert_eq!(fresh.l_f, carried.l_f, "{what}");
        assert_eq!(fresh.l_phi, carried.l_phi, "{what}");
        for (x, y) in fresh.f.iter().zip(&carried.f) {
            assert_eq!(values(x.clone()), values(y.clone()), "{what}: f");
        }
        for (x, y) in fresh.phi.iter().zip(&carried.phi) {
            assert_eq!(values(x.clone()), values(y.clone()), "{what}: φ");
        }
    }
    // The joint sweeps moved the frames: the carried values were used on a changing state.
    assert_ne!(
        values(initial.phi[0].clone()),
        values(carried.phi[0].clone())
    );
    let batched = Ipalm::new(
        &grid,
        params,
        layout,
        IpalmConfig {
            schedule: Schedule::Batched,
            ..IpalmConfig::default()
        },
    )
    .unwrap();
    batched
        .sweep_carrying(&mut carried, SweepKind::Joint, &mut carry)
        .unwrap();
    assert!(
        carry.is_empty(),
        "{backend:?}: the batched schedule carried something"
    );
}

/// A feature step near its minimiser must not freeze (SPEC §6's decrease test, evaluated
/// on `Q`'s exact quadratic remainder): with the deformations fixed, feature-only sweeps
/// drive `∇Q` to the rounding level of the float32 warps. Tested on `Q(x_new) − Q(x̃)`, the
/// rounding of the two values then exceeded the decrease `‖∇Q‖²/(2L)` the step predicts,
/// every trial failed and `L_f` doubled each sweep until that decrease fell below float64's
/// resolution of `Q` (about 2³⁵ times the curvature; seen on every deep 256² run's coarse
/// levels). The remainder `scale·(‖T[d]‖² + ‖d‖²)` has no such cancellation: the accepted
/// `L_f` stays near the curvature, on both schedules.
fn converged_features_do_not_freeze(backend: Backend) {
    use deepmorph::solver::ipalm::Schedule;
    let device = device(backend, Precision::F32, true);
    let grid = Grid::new(24, 24, &device, Precision::F32.dtype()).unwrap();
    let layout = FeatureLayout::rgb();
    let (k, delta) = (3, EnergyParams::rgb().delta);
    let (a, b) = (blob(&grid, 9.0, 9.0), blob(&grid, 11.0, 13.0));
    for schedule in [Schedule::Sequential, Schedule::Batched] {
        let mut state =
            LevelState::initial(&grid, &layout, a.clone(), b.clone(), k, delta).unwrap();
        for (i, phi) in state.phi.iter_mut().enumerate() {
            *phi = bumped(&grid, 0.6 + 0.3 * i as f64);
        }
        state.phi_prev = state.phi.clone();
        let start = state.l_f[0][0];
        let config = IpalmConfig {
            schedule,
            ..IpalmConfig::default()
        };
        let ipalm = Ipalm::new(&grid, EnergyParams::rgb(), layout.clone(), config).unwrap();
        let mut largest: f64 = 0.0;
        for _ in 0..300 {
            ipalm.sweep(&mut state, SweepKind::FeaturesOnly).unwrap();
            largest = state.l_f.iter().flatten().fold(largest, |m, &l| m.max(l));
        }
        assert!(
            largest < 100.0 * start,
            "{backend:?}, {schedule:?}: L_f reached {largest:e} from {start:e}"
        );
    }
}

/// The batched schedule decides each step on the items still undecided only: an item's
/// decision sum and its prox must then be what they are inside the whole batch, bit for
/// bit, or evaluating fewer items would change the morph.
fn a_batch_item_is_decided_as_inside_the_whole_batch(backend: Backend) {
    let device = device(backend, Precision::F32, false);
    let (h, w, n, c) = (20, 24, 3, 5);
    let grid = Grid::new(h, w, &device, Precision::F32.dtype()).unwrap();
    let wave = |seed: f64, len: usize, amplitude: f64| -> Vec<f64> {
        (0..len)
            .map(|i| (i as f64 * 0.377 + seed).sin() * amplitude)
            .collect()
    };
    let t: Tensor<4> = grid.tensor(wave(0.4, n * c * h * w, 2.0), [n, c, h, w]);
    let each = values(grid.decision_sum_each(t.clone()));
    for (i, got) in each.iter().enumerate() {
        let alone = values(grid.decision_sum(t.clone().narrow(0, i, 1)))[0];
        assert_eq!(got.to_bits(), alone.to_bits(), "{backend:?}, item {i}");
    }

    let bspline = BSpline::new(&grid);
    let frames = |seed: f64| -> Tensor<4> {
        grid.tensor(
            wave(seed, n * c * h * w, 0.3)
                .into_iter()
                .map(|v| v + 0.5)
                .collect(),
            [n, c, h, w],
        )
    };
    let point = grid.identity(n) + grid.tensor(wave(2.1, n * 2 * h * w, 0.4), [n, 2, h, w]);
    let coeffs = bspline.coefficients(frames(0.9));
    let around = |warped: Option<Tensor<4>>| {
        LinearisedData::around(
            &grid,
            &bspline,
            &Sobel::new(&grid),
            coeffs.clone(),
            frames(1.7),
            point.clone(),
            0.05,
            warped,
        )
    };
    let data = around(None);
    let l = [0.7, 3.0, 0.2];
    let whole = data.prox_each(point.clone(), &l);
    // A safeguard restart hands over the warp it has just evaluated at the point: the
    // linearisation must be the one that evaluates it, bit for bit.
    let given = around(Some(bspline.interpolate(coeffs.clone(), point.clone())))
        .prox_each(point.clone(), &l);
    assert_eq!(
        values(given),
        values(whole.clone()),
        "{backend:?}: the linearisation given T[f, point]"
    );
    let items = [2, 0];
    let picked = Tensor::cat(
        items
            .iter()
            .map(|&i| point.clone().narrow(0, i, 1))
            .collect(),
        0,
    );
    let some = data.select(&items).prox_each(picked, &items.map(|i| l[i]));
    for (j, &i) in items.iter().enumerate() {
        assert_eq!(
            values(some.clone().narrow(0, j, 1)),
            values(whole.clone().narrow(0, i, 1)),
            "{backend:?}: item {i} of the selection"
        );
    }
}

/// SPEC §6, "Where a search starts": a deformation search starts from `0.9^(m+1)·L_φ,k`,
/// `m` the sweeps in a row whose search for this `k` accepted its first trial (no restart,
/// no drop); anything else resets `m`. Followed sweep by sweep in both schedules, with the
/// streak recomputed here from each step's own record, not by the solver's rule.
fn deformation_searches_shrink_faster_while_they_accept_at_once(backend: Backend) {
    use deepmorph::solver::ipalm::Schedule;
    let device = device(backend, Precision::F32, true);
    let grid = Grid::new(16, 16, &device, Precision::F32.dtype()).unwrap();
    let params = EnergyParams::rgb();
    let layout = FeatureLayout::rgb();
    let k = 3;
    for schedule in [Schedule::Sequential, Schedule::Batched] {
        let config = IpalmConfig {
            schedule,
            ..IpalmConfig::default()
        };
        let shrink = config.backtracking.shrink;
        let ipalm = Ipalm::new(&grid, params, layout.clone(), config).unwrap();
        let mut state = LevelState::initial(
            &grid,
            &layout,
            blob(&grid, 6.0, 6.0),
            blob(&grid, 8.0, 9.0),
            k,
            params.delta,
        )
        .unwrap();
        let mut expected = vec![0u32; k];
        let (mut longest, mut resets) = (0, 0);
        for sweep in 1..=20 {
            let before = state.l_phi.clone();
            let report = ipalm.sweep(&mut state, SweepKind::Joint).unwrap();
            for (i, step) in report.deformation.iter().enumerate() {
                let what = format!("{backend:?} {schedule:?} sweep {sweep}, k = {}", i + 1);
                assert_eq!(step.streak, expected[i], "{what}: {step:?}");
                let first = step.trials == 1 && !step.restarted && !step.dropped;
                if first {
                    let start = before[i] * shrink.powi(expected[i] as i32 + 1);
                    assert!(
                        (step.lipschitz - start).abs() <= 1e-12 * start,
                        "{what}: accepted L {} is not 0.9^(m+1)·{} = {start}",
                        step.lipschitz,
                        before[i]
                    );
                    expected[i] += 1;
                } else {
                    resets += usize::from(expected[i] > 0);
                    expected[i] = 0;
                }
                longest = longest.max(expected[i]);
            }
            assert_eq!(state.phi_streak, expected, "{schedule:?} sweep {sweep}");
        }
        // The case must exercise the rule: a streak long enough to accelerate, and its end.
        assert!(longest >= 2, "{schedule:?}: longest streak {longest}");
        assert!(resets >= 1, "{schedule:?}: no streak ended");
    }
}

/// An interrupt within a sweep (issue 43 #10): a sweep stopped before any of its blocks and
/// continued from its [`PartialSweep`] (written to JSON and read back, as the checkpoint
/// holds it) leaves the iterate, the stored estimates and streaks, and the report of the
/// sweep run without a stop, bit for bit, in both schedules; and so does the energy after
/// it, which reuses the report's residuals.
fn a_sweep_stopped_between_blocks_goes_on_exactly(backend: Backend) {
    use deepmorph::solver::ipalm::{PartialSweep, Schedule, SweepCarry, SweepEnd};
    use std::cell::Cell;
    let device = device(backend, Precision::F32, true);
    let grid = Grid::new(16, 16, &device, Precision::F32.dtype()).unwrap();
    let eta = 1e-3;
    let layout = FeatureLayout::deep(eta, 4).unwrap();
    let params = EnergyParams::deep();
    let k = 4;
    for schedule in [Schedule::Sequential, Schedule::Batched] {
        let ipalm = Ipalm::new(
            &grid,
            params,
            layout.clone(),
            IpalmConfig {
                schedule,
                ..IpalmConfig::default()
            },
        )
        .unwrap();
        let mut start = LevelState::initial(
            &grid,
            &layout,
            deep_frame(&grid, eta, 7.0, 6.0),
            deep_frame(&grid, eta, 8.5, 9.0),
            k,
            params.delta,
        )
        .unwrap();
        // A state with inertia and streaks, as a sweep in the middle of a level has.
        for _ in 0..2 {
            ipalm.sweep(&mut start, SweepKind::Joint).unwrap();
        }
        let mut whole = start.clone();
        let report = ipalm.sweep(&mut whole, SweepKind::Joint).unwrap();
        let blocks = match schedule {
            Schedule::Sequential => 2 * k - 1,
            Schedule::Batched => 3,
        };
        for stop_after in 1..blocks {
            let what = format!("{backend:?} {schedule:?}, stopped after {stop_after} blocks");
            let mut state = start.clone();
            let asked = Cell::new(0);
            let stop = || {
                asked.set(asked.get() + 1);
                asked.get() >= stop_after
            };
            let mut carry = SweepCarry::default();
            let partial = match ipalm
                .sweep_until(&mut state, SweepKind::Joint, &mut carry, None, &stop)
                .unwrap()
            {
                SweepEnd::Stopped(partial) => partial,
                SweepEnd::Done(_) => panic!("{what}: not stopped"),
            };
            assert_eq!(partial.blocks, stop_after, "{what}");
            // Stopped means stopped: the blocks after it left their values as they were.
            let moved = |a: &[Tensor<4>], b: &[Tensor<4>]| {
                a.iter()
                    .zip(b)
                    .filter(|(x, y)| values((*x).clone()) != values((*y).clone()))
                    .count()
            };
            assert!(
                moved(&state.phi, &whole.phi) + moved(&state.f, &whole.f) > 0,
                "{what}: nothing left to do"
            );
            let json = serde_json::to_string(&partial).unwrap();
            let read: PartialSweep = serde_json::from_str(&json).unwrap();
            assert_eq!(read, partial, "{what}: JSON round trip");
            // A resumed run continues in a new process: nothing carried.
            let mut carry = SweepCarry::default();
            let SweepEnd::Done(continued) = ipalm
                .sweep_until(
                    &mut state,
                    SweepKind::Joint,
                    &mut carry,
                    Some(read),
                    &|| false,
                )
                .unwrap()
            else {
                panic!("{what}: stopped again");
            };
            for (x, y) in state.f.iter().zip(&whole.f) {
                assert_eq!(values(x.clone()), values(y.clone()), "{what}: f");
            }
            for (x, y) in state.f_prev.iter().zip(&whole.f_prev) {
                assert_eq!(values(x.clone()), values(y.clone()), "{what}: f_prev");
            }
            for (x, y) in state.phi.iter().zip(&whole.phi) {
                assert_eq!(values(x.clone()), values(y.clone()), "{what}: φ");
            }
            for (x, y) in state.phi_prev.iter().zip(&whole.phi_prev) {
                assert_eq!(values(x.clone()), values(y.clone()), "{what}: φ_prev");
            }
            assert_eq!(state.l_phi, whole.l_phi, "{what}");
            assert_eq!(state.l_f, whole.l_f, "{what}");
            assert_eq!(state.phi_streak, whole.phi_streak, "{what}");
            assert_eq!(continued.deformation, report.deformation, "{what}");
            assert_eq!(continued.features, report.features, "{what}");
            assert_eq!(continued.residual_norm2, report.residual_norm2, "{what}");
            assert_eq!(
                format!("{:?}", ipalm.energy_after(&state, Some(&continued))),
                format!("{:?}", ipalm.energy_after(&whole, Some(&report))),
                "{what}: energy"
            );
        }
    }
}

/// The steps' fused updates (`update_op`) are the composed chains they replace, bit for bit:
/// the extrapolation `x + (x − x_prev)·β` and a feature trial's `x̃ − ∇Q·(1/L)`, one `L` per
/// item and channel block, on planes that straddle the flex kernel's chunks; where decision
/// sums are float64, the same with the distances they fold.
fn fused_updates_equal_the_composed_chains(backend: Backend) {
    use deepmorph::solver::update_op::{
        descend, descend_distance2, extrapolate, extrapolate_distance2,
    };
    let device = device(backend, Precision::F32, true);
    let grid = Grid::new(96, 90, &device, burn::tensor::DType::F32).unwrap();
    let shape = [2, 3, 96, 90];
    let len: usize = shape.iter().product();
    let wave = |seed: f64| {
        let values = (0..len)
            .map(|i| (i as f64 * 0.377 + seed).sin() * 1.7)
            .collect();
        grid.tensor(values, shape)
    };
    let (x, previous, g) = (wave(0.1), wave(2.3), wave(4.9));
    let beta = std::f64::consts::FRAC_1_SQRT_2;
    assert_eq!(
        values(extrapolate(x.clone(), previous.clone(), beta)),
        values(x.clone() + (x.clone() - previous.clone()).mul_scalar(beta)),
        "{backend:?}: extrapolation"
    );
    // One L per item and channel block; L = ∞ leaves a block at x.
    let blocks = [0..1, 1..3];
    let lipschitz = [3.7, 0.061, f64::INFINITY, 12.5];
    let stepped = descend(x.clone(), g.clone(), &lipschitz, &blocks);
    for (e, l) in lipschitz.iter().enumerate() {
        let (i, block) = (e / 2, blocks[e % 2].clone());
        let part = |t: &Tensor<4>| {
            t.clone()
                .narrow(0, i, 1)
                .narrow(1, block.start, block.len())
        };
        let composed = if l.is_finite() {
            values(part(&x) - part(&g).mul_scalar(1.0 / l))
        } else {
            values(part(&x))
        };
        assert_eq!(
            values(part(&stepped)),
            composed,
            "{backend:?}: gradient step of item {i}, channels {block:?}"
        );
    }
    // With float64 decision sums, the updates that fold the new frame's distance to a third
    // one as they write it: the same frame, and the sums `decision_distance2_blocks` gives.
    if grid.accumulation() == Accumulation::Float64 {
        let r = wave(6.1);
        let (fused, sums) =
            descend_distance2(&grid, x.clone(), g.clone(), &lipschitz, &blocks, r.clone());
        assert_eq!(
            values(fused),
            values(stepped.clone()),
            "{backend:?}: gradient step"
        );
        assert_eq!(
            values(sums),
            values(grid.decision_distance2_blocks(r.clone(), stepped, &blocks)),
            "{backend:?}: the gradient step's distances"
        );
        // Blocks the fused kernels do not take: the two passes.
        let thirds = [0..1, 1..2, 2..3];
        let six = [3.7, 0.061, 1.5, 12.5, 0.25, f64::INFINITY];
        let (stepped, sums) =
            descend_distance2(&grid, x.clone(), g.clone(), &six, &thirds, r.clone());
        let composed = descend(x.clone(), g.clone(), &six, &thirds);
        assert_eq!(
            values(sums),
            values(grid.decision_distance2_blocks(r.clone(), composed.clone(), &thirds)),
            "{backend:?}: three blocks' distances"
        );
        assert_eq!(
            values(stepped),
            values(composed),
            "{backend:?}: three blocks"
        );
        let every_channel = 0..3;
        let whole = std::slice::from_ref(&every_channel);
        let (fused, sums) =
            extrapolate_distance2(&grid, x.clone(), previous.clone(), beta, whole, r.clone());
        let composed = extrapolate(x, previous, beta);
        assert_eq!(
            values(fused),
            values(composed.clone()),
            "{backend:?}: extrapolation"
        );
        assert_eq!(
            values(sums),
            values(grid.decision_distance2_blocks(r, composed, whole)),
            "{backend:?}: the extrapolation's distances"
        );
    }
}

on_each_cpu_backend!(
    a_sweep_stopped_between_blocks_goes_on_exactly,
    deformation_searches_shrink_faster_while_they_accept_at_once,
    a_carried_sweep_equals_a_fresh_one,
    converged_features_do_not_freeze,
    the_energy_after_a_sweep_reuses_the_sweeps_residuals,
    decision_sums_are_float64_sums_of_the_float32_values,
    a_level_stops_when_the_energy_stalls,
    an_overshooting_extrapolation_is_restarted_not_dropped,
    an_exhausted_step_keeps_the_estimate_it_started_from,
    float64_accumulation_decides_what_float32_rounding_flips,
    feature_blocks_start_from_the_data_curvature,
    stacked_rgb_parts_equal_the_rgb_part_of_the_stack,
    a_batch_item_is_decided_as_inside_the_whole_batch,
);

/// The non-finite path and the fused updates on every backend, wgpu included.
mod every_backend {
    use super::*;

    on_each_backend!(
        a_nan_stops_with_the_last_finite_iterate,
        fused_updates_equal_the_composed_chains
    );
}
