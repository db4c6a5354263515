//! Gradient checks in float64 on the CPU backends: for `W`, `R`, `D` (w.r.t. `f`, `f̃`, `φ`)
//! and `E`, the hand-derived gradient (SPEC §2's `∂W/∂J` through the adjoint of the forward
//! differences; `β'` and the adjoint of the warp for `D`), Burn autodiff, and central finite
//! differences of every single entry must agree. On every backend (wgpu included), float32
//! autodiff gradients must match those float64 results (backend parity).
//!
//! Inputs are random but smooth and reproducible: images are sums of low-frequency cosines,
//! deformations are `Id` plus a sine series that vanishes on the boundary (admissible, up to
//! about a pixel of displacement), drawn from a fixed-seed SplitMix64.
//!
//! Tolerances, as `max|got − want| ≤ rel · max|want| + abs`:
//! - hand vs autodiff: `rel = 1e-10`, `abs = 1e-14` (the same float64 arithmetic reordered);
//! - finite differences (step `h = 1e-5`, error `O(h²)` plus rounding `ε/h`):
//!   `rel = 1e-6`, `abs = 1e-11`.

use crate::common;

use burn::tensor::{DType, Tensor};
use common::{Rng, assert_close, device, values};
use deepmorph::backend::Gather;
use deepmorph::check::data_term_gradient;
use deepmorph::check::density_gradient;
use deepmorph::check::regularizer_gradient;
use deepmorph::model::deformation::jacobian;
use deepmorph::model::deformation::{Jacobian, admissible_each};
use deepmorph::model::energy::data::data_term;
use deepmorph::model::energy::density::density;
use deepmorph::model::energy::path::PathEnergy;
use deepmorph::model::energy::regularizer::{regularizer, weighted_density};
use deepmorph::model::warp::BSpline;
use deepmorph::{Backend, EnergyParams, Grid, Precision};

const F64: DType = DType::F64;
const STEP: f64 = 1e-5;
const HAND_VS_AUTODIFF: (f64, f64) = (1e-10, 1e-14);
const FINITE_DIFFERENCE: (f64, f64) = (1e-6, 1e-11);
/// Non-square on purpose: a swapped axis cannot hide.
const H: usize = 10;
const W: usize = 12;

/// Finite differences of a batched function at `x`, every entry, `O(h²)` accurate.
///
/// `inward(i)` is 0 for a central difference `(F(x + h eᵢ) − F(x − h eᵢ)) / 2h`, or the
/// sign `s = ±1` of a one-sided second-order difference `s (−3F(x) + 4F(x + s h eᵢ) −
/// F(x + 2 s h eᵢ)) / 2h`. The warp clamps sample points to the grid, so the data term has a
/// kink at a boundary deformation entry's normal component: there only the inward side is
/// smooth (its one-sided derivative is the true one, 0 for the warp by the mirror symmetry).
///
/// `eval` receives all perturbed copies (two per entry, then `x` itself) and returns one
/// value per copy, so a batched function is evaluated once.
fn finite_differences(
    x: &[f64],
    inward: impl Fn(usize) -> f64,
    eval: impl Fn(Vec<Vec<f64>>) -> Vec<f64>,
) -> Vec<f64> {
    let steps = |i: usize| match inward(i) {
        0.0 => [STEP, -STEP],
        s => [s * STEP, 2.0 * s * STEP],
    };
    let mut copies: Vec<Vec<f64>> = (0..x.len())
        .flat_map(|i| {
            steps(i).map(|d| {
                let mut y = x.to_vec();
                y[i] += d;
                y
            })
        })
        .collect();
    copies.push(x.to_vec());
    let v = eval(copies);
    assert_eq!(v.len(), 2 * x.len() + 1);
    let base = v[2 * x.len()];
    (0..x.len())
        .map(|i| match inward(i) {
            0.0 => (v[2 * i] - v[2 * i + 1]) / (2.0 * STEP),
            s => s * (-3.0 * base + 4.0 * v[2 * i] - v[2 * i + 1]) / (2.0 * STEP),
        })
        .collect()
}

/// Central differences everywhere.
fn central(_: usize) -> f64 {
    0.0
}

/// For an entry of a flat `[n, 2, H, W]` deformation: the inward direction if it is the
/// normal component on the boundary (row component on the first/last row, column component
/// on the first/last column), else 0.
fn inward_on_boundary(i: usize) -> f64 {
    let (axis, row, col) = ((i / (H * W)) % 2, (i / W) % H, i % W);
    let (pos, last) = if axis == 0 {
        (row, H - 1)
    } else {
        (col, W - 1)
    };
    if pos == 0 {
        1.0
    } else if pos == last {
        -1.0
    } else {
        0.0
    }
}

