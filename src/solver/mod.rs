//! The solver: iPALM on one level (SPEC §6, the paper's Algorithm 1) and the coarse-to-fine
//! driver (SPEC §7), with the observers that watch it.
//!
//! - [`backtracking`]: the one backtracking search on a Lipschitz estimate, with its give-up
//!   rule, used by every step.
//! - [`prox`]: the linearised data term of a deformation step and its pointwise prox;
//!   [`prox_op`] its trial fused into one custom op (flex); [`update_op`] the steps'
//!   elementwise updates (the inertial extrapolation, a feature trial's gradient step) fused.
//! - [`ipalm`]: the level's state and one sweep in either schedule ([`ipalm::Schedule`]):
//!   the sequential one runs the steps `k = 1..K` one at a time, `batched` as three stacked
//!   blocks; both take their steps from `steps` (SPEC §6 steps 2 and 3 for any set of `k`
//!   at once: deformation and feature steps, the safeguard and its inertia restart).
//! - [`level_run`]: one level as a state machine ([`level_run::LevelRun`]: `init` from
//!   how its state began, `next_sweep`, `terminate`), the named energy record of a sweep,
//!   and [`level_run::prolongate`].
//! - [`multilevel`]: the pyramid and the executor: runs the levels coarse to fine and owns
//!   the tolerance, the interrupt and the observers.
//! - [`estimate`]: how long a morph will take, from sweeps timed on two of its levels.
//! - [`observer`]: what the driver reports after each sweep, and to whom.

pub mod backtracking;
mod batched;
pub mod estimate;
pub mod initial;
pub mod ipalm;
pub mod level_run;
pub mod multilevel;
pub mod observer;
pub mod prox;
pub mod prox_op;
mod steps;
pub mod update_op;
