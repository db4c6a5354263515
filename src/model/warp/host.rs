//! The cubic B-spline prefilter and warp of SPEC §1 as plain loops over host slices: the
//! native CPU kernels behind the fused warp op ([`super::op`]), threaded with rayon over
//! pixels (channels inner) and over lines.
//!
//! Every function here is a linear map or the derivative of one, written with its adjoint:
//!
//! - [`prefilter`]: `c = P f` per channel (or `Pᵀ g`), the exact interpolating prefilter
//!   with whole-sample mirror boundary, as a tridiagonal solve along each axis: O(n) per line
//!   instead of a dense `n × n` matmul.
//! - [`sample`]: `T = B(φ) c`, the 4 × 4 B-spline evaluation at clamped points.
//! - [`sample_adjoint`]: `B(φ)ᵀ g`, a scatter-add (the gradient w.r.t. the coefficients).
//! - [`sample_position_grad`]: `Σ_c g_c ∂T_c/∂p` (the gradient w.r.t. `φ`), zero along an
//!   axis where the point lies outside the clamp range.
//!
//! Layouts are row-major and contiguous: coefficients `[N, C, H, W]`, deformations
//! `[N, 2, H', W']`, warped maps `[N, C, H', W']`. Many channels ([`reads_channels_last`])
//! are read channels-last; [`prefilter_channels_last`] writes coefficients so, and
//! [`sample_from_table`] / [`position_grad_from_table`] read such a table in place, a block
//! of its channels too ([`Layout`]), where the planar entry points transpose per call. Three
//! or four channels are evaluated and scattered through per-call quad tables ([`quad`]).

use std::borrow::Cow;
use std::mem::MaybeUninit;
use std::ops::{Add, AddAssign, Div, Mul, Sub};

use rayon::prelude::*;

pub mod quad;

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
    /// `eˣ`.
    fn exp(self) -> Self;
    /// The natural logarithm.
    fn ln(self) -> Self;
    /// [`ln`](Self::ln) of eight values: libm's, one at a time, unless the type has a
    /// vectorisable one ([`crate::model::elementary`] for float32).
    #[inline(always)]
    fn ln8(x: [Self; 8]) -> [Self; 8] {
        x.map(Self::ln)
    }
    /// [`exp`](Self::exp) of eight values, as [`ln8`](Self::ln8).
    #[inline(always)]
    fn exp8(x: [Self; 8]) -> [Self; 8] {
        x.map(Self::exp)
    }
    /// The stencils of the first `n` points of a block over a quad table ([`quad`]), where a
    /// type has a faster kernel for them: written to `block[l]` for the lanes of the mask it
    /// returns (none by default; float32 on AVX2 does those whose columns are contiguous).
    #[inline(always)]
    fn quad_block(
        table: &[Self],
        w: usize,
        rows: quad::BlockAxis<'_, Self>,
        cols: quad::BlockAxis<'_, Self>,
        n: usize,
        block: &mut [[Self; 4]; LANES],
    ) -> u32 {
        let _ = (table, w, rows, cols, n, block);
        0
    }
    /// Adds the values of the lanes `lanes` of a block into a quad table (the adjoint of
    /// [`quad_block`](Self::quad_block)), in lane order, as far as the type has a faster
    /// kernel for them; returns the first lane not done (by default `lanes.start`: none;
    /// float32 on AVX2 stops at the first lane whose columns the mirror folded).
    #[inline(always)]
    fn quad_scatter(
        table: &mut [Self],
        w: usize,
        rows: quad::BlockAxis<'_, Self>,
        cols: quad::BlockAxis<'_, Self>,
        lanes: std::ops::Range<usize>,
        values: &[[Self; 4]; LANES],
    ) -> usize {
        let _ = (table, w, rows, cols, values);
        lanes.start
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
}

/// The largest value [`Real::truncate`] converts (`2³⁰`, exact in both precisions).
const GRID_INDEX_MAX: f64 = (1u32 << 30) as f64;

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
    fn exp(self) -> Self {
        f32::exp(self)
    }
    fn ln(self) -> Self {
        f32::ln(self)
    }
    #[inline(always)]
    fn ln8(x: [Self; 8]) -> [Self; 8] {
        crate::model::elementary::ln8(x)
    }
    #[inline(always)]
    fn exp8(x: [Self; 8]) -> [Self; 8] {
        crate::model::elementary::exp8(x)
    }
    #[inline(always)]
    fn quad_block(
        table: &[Self],
        w: usize,
        rows: quad::BlockAxis<'_, Self>,
        cols: quad::BlockAxis<'_, Self>,
        n: usize,
        block: &mut [[Self; 4]; LANES],
    ) -> u32 {
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            // SAFETY: the CPU has AVX2.
            return unsafe { quad::block_avx(table, w, rows, cols, n, block) };
        }
        let _ = (table, w, rows, cols, n, block);
        0
    }
    #[inline(always)]
    fn quad_scatter(
        table: &mut [Self],
        w: usize,
        rows: quad::BlockAxis<'_, Self>,
        cols: quad::BlockAxis<'_, Self>,
        lanes: std::ops::Range<usize>,
        values: &[[Self; 4]; LANES],
    ) -> usize {
        #[cfg(target_arch = "x86_64")]
        if has_avx2() {
            // SAFETY: the CPU has AVX2.
            return unsafe { quad::scatter_avx(table, w, rows, cols, lanes, values) };
        }
        let _ = (table, w, rows, cols, values);
        lanes.start
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
}

