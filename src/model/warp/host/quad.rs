//! The spline's evaluation and its adjoint for a few channels (RGB's 3, or 4) through quad
//! tables: each pixel's channels side by side, padded with zeros to four.
//!
//! Planar, a point's 4 × 4 stencil is, per channel, four loads of four contiguous columns, a
//! sum down the rows and a sum across them: three times for RGB, each ending in a horizontal
//! sum (the 3-channel evaluation was a third of an RGB sweep at 256²). From a quad table a row
//! of the stencil is 16 contiguous values, all channels of its four columns: two AVX registers
//! per row, the sums down the rows for every channel at once, and one fold across columns
//! at the end ([`SplineReal::quad_block`]). Building the table is one pass over the coefficients
//! per call. The adjoint adds every channel of a point at once into private quad tables
//! ([`SplineReal::quad_scatter`]), where the planar scatter set each point up once per channel.
//! The position gradient stays planar: an RGB sweep takes its deformation gradients from
//! the image's slopes, not from this op.
//!
//! Every sum is the planar kernels' in the same order (no fused multiply-adds), so the
//! values are the same bits (tested).

use std::mem::MaybeUninit;
use std::ops::Range;

use rayon::prelude::*;

use super::{
    Axis, AxisLanes, Dims, LANES, PIXELS_PER_TASK, Shared, SplineReal, contiguous,
    deformation_planes, simd_dispatch, stencil as stencil_offsets, zeros,
};

/// Channels per pixel of a quad table.
pub(super) const QUAD: usize = 4;

/// Whether the planar entry points evaluate `c` channels through a quad table (1 and 2
/// channels would be mostly padding).
pub(super) fn reads_quads(c: usize) -> bool {
    (3..=QUAD).contains(&c)
}

/// The planar coefficients `[N, C, H, W]` (`C ≤ 4`) as quad tables `[N, H, W, 4]`, the
/// channels from `C` on zero.
fn table<T: SplineReal>(planar: &[T], d: &Dims) -> Vec<T> {
    let plane = d.h * d.w;
    let mut table = Vec::with_capacity(d.n * plane * QUAD);
    let tasks = plane.div_ceil(PIXELS_PER_TASK);
    let out = Shared(table.spare_capacity_mut().as_mut_ptr().cast::<T>());
    (0..d.n * tasks).into_par_iter().for_each(|task| {
        let (b, chunk) = (task / tasks, task % tasks);
        let pixels = chunk * PIXELS_PER_TASK..((chunk + 1) * PIXELS_PER_TASK).min(plane);
        let image = &planar[b * d.c * plane..(b + 1) * d.c * plane];
        for i in pixels {
            let mut quad = [T::default(); QUAD];
            for (ch, q) in quad[..d.c].iter_mut().enumerate() {
                *q = image[ch * plane + i];
            }
            for (k, &q) in quad.iter().enumerate() {
                // SAFETY: pixel i of image b is this task's alone and within the capacity.
                unsafe { out.write((b * plane + i) * QUAD + k, q) };
            }
        }
    });
    // SAFETY: the tasks wrote every quad of every image.
    unsafe { table.set_len(d.n * plane * QUAD) };
    table
}

/// `Σ_b wc[b] · (Σ_a wr[a] · table[(rows[a] + j0 + b)·4 + ch])` for each channel `ch`: a
/// stencil whose four columns `j0 …` are contiguous. Down the rows in order, then across
/// the columns as two independent pairs: the planar kernel's `sum4(wc, down_rows(…, wr))`.
#[inline(always)]
fn stencil<T: SplineReal>(
    table: &[T],
    rows: &[usize; 4],
    j0: usize,
    wr: &[T; 4],
    wc: &[T; 4],
) -> [T; QUAD] {
    let mut v = [T::default(); 16];
    for a in 0..4 {
        let at = (rows[a] + j0) * QUAD;
        let run: &[T; 16] = table[at..at + 16].try_into().expect("four quads");
        for k in 0..16 {
            v[k] += wr[a] * run[k];
        }
    }
    let mut s = [T::default(); QUAD];
    for ch in 0..QUAD {
        s[ch] = (wc[0] * v[ch] + wc[1] * v[QUAD + ch])
            + (wc[2] * v[2 * QUAD + ch] + wc[3] * v[3 * QUAD + ch]);
    }
    s
}

/// The axes of a block of `LANES` points: their four indices and weights along the axis,
/// structure of arrays (as `AxisLanes` holds them).
pub type BlockAxis<'a, T> = (&'a [[u32; LANES]; 4], &'a [[T; LANES]; 4]);

