//! Every golden case of SPEC §0–§5 and §7's resizing (`tests/golden/README.md`), in float32 on
//! every compiled backend, at the SPEC tolerance: `max|got − want| ≤ 1e-4 · max|want| + 1e-7`.
//!
//! Gradients are checked twice: Burn autodiff and the hand-derived adjoints.

use crate::common;

use burn::tensor::{DType, Device, Tensor};
use common::{Golden, assert_close, assert_golden, device, grid_for, tensor, values};
use deepmorph::check::data_term_gradient;
use deepmorph::check::density_gradient;
use deepmorph::check::regularizer_gradient;
use deepmorph::check::{self, bspline_prefilter_taps25};
use deepmorph::check::{domain_derivative, gaussian_smoothing};
use deepmorph::model::deformation::{Jacobian, admissible_each, jacobian};
use deepmorph::model::energy::anisotropy::Anisotropy;
use deepmorph::model::energy::data::data_term;
use deepmorph::model::energy::density::density;
use deepmorph::model::energy::path::PathEnergy;
use deepmorph::model::energy::regularizer::regularizer;
use deepmorph::model::resample::{Resize, prolongate_deformation};
use deepmorph::model::separable::Separable;
use deepmorph::model::sobel::Sobel;
use deepmorph::model::stencil::{Matrix, bspline_prefilter, gaussian_taps, mirror_index};
use deepmorph::model::warp::BSpline;
use deepmorph::{Backend, EnergyParams, Grid, Precision};

const F32: DType = DType::F32;

/// A golden case opened on one backend in float32.
struct Case {
    golden: Golden,
    device: Device,
}

impl Case {
    fn open(name: &str, backend: Backend, autodiff: bool) -> Self {
        Self {
            golden: Golden::load(name),
            device: device(backend, Precision::F32, autodiff),
        }
    }

    fn input<const D: usize>(&self, name: &str) -> Tensor<D> {
        tensor(self.golden.input(name), &self.device, F32)
    }

    fn grid(&self, input: &str) -> Grid {
        grid_for(&self.golden.input(input).shape, &self.device, F32)
    }

    fn check<const D: usize>(&self, output: &str, got: Tensor<D>) {
        let what = format!("{}.{output}", self.golden.name);
        assert_golden(&what, &values(got), self.golden.output(output));
    }

    fn check_host(&self, output: &str, got: &[f64]) {
        let what = format!("{}.{output}", self.golden.name);
        assert_golden(&what, got, self.golden.output(output));
    }

    fn param(&self, name: &str) -> f64 {
        self.golden.param(name)
    }
}

/// The Jacobian of golden matrices stored as `J[a][b][...]`, each entry a `[1, 1, n]` map.
fn jacobian_of(j: Tensor<4>) -> Jacobian {
    // j: [1, 2, 2, n] after the leading unit dim.
    let [_, _, _, n] = j.dims();
    let entry = |a: usize, b: usize| j.clone().narrow(1, a, 1).narrow(2, b, 1).reshape([1, 1, n]);
    Jacobian {
        j00: entry(0, 0),
        j01: entry(0, 1),
        j10: entry(1, 0),
        j11: entry(1, 1),
    }
}

#[test]
fn mirror_index_matches_the_spec() {
    let golden = Golden::load("mirror_index");
    let indices = &golden.input("i").data;
    for n in [2usize, 4, 9, 11] {
        let got: Vec<f64> = indices
            .iter()
            .map(|&i| mirror_index(i as i64, n) as f64)
            .collect();
        assert_eq!(got, golden.output(&format!("m_n{n}")).data, "n = {n}");
    }
}

#[test]
fn prefilter_matrices_and_taps() {
    let golden = Golden::load("prefilter_9x11");
    for n in [9usize, 11] {
        let p = bspline_prefilter(n);
        assert_golden(
            &format!("P1d_{n}"),
            &p.data,
            golden.output(&format!("P1d_{n}")),
        );
    }
    assert_golden(
        "taps25",
        &bspline_prefilter_taps25(),
        golden.output("taps25"),
    );
}

fn prefilter(backend: Backend) {
    let case = Case::open("prefilter_9x11", backend, false);
    let grid = case.grid("f");
    let f: Tensor<4> = case.input("f");
    case.check("c", BSpline::new(&grid).coefficients(f.clone()));
    let taps = bspline_prefilter_taps25();
    let truncated = Separable::new(
        &grid,
        &Matrix::from_stencil(grid.height(), &taps),
        &Matrix::from_stencil(grid.width(), &taps),
    );
    case.check("c_trunc25", truncated.apply(f));
}