fn check(what: &str, got: &[f64], want: &[f64], (rel, abs): (f64, f64)) {
    assert_close(what, got, want, rel, abs);
}

struct Setup {
    grid: Grid,
    rng: Rng,
}

impl Setup {
    fn new(backend: Backend, seed: u64) -> Self {
        let device = device(backend, Precision::F64, true);
        let grid = Grid::new(H, W, &device, F64).unwrap();
        Self {
            grid,
            rng: Rng(seed),
        }
    }

    fn tensor<const D: usize>(&self, data: Vec<f64>, shape: [usize; D]) -> Tensor<D> {
        self.grid.tensor(data, shape)
    }

    /// `copies` stacked into one batch tensor of `[copies.len(), rest...]`.
    fn batch<const D: usize>(&self, copies: Vec<Vec<f64>>, rest: [usize; D]) -> Tensor<D> {
        let n = copies.len();
        let mut shape = rest;
        shape[0] = n;
        self.tensor(copies.concat(), shape)
    }
}

fn density_gradient_check(backend: Backend) {
    let mut s = Setup::new(backend, 1);
    let params = EnergyParams::rgb();
    let n = 40;
    // Matrices near I with det bounded away from 0 (rejection sampling), [4][n] entry-major.
    let mut entries = vec![Vec::new(); 4];
    while entries[0].len() < n {
        let m: Vec<f64> = (0..4).map(|_| 0.35 * s.rng.symmetric()).collect();
        let (a, b, c, d) = (1.0 + m[0], m[1], m[2], 1.0 + m[3]);
        if a * d - b * c > 0.3 {
            for (e, v) in entries.iter_mut().zip([a, b, c, d]) {
                e.push(v);
            }
        }
    }
    let map = |v: Vec<f64>| -> Tensor<3> { s.tensor(v, [1, 1, n]) };
    let jac = |e: &[Vec<f64>]| Jacobian {
        j00: map(e[0].clone()),
        j01: map(e[1].clone()),
        j10: map(e[2].clone()),
        j11: map(e[3].clone()),
    };

    let leaf = jac(&entries);
    let leaf = Jacobian {
        j00: leaf.j00.require_grad(),
        j01: leaf.j01.require_grad(),
        j10: leaf.j10.require_grad(),
        j11: leaf.j11.require_grad(),
    };
    let grads = density(&leaf, params.lambda, params.mu).sum().backward();
    let hand = density_gradient(&jac(&entries), params.lambda, params.mu);
    let auto =
        [&leaf.j00, &leaf.j01, &leaf.j10, &leaf.j11].map(|t| values(t.grad(&grads).unwrap()));
    let hand = [hand.j00, hand.j01, hand.j10, hand.j11].map(values);
    for e in 0..4 {
        let what = format!("dW/dJ[{}][{}]", e / 2, e % 2);
        check(
            &format!("{what} hand vs autodiff"),
            &hand[e],
            &auto[e],
            HAND_VS_AUTODIFF,
        );
        // W acts matrix by matrix, so one ± step of entry e in all n matrices at once is a
        // full set of central differences.
        let shifted = |sign: f64| {
            let mut moved = entries.clone();
            moved[e].iter_mut().for_each(|v| *v += sign * STEP);
            values(density(&jac(&moved), params.lambda, params.mu))
        };
        let (plus, minus) = (shifted(1.0), shifted(-1.0));
        let fd: Vec<f64> = plus
            .iter()
            .zip(&minus)
            .map(|(p, m)| (p - m) / (2.0 * STEP))
            .collect();
        check(
            &format!("{what} hand vs FD"),
            &hand[e],
            &fd,
            FINITE_DIFFERENCE,
        );
    }
}