/// [`stencil`] of float32 for the first `n` points of a block whose columns are contiguous,
/// in AVX registers, into `block[l]`; returns the mask of the lanes done (the others' columns
/// the mirror folded). A row's 16 values are two registers; the fold across columns
/// multiplies each register by its two column weights and adds its halves. The same
/// operations in the same order as [`stencil`], so the same bits. The weights are read from
/// the block's arrays one broadcast at a time: copied per point into small arrays (the
/// generic kernel's `Axis`), the compiler stored them as scalars and reloaded them as a
/// vector, a store-forwarding stall on every point.
///
/// # Safety
///
/// The CPU has AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn block_avx(
    table: &[f32],
    w: usize,
    rows: BlockAxis<'_, f32>,
    cols: BlockAxis<'_, f32>,
    n: usize,
    block: &mut [[f32; QUAD]; LANES],
) -> u32 {
    use std::arch::x86_64::*;
    let mut done = 0;
    for l in 0..n.min(LANES) {
        let j0 = cols.0[0][l] as usize;
        if cols.0[3][l] as usize != j0 + 3 {
            continue;
        }
        let (mut left, mut right) = (_mm256_setzero_ps(), _mm256_setzero_ps());
        for a in 0..4 {
            let at = (rows.0[a][l] as usize * w + j0) * QUAD;
            let run: &[f32; 16] = table[at..at + 16].try_into().expect("four quads");
            let wa = _mm256_set1_ps(rows.1[a][l]);
            // SAFETY: `run` holds 16 values: two loads of 8.
            let (x, y) = unsafe {
                (
                    _mm256_loadu_ps(run.as_ptr()),
                    _mm256_loadu_ps(run.as_ptr().add(8)),
                )
            };
            left = _mm256_add_ps(left, _mm256_mul_ps(wa, x));
            right = _mm256_add_ps(right, _mm256_mul_ps(wa, y));
        }
        let pair = |k: usize, v: __m256| {
            let wk = _mm256_setr_m128(_mm_set1_ps(cols.1[k][l]), _mm_set1_ps(cols.1[k + 1][l]));
            let p = _mm256_mul_ps(wk, v);
            _mm_add_ps(_mm256_castps256_ps128(p), _mm256_extractf128_ps::<1>(p))
        };
        let s = _mm_add_ps(pair(0, left), pair(2, right));
        // SAFETY: `block[l]` holds four values.
        unsafe { _mm_storeu_ps(block[l].as_mut_ptr(), s) };
        done |= 1 << l;
    }
    done
}

/// `Σ_b weight[b] · line[index[b]·4 + ch]` per channel, as two independent pairs: a row of a
/// stencil whose columns the mirror folded (the planar kernel's `dot4`).
#[inline(always)]
fn folded_row<T: SplineReal>(line: &[T], index: &[usize; 4], weight: &[T; 4]) -> [T; QUAD] {
    let at = |k: usize| -> &[T; QUAD] {
        line[index[k] * QUAD..index[k] * QUAD + QUAD]
            .try_into()
            .expect("a quad")
    };
    let (q0, q1, q2, q3) = (at(0), at(1), at(2), at(3));
    let mut s = [T::default(); QUAD];
    for ch in 0..QUAD {
        s[ch] =
            (weight[0] * q0[ch] + weight[1] * q1[ch]) + (weight[2] * q2[ch] + weight[3] * q3[ch]);
    }
    s
}

/// Runs `kernel` over the points of every image in tasks of [`PIXELS_PER_TASK`].
fn for_each_task(d: &Dims, kernel: impl Fn(usize, Range<usize>) + Sync) {
    let points = d.points();
    let tasks = points.div_ceil(PIXELS_PER_TASK);
    (0..d.n * tasks).into_par_iter().for_each(|task| {
        let (b, chunk) = (task / tasks, task % tasks);
        kernel(
            b,
            chunk * PIXELS_PER_TASK..((chunk + 1) * PIXELS_PER_TASK).min(points),
        );
    });
}

/// [`super::sample`] for 3 or 4 channels: writes every value of `out`.
pub(super) fn sample<T: SplineReal>(coeffs: &[T], phi: &[T], out: &mut [MaybeUninit<T>], d: Dims) {
    let table = table(coeffs, &d);
    let out = Shared(out.as_mut_ptr().cast::<T>());
    for_each_task(&d, |b, points| {
        sample_at_simd(&table, phi, out, d, b, points)
    });
}

