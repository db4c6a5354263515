//! What the native CPU kernels of the custom ops share, and nothing else: the element
//! types they run in ([`Real`]), the AVX2 dispatch of their hot loops ([`has_avx2`],
//! [`simd_dispatch`]), a pointer that tasks writing disjoint indices share ([`Shared`]),
//! an elementwise map of two slices with one factor per segment split over the cores
//! ([`combine`]), frame-sized zeros written by every core ([`zeros`]), and vectorisable
//! `ln`/`exp` ([`elementary`]). The kernels themselves live beside their
//! ops (`warp/host`, `separable/host`, the `*_op.rs` files); they import from here, never
//! from each other.

use std::mem::MaybeUninit;
use std::ops::{Add, AddAssign, Div, Mul, Sub};

use rayon::prelude::*;

pub(crate) mod elementary;

/// [`Real::flush_tiny`]'s threshold for float32: `2⁻¹⁰⁰ ≈ 7.9e-31`, far above the subnormal
/// range (below `1.2e-38`) so that a flushed value times a spline weight (down to about
/// `1e-7` in practice) does not land there either, and 24 orders of magnitude or more below
/// the data (features of RMS 0.1, colours scaled by `η = 1e-6`): below the float32
/// rounding of any sum that holds a value of the data's size.
pub const FLUSH_BELOW_F32: f32 = 7.888_609e-31;

/// [`Real::flush_tiny`]'s threshold for float64: about `2⁻⁹⁰⁰`, likewise far above the float64
/// subnormals (below `2.2e-308`) and far below anything the data holds.
pub const FLUSH_BELOW_F64: f64 = 1.183_052_186_166_5e-271;

/// The element types the kernels run in.
pub trait Real:
    Copy
    + Default
    + Send
    + Sync
    + 'static
    + Add<Output = Self>
    + Sub<Output = Self>
    + Mul<Output = Self>
    + Div<Output = Self>
    + AddAssign
    + PartialOrd
{
    /// From float64 (rounded for float32).
    fn from_f64(v: f64) -> Self;
    /// To float64 (exact).
    fn to_f64(self) -> f64;
    /// Rounded towards zero to an integer where that is in `[0, 2³⁰]`, else 0 (NaN
    /// included): the floor of a clamped grid coordinate. Not `as i32`: its saturation and
    /// NaN rule kept the points' setup scalar (one conversion and two compares per lane),
    /// where a select and an unchecked conversion vectorise.
    fn truncate(self) -> i32;
    /// From an integer (exact for the grid's indices).
    fn from_i32(i: i32) -> Self;
    /// 0 where `|self|` is below [`FLUSH_BELOW_F32`] (float32) or [`FLUSH_BELOW_F64`]
    /// (float64), else `self` (NaN kept). The prefilter's recurrences decay by `2 − √3` a
    /// sample into a run of zeros (ReLU features have long ones) and reach subnormal
    /// numbers, which on Intel CPUs cost a microcode assist per operation: every later sum
    /// that reads them (the 16-neighbour sums of each warp) ran 18× slower per value, a
    /// 112² deep sweep 4.6× (docs/benchmarks.md, "Subnormal coefficients"). A vector
    /// compare and mask per value.
    fn flush_tiny(self) -> Self;
    /// `eˣ`.
    fn exp(self) -> Self;
    /// The natural logarithm.
    fn ln(self) -> Self;
    /// [`ln`](Self::ln) of eight values: libm's, one at a time, unless the type has a
    /// vectorisable one ([`super::elementary`] for float32).
    #[inline(always)]
    fn ln8(x: [Self; 8]) -> [Self; 8] {
        x.map(Self::ln)
    }
    /// [`exp`](Self::exp) of eight values, as [`ln8`](Self::ln8).
    #[inline(always)]
    fn exp8(x: [Self; 8]) -> [Self; 8] {
        x.map(Self::exp)
    }
    /// Writes the 8 × 8 block at `src` (rows `src_stride` values apart) transposed to `dst`
    /// (rows `dst_stride` apart): `dst[j·dst_stride + i] = src[i·src_stride + j]`.
    ///
    /// # Safety
    ///
    /// `src` and `dst` are valid for their 8 rows of 8 values and do not overlap.
    #[inline(always)]
    unsafe fn transpose8(src: *const Self, src_stride: usize, dst: *mut Self, dst_stride: usize) {
        // SAFETY: the caller's promise.
        unsafe { transpose8_scalar(src, src_stride, dst, dst_stride) }
    }
    /// [`transpose8`](Self::transpose8) of the 16 × 8 block at `src` (16 rows): each of
    /// the 8 destination rows gets 16 contiguous values. Where a type can, it writes them
    /// around the caches (float32 on AVX, when every destination row starts on a cache
    /// line): a kernel that scatters a tile into many planes a plane apart otherwise reads
    /// each destination line before writing it, and with more planes than cache ways it
    /// reads it twice, once per half. Call [`store_fence`](Self::store_fence) before
    /// another thread reads what it wrote.
    ///
    /// # Safety
    ///
    /// `src` is valid for 16 rows of 8 values, `dst` for 8 rows of 16, and they do not
    /// overlap.
    #[inline(always)]
    unsafe fn transpose16x8(
        src: *const Self,
        src_stride: usize,
        dst: *mut Self,
        dst_stride: usize,
    ) {
        // SAFETY: the caller's promise.
        unsafe { transpose16x8_by_halves(src, src_stride, dst, dst_stride) }
    }
    /// Orders the stores of [`transpose16x8`](Self::transpose16x8) before this thread's
    /// later ones (nothing where that wrote through the caches).
    #[inline(always)]
    fn store_fence() {}
}

