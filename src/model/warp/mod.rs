//! The cubic B-spline warp `T[f, φ]` (SPEC §1).
//!
//! `T[f, φ](x) = Σ c(m(i), m(j)) β(φ₀(x) − i) β(φ₁(x) − j)` with `c = P f` the interpolating
//! coefficients and `m` the mirror index. Two implementations, both exact and both
//! differentiable with respect to `f` and `φ` (the solver takes its gradients from
//! `backward()` either way):
//!
//! - **fused** ([`op`]): the prefilter as a tridiagonal solve along each axis (O(n) per
//!   line) and the evaluation as one kernel per backend (native loops on flex, CubeCL on
//!   wgpu), each a custom Burn op with a hand-written backward;
//! - **composed**: the prefilter as two dense matmuls with the exact inverse
//!   ([`crate::model::stencil::bspline_prefilter`]) and the evaluation as gathers of the
//!   4 × 4 coefficients around each point weighted by the B-spline polynomials; autodiff
//!   differentiates the chain. ndarray runs this; the tests compare both everywhere.
//!
//! [`crate::backend::Gather`] says which one (and which gather) a backend gets.

#[cfg(feature = "wgpu")]
mod cube;
pub mod host;
pub mod op;

use std::cell::OnceCell;

use burn::tensor::{Int, Tensor};

use crate::backend::Gather;
use crate::model::grid::Grid;
use crate::model::separable::Separable;
use crate::model::stencil::bspline_prefilter;

/// The cubic B-spline interpolator of one grid: the prefilter, ready on the device, and the
/// evaluation at arbitrary sample points.
#[derive(Clone, Debug)]
pub struct BSpline {
    grid: Grid,
    /// The dense prefilter of the composed form (`None` when fused).
    prefilter: Option<Separable>,
    gather: Gather,
}

/// The spline evaluation at fixed points (see [`BSpline::sampler`]): a backtracking search
/// evaluates the same `φ` on every trial's frame.
#[derive(Clone, Debug)]
pub struct Sampler(SamplerKind);

// One sampler per deformation and step: the size of the fused variant does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug)]
enum SamplerKind {
    /// The fused op reads `φ` itself.
    Fused(Tensor<4>),
    /// Indices and weights prepared once as tensors.
    Composed(ComposedSampler),
}

impl Sampler {
    /// The spline with coefficients `coeffs` at the sampler's points.
    ///
    /// # Shapes
    /// - `coeffs`: `[N, C, H, W]` on the sampler's grid
    /// - output: `[N, C, H', W']`
    pub fn sample(&self, coeffs: Tensor<4>) -> Tensor<4> {
        match &self.0 {
            SamplerKind::Fused(phi) => op::sample(coeffs, phi.clone()),
            SamplerKind::Composed(sampler) => sampler.sample(coeffs),
        }
    }
}

/// The composed evaluation at fixed points.
///
/// The row form of the stencil is built on the first sample that reads rows and kept: with
/// [`Gather::RowsFrom`] one sampler may serve a 3-channel and a 64-channel block (the deep
/// model's feature step), and a sampler that only ever reads scalars never builds it.
#[derive(Clone, Debug)]
struct ComposedSampler {
    batch: usize,
    out: [usize; 2],
    gather: Gather,
    /// `H·W` of the coefficient grid: the row offset between batch items.
    pixels: usize,
    /// 16 flat indices `m(i)·W + m(j)`, `[N, 1, P]` each.
    index: Vec<Tensor<3, Int>>,
    /// The 16 weights `β(p₀ − i) β(p₁ − j)`, `[N, 1, P]` each.
    weights: Vec<Tensor<3>>,
    /// Row indices of the channels-last table, `[N·P·16]` point-major, and the weights,
    /// `[N·P, 1, 16]`.
    rows: OnceCell<(Tensor<1, Int>, Tensor<3>)>,
}

impl ComposedSampler {
    fn sample(&self, coeffs: Tensor<4>) -> Tensor<4> {
        let [n, c, h, w] = coeffs.dims();
        assert_eq!(
            n, self.batch,
            "the sampler was built for {} frames",
            self.batch
        );
        let [ho, wo] = self.out;
        let p = ho * wo;
        if !self.gather.reads_rows(c) {
            let coeffs = coeffs.reshape([n, c, h * w]);
            return self
                .index
                .iter()
                .zip(&self.weights)
                .map(|(i, wt)| coeffs.clone().gather(2, i.clone().expand([n, c, p])) * wt.clone())
                .reduce(|acc, term| acc + term)
                .expect("16 neighbours")
                .reshape([n, c, ho, wo]);
        }
        let (index, weights) = self.rows.get_or_init(|| self.row_stencil());
        // The weighted sum over the 16 rows of a point is a `[1, 16] × [16, C]` product:
        // one batched matmul beats a broadcast multiply and a sum 4× on flex.
        weights
            .clone()
            .matmul(
                coeffs
                    .permute([0, 2, 3, 1])
                    .reshape([n * h * w, c])
                    .select(0, index.clone())
                    .reshape([n * p, 16, c]),
            )
            .reshape([n, p, c])
            .swap_dims(1, 2)
            .reshape([n, c, ho, wo])
    }