/// [`sample`] at the points `points` of image `b`, a block of [`LANES`] points at a time:
/// [`SplineReal::quad_block`] first, then the generic sums for the lanes it left.
#[inline(always)]
fn sample_at<T: SplineReal>(
    table: &[T],
    phi: &[T],
    out: Shared<T>,
    d: Dims,
    b: usize,
    points: Range<usize>,
) {
    let (plane, count) = (d.h * d.w, d.points());
    let table = &table[b * plane * QUAD..(b + 1) * plane * QUAD];
    let planes = deformation_planes(phi, &d, b);
    let mut block = [[T::default(); QUAD]; LANES];
    for first in points.clone().step_by(LANES) {
        let n = LANES.min(points.end - first);
        let (rows, cols) = AxisLanes::block(planes, first, n, d.h, d.w);
        let done = T::quad_block(
            table,
            d.w,
            (&rows.index, &rows.weight),
            (&cols.index, &cols.weight),
            n,
            &mut block,
        );
        for (l, value) in block[..n].iter_mut().enumerate() {
            if done & (1 << l) == 0 {
                *value = generic_lane(table, d.w, &rows.lane(l), &cols.lane(l));
            }
        }
        for ch in 0..d.c {
            for (l, value) in block[..n].iter().enumerate() {
                // SAFETY: the block's points of image b are the calling task's alone.
                unsafe { out.write((b * d.c + ch) * count + first + l, value[ch]) };
            }
        }
    }
}

/// The stencil of one point by the generic sums: [`stencil`] where its columns are
/// contiguous, else row by row through the mirror's indices.
#[inline(always)]
fn generic_lane<T: SplineReal>(table: &[T], w: usize, rows: &Axis<T>, cols: &Axis<T>) -> [T; QUAD] {
    let (wr, wc) = (&rows.weight, &cols.weight);
    if let Some((ro, j0)) = contiguous(rows, cols, w) {
        return stencil(table, &ro, j0, wr, wc);
    }
    let row = |a: usize| folded_row(&table[rows.index[a] * w * QUAD..], &cols.index, wc);
    let (r0, r1, r2, r3) = (row(0), row(1), row(2), row(3));
    let mut s = [T::default(); QUAD];
    for ch in 0..QUAD {
        s[ch] = (wr[0] * r0[ch] + wr[1] * r1[ch]) + (wr[2] * r2[ch] + wr[3] * r3[ch]);
    }
    s
}

simd_dispatch!(fn sample_at_simd<T: SplineReal>(
    table: &[T], phi: &[T], out: Shared<T>, d: Dims, b: usize, points: Range<usize>
) => sample_at);

/// `B(φ)ᵀ g` for 3 or 4 channels whose points [`super::sample_adjoint`] splits into `parts`
/// per image (few planes: the sequential schedule's frames): each part scatters every
/// channel of its points into a private quad table, and the parts are summed in order into
/// the planar `out`. The planar scatter ran one channel per task, so each point's setup was
/// computed once per channel; here once. Same sums in the same order as the planar path
/// (its parts split the points the same way), so the same bits.
pub(super) fn adjoint<T: SplineReal>(
    grad: &[T],
    phi: &[T],
    out: &mut [MaybeUninit<T>],
    d: Dims,
    parts: usize,
) {
    let (points, plane) = (d.points(), d.h * d.w);
    let per_part = points.div_ceil(parts);
    let mut tables = zeros(d.n * parts * plane * QUAD);
    tables
        .par_chunks_mut(plane * QUAD)
        .enumerate()
        .for_each(|(task, table)| {
            let (b, part) = (task / parts, task % parts);
            let range = part * per_part..((part + 1) * per_part).min(points);
            scatter_simd(grad, phi, table, d, b, range);
        });
    let tasks = plane.div_ceil(PIXELS_PER_TASK);
    let out = Shared(out.as_mut_ptr().cast::<T>());
    (0..d.n * tasks).into_par_iter().for_each(|task| {
        let (b, chunk) = (task / tasks, task % tasks);
        let pixels = chunk * PIXELS_PER_TASK..((chunk + 1) * PIXELS_PER_TASK).min(plane);
        let image = &tables[b * parts * plane * QUAD..(b + 1) * parts * plane * QUAD];
        for ch in 0..d.c {
            for i in pixels.clone() {
                let mut sum = image[i * QUAD + ch];
                for part in 1..parts {
                    sum += image[(part * plane + i) * QUAD + ch];
                }
                // SAFETY: pixel i of image b is this task's alone, in every channel's plane.
                unsafe { out.write((b * d.c + ch) * plane + i, sum) };
            }
        }
    });
}