/// [`Real::transpose8`] of float32 in eight registers: interleave pairs of rows, then pairs
/// of pairs, then swap 128-bit halves (the compiler made the generic loop 64 scalar moves).
///
/// # Safety
///
/// The CPU has AVX; the pointers as [`Real::transpose8`].
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn transpose8_avx(src: *const f32, src_stride: usize, dst: *mut f32, dst_stride: usize) {
    use std::arch::x86_64::*;
    // SAFETY (every load and store): the caller's promise; unaligned accesses.
    let r: [__m256; 8] =
        std::array::from_fn(|i| unsafe { _mm256_loadu_ps(src.add(i * src_stride)) });
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
    for j in 0..4 {
        unsafe {
            _mm256_storeu_ps(
                dst.add(j * dst_stride),
                _mm256_permute2f128_ps::<0x20>(u[j], u[j + 4]),
            );
            _mm256_storeu_ps(
                dst.add((j + 4) * dst_stride),
                _mm256_permute2f128_ps::<0x31>(u[j], u[j + 4]),
            );
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

/// `fn $name<T: Real>(args)` calling the `#[inline(always)]` function `$body` with the same
/// arguments, compiled for AVX2 where the CPU has it ([`has_avx2`]) and for the baseline
/// otherwise. Both copies are the same source, so they compute the same values (no fused
/// multiply-adds are introduced: Rust does not contract `a * b + c`).
macro_rules! simd_dispatch {
    (fn $name:ident<$t:ident: Real>($($arg:ident: $ty:ty),* $(,)?) => $body:ident) => {
        fn $name<$t: Real>($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                fn wide<$t: Real>($($arg: $ty),*) {
                    $body($($arg),*)
                }
                if has_avx2() {
                    // SAFETY: the CPU has AVX2, checked just now.
                    return unsafe { wide($($arg),*) };
                }
            }
            $body($($arg),*)
        }
    };
    // The same for an `unsafe fn` body: the copy has the body's safety contract.
    ($(#[$doc:meta])* unsafe fn $name:ident<$t:ident: Real>($($arg:ident: $ty:ty),* $(,)?) => $body:ident) => {
        $(#[$doc])*
        unsafe fn $name<$t: Real>($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx2")]
                unsafe fn wide<$t: Real>($($arg: $ty),*) {
                    // SAFETY: the caller's promise, passed on.
                    unsafe { $body($($arg),*) }
                }
                if has_avx2() {
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

/// Pixels per task: large enough that a task outweighs rayon's overhead, small enough that
/// both cores (or sixteen) get an even share at 64².
const PIXELS_PER_TASK: usize = 1024;

/// A raw pointer that tasks writing disjoint indices of one buffer may share.
#[derive(Clone, Copy)]
pub(crate) struct Shared<T>(pub(crate) *mut T);
// SAFETY: every user writes only indices no other task touches (stated at each use).
unsafe impl<T: Send> Send for Shared<T> {}
unsafe impl<T: Send> Sync for Shared<T> {}

impl<T> Shared<T> {
    /// # Safety
    ///
    /// `i` is in bounds and no other thread reads or writes it meanwhile.
    unsafe fn write(self, i: usize, v: T) {
        unsafe { self.0.add(i).write(v) }
    }

    /// # Safety
    ///
    /// As [`write`](Self::write).
    pub(crate) unsafe fn get(self, i: usize) -> *mut T {
        unsafe { self.0.add(i) }
    }
}

// ---- the prefilter ------------------------------------------------------------------------

/// The factorisation of one mirrored tridiagonal system of size `n` (SPEC §1: the matrix `A`
/// with `(A x)(i) = (x(m(i−1)) + 4 x(i) + x(m(i+1))) / 6`, whose inverse is the prefilter), or
/// of its transpose: the Thomas algorithm's multipliers, computed once per line length.
#[derive(Clone, Debug)]
struct Tridiagonal {
    /// `A[i][i−1]`, `i ≥ 1`.
    lower: Vec<f64>,
    /// `1 / (A[i][i] − A[i][i−1] c'[i−1])`.
    inverse_pivot: Vec<f64>,
    /// `c'[i] = A[i][i+1] · inverse_pivot[i]`.
    upper_ratio: Vec<f64>,
}

impl Tridiagonal {
    /// `A` (or `Aᵀ`) for lines of `n ≥ 2` samples. Folding the mirror into `A` doubles the
    /// coupling of the end samples to their neighbours: `A[0][1] = A[n−1][n−2] = 2/6`.
    fn mirrored(n: usize, transpose: bool) -> Self {
        assert!(n >= 2, "the prefilter needs at least 2 samples per line");
        let entry = |i: usize, j: usize| -> f64 {
            let (i, j) = if transpose { (j, i) } else { (i, j) };
            if i == j {
                4.0 / 6.0
            } else if (i == 0 && j == 1) || (i == n - 1 && j == n - 2) {
                2.0 / 6.0
            } else {
                1.0 / 6.0
            }
        };
        let mut lower = vec![0.0; n];
        let mut inverse_pivot = vec![0.0; n];
        let mut upper_ratio = vec![0.0; n];
        for i in 0..n {
            lower[i] = if i > 0 { entry(i, i - 1) } else { 0.0 };
            let previous = if i > 0 { upper_ratio[i - 1] } else { 0.0 };
            inverse_pivot[i] = 1.0 / (entry(i, i) - lower[i] * previous);
            upper_ratio[i] = if i + 1 < n {
                entry(i, i + 1) * inverse_pivot[i]
            } else {
                0.0
            };
        }
        Self {
            lower,
            inverse_pivot,
            upper_ratio,
        }
    }

    /// The factors in the element type.
    fn cast<T: Real>(&self) -> (Vec<T>, Vec<T>, Vec<T>) {
        let cast = |v: &[f64]| v.iter().map(|&x| T::from_f64(x)).collect();
        (
            cast(&self.lower),
            cast(&self.inverse_pivot),
            cast(&self.upper_ratio),
        )
    }
}

/// The Thomas factors `(lower, inverse pivot, upper ratio)` of the prefilter's system for
/// lines of `n` samples (or of its transpose): what a device kernel needs to run the same
/// solve.
pub fn factors(n: usize, transpose: bool) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let t = Tridiagonal::mirrored(n, transpose);
    (t.lower, t.inverse_pivot, t.upper_ratio)
}

/// Lines solved side by side along the rows: the Thomas recurrence is a chain of dependent
/// multiply-adds, so one line at a time waits on each step's latency; eight independent
/// chains keep the pipeline full (measured: the row pass was 2/3 of the prefilter's time).
const LINES_TOGETHER: usize = 8;

/// Solves the system in place on each of the contiguous lines of `n` samples in `group`,
/// the lines interleaved step by step.
fn solve_lines<T: Real>(
    group: &mut [T],
    n: usize,
    (lower, pivot, upper): &(Vec<T>, Vec<T>, Vec<T>),
) {
    let lines = group.len() / n;
    debug_assert_eq!(group.len(), lines * n);
    debug_assert!(lower.len() == n && pivot.len() == n && upper.len() == n);
    for r in 0..lines {
        group[r * n] = group[r * n] * pivot[0];
    }
    for i in 1..n {
        let (l, p) = (lower[i], pivot[i]);
        for r in 0..lines {
            let at = r * n + i;
            group[at] = (group[at] - l * group[at - 1]) * p;
        }
    }
    for i in (0..n - 1).rev() {
        let u = upper[i];
        for r in 0..lines {
            let at = r * n + i;
            group[at] = group[at] - u * group[at + 1];
        }
    }
}

/// The forward elimination of step `i` of the system along a line, on a whole row of lanes
/// at once (lane by lane the Thomas recurrence): `here` is row `i`, `above` row `i − 1`
/// already eliminated (`None` for `i = 0`).
#[inline(always)]
fn eliminate<T: Real>(
    here: &mut [T],
    above: Option<&[T]>,
    i: usize,
    (lower, pivot, _): &(Vec<T>, Vec<T>, Vec<T>),
) {
    if let Some(above) = above {
        let (l, p) = (lower[i], pivot[i]);
        for (x, &a) in here.iter_mut().zip(above) {
            *x = (*x - l * a) * p;
        }
    } else {
        for x in here.iter_mut() {
            *x = *x * pivot[0];
        }
    }
}

/// The back substitution of step `i` (after [`eliminate`] of every step): `below` is row
/// `i + 1`, already solved.
#[inline(always)]
fn substitute<T: Real>(
    here: &mut [T],
    below: &[T],
    i: usize,
    (_, _, upper): &(Vec<T>, Vec<T>, Vec<T>),
) {
    let u = upper[i];
    for (x, &b) in here.iter_mut().zip(below) {
        *x = *x - u * b;
    }
}

/// Solves the system along the first axis of a `[rows, width]` block of columns `cols` of a
/// plane, one whole row segment at a time (unit stride, vectorisable).
///
/// # Safety
///
/// `plane` points to a `rows × width` plane whose columns `cols` no other thread touches.
unsafe fn solve_columns<T: Real>(
    plane: Shared<T>,
    width: usize,
    rows: usize,
    cols: std::ops::Range<usize>,
    factors: &(Vec<T>, Vec<T>, Vec<T>),
) {
    let row = |i: usize| -> &mut [T] {
        // SAFETY: the caller owns columns `cols` of every row.
        unsafe { std::slice::from_raw_parts_mut(plane.get(i * width + cols.start), cols.len()) }
    };
    for i in 0..rows {
        eliminate(row(i), (i > 0).then(|| &*row(i - 1)), i, factors);
    }
    for i in (0..rows - 1).rev() {
        substitute(row(i), row(i + 1), i, factors);
    }
}

/// The interpolating prefilter `c = P f` of every `height × width` plane of `data`, in place
/// (SPEC §1, exact); with `transpose`, its adjoint `Pᵀ g`. `P` is separable: the same 1-D
/// solve along each axis, in either order.
pub fn prefilter<T: Real>(data: &mut [T], height: usize, width: usize, transpose: bool) {
    prefilter_from(None, data, height, width, transpose);
}

/// [`prefilter`] of `source` into `data` (same length), without a separate copy pass: each
/// group of lines is copied just before it is solved, while it is in cache.
pub fn prefilter_into<T: Real>(
    source: &[T],
    data: &mut [T],
    height: usize,
    width: usize,
    transpose: bool,
) {
    assert_eq!(
        source.len(),
        data.len(),
        "prefilter: source and target differ in length"
    );
    prefilter_from(Some(source), data, height, width, transpose);
}

fn prefilter_from<T: Real>(
    source: Option<&[T]>,
    data: &mut [T],
    height: usize,
    width: usize,
    transpose: bool,
) {
    let plane = height * width;
    assert_eq!(data.len() % plane, 0, "prefilter: data is not whole planes");
    let along_w = Tridiagonal::mirrored(width, transpose).cast::<T>();
    let along_h = Tridiagonal::mirrored(height, transpose).cast::<T>();
    if data.len() / plane >= rayon::current_num_threads() {
        // A task per plane: its column pass finds the plane in cache where the row pass left
        // it, instead of a second trip through memory (measured, `energy` bench: −40 % for
        // the 1005 planes of 15 frames of 67 channels at 256², −30 – −50 % for RGB's 45).
        data.par_chunks_mut(plane)
            .enumerate()
            .for_each(|(p, values)| {
                if let Some(source) = source {
                    values.copy_from_slice(&source[p * plane..(p + 1) * plane]);
                }
                solve_plane_simd(values, width, &along_w, &along_h);
            });
        return;
    }
    // Fewer planes than threads: rows, then columns, each pass split finely enough that
    // every thread has work even for one plane.
    let group = width * LINES_TOGETHER;
    data.par_chunks_mut(group)
        .enumerate()
        .with_min_len((PIXELS_PER_TASK / group).max(1))
        .for_each(|(g, lines)| {
            if let Some(source) = source {
                lines.copy_from_slice(&source[g * group..g * group + lines.len()]);
            }
            solve_lines(lines, width, &along_w)
        });
    // Columns in blocks that keep a task's rows in cache.
    solve_all_columns(data, width, height, 64, &along_h);
}

/// Solves the system along both axes of one `[height, width]` plane, in place.
#[inline(always)]
fn solve_plane<T: Real>(
    plane: &mut [T],
    width: usize,
    along_w: &(Vec<T>, Vec<T>, Vec<T>),
    along_h: &(Vec<T>, Vec<T>, Vec<T>),
) {
    for lines in plane.chunks_mut(width * LINES_TOGETHER) {
        solve_lines(lines, width, along_w);
    }
    solve_interleaved(plane, width, along_h);
}

simd_dispatch!(fn solve_plane_simd<T: Real>(
    plane: &mut [T], width: usize,
    along_w: &(Vec<T>, Vec<T>, Vec<T>), along_h: &(Vec<T>, Vec<T>, Vec<T>)
) => solve_plane);

/// Solves the system along the first axis of every `[height, width]` plane of `data`, in
/// parallel tasks of `block` columns of one plane each.
fn solve_all_columns<T: Real>(
    data: &mut [T],
    width: usize,
    height: usize,
    block: usize,
    along_h: &(Vec<T>, Vec<T>, Vec<T>),
) {
    let plane = height * width;
    let block = block.min(width);
    let blocks = width.div_ceil(block);
    let base = Shared(data.as_mut_ptr());
    (0..data.len() / plane * blocks)
        .into_par_iter()
        .for_each(|task| {
            let (p, b) = (task / blocks, task % blocks);
            let cols = b * block..((b + 1) * block).min(width);
            // SAFETY: task (p, b) owns columns `cols` of plane `p`; tasks differ in one or the
            // other.
            unsafe { solve_columns(Shared(base.get(p * plane)), width, height, cols, along_h) };
        });
}

/// The forward prefilter `c = P f` of `n` images of `c` planar channels, written
/// channels-last (`out[((b·H + i)·W + j)·C + ch]`): what the many-channel kernels read
/// ([`reads_channels_last`]), so that they need not transpose the coefficients on every
/// evaluation. Each row of an image is gathered from its `C` planes into a cache-resident
/// `W × C` line and solved along `W` with the `C` channels as vector lanes; then the
/// columns, along `H`, with whole rows of `W·C` values as lanes: a task per image, each row
/// eliminated down the columns right after its solve along `W`, where there are at least as
/// many images as threads; else rows and column blocks split across the threads. Per value
/// the same operations in the same order as [`prefilter`]: the same bits.
pub fn prefilter_channels_last<T: Real>(
    source: &[T],
    out: &mut [T],
    shape: (usize, usize, usize, usize),
) {
    // SAFETY: the kernel writes only initialised values.
    prefilter_channels_last_uninit(source, unsafe { as_uninit(out) }, shape);
}

/// [`prefilter_channels_last`] into an output not yet initialised: each row is gathered
/// (every value written) before anything reads it.
pub fn prefilter_channels_last_uninit<T: Real>(
    source: &[T],
    out: &mut [MaybeUninit<T>],
    (n, c, height, width): (usize, usize, usize, usize),
) {
    let plane = height * width;
    assert!(
        source.len() == n * c * plane && out.len() == source.len(),
        "prefilter: {} values for {n} × {c} planes of {height} × {width}, into {}",
        source.len(),
        out.len()
    );
    let along_w = Tridiagonal::mirrored(width, false).cast::<T>();
    let along_h = Tridiagonal::mirrored(height, false).cast::<T>();
    let line = width * c;
    if n >= rayon::current_num_threads() {
        // A task per image, rows top to bottom: each row's elimination down the columns runs
        // while the row is in cache from its solve along `W`, so the image passes through
        // memory once before the back substitution instead of twice (measured: −40 % for 15
        // images of 67 channels at 256²).
        out.par_chunks_mut(height * line)
            .enumerate()
            .for_each(|(b, image)| {
                let source = &source[b * c * plane..(b + 1) * c * plane];
                image_channels_last_simd(source, image, (c, width), &along_w, &along_h);
            });
        return;
    }
    out.par_chunks_mut(line)
        .enumerate()
        .with_min_len((PIXELS_PER_TASK / width).max(1))
        .for_each(|(row, values)| {
            let (b, i) = (row / height, row % height);
            let values = gather_row(&source[b * c * plane..(b + 1) * c * plane], values, i, c);
            solve_interleaved_simd(values, c, &along_w);
        });
    // SAFETY: every row was gathered above.
    let out = unsafe { assume_init(out) };
    // An image is one `[H, W·C]` plane here; wider blocks, as a row holds `C` times more.
    solve_all_columns(out, line, height, 256, &along_h);
}

/// Row `i` of the `C` planes of `image` (`[C, H, W]`), channels-last into `values`
/// (`[W, C]`): every value written, and returned initialised.
#[inline(always)]
fn gather_row<'a, T: Real>(
    image: &[T],
    values: &'a mut [MaybeUninit<T>],
    i: usize,
    c: usize,
) -> &'a mut [T] {
    let width = values.len() / c;
    assert_eq!(width * c, values.len(), "a row of {c} channels");
    let plane = image.len() / c;
    assert!(i < plane / width.max(1), "row {i} of planes of {plane}");
    // SAFETY: `values` holds the `width · c` values written; row i of every plane is in
    // `image` from its offset.
    unsafe {
        transpose_pixels(
            &image[i * width..],
            c,
            plane,
            Shared(values.as_mut_ptr().cast::<T>()),
            0..width,
        )
    };
    // SAFETY: the transpose wrote all `width · c` values.
    unsafe { assume_init(values) }
}

/// `values` as initialised values.
///
/// # Safety
///
/// Every value of `values` has been written.
unsafe fn assume_init<T>(values: &mut [MaybeUninit<T>]) -> &mut [T] {
    // SAFETY: `MaybeUninit<T>` has `T`'s layout, and the caller's promise.
    unsafe { &mut *(values as *mut [MaybeUninit<T>] as *mut [T]) }
}

/// The channels-last prefilter of one image (`source` `[C, H, W]` planar, `image`
/// `[H, W, C]`): each row gathered, solved along `W`, and eliminated down the columns
/// against the row above; then the back substitution up the columns.
#[inline(always)]
fn image_channels_last<T: Real>(
    source: &[T],
    image: &mut [MaybeUninit<T>],
    (c, width): (usize, usize),
    along_w: &(Vec<T>, Vec<T>, Vec<T>),
    along_h: &(Vec<T>, Vec<T>, Vec<T>),
) {
    let line = width * c;
    let height = image.len() / line;
    for i in 0..height {
        let row = gather_row(source, &mut image[i * line..(i + 1) * line], i, c);
        solve_interleaved(row, c, along_w);
        // SAFETY: rows 0..=i are gathered; the elimination reads rows i − 1 and i.
        eliminate_row(
            unsafe { assume_init(&mut image[..(i + 1) * line]) },
            line,
            i,
            along_h,
        );
    }
    // SAFETY: every row was gathered above.
    let image = unsafe { assume_init(image) };
    for i in (0..height - 1).rev() {
        substitute_row(image, line, i, along_h);
    }
}

simd_dispatch!(fn image_channels_last_simd<T: Real>(
    source: &[T], image: &mut [MaybeUninit<T>], shape: (usize, usize),
    along_w: &(Vec<T>, Vec<T>, Vec<T>), along_h: &(Vec<T>, Vec<T>, Vec<T>)
) => image_channels_last);

/// [`eliminate`] of row `i` of a `[n, lanes]` block.
#[inline(always)]
fn eliminate_row<T: Real>(
    values: &mut [T],
    lanes: usize,
    i: usize,
    factors: &(Vec<T>, Vec<T>, Vec<T>),
) {
    let (before, here) = values.split_at_mut(i * lanes);
    let above = i.checked_sub(1).map(|k| &before[k * lanes..]);
    eliminate(&mut here[..lanes], above, i, factors);
}

/// [`substitute`] of row `i` of a `[n, lanes]` block.
#[inline(always)]
fn substitute_row<T: Real>(
    values: &mut [T],
    lanes: usize,
    i: usize,
    factors: &(Vec<T>, Vec<T>, Vec<T>),
) {
    let (here, below) = values.split_at_mut((i + 1) * lanes);
    substitute(&mut here[i * lanes..], &below[..lanes], i, factors);
}

/// Solves the system along a line of `n` points stored `lanes` values apart (point-major),
/// for each lane: the lanes are independent systems, solved side by side.
#[inline(always)]
fn solve_interleaved<T: Real>(values: &mut [T], lanes: usize, factors: &(Vec<T>, Vec<T>, Vec<T>)) {
    let n = values.len() / lanes;
    debug_assert!(factors.0.len() == n && factors.1.len() == n && factors.2.len() == n);
    for i in 0..n {
        eliminate_row(values, lanes, i, factors);
    }
    for i in (0..n - 1).rev() {
        substitute_row(values, lanes, i, factors);
    }
}

simd_dispatch!(fn solve_interleaved_simd<T: Real>(
    values: &mut [T], lanes: usize, factors: &(Vec<T>, Vec<T>, Vec<T>)
) => solve_interleaved);

// ---- the evaluation -----------------------------------------------------------------------

/// Where a sample point falls along one axis: the 4 mirrored indices, the B-spline weights
/// `β(t+1), β(t), β(t−1), β(t−2)` of the fractional part and their derivatives `β'`, and
/// whether the point lies inside the clamp range (else the clamped function is flat).
#[derive(Clone, Copy, Debug)]
struct Axis<T> {
    index: [usize; 4],
    weight: [T; 4],
    slope: [T; 4],
    inside: bool,
}

/// Points whose setup is computed together: one AVX2 register of float32 values.
const LANES: usize = 8;

/// [`Axis`] of `LANES` points at once, structure of arrays, in the kernels' precision: the
/// setup is a few dozen arithmetic operations per point with no data-dependent branch, so
/// across points it vectorises (it cost as much as the 48 multiply-adds of a 3-channel
/// evaluation when done a point at a time in float64).
struct AxisLanes<T> {
    index: [[u32; LANES]; 4],
    weight: [[T; LANES]; 4],
    slope: [[T; LANES]; 4],
    inside: [bool; LANES],
}

impl<T: Real> AxisLanes<T> {
    /// The axes of the points `p` (coordinates along an axis of `n ≥ 4` samples).
    #[inline(always)]
    fn new(p: &[T; LANES], n: usize) -> Self {
        let zero = T::default();
        let one = T::from_f64(1.0);
        let hi = T::from_f64((n - 1) as f64);
        let last = n as i32 - 1;
        let (sixth, half, minus_half) = (T::from_f64(SIXTH), T::from_f64(0.5), T::from_f64(-0.5));
        let (two, one_and_half, two_thirds) =
            (T::from_f64(2.0), T::from_f64(1.5), T::from_f64(2.0 / 3.0));
        let mut lanes = Self {
            index: [[0; LANES]; 4],
            weight: [[zero; LANES]; 4],
            slope: [[zero; LANES]; 4],
            inside: [false; LANES],
        };
        for (l, &p) in p.iter().enumerate() {
            // `!(p > hi)` and `!(p < 0)` so that a NaN lands inside and stays NaN in the
            // output (the clamp keeps it too).
            lanes.inside[l] = !(p < zero) && !(p > hi);
            let q = if p < zero {
                zero
            } else if p > hi {
                hi
            } else {
                p
            };
            // `q ≥ 0`, so truncation is the floor; a NaN truncates to 0 and stays NaN in `t`.
            let base = q.truncate();
            let t = q - T::from_i32(base);
            let s = one - t;
            let (t2, s2) = (t * t, s * s);
            for a in 0..4 {
                // Whole-sample mirror (SPEC §0) of an index in `[−1, n + 1]`.
                let i = base + a as i32 - 1;
                lanes.index[a][l] = (last - (i.abs() - last).abs()) as u32;
            }
            lanes.weight[0][l] = s2 * s * sixth;
            lanes.weight[1][l] = half * t2 * t - t2 + two_thirds;
            lanes.weight[2][l] = half * s2 * s - s2 + two_thirds;
            lanes.weight[3][l] = t2 * t * sixth;
            lanes.slope[0][l] = minus_half * s2;
            lanes.slope[1][l] = one_and_half * t2 - two * t;
            lanes.slope[2][l] = two * s - one_and_half * s2;
            lanes.slope[3][l] = half * t2;
        }
        lanes
    }

    /// The row and column axes of the `n ≤ LANES` points from `first` of an image whose
    /// deformation planes are `(p0, p1)` ([`deformation_planes`]), on an `h × w` grid.
    #[inline(always)]
    fn block((p0, p1): (&[T], &[T]), first: usize, n: usize, h: usize, w: usize) -> (Self, Self) {
        let load = |axis: &[T]| {
            let mut v = [T::default(); LANES];
            v[..n].copy_from_slice(&axis[first..first + n]);
            v
        };
        (Self::new(&load(p0), h), Self::new(&load(p1), w))
    }

    /// The axis of point `l`.
    #[inline(always)]
    fn lane(&self, l: usize) -> Axis<T> {
        // Written out: `array::map` is not inlined here and cost a tenth of a sweep.
        let (i, w, s) = (&self.index, &self.weight, &self.slope);
        Axis {
            index: [
                i[0][l] as usize,
                i[1][l] as usize,
                i[2][l] as usize,
                i[3][l] as usize,
            ],
            weight: [w[0][l], w[1][l], w[2][l], w[3][l]],
            slope: [s[0][l], s[1][l], s[2][l], s[3][l]],
            inside: self.inside[l],
        }
    }
}

/// Image `b`'s deformation `φ_b` as its two planes (row and column coordinates).
#[inline(always)]
fn deformation_planes<'a, T>(phi: &'a [T], d: &Dims, b: usize) -> (&'a [T], &'a [T]) {
    let plane = d.points();
    phi[b * 2 * plane..(b + 1) * 2 * plane].split_at(plane)
}

/// `1/6`, a product where a division would stall the point's setup.
const SIXTH: f64 = 1.0 / 6.0;

/// The points `p` of a range of image `b` with their axes `(p, rows, cols)`, set up `LANES`
/// points at a time. An iterator, not a callback, so that the caller's loop body stays in
/// the caller (and in its AVX2 copy): a closure was compiled apart and called per point.
struct Points<'a, T> {
    p0: &'a [T],
    p1: &'a [T],
    h: usize,
    w: usize,
    next: usize,
    end: usize,
    /// The first point of the block set up in `rows` and `cols`.
    first: usize,
    rows: AxisLanes<T>,
    cols: AxisLanes<T>,
}

impl<'a, T: Real> Points<'a, T> {
    #[inline(always)]
    fn new(phi: &'a [T], d: &Dims, b: usize, points: std::ops::Range<usize>) -> Self {
        let zero = [T::default(); LANES];
        let (p0, p1) = deformation_planes(phi, d, b);
        Self {
            p0,
            p1,
            h: d.h,
            w: d.w,
            next: points.start,
            end: points.end,
            first: points.start,
            // Set up on the first call of `next`.
            rows: AxisLanes::new(&zero, d.h),
            cols: AxisLanes::new(&zero, d.w),
        }
    }
}

impl<T: Real> Iterator for Points<'_, T> {
    type Item = (usize, Axis<T>, Axis<T>);

    #[inline(always)]
    fn next(&mut self) -> Option<Self::Item> {
        let p = self.next;
        if p >= self.end {
            return None;
        }
        if (p - self.first) % LANES == 0 {
            let count = LANES.min(self.end - p);
            self.first = p;
            (self.rows, self.cols) = AxisLanes::block((self.p0, self.p1), p, count, self.h, self.w);
        }
        self.next = p + 1;
        let l = p - self.first;
        Some((p, self.rows.lane(l), self.cols.lane(l)))
    }
}

/// The shapes of an evaluation: `n` images of `c` channels on a `h × w` coefficient grid,
/// sampled at `ho × wo` points each.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Dims {
    /// Batch `N`.
    pub n: usize,
    /// Channels `C`.
    pub c: usize,
    /// Coefficient rows `H`.
    pub h: usize,
    /// Coefficient columns `W`.
    pub w: usize,
    /// Sample rows `H'`.
    pub ho: usize,
    /// Sample columns `W'`.
    pub wo: usize,
}

impl Dims {
    fn points(&self) -> usize {
        self.ho * self.wo
    }

    fn check<T>(&self, coeffs: usize, phi: &[T], samples: usize) {
        assert!(self.h >= 4 && self.w >= 4, "the spline needs 4 × 4 samples");
        assert_eq!(coeffs, self.n * self.c * self.h * self.w, "coefficients");
        assert_eq!(phi.len(), self.n * 2 * self.points(), "deformation");
        assert_eq!(samples, self.n * self.c * self.points(), "samples");
    }
}

/// The 16 offsets and weights `β(p₀ − i) β(p₁ − j)` of a point.
#[inline(always)]
fn stencil<T: Real>(rows: &Axis<T>, cols: &Axis<T>, w: usize) -> ([usize; 16], [T; 16]) {
    let mut offset = [0; 16];
    let mut weight = [T::default(); 16];
    for a in 0..4 {
        for b in 0..4 {
            offset[4 * a + b] = rows.index[a] * w + cols.index[b];
            weight[4 * a + b] = rows.weight[a] * cols.weight[b];
        }
    }
    (offset, weight)
}

// ---- many channels: channels-last ---------------------------------------------------------

/// From this many channels on, the evaluation and its position gradient read the coefficients
/// channels-last: a point's 16 neighbours are then 16 contiguous runs of `C` values (vector
/// loads, a few cache lines) instead of `16·C` reads spread over `C` planes. The transposition
/// costs one pass over the coefficients per call; below this it does not pay.
const CHANNELS_LAST_FROM: usize = 8;

/// Points (or pixels) per tile of a layout change between planar and channels-last: a tile
/// of `C` values per point stays in the second-level cache even at `C = 515`, and each plane
/// is read or written in runs of this many contiguous values. Writing a point's `C` values
/// straight into `C` planes, a plane apart, cost more than evaluating them (measured: about
/// 60 % of the evaluation's profile samples in a deep morph at 256²).
const TILE: usize = 64;

/// How a kernel's coefficients lie in memory.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Layout {
    /// `[N, C, H, W]`, row-major.
    Planar,
    /// Channels-last, `stride` values from one pixel to the next (`≥ C`: the channels may
    /// be a block of a wider table) and `H·W·stride` from one image to the next.
    ChannelsLast {
        /// Values per pixel in the buffer.
        stride: usize,
    },
}