fn regularizer_gradient_check(backend: Backend) {
    let mut s = Setup::new(backend, 2);
    let params = EnergyParams::rgb();
    let phi_host = s.rng.smooth_deformation(1, H, W, 0.8);
    let a_host = s.rng.weights(1, H, W);
    let phi: Tensor<4> = s.tensor(phi_host.clone(), [1, 2, H, W]);
    assert_eq!(admissible_each(&s.grid, phi.clone()), vec![true]);
    let a: Tensor<3> = s.tensor(a_host.clone(), [1, H, W]);

    let leaf = phi.clone().require_grad();
    let grads = regularizer(leaf.clone(), a.clone(), params.lambda, params.mu)
        .sum()
        .backward();
    let auto = values(leaf.grad(&grads).unwrap());
    let hand = values(regularizer_gradient(
        phi,
        a.clone(),
        params.lambda,
        params.mu,
    ));
    check("dR/dphi hand vs autodiff", &hand, &auto, HAND_VS_AUTODIFF);

    let fd = finite_differences(&phi_host, central, |copies| {
        let n = copies.len();
        let phis = s.batch(copies, [0, 2, H, W]);
        let a = s.tensor(a_host.repeat(n), [n, H, W]);
        values(regularizer(phis, a, params.lambda, params.mu))
    });
    check("dR/dphi hand vs FD", &hand, &fd, FINITE_DIFFERENCE);

    // Per pixel, the density as the solver takes it (the fused op on flex) against SPEC §2's
    // formula composed from tensor ops.
    let fused = values(weighted_density(
        phi_of(&s, &phi_host),
        a.clone(),
        params.lambda,
        params.mu,
    ));
    let composed = values(a * density(&jacobian(phi_of(&s, &phi_host)), params.lambda, params.mu));
    check(
        "a W(J) fused vs composed",
        &composed,
        &fused,
        HAND_VS_AUTODIFF,
    );

    // The weight differentiated too (the solver never does; a library user may): ∂R/∂a is
    // W(J(φ)) / (H·W).
    let a_leaf: Tensor<3> = s.tensor(a_host.clone(), [1, H, W]).require_grad();
    let grads = regularizer(
        phi_of(&s, &phi_host),
        a_leaf.clone(),
        params.lambda,
        params.mu,
    )
    .sum()
    .backward();
    let auto = values(a_leaf.grad(&grads).unwrap());
    let hand = values(
        density(&jacobian(phi_of(&s, &phi_host)), params.lambda, params.mu)
            .mul_scalar(1.0 / (H * W) as f64),
    );
    check("dR/da hand vs autodiff", &hand, &auto, HAND_VS_AUTODIFF);
}

fn phi_of(s: &Setup, host: &[f64]) -> Tensor<4> {
    s.tensor(host.to_vec(), [1, 2, H, W])
}

/// Every way of computing the warp (`Gather`) gets the full check: both composed gathers,
/// and the fused op where the backend has it, whose autodiff gradient is then its
/// hand-written backward (`model::warp::op`) checked against the composed hand-derived
/// adjoint and against finite differences.
fn data_term_gradient_check(backend: Backend) {
    let mut gathers = vec![Gather::Elements, Gather::Rows];
    if backend.has_fused_warp() {
        gathers.push(Gather::Fused);
    }
    for gather in gathers {
        data_term_gradient_check_with(backend, gather);
    }
}

fn data_term_gradient_check_with(backend: Backend, gather: Gather) {
    let mut s = Setup::new(backend, 3);
    let c = 3;
    let c_tot = 5; // a block of a larger feature vector: the divisor is not read off f
    let bspline = BSpline::with_gather(&s.grid, gather);
    let f_host = s.rng.smooth_image(c, H, W);
    let ft_host = s.rng.smooth_image(c, H, W);
    let phi_host = s.rng.smooth_deformation(1, H, W, 0.8);
    let f: Tensor<4> = s.tensor(f_host.clone(), [1, c, H, W]);
    let ft: Tensor<4> = s.tensor(ft_host.clone(), [1, c, H, W]);
    let phi: Tensor<4> = s.tensor(phi_host.clone(), [1, 2, H, W]);
    assert_eq!(admissible_each(&s.grid, phi.clone()), vec![true]);

    let leaves = [f.clone(), ft.clone(), phi.clone()].map(|t| t.require_grad());
    let d = data_term(
        &bspline,
        leaves[0].clone(),
        leaves[1].clone(),
        leaves[2].clone(),
        c_tot,
    );
    let grads = d.sum().backward();
    let auto = leaves.clone().map(|t| values(t.grad(&grads).unwrap()));
    let hand = data_term_gradient(&bspline, f, ft, phi, c_tot);
    let hand = [hand.f, hand.f_tilde, hand.phi].map(values);

    let repeat = |host: &[f64], n: usize, shape: [usize; 4]| -> Tensor<4> {
        s.tensor(host.repeat(n), [n, shape[1], shape[2], shape[3]])
    };
    let image = [0, c, H, W];
    let deformation = [0, 2, H, W];
    let fd = [
        finite_differences(&f_host, central, |copies| {
            let n = copies.len();
            let d = data_term(
                &bspline,
                s.batch(copies, image),
                repeat(&ft_host, n, image),
                repeat(&phi_host, n, deformation),
                c_tot,
            );
            values(d)
        }),
        finite_differences(&ft_host, central, |copies| {
            let n = copies.len();
            let d = data_term(
                &bspline,
                repeat(&f_host, n, image),
                s.batch(copies, image),
                repeat(&phi_host, n, deformation),
                c_tot,
            );
            values(d)
        }),
        finite_differences(&phi_host, inward_on_boundary, |copies| {
            let n = copies.len();
            let d = data_term(
                &bspline,
                repeat(&f_host, n, image),
                repeat(&ft_host, n, image),
                s.batch(copies, deformation),
                c_tot,
            );
            values(d)
        }),
    ];
    for (i, name) in ["f", "f~", "phi"].iter().enumerate() {
        check(
            &format!("dD/d{name} auto vs FD ({gather:?})"),
            &auto[i],
            &fd[i],
            FINITE_DIFFERENCE,
        );
        check(
            &format!("dD/d{name} hand vs FD ({gather:?})"),
            &hand[i],
            &fd[i],
            FINITE_DIFFERENCE,
        );
        check(
            &format!("dD/d{name} hand vs autodiff ({gather:?})"),
            &hand[i],
            &auto[i],
            HAND_VS_AUTODIFF,
        );
    }
}