/// `T[f, φ]` and the gradients of `Σ w · T[f, φ]`, by autodiff and by hand.
fn check_warp(case: &Case, with_identity: bool) {
    let grid = case.grid("f");
    let bspline = BSpline::new(&grid);
    let f: Tensor<4> = case.input::<4>("f").require_grad();
    let phi: Tensor<4> = case.input::<4>("phi").require_grad();
    let w: Tensor<4> = case.input("w");

    let warped = bspline.warp(f.clone(), phi.clone());
    case.check("T_phi", warped.clone());
    if with_identity {
        case.check("T_id", bspline.warp(f.clone(), grid.identity(1)));
    }

    let grads = (warped * w.clone()).sum().backward();
    case.check("grad_f", f.grad(&grads).expect("grad f"));
    case.check("grad_phi", phi.grad(&grads).expect("grad phi"));

    // Hand-derived: Pᵀ Bᵀ w for f, and Σ_c w_c ∂_p T_c with β' for φ.
    let (f, phi) = (f.detach(), phi.detach());
    let hand_f = check::coefficients_adjoint(
        &bspline,
        check::interpolate_adjoint(&bspline, w.clone(), phi.clone()),
    );
    case.check("grad_f", hand_f);
    let (d0, d1) = check::interpolate_position_derivative(&bspline, bspline.coefficients(f), phi);
    let along = |d: Tensor<4>| (d * w.clone()).sum_dim(1);
    case.check("grad_phi", Tensor::cat(vec![along(d0), along(d1)], 1));
}

fn warp_admissible(backend: Backend) {
    check_warp(&Case::open("warp_9x11", backend, true), true);
}

fn warp_clamped(backend: Backend) {
    check_warp(&Case::open("warp_clamp_10x13", backend, true), false);
}

fn energy_density(backend: Backend) {
    let case = Case::open("energy_density", backend, true);
    for model in ["rgb", "deep"] {
        let lambda = case.param(&format!("lambda_{model}"));
        let mu = case.param(&format!("mu_{model}"));

        let j: Tensor<4> = case.input::<4>("J").require_grad();
        let jac = jacobian_of(j.clone());
        let w = density(&jac, lambda, mu);
        case.check(&format!("W_{model}"), w.clone());
        let grads = w.sum().backward();
        case.check(&format!("dW_dJ_{model}"), j.grad(&grads).expect("grad J"));

        let hand = density_gradient(&jacobian_of(j.detach()), lambda, mu);
        let hand = check::stacked(&hand); // [1, 2, 2, 1, 12]
        case.check(&format!("dW_dJ_{model}"), hand);

        let nonpos = jacobian_of(case.input("J_nonpos"));
        case.check(&format!("W_nonpos_{model}"), density(&nonpos, lambda, mu));
    }
}

fn jacobian_energy(backend: Backend) {
    let case = Case::open("jacobian_energy_10x13", backend, true);
    let (lambda, mu) = (case.param("lambda"), case.param("mu"));
    let grid = case.grid("phi");
    let phi: Tensor<4> = case.input::<4>("phi").require_grad();
    let a: Tensor<3> = case.input("a");

    let jac = jacobian(phi.clone());
    case.check("J", check::stacked(&jac));
    case.check("det", jac.det());
    case.check("W", density(&jac, lambda, mu));
    let r = regularizer(phi.clone(), a.clone(), lambda, mu);
    case.check("R", r.clone());
    let grads = r.sum().backward();
    case.check("grad_R_phi", phi.grad(&grads).expect("grad phi"));
    case.check(
        "grad_R_phi",
        regularizer_gradient(phi.clone().detach(), a, lambda, mu),
    );
    assert_eq!(admissible_each(&grid, phi.detach()), vec![true]);
}

fn jacobian_energy_fold(backend: Backend) {
    let case = Case::open("jacobian_energy_fold_9x11", backend, false);
    let (lambda, mu) = (case.param("lambda"), case.param("mu"));
    let grid = case.grid("phi");
    let phi: Tensor<4> = case.input("phi");
    let jac = jacobian(phi.clone());
    case.check("J", check::stacked(&jac));
    case.check("det", jac.det());
    case.check("W", density(&jac, lambda, mu));
    case.check("R", regularizer(phi.clone(), case.input("a"), lambda, mu));
    let admissible = admissible_each(&grid, phi);
    let want = case.golden.output("admissible").data[0] != 0.0;
    assert_eq!(admissible, vec![want]);
}

