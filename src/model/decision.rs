//! The float64 sums that decide a backtracking test or the safeguard (SPEC §6, "Floating
//! point") as custom Burn ops (Burn 0.22's `#[backend_extension]`).
//!
//! - flex: one pass over the float32 (or float64) buffer, read in place, products and sums
//!   in float64, split over the cores. Composed, the same sum was three passes: the product
//!   or square in float32, a float64 copy of it (twice the memory) and the sum.
//! - ndarray, wgpu: the trait's default bodies, the composed ops, products in float64 too
//!   (wgpu is never asked: it has no float64, and its decisions sum in float32,
//!   [`crate::model::grid::Accumulation`]).
//! - autodiff: not differentiable; the inputs are detached by the caller.
//!
//! The custom ops and the backends they have kernels for are listed in one place,
//! `docs/architecture.md` ("Custom ops"): they are the only numerical code that names backends.

#![allow(deprecated)] // `NdArray` is deprecated upstream in favour of flex; it stays served.

use burn::backend::tensor::FloatTensor;
use burn::backend::{Backend, Dispatch, backend_extension};
use burn::tensor::{FloatDType, Tensor};

/// The decision sums' primitives, each a `[1]` float64 tensor.
#[backend_extension(
    Flex: cfg(feature = "flex"),
    NdArray: cfg(feature = "ndarray"),
    Cube: cfg(feature = "wgpu"),
    Autodiff
)]
pub trait DecisionOps: Backend {
    /// `Σ a` over every entry.
    fn decision_sum(a: FloatTensor<Self>) -> FloatTensor<Self> {
        Self::float_sum(Self::float_cast(a, FloatDType::F64))
    }
    /// `Σ a·b` over every entry (shapes equal).
    fn decision_dot(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
        let (a, b) = (
            Self::float_cast(a, FloatDType::F64),
            Self::float_cast(b, FloatDType::F64),
        );
        Self::float_sum(Self::float_mul(a, b))
    }
    /// `Σ (a − b)²` over every entry (shapes equal): the difference in the tensors' own
    /// precision, as `a − b` would be, its square and the sum in float64.
    fn decision_distance2(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
        composed_distance2::<Self>(a, b)
    }
    /// `[Σ (a − b)², Σ (a − c)²]` (shapes equal): two [`decision_distance2`] from one
    /// tensor, each the same value bit for bit.
    ///
    /// [`decision_distance2`]: DecisionOps::decision_distance2
    fn decision_distance2_pair(
        a: FloatTensor<Self>,
        b: FloatTensor<Self>,
        c: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        Self::float_cat(
            vec![
                Self::decision_distance2(a.clone(), b),
                Self::decision_distance2(a, c),
            ],
            0,
        )
    }
}

/// [`DecisionOps::decision_distance2`] composed of primitives: what the backends without a
/// kernel of their own run (here and in fused ops' default bodies), `[1]` float64.
pub(crate) fn composed_distance2<B: Backend>(
    a: FloatTensor<B>,
    b: FloatTensor<B>,
) -> FloatTensor<B> {
    let d = B::float_cast(B::float_sub(a, b), FloatDType::F64);
    B::float_sum(B::float_mul(d.clone(), d))
}

#[cfg(feature = "ndarray")]
impl DecisionOps for burn::backend::NdArray {}

#[cfg(feature = "wgpu")]
impl DecisionOps for burn::backend::Cube {}

/// `Σ t` over every entry of `t`, accumulated in float64, `[1]`.
pub fn sum<const D: usize>(t: Tensor<D>) -> Tensor<1> {
    Tensor::<1>::from_dispatch(Dispatch::decision_sum(t.detach().into_dispatch()))
}

/// `Σ a·b` over every entry, the products and their sum in float64, `[1]`.
///
/// # Panics
///
/// If the shapes differ.
pub fn dot<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> Tensor<1> {
    assert_eq!(a.dims(), b.dims(), "decision dot: shapes differ");
    Tensor::<1>::from_dispatch(Dispatch::decision_dot(
        a.detach().into_dispatch(),
        b.detach().into_dispatch(),
    ))
}

/// `Σ (a − b)²`, `[1]`: [`sum_squares`] of `a − b` without the difference as a tensor (a
/// fresh frame per backtracking trial), the same value bit for bit.
///
/// # Panics
///
/// If the shapes differ.
pub fn distance2<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> Tensor<1> {
    assert_eq!(a.dims(), b.dims(), "decision distance: shapes differ");
    Tensor::<1>::from_dispatch(Dispatch::decision_distance2(
        a.detach().into_dispatch(),
        b.detach().into_dispatch(),
    ))
}

