//! The backtracking rule shared by the deformation and feature steps (SPEC §6).

use crate::error::{Error, Result};

/// Backtracking on a Lipschitz estimate `L`: each step starts from `shrink · L_stored` and
/// doubles `L` until the trial is accepted.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Backtracking {
    /// Factor applied to the stored `L` before the first trial of a step. Default 0.9
    /// (SPEC §6). Must lie in `(0, 1]`.
    pub shrink: f64,
    /// Trials per step before giving up and keeping the current iterate. Default 60 (`L`
    /// grows by 2⁶⁰ by then; in practice a handful of trials suffice).
    pub max_trials: usize,
    /// Relative slack of the sufficient-decrease test. The energies are computed in the
    /// working precision (float32 on the GPU), where a step that barely changes the energy
    /// can fail the test by rounding alone; a violation below `slack · |F(x̃)|` counts as
    /// satisfied (SPEC §6 "Floating point"). Default 1e-6. Must lie in `[0, 1e-3]`.
    pub slack: f64,
}

impl Default for Backtracking {
    fn default() -> Self {
        Self {
            shrink: 0.9,
            max_trials: 60,
            slack: 1e-6,
        }
    }
}

impl Backtracking {
    /// Checks the ranges.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] naming the bad field.
    pub fn validate(&self) -> Result<()> {
        if !(self.shrink > 0.0 && self.shrink <= 1.0) {
            return Err(Error::invalid("shrink", self.shrink, "in (0, 1]"));
        }
        if self.max_trials == 0 {
            return Err(Error::invalid("max_trials", "0", "at least 1"));
        }
        if !(0.0..=1e-3).contains(&self.slack) {
            return Err(Error::invalid("slack", self.slack, "in [0, 1e-3]"));
        }
        Ok(())
    }

    /// The sufficient-decrease test of SPEC §6,
    /// `F(x_new) ≤ F(x̃) + ⟨∇F(x̃), x_new − x̃⟩ + L/2 ‖x_new − x̃‖²`, with the float slack.
    /// A non-finite `F(x_new)` never passes.
    pub fn accepts(&self, new: f64, old: f64, inner: f64, norm2: f64, l: f64) -> bool {
        new.is_finite() && new <= old + inner + 0.5 * l * norm2 + self.slack * old.abs()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decrease_test_and_slack() {
        let b = Backtracking::default();
        assert!(b.accepts(1.0, 1.0, 0.0, 0.0, 1.0));
        assert!(b.accepts(1.0 + 5e-7, 1.0, 0.0, 0.0, 1.0));
        assert!(!b.accepts(1.0 + 2e-6, 1.0, 0.0, 0.0, 1.0));
        assert!(b.accepts(1.5, 1.0, -0.5, 2.0, 1.0)); // 1.5 <= 1 − 0.5 + 1
        assert!(!b.accepts(f64::INFINITY, 1.0, 0.0, 0.0, 1.0));
        assert!(!b.accepts(f64::NAN, 1.0, 0.0, 0.0, 1.0));
        let bad = Backtracking { shrink: 1.5, ..b };
        assert!(
            bad.validate()
                .unwrap_err()
                .to_string()
                .contains("shrink = 1.5")
        );
    }
}
