//! One level of the iPALM solver (SPEC §6, the paper's Algorithm 1).
//!
//! [`Ipalm`] holds the level's operators and the configuration and performs one sweep
//! ([`Ipalm::sweep`]) on a [`LevelState`]; the loop over sweeps, termination, progress and
//! interruption belong to the caller (the multilevel driver), as in argmin's split between
//! solver and executor.

use burn::tensor::Tensor;

use crate::deformation::{admissible_each, is_admissible};
use crate::energy::data::{data_term_from_coefficients, data_term_from_warped};
use crate::energy::path::{EnergyValue, PathEnergy};
use crate::energy::regularizer::regularizer;
use crate::error::{Error, Result};
use crate::grid::Grid;
use crate::io::to_host;
use crate::layout::FeatureLayout;
use crate::optim::backtracking::Backtracking;
use crate::optim::prox::{LinearisedData, linearise};
use crate::params::EnergyParams;
use crate::sobel::Sobel;

/// The solver's settings beyond the energy (SPEC §6, §9).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IpalmConfig {
    /// Inertial extrapolation `β`, in `[0, 1)`. Default `1/√2`.
    pub beta: f64,
    /// The safeguard of SPEC §6: after a deformation step is accepted, keep doubling `L`
    /// while the true local energy is above its value at the current `φ_k`. Default on;
    /// off is the paper's plain algorithm (and the golden sweeps).
    pub safeguard: bool,
    /// Doublings of the safeguard before the step is dropped (`φ_k` kept). Default 30.
    pub safeguard_max: usize,
    /// The backtracking rule of both steps.
    pub backtracking: Backtracking,
}

impl Default for IpalmConfig {
    fn default() -> Self {
        Self {
            beta: std::f64::consts::FRAC_1_SQRT_2,
            safeguard: true,
            safeguard_max: 30,
            backtracking: Backtracking::default(),
        }
    }
}

impl IpalmConfig {
    /// Checks the ranges.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] naming the bad field.
    pub fn validate(&self) -> Result<()> {
        if !(0.0..1.0).contains(&self.beta) {
            return Err(Error::invalid("beta", self.beta, "in [0, 1)"));
        }
        self.backtracking.validate()
    }
}

/// The iterate of one level: frames, deformations, their values of the previous sweep, and
/// the stored Lipschitz estimates.
#[derive(Clone, Debug)]
pub struct LevelState {
    /// `f_0..f_K`, each `[1, C_tot, H, W]`; `f_0` and `f_K` never change.
    pub f: Vec<Tensor<4>>,
    /// `f_k` of the previous sweep.
    pub f_prev: Vec<Tensor<4>>,
    /// `φ_1..φ_K` (index `k − 1`), each `[1, 2, H, W]`.
    pub phi: Vec<Tensor<4>>,
    /// `φ_k` of the previous sweep.
    pub phi_prev: Vec<Tensor<4>>,
    /// Stored `L_φ,k`, `k = 1..K`.
    pub l_phi: Vec<f64>,
    /// Stored `L_f,k` per block, `k = 1..K−1`.
    pub l_f: Vec<Vec<f64>>,
}

impl LevelState {
    /// A state with `prev = current`.
    ///
    /// # Errors
    ///
    /// If the counts do not fit (`K + 1` frames, `K` deformations, `K` and `K − 1` estimates).
    pub fn new(
        f: Vec<Tensor<4>>,
        phi: Vec<Tensor<4>>,
        l_phi: Vec<f64>,
        l_f: Vec<Vec<f64>>,
    ) -> Result<Self> {
        let k = phi.len();
        if k == 0 || f.len() != k + 1 || l_phi.len() != k || l_f.len() != k - 1 {
            return Err(Error::Shape {
                op: "LevelState::new",
                detail: format!(
                    "{} frames, {} deformations, {} L_phi, {} L_f: expected K+1, K, K, K-1",
                    f.len(),
                    k,
                    l_phi.len(),
                    l_f.len()
                ),
            });
        }
        Ok(Self {
            f_prev: f.clone(),
            phi_prev: phi.clone(),
            f,
            phi,
            l_phi,
            l_f,
        })
    }