/// The fused squared distance `Σ (a_n − b_n)²` under the data term (a custom op with a
/// hand-written backward on flex, composed elsewhere): its value against the composed sum,
/// its autodiff gradients of `Σ_n w_n D_n` against the hand-derived `±2 w_n (a_n − b_n)` and
/// finite differences in float64; in float32 its gradient is the composed backward's bit for
/// bit (`2g·d` against `g·d + g·d`); given its value, the same value and gradients.
fn squared_distance_gradient_check(backend: Backend) {
    use deepmorph::model::energy::distance_op::distance2_each;
    let mut s = Setup::new(backend, 6);
    let (n, c) = (2, 2);
    let shape = [n, c, H, W];
    let a_host = s.rng.smooth_image(n * c, H, W);
    let b_host = s.rng.smooth_image(n * c, H, W);
    let weights = [0.7, -1.3];
    let (a, b): (Tensor<4>, Tensor<4>) = (
        s.tensor(a_host.clone(), shape),
        s.tensor(b_host.clone(), shape),
    );
    let w = s.tensor(weights.to_vec(), [n]);
    let composed = |a: Tensor<4>, b: Tensor<4>| {
        (a - b)
            .square()
            .reshape([n, c * H * W])
            .sum_dim(1)
            .reshape([n])
    };
    check(
        "sum (a - b)^2 fused vs composed",
        &values(distance2_each(a.clone(), b.clone())),
        &values(composed(a.clone(), b.clone())),
        HAND_VS_AUTODIFF,
    );

    let leaves = [a.clone(), b.clone()].map(|t| t.require_grad());
    let grads = (distance2_each(leaves[0].clone(), leaves[1].clone()) * w.clone())
        .sum()
        .backward();
    let auto = leaves.clone().map(|t| values(t.grad(&grads).unwrap()));
    let per_item = c * H * W;
    let hand_a: Vec<f64> = (0..n * per_item)
        .map(|i| 2.0 * weights[i / per_item] * (a_host[i] - b_host[i]))
        .collect();
    let hand_b: Vec<f64> = hand_a.iter().map(|g| -g).collect();
    check(
        "dD/da hand vs autodiff",
        &hand_a,
        &auto[0],
        HAND_VS_AUTODIFF,
    );
    check(
        "dD/db hand vs autodiff",
        &hand_b,
        &auto[1],
        HAND_VS_AUTODIFF,
    );
    // Item by item: a batch of copies of one item at a time.
    let weighted = |copies: Vec<Vec<f64>>, fixed: &[f64], item: usize, moved_first: bool| {
        let m = copies.len();
        let moved = s.batch(copies, [0, c, H, W]);
        let fixed = s.tensor(fixed.repeat(m), [m, c, H, W]);
        let d = if moved_first {
            distance2_each(moved, fixed)
        } else {
            distance2_each(fixed, moved)
        };
        values(d.mul_scalar(weights[item]))
    };
    for item in 0..n {
        let range = item * per_item..(item + 1) * per_item;
        let (a_item, b_item) = (&a_host[range.clone()], &b_host[range.clone()]);
        let fd_a = finite_differences(a_item, central, |copies| {
            weighted(copies, b_item, item, true)
        });
        let fd_b = finite_differences(b_item, central, |copies| {
            weighted(copies, a_item, item, false)
        });
        check(
            "dD/da autodiff vs FD",
            &auto[0][range.clone()],
            &fd_a,
            FINITE_DIFFERENCE,
        );
        check(
            "dD/db autodiff vs FD",
            &auto[1][range.clone()],
            &fd_b,
            FINITE_DIFFERENCE,
        );
    }

    let device = device(backend, Precision::F32, true);
    let grid = Grid::new(H, W, &device, DType::F32).unwrap();
    let (a, b) = (grid.tensor(a_host, shape), grid.tensor(b_host, shape));
    let w = grid.tensor(weights.to_vec(), [n]);
    let gradients = |fused: bool| {
        let leaves = [a.clone(), b.clone()].map(|t| t.require_grad());
        let d = if fused {
            distance2_each(leaves[0].clone(), leaves[1].clone())
        } else {
            composed(leaves[0].clone(), leaves[1].clone())
        };
        let grads = (d * w.clone()).sum().backward();
        leaves.map(|t| values(t.grad(&grads).unwrap()))
    };
    let (fused, composed) = (gradients(true), gradients(false));
    assert_eq!(
        fused[0], composed[0],
        "float32 dD/da: fused and composed backward differ"
    );
    assert_eq!(
        fused[1], composed[1],
        "float32 dD/db: fused and composed backward differ"
    );

    // Given its value (a feature step passes its decision sums), the op returns that value
    // in the tensors' dtype and differentiates exactly as the fused one.
    use deepmorph::model::energy::distance_op::distance2_each_given;
    let sums = grid.decision_distance2_each(a.clone(), b.clone());
    let leaves = [a.clone(), b.clone()].map(|t| t.require_grad());
    let given = distance2_each_given(leaves[0].clone(), leaves[1].clone(), sums.clone());
    let want: Vec<f64> = values(sums).iter().map(|&v| f64::from(v as f32)).collect();
    assert_eq!(values(given.clone()), want, "the given value comes back");
    let grads = (given * w.clone()).sum().backward();
    let given = leaves.map(|t| values(t.grad(&grads).unwrap()));
    assert_eq!(
        given, fused,
        "float32 dD/da, dD/db: given and fused backward differ"
    );
}

