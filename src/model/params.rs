//! Model parameters with the defaults of SPEC §9 (the paper's Table 2).

use crate::error::{Error, Result};

/// The parameters of the path energy (SPEC §2, §3, §5). Construct with [`EnergyParams::rgb`]
/// or [`EnergyParams::deep`], change fields, then [`validate`](EnergyParams::validate).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EnergyParams {
    /// `λ`, weight of the volumetric term `exp((log det J)²) − 1` of `W` (SPEC §2).
    /// Default 0.1 (RGB), 0.002 (deep).
    pub lambda: f64,
    /// `μ`, weight of the linearised-strain term `|sym J − I|²` of `W` (SPEC §2).
    /// Default 0.025 (RGB), 0.002 (deep).
    pub mu: f64,
    /// `δ`, the data term's weight is `1/δ` (SPEC §5). Default 1.
    pub delta: f64,
    /// `σ`, pre-smoothing of the image for the anisotropy, in pixels (SPEC §3). Default 0.5.
    pub sigma: f64,
    /// `ρ`, smoothing of the gradient maps for the anisotropy, in pixels (SPEC §3). Default 2.
    pub rho: f64,
    /// `ξ₁`, edge sensitivity of the anisotropy (SPEC §3). Default 1000.
    pub xi1: f64,
    /// `ξ₂`, lower bound of the anisotropy (SPEC §3). Default 1e-6.
    pub xi2: f64,
}

impl EnergyParams {
    /// SPEC §9 defaults of the RGB model.
    pub fn rgb() -> Self {
        Self {
            lambda: 0.1,
            mu: 0.025,
            delta: 1.0,
            sigma: 0.5,
            rho: 2.0,
            xi1: 1000.0,
            xi2: 1e-6,
        }
    }

    /// SPEC §9 defaults of the deep model.
    pub fn deep() -> Self {
        Self {
            lambda: 0.002,
            mu: 0.002,
            ..Self::rgb()
        }
    }

    /// Checks every parameter against its valid range.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] naming the first bad value and its range.
    pub fn validate(&self) -> Result<()> {
        positive("lambda", self.lambda)?;
        positive("mu", self.mu)?;
        positive("delta", self.delta)?;
        positive("sigma", self.sigma)?;
        positive("rho", self.rho)?;
        // A Gaussian has 2⌈3s⌉ + 1 taps: wider than any image is meaningless, and a huge s
        // would allocate without bound.
        for (name, s) in [("sigma", self.sigma), ("rho", self.rho)] {
            if s > MAX_SMOOTHING {
                return Err(Error::invalid(name, s, "at most 100 pixels"));
            }
        }
        positive("xi1", self.xi1)?;
        positive("xi2", self.xi2)?;
        Ok(())
    }
}

/// The largest `σ` and `ρ` of the anisotropy, in pixels.
pub const MAX_SMOOTHING: f64 = 100.0;

/// Checks that `value` is finite and `> 0`.
pub(crate) fn positive(name: &'static str, value: f64) -> Result<()> {
    if value.is_finite() && value > 0.0 {
        Ok(())
    } else {
        Err(Error::invalid(name, value, "a finite number > 0"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_bad_values_are_named() {
        EnergyParams::rgb().validate().unwrap();
        EnergyParams::deep().validate().unwrap();
        let bad = EnergyParams {
            delta: f64::NAN,
            ..EnergyParams::rgb()
        };
        let msg = bad.validate().unwrap_err().to_string();
        assert!(msg.contains("delta") && msg.contains("NaN"), "{msg}");
        let bad = EnergyParams {
            mu: -1.0,
            ..EnergyParams::rgb()
        };
        assert!(bad.validate().unwrap_err().to_string().contains("mu = -1"));
    }
}