    /// The initial state of SPEC §6/§7: `φ_k = Id`, `f_k = (1 − k/K) f_A + (k/K) f_B`, prev
    /// = current, and the initial Lipschitz estimates `s²/(H·W)` of each block.
    ///
    /// # Shapes
    /// - `f_a`, `f_b`: `[1, C_tot, H, W]`
    pub fn initial(
        grid: &Grid,
        layout: &FeatureLayout,
        f_a: Tensor<4>,
        f_b: Tensor<4>,
        k: usize,
    ) -> Result<Self> {
        let f = (0..=k)
            .map(|step| {
                let t = step as f64 / k as f64;
                match step {
                    0 => f_a.clone(),
                    s if s == k => f_b.clone(),
                    _ => f_a.clone().mul_scalar(1.0 - t) + f_b.clone().mul_scalar(t),
                }
            })
            .collect();
        let phi = vec![grid.identity(1); k];
        let (l_phi, l_f) = initial_lipschitz(grid, layout, k);
        Self::new(f, phi, l_phi, l_f)
    }

    /// `K`.
    pub fn steps(&self) -> usize {
        self.phi.len()
    }

    /// `f_0..f_K` as one `[K+1, C_tot, H, W]` tensor.
    pub fn frames(&self) -> Tensor<4> {
        Tensor::cat(self.f.clone(), 0)
    }

    /// `φ_1..φ_K` as one `[K, 2, H, W]` tensor.
    pub fn deformations(&self) -> Tensor<4> {
        Tensor::cat(self.phi.clone(), 0)
    }
}

/// The initial estimates `L = s²/(H·W)` (SPEC §6): `K` values of `L_φ` (`s = 1`) and, per
/// interior frame, one per block (`s` = the block's scale).
pub fn initial_lipschitz(
    grid: &Grid,
    layout: &FeatureLayout,
    k: usize,
) -> (Vec<f64>, Vec<Vec<f64>>) {
    let pixels = grid.pixels() as f64;
    let l_f: Vec<f64> = layout
        .blocks()
        .iter()
        .map(|b| b.scale * b.scale / pixels)
        .collect();
    (vec![1.0 / pixels; k], vec![l_f; k.saturating_sub(1)])
}

/// Which steps a sweep runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SweepKind {
    /// Anisotropy, deformation and feature steps for every `k` (SPEC §6).
    Joint,
    /// Only the feature steps, deformations fixed (the deep model's `J_pre` sweeps, SPEC §7).
    FeaturesOnly,
}

/// What the deformation step of one `k` did.
#[derive(Clone, Debug, PartialEq)]
pub struct DeformationStep {
    /// The accepted (stored) `L_φ,k`.
    pub lipschitz: f64,
    /// Trial values of `L` until acceptance (1 = the first trial was accepted).
    pub trials: usize,
    /// How many of those trials gave an inadmissible `φ_new`.
    pub inadmissible_trials: usize,
    /// Doublings of `L` by the safeguard after acceptance.
    pub safeguard_doublings: usize,
    /// Whether the step was dropped (`φ_k` kept): backtracking or safeguard exhausted.
    pub dropped: bool,
}

/// What the feature step of one `k` did, per block.
#[derive(Clone, Debug, PartialEq)]
pub struct FeatureStep {
    /// The accepted (stored) `L_f,k` of each block.
    pub lipschitz: Vec<f64>,
    /// Trials of each block until acceptance.
    pub trials: Vec<usize>,
}