/// The separable operator `R · x · Cᵀ` (banded on flex, dense matmuls elsewhere) against
/// the dense product of its own matrices, and its autodiff gradient (the op's hand-written
/// backward `Rᵀ · g · C`) against the dense adjoint and finite differences. The operators
/// are the anisotropy's `G_ρ D G_σ` and a Gaussian wider than the grid (it reflects twice).
fn separable_gradient_check(backend: Backend) {
    use deepmorph::model::separable::Separable;
    use deepmorph::model::stencil::{central_difference_domain, gaussian};
    let mut s = Setup::new(backend, 5);
    let c = 2;
    let derivative =
        |n| gaussian(n, 1.5).matmul(&central_difference_domain(n).matmul(&gaussian(n, 0.7)));
    let op = Separable::new(&s.grid, &gaussian(H, 4.0), &derivative(W));
    let x_host = s.rng.smooth_image(c, H, W);
    let w_host = s.rng.smooth_image(c, H, W);
    let x: Tensor<4> = s.tensor(x_host.clone(), [1, c, H, W]);
    let w: Tensor<4> = s.tensor(w_host.clone(), [1, c, H, W]);

    let (rows, cols_t) = deepmorph::check::separable_matrices(&op);
    let dense = rows.matmul(x.clone()).matmul(cols_t);
    check(
        "R x C^T op vs dense",
        &values(op.apply(x.clone())),
        &values(dense),
        HAND_VS_AUTODIFF,
    );

    let leaf = x.require_grad();
    let grads = (op.apply(leaf.clone()) * w.clone()).sum().backward();
    let auto = values(leaf.grad(&grads).unwrap());
    let hand = values(deepmorph::check::separable_adjoint(&op, w));
    check(
        "d<w, Sx>/dx hand vs autodiff",
        &hand,
        &auto,
        HAND_VS_AUTODIFF,
    );
    let fd = finite_differences(&x_host, central, |copies| {
        let n = copies.len();
        let y = op.apply(s.batch(copies, [0, c, H, W]));
        let w = s.tensor(w_host.repeat(n), [n, c, H, W]);
        values((y * w).sum_dim(3).sum_dim(2).sum_dim(1).reshape([n]))
    });
    check("d<w, Sx>/dx autodiff vs FD", &auto, &fd, FINITE_DIFFERENCE);
}