    /// The stencil for row selects: indices into the channels-last table `[N·H·W, C]` and
    /// the weights, 16 per point and adjacent.
    fn row_stencil(&self) -> (Tensor<1, Int>, Tensor<3>) {
        let n = self.batch;
        let np = n * self.out[0] * self.out[1];
        // Row `m` of batch item `b` is `b·H·W + m`.
        let offsets = Tensor::<1, Int>::arange(0..n as i64, &self.index[0].device())
            .mul_scalar(self.pixels as i64)
            .reshape([n, 1, 1]);
        let index = self
            .index
            .iter()
            .map(|i| (i.clone() + offsets.clone()).reshape([np, 1]))
            .collect();
        let weights = self
            .weights
            .iter()
            .map(|w| w.clone().reshape([np, 1]))
            .collect();
        (
            Tensor::cat(index, 1).reshape([16 * np]),
            Tensor::cat(weights, 1).reshape([np, 1, 16]),
        )
    }
}

/// Where each sample point falls: per axis, the 4 mirrored grid indices and the 4 B-spline
/// weights (and their derivatives) of the fractional position.
#[cfg_attr(not(feature = "check"), allow(dead_code))]
pub(crate) struct Stencil {
    /// Flat indices `m(i)·W + m(j)` for the 16 neighbours, `[N, 1, P]` each, `a` major.
    pub(crate) flat: Vec<Tensor<3, Int>>,
    /// Row weights `β(p₀ − i)`, `[N, 1, P]` each.
    pub(crate) w0: [Tensor<3>; 4],
    /// Column weights `β(p₁ − j)`, `[N, 1, P]` each.
    pub(crate) w1: [Tensor<3>; 4],
    /// Fractional positions (after clamping), `[N, 1, P]`.
    pub(crate) t0: Tensor<3>,
    pub(crate) t1: Tensor<3>,
    /// 1 where the sample point lies inside the clamp range on each axis, else 0.
    pub(crate) inside0: Tensor<3>,
    pub(crate) inside1: Tensor<3>,
}

/// The 4 cubic B-spline weights `β(t+1), β(t), β(t−1), β(t−2)` for `t ∈ [0, 1)`, as
/// polynomials (each in its branch of SPEC §1's `β`), so their autodiff derivative is `β'`.
fn bspline_weights(t: Tensor<3>) -> [Tensor<3>; 4] {
    let s = t.clone().neg().add_scalar(1.0); // 1 − t
    let t2 = t.clone().square();
    let t3 = t2.clone() * t.clone();
    let s2 = s.clone().square();
    let s3 = s2.clone() * s.clone();
    [
        s3.clone().mul_scalar(1.0 / 6.0),
        t3.clone().mul_scalar(0.5) - t2 + (2.0 / 3.0),
        s3.mul_scalar(0.5) - s2 + (2.0 / 3.0),
        t3.mul_scalar(1.0 / 6.0),
    ]
}

/// Whole-sample mirror of integer-valued float indices in `[−1, n+1]` (SPEC §0), valid for
/// `n ≥ 4`, which covers every index a clamped cubic stencil reads.
fn mirror(i: Tensor<3>, n: usize) -> Tensor<3> {
    let last = (n - 1) as f64;
    i.abs().sub_scalar(last).abs().neg().add_scalar(last)
}

impl BSpline {
    /// The interpolator for `grid`, computing the way the grid's backend does fastest
    /// ([`Grid::gather`]).
    pub fn new(grid: &Grid) -> Self {
        Self::with_gather(grid, grid.gather())
    }

    /// [`new`](Self::new) with the implementation chosen by the caller (the tests compare
    /// them on every backend). The composed form builds the `H × H` and `W × W` prefilter
    /// matrices.
    pub fn with_gather(grid: &Grid, gather: Gather) -> Self {
        let prefilter = (gather != Gather::Fused).then(|| {
            Separable::new(
                grid,
                &bspline_prefilter(grid.height()),
                &bspline_prefilter(grid.width()),
            )
        });
        Self {
            grid: grid.clone(),
            prefilter,
            gather,
        }
    }

    /// The grid this interpolator belongs to.
    #[cfg(feature = "check")]
    pub(crate) fn grid(&self) -> &Grid {
        &self.grid
    }

    /// The dense prefilter `P` as a separable operator (the composed form only).
    #[cfg(feature = "check")]
    pub(crate) fn prefilter(&self) -> Option<&Separable> {
        self.prefilter.as_ref()
    }