/// Adds `B(φ)ᵀ g` of the points `points` of image `b` into the quad `table`, a block of
/// [`LANES`] points at a time: [`SplineReal::quad_scatter`] as far as it goes, the generic sums for
/// a lane it stops at, in point order (the order of the adds into shared coefficients).
#[inline(always)]
fn scatter<T: SplineReal>(
    grad: &[T],
    phi: &[T],
    table: &mut [T],
    d: Dims,
    b: usize,
    points: Range<usize>,
) {
    let count = d.points();
    let planes = deformation_planes(phi, &d, b);
    let mut values = [[T::default(); QUAD]; LANES];
    for first in points.clone().step_by(LANES) {
        let n = LANES.min(points.end - first);
        let (rows, cols) = AxisLanes::block(planes, first, n, d.h, d.w);
        for ch in 0..d.c {
            let g = &grad[(b * d.c + ch) * count + first..(b * d.c + ch) * count + first + n];
            for (value, &g) in values.iter_mut().zip(g) {
                value[ch] = g;
            }
        }
        let mut l = 0;
        while l < n {
            l = T::quad_scatter(
                table,
                d.w,
                (&rows.index, &rows.weight),
                (&cols.index, &cols.weight),
                l..n,
                &values,
            );
            if l < n {
                scatter_lane(table, d.w, &rows.lane(l), &cols.lane(l), &values[l]);
                l += 1;
            }
        }
    }
}

simd_dispatch!(fn scatter_simd<T: SplineReal>(
    grad: &[T], phi: &[T], table: &mut [T], d: Dims, b: usize, points: Range<usize>
) => scatter);

/// Adds one point's `values` into the quad `table` by the generic sums: the planar scatter's
/// per channel (`(wr·v)·wc` down four contiguous columns, else `(wr·wc)·v` through the
/// mirror's indices).
#[inline(always)]
fn scatter_lane<T: SplineReal>(
    table: &mut [T],
    w: usize,
    rows: &Axis<T>,
    cols: &Axis<T>,
    values: &[T; QUAD],
) {
    let (wr, wc) = (&rows.weight, &cols.weight);
    if let Some((ro, j0)) = contiguous(rows, cols, w) {
        for a in 0..4 {
            let at = (ro[a] + j0) * QUAD;
            let run: &mut [T; 16] = (&mut table[at..at + 16]).try_into().expect("four quads");
            for ch in 0..QUAD {
                let s = wr[a] * values[ch];
                for k in 0..4 {
                    run[k * QUAD + ch] += s * wc[k];
                }
            }
        }
        return;
    }
    let (offset, weight) = stencil_offsets(rows, cols, w);
    for k in 0..16 {
        for ch in 0..QUAD {
            table[offset[k] * QUAD + ch] += weight[k] * values[ch];
        }
    }
}

/// Adds the `values` of the lanes `lanes` of a block into the quad `table` in AVX registers,
/// in lane order, until a lane whose columns the mirror folded; returns the first lane not
/// done. Per value the planar scatter's `(wr·v)·wc`, so the same bits.
///
/// # Safety
///
/// The CPU has AVX2.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx2")]
pub(super) unsafe fn scatter_avx(
    table: &mut [f32],
    w: usize,
    rows: BlockAxis<'_, f32>,
    cols: BlockAxis<'_, f32>,
    lanes: Range<usize>,
    values: &[[f32; QUAD]; LANES],
) -> usize {
    use std::arch::x86_64::*;
    for l in lanes.start..lanes.end.min(LANES) {
        let j0 = cols.0[0][l] as usize;
        if cols.0[3][l] as usize != j0 + 3 {
            return l;
        }
        // SAFETY: `values[l]` holds four values.
        let v = unsafe { _mm_loadu_ps(values[l].as_ptr()) };
        let columns =
            |k: usize| _mm256_setr_m128(_mm_set1_ps(cols.1[k][l]), _mm_set1_ps(cols.1[k + 1][l]));
        let (left, right) = (columns(0), columns(2));
        for a in 0..4 {
            let at = (rows.0[a][l] as usize * w + j0) * QUAD;
            let run: &mut [f32; 16] = (&mut table[at..at + 16]).try_into().expect("four quads");
            let s = _mm_mul_ps(_mm_set1_ps(rows.1[a][l]), v);
            let s = _mm256_setr_m128(s, s);
            let ptr = run.as_mut_ptr();
            // SAFETY: `run` holds 16 values: two loads and stores of 8.
            unsafe {
                let x = _mm256_add_ps(_mm256_loadu_ps(ptr), _mm256_mul_ps(s, left));
                let y = _mm256_add_ps(_mm256_loadu_ps(ptr.add(8)), _mm256_mul_ps(s, right));
                _mm256_storeu_ps(ptr, x);
                _mm256_storeu_ps(ptr.add(8), y);
            }
        }
    }
    lanes.end
}