/// `[Σ (a − b)², Σ (a − c)²]`, `[2]`: [`distance2`] of `a` with `b` and with `c`, each the
/// same value bit for bit, `a` read once where the backend fuses the two (a backtracking
/// trial's warp against the previous frame and against the extrapolated point's warp).
///
/// # Panics
///
/// If the shapes differ.
pub fn distance2_pair<const D: usize>(a: Tensor<D>, b: Tensor<D>, c: Tensor<D>) -> Tensor<1> {
    assert!(
        a.dims() == b.dims() && a.dims() == c.dims(),
        "decision distances: shapes differ"
    );
    Tensor::<1>::from_dispatch(Dispatch::decision_distance2_pair(
        a.detach().into_dispatch(),
        b.detach().into_dispatch(),
        c.detach().into_dispatch(),
    ))
}

/// `Σ t²`, `[1]`: [`dot`] of `t` with itself.
pub fn sum_squares<const D: usize>(t: Tensor<D>) -> Tensor<1> {
    dot(t.clone(), t)
}

#[cfg(feature = "flex")]
pub(crate) mod flex {
    use burn::backend::Flex;
    use burn::backend::flex::FlexTensor;
    use burn::tensor::{DType, TensorData};
    use rayon::prelude::*;

    use super::DecisionOps;
    use crate::model::cpu::has_avx2;
    use crate::model::host_view::HostView;

    /// Values per task: a task's float64 partial sum then adds to the others in a fixed
    /// order, so the result does not depend on the thread count.
    pub(crate) const CHUNK: usize = 1 << 14;

    /// The float64 term a reduction adds per pair of values.
    #[derive(Clone, Copy, Debug, PartialEq, Eq)]
    pub(crate) enum Term {
        /// `a_i`.
        First,
        /// `a_i · b_i`.
        Product,
        /// `(a_i − b_i)²`, the difference in the values' own precision.
        SquaredDifference,
    }

    /// The element types the reductions read.
    pub(crate) trait Value: Copy + Sync + Into<f64> + std::ops::Sub<Output = Self> {
        /// `Σ term(a_i, b_i)` of one chunk in eight interleaved float64 lanes, summed as
        /// `((l0 + l1) + (l2 + l3)) + ((l4 + l5) + (l6 + l7))`, then the remainder in order.
        fn fold(a: &[Self], b: &[Self], term: Term) -> f64 {
            lanes(a, b, term)
        }
    }

    impl Value for f64 {}

    impl Value for f32 {
        /// In AVX2 where the CPU has it: eight differences in one vector, four float64 lanes
        /// per vector after the conversion. The baseline copy (SSE2) converted and summed
        /// two lanes at a time with shuffles between, and these sums were 7 % of a deep
        /// sweep's samples. The same operations per lane, so the same bits.
        fn fold(a: &[f32], b: &[f32], term: Term) -> f64 {
            #[cfg(target_arch = "x86_64")]
            if has_avx2() {
                // SAFETY: the CPU has AVX2, checked just now.
                return unsafe { avx2::fold(a, b, term) };
            }
            lanes(a, b, term)
        }
    }

    #[inline(always)]
    fn term_of<T: Value>(x: T, y: T, term: Term) -> f64 {
        match term {
            Term::First => x.into(),
            Term::Product => x.into() * y.into(),
            Term::SquaredDifference => {
                let d: f64 = (x - y).into();
                d * d
            }
        }
    }

    /// The eight lanes' sum and the remainder's terms, as [`Value::fold`] says.
    #[inline(always)]
    fn finish<T: Value>(lanes: [f64; 8], a_rest: &[T], b_rest: &[T], term: Term) -> f64 {
        let mut s = ((lanes[0] + lanes[1]) + (lanes[2] + lanes[3]))
            + ((lanes[4] + lanes[5]) + (lanes[6] + lanes[7]));
        for (&x, &y) in a_rest.iter().zip(b_rest) {
            s += term_of(x, y, term);
        }
        s
    }

    fn lanes<T: Value>(a: &[T], b: &[T], term: Term) -> f64 {
        let mut lanes = [0.0f64; 8];
        let (a8, b8) = (a.chunks_exact(8), b.chunks_exact(8));
        let (a_rest, b_rest) = (a8.remainder(), b8.remainder());
        for (x, y) in a8.zip(b8) {
            for j in 0..8 {
                lanes[j] += term_of(x[j], y[j], term);
            }
        }
        finish(lanes, a_rest, b_rest, term)
    }

    #[cfg(target_arch = "x86_64")]
    mod avx2 {
        use std::arch::x86_64::*;

        use super::{Term, finish};