/// The record of one sweep.
#[derive(Clone, Debug)]
pub struct SweepReport {
    /// The anisotropies `a_1..a_K` of step 1, `[1, H, W]` each (empty for a features-only
    /// sweep).
    pub anisotropy: Vec<Tensor<3>>,
    /// Deformation steps, `k = 1..K` (empty for a features-only sweep).
    pub deformation: Vec<DeformationStep>,
    /// Feature steps, `k = 1..K−1`.
    pub features: Vec<FeatureStep>,
}

/// The iPALM solver on one level.
#[derive(Clone, Debug)]
pub struct Ipalm {
    grid: Grid,
    energy: PathEnergy,
    layout: FeatureLayout,
    sobel: Sobel,
    config: IpalmConfig,
}

/// One number read back from the device.
fn scalar(t: Tensor<1>) -> f64 {
    to_host(t)[0]
}

/// Several numbers read back at once (one synchronisation).
fn scalars(parts: Vec<Tensor<1>>) -> Vec<f64> {
    to_host(Tensor::cat(parts, 0))
}

impl Ipalm {
    /// The solver on `grid` (whose device must have autodiff enabled: the steps take
    /// gradients) for features laid out as `layout`.
    ///
    /// # Errors
    ///
    /// If a parameter is out of range.
    pub fn new(
        grid: &Grid,
        params: EnergyParams,
        layout: FeatureLayout,
        config: IpalmConfig,
    ) -> Result<Self> {
        config.validate()?;
        Ok(Self {
            grid: grid.clone(),
            energy: PathEnergy::new(grid, params, layout.channels())?,
            sobel: Sobel::new(grid),
            layout,
            config,
        })
    }

    /// The path energy of this level.
    pub fn path_energy(&self) -> &PathEnergy {
        &self.energy
    }

    /// The configuration.
    pub fn config(&self) -> &IpalmConfig {
        &self.config
    }

    /// `a_k = a[u_k]` for the frames `f_1..f_K` of `state`, `[K, H, W]`.
    pub fn anisotropies(&self, state: &LevelState) -> Tensor<3> {
        let k = state.steps();
        let frames = Tensor::cat(state.f[1..=k].to_vec(), 0);
        self.energy
            .anisotropy()
            .compute(self.layout.rgb_part(frames))
    }

    /// `E` of `state` with every `a_k` recomputed from its `f_k` (SPEC §10: the energy after
    /// a sweep).
    pub fn energy(&self, state: &LevelState) -> EnergyValue {
        self.energy.value(
            state.frames(),
            state.deformations(),
            self.anisotropies(state),
        )
    }

    /// One sweep over `k = 1..K` (SPEC §6), updating `state` in place.
    ///
    /// # Errors
    ///
    /// [`Error::NonFinite`] if a NaN or infinity shows up in an energy or gradient of the
    /// state; the state is then left at the last finite iterate.
    pub fn sweep(&self, state: &mut LevelState, kind: SweepKind) -> Result<SweepReport> {
        let k_steps = state.steps();
        let mut report = SweepReport {
            anisotropy: Vec::new(),
            deformation: Vec::new(),
            features: Vec::new(),
        };
        for k in 1..=k_steps {
            if kind == SweepKind::Joint {
                let rgb = self.layout.rgb_part(state.f[k].clone());
                let a = self.energy.anisotropy().compute(rgb);
                let [_, h, w] = a.dims();
                let a = a.reshape([1, h, w]);
                let (phi_new, step) = self.deformation_step(state, k, a.clone())?;
                state.l_phi[k - 1] = step.lipschitz;
                state.phi_prev[k - 1] = std::mem::replace(&mut state.phi[k - 1], phi_new);
                report.anisotropy.push(a);
                report.deformation.push(step);
            }
            if k < k_steps {
                let (f_new, step) = self.feature_step(state, k)?;
                state.l_f[k - 1] = step.lipschitz.clone();
                state.f_prev[k] = std::mem::replace(&mut state.f[k], f_new);
                report.features.push(step);
            }
        }
        Ok(report)
    }

