//! The test hooks of the command line, read from the environment: how the end-to-end tests
//! make a run meet a NaN or an interrupt at a chosen sweep without a real fault or signal.
//! A user never sets them; they change nothing when unset.
//!
//! - `DEEPMORPH_INJECT_NONFINITE=LEVEL:SWEEP`: the solver meets a NaN after that sweep (the
//!   non-finite path end to end: outputs written from the last finite iterate, exit 3).
//!   Only in builds with the test-only feature `check` (the tests' builds); elsewhere it is
//!   refused.
//! - `DEEPMORPH_INTERRUPT_AT=LEVEL:SWEEP`: the interrupt flag is raised after that joint
//!   sweep, as a signal would (`--resume` end to end).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use crate::app::job::MorphJob;
use crate::error::{Error, Result};
use crate::solver::observer::{Observer, Phase, SweepEvent};

/// The hooks that are set.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TestHooks {
    /// `DEEPMORPH_INJECT_NONFINITE`.
    pub inject_nonfinite: Option<(usize, usize)>,
    /// `DEEPMORPH_INTERRUPT_AT`.
    pub interrupt_at: Option<(usize, usize)>,
}

impl TestHooks {
    /// The hooks of this process's environment.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] if a variable is set but not `LEVEL:SWEEP`.
    pub fn from_env() -> Result<Self> {
        Ok(Self {
            inject_nonfinite: level_and_sweep("DEEPMORPH_INJECT_NONFINITE")?,
            interrupt_at: level_and_sweep("DEEPMORPH_INTERRUPT_AT")?,
        })
    }

    /// `job` with the fault injected, if one is set.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] if a fault is asked for in a build without the test-only
    /// feature `check`, which alone can inject one.
    pub fn apply(&self, job: MorphJob) -> Result<MorphJob> {
        match self.inject_nonfinite {
            None => Ok(job),
            #[cfg(feature = "check")]
            Some((level, sweep)) => Ok(job.inject_nonfinite(level, sweep)),
            #[cfg(not(feature = "check"))]
            Some((level, sweep)) => Err(Error::invalid(
                "DEEPMORPH_INJECT_NONFINITE",
                format!("{level}:{sweep}"),
                "unset: fault injection is a test hook, built only with the feature `check`",
            )),
        }
    }

    /// An observer that raises `flag` after the joint sweep of `DEEPMORPH_INTERRUPT_AT`
    /// (never, when unset).
    pub fn interrupter(&self, flag: Arc<AtomicBool>) -> InterruptAt {
        InterruptAt {
            at: self.interrupt_at,
            flag,
        }
    }
}

/// `LEVEL:SWEEP` from the environment variable `name`.
fn level_and_sweep(name: &'static str) -> Result<Option<(usize, usize)>> {
    let Some(value) = std::env::var_os(name) else {
        return Ok(None);
    };
    let value = value.to_string_lossy();
    value
        .split_once(':')
        .and_then(|(l, s)| Some((l.trim().parse().ok()?, s.trim().parse().ok()?)))
        .map(Some)
        .ok_or_else(|| Error::invalid(name, value, "LEVEL:SWEEP, two whole numbers"))
}

/// Raises the interrupt flag after one joint sweep `(level, sweep)`, as a signal would.
#[derive(Debug)]
pub struct InterruptAt {
    at: Option<(usize, usize)>,
    flag: Arc<AtomicBool>,
}

impl Observer for InterruptAt {
    fn sweep(&mut self, e: &SweepEvent<'_>) {
        if e.phase == Phase::Joint && self.at == Some((e.level, e.sweep)) {
            self.flag.store(true, Ordering::SeqCst);
        }
    }
}