        /// [`super::lanes`] for float32 in AVX2 intrinsics: lanes 0–3 and 4–7 are the two
        /// halves of each group of eight, converted to float64.
        ///
        /// # Safety
        ///
        /// The CPU has AVX2.
        #[target_feature(enable = "avx2")]
        pub(super) unsafe fn fold(a: &[f32], b: &[f32], term: Term) -> f64 {
            let (a8, b8) = (a.chunks_exact(8), b.chunks_exact(8));
            let (a_rest, b_rest) = (a8.remainder(), b8.remainder());
            let (mut lo, mut hi) = (_mm256_setzero_pd(), _mm256_setzero_pd());
            for (x, y) in a8.zip(b8) {
                // SAFETY: x and y hold eight values each.
                let (x, y) = unsafe { (_mm256_loadu_ps(x.as_ptr()), _mm256_loadu_ps(y.as_ptr())) };
                let halves = |v: __m256| {
                    (
                        _mm256_cvtps_pd(_mm256_castps256_ps128(v)),
                        _mm256_cvtps_pd(_mm256_extractf128_ps::<1>(v)),
                    )
                };
                let (t_lo, t_hi) = match term {
                    Term::First => halves(x),
                    Term::Product => {
                        let ((x_lo, x_hi), (y_lo, y_hi)) = (halves(x), halves(y));
                        (_mm256_mul_pd(x_lo, y_lo), _mm256_mul_pd(x_hi, y_hi))
                    }
                    Term::SquaredDifference => {
                        let (d_lo, d_hi) = halves(_mm256_sub_ps(x, y));
                        (_mm256_mul_pd(d_lo, d_lo), _mm256_mul_pd(d_hi, d_hi))
                    }
                };
                lo = _mm256_add_pd(lo, t_lo);
                hi = _mm256_add_pd(hi, t_hi);
            }
            let mut lanes = [0.0f64; 8];
            // SAFETY: lanes holds eight values.
            unsafe {
                _mm256_storeu_pd(lanes.as_mut_ptr(), lo);
                _mm256_storeu_pd(lanes.as_mut_ptr().add(4), hi);
            }
            finish(lanes, a_rest, b_rest, term)
        }
    }

    /// `Σ term(a_i, b_i)` in float64 over chunks of [`CHUNK`] values, split over the cores.
    pub(crate) fn reduce<T: Value>(a: &[T], b: &[T], term: Term) -> f64 {
        let partial: Vec<f64> = a
            .par_chunks(CHUNK)
            .zip(b.par_chunks(CHUNK))
            .map(|(a, b)| T::fold(a, b, term))
            .collect();
        partial.iter().sum()
    }

    /// [`reduce`] of `(a, b)` and of `(a, c)` with the same term, each chunk's two folds in
    /// one task (the chunk of `a` is still in cache for the second): the same chunks and
    /// lanes as two calls, so the same bits.
    pub(crate) fn reduce_pair<T: Value>(a: &[T], b: &[T], c: &[T], term: Term) -> [f64; 2] {
        let partial: Vec<(f64, f64)> = a
            .par_chunks(CHUNK)
            .zip(b.par_chunks(CHUNK))
            .zip(c.par_chunks(CHUNK))
            .map(|((a, b), c)| (T::fold(a, b, term), T::fold(a, c, term)))
            .collect();
        [
            partial.iter().map(|p| p.0).sum(),
            partial.iter().map(|p| p.1).sum(),
        ]
    }

    /// `$body` with `$T` the host type of `$dtype`'s values: decision sums read float32 or
    /// float64.
    macro_rules! by_dtype {
        ($dtype:expr, |$T:ident| $body:expr) => {
            match $dtype {
                DType::F32 => {
                    type $T = f32;
                    $body
                }
                DType::F64 => {
                    type $T = f64;
                    $body
                }
                other => panic!("decision sums read float32 or float64, not {other:?}"),
            }
        };
    }

    fn scalar(v: f64) -> FlexTensor {
        FlexTensor::from_data(TensorData::new(vec![v], [1]))
    }

    impl DecisionOps for Flex {
        fn decision_sum(a: FlexTensor) -> FlexTensor {
            let a = HostView::new(a);
            scalar(by_dtype!(a.dtype(), |T| reduce(
                a.values::<T>(),
                a.values::<T>(),
                Term::First
            )))
        }

        fn decision_dot(a: FlexTensor, b: FlexTensor) -> FlexTensor {
            let (a, b) = (HostView::new(a), HostView::new(b));
            assert_eq!(a.dtype(), b.dtype(), "decision dot: dtypes differ");
            scalar(by_dtype!(a.dtype(), |T| reduce(
                a.values::<T>(),
                b.values::<T>(),
                Term::Product
            )))
        }