/// The largest value [`Real::truncate`] converts (`2³⁰`, exact in both precisions).
const GRID_INDEX_MAX: f64 = (1u32 << 30) as f64;

/// [`Real::transpose16x8`] as two [`Real::transpose8`], through the caches.
///
/// # Safety
///
/// As [`Real::transpose16x8`].
#[inline(always)]
unsafe fn transpose16x8_by_halves<T: Real>(
    src: *const T,
    src_stride: usize,
    dst: *mut T,
    dst_stride: usize,
) {
    // SAFETY: the caller's promise, for each half.
    unsafe {
        T::transpose8(src, src_stride, dst, dst_stride);
        T::transpose8(src.add(8 * src_stride), src_stride, dst.add(8), dst_stride);
    }
}

/// [`Real::transpose8`] one value at a time.
///
/// # Safety
///
/// As [`Real::transpose8`].
#[inline(always)]
unsafe fn transpose8_scalar<T: Copy>(
    src: *const T,
    src_stride: usize,
    dst: *mut T,
    dst_stride: usize,
) {
    for i in 0..8 {
        for j in 0..8 {
            // SAFETY: the caller's promise.
            unsafe { *dst.add(j * dst_stride + i) = *src.add(i * src_stride + j) };
        }
    }
}

impl Real for f32 {
    fn from_f64(v: f64) -> Self {
        v as f32
    }
    fn to_f64(self) -> f64 {
        f64::from(self)
    }
    #[inline(always)]
    fn truncate(self) -> i32 {
        let q = if (0.0..=GRID_INDEX_MAX as f32).contains(&self) {
            self
        } else {
            0.0
        };
        // SAFETY: `q` is finite and in `[0, 2³⁰]`, so its truncation is an `i32`.
        unsafe { q.to_int_unchecked() }
    }
    fn from_i32(i: i32) -> Self {
        i as f32
    }
    #[inline(always)]
    fn flush_tiny(self) -> Self {
        if self.abs() < FLUSH_BELOW_F32 {
            0.0
        } else {
            self
        }
    }
    fn exp(self) -> Self {
        f32::exp(self)
    }
    fn ln(self) -> Self {
        f32::ln(self)
    }
    #[inline(always)]
    fn ln8(x: [Self; 8]) -> [Self; 8] {
        elementary::ln8(x)
    }
    #[inline(always)]
    fn exp8(x: [Self; 8]) -> [Self; 8] {
        elementary::exp8(x)
    }
    #[inline(always)]
    unsafe fn transpose8(src: *const Self, src_stride: usize, dst: *mut Self, dst_stride: usize) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            // SAFETY: the CPU has AVX2; the pointers are the caller's promise.
            return unsafe { transpose8_avx(src, src_stride, dst, dst_stride) };
        }
        // SAFETY: the caller's promise.
        unsafe { transpose8_scalar(src, src_stride, dst, dst_stride) }
    }
    #[inline(always)]
    unsafe fn transpose16x8(
        src: *const Self,
        src_stride: usize,
        dst: *mut Self,
        dst_stride: usize,
    ) {
        #[cfg(target_arch = "x86_64")]
        if has_avx2() && (dst as usize).is_multiple_of(64) && dst_stride.is_multiple_of(16) {
            // SAFETY: the CPU has AVX2; every destination row starts on a 64-byte line; the
            // pointers are the caller's promise.
            return unsafe { transpose16x8_stream_avx(src, src_stride, dst, dst_stride) };
        }
        // SAFETY: the caller's promise.
        unsafe { transpose16x8_by_halves(src, src_stride, dst, dst_stride) }
    }
    #[inline(always)]
    fn store_fence() {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `sfence` is SSE, which every x86_64 CPU has.
        unsafe {
            std::arch::x86_64::_mm_sfence()
        };
    }
}