fn gaussian(backend: Backend) {
    let case = Case::open("gaussian_10x13", backend, false);
    let grid = case.grid("u");
    let u: Tensor<4> = case.input("u");
    for (s, name) in [(case.param("sigma"), "sigma"), (case.param("rho"), "rho")] {
        case.check_host(&format!("taps_{name}"), &gaussian_taps(s));
        case.check(
            &format!("smooth_{name}"),
            gaussian_smoothing(&grid, s).apply(u.clone()),
        );
    }
}

fn anisotropy_case(backend: Backend, name: &str, intermediates: bool) {
    let case = Case::open(name, backend, false);
    let grid = case.grid("u");
    let (sigma, rho) = (case.param("sigma"), case.param("rho"));
    let op = Anisotropy::new(&grid, sigma, rho, case.param("xi1"), case.param("xi2")).unwrap();
    let u: Tensor<4> = case.input("u");
    let [_, c, h, w] = u.dims();
    if intermediates {
        let smooth = gaussian_smoothing(&grid, sigma).apply(u.clone());
        case.check("smooth_sigma", smooth.clone());
        let d0 = domain_derivative(&grid, 0).apply(smooth.clone());
        let d1 = domain_derivative(&grid, 1).apply(smooth);
        case.check("grad_domain", Tensor::stack::<5>(vec![d0, d1], 2));
    }
    case.check(
        "smoothed_grad",
        check::smoothed_gradient(&op, u.clone()).reshape([2 * c, h, w]),
    );
    case.check("a", op.compute(u));
}

fn anisotropy(backend: Backend) {
    anisotropy_case(backend, "anisotropy_10x13", true);
}

fn anisotropy_strong(backend: Backend) {
    anisotropy_case(backend, "anisotropy_xi1_2_10x13", false);
}

fn sobel(backend: Backend) {
    let case = Case::open("sobel_9x11", backend, false);
    let grid = case.grid("g");
    case.check("sobel", Sobel::new(&grid).gradient(case.input("g")));
}

fn data_term_case(backend: Backend, name: &str) {
    let case = Case::open(name, backend, true);
    let c_tot = case.param("C_tot") as usize;
    let grid = case.grid("f");
    let bspline = BSpline::new(&grid);
    let f: Tensor<4> = case.input::<4>("f").require_grad();
    let f_tilde: Tensor<4> = case.input::<4>("f_tilde").require_grad();
    let phi: Tensor<4> = case.input::<4>("phi").require_grad();

    let d = data_term(&bspline, f.clone(), f_tilde.clone(), phi.clone(), c_tot);
    case.check("D", d.clone());
    let grads = d.sum().backward();
    case.check("grad_f", f.grad(&grads).expect("grad f"));
    case.check("grad_f_tilde", f_tilde.grad(&grads).expect("grad f~"));
    case.check("grad_phi", phi.grad(&grads).expect("grad phi"));

    let hand = data_term_gradient(&bspline, f.detach(), f_tilde.detach(), phi.detach(), c_tot);
    case.check("grad_f", hand.f);
    case.check("grad_f_tilde", hand.f_tilde);
    case.check("grad_phi", hand.phi);
}

fn data_term_c3(backend: Backend) {
    data_term_case(backend, "data_term_c3_10x13");
}

fn data_term_c5(backend: Backend) {
    data_term_case(backend, "data_term_c5_9x11");
}

fn path_energy(backend: Backend) {
    let case = Case::open("path_energy_K3_9x11", backend, true);
    let params = EnergyParams {
        lambda: case.param("lambda"),
        mu: case.param("mu"),
        delta: case.param("delta"),
        sigma: case.param("sigma"),
        rho: case.param("rho"),
        xi1: case.param("xi1"),
        xi2: case.param("xi2"),
    };
    let k = case.param("K") as usize;
    let f: Tensor<4> = case.input::<4>("f").require_grad();
    let phi: Tensor<4> = case.input::<4>("phi").require_grad();
    let a: Tensor<3> = case.input("a");
    let grid = case.grid("f");
    let energy = PathEnergy::new(&grid, params, 3).unwrap();

    let value = energy.value(f.clone(), phi.clone(), a.clone());
    case.check("E", value.total.clone());
    case.check("R_k", value.regularizer);
    case.check("D_k", value.data);
    let grads = value.total.backward();
    let grad_f = f.grad(&grads).expect("grad f").narrow(0, 1, k - 1);
    case.check("grad_f_interior", grad_f);
    case.check("grad_phi", phi.grad(&grads).expect("grad phi"));

    let hand = check::path_energy_gradient(&energy, f.detach(), phi.detach(), a);
    case.check("grad_f_interior", hand.f_interior);
    case.check("grad_phi", hand.phi);
}