        fn decision_distance2(a: FlexTensor, b: FlexTensor) -> FlexTensor {
            let (a, b) = (HostView::new(a), HostView::new(b));
            assert_eq!(a.dtype(), b.dtype(), "decision distance: dtypes differ");
            scalar(by_dtype!(a.dtype(), |T| reduce(
                a.values::<T>(),
                b.values::<T>(),
                Term::SquaredDifference
            )))
        }

        fn decision_distance2_pair(a: FlexTensor, b: FlexTensor, c: FlexTensor) -> FlexTensor {
            let (a, b, c) = (HostView::new(a), HostView::new(b), HostView::new(c));
            assert!(
                a.dtype() == b.dtype() && a.dtype() == c.dtype(),
                "decision distances: dtypes differ"
            );
            let pair = by_dtype!(a.dtype(), |T| reduce_pair(
                a.values::<T>(),
                b.values::<T>(),
                c.values::<T>(),
                Term::SquaredDifference
            ));
            FlexTensor::from_data(TensorData::new(pair.to_vec(), [2]))
        }
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        /// The AVX2 copy adds the same terms in the same lanes as the baseline one: the
        /// same bits, for every term, with a remainder after the groups of eight.
        #[test]
        fn the_vector_fold_is_the_scalar_one_bit_for_bit() {
            let a: Vec<f32> = (0..1003)
                .map(|i| ((i * 37) % 101) as f32 * 0.0131 - 0.6)
                .collect();
            let b: Vec<f32> = (0..1003)
                .map(|i| ((i * 11) % 89) as f32 * 0.0217 + 0.1)
                .collect();
            for term in [Term::First, Term::Product, Term::SquaredDifference] {
                let want = lanes(&a, &b, term);
                assert_eq!(
                    f32::fold(&a, &b, term).to_bits(),
                    want.to_bits(),
                    "{term:?}"
                );
                let exact: f64 = a.iter().zip(&b).map(|(&x, &y)| term_of(x, y, term)).sum();
                assert!((want - exact).abs() <= 1e-12 * exact.abs(), "{term:?}");
            }
        }

        /// The pair of distances is the two single ones bit for bit, over several chunks
        /// with a short last one.
        #[test]
        fn a_pair_of_distances_is_the_two_distances_bit_for_bit() {
            let len = 2 * CHUNK + 1003;
            let wave = |f: usize, m: usize, s: f32| -> Vec<f32> {
                (0..len).map(|i| ((i * f) % m) as f32 * s - 0.4).collect()
            };
            let (a, b, c) = (
                wave(37, 101, 0.0131),
                wave(11, 89, 0.0217),
                wave(7, 97, 0.019),
            );
            let pair = reduce_pair(&a, &b, &c, Term::SquaredDifference);
            let single = [
                reduce(&a, &b, Term::SquaredDifference),
                reduce(&a, &c, Term::SquaredDifference),
            ];
            assert_eq!(pair.map(f64::to_bits), single.map(f64::to_bits));
            assert_ne!(pair[0], pair[1]);
        }
    }
}

mod autodiff {
    use burn::backend::Autodiff;
    use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
    use burn::backend::tensor::FloatTensor;

    use super::DecisionOps;

    /// A decision sum's inputs are detached ([`super::sum`], [`super::dot`]): the op runs on
    /// the inner backend and its result is a constant.
    impl<B: DecisionOps, C: CheckpointStrategy> DecisionOps for Autodiff<B, C> {
        fn decision_sum(a: FloatTensor<Self>) -> FloatTensor<Self> {
            assert!(!a.is_tracked(), "a decision sum is not differentiable");
            let (a, _) = a.into_parts();
            FloatTensor::<Self>::new(B::decision_sum(a))
        }

        fn decision_dot(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
            assert!(
                !a.is_tracked() && !b.is_tracked(),
                "a decision sum is not differentiable"
            );
            let (a, _) = a.into_parts();
            let (b, _) = b.into_parts();
            FloatTensor::<Self>::new(B::decision_dot(a, b))
        }

        fn decision_distance2(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
            assert!(
                !a.is_tracked() && !b.is_tracked(),
                "a decision sum is not differentiable"
            );
            let (a, _) = a.into_parts();
            let (b, _) = b.into_parts();
            FloatTensor::<Self>::new(B::decision_distance2(a, b))
        }

        fn decision_distance2_pair(
            a: FloatTensor<Self>,
            b: FloatTensor<Self>,
            c: FloatTensor<Self>,
        ) -> FloatTensor<Self> {
            assert!(
                !a.is_tracked() && !b.is_tracked() && !c.is_tracked(),
                "a decision sum is not differentiable"
            );
            let (a, _) = a.into_parts();
            let (b, _) = b.into_parts();
            let (c, _) = c.into_parts();
            FloatTensor::<Self>::new(B::decision_distance2_pair(a, b, c))
        }
    }
}