    /// Interpolation coefficients `c = P f` (SPEC §1), per channel.
    ///
    /// A frame's coefficients can be computed once and reused for every warp of that frame.
    ///
    /// # Shapes
    /// - `f`: `[N, C, H, W]`
    /// - output: `[N, C, H, W]`
    pub fn coefficients(&self, f: Tensor<4>) -> Tensor<4> {
        match &self.prefilter {
            Some(dense) => dense.apply(f),
            None => op::prefilter(f, false),
        }
    }

    /// The warp `T[f, φ] = interpolate(P f, φ)`.
    ///
    /// # Shapes
    /// - `f`: `[N, C, H, W]`
    /// - `phi`: `[N, 2, H', W']`, pixel units (`phi[:, 0]` rows, `phi[:, 1]` columns)
    /// - output: `[N, C, H', W']`
    pub fn warp(&self, f: Tensor<4>, phi: Tensor<4>) -> Tensor<4> {
        self.interpolate(self.coefficients(f), phi)
    }

    /// Evaluates the spline with coefficients `coeffs` at the points `phi`, clamped to
    /// `[0, H−1] × [0, W−1]` (SPEC §1).
    ///
    /// # Shapes
    /// - `coeffs`: `[N, C, H, W]`
    /// - `phi`: `[N, 2, H', W']`
    /// - output: `[N, C, H', W']`
    pub fn interpolate(&self, coeffs: Tensor<4>, phi: Tensor<4>) -> Tensor<4> {
        self.sampler(phi).sample(coeffs)
    }

    /// The evaluation at the points `phi`, prepared once (indices and B-spline weights) for
    /// any number of coefficient tensors: a backtracking search evaluates the same `φ` on
    /// every trial's frame.
    ///
    /// # Shapes
    /// - `phi`: `[N, 2, H', W']`
    pub fn sampler(&self, phi: Tensor<4>) -> Sampler {
        if self.gather == Gather::Fused {
            return Sampler(SamplerKind::Fused(phi));
        }
        let [n, _, ho, wo] = phi.dims();
        let st = self.stencil(phi);
        let mut weights = Vec::with_capacity(16);
        for w0 in &st.w0 {
            for w1 in &st.w1 {
                weights.push(w0.clone() * w1.clone());
            }
        }
        Sampler(SamplerKind::Composed(ComposedSampler {
            batch: n,
            out: [ho, wo],
            gather: self.gather,
            pixels: self.grid.pixels(),
            index: st.flat,
            weights,
            rows: OnceCell::new(),
        }))
    }

    pub(crate) fn stencil(&self, phi: Tensor<4>) -> Stencil {
        let [n, two, ho, wo] = phi.dims();
        assert_eq!(
            two,
            2,
            "a deformation has 2 components, got shape {:?}",
            phi.dims()
        );
        let (h, w) = (self.grid.height(), self.grid.width());
        let p = phi.reshape([n, 2, ho * wo]);
        let p0 = p.clone().narrow(1, 0, 1);
        let p1 = p.narrow(1, 1, 1);
        // Built by masking (not `Bool::float()`, which would take the device's default
        // dtype) so the indicator has the dtype of `phi`.
        let inside = |q: &Tensor<3>, hi: f64| {
            let q = q.clone().detach();
            let outside = q
                .clone()
                .lower_elem(0.0)
                .bool_or(q.clone().greater_elem(hi));
            q.ones_like().mask_fill(outside, 0.0)
        };
        let inside0 = inside(&p0, (h - 1) as f64);
        let inside1 = inside(&p1, (w - 1) as f64);
        let p0 = p0.clamp(0.0, (h - 1) as f64);
        let p1 = p1.clamp(0.0, (w - 1) as f64);
        // The integer part carries no gradient; the fractional part carries all of it.
        let fl0 = p0.clone().detach().floor();
        let fl1 = p1.clone().detach().floor();
        let t0 = p0 - fl0.clone();
        let t1 = p1 - fl1.clone();
        let rows: Vec<Tensor<3>> = (0..4)
            .map(|a| mirror(fl0.clone().add_scalar(a as f64 - 1.0), h))
            .collect();
        let cols: Vec<Tensor<3>> = (0..4)
            .map(|b| mirror(fl1.clone().add_scalar(b as f64 - 1.0), w))
            .collect();
        let mut flat = Vec::with_capacity(16);
        for r in &rows {
            let base = r.clone().mul_scalar(w as f64);
            for col in &cols {
                flat.push((base.clone() + col.clone()).int());
            }
        }
        Stencil {
            flat,
            w0: bspline_weights(t0.clone()),
            w1: bspline_weights(t1.clone()),
            t0: t0.detach(),
            t1: t1.detach(),
            inside0,
            inside1,
        }
    }
}
