//! SPEC §10 properties of the discrete model, on every backend in float32 and on the CPU
//! backends in float64: `T[f, Id] = f`, `T` linear in `f`, `W(I) = 0`, `∂W/∂J(I) = 0`, and
//! `E = 0` (with a vanishing gradient) for `A = B` at the initial state.

use crate::common;

use burn::tensor::{Device, Tensor};
use common::{Rng, assert_close, device, values};
use deepmorph::check::density_gradient;
use deepmorph::model::deformation::{admissible_each, jacobian};
use deepmorph::model::energy::density::density;
use deepmorph::model::energy::path::PathEnergy;
use deepmorph::model::energy::regularizer::regularizer;
use deepmorph::model::resample::prolongate_deformation;
use deepmorph::model::warp::BSpline;
use deepmorph::{Backend, EnergyParams, Grid, Precision};

/// Grids of both parities and aspect ratios, including the minimum size 4.
const SIZES: [(usize, usize); 4] = [(4, 4), (9, 11), (16, 13), (32, 32)];

/// Absolute tolerance for quantities that are exactly 0 in exact arithmetic, for values of
/// order 1: a few ulps of the precision, summed over a 4×4 stencil.
fn zero_tolerance(precision: Precision) -> f64 {
    match precision {
        Precision::F32 => 2e-6,
        Precision::F64 => 1e-14,
    }
}

fn grid(device: &Device, precision: Precision, (h, w): (usize, usize)) -> Grid {
    Grid::new(h, w, device, precision.dtype()).unwrap()
}

fn warp_of_identity_is_identity(backend: Backend, precision: Precision) {
    let device = device(backend, precision, false);
    let mut rng = Rng(10);
    for size in SIZES {
        let grid = grid(&device, precision, size);
        let (h, w) = size;
        let f_host = rng.smooth_image(3, h, w);
        let f: Tensor<4> = grid.tensor(f_host.clone(), [1, 3, h, w]);
        let warped = BSpline::new(&grid).warp(f, grid.identity(1));
        let what = format!("T[f, Id] on {h}x{w}");
        assert_close(
            &what,
            &values(warped),
            &f_host,
            0.0,
            zero_tolerance(precision),
        );
    }
}

fn warp_is_linear_in_the_image(backend: Backend, precision: Precision) {
    let device = device(backend, precision, false);
    let mut rng = Rng(11);
    for size in SIZES {
        let grid = grid(&device, precision, size);
        let (h, w) = size;
        let bspline = BSpline::new(&grid);
        let phi: Tensor<4> = grid.tensor(rng.smooth_deformation(1, h, w, 0.8), [1, 2, h, w]);
        assert_eq!(admissible_each(&grid, phi.clone()), vec![true]);
        let f: Tensor<4> = grid.tensor(rng.smooth_image(2, h, w), [1, 2, h, w]);
        let g: Tensor<4> = grid.tensor(rng.smooth_image(2, h, w), [1, 2, h, w]);
        let (alpha, beta) = (0.7, -1.3);
        let combined = bspline.warp(
            f.clone().mul_scalar(alpha) + g.clone().mul_scalar(beta),
            phi.clone(),
        );
        let separate =
            bspline.warp(f, phi.clone()).mul_scalar(alpha) + bspline.warp(g, phi).mul_scalar(beta);
        assert_close(
            &format!("T linear on {h}x{w}"),
            &values(combined),
            &values(separate),
            0.0,
            2.0 * zero_tolerance(precision),
        );
    }
}