fn path_energy_gradient_check(backend: Backend) {
    let mut s = Setup::new(backend, 4);
    let k = 3;
    let c = 3;
    let params = EnergyParams {
        delta: 0.7, // not 1, so a missing 1/δ shows
        ..EnergyParams::rgb()
    };
    let energy = PathEnergy::new(&s.grid, params, c).unwrap();
    let f_host = s.rng.smooth_image((k + 1) * c, H, W);
    let phi_host = s.rng.smooth_deformation(k, H, W, 0.8);
    let a_host = s.rng.weights(k, H, W);
    let f: Tensor<4> = s.tensor(f_host.clone(), [k + 1, c, H, W]);
    let phi: Tensor<4> = s.tensor(phi_host.clone(), [k, 2, H, W]);
    let a: Tensor<3> = s.tensor(a_host.clone(), [k, H, W]);
    assert_eq!(admissible_each(&s.grid, phi.clone()), vec![true; k]);

    let (f_leaf, phi_leaf) = (f.clone().require_grad(), phi.clone().require_grad());
    let grads = energy
        .value(f_leaf.clone(), phi_leaf.clone(), a.clone())
        .total
        .backward();
    let auto_f = values(f_leaf.grad(&grads).unwrap().narrow(0, 1, k - 1));
    let auto_phi = values(phi_leaf.grad(&grads).unwrap());
    let hand = deepmorph::check::path_energy_gradient(&energy, f, phi, a.clone());
    let (hand_f, hand_phi) = (values(hand.f_interior), values(hand.phi));

    // E couples the frames, so each perturbed copy is one full evaluation.
    let total = |f: Vec<f64>, phi: Vec<f64>| {
        let f = s.tensor(f, [k + 1, c, H, W]);
        let phi = s.tensor(phi, [k, 2, H, W]);
        values(energy.value(f, phi, a.clone()).total)[0]
    };
    let frame = c * H * W;
    let interior = f_host[frame..k * frame].to_vec();
    let fd_f = finite_differences(&interior, central, |copies| {
        copies
            .into_iter()
            .map(|inner| {
                let mut full = f_host.clone();
                full[frame..k * frame].copy_from_slice(&inner);
                total(full, phi_host.clone())
            })
            .collect()
    });
    let fd_phi = finite_differences(&phi_host, inward_on_boundary, |copies| {
        copies
            .into_iter()
            .map(|p| total(f_host.clone(), p))
            .collect()
    });
    check("dE/df hand vs FD", &hand_f, &fd_f, FINITE_DIFFERENCE);
    check("dE/dphi hand vs FD", &hand_phi, &fd_phi, FINITE_DIFFERENCE);
    check("dE/df auto vs FD", &auto_f, &fd_f, FINITE_DIFFERENCE);
    check("dE/df hand vs autodiff", &hand_f, &auto_f, HAND_VS_AUTODIFF);
    check(
        "dE/dphi hand vs autodiff",
        &hand_phi,
        &auto_phi,
        HAND_VS_AUTODIFF,
    );
}

/// Backend parity (wgpu included): a module of its own, since the float64 checks below
/// already instantiate the CPU backends' test modules.
mod parity {
    use super::*;

