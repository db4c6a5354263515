//! The batched schedule ([`Schedule::Batched`](super::ipalm::Schedule::Batched)): the steps of
//! SPEC §6 for every `k`, grouped into three blocks per sweep, each one operation on stacked
//! `[n, C, H, W]` tensors.
//!
//! 1. All deformations `φ_1..φ_K`: given the frames they are independent. Each `k` keeps its
//!    own `L_φ,k`, backtracking search, safeguard and inertia restart; the searches run in
//!    lockstep (one batched trial and one read-back per round, until every `k` is decided).
//!    A round, a restart and a safeguard doubling evaluate only the steps still undecided:
//!    recomputing every `k` for the one still searching made a deep batched sweep several
//!    times the work of a sequential one.
//! 2. All odd frames, then 3. all even frames: given the deformations and the frames of the
//!    other parity, `f_k` only meets `f_{k±1}`, so the frames of one parity are independent.
//!
//! The steps themselves are the sequential schedule's ([`super::steps`]), run for many `k`
//! at once.
//!
//! This is iPALM with three blocks instead of `2K − 1`: the same energy and the same
//! admissibility guarantee, another block order (every `φ_k` sees the frames of the previous
//! sweep, every `f_k` the new deformations).

use burn::tensor::Tensor;

use crate::error::Result;
use crate::solver::ipalm::{
    Block, FeatureStep, Ipalm, LevelState, PartialSweep, SweepEnd, SweepKind,
};
use crate::solver::steps::FeatureSteps;

impl Ipalm {
    /// One sweep of the batched schedule; `anisotropy`, when given, holds `a_1..a_K` of
    /// `state` (`[K, H, W]`, [`super::ipalm::SweepCarry`]). Its blocks, `stop` and `from` as
    /// in [`Ipalm::sweep_until`].
    pub(super) fn sweep_batched(
        &self,
        state: &mut LevelState,
        kind: SweepKind,
        anisotropy: Option<Tensor<3>>,
        from: Option<PartialSweep>,
        stop: &dyn Fn() -> bool,
    ) -> Result<SweepEnd> {
        let k = state.steps();
        let (mut cursor, mut report) = PartialSweep::start(from, k, stop);
        if kind == SweepKind::Joint && cursor.next(false) == Block::Run {
            let a = anisotropy.unwrap_or_else(|| self.anisotropies(state));
            let all: Vec<usize> = (1..=k).collect();
            let steps = self.deformation_steps(state, &all, a.clone(), None, false)?;
            for (i, (phi, step, _)) in steps.into_iter().enumerate() {
                state.apply_deformation(i + 1, phi, &step);
                report.record_deformation(i + 1, step);
            }
            report.anisotropy = (0..k).map(|i| a.clone().narrow(0, i, 1)).collect();
        }
        let mut features: Vec<Option<FeatureStep>> = vec![None; k.saturating_sub(1)];
        // A continued sweep's: those of the passes run, in `k` order.
        let mut recorded = std::mem::take(&mut report.features).into_iter();
        for parity in [1, 0] {
            let ks: Vec<usize> = (1..k).filter(|j| j % 2 == parity).collect();
            match cursor.next(ks.is_empty()) {
                Block::Ran => {
                    for &j in &ks {
                        features[j - 1] = recorded.next();
                    }
                    continue;
                }
                Block::Stop { blocks } => {
                    report.features = features.into_iter().flatten().collect();
                    return Ok(SweepEnd::Stopped(PartialSweep::of(report, blocks)));
                }
                Block::Run if ks.is_empty() => continue,
                Block::Run => {}
            }
            let FeatureSteps { frames, steps, .. } = self.feature_steps(state, &ks, None)?;
            // Recorded in the order the passes run: every `D_k` next to an even frame is final
            // only after the even pass, `D_1` and (for even `K`) `D_K` after the odd one.
            for ((&j, f), step) in ks.iter().zip(frames).zip(steps) {
                report.record_residuals(j, step.residual_norm2);
                state.l_f[j - 1] = step.lipschitz.clone();
                state.f_prev[j] = std::mem::replace(&mut state.f[j], f);
                features[j - 1] = Some(step);
            }
        }
        report.features = features
            .into_iter()
            .map(|s| s.expect("every k < K has a feature step"))
            .collect();
        Ok(SweepEnd::Done(report))
    }
}