    /// The deformation step of `k` (SPEC §6 step 2): returns `φ_new` and what happened.
    fn deformation_step(
        &self,
        state: &LevelState,
        k: usize,
        a: Tensor<3>,
    ) -> Result<(Tensor<4>, DeformationStep)> {
        let k_steps = state.steps() as f64;
        let p = *self.energy.params();
        let bt = self.config.backtracking;
        let phi = state.phi[k - 1].clone();
        let smooth =
            |phi: Tensor<4>| regularizer(phi, a.clone(), p.lambda, p.mu).mul_scalar(k_steps);

        let mut phi_tilde = phi.clone();
        if self.config.beta > 0.0 {
            let extrapolated = phi.clone()
                + (phi.clone() - state.phi_prev[k - 1].clone()).mul_scalar(self.config.beta);
            if is_admissible(&self.grid, extrapolated.clone()) {
                phi_tilde = extrapolated;
            }
        }

        // S(φ̃) and g = ∇S(φ̃) by autodiff.
        let leaf = phi_tilde.clone().detach().require_grad();
        let s_tilde = smooth(leaf.clone());
        let grads = s_tilde.backward();
        let g = leaf
            .grad(&grads)
            .expect("the regulariser depends on phi")
            .autodiff();
        let s_tilde = scalar(s_tilde.detach());
        if !s_tilde.is_finite() {
            return Err(Error::NonFinite {
                what: format!("K·R at the extrapolated deformation of step k = {k} is {s_tilde}"),
            });
        }

        let bspline = self.energy.bspline();
        let coeffs_k = bspline.coefficients(state.f[k].clone());
        let lin = linearise(
            bspline,
            &self.sobel,
            coeffs_k.clone(),
            state.f[k - 1].clone(),
            phi_tilde.clone(),
        );
        let kappa = k_steps / (p.delta * self.layout.channels() as f64 * self.grid.pixels() as f64);
        let data = LinearisedData::new(&self.grid, lin, phi_tilde.clone(), kappa);
        let trial = |l: f64| data.prox(phi_tilde.clone() - g.clone().mul_scalar(1.0 / l), l);

        let mut l = bt.shrink * state.l_phi[k - 1];
        let mut step = DeformationStep {
            lipschitz: l,
            trials: 0,
            inadmissible_trials: 0,
            safeguard_doublings: 0,
            dropped: false,
        };
        let mut accepted = None;
        while step.trials < bt.max_trials {
            step.trials += 1;
            let candidate = trial(l);
            if !admissible_each(&self.grid, candidate.clone())[0] {
                step.inadmissible_trials += 1;
                l *= 2.0;
                continue;
            }
            let d = candidate.clone() - phi_tilde.clone();
            let v = scalars(vec![
                smooth(candidate.clone()),
                (g.clone() * d.clone()).sum(),
                d.square().sum(),
            ]);
            if bt.accepts(v[0], s_tilde, v[1], v[2], l) {
                accepted = Some(candidate);
                break;
            }
            l *= 2.0;
        }
        let Some(mut phi_new) = accepted else {
            step.dropped = true;
            step.lipschitz = l;
            return Ok((phi, step));
        };

        if self.config.safeguard {
            // The true local energy e(φ) = K·R[φ, a_k] + (K/δ)·D[f_{k−1}, f_k, φ].
            let local = |phi: Tensor<4>| {
                let d = data_term_from_coefficients(
                    bspline,
                    state.f[k - 1].clone(),
                    coeffs_k.clone(),
                    phi.clone(),
                    self.layout.channels(),
                );
                scalar(smooth(phi) + d.mul_scalar(k_steps / p.delta))
            };
            let current = local(phi.clone());
            // Written so that a NaN energy counts as a rise.
            while !(local(phi_new.clone()) <= current) {
                if step.safeguard_doublings == self.config.safeguard_max {
                    step.dropped = true;
                    phi_new = phi.clone();
                    break;
                }
                step.safeguard_doublings += 1;
                l *= 2.0;
                phi_new = trial(l);
            }
        }
        step.lipschitz = l;
        Ok((phi_new, step))
    }