/// Each channel's coefficients and warp depend on that channel alone, bit for bit: a frame
/// whose first block changed warps its other channels to the same values. A feature step
/// relies on it: it searches the blocks of a frame in lockstep, and a block decided in an
/// earlier round is evaluated again inside the later rounds' frames.
fn a_channels_warp_does_not_depend_on_the_others(backend: Backend, precision: Precision) {
    let device = device(backend, precision, false);
    let mut rng = Rng(12);
    for (h, w) in [(9, 11), (16, 13)] {
        let grid = grid(&device, precision, (h, w));
        let bspline = BSpline::new(&grid);
        let c = 3 + 64;
        let f: Tensor<4> = grid.tensor(rng.smooth_image(c, h, w), [1, c, h, w]);
        let other: Tensor<4> = grid.tensor(rng.smooth_image(3, h, w), [1, 3, h, w]);
        let changed = Tensor::cat(vec![other, f.clone().narrow(1, 3, 64)], 1);
        let phi: Tensor<4> = grid.tensor(rng.smooth_deformation(1, h, w, 0.8), [1, 2, h, w]);
        let rest = |t: Tensor<4>| values(t.narrow(1, 3, 64));
        let (coeffs, coeffs_changed) = (
            bspline.coefficients(f.clone()),
            bspline.coefficients(changed.clone()),
        );
        assert_eq!(
            rest(coeffs.clone()),
            rest(coeffs_changed.clone()),
            "{backend:?} {precision:?} {h}x{w}: coefficients"
        );
        assert_eq!(
            rest(bspline.interpolate(coeffs, phi.clone())),
            rest(bspline.interpolate(coeffs_changed, phi)),
            "{backend:?} {precision:?} {h}x{w}: warp"
        );
    }
}

fn density_vanishes_at_identity(backend: Backend, precision: Precision) {
    let device = device(backend, precision, true);
    let (h, w) = (9, 11);
    let grid = grid(&device, precision, (h, w));
    for params in [EnergyParams::rgb(), EnergyParams::deep()] {
        let (lambda, mu) = (params.lambda, params.mu);
        let id = grid.identity(1).require_grad();
        let j = jacobian(id.clone());
        let zeros = vec![0.0; h * w];
        // J(Id) = I exactly (differences of integers), hence W and ∂W/∂J are exactly 0.
        assert_eq!(values(j.det()), vec![1.0; h * w]);
        assert_eq!(values(density(&j, lambda, mu)), zeros);
        let g = density_gradient(&j, lambda, mu);
        for entry in [g.j00, g.j01, g.j10, g.j11] {
            assert_eq!(values(entry), zeros);
        }
        let a = grid.full([1, h, w], 0.5);
        let r = regularizer(id.clone(), a, lambda, mu);
        assert_eq!(values(r.clone()), vec![0.0]);
        let grads = r.sum().backward();
        assert_eq!(values(id.grad(&grads).unwrap()), vec![0.0; 2 * h * w]);
    }
}

/// `A = B`: the initial state (SPEC §7: `f_k` interpolates linearly between `A` and `B`,
/// `φ_k = Id`) is the constant path, with `E = 0` and `∇E = 0`.
fn constant_path_has_zero_energy(backend: Backend, precision: Precision) {
    let device = device(backend, precision, true);
    let (h, w, c, k) = (16, 13, 3, 4);
    let grid = grid(&device, precision, (h, w));
    let image = Rng(12).smooth_image(c, h, w);
    let f: Tensor<4> = grid
        .tensor(image.repeat(k + 1), [k + 1, c, h, w])
        .require_grad();
    let phi = grid.identity(k).require_grad();
    let energy = PathEnergy::new(&grid, EnergyParams::rgb(), c).unwrap();
    let a = energy.anisotropy().compute(f.clone().narrow(0, 1, k));
    let value = energy.value(f.clone(), phi.clone(), a);
    let tol = zero_tolerance(precision);
    // E is a mean of squared residuals of size `tol`, so it vanishes to `tol²`.
    assert_close(
        "E(A = B)",
        &values(value.total.clone()),
        &[0.0],
        0.0,
        tol * tol,
    );
    let grads = value.total.backward();
    let grad_f = values(f.grad(&grads).unwrap().narrow(0, 1, k - 1));
    let grad_phi = values(phi.grad(&grads).unwrap());
    // ∇E is of the order of the residual over the pixel count.
    let grad_tol = tol * k as f64 / (h * w) as f64;
    assert_close(
        "dE/df(A = B)",
        &grad_f,
        &vec![0.0; grad_f.len()],
        0.0,
        grad_tol,
    );
    assert_close(
        "dE/dphi(A = B)",
        &grad_phi,
        &vec![0.0; grad_phi.len()],
        0.0,
        grad_tol,
    );
}