/// Whether the kernels read `c` channels channels-last (and so whether
/// [`prefilter_channels_last`] saves them a transpose per evaluation).
pub fn reads_channels_last(c: usize) -> bool {
    c >= CHANNELS_LAST_FROM
}

/// Checks that a channels-last table of `stride` values per pixel holds `d`'s coefficients.
fn check_table<T>(values: &[T], stride: usize, d: &Dims) {
    assert!(
        reads_channels_last(d.c),
        "a channels-last table of {} channels",
        d.c
    );
    let plane = d.h * d.w;
    assert!(
        stride >= d.c && values.len() >= ((d.n - 1) * plane + plane - 1) * stride + d.c,
        "channels-last table of {} values with stride {stride} for {d:?}",
        values.len()
    );
}

/// [`sample`] from channels-last coefficients (`layout` [`Layout::ChannelsLast`]): `values`
/// starts at image 0's first channel.
pub fn sample_from_table<T: Real>(values: &[T], stride: usize, phi: &[T], out: &mut [T], d: Dims) {
    // SAFETY: the kernel writes only initialised values.
    sample_from_table_uninit(values, stride, phi, unsafe { as_uninit(out) }, d);
}

/// [`sample_from_table`] into an output not yet initialised: every value is written.
pub fn sample_from_table_uninit<T: Real>(
    values: &[T],
    stride: usize,
    phi: &[T],
    out: &mut [MaybeUninit<T>],
    d: Dims,
) {
    check_table(values, stride, &d);
    assert_eq!(phi.len(), d.n * 2 * d.points(), "deformation");
    assert_eq!(out.len(), d.n * d.c * d.points(), "samples");
    sample_channels_last(values, Layout::ChannelsLast { stride }, phi, out, d);
}