#[cfg(test)]
mod tests {
    use super::super::sample_planar;
    use super::*;

    /// The quad adjoint is the planar scatter's, bit for bit: per plane, each part of the
    /// points scattered into zeros, the parts summed in order (float32 through the AVX2
    /// kernel, float64 through the generic sums), with points on the mirror's folds and
    /// parts that end inside a block.
    #[test]
    fn the_quad_adjoint_is_the_planar_scatter_bit_for_bit() {
        adjoint_check::<f32>(|x| u64::from(x.to_bits()));
        adjoint_check::<f64>(f64::to_bits);
    }

    fn adjoint_check<T: SplineReal + std::fmt::Debug>(bits: fn(T) -> u64) {
        let (d, phi) = dims_and_points::<T>(3);
        let grad = ramp::<T>(d.n * d.c * d.points(), 1.1);
        let plane = d.h * d.w;
        for parts in [1, 2, 3] {
            let mut quads = vec![MaybeUninit::new(T::from_f64(f64::NAN)); d.n * d.c * plane];
            adjoint(&grad, &phi, &mut quads, d, parts);
            // SAFETY: the adjoint writes every value.
            let quads: Vec<T> = quads.iter().map(|v| unsafe { v.assume_init() }).collect();
            let per_part = d.points().div_ceil(parts);
            for b in 0..d.n {
                for ch in 0..d.c {
                    let mut want = vec![T::default(); plane];
                    for part in 0..parts {
                        let mut partial = vec![T::default(); plane];
                        let range = part * per_part..((part + 1) * per_part).min(d.points());
                        super::super::scatter(&grad, &phi, &mut partial, d, b, ch..ch + 1, range);
                        for (w, p) in want.iter_mut().zip(&partial) {
                            *w = if part == 0 { *p } else { *w + *p };
                        }
                    }
                    let at = (b * d.c + ch) * plane;
                    let got: Vec<u64> = quads[at..at + plane].iter().map(|&x| bits(x)).collect();
                    let want: Vec<u64> = want.iter().map(|&x| bits(x)).collect();
                    assert_eq!(got, want, "{parts} parts, image {b}, channel {ch}");
                }
            }
        }
    }

    fn ramp<T: SplineReal>(n: usize, seed: f64) -> Vec<T> {
        (0..n)
            .map(|i| T::from_f64((i as f64 * 0.37 + seed).sin() + 0.1 * i as f64 % 3.0))
            .collect()
    }

    /// Two images of `c` channels, 23 × 29 coefficients sampled at 41 × 37 points inside,
    /// outside and on the edges of the clamp range.
    fn dims_and_points<T: SplineReal>(c: usize) -> (Dims, Vec<T>) {
        let d = Dims {
            n: 2,
            c,
            h: 23,
            w: 29,
            ho: 41,
            wo: 37,
        };
        let phi = (0..d.n * 2 * d.points())
            .map(|i| {
                let hi = if (i / d.points()).is_multiple_of(2) {
                    d.h
                } else {
                    d.w
                } as f64;
                T::from_f64((i as f64 * 0.618).rem_euclid(hi + 4.0) - 2.0)
            })
            .collect();
        (d, phi)
    }

    /// Three and four channels go through quad tables: the same sums in the same order as
    /// the planar kernel, so the same bits, in float32 (the AVX2 kernel) where reordered
    /// arithmetic would show and in float64 (the generic sums); at points inside, outside and
    /// on the edges of the clamp range (contiguous and folded stencils), with more points
    /// than a task and a last block shorter than [`LANES`].
    #[test]
    fn quads_are_the_planar_kernel_bit_for_bit() {
        check::<f32>(|x| u64::from(x.to_bits()));
        check::<f64>(f64::to_bits);
    }

    fn check<T: SplineReal + std::fmt::Debug>(bits: fn(T) -> u64) {
        for c in [3, 4] {
            let (d, phi) = dims_and_points::<T>(c);
            let coeffs = ramp::<T>(d.n * c * d.h * d.w, 0.3);
            let len = d.n * c * d.points();
            let nan = T::from_f64(f64::NAN);
            let (mut quads, mut planar) = (vec![nan; len], vec![nan; len]);
            super::super::sample(&coeffs, &phi, &mut quads, d);
            for b in 0..d.n {
                let out = Shared(planar.as_mut_ptr());
                sample_planar(&coeffs, &phi, out, d, b, 0..d.points());
            }
            let bits = |v: &[T]| v.iter().map(|&x| bits(x)).collect::<Vec<_>>();
            assert_eq!(bits(&quads), bits(&planar), "{c} channels");
        }
    }
}