/// Prolongating `Id` gives `Id`: a multilevel run of `A = B` stays constant across levels.
fn identity_prolongates_to_identity(backend: Backend, precision: Precision) {
    let device = device(backend, precision, false);
    let coarse = grid(&device, precision, (8, 10));
    let fine = grid(&device, precision, (16, 20));
    let phi = prolongate_deformation(&coarse, &fine, coarse.identity(2));
    assert_close(
        "prolongated Id",
        &values(phi),
        &values(fine.identity(2)),
        0.0,
        8.0 * zero_tolerance(precision),
    );
}

/// In-between frames (`model::inbetween`): `K + 1` of them are the frames themselves; on a
/// blob translated by a constant `d` per step they move linearly, `s·d` into a step.
fn inbetween_frames_move_linearly(backend: Backend, precision: Precision) {
    use deepmorph::model::inbetween::inbetween;
    let device = device(backend, precision, false);
    let (h, w, steps) = (24, 40, 2);
    let grid = grid(&device, precision, (h, w));
    // A smooth blob whose centre moves 6 columns per step: u_k(x) = blob(x − (8 + 6k)).
    let blob = |centre: f64| -> Vec<f64> {
        (0..3 * h * w)
            .map(|i| {
                let (r, c) = (((i / w) % h) as f64, (i % w) as f64);
                (-((r - 12.0).powi(2) + (c - centre).powi(2)) / 18.0).exp()
            })
            .collect()
    };
    let frames_host: Vec<f64> = (0..=steps)
        .flat_map(|k| blob(8.0 + 6.0 * k as f64))
        .collect();
    let frames: Tensor<4> = grid.tensor(frames_host, [steps + 1, 3, h, w]);
    // u_{k−1} = u_k ∘ φ_k with φ_k = Id + (0, 6): a constant shift of 6 columns.
    let shift: Vec<f64> = (0..2 * h * w)
        .map(|i| if i < h * w { 0.0 } else { 6.0 })
        .collect();
    let phi = grid.identity(steps) + grid.tensor(shift.repeat(steps), [steps, 2, h, w]);

    let same = inbetween(&grid, frames.clone(), phi.clone(), steps + 1).unwrap();
    assert_eq!(
        values(same),
        values(frames.clone()),
        "K + 1 in-between frames are the frames"
    );

    // 5 frames: the centre at 8, 11, 14, 17, 20; compare with the blob there.
    let clip = values(inbetween(&grid, frames, phi.clone(), 5).unwrap());
    for j in 0..5 {
        let want = blob(8.0 + 3.0 * j as f64);
        // Away from the side columns (the mirror boundary shows there).
        let got = &clip[j * 3 * h * w..(j + 1) * 3 * h * w];
        let interior = |i: &usize| (4..w - 4).contains(&(i % w));
        let err = (0..3 * h * w)
            .filter(interior)
            .map(|i| (got[i] - want[i]).abs())
            .fold(0.0, f64::max);
        assert!(err < 0.02, "frame {j}: max error {err}");
    }
    assert!(inbetween(&grid, grid.full([3, 3, h, w], 0.0), phi, 2).is_err());
}

macro_rules! in_both_precisions {
    ($($name:ident),* $(,)?) => {
        mod f32 {
            use super::*;
            $( fn $name(backend: Backend) { super::$name(backend, Precision::F32) } )*
            on_each_backend!($($name),*);
        }
        mod f64 {
            use super::*;
            $( fn $name(backend: Backend) { super::$name(backend, Precision::F64) } )*
            on_each_cpu_backend!($($name),*);
        }
    };
}

in_both_precisions!(
    warp_of_identity_is_identity,
    warp_is_linear_in_the_image,
    a_channels_warp_does_not_depend_on_the_others,
    density_vanishes_at_identity,
    constant_path_has_zero_energy,
    identity_prolongates_to_identity,
    inbetween_frames_move_linearly,
);