/// [`Real::transpose8`] of float32 in eight registers ([`transposed8_avx`]).
///
/// # Safety
///
/// The CPU has AVX; the pointers as [`Real::transpose8`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn transpose8_avx(src: *const f32, src_stride: usize, dst: *mut f32, dst_stride: usize) {
    use std::arch::x86_64::*;
    // SAFETY: the caller's promise: 8 rows of 8 at `src`.
    let rows = unsafe { transposed8_avx(src, src_stride) };
    for (j, row) in rows.into_iter().enumerate() {
        // SAFETY: the caller's promise: 8 rows of 8 at `dst`; unaligned stores.
        unsafe { _mm256_storeu_ps(dst.add(j * dst_stride), row) };
    }
}

/// The 8 × 8 block at `src` transposed, row `j` of the result holding column `j`, in
/// registers: interleave pairs of rows, then pairs of pairs, then swap 128-bit halves (the
/// compiler made the generic loop 64 scalar moves).
///
/// # Safety
///
/// The CPU has AVX; `src` is valid for 8 rows of 8 values.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn transposed8_avx(src: *const f32, src_stride: usize) -> [std::arch::x86_64::__m256; 8] {
    use std::arch::x86_64::*;
    let r: [__m256; 8] = std::array::from_fn(|i| {
        // SAFETY: the caller's promise: 8 rows of 8 at `src`; unaligned loads.
        unsafe { _mm256_loadu_ps(src.add(i * src_stride)) }
    });
    let t = [
        _mm256_unpacklo_ps(r[0], r[1]),
        _mm256_unpackhi_ps(r[0], r[1]),
        _mm256_unpacklo_ps(r[2], r[3]),
        _mm256_unpackhi_ps(r[2], r[3]),
        _mm256_unpacklo_ps(r[4], r[5]),
        _mm256_unpackhi_ps(r[4], r[5]),
        _mm256_unpacklo_ps(r[6], r[7]),
        _mm256_unpackhi_ps(r[6], r[7]),
    ];
    let u = [
        _mm256_shuffle_ps::<0x44>(t[0], t[2]),
        _mm256_shuffle_ps::<0xEE>(t[0], t[2]),
        _mm256_shuffle_ps::<0x44>(t[1], t[3]),
        _mm256_shuffle_ps::<0xEE>(t[1], t[3]),
        _mm256_shuffle_ps::<0x44>(t[4], t[6]),
        _mm256_shuffle_ps::<0xEE>(t[4], t[6]),
        _mm256_shuffle_ps::<0x44>(t[5], t[7]),
        _mm256_shuffle_ps::<0xEE>(t[5], t[7]),
    ];
    std::array::from_fn(|j| {
        if j < 4 {
            _mm256_permute2f128_ps::<0x20>(u[j], u[j + 4])
        } else {
            _mm256_permute2f128_ps::<0x31>(u[j - 4], u[j])
        }
    })
}

