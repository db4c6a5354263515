//! `ln` and `exp` of eight float32 values at a time, evaluated in float64 by polynomials the
//! compiler vectorises, for the hyperelastic density's kernels (`W(J)` needs
//! `exp((log det J)²)` at every pixel, SPEC §2).
//!
//! libm's `logf` and `expf` are calls the compiler cannot vectorise: in a 256² RGB sweep
//! they and the scalar loop around them were a fifth of the samples (the density 14 %, its
//! gradient 5 %). Here both are branch-free float64 arithmetic on bit patterns (vector
//! selects instead of branches), accurate to a few float64 ulps, so rounding the result to
//! float32 gives the correctly rounded `ln x` and `eˣ` except where the exact value lies
//! within about 1e-15 (relative) of a midpoint between two float32 values: the same values
//! as `(x as f64).ln() as f32`, and as libm's float32 functions wherever those round
//! correctly (glibc's claim: to 0.502 ulp).
//!
//! Special values follow IEEE 754 and libm: `ln 0 = −∞`, `ln` of a negative number or NaN
//! is NaN, `ln ∞ = ∞`; `exp` overflows to `∞` (for float32) and underflows to 0, and a NaN
//! stays NaN, which is what lets a non-finite deformation surface as a NaN energy.

#[cfg(target_arch = "x86_64")]
use super::has_avx2;

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

/// `Σ coefficients[k] · xᵏ` by Estrin's scheme: adjacent coefficients paired as
/// `c₂ᵢ + c₂ᵢ₊₁ x`, those paired with `x²`, then `x⁴`, …: a tree of depth `log₂ N` where
/// Horner's rule is a chain of `N` dependent multiply-adds (the density's kernel waited on
/// those chains). [`avx2`] pairs the same terms in the same order.
#[inline(always)]
fn estrin<const N: usize>(x: f64, coefficients: &[f64; N]) -> f64 {
    let mut terms = *coefficients;
    let (mut len, mut power) = (N, x);
    while len > 1 {
        for i in 0..len / 2 {
            terms[i] = terms[2 * i] + terms[2 * i + 1] * power;
        }
        if len % 2 == 1 {
            terms[len / 2] = terms[len - 1];
        }
        len = len.div_ceil(2);
        power = power * power;
    }
    terms[0]
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
    let ln_m = 2.0 * s * estrin(s * s, &ATANH_SERIES);
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
    estrin(r, &EXP_SERIES) * scale
}

/// `ln` of eight float32 values (see the module's accuracy).
#[inline(always)]
pub(crate) fn ln8(x: [f32; 8]) -> [f32; 8] {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the CPU has AVX2, checked just now.
        return unsafe { avx2::ln8(x) };
    }
    x.map(|v| ln_lane(f64::from(v)) as f32)
}

/// `exp` of eight float32 values (see the module's accuracy).
#[inline(always)]
pub(crate) fn exp8(y: [f32; 8]) -> [f32; 8] {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the CPU has AVX2, checked just now.
        return unsafe { avx2::exp8(y) };
    }
    y.map(|v| exp_lane(f64::from(v)) as f32)
}