    /// The feature step of `k < K` (SPEC §6 step 3), block by block: returns `f_new`.
    fn feature_step(&self, state: &LevelState, k: usize) -> Result<(Tensor<4>, FeatureStep)> {
        let k_steps = state.steps() as f64;
        let p = *self.energy.params();
        let bt = self.config.backtracking;
        let bspline = self.energy.bspline();
        let c_tot = self.layout.channels();
        let f_k = state.f[k].clone();
        let f_tilde = if self.config.beta > 0.0 {
            f_k.clone() + (f_k.clone() - state.f_prev[k].clone()).mul_scalar(self.config.beta)
        } else {
            f_k
        };
        // φ_k is already this sweep's, φ_{k+1} still the previous one. Both stay fixed for the
        // whole step: φ_k's stencil serves every block and trial, and T[f_{k+1}, φ_{k+1}] does
        // not depend on f_k at all.
        let sampler_k = bspline.sampler(state.phi[k - 1].clone());
        let next_warped = bspline.interpolate(
            bspline.coefficients(state.f[k + 1].clone()),
            state.phi[k].clone(),
        );

        let mut blocks = Vec::new();
        let mut step = FeatureStep {
            lipschitz: Vec::new(),
            trials: Vec::new(),
        };
        for (b, block) in self.layout.blocks().iter().enumerate() {
            let (start, len) = (block.channels.start, block.channels.len());
            let prev = state.f[k - 1].clone().narrow(1, start, len);
            let next = next_warped.clone().narrow(1, start, len);
            // Q restricted to the block: (K/δ)(D[f_{k−1}, x, φ_k] + D[x, f_{k+1}, φ_{k+1}]),
            // still divided by C_tot.
            let q = |x: Tensor<4>| {
                let warped = sampler_k.sample(bspline.coefficients(x.clone()));
                let moved = data_term_from_warped(warped, prev.clone(), c_tot);
                let fixed = data_term_from_warped(next.clone(), x, c_tot);
                (moved + fixed).mul_scalar(k_steps / p.delta)
            };
            let x_tilde = f_tilde.clone().narrow(1, start, len).detach();
            let leaf = x_tilde.clone().require_grad();
            let q_leaf = q(leaf.clone());
            let grads = q_leaf.backward();
            let grad = leaf.grad(&grads).expect("Q depends on f_k").autodiff();
            let v = scalars(vec![q_leaf.detach(), grad.clone().square().sum()]);
            let (q_tilde, grad_norm2) = (v[0], v[1]);
            if !(q_tilde.is_finite() && grad_norm2.is_finite()) {
                return Err(Error::NonFinite {
                    what: format!(
                        "feature step k = {k}, block {b}: Q = {q_tilde}, |grad Q|^2 = {grad_norm2}"
                    ),
                });
            }
            let mut l = bt.shrink * state.l_f[k - 1][b];
            let mut trials = 0;
            let mut accepted = None;
            while trials < bt.max_trials {
                trials += 1;
                let candidate = x_tilde.clone() - grad.clone().mul_scalar(1.0 / l);
                let q_new = scalar(q(candidate.clone()));
                // x_new − x̃ = −∇Q/L: ⟨∇Q, x_new − x̃⟩ = −‖∇Q‖²/L, ‖x_new − x̃‖² = ‖∇Q‖²/L².
                if bt.accepts(q_new, q_tilde, -grad_norm2 / l, grad_norm2 / (l * l), l) {
                    accepted = Some(candidate);
                    break;
                }
                l *= 2.0;
            }
            // Exhausted backtracking keeps the block's current values.
            blocks.push(accepted.unwrap_or_else(|| state.f[k].clone().narrow(1, start, len)));
            step.lipschitz.push(l);
            step.trials.push(trials);
        }
        Ok((Tensor::cat(blocks, 1), step))
    }
}