/// [`Real::transpose16x8`] of float32 with streaming stores: each destination row's 16
/// values are one whole 64-byte line, written in two back-to-back stores that the CPU
/// combines into one line write, with no read of the line first.
///
/// # Safety
///
/// The CPU has AVX; `dst` and every row `dst_stride` apart start on a 64-byte boundary;
/// the pointers as [`Real::transpose16x8`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn transpose16x8_stream_avx(
    src: *const f32,
    src_stride: usize,
    dst: *mut f32,
    dst_stride: usize,
) {
    use std::arch::x86_64::*;
    // SAFETY: the caller's promise: 16 rows of 8 at `src`.
    let (low, high) = unsafe {
        (
            transposed8_avx(src, src_stride),
            transposed8_avx(src.add(8 * src_stride), src_stride),
        )
    };
    for j in 0..8 {
        // SAFETY: the caller's promise: row j's 16 values at a 64-byte boundary.
        unsafe {
            let row = dst.add(j * dst_stride);
            _mm256_stream_ps(row, low[j]);
            _mm256_stream_ps(row.add(8), high[j]);
        }
    }
}

impl Real for f64 {
    fn from_f64(v: f64) -> Self {
        v
    }
    fn to_f64(self) -> f64 {
        self
    }
    #[inline(always)]
    fn truncate(self) -> i32 {
        let q = if (0.0..=GRID_INDEX_MAX).contains(&self) {
            self
        } else {
            0.0
        };
        // SAFETY: `q` is finite and in `[0, 2³⁰]`, so its truncation is an `i32`.
        unsafe { q.to_int_unchecked() }
    }
    fn from_i32(i: i32) -> Self {
        f64::from(i)
    }
    #[inline(always)]
    fn flush_tiny(self) -> Self {
        if self.abs() < FLUSH_BELOW_F64 {
            0.0
        } else {
            self
        }
    }
    fn exp(self) -> Self {
        f64::exp(self)
    }
    fn ln(self) -> Self {
        f64::ln(self)
    }
}