/// `out` as a slice of possibly uninitialised values, for the kernels that write every value
/// of their output and read none.
///
/// # Safety
///
/// The caller writes only initialised values through the result (a `T` slice must stay
/// initialised).
unsafe fn as_uninit<T>(out: &mut [T]) -> &mut [MaybeUninit<T>] {
    // SAFETY: `MaybeUninit<T>` has `T`'s layout; the caller's promise keeps `out` valid.
    unsafe { &mut *(out as *mut [T] as *mut [MaybeUninit<T>]) }
}

/// [`sample_position_grad`] from channels-last coefficients, as [`sample_from_table`].
pub fn position_grad_from_table<T: Real>(
    values: &[T],
    stride: usize,
    phi: &[T],
    grad: &[T],
    out: &mut [T],
    d: Dims,
) {
    check_table(values, stride, &d);
    assert_eq!(phi.len(), d.n * 2 * d.points(), "deformation");
    assert_eq!(grad.len(), d.n * d.c * d.points(), "output gradient");
    assert_eq!(out.len(), phi.len(), "position gradient");
    position_grad_channels_last(values, Layout::ChannelsLast { stride }, phi, grad, out, d);
}

/// One image's `C` planes of `plane` values, channels-last: `out[p·C + c] = planar[c·plane + p]`.
fn channels_last<T: Real>(planar: &[T], c: usize, plane: usize) -> Vec<T> {
    let mut out = vec![T::default(); planar.len()];
    channels_last_into(planar, c, plane, &mut out);
    out
}

