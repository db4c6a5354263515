//! Golden cases of the solver (SPEC §6, §7), float32 on every compiled backend: the prox at
//! 1e-4 relative (plus the 1e-7 floor), the sweep and multilevel cases at the README's loose
//! 1e-3.

mod common;

use burn::tensor::{DType, Tensor};
use common::{Golden, assert_golden, device, grid_for, tensor, values};
use deepmorph::Backend;
use deepmorph::Precision;
use deepmorph::optim::prox::{LinearisedData, linearise};
use deepmorph::sobel::Sobel;
use deepmorph::warp::BSpline;

const F32: DType = DType::F32;

fn prox(backend: Backend) {
    let golden = Golden::load("prox_10x13");
    let device = device(backend, Precision::F32, false);
    let input = |name: &str| -> Tensor<4> { tensor(golden.input(name), &device, F32) };
    let check = |name: &str, got: Vec<f64>| {
        assert_golden(&format!("prox_10x13.{name}"), &got, golden.output(name))
    };
    let grid = grid_for(&golden.input("f_k").shape, &device, F32);
    let bspline = BSpline::new(&grid);
    let phi_tilde = input("phi_tilde");
    let g = input("g");

    let lin = linearise(
        &bspline,
        &Sobel::new(&grid),
        bspline.coefficients(input("f_k")),
        input("f_km1"),
        phi_tilde.clone(),
    );
    check("r", values(lin.residual.clone()));
    check("Lambda", values(lin.slopes.clone()));

    let kappa = golden.param("kappa");
    let (k, delta, c_tot) = (golden.param("K"), golden.param("delta"), golden.param("C_tot"));
    let (h, w) = (grid.height() as f64, grid.width() as f64);
    assert!((kappa - k / (delta * c_tot * h * w)).abs() < 1e-15 * kappa);
    let data = LinearisedData::new(&grid, lin, phi_tilde.clone(), kappa);
    for (i, l) in [golden.param("L0"), golden.param("L1")].into_iter().enumerate() {
        let y = phi_tilde.clone() - g.clone().mul_scalar(1.0 / l);
        check(&format!("y_L{i}"), values(y.clone()));
        check(&format!("phi_new_L{i}"), values(data.prox(y, l)));
    }
}

on_each_backend!(prox);