/// Whether the CPU has AVX2: the crate is built for baseline x86-64 (SSE2), so the hot loops
/// also exist compiled for AVX2 ([`simd_dispatch`]) and run that copy where the CPU has it:
/// twice the lanes for the same source.
#[inline]
pub(crate) fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// `fn $name<T: Bound>(args)` (any bound that implies [`Real`]; more type parameters, such
/// as a closure's, may follow) calling the `#[inline(always)]` function `$body` with the same
/// arguments, compiled for AVX2 where the CPU has it ([`has_avx2`]) and for the baseline
/// otherwise. Both copies are the same source, so they compute the same values (no fused
/// multiply-adds are introduced: Rust does not contract `a * b + c`).
macro_rules! simd_dispatch {
    ($(#[$doc:meta])* $vis:vis fn $name:ident<$($t:ident: $bound:path),+>($($arg:ident: $ty:ty),* $(,)?) => $body:ident) => {
        $(#[$doc])*
        $vis fn $name<$($t: $bound),+>($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                fn wide<$($t: $bound),+>($($arg: $ty),*) {
                    $body($($arg),*)
                }
                if $crate::model::cpu::has_avx2() {
                    // SAFETY: the CPU has AVX2, checked just now.
                    return unsafe { wide($($arg),*) };
                }
            }
            $body($($arg),*)
        }
    };
    // The same for an `unsafe fn` body: the copy has the body's safety contract.
    ($(#[$doc:meta])* $vis:vis unsafe fn $name:ident<$t:ident: $bound:path>($($arg:ident: $ty:ty),* $(,)?) => $body:ident) => {
        $(#[$doc])*
        $vis unsafe fn $name<$t: $bound>($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                unsafe fn wide<$t: $bound>($($arg: $ty),*) {
                    // SAFETY: the caller's promise, passed on.
                    unsafe { $body($($arg),*) }
                }
                if $crate::model::cpu::has_avx2() {
                    // SAFETY: the CPU has AVX2, checked just now; the rest is the caller's
                    // promise.
                    return unsafe { wide($($arg),*) };
                }
            }
            // SAFETY: the caller's promise, passed on.
            unsafe { $body($($arg),*) }
        }
    };
}
pub(crate) use simd_dispatch;

/// `out_i = f(a_i, b_i, s_m)` for the values `i` of segment `m` (`a`, `b` and `out` hold
/// `s.len()` segments of equal length: items, or planes), written in chunks split over the
/// cores.
#[cfg(any(feature = "flex", test))]
pub(crate) fn combine<T: Copy + Send + Sync>(
    a: &[T],
    b: &[T],
    s: &[T],
    f: impl Fn(T, T, T) -> T + Sync,
) -> Vec<T> {
    /// Values per task.
    const CHUNK: usize = 1 << 14;
    let per_segment = segment_length(a, b, s);
    // Written chunk by chunk on the pool without zeroing first (a zeroed frame was a serial
    // memset on the solver's thread).
    let mut out = Vec::<T>::with_capacity(a.len());
    let spare = &mut out.spare_capacity_mut()[..a.len()];
    spare
        .par_chunks_mut(CHUNK)
        .zip(a.par_chunks(CHUNK).zip(b.par_chunks(CHUNK)))
        .enumerate()
        .for_each(|(chunk, (out, (a, b)))| {
            combine_span_simd(out, a, b, chunk * CHUNK, per_segment, s, &f);
        });
    // SAFETY: every one of the `a.len()` values was written above.
    unsafe { out.set_len(a.len()) };
    out
}

/// The values per factor of [`combine`]'s segments.
#[cfg(any(feature = "flex", test))]
fn segment_length<T>(a: &[T], b: &[T], s: &[T]) -> usize {
    assert_eq!(a.len(), b.len(), "update: lengths differ");
    let per_segment = a.len() / s.len().max(1);
    assert_eq!(
        per_segment * s.len(),
        a.len(),
        "update: {} factors",
        s.len()
    );
    per_segment
}

simd_dispatch!(
    /// [`combine_span`] compiled for AVX2 where the CPU has it: the gradient steps and
    /// extrapolations of a feature step were baseline (SSE2) loops of four lanes, 9 % of a
    /// deep sweep's samples at 256².
    #[cfg(any(feature = "flex", test))]
    fn combine_span_simd<T: Copy, F: Fn(T, T, T) -> T>(
        out: &mut [MaybeUninit<T>], a: &[T], b: &[T], first: usize, per_segment: usize, s: &[T],
        f: &F
    ) => combine_span
);

/// [`combine`] of one span of values starting at value `first` of the whole: the span's runs
/// of one segment each, so the inner loop vectorises.
#[cfg(any(feature = "flex", test))]
#[inline(always)]
fn combine_span<T: Copy>(
    out: &mut [MaybeUninit<T>],
    a: &[T],
    b: &[T],
    first: usize,
    per_segment: usize,
    s: &[T],
    f: &impl Fn(T, T, T) -> T,
) {
    let mut from = 0;
    while from < out.len() {
        let segment = (first + from) / per_segment;
        let to = ((segment + 1) * per_segment - first).min(out.len());
        let factor = s[segment];
        for ((o, &x), &y) in out[from..to].iter_mut().zip(&a[from..to]).zip(&b[from..to]) {
            o.write(f(x, y, factor));
        }
        from = to;
    }
}

/// [`combine`], and `Σ (r_i − out_i)²` over each of the consecutive `regions` (lengths
/// covering every value: an item's channel block each) summed as the decision sums sum it
/// ([`crate::model::decision::flex::reduce`] of the region's `r` and `out`: the same chunks
/// from the region's start, the same lanes, the same bits). Each chunk is folded right after
/// it is written, while it is in cache: the frame is not read back (a feature trial's
/// gradient step and its distance to the next frame's warp, one pass instead of two).
#[cfg(feature = "flex")]
pub(crate) fn combine_distance2<T: crate::model::decision::flex::Value + Send>(
    a: &[T],
    b: &[T],
    s: &[T],
    r: &[T],
    regions: &[usize],
    f: impl Fn(T, T, T) -> T + Sync,
) -> (Vec<T>, Vec<f64>) {
    use crate::model::decision::flex::{CHUNK, Term};
    let per_segment = segment_length(a, b, s);
    assert_eq!(r.len(), a.len(), "update: lengths differ");
    assert_eq!(
        regions.iter().sum::<usize>(),
        a.len(),
        "update: regions {regions:?} do not cover {} values",
        a.len()
    );
    // (region, first value, length) of every task: the region's chunks from its start.
    let mut tasks = Vec::new();
    let mut start = 0;
    for (region, &len) in regions.iter().enumerate() {
        tasks.extend(
            (0..len)
                .step_by(CHUNK)
                .map(|at| (region, start + at, CHUNK.min(len - at))),
        );
        start += len;
    }
    let mut out = Vec::<T>::with_capacity(a.len());
    let mut spare = &mut out.spare_capacity_mut()[..a.len()];
    let mut spans = Vec::with_capacity(tasks.len());
    for &(_, _, len) in &tasks {
        let (span, rest) = spare.split_at_mut(len);
        spans.push(span);
        spare = rest;
    }
    let partial: Vec<f64> = tasks
        .par_iter()
        .zip(spans)
        .map(|(&(_, first, len), span)| {
            let at = first..first + len;
            combine_span_simd(
                span,
                &a[at.clone()],
                &b[at.clone()],
                first,
                per_segment,
                s,
                &f,
            );
            // SAFETY: combine_span wrote every value of the span just now.
            let written = unsafe { &*(std::ptr::from_mut(span) as *const [T]) };
            T::fold(&r[at], written, Term::SquaredDifference)
        })
        .collect();
    // SAFETY: the spans cover the `a.len()` values, every one written above.
    unsafe { out.set_len(a.len()) };
    // Each region's chunk sums in order, as `reduce` adds them.
    let mut parts: Vec<Vec<f64>> = vec![Vec::new(); regions.len()];
    for (&(region, _, _), p) in tasks.iter().zip(partial) {
        parts[region].push(p);
    }
    (out, parts.iter().map(|p| p.iter().sum()).collect())
}

/// A raw pointer that tasks writing disjoint indices of one buffer may share.
#[derive(Clone, Copy)]
pub(crate) struct Shared<T>(pub(crate) *mut T);
// SAFETY: every user writes only indices no other task touches (stated at each use).
unsafe impl<T: Send> Send for Shared<T> {}
// SAFETY: as for `Send`: shared use is writes to disjoint indices only.
unsafe impl<T: Send> Sync for Shared<T> {}

impl<T> Shared<T> {
    /// # Safety
    ///
    /// `i` is in bounds and no other thread reads or writes it meanwhile.
    pub(crate) unsafe fn write(self, i: usize, v: T) {
        // SAFETY: the caller's promise: `i` in bounds and this thread's alone.
        unsafe { self.0.add(i).write(v) }
    }

    /// # Safety
    ///
    /// As [`write`](Self::write).
    pub(crate) unsafe fn get(self, i: usize) -> *mut T {
        // SAFETY: the caller's promise: `i` in bounds.
        unsafe { self.0.add(i) }
    }
}

/// Values per task of [`zeros`]: 256 KiB of float32, a few pages each.
const ZEROS_PER_TASK: usize = 1 << 16;

/// `len` zeros, written by the cores side by side: a kernel's output or accumulator.
/// `vec![0; len]` of a frame zeroed it on the calling thread alone (the allocator's
/// `memset` and the page faults of fresh memory), while the other core waited for the
/// kernel: 4.5 % of an RGB 512² sweep's samples, all on one thread.
pub(crate) fn zeros<T: Copy + Default + Send + Sync>(len: usize) -> Vec<T> {
    let mut values = Vec::with_capacity(len);
    values.spare_capacity_mut()[..len]
        .par_chunks_mut(ZEROS_PER_TASK)
        .for_each(|chunk| chunk.fill(MaybeUninit::new(T::default())));
    // SAFETY: the first `len` values were written just now.
    unsafe { values.set_len(len) };
    values
}

/// Pixels per task: large enough that a task outweighs rayon's overhead, small enough that
/// both cores (or sixteen) get an even share at 64².
pub(crate) const PIXELS_PER_TASK: usize = 1024;

/// Values (pixels × channels) per task of the kernels that run over pixels with the channels
/// inner: what a task of [`PIXELS_PER_TASK`] pixels holds at the finest deep level's 67
/// channels.
const VALUES_PER_TASK: usize = PIXELS_PER_TASK * 67;

/// Pixels per task of a kernel over pixels with `c` channels inner: about
/// [`VALUES_PER_TASK`] values, at most [`PIXELS_PER_TASK`] pixels, a multiple of 64 (whole
/// tiles and transpose blocks). With [`PIXELS_PER_TASK`] pixels whatever the channels, a
/// 32² image of 515 channels (a deep morph's second level: 8 M multiply-adds an evaluation)
/// was one task, and that level's evaluations and transposes ran on one core.
pub(crate) fn pixels_per_task(c: usize) -> usize {
    (VALUES_PER_TASK / c.max(1)).clamp(64, PIXELS_PER_TASK) / 64 * 64
}

/// One image's `C` planes of `plane` values, channels-last, into `out` (same length):
/// `out[p·C + c] = planar[c·plane + p]`. Also the transpose of a `c × plane` matrix
/// (the separable operators' transposes of whole planes).
pub(crate) fn channels_last_into<T: Real>(planar: &[T], c: usize, plane: usize, out: &mut [T]) {
    assert!(
        planar.len() == c * plane && out.len() == planar.len(),
        "channels-last: {} values for {c} planes of {plane}, into {}",
        planar.len(),
        out.len()
    );
    let target = Shared(out.as_mut_ptr());
    let per_task = pixels_per_task(c);
    (0..plane.div_ceil(per_task))
        .into_par_iter()
        .for_each(|chunk| {
            let pixels = chunk * per_task..((chunk + 1) * per_task).min(plane);
            // SAFETY: the chunk's pixels' rows of `out` are this task's alone.
            unsafe { transpose_pixels_simd(planar, c, plane, target, pixels) };
        });
}

/// Writes `out[i·c + ch] = planar[ch·plane + i]` for the pixels `i` of `pixels`: blocks of
/// 8 pixels × 8 channels through [`Real::transpose8`] (one value at a time, the stores a
/// stride of `c` apart made the separable operators' transposes a tenth of an RGB sweep),
/// the edges one value at a time.
///
/// # Safety
///
/// `out` is valid for `plane · c` values, and the rows of `pixels` are the caller's alone.
#[inline(always)]
pub(crate) unsafe fn transpose_pixels<T: Real>(
    planar: &[T],
    c: usize,
    plane: usize,
    out: Shared<T>,
    pixels: std::ops::Range<usize>,
) {
    const B: usize = 8;
    let whole_pixels = pixels.start + (pixels.len() - pixels.len() % B);
    let whole_channels = c - c % B;
    for i0 in (pixels.start..whole_pixels).step_by(B) {
        for ch0 in (0..whole_channels).step_by(B) {
            let src = &planar[ch0 * plane + i0..(ch0 + B - 1) * plane + i0 + B];
            // SAFETY: `src` holds the 8 rows of 8 from its start, `plane` apart; the 8 rows of
            // 8 at `out[i0·c + ch0]`, `c` apart, are in `out` and the caller's alone.
            unsafe { T::transpose8(src.as_ptr(), plane, out.get(i0 * c + ch0), c) };
        }
        for ch in whole_channels..c {
            for i in i0..i0 + B {
                // SAFETY: as above.
                unsafe { out.write(i * c + ch, planar[ch * plane + i]) };
            }
        }
    }
    for i in whole_pixels..pixels.end {
        for ch in 0..c {
            // SAFETY: as above.
            unsafe { out.write(i * c + ch, planar[ch * plane + i]) };
        }
    }
}

simd_dispatch!(
    /// [`transpose_pixels`], compiled for AVX2 where the CPU has it.
    ///
    /// # Safety
    ///
    /// As [`transpose_pixels`].
    unsafe fn transpose_pixels_simd<T: Real>(
        planar: &[T], c: usize, plane: usize, out: Shared<T>, pixels: std::ops::Range<usize>
    ) => transpose_pixels
);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_value_takes_its_segments_factor() {
        // Items longer than a chunk and not a multiple of it, so chunks straddle items.
        let per_item = (1 << 14) + 7;
        let a: Vec<f32> = (0..3 * per_item).map(|i| (i % 13) as f32 * 0.5).collect();
        let b: Vec<f32> = (0..3 * per_item).map(|i| (i % 7) as f32 * 0.25).collect();
        let s = [2.0f32, -0.5, 3.0];
        let out = combine(&a, &b, &s, |x, y, s| x - y * s);
        assert_eq!(out.len(), a.len());
        for (i, &v) in out.iter().enumerate() {
            assert_eq!(v, a[i] - b[i] * s[i / per_item], "value {i}");
        }
    }

    /// The fused update's frame is [`combine`]'s and its sums the decision sums of each
    /// region, bit for bit: regions shorter than a chunk, longer and not a multiple of it,
    /// segments that straddle regions.
    #[cfg(feature = "flex")]
    #[test]
    fn a_fused_update_folds_each_region_as_the_decision_sums_do() {
        use crate::model::decision::flex::{Term, reduce};
        let regions = [3 * 1000, 20000, 40000, 257];
        let len: usize = regions.iter().sum();
        let a: Vec<f32> = (0..len).map(|i| (i % 13) as f32 * 0.5 - 1.0).collect();
        let b: Vec<f32> = (0..len).map(|i| (i % 7) as f32 * 0.25).collect();
        let r: Vec<f32> = (0..len).map(|i| (i % 11) as f32 * 0.3 - 0.7).collect();
        // 61 segments of 1037 values: not aligned with the regions or the chunks.
        let s: Vec<f32> = (0..61).map(|m| 0.1 + m as f32 * 0.05).collect();
        let f = |x: f32, y: f32, s: f32| x - y * s;
        let (out, sums) = combine_distance2(&a, &b, &s, &r, &regions, f);
        let want = combine(&a, &b, &s, f);
        assert_eq!(out, want);
        let mut start = 0;
        for (j, &len) in regions.iter().enumerate() {
            let at = start..start + len;
            let single = reduce(&r[at.clone()], &want[at], Term::SquaredDifference);
            assert_eq!(sums[j].to_bits(), single.to_bits(), "region {j}");
            start += len;
        }
    }

    /// `transpose16x8` into each offset of a 64-byte-aligned buffer (the streaming path at
    /// offset 0 when the row stride is a multiple of 16, the cached path elsewhere), for both
    /// precisions: every value lands where the transposition puts it, and nothing else is
    /// written.
    fn transposes_sixteen_rows_of_eight<T: Real + PartialEq + std::fmt::Debug>() {
        let src_stride = 11;
        let src: Vec<T> = (0..16 * src_stride)
            .map(|i| T::from_f64(i as f64 + 0.5))
            .collect();
        for dst_stride in [16, 32, 40, 21] {
            for offset in [0, 1, 8, 16] {
                let len = offset + 8 * dst_stride;
                let mut buffer = vec![T::from_f64(-1.0); len + 64];
                // The first value on a 64-byte boundary (a line holds 16 float32, 8 float64).
                let line = buffer.as_ptr().align_offset(64);
                let dst = &mut buffer[line..line + len];
                // SAFETY: 16 rows of 8 from src, 8 rows of 16 from dst[offset..].
                unsafe {
                    T::transpose16x8(
                        src.as_ptr(),
                        src_stride,
                        dst[offset..].as_mut_ptr(),
                        dst_stride,
                    )
                };
                T::store_fence();
                for (at, &v) in dst.iter().enumerate() {
                    let (j, i) = (
                        (at - offset.min(at)) / dst_stride,
                        (at - offset.min(at)) % dst_stride,
                    );
                    let want = if at >= offset && j < 8 && i < 16 {
                        src[i * src_stride + j]
                    } else {
                        T::from_f64(-1.0)
                    };
                    assert_eq!(v, want, "stride {dst_stride}, offset {offset}, value {at}");
                }
            }
        }
    }

    #[test]
    fn transposes_sixteen_rows_of_eight_in_either_precision() {
        transposes_sixteen_rows_of_eight::<f32>();
        transposes_sixteen_rows_of_eight::<f64>();
    }

    /// Every value is a zero, across tasks and a short last one; none at all works too. Each
    /// length first frees a buffer of NaNs as long, which the allocator may hand back.
    #[test]
    fn zeros_are_zeros_of_the_length_asked() {
        for len in [0, 1, ZEROS_PER_TASK - 1, 3 * ZEROS_PER_TASK + 17] {
            drop(std::hint::black_box(vec![f32::NAN; len]));
            let v = zeros::<f32>(len);
            assert_eq!(v.len(), len);
            assert!(v.iter().all(|&x| x.to_bits() == 0), "{len}");
        }
        assert!(zeros::<f64>(1000).iter().all(|&x| x.to_bits() == 0));
    }
}