    /// Backend parity: float32 autodiff gradients of `R`, `D` and `E` on `backend` (wgpu
    /// included) against the float64 hand-derived gradients on `common::reference_backend()`.
    ///
    /// Tolerance `2e-4 · max|want|`: float32 rounding (ε ≈ 6e-8) amplified by the `exp(log² d)`
    /// of `W`, the 16-tap B-spline sums and the reductions of `mean`. Measured (2026-11-24):
    /// at most 7.1e-6, for `dR/dφ` on wgpu/lavapipe; 7.0e-6 on flex and ndarray.
    fn autodiff_in_float32_matches_the_float64_reference(backend: Backend) {
        const PARITY: (f64, f64) = (2e-4, 0.0);
        let (k, c) = (3, 3);
        let mut rng = Rng(5);
        let f_host = rng.smooth_image((k + 1) * c, H, W);
        let phi_host = rng.smooth_deformation(k, H, W, 0.8);
        let a_host = rng.weights(k, H, W);
        let params = EnergyParams {
            delta: 0.7,
            ..EnergyParams::rgb()
        };
        let frame = c * H * W;

        let reference = {
            let s = Setup::new(common::reference_backend(), 0);
            let f: Tensor<4> = s.tensor(f_host.clone(), [k + 1, c, H, W]);
            let phi: Tensor<4> = s.tensor(phi_host.clone(), [k, 2, H, W]);
            let a: Tensor<3> = s.tensor(a_host.clone(), [k, H, W]);
            assert_eq!(admissible_each(&s.grid, phi.clone()), vec![true; k]);
            let bspline = BSpline::new(&s.grid);
            let r = regularizer_gradient(phi.clone(), a.clone(), params.lambda, params.mu);
            let (f0, f1) = (f.clone().narrow(0, 0, k), f.clone().narrow(0, 1, k));
            let d = data_term_gradient(&bspline, f0, f1, phi.clone(), c);
            let e = deepmorph::check::path_energy_gradient(
                &PathEnergy::new(&s.grid, params, c).unwrap(),
                f,
                phi,
                a,
            );
            [r, d.f, d.f_tilde, d.phi, e.f_interior, e.phi].map(values)
        };

        let device = device(backend, Precision::F32, true);
        let grid = Grid::new(H, W, &device, DType::F32).unwrap();
        let leaf =
            |data: &[f64], shape: [usize; 4]| grid.tensor(data.to_vec(), shape).require_grad();
        let a: Tensor<3> = grid.tensor(a_host.clone(), [k, H, W]);
        let bspline = BSpline::new(&grid);

        let phi = leaf(&phi_host, [k, 2, H, W]);
        let grads = regularizer(phi.clone(), a.clone(), params.lambda, params.mu)
            .sum()
            .backward();
        let r = values(phi.grad(&grads).unwrap());

        let f0 = leaf(&f_host[..k * frame], [k, c, H, W]);
        let f1 = leaf(&f_host[frame..], [k, c, H, W]);
        let phi = leaf(&phi_host, [k, 2, H, W]);
        let grads = data_term(&bspline, f0.clone(), f1.clone(), phi.clone(), c)
            .sum()
            .backward();
        let [d_f, d_ft, d_phi] = [f0, f1, phi].map(|t| values(t.grad(&grads).unwrap()));

        let f = leaf(&f_host, [k + 1, c, H, W]);
        let phi = leaf(&phi_host, [k, 2, H, W]);
        let grads = PathEnergy::new(&grid, params, c)
            .unwrap()
            .value(f.clone(), phi.clone(), a)
            .total
            .backward();
        let e_f = values(f.grad(&grads).unwrap().narrow(0, 1, k - 1));
        let e_phi = values(phi.grad(&grads).unwrap());

        let got = [r, d_f, d_ft, d_phi, e_f, e_phi];
        let names = ["dR/dphi", "dD/df", "dD/df~", "dD/dphi", "dE/df", "dE/dphi"];
        for ((name, got), want) in names.iter().zip(&got).zip(&reference) {
            check(
                &format!("{name} float32 autodiff vs float64 hand"),
                got,
                want,
                PARITY,
            );
        }
    }

    /// Every way of computing the warp gives the same warp and the same autodiff gradients
    /// (w.r.t. the coefficients' frame and `φ`) on every backend, wgpu included: row gathers,
    /// and the fused op (flex's native kernels, wgpu's CubeCL ones), against scalar gathers,
    /// for a batch of 3 (the row gather offsets each batch item's rows) and 5 channels.
    /// Tolerance `1e-5 · max|want|`: the same float32 sums in another order.
    fn gather_strategies_agree(backend: Backend) {
        const SAME: (f64, f64) = (1e-5, 0.0);
        let (n, c) = (3, 5);
        let mut rng = Rng(6);
        let f_host = rng.smooth_image(n * c, H, W);
        let phi_host = rng.smooth_deformation(n, H, W, 1.5);
        let y_host = rng.smooth_image(n * c, H, W);
        let device = device(backend, Precision::F32, true);
        let grid = Grid::new(H, W, &device, DType::F32).unwrap();
        let run = |gather: Gather| {
            let bspline = BSpline::with_gather(&grid, gather);
            let f = grid.tensor(f_host.clone(), [n, c, H, W]).require_grad();
            let phi = grid.tensor(phi_host.clone(), [n, 2, H, W]).require_grad();
            let y: Tensor<4> = grid.tensor(y_host.clone(), [n, c, H, W]);
            let warped = bspline.warp(f.clone(), phi.clone());
            let grads = (warped.clone() * y).sum().backward();
            [warped, f.grad(&grads).unwrap(), phi.grad(&grads).unwrap()].map(values)
        };
        let elements = run(Gather::Elements);
        let mut others = vec![("rows", Gather::Rows)];
        if backend.has_fused_warp() {
            others.push(("fused", Gather::Fused));
        }
        for (label, gather) in others {
            let got = run(gather);
            for ((name, got), want) in ["T", "dT/df", "dT/dphi"].iter().zip(&got).zip(&elements) {
                check(&format!("{name} {label} vs elements"), got, want, SAME);
            }
        }
    }