fn resize_and_prolongate(backend: Backend) {
    let case = Case::open("resize_prolong_20x28", backend, false);
    let fine = case.grid("u");
    let coarse = case.grid("phi_coarse");
    let tiny = Grid::new(5, 7, &case.device, F32).unwrap();
    let u: Tensor<4> = case.input("u");

    let down2 = Resize::new(&fine, &coarse).apply(u.clone());
    case.check("down2", down2.clone());
    case.check("down4", Resize::new(&fine, &tiny).apply(u));
    case.check("up2", Resize::new(&coarse, &fine).apply(down2));

    let phi_fine = prolongate_deformation(&coarse, &fine, case.input("phi_coarse"));
    case.check("phi_fine", phi_fine.clone());
    assert_eq!(admissible_each(&fine, phi_fine), vec![true]);
    let fold = prolongate_deformation(&coarse, &fine, case.input("phi_coarse_fold"));
    case.check("phi_fine_fold", fold);
}

/// The README's floor: a tensor that is zero up to rounding must stay within the 1e-7
/// absolute floor, and a wrong value must fail (the comparison itself can fail).
#[test]
fn golden_comparison_rejects_a_wrong_value() {
    let want = [1.0, 2.0, -4.0];
    assert_close("exact", &[1.0, 2.0, -4.0], &want, 1e-4, 1e-7);
    let outcome = std::panic::catch_unwind(|| {
        assert_close("off", &[1.0, 2.001, -4.0], &want, 1e-4, 1e-7);
    });
    assert!(outcome.is_err());
}

/// SPEC §11's landmark term: `E_lm`, the residuals `φ_k(p_i^{k−1}) − p_i^k` and `∂E_lm/∂φ`
/// by autodiff and by the hand-derived sparse form.
fn landmark_energy(backend: Backend) {
    use deepmorph::model::energy::landmarks::{LandmarkTerm, Landmarks};
    let case = Case::open("landmark_energy_K3_10x13", backend, true);
    let k = case.param("K") as usize;
    let grid = case.grid("phi");
    let pairs = |name: &str| -> Vec<[f64; 2]> {
        case.golden
            .input(name)
            .data
            .chunks(2)
            .map(|p| [p[0], p[1]])
            .collect()
    };
    let landmarks = Landmarks::new(pairs("P"), pairs("Q"), (grid.height(), grid.width())).unwrap();
    let term = LandmarkTerm::new(&grid, &landmarks, k, case.param("gamma")).unwrap();
    let phi: Tensor<4> = case.input::<4>("phi").require_grad();
    let energy = term.energy(phi.clone());
    case.check("E_lm", energy.clone());
    case.check("residuals", term.residuals(phi.clone().detach()));
    let grads = energy.backward();
    case.check("grad_phi", phi.grad(&grads).expect("grad phi"));
    let host = term.gradient_host(
        &case.golden.input("phi").data,
        (grid.height(), grid.width()),
    );
    case.check_host("grad_phi", &host);
    // The steps' parts add up to the whole.
    let by_steps: f64 = (1..=k)
        .map(|step| values(term.step_energy(step, phi.clone().detach().narrow(0, step - 1, 1)))[0])
        .sum();
    let whole = values(term.energy(phi.detach()))[0];
    assert!(
        (by_steps - whole).abs() <= 1e-6 * whole,
        "{by_steps} vs {whole}"
    );
}

on_each_backend!(
    landmark_energy,
    prefilter,
    warp_admissible,
    warp_clamped,
    energy_density,
    jacobian_energy,
    jacobian_energy_fold,
    gaussian,
    anisotropy,
    anisotropy_strong,
    sobel,
    data_term_c3,
    data_term_c5,
    path_energy,
    resize_and_prolongate,
);
