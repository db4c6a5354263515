//! `ln` and `exp` of eight float32 values at a time, evaluated in float64 by polynomials the
//! compiler vectorises, for the hyperelastic density's kernels (`W(J)` needs
//! `exp((log det J)²)` at every pixel, SPEC §2).
//!
//! libm's `logf` and `expf` are calls the compiler cannot vectorise: in a 256² RGB sweep
//! they and the scalar loop around them were a sixth of the samples. Here both are branch-free
//! float64 arithmetic on bit patterns (vector selects instead of branches), accurate to a few
//! float64 ulps, so rounding the result to float32 gives the correctly rounded `ln x` and
//! `eˣ` except where the exact value lies within about 1e-15 (relative) of a midpoint
//! between two float32 values: the same values as `(x as f64).ln() as f32`, and as libm's
//! float32 functions wherever those round correctly (glibc's claim: to 0.502 ulp).
//!
//! Special values follow IEEE 754 and libm: `ln 0 = −∞`, `ln` of a negative number or NaN
//! is NaN, `ln ∞ = ∞`; `exp` overflows to `∞` (for float32) and underflows to 0, and a NaN
//! stays NaN, which is what lets a non-finite deformation surface as a NaN energy.

/// `ln 2` split so that `n · LN2_HI` is exact for `|n| < 2¹¹` (Cody and Waite).
const LN2_HI: f64 = f64::from_bits(0x3FE6_2E42_FEE0_0000);
/// `ln 2 − LN2_HI`.
const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
/// `1.5 · 2⁵²`: adding it rounds a float64 of magnitude below `2⁵¹` to an integer, which
/// then sits in the low bits of the sum's bit pattern.
const ROUNDER: f64 = 6_755_399_441_055_744.0;
/// Past `|y| = 200`, `eʸ` is ∞ or 0 in float32; clamping keeps `2ⁿ` a normal float64.
const EXP_CLAMP: f64 = 200.0;

/// `2 atanh(s) / (2s) = Σ s²ᵏ / (2k + 1)` for `|s| ≤ 3 − 2√2 ≈ 0.1716`, up to `s¹⁸`: the
/// first term left out is below 1e-15 of the sum.
const ATANH_SERIES: [f64; 10] = [
    1.0,
    1.0 / 3.0,
    1.0 / 5.0,
    1.0 / 7.0,
    1.0 / 9.0,
    1.0 / 11.0,
    1.0 / 13.0,
    1.0 / 15.0,
    1.0 / 17.0,
    1.0 / 19.0,
];

/// `1/k!`, `k = 0 … 13`: the Taylor series of `eʳ` for `|r| ≤ ln 2 / 2`, whose first term
/// left out is below 3e-17.
const EXP_SERIES: [f64; 14] = [
    1.0,
    1.0,
    1.0 / 2.0,
    1.0 / 6.0,
    1.0 / 24.0,
    1.0 / 120.0,
    1.0 / 720.0,
    1.0 / 5_040.0,
    1.0 / 40_320.0,
    1.0 / 362_880.0,
    1.0 / 3_628_800.0,
    1.0 / 39_916_800.0,
    1.0 / 479_001_600.0,
    1.0 / 6_227_020_800.0,
];

/// `Σ coefficients[k] · xᵏ` by Horner's rule.
#[inline(always)]
fn horner<const N: usize>(x: f64, coefficients: &[f64; N]) -> f64 {
    coefficients.iter().rev().fold(0.0, |sum, &c| sum * x + c)
}

/// The integer `n` held by `t = v + ROUNDER` (`|n| < 2⁵¹`), as a bit-pattern difference:
/// AVX2 has no float64 → int64 conversion, but it has 64-bit integer subtraction.
#[inline(always)]
fn rounded_integer(t: f64) -> i64 {
    (t.to_bits() as i64).wrapping_sub(ROUNDER.to_bits() as i64)
}

/// `ln x` in float64 for a float64 `x` converted from a float32 (so normal when positive).
///
/// `x = 2ᵉ · m` with `m ∈ [√½, √2)`, `ln m = 2 atanh((m − 1)/(m + 1))`.
#[inline(always)]
fn ln_lane(x: f64) -> f64 {
    let bits = x.to_bits();
    let mantissa = f64::from_bits((bits & 0x000F_FFFF_FFFF_FFFF) | 0x3FF0_0000_0000_0000);
    let exponent = ((bits >> 52) & 0x7FF) as i64 - 1023;
    let high = mantissa > std::f64::consts::SQRT_2;
    let m = if high { mantissa * 0.5 } else { mantissa };
    let e = exponent + i64::from(high);
    // The exponent as a float64 by the same bit trick (|e| < 2¹¹).
    let e = f64::from_bits((ROUNDER.to_bits() as i64).wrapping_add(e) as u64) - ROUNDER;
    let s = (m - 1.0) / (m + 1.0);
    let ln_m = 2.0 * s * horner(s * s, &ATANH_SERIES);
    let value = e * LN2_HI + (e * LN2_LO + ln_m);
    if x > 0.0 && x < f64::INFINITY {
        value
    } else if x == 0.0 {
        f64::NEG_INFINITY
    } else if x == f64::INFINITY {
        x
    } else {
        f64::NAN
    }
}