    /// One sampler with `Gather::RowsFrom(4)` reads a 3-channel tensor with scalar gathers
    /// and an 8-channel one with rows (as the deep model's feature step does with its η and
    /// VGG blocks), in either order, and both match the scalar-gather evaluation.
    fn a_threshold_sampler_serves_narrow_and_wide_tensors(backend: Backend) {
        const SAME: (f64, f64) = (1e-5, 0.0);
        let n = 2;
        let mut rng = Rng(7);
        let phi_host = rng.smooth_deformation(n, H, W, 1.5);
        let device = device(backend, Precision::F32, false);
        let grid = Grid::new(H, W, &device, DType::F32).unwrap();
        let phi = grid.tensor(phi_host, [n, 2, H, W]);
        let narrow = grid.tensor(rng.smooth_image(n * 3, H, W), [n, 3, H, W]);
        let wide = grid.tensor(rng.smooth_image(n * 8, H, W), [n, 8, H, W]);
        let elements = BSpline::with_gather(&grid, Gather::Elements).sampler(phi.clone());
        let threshold = BSpline::with_gather(&grid, Gather::RowsFrom(4));
        for order in [[&narrow, &wide], [&wide, &narrow]] {
            let sampler = threshold.sampler(phi.clone());
            for coeffs in order {
                let c = coeffs.dims()[1];
                check(
                    &format!("RowsFrom(4) vs elements, {c} channels"),
                    &values(sampler.sample(coeffs.clone())),
                    &values(elements.sample(coeffs.clone())),
                    SAME,
                );
            }
        }
    }

    on_each_backend!(
        autodiff_in_float32_matches_the_float64_reference,
        gather_strategies_agree,
        a_threshold_sampler_serves_narrow_and_wide_tensors,
    );
}

/// SPEC §11's landmark term: the hand-derived sparse gradient against autodiff and central
/// differences of every entry (the term is quadratic in `φ`: the points are fixed).
fn landmark_gradient_check(backend: Backend) {
    use deepmorph::model::energy::landmarks::{LandmarkTerm, Landmarks};
    let mut s = Setup::new(backend, 11);
    let k = 3;
    let phi_host = s.rng.smooth_deformation(k, H, W, 0.8);
    let landmarks = Landmarks::new(
        vec![[2.3, 3.7], [5.0, 6.0], [7.6, 1.4], [1.2, 9.9]],
        vec![[3.1, 5.2], [4.2, 7.5], [6.9, 3.0], [2.0, 8.6]],
        (H, W),
    )
    .unwrap();
    let term = LandmarkTerm::new(&s.grid, &landmarks, k, 250.0).unwrap();
    let leaf = s.tensor(phi_host.clone(), [k, 2, H, W]).require_grad();
    let grads = term.energy(leaf.clone()).backward();
    let auto = values(leaf.grad(&grads).unwrap());
    let hand = term.gradient_host(&phi_host, (H, W));
    check(
        "dE_lm/dphi hand vs autodiff",
        &hand,
        &auto,
        HAND_VS_AUTODIFF,
    );
    let fd = finite_differences(&phi_host, central, |copies| {
        copies
            .into_iter()
            .map(|c| values(term.energy(s.tensor(c, [k, 2, H, W])))[0])
            .collect()
    });
    check("dE_lm/dphi hand vs FD", &hand, &fd, FINITE_DIFFERENCE);
}

on_each_cpu_backend!(
    landmark_gradient_check,
    density_gradient_check,
    regularizer_gradient_check,
    data_term_gradient_check,
    squared_distance_gradient_check,
    separable_gradient_check,
    path_energy_gradient_check,
);