/// [`channels_last`] into `out` (same length). Also the transpose of a `c × plane` matrix
/// (the separable operators' transposes of whole planes).
pub(crate) fn channels_last_into<T: Real>(planar: &[T], c: usize, plane: usize, out: &mut [T]) {
    assert!(
        planar.len() == c * plane && out.len() == planar.len(),
        "channels-last: {} values for {c} planes of {plane}, into {}",
        planar.len(),
        out.len()
    );
    let target = Shared(out.as_mut_ptr());
    (0..plane.div_ceil(PIXELS_PER_TASK))
        .into_par_iter()
        .for_each(|chunk| {
            let pixels = chunk * PIXELS_PER_TASK..((chunk + 1) * PIXELS_PER_TASK).min(plane);
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
unsafe fn transpose_pixels<T: Real>(
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

/// `Σ_i a[i] · b[i]` in eight interleaved partial sums (vectorisable, and short dependency
/// chains).
#[inline]
fn dot<T: Real>(a: &[T], b: &[T]) -> T {
    let mut lanes = [T::default(); 8];
    let (a8, b8) = (a.chunks_exact(8), b.chunks_exact(8));
    let (a_rest, b_rest) = (a8.remainder(), b8.remainder());
    for (x, y) in a8.zip(b8) {
        for j in 0..8 {
            lanes[j] += x[j] * y[j];
        }
    }
    let mut sum = ((lanes[0] + lanes[1]) + (lanes[2] + lanes[3]))
        + ((lanes[4] + lanes[5]) + (lanes[6] + lanes[7]));
    for (&x, &y) in a_rest.iter().zip(b_rest) {
        sum += x * y;
    }
    sum
}

/// Image `b`'s coefficients as a channels-last table and its pixel stride: `values` itself
/// when it is one, else transposed from planar.
fn image_table<T: Real>(values: &[T], layout: Layout, d: Dims, b: usize) -> (Cow<'_, [T]>, usize) {
    let plane = d.h * d.w;
    match layout {
        Layout::Planar => (
            Cow::Owned(channels_last(
                &values[b * d.c * plane..(b + 1) * d.c * plane],
                d.c,
                plane,
            )),
            d.c,
        ),
        Layout::ChannelsLast { stride } => (Cow::Borrowed(&values[b * plane * stride..]), stride),
    }
}

/// [`sample`] for many channels: writes every value of `out`.
fn sample_channels_last<T: Real>(
    coeffs: &[T],
    layout: Layout,
    phi: &[T],
    out: &mut [MaybeUninit<T>],
    d: Dims,
) {
    let (points, c) = (d.points(), d.c);
    let tasks = points.div_ceil(PIXELS_PER_TASK);
    let out = Shared(out.as_mut_ptr().cast::<T>());
    for b in 0..d.n {
        let (table, stride) = image_table(coeffs, layout, d, b);
        (0..tasks).into_par_iter().for_each(|chunk| {
            let mut tile = vec![T::default(); c * TILE];
            let end = ((chunk + 1) * PIXELS_PER_TASK).min(points);
            for first in (chunk * PIXELS_PER_TASK..end).step_by(TILE) {
                let count = TILE.min(end - first);
                evaluate_tile_simd(&table, stride, phi, d, b, first..first + count, &mut tile);
                // SAFETY: points first..first + count of image b are this task's alone, in
                // every channel's plane.
                unsafe {
                    tile_to_planes_simd(
                        &tile[..count * c],
                        c,
                        Shared(out.get(b * c * points + first)),
                        points,
                    )
                };
            }
        });
    }
}

/// Writes the channels-last `tile` (`count × c`) into `c` planes `plane` values apart from
/// `out`: `out[ch·plane + i] = tile[i·c + ch]`, in blocks of 8 points × 8 channels
/// ([`Real::transpose8`]): one value at a time, the gather with a stride of `c` cost half as
/// much as the evaluation itself.
///
/// # Safety
///
/// `out` is valid for the `count` values from each `ch·plane`, which no other thread
/// touches meanwhile.
#[inline(always)]
unsafe fn tile_to_planes<T: Real>(tile: &[T], c: usize, out: Shared<T>, plane: usize) {
    const B: usize = 8;
    let count = tile.len() / c;
    let column = |ch: usize, from: usize, len: usize| -> &mut [T] {
        // SAFETY: the caller's promise, for channel ch's points from..from + len.
        unsafe { std::slice::from_raw_parts_mut(out.get(ch * plane + from), len) }
    };
    let (whole_points, whole_channels) = (count - count % B, c - c % B);
    for i0 in (0..whole_points).step_by(B) {
        for ch0 in (0..whole_channels).step_by(B) {
            // SAFETY: the 8 rows of 8 from (i0, ch0) lie in the tile; the 8 columns are
            // the caller's promise.
            unsafe {
                T::transpose8(
                    tile[i0 * c + ch0..].as_ptr(),
                    c,
                    out.get(ch0 * plane + i0),
                    plane,
                )
            };
        }
        for ch in whole_channels..c {
            for (i, v) in column(ch, i0, B).iter_mut().enumerate() {
                *v = tile[(i0 + i) * c + ch];
            }
        }
    }
    for ch in 0..c {
        for (i, v) in column(ch, whole_points, count - whole_points)
            .iter_mut()
            .enumerate()
        {
            *v = tile[(whole_points + i) * c + ch];
        }
    }
}

simd_dispatch!(
    /// [`tile_to_planes`], compiled for AVX2 where the CPU has it.
    ///
    /// # Safety
    ///
    /// As [`tile_to_planes`].
    unsafe fn tile_to_planes_simd<T: Real>(tile: &[T], c: usize, out: Shared<T>, plane: usize)
        => tile_to_planes
);

/// The points `points` of image `b` evaluated from the channels-last `table` into `tile`,
/// channels-last (`C` values per point).
#[inline(always)]
fn evaluate_tile<T: Real>(
    table: &[T],
    stride: usize,
    phi: &[T],
    d: Dims,
    b: usize,
    points: std::ops::Range<usize>,
    tile: &mut [T],
) {
    let (c, first) = (d.c, points.start);
    for (p, rows, cols) in Points::new(phi, &d, b, points) {
        let acc = &mut tile[(p - first) * c..(p - first + 1) * c];
        let (offset, weight) = stencil::<T>(&rows, &cols, d.w);
        let at: [usize; 16] = std::array::from_fn(|k| offset[k] * stride);
        // Channels in runs of registers through all 16 neighbours: the partial sums stay in
        // registers (through memory once per neighbour, the loop was bound by those loads
        // and stores), and several registers are independent chains of adds. Per channel
        // the same adds in the same order.
        let mut start = 0;
        start = neighbour_runs::<T, 8>(table, &at, &weight, start, acc);
        start = neighbour_runs::<T, 4>(table, &at, &weight, start, acc);
        start = neighbour_runs::<T, 2>(table, &at, &weight, start, acc);
        start = neighbour_runs::<T, 1>(table, &at, &weight, start, acc);
        let lanes = c - start;
        if lanes == 0 {
            continue;
        }
        let last = at.iter().max().expect("16 neighbours") + start;
        if last + CHANNEL_LANES <= table.len() {
            // A whole register read past the last channel (the next pixel's values, or the
            // next block's), its extra lanes dropped.
            let sum = neighbour_sums::<T, 1>(table, &at, &weight, start);
            acc[start..].copy_from_slice(&sum[0][..lanes]);
        } else {
            for (ch, x) in acc[start..].iter_mut().enumerate() {
                let mut sum = T::default();
                for k in 0..16 {
                    sum += weight[k] * table[at[k] + start + ch];
                }
                *x = sum;
            }
        }
    }
}

/// Sums `Σ_k weight[k] · table[at[k] + ch]` for the channels `ch` of `R` registers from
/// `start`, the neighbours `k` in order.
#[inline(always)]
fn neighbour_sums<T: Real, const R: usize>(
    table: &[T],
    at: &[usize; 16],
    weight: &[T; 16],
    start: usize,
) -> [[T; CHANNEL_LANES]; R] {
    let mut sum = [[T::default(); CHANNEL_LANES]; R];
    for k in 0..16 {
        let run = &table[at[k] + start..at[k] + start + R * CHANNEL_LANES];
        for (r, lanes) in sum.iter_mut().enumerate() {
            for (j, x) in lanes.iter_mut().enumerate() {
                *x += weight[k] * run[r * CHANNEL_LANES + j];
            }
        }
    }
    sum
}

/// [`neighbour_sums`] of whole runs of `R` registers into `acc` (a point's channels) from
/// channel `start` while they fit; returns the first channel left.
#[inline(always)]
fn neighbour_runs<T: Real, const R: usize>(
    table: &[T],
    at: &[usize; 16],
    weight: &[T; 16],
    mut start: usize,
    acc: &mut [T],
) -> usize {
    let width = R * CHANNEL_LANES;
    while start + width <= acc.len() {
        let sum = neighbour_sums::<T, R>(table, at, weight, start);
        for (r, lanes) in sum.iter().enumerate() {
            let at = start + r * CHANNEL_LANES;
            acc[at..at + CHANNEL_LANES].copy_from_slice(lanes);
        }
        start += width;
    }
    start
}

/// Channels summed side by side in [`evaluate_tile`]: one AVX2 register of float32.
const CHANNEL_LANES: usize = 8;

simd_dispatch!(fn evaluate_tile_simd<T: Real>(
    table: &[T], stride: usize, phi: &[T], d: Dims, b: usize, points: std::ops::Range<usize>,
    tile: &mut [T]
) => evaluate_tile);

/// The position gradient at the points `points` of image `b` from the channels-last
/// coefficients `table` and output gradient `g`, written into `out` (`[N, 2, H', W']`).
#[inline(always)]
fn position_grad_tile<T: Real>(
    table: &[T],
    stride: usize,
    phi: &[T],
    g: &[T],
    out: Shared<T>,
    d: Dims,
    b: usize,
    points: std::ops::Range<usize>,
) {
    let (c, plane) = (d.c, d.points());
    for (p, rows, cols) in Points::new(phi, &d, b, points) {
        let gp = &g[p * c..(p + 1) * c];
        // ⟨g, c_ab⟩ for each neighbour, then the two derivative stencils.
        let (mut g0, mut g1) = (0.0, 0.0);
        for a in 0..4 {
            for k in 0..4 {
                let at = rows.index[a] * d.w + cols.index[k];
                let v = dot(gp, &table[at * stride..at * stride + c]).to_f64();
                g0 += (rows.slope[a] * cols.weight[k]).to_f64() * v;
                g1 += (rows.weight[a] * cols.slope[k]).to_f64() * v;
            }
        }
        let at = b * 2 * plane + p;
        let zero = T::default();
        // SAFETY: point p of image b is the calling task's alone.
        unsafe {
            out.write(at, if rows.inside { T::from_f64(g0) } else { zero });
            out.write(at + plane, if cols.inside { T::from_f64(g1) } else { zero });
        }
    }
}

simd_dispatch!(fn position_grad_tile_simd<T: Real>(
    table: &[T], stride: usize, phi: &[T], g: &[T], out: Shared<T>, d: Dims, b: usize,
    points: std::ops::Range<usize>
) => position_grad_tile);

/// [`sample_position_grad`] for many channels.
fn position_grad_channels_last<T: Real>(
    coeffs: &[T],
    layout: Layout,
    phi: &[T],
    grad: &[T],
    out: &mut [T],
    d: Dims,
) {
    let (points, c) = (d.points(), d.c);
    let tasks = points.div_ceil(PIXELS_PER_TASK);
    let out = Shared(out.as_mut_ptr());
    for b in 0..d.n {
        let (table, stride) = image_table(coeffs, layout, d, b);
        let g = channels_last(&grad[b * c * points..(b + 1) * c * points], c, points);
        (0..tasks).into_par_iter().for_each(|chunk| {
            let range = chunk * PIXELS_PER_TASK..((chunk + 1) * PIXELS_PER_TASK).min(points);
            position_grad_tile_simd(&table, stride, phi, &g, out, d, b, range);
        });
    }
}

/// `Σ_b weight[b] · line[index[b]]` as two independent pairs.
#[inline]
fn dot4<T: Real>(line: &[T], index: &[usize; 4], weight: &[T; 4]) -> T {
    debug_assert!(index.iter().all(|&i| i < line.len()));
    // SAFETY: the indices are mirrored into `[0, w)` (`AxisLanes::new`) and `line` starts a row
    // of the plane, so it holds at least `w` values.
    let at = |b: usize| unsafe { *line.get_unchecked(index[b]) };
    (weight[0] * at(0) + weight[1] * at(1)) + (weight[2] * at(2) + weight[3] * at(3))
}

/// Where a point's four columns are contiguous (the usual case: not within two samples of
/// the left or right edge), its row offsets `index·W` and first column; else `None` (the
/// mirror folds a column index back, and the gathers of [`dot4`] are needed).
#[inline(always)]
fn contiguous<T>(rows: &Axis<T>, cols: &Axis<T>, w: usize) -> Option<([usize; 4], usize)> {
    let (r, j0) = (&rows.index, cols.index[0]);
    // Mirrored neighbours differ by ±1, so a rise of 3 over 3 steps means +1 each time.
    (cols.index[3] == j0 + 3).then_some(([r[0] * w, r[1] * w, r[2] * w, r[3] * w], j0))
}

/// `v[k] = Σ_a weight[a] · c[rows[a] + j0 + k]`, `k < 4`: the four columns summed down the four
/// rows side by side (one vector of four lanes), before the sum across them.
#[inline(always)]
fn down_rows<T: Real>(c: &[T], rows: &[usize; 4], j0: usize, weight: &[T; 4]) -> [T; 4] {
    let mut v = [T::default(); 4];
    for a in 0..4 {
        let line: &[T; 4] = c[rows[a] + j0..rows[a] + j0 + 4]
            .try_into()
            .expect("four columns");
        for k in 0..4 {
            v[k] += weight[a] * line[k];
        }
    }
    v
}

/// `Σ_k a[k] · b[k]` as two independent pairs.
#[inline(always)]
fn sum4<T: Real>(a: &[T; 4], b: &[T; 4]) -> T {
    (a[0] * b[0] + a[1] * b[1]) + (a[2] * b[2] + a[3] * b[3])
}

/// `T = B(φ) c`: the spline with coefficients `coeffs` at the clamped points `phi`.
pub fn sample<T: Real>(coeffs: &[T], phi: &[T], out: &mut [T], d: Dims) {
    // SAFETY: the kernels write only initialised values.
    sample_uninit(coeffs, phi, unsafe { as_uninit(out) }, d);
}

/// [`sample`] into an output not yet initialised: every value is written (a zeroed output
/// was a serial memset, or page clearing, of a whole frame before each parallel warp).
pub fn sample_uninit<T: Real>(coeffs: &[T], phi: &[T], out: &mut [MaybeUninit<T>], d: Dims) {
    d.check(coeffs.len(), phi, out.len());
    if d.c >= CHANNELS_LAST_FROM {
        return sample_channels_last(coeffs, Layout::Planar, phi, out, d);
    }
    if quad::reads_quads(d.c) {
        return quad::sample(coeffs, phi, out, d);
    }
    let points = d.points();
    let tasks = points.div_ceil(PIXELS_PER_TASK);
    let out = Shared(out.as_mut_ptr().cast::<T>());
    (0..d.n * tasks).into_par_iter().for_each(|task| {
        let (b, chunk) = (task / tasks, task % tasks);
        let range = chunk * PIXELS_PER_TASK..((chunk + 1) * PIXELS_PER_TASK).min(points);
        sample_planar_simd(coeffs, phi, out, d, b, range);
    });
}

/// [`sample`] of the points `points` of image `b` from planar coefficients, into `out`.
#[inline(always)]
fn sample_planar<T: Real>(
    coeffs: &[T],
    phi: &[T],
    out: Shared<T>,
    d: Dims,
    b: usize,
    points: std::ops::Range<usize>,
) {
    let (plane, count) = (d.h * d.w, d.points());
    for (p, rows, cols) in Points::new(phi, &d, b, points) {
        let (wr, wc) = (rows.weight, cols.weight);
        let inner = contiguous(&rows, &cols, d.w);
        for ch in 0..d.c {
            let c = &coeffs[(b * d.c + ch) * plane..(b * d.c + ch + 1) * plane];
            let acc = if let Some((ro, j0)) = inner {
                sum4(&wc, &down_rows(c, &ro, j0, &wr))
            } else {
                // Separably, one row of four at a time: four short independent sums instead
                // of one chain of sixteen dependent adds.
                let row = |a: usize| dot4(&c[rows.index[a] * d.w..], &cols.index, &wc);
                (wr[0] * row(0) + wr[1] * row(1)) + (wr[2] * row(2) + wr[3] * row(3))
            };
            // SAFETY: point p of image b is the calling task's alone.
            unsafe { out.write((b * d.c + ch) * count + p, acc) };
        }
    }
}

simd_dispatch!(fn sample_planar_simd<T: Real>(
    coeffs: &[T], phi: &[T], out: Shared<T>, d: Dims, b: usize, points: std::ops::Range<usize>
) => sample_planar);

/// `Σ_c g_c ∂T_c/∂p` at every point: the gradient of `⟨g, B(φ) c⟩` w.r.t. `φ`, `[N, 2, H', W']`.
pub fn sample_position_grad<T: Real>(coeffs: &[T], phi: &[T], grad: &[T], out: &mut [T], d: Dims) {
    d.check(coeffs.len(), phi, grad.len());
    assert_eq!(out.len(), phi.len(), "position gradient");
    if d.c >= CHANNELS_LAST_FROM {
        return position_grad_channels_last(coeffs, Layout::Planar, phi, grad, out, d);
    }
    let points = d.points();
    let tasks = points.div_ceil(PIXELS_PER_TASK);
    let out = Shared(out.as_mut_ptr());
    (0..d.n * tasks).into_par_iter().for_each(|task| {
        let (b, chunk) = (task / tasks, task % tasks);
        let range = chunk * PIXELS_PER_TASK..((chunk + 1) * PIXELS_PER_TASK).min(points);
        position_grad_planar_simd(coeffs, phi, grad, out, d, b, range);
    });
}

/// [`sample_position_grad`] at the points `points` of image `b` from planar coefficients.
#[inline(always)]
fn position_grad_planar<T: Real>(
    coeffs: &[T],
    phi: &[T],
    grad: &[T],
    out: Shared<T>,
    d: Dims,
    b: usize,
    points: std::ops::Range<usize>,
) {
    let (plane, count) = (d.h * d.w, d.points());
    for (p, rows, cols) in Points::new(phi, &d, b, points) {
        let (wr, sr) = (rows.weight, rows.slope);
        let (wc, sc) = (cols.weight, cols.slope);
        let (mut g0, mut g1) = (T::default(), T::default());
        let inner = contiguous(&rows, &cols, d.w);
        for ch in 0..d.c {
            let c = &coeffs[(b * d.c + ch) * plane..(b * d.c + ch + 1) * plane];
            // ∂/∂p₀ = Σ_a β'_a (Σ_b β_b c_ab), ∂/∂p₁ = Σ_a β_a (Σ_b β'_b c_ab).
            let (mut t0, mut t1) = (T::default(), T::default());
            if let Some((ro, j0)) = inner {
                t0 = sum4(&wc, &down_rows(c, &ro, j0, &sr));
                t1 = sum4(&sc, &down_rows(c, &ro, j0, &wr));
            } else {
                for a in 0..4 {
                    let line = &c[rows.index[a] * d.w..];
                    t0 += sr[a] * dot4(line, &cols.index, &wc);
                    t1 += wr[a] * dot4(line, &cols.index, &sc);
                }
            }
            let g = grad[(b * d.c + ch) * count + p];
            g0 += g * t0;
            g1 += g * t1;
        }
        let zero = T::default();
        let at = b * 2 * count + p;
        // SAFETY: point p of image b is the calling task's alone.
        unsafe {
            out.write(at, if rows.inside { g0 } else { zero });
            out.write(at + count, if cols.inside { g1 } else { zero });
        }
    }
}

simd_dispatch!(fn position_grad_planar_simd<T: Real>(
    coeffs: &[T], phi: &[T], grad: &[T], out: Shared<T>, d: Dims, b: usize,
    points: std::ops::Range<usize>
) => position_grad_planar);

/// Adds `B(φ)ᵀ g` of the points `points` of image `b` into `target`, the planes of the
/// channels `channels` of that image.
#[inline(always)]
fn scatter<T: Real>(
    grad: &[T],
    phi: &[T],
    target: &mut [T],
    d: Dims,
    b: usize,
    channels: std::ops::Range<usize>,
    points: std::ops::Range<usize>,
) {
    let (plane, count) = (d.h * d.w, d.points());
    assert!(
        channels.len() <= MAX_GROUP,
        "at most {MAX_GROUP} channels per scatter"
    );
    for (p, rows, cols) in Points::new(phi, &d, b, points) {
        // The group's values at p first: their loads overlap, where each waited behind the
        // previous channel's stores.
        let mut values = [T::default(); MAX_GROUP];
        for (i, ch) in channels.clone().enumerate() {
            values[i] = grad[(b * d.c + ch) * count + p];
        }
        if let Some((ro, j0)) = contiguous(&rows, &cols, d.w) {
            // Four rows of four contiguous columns: a vector of four per row.
            let (wr, wc) = (rows.weight, cols.weight);
            for (i, &v) in values[..channels.len()].iter().enumerate() {
                let target = &mut target[i * plane..(i + 1) * plane];
                for a in 0..4 {
                    let s = wr[a] * v;
                    let line: &mut [T; 4] = (&mut target[ro[a] + j0..ro[a] + j0 + 4])
                        .try_into()
                        .expect("four columns");
                    for k in 0..4 {
                        line[k] += s * wc[k];
                    }
                }
            }
            continue;
        }
        let (offset, weight) = stencil::<T>(&rows, &cols, d.w);
        for (i, &v) in values[..channels.len()].iter().enumerate() {
            let target = &mut target[i * plane..(i + 1) * plane];
            for k in 0..16 {
                target[offset[k]] += weight[k] * v;
            }
        }
    }
}

/// The most channels one [`scatter`] adds at once. The planes of a 256² image are 256 KiB
/// apart, so the same pixel of every plane falls in the same cache set: with 8 channels, 8
/// gradient and 8 target lines competed for each set of the 8-way caches (measured, deep
/// 256² sweeps: the scatter's share of the profile 15.6 % with 8, 12.9 % with 4, 15.0 % with
/// 2, where the stencil is shared by fewer channels).
const MAX_GROUP: usize = 4;

simd_dispatch!(fn scatter_simd<T: Real>(
    grad: &[T], phi: &[T], target: &mut [T], d: Dims, b: usize,
    channels: std::ops::Range<usize>, points: std::ops::Range<usize>
) => scatter);

/// `B(φ)ᵀ g`: the gradient of `⟨g, B(φ) c⟩` w.r.t. the coefficients, `[N, C, H, W]`.
///
/// A scatter-add: each point adds into 16 coefficients, and points collide. The planes
/// `(image, channel)` are independent: with many, tasks take groups of up to 8 channels of
/// one image; when there are fewer planes than twice the threads, each plane's points are
/// split into parts that add into private copies, summed at the end, so that 3 RGB channels
/// still keep every core busy.
pub fn sample_adjoint<T: Real>(grad: &[T], phi: &[T], out: &mut [T], d: Dims) {
    // SAFETY: the kernel writes only initialised values.
    sample_adjoint_uninit(grad, phi, unsafe { as_uninit(out) }, d);
}

/// [`sample_adjoint`] into an output not yet initialised: each task clears (or first
/// copies) the planes it owns before adding to them.
pub fn sample_adjoint_uninit<T: Real>(grad: &[T], phi: &[T], out: &mut [MaybeUninit<T>], d: Dims) {
    d.check(out.len(), phi, grad.len());
    let (points, plane) = (d.points(), d.h * d.w);
    let planes = d.n * d.c;
    let threads = rayon::current_num_threads();
    let parts = if planes >= 2 * threads {
        1
    } else {
        (2 * threads)
            .div_ceil(planes)
            .min(points.div_ceil(PIXELS_PER_TASK))
            .max(1)
    };
    if parts == 1 {
        // Many planes: a task scatters a group of an image's channels, so that each point's
        // stencil serves the whole group instead of being recomputed for every channel.
        let group = (planes / (2 * threads)).clamp(1, MAX_GROUP);
        let groups = d.c.div_ceil(group);
        let base = Shared(out.as_mut_ptr());
        (0..d.n * groups).into_par_iter().for_each(|task| {
            let (b, first) = (task / groups, (task % groups) * group);
            let channels = first..(first + group).min(d.c);
            let planes_at = (b * d.c + channels.start) * plane;
            // SAFETY: task (b, group) owns these planes of image b; tasks differ in one or
            // the other.
            let target = unsafe {
                std::slice::from_raw_parts_mut(base.get(planes_at), channels.len() * plane)
            };
            target.fill(MaybeUninit::new(T::default()));
            // SAFETY: cleared just now.
            let target = unsafe { assume_init(target) };
            scatter_simd(grad, phi, target, d, b, channels, 0..points);
        });
        return;
    }
    if quad::reads_quads(d.c) {
        return quad::adjoint(grad, phi, out, d, parts);
    }
    let per_part = points.div_ceil(parts);
    let scatter = |target: &mut [T], pl: usize, part: usize| {
        let (b, ch) = (pl / d.c, pl % d.c);
        let range = part * per_part..((part + 1) * per_part).min(points);
        scatter_simd(grad, phi, target, d, b, ch..ch + 1, range);
    };
    let mut partial = vec![T::default(); planes * parts * plane];
    partial
        .par_chunks_mut(plane)
        .enumerate()
        .for_each(|(task, target)| scatter(target, task / parts, task % parts));
    out.par_chunks_mut(plane)
        .enumerate()
        .for_each(|(pl, target)| {
            let first = &partial[pl * parts * plane..(pl * parts + 1) * plane];
            for (t, &v) in target.iter_mut().zip(first) {
                t.write(v);
            }
            // SAFETY: the plane's every value was written just now.
            let target = unsafe { assume_init(target) };
            for part in 1..parts {
                let more = &partial[(pl * parts + part) * plane..(pl * parts + part + 1) * plane];
                for (t, &m) in target.iter_mut().zip(more) {
                    *t += m;
                }
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The dense prefilter of `crate::model::stencil`, applied along both axes.
    fn dense_prefilter(data: &[f64], h: usize, w: usize) -> Vec<f64> {
        let (ph, pw) = (
            crate::model::stencil::bspline_prefilter(h),
            crate::model::stencil::bspline_prefilter(w),
        );
        let mut out = vec![0.0; h * w];
        for i in 0..h {
            for j in 0..w {
                let mut acc = 0.0;
                for k in 0..h {
                    for l in 0..w {
                        acc += ph.get(i, k) * pw.get(j, l) * data[k * w + l];
                    }
                }
                out[i * w + j] = acc;
            }
        }
        out
    }

    fn ramp(n: usize, seed: f64) -> Vec<f64> {
        (0..n)
            .map(|i| (i as f64 * 0.37 + seed).sin() + 0.1 * i as f64 % 3.0)
            .collect()
    }

    #[test]
    fn prefiltering_into_a_new_buffer_equals_prefiltering_in_place() {
        // 3 planes of 11 × 9: line groups that end inside a plane and across planes.
        let (h, w) = (11, 9);
        let source: Vec<f64> = ramp(3 * h * w, 0.4);
        for transpose in [false, true] {
            let mut in_place = source.clone();
            prefilter(&mut in_place, h, w, transpose);
            let mut into = vec![0.0; source.len()];
            prefilter_into(&source, &mut into, h, w, transpose);
            assert_eq!(in_place, into, "transpose {transpose}");
        }
    }

    /// The prefilters run a task per plane (or image) when there are at least as many as
    /// threads, else split rows and column blocks across threads: both orders of work give
    /// the same bits, in float32 where reordered arithmetic would show.
    #[test]
    fn the_prefilters_split_of_work_does_not_change_a_bit() {
        // Two images of 21 or 9 channels, 13 × 10 (line groups and column blocks that end
        // inside a plane). One thread: a task per plane or image. 4 threads: the
        // channels-last images in split rows and columns. 64 threads: the planar passes too.
        let (n, h, w) = (2, 13, 10);
        for c in [21, 9] {
            let f: Vec<f32> = ramp(n * c * h * w, 0.6).iter().map(|&v| v as f32).collect();
            let run = |threads: usize| {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .expect("a thread pool");
                pool.install(|| {
                    let (mut forward, mut adjoint) = (f.clone(), f.clone());
                    prefilter(&mut forward, h, w, false);
                    prefilter(&mut adjoint, h, w, true);
                    let mut into = vec![0.0f32; f.len()];
                    prefilter_into(&f, &mut into, h, w, true);
                    let mut table = vec![f32::NAN; f.len()];
                    prefilter_channels_last(&f, &mut table, (n, c, h, w));
                    [forward, adjoint, into, table]
                })
            };
            let whole = run(1);
            for threads in [4, 64] {
                let split = run(threads);
                for (what, (a, b)) in ["P", "Pᵀ", "Pᵀ into", "channels-last P"]
                    .iter()
                    .zip(whole.iter().zip(&split))
                {
                    let same = a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits());
                    assert!(
                        same,
                        "{what}, {c} channels, {threads} threads: not the same bits"
                    );
                }
            }
        }
    }

    #[test]
    fn the_line_solve_is_the_dense_prefilter_and_its_transpose_the_adjoint() {
        for (h, w) in [(4, 4), (5, 9), (13, 7), (40, 33)] {
            let f = ramp(2 * h * w, 0.3);
            let mut c = f.clone();
            prefilter(&mut c, h, w, false);
            for p in 0..2 {
                let want = dense_prefilter(&f[p * h * w..(p + 1) * h * w], h, w);
                for (a, b) in c[p * h * w..(p + 1) * h * w].iter().zip(&want) {
                    assert!((a - b).abs() < 1e-12, "{h}x{w}: {a} vs {b}");
                }
            }
            // ⟨P f, g⟩ = ⟨f, Pᵀ g⟩.
            let g = ramp(2 * h * w, 1.7);
            let mut pt = g.clone();
            prefilter(&mut pt, h, w, true);
            let lhs: f64 = c.iter().zip(&g).map(|(a, b)| a * b).sum();
            let rhs: f64 = f.iter().zip(&pt).map(|(a, b)| a * b).sum();
            assert!(
                (lhs - rhs).abs() < 1e-10 * lhs.abs().max(1.0),
                "{lhs} vs {rhs}"
            );
        }
    }

    /// For few channels (planar reads) and many (channels-last, with a remainder after the
    /// 8-wide lanes of the dot products).
    #[test]
    fn the_adjoint_and_the_position_gradient_match_the_evaluation() {
        for c in [3, CHANNELS_LAST_FROM + 3] {
            adjoint_and_position_gradient_match(c);
        }
    }

    /// The evaluation writes every output value (the op hands it uninitialised memory):
    /// planar and channels-last, whole tasks and tiles and their remainders, from planar
    /// coefficients and from a channels-last table, each output first filled with NaN.
    #[test]
    fn the_evaluation_writes_every_value() {
        // 2 images of 40 × 31 points: a task of 1024 points and a remainder, tiles of 64
        // and a remainder.
        let (n, h, w) = (2, 40, 31);
        let phi: Vec<f64> = (0..n * 2 * h * w)
            .map(|i| (i as f64 * 0.377).rem_euclid(30.0) - 1.0)
            .collect();
        for c in [3, CHANNELS_LAST_FROM, 13] {
            let d = Dims {
                n,
                c,
                h,
                w,
                ho: h,
                wo: w,
            };
            let coeffs = ramp(n * c * h * w, 0.3);
            let mut out = vec![f64::NAN; n * c * h * w];
            sample(&coeffs, &phi, &mut out, d);
            assert!(out.iter().all(|v| v.is_finite()), "{c} planar channels");
            if !reads_channels_last(c) {
                continue;
            }
            let mut table = vec![0.0; coeffs.len()];
            for b in 0..n {
                let image = b * c * h * w..(b + 1) * c * h * w;
                channels_last_into(&coeffs[image.clone()], c, h * w, &mut table[image]);
            }
            let mut from_table = vec![f64::NAN; out.len()];
            sample_from_table(&table, c, &phi, &mut from_table, d);
            assert_eq!(from_table, out, "{c} channels from a channels-last table");
        }
    }

    /// The adjoint writes every output value (the op hands it uninitialised memory), on both
    /// of its paths: a task per group of planes (many planes), and partial planes added
    /// (fewer planes than twice the threads).
    #[test]
    fn the_adjoint_writes_every_value() {
        let (h, w) = (40, 31);
        for (n, c) in [(1, 1), (1, 3), (2, 11)] {
            let d = Dims {
                n,
                c,
                h,
                w,
                ho: h,
                wo: w,
            };
            let phi: Vec<f64> = (0..n * 2 * h * w)
                .map(|i| (i as f64 * 0.377).rem_euclid(30.0) - 1.0)
                .collect();
            let grad = ramp(n * c * h * w, 0.3);
            let run = |threads: usize| {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .expect("a thread pool");
                let mut out = vec![f64::NAN; n * c * h * w];
                pool.install(|| sample_adjoint(&grad, &phi, &mut out, d));
                out
            };
            let one = run(1);
            for threads in [2, 8] {
                let many = run(threads);
                for (i, (&x, &y)) in many.iter().zip(&one).enumerate() {
                    assert!(
                        (x - y).abs() <= 1e-12 * (1.0 + y.abs()),
                        "{n} × {c} planes, {threads} threads, value {i}: {x} against {y}"
                    );
                }
            }
        }
    }

    /// Two images of `c` channels, 9 × 11 coefficients sampled at 7 × 5 points.
    fn small_dims(c: usize) -> Dims {
        Dims {
            n: 2,
            c,
            h: 9,
            w: 11,
            ho: 7,
            wo: 5,
        }
    }

    /// The channels-last prefilter, and evaluations and position gradients read from its
    /// table (whole, or a block of channels of it), give the planar path's values bit for
    /// bit, in float32 where reordered arithmetic would show.
    #[test]
    fn channels_last_coefficients_are_the_planar_ones_bit_for_bit() {
        // Two images of 21 channels (a block of 3 + a block of 18), 13 × 10: line groups
        // that end inside an image, and column blocks of 256 values that end inside a row.
        let (n, c, h, w) = (2, 21, 13, 10);
        let (ho, wo) = (6, 7);
        let f: Vec<f32> = ramp(n * c * h * w, 0.2).iter().map(|&v| v as f32).collect();
        let mut planar = f.clone();
        prefilter(&mut planar, h, w, false);
        // NaN first: the op hands the prefilter uninitialised memory, every value is written.
        let mut table = vec![f32::NAN; f.len()];
        prefilter_channels_last(&f, &mut table, (n, c, h, w));
        for b in 0..n {
            let want = channels_last(&planar[b * c * h * w..(b + 1) * c * h * w], c, h * w);
            assert_eq!(
                &table[b * c * h * w..(b + 1) * c * h * w],
                &want[..],
                "image {b}"
            );
        }
        let phi: Vec<f32> = (0..n * 2 * ho * wo)
            .map(|i| ((i as f64 * 0.731).rem_euclid(14.0) - 1.5) as f32)
            .collect();
        for (start, len) in [(0, c), (3, c - 3), (1, CHANNELS_LAST_FROM)] {
            let d = Dims {
                n,
                c: len,
                h,
                w,
                ho,
                wo,
            };
            // The planar coefficients of the block, contiguous.
            let block: Vec<f32> = (0..n)
                .flat_map(|b| {
                    let at = (b * c + start) * h * w;
                    planar[at..at + len * h * w].to_vec()
                })
                .collect();
            let (mut want, mut got) = (
                vec![0.0f32; n * len * ho * wo],
                vec![1.0f32; n * len * ho * wo],
            );
            sample(&block, &phi, &mut want, d);
            sample_from_table(&table[start..], c, &phi, &mut got, d);
            assert_eq!(want, got, "evaluation of channels {start}..{}", start + len);
            let grad: Vec<f32> = ramp(want.len(), 0.9).iter().map(|&v| v as f32).collect();
            let (mut want, mut got) = (vec![0.0f32; phi.len()], vec![1.0f32; phi.len()]);
            sample_position_grad(&block, &phi, &grad, &mut want, d);
            position_grad_from_table(&table[start..], c, &phi, &grad, &mut got, d);
            assert_eq!(
                want,
                got,
                "position gradient of channels {start}..{}",
                start + len
            );
        }
    }

    /// Channels-last evaluation gives each plane what the planar one-channel kernel gives it.
    #[test]
    fn tiles_go_to_planes_as_the_definition_says() {
        // Whole 8 × 8 blocks, channels and points left over, in both precisions.
        fn check<T: Real + std::fmt::Debug>() {
            for (count, c) in [(64, 67), (35, 13), (8, 8), (5, 3)] {
                let plane = count + 3;
                let tile: Vec<T> = (0..count * c).map(|i| T::from_i32(i as i32)).collect();
                let mut out = vec![T::from_f64(-1.0); c * plane];
                // SAFETY: `out` holds `c` planes of `plane ≥ count` values.
                unsafe { tile_to_planes_simd(&tile, c, Shared(out.as_mut_ptr()), plane) };
                for ch in 0..c {
                    for i in 0..plane {
                        let want = if i < count {
                            tile[i * c + ch]
                        } else {
                            T::from_f64(-1.0)
                        };
                        assert_eq!(
                            out[ch * plane + i].to_f64(),
                            want.to_f64(),
                            "{count} × {c}: ({ch}, {i})"
                        );
                    }
                }
            }
        }
        check::<f32>();
        check::<f64>();
    }

    /// The blocked transpose is the definition, for channel and pixel counts that are and are
    /// not multiples of the block, and more pixels than a task.
    #[test]
    fn planes_go_channels_last_as_the_definition_says() {
        fn check<T: Real + std::fmt::Debug>() {
            for c in [1, 7, 8, 13, 67] {
                for plane in [5, 8, 1030, 2100] {
                    let planar: Vec<T> = (0..c * plane).map(|i| T::from_i32(i as i32)).collect();
                    let mut out = vec![T::from_i32(-1); c * plane];
                    channels_last_into(&planar, c, plane, &mut out);
                    for i in 0..plane {
                        for ch in 0..c {
                            assert_eq!(out[i * c + ch], planar[ch * plane + i], "{c} × {plane}");
                        }
                    }
                }
            }
        }
        check::<f32>();
        check::<f64>();
    }

    #[test]
    fn many_channels_evaluate_as_each_plane_alone() {
        // Channel counts that take each run width of the evaluation (8, 4, 2 and 1
        // registers) and a remainder.
        for c in [CHANNELS_LAST_FROM + 5, 30, 45, 67] {
            evaluate_as_each_plane_alone(c);
        }
    }

    fn evaluate_as_each_plane_alone(c: usize) {
        let d = small_dims(c);
        let coeffs = ramp(d.n * c * d.h * d.w, 0.4);
        let phi: Vec<f64> = (0..d.n * 2 * d.ho * d.wo)
            .map(|i| (i as f64 * 0.731).rem_euclid(12.0) - 1.0)
            .collect();
        let mut all = vec![0.0; d.n * c * d.ho * d.wo];
        sample(&coeffs, &phi, &mut all, d);
        let one = Dims { n: 1, c: 1, ..d };
        let (plane, points) = (d.h * d.w, d.ho * d.wo);
        for b in 0..d.n {
            let phi_b = &phi[b * 2 * points..(b + 1) * 2 * points];
            for ch in 0..c {
                let at = b * c + ch;
                let mut alone = vec![0.0; points];
                sample(
                    &coeffs[at * plane..(at + 1) * plane],
                    phi_b,
                    &mut alone,
                    one,
                );
                for (x, y) in all[at * points..(at + 1) * points].iter().zip(&alone) {
                    assert!((x - y).abs() < 1e-13, "image {b}, channel {ch}: {x} vs {y}");
                }
            }
        }
    }

    fn adjoint_and_position_gradient_match(c: usize) {
        let d = small_dims(c);
        let coeffs = ramp(d.n * d.c * d.h * d.w, 0.1);
        // Points inside and outside the clamp range, and on grid lines.
        let phi: Vec<f64> = (0..d.n * 2 * d.ho * d.wo)
            .map(|i| {
                let axis = (i / (d.ho * d.wo)) % 2;
                let hi = if axis == 0 { 8.0 } else { 10.0 };
                (i as f64 * 1.618).rem_euclid(hi + 3.0) - 1.5 + if i % 7 == 0 { 0.0 } else { 0.25 }
            })
            .collect();
        let g = ramp(d.n * d.c * d.ho * d.wo, 2.2);
        let mut t = vec![0.0; g.len()];
        sample(&coeffs, &phi, &mut t, d);
        let mut adj = vec![0.0; coeffs.len()];
        sample_adjoint(&g, &phi, &mut adj, d);
        let lhs: f64 = t.iter().zip(&g).map(|(a, b)| a * b).sum();
        let rhs: f64 = coeffs.iter().zip(&adj).map(|(a, b)| a * b).sum();
        assert!((lhs - rhs).abs() < 1e-10 * lhs.abs(), "{lhs} vs {rhs}");

        let mut grad = vec![0.0; phi.len()];
        sample_position_grad(&coeffs, &phi, &g, &mut grad, d);
        let value = |phi: &[f64]| {
            let mut t = vec![0.0; g.len()];
            sample(&coeffs, phi, &mut t, d);
            t.iter().zip(&g).map(|(a, b)| a * b).sum::<f64>()
        };
        let h = 1e-6;
        for i in 0..phi.len() {
            let frac = phi[i] - phi[i].floor();
            let axis_hi = if (i / (d.ho * d.wo)) % 2 == 0 {
                8.0
            } else {
                10.0
            };
            if frac.min(1.0 - frac) < 1e-3 || (phi[i] + h > axis_hi && phi[i] - h < axis_hi) {
                continue; // a kink of the clamp or of a weight's branch
            }
            let (mut up, mut down) = (phi.clone(), phi.clone());
            up[i] += h;
            down[i] -= h;
            let fd = (value(&up) - value(&down)) / (2.0 * h);
            assert!(
                (fd - grad[i]).abs() < 1e-6 * (1.0 + fd.abs()),
                "φ[{i}]: {fd} vs {}",
                grad[i]
            );
        }
    }

    #[test]
    fn the_adjoint_splits_few_planes_without_changing_the_sum() {
        let d = Dims {
            n: 1,
            c: 1,
            h: 64,
            w: 64,
            ho: 64,
            wo: 64,
        };
        let phi: Vec<f64> = (0..2 * 64 * 64)
            .map(|i| {
                let (axis, p) = (i / 4096, i % 4096);
                let v = if axis == 0 { p / 64 } else { p % 64 } as f64;
                v + 0.3 * ((p as f64) * 0.01).sin()
            })
            .collect();
        let g = ramp(4096, 0.5);
        let mut out = vec![0.0; 4096];
        sample_adjoint(&g, &phi, &mut out, d);
        // Against a plain sequential scatter.
        let mut want = vec![0.0; 4096];
        for (p, rows, cols) in Points::new(&phi, &d, 0, 0..4096) {
            let (offset, weight) = stencil::<f64>(&rows, &cols, 64);
            for k in 0..16 {
                want[offset[k]] += weight[k] * g[p];
            }
        }
        for (a, b) in out.iter().zip(&want) {
            assert!((a - b).abs() < 1e-12);
        }
    }
}
