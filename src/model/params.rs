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

/// The range of a model parameter (weights, widths, `η`): the defaults span 1e-6 … 1e3,
/// and the energy is computed in float32, where a factor past 1e12 (or below 1e-12, in a
/// denominator) meets the squares of the terms and overflows to infinity (issue 43 #11:
/// `--lambda 1e308` and `--delta 1e-320` made NaN before the first sweep).
pub const PARAMETER_RANGE: (f64, f64) = (1e-12, 1e12);

/// Checks that `value` is a number in [`PARAMETER_RANGE`].
pub(crate) fn positive(name: &'static str, value: f64) -> Result<()> {
    let (least, most) = PARAMETER_RANGE;
    if (least..=most).contains(&value) {
        Ok(())
    } else {
        Err(Error::invalid(
            name,
            value,
            format!("a number in [{least:e}, {most:e}] (the model computes in float32)"),
        ))
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
        // Finite but past what float32 energies hold (issue 43 #11).
        for (name, value) in [("lambda", 1e308), ("delta", 1e-320), ("xi2", 1e13)] {
            let mut bad = EnergyParams::rgb();
            match name {
                "lambda" => bad.lambda = value,
                "delta" => bad.delta = value,
                _ => bad.xi2 = value,
            }
            let msg = bad.validate().unwrap_err().to_string();
            assert!(msg.contains(name) && msg.contains("[1e-12, 1e12]"), "{msg}");
        }
    }
}
