//! The test hooks of the command line, read from the environment: how the end-to-end tests
//! make a run meet a NaN or an interrupt at a chosen sweep without a real fault or signal.
//! A user never sets them; they change nothing when unset.
//!
//! - `DEEPMORPH_INJECT_NONFINITE=LEVEL:SWEEP`: the solver meets a NaN after that sweep (the
//!   non-finite path end to end: outputs written from the last finite iterate, exit 3).
//!   Only in builds with the test-only feature `check` (the tests' builds); elsewhere it is
//!   refused.
//! - `DEEPMORPH_INTERRUPT_AT=LEVEL:SWEEP`: the interrupt flag is raised after that joint
//!   sweep, as a signal would (`--resume` end to end); `LEVEL:SWEEP:BLOCKS`: the next sweep
//!   stops after `BLOCKS` of its blocks, as a signal during it would (`--resume` within a
//!   sweep).

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
    /// `DEEPMORPH_INTERRUPT_AT`'s level and sweep.
    pub interrupt_at: Option<(usize, usize)>,
    /// `DEEPMORPH_INTERRUPT_AT`'s blocks of the next sweep, if given.
    pub interrupt_within: Option<usize>,
}

impl TestHooks {
    /// The hooks of this process's environment.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] if a variable is set but not `LEVEL:SWEEP`.
    pub fn from_env() -> Result<Self> {
        let (interrupt_at, interrupt_within) = match numbers("DEEPMORPH_INTERRUPT_AT", 3)? {
            None => (None, None),
            Some(n) => (Some((n[0], n[1])), n.get(2).copied()),
        };
        Ok(Self {
            inject_nonfinite: numbers("DEEPMORPH_INJECT_NONFINITE", 2)?.map(|n| (n[0], n[1])),
            interrupt_at,
            interrupt_within,
        })
    }

    /// `job` with the fault injected, if one is set.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] if a fault is asked for in a build without the test-only
    /// feature `check`, which alone can inject one.
    pub fn apply(&self, mut job: MorphJob) -> Result<MorphJob> {
        if let (Some((level, sweep)), Some(blocks)) = (self.interrupt_at, self.interrupt_within) {
            job = job.stop_within(level, sweep + 1, blocks);
        }
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
    /// (never, when unset or when the interrupt falls within the next sweep).
    pub fn interrupter(&self, flag: Arc<AtomicBool>) -> InterruptAt {
        InterruptAt {
            at: self
                .interrupt_at
                .filter(|_| self.interrupt_within.is_none()),
            flag,
        }
    }
}

/// `LEVEL:SWEEP` (and up to `most` numbers in all, `:`-separated) from the environment
/// variable `name`.
fn numbers(name: &'static str, most: usize) -> Result<Option<Vec<usize>>> {
    let Some(value) = std::env::var_os(name) else {
        return Ok(None);
    };
    let value = value.to_string_lossy();
    let parsed: Option<Vec<usize>> = value.split(':').map(|n| n.trim().parse().ok()).collect();
    match parsed {
        Some(n) if (2..=most).contains(&n.len()) => Ok(Some(n)),
        _ => Err(Error::invalid(
            name,
            value,
            if most == 2 {
                "LEVEL:SWEEP, two whole numbers"
            } else {
                "LEVEL:SWEEP or LEVEL:SWEEP:BLOCKS, whole numbers"
            },
        )),
    }
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