/// [`ln_lane`] and [`exp_lane`] in AVX2 intrinsics, four float64 lanes per register: the
/// compiler kept the lane functions scalar (one `vdivsd` per lane). The same operations in
/// the same order, without fused multiply-adds, so both give the same values.
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use std::arch::x86_64::*;

    use super::{ATANH_SERIES, EXP_CLAMP, EXP_SERIES, LN2_HI, LN2_LO, ROUNDER};

    /// The eight values as two registers of four float64.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn widen(x: [f32; 8]) -> [__m256d; 2] {
        // SAFETY: `x` holds eight values.
        let v = unsafe { _mm256_loadu_ps(x.as_ptr()) };
        [
            _mm256_cvtps_pd(_mm256_castps256_ps128(v)),
            _mm256_cvtps_pd(_mm256_extractf128_ps::<1>(v)),
        ]
    }

    /// Two registers of four float64 rounded to eight float32 (to nearest, as `as f32`).
    #[inline]
    #[target_feature(enable = "avx2")]
    fn narrow([lo, hi]: [__m256d; 2]) -> [f32; 8] {
        let v = _mm256_set_m128(_mm256_cvtpd_ps(hi), _mm256_cvtpd_ps(lo));
        let mut out = [0.0f32; 8];
        // SAFETY: `out` holds eight values.
        unsafe { _mm256_storeu_ps(out.as_mut_ptr(), v) };
        out
    }

    /// [`super::estrin`], four lanes at a time.
    #[inline]
    #[target_feature(enable = "avx2")]
    fn estrin<const N: usize>(x: __m256d, coefficients: &[f64; N]) -> __m256d {
        let mut terms: [__m256d; N] = std::array::from_fn(|k| _mm256_set1_pd(coefficients[k]));
        let (mut len, mut power) = (N, x);
        while len > 1 {
            for i in 0..len / 2 {
                terms[i] = _mm256_add_pd(terms[2 * i], _mm256_mul_pd(terms[2 * i + 1], power));
            }
            if len % 2 == 1 {
                terms[len / 2] = terms[len - 1];
            }
            len = len.div_ceil(2);
            power = _mm256_mul_pd(power, power);
        }
        terms[0]
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn ln4(x: __m256d) -> __m256d {
        let one = _mm256_set1_pd(1.0);
        let bits = _mm256_castpd_si256(x);
        let mantissa = _mm256_castsi256_pd(_mm256_or_si256(
            _mm256_and_si256(bits, _mm256_set1_epi64x(0x000F_FFFF_FFFF_FFFF)),
            _mm256_set1_epi64x(0x3FF0_0000_0000_0000),
        ));
        let exponent = _mm256_sub_epi64(
            _mm256_and_si256(_mm256_srli_epi64::<52>(bits), _mm256_set1_epi64x(0x7FF)),
            _mm256_set1_epi64x(1023),
        );
        let high = _mm256_cmp_pd::<_CMP_GT_OQ>(mantissa, _mm256_set1_pd(std::f64::consts::SQRT_2));
        let m = _mm256_blendv_pd(mantissa, _mm256_mul_pd(mantissa, _mm256_set1_pd(0.5)), high);
        // `high` is all ones (−1 as an integer) where the mantissa was halved.
        let e = _mm256_sub_epi64(exponent, _mm256_castpd_si256(high));
        let rounder = _mm256_set1_pd(ROUNDER);
        let e = _mm256_sub_pd(
            _mm256_castsi256_pd(_mm256_add_epi64(_mm256_castpd_si256(rounder), e)),
            rounder,
        );
        let s = _mm256_div_pd(_mm256_sub_pd(m, one), _mm256_add_pd(m, one));
        let ln_m = _mm256_mul_pd(
            _mm256_mul_pd(_mm256_set1_pd(2.0), s),
            estrin(_mm256_mul_pd(s, s), &ATANH_SERIES),
        );
        let value = _mm256_add_pd(
            _mm256_mul_pd(e, _mm256_set1_pd(LN2_HI)),
            _mm256_add_pd(_mm256_mul_pd(e, _mm256_set1_pd(LN2_LO)), ln_m),
        );
        let (zero, infinity) = (_mm256_setzero_pd(), _mm256_set1_pd(f64::INFINITY));
        let finite_positive = _mm256_and_pd(
            _mm256_cmp_pd::<_CMP_GT_OQ>(x, zero),
            _mm256_cmp_pd::<_CMP_LT_OQ>(x, infinity),
        );
        let special = _mm256_blendv_pd(
            _mm256_blendv_pd(
                _mm256_set1_pd(f64::NAN),
                infinity,
                _mm256_cmp_pd::<_CMP_EQ_OQ>(x, infinity),
            ),
            _mm256_set1_pd(f64::NEG_INFINITY),
            _mm256_cmp_pd::<_CMP_EQ_OQ>(x, zero),
        );
        _mm256_blendv_pd(special, value, finite_positive)
    }

    #[inline]
    #[target_feature(enable = "avx2")]
    fn exp4(y: __m256d) -> __m256d {
        // `min(c, y)` is `c < y ? c : y`: a NaN `y` stays, as in the scalar clamp.
        let y = _mm256_min_pd(_mm256_set1_pd(EXP_CLAMP), y);
        let y = _mm256_max_pd(_mm256_set1_pd(-EXP_CLAMP), y);
        let rounder = _mm256_set1_pd(ROUNDER);
        let t = _mm256_add_pd(
            _mm256_mul_pd(y, _mm256_set1_pd(std::f64::consts::LOG2_E)),
            rounder,
        );
        let n = _mm256_sub_pd(t, rounder);
        let r = _mm256_sub_pd(
            _mm256_sub_pd(y, _mm256_mul_pd(n, _mm256_set1_pd(LN2_HI))),
            _mm256_mul_pd(n, _mm256_set1_pd(LN2_LO)),
        );
        let integer = _mm256_sub_epi64(_mm256_castpd_si256(t), _mm256_castpd_si256(rounder));
        let scale = _mm256_castsi256_pd(_mm256_slli_epi64::<52>(_mm256_add_epi64(
            integer,
            _mm256_set1_epi64x(1023),
        )));
        _mm256_mul_pd(estrin(r, &EXP_SERIES), scale)
    }

    /// [`super::ln8`] on a CPU with AVX2.
    ///
    /// # Safety
    ///
    /// The CPU has AVX2.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn ln8(x: [f32; 8]) -> [f32; 8] {
        let [lo, hi] = widen(x);
        narrow([ln4(lo), ln4(hi)])
    }

    /// [`super::exp8`] on a CPU with AVX2.
    ///
    /// # Safety
    ///
    /// The CPU has AVX2.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn exp8(y: [f32; 8]) -> [f32; 8] {
        let [lo, hi] = widen(y);
        narrow([exp4(lo), exp4(hi)])
    }
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
    fn the_vector_and_scalar_paths_agree_bit_for_bit() {
        use super::{exp_lane, ln_lane};
        for chunk in samples().chunks_exact(8) {
            let x: [f32; 8] = chunk.try_into().unwrap();
            for ((v, l), e) in x.into_iter().zip(ln8(x)).zip(exp8(x)) {
                let (sl, se) = (ln_lane(f64::from(v)) as f32, exp_lane(f64::from(v)) as f32);
                assert!(
                    same(l, sl) && same(e, se),
                    "{v:e}: ln {l:e} / {sl:e}, exp {e:e} / {se:e}"
                );
            }
        }
    }

    #[test]
    fn they_agree_with_libm_float32_to_an_ulp() {
        for chunk in samples().chunks_exact(8) {
            let x: [f32; 8] = chunk.try_into().unwrap();
            for ((v, l), e) in x.into_iter().zip(ln8(x)).zip(exp8(x)) {
                for (got, want) in [(l, v.ln()), (e, v.exp())] {
                    let ulps = (got.to_bits() as i64 - want.to_bits() as i64).abs();
                    assert!(
                        same(got, want) || ulps <= 1,
                        "{v:e}: {got:e} against libm {want:e}"
                    );
                }
            }
        }
    }
}