/// `eʸ` in float64, `y` clamped to `±EXP_CLAMP` (a NaN stays NaN).
///
/// `y = n ln 2 + r` with `n` the nearest integer to `y / ln 2`, `eʸ = 2ⁿ eʳ`.
#[inline(always)]
fn exp_lane(y: f64) -> f64 {
    let y = if y > EXP_CLAMP { EXP_CLAMP } else { y };
    let y = if y < -EXP_CLAMP { -EXP_CLAMP } else { y };
    let t = y * std::f64::consts::LOG2_E + ROUNDER;
    let n = t - ROUNDER;
    let r = (y - n * LN2_HI) - n * LN2_LO;
    let scale = f64::from_bits(((rounded_integer(t) + 1023) as u64) << 52);
    horner(r, &EXP_SERIES) * scale
}

/// `ln` of eight float32 values (see the module's accuracy).
#[inline(always)]
pub(crate) fn ln8(x: [f32; 8]) -> [f32; 8] {
    x.map(|v| ln_lane(f64::from(v)) as f32)
}

/// `exp` of eight float32 values (see the module's accuracy).
#[inline(always)]
pub(crate) fn exp8(y: [f32; 8]) -> [f32; 8] {
    y.map(|v| exp_lane(f64::from(v)) as f32)
}

#[cfg(test)]
mod tests {
    use super::{exp8, ln8};

    /// Float32 values spread over every binade (a xorshift's bit patterns), plus the
    /// neighbourhood of 1 where `ln` is small and the edge cases.
    fn samples() -> Vec<f32> {
        let mut state = 0x9E37_79B9_7F4A_7C15_u64;
        let mut values: Vec<f32> = (0..400_000)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                f32::from_bits((state >> 32) as u32)
            })
            .collect();
        values.extend((0..20_000).map(|i| 1.0 + (i as f32 - 10_000.0) * 1e-6));
        values.extend([
            0.0,
            -0.0,
            1.0,
            -1.0,
            f32::MIN_POSITIVE,
            1e-45,
            f32::MAX,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            88.72,
            88.73,
            -103.0,
            -87.3,
            200.5,
            -200.5,
        ]);
        values.resize(values.len().next_multiple_of(8), 1.0);
        values
    }

    /// Whether `got` is `want` or both are NaN.
    fn same(got: f32, want: f32) -> bool {
        got == want || (got.is_nan() && want.is_nan())
    }

    /// Checks `f8` against the float64 reference rounded to float32: equal everywhere (a
    /// value within 1e-15 of a rounding midpoint would be the exception; none of these is).
    fn check(f8: fn([f32; 8]) -> [f32; 8], reference: fn(f64) -> f64, what: &str) {
        for chunk in samples().chunks_exact(8) {
            let x: [f32; 8] = chunk.try_into().unwrap();
            for (v, got) in x.into_iter().zip(f8(x)) {
                let want = reference(f64::from(v)) as f32;
                assert!(same(got, want), "{what}({v:e}) = {got:e}, want {want:e}");
            }
        }
    }

    #[test]
    fn ln_is_the_rounded_float64_logarithm() {
        check(ln8, f64::ln, "ln");
    }

    #[test]
    fn exp_is_the_rounded_float64_exponential() {
        check(exp8, f64::exp, "exp");
    }

    #[test]
    fn they_agree_with_libm_float32_to_an_ulp() {
        for chunk in samples().chunks_exact(8) {
            let x: [f32; 8] = chunk.try_into().unwrap();
            for ((v, l), e) in x.into_iter().zip(ln8(x)).zip(exp8(x)) {
                for (got, want) in [(l, v.ln()), (e, v.exp())] {
                    let ulps = (got.to_bits() as i64 - want.to_bits() as i64).abs();
                    assert!(same(got, want) || ulps <= 1, "{v:e}: {got:e} against libm {want:e}");
                }
            }
        }
    }
}
