//! The spline's evaluation and position gradient for a few channels (RGB's 3, or 4) through a
//! quad table: each pixel's channels side by side, padded with zeros to four.
//!
//! Planar, a point's 4 × 4 stencil is, per channel, four loads of four contiguous columns, a
//! sum down the rows and a sum across them: three times for RGB, each ending in a horizontal
//! sum (the 3-channel evaluation was a third of an RGB sweep at 256²). From a quad table a row
//! of the stencil is 16 contiguous values, all channels of its four columns: two AVX registers
//! per row, the sums down the rows for every channel at once, and one fold across columns
//! at the end ([`Real::quad_stencil`]). Building the table is one pass over the coefficients
//! per call.
//!
//! Every sum is the planar kernels' in the same order (no fused multiply-adds), so the
//! values are the same bits (tested).

use std::mem::MaybeUninit;
use std::ops::Range;

use rayon::prelude::*;

use super::{Dims, PIXELS_PER_TASK, Points, Real, Shared, contiguous, has_avx2, simd_dispatch};

/// Channels per pixel of a quad table.
pub(super) const QUAD: usize = 4;

/// Whether the planar entry points evaluate `c` channels through a quad table (1 and 2
/// channels would be mostly padding).
pub(super) fn reads_quads(c: usize) -> bool {
    (3..=QUAD).contains(&c)
}

/// The planar coefficients `[N, C, H, W]` (`C ≤ 4`) as quad tables `[N, H, W, 4]`, the
/// channels from `C` on zero.
fn table<T: Real>(planar: &[T], d: &Dims) -> Vec<T> {
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
pub(super) fn stencil<T: Real>(
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

/// [`stencil`] of float32 in AVX registers: a row's 16 values are two registers, and the
/// fold across columns multiplies each register by its two column weights and adds its
/// halves. The same operations in the same order, so the same bits (the compiler had
/// turned the generic loops into 128-bit shuffles, and reloaded the weights it had just
/// stored as scalars as a vector: a store-forwarding stall on every point).
///
/// # Safety
///
/// The CPU has AVX.
#[cfg(target_arch = "x86_64")]
#[inline]
#[target_feature(enable = "avx")]
pub(super) unsafe fn stencil_avx(
    table: &[f32],
    rows: &[usize; 4],
    j0: usize,
    wr: &[f32; 4],
    wc: &[f32; 4],
) -> [f32; QUAD] {
    use std::arch::x86_64::*;
    let (mut left, mut right) = (_mm256_setzero_ps(), _mm256_setzero_ps());
    for a in 0..4 {
        let at = (rows[a] + j0) * QUAD;
        let run: &[f32; 16] = table[at..at + 16].try_into().expect("four quads");
        let w = _mm256_set1_ps(wr[a]);
        // SAFETY: `run` holds 16 values: two loads of 8.
        let (x, y) = unsafe {
            (
                _mm256_loadu_ps(run.as_ptr()),
                _mm256_loadu_ps(run.as_ptr().add(8)),
            )
        };
        left = _mm256_add_ps(left, _mm256_mul_ps(w, x));
        right = _mm256_add_ps(right, _mm256_mul_ps(w, y));
    }
    let pair = |w0: f32, w1: f32, v: __m256| {
        let p = _mm256_mul_ps(_mm256_setr_m128(_mm_set1_ps(w0), _mm_set1_ps(w1)), v);
        _mm_add_ps(_mm256_castps256_ps128(p), _mm256_extractf128_ps::<1>(p))
    };
    let s = _mm_add_ps(pair(wc[0], wc[1], left), pair(wc[2], wc[3], right));
    let mut out = [0.0; QUAD];
    // SAFETY: `out` holds four values.
    unsafe { _mm_storeu_ps(out.as_mut_ptr(), s) };
    out
}

/// `Σ_b weight[b] · line[index[b]·4 + ch]` per channel, as two independent pairs: a row of a
/// stencil whose columns the mirror folded (the planar kernel's `dot4`).
#[inline(always)]
fn folded_row<T: Real>(line: &[T], index: &[usize; 4], weight: &[T; 4]) -> [T; QUAD] {
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
pub(super) fn sample<T: Real>(coeffs: &[T], phi: &[T], out: &mut [MaybeUninit<T>], d: Dims) {
    let table = table(coeffs, &d);
    let out = Shared(out.as_mut_ptr().cast::<T>());
    for_each_task(&d, |b, points| {
        sample_at_simd(&table, phi, out, d, b, points)
    });
}

/// [`sample`] at the points `points` of image `b`.
#[inline(always)]
fn sample_at<T: Real>(
    table: &[T],
    phi: &[T],
    out: Shared<T>,
    d: Dims,
    b: usize,
    points: Range<usize>,
) {
    let (plane, count) = (d.h * d.w, d.points());
    let table = &table[b * plane * QUAD..(b + 1) * plane * QUAD];
    for (p, rows, cols) in Points::new(phi, &d, b, points) {
        let (wr, wc) = (&rows.weight, &cols.weight);
        let value = if let Some((ro, j0)) = contiguous(&rows, &cols, d.w) {
            T::quad_stencil(table, &ro, j0, wr, wc)
        } else {
            let row = |a: usize| folded_row(&table[rows.index[a] * d.w * QUAD..], &cols.index, wc);
            let (r0, r1, r2, r3) = (row(0), row(1), row(2), row(3));
            let mut s = [T::default(); QUAD];
            for ch in 0..QUAD {
                s[ch] = (wr[0] * r0[ch] + wr[1] * r1[ch]) + (wr[2] * r2[ch] + wr[3] * r3[ch]);
            }
            s
        };
        for (ch, &v) in value[..d.c].iter().enumerate() {
            // SAFETY: point p of image b is the calling task's alone.
            unsafe { out.write((b * d.c + ch) * count + p, v) };
        }
    }
}

simd_dispatch!(fn sample_at_simd<T: Real>(
    table: &[T], phi: &[T], out: Shared<T>, d: Dims, b: usize, points: Range<usize>
) => sample_at);

/// [`super::sample_position_grad`] for 3 or 4 channels.
pub(super) fn position_grad<T: Real>(coeffs: &[T], phi: &[T], grad: &[T], out: &mut [T], d: Dims) {
    let table = table(coeffs, &d);
    let out = Shared(out.as_mut_ptr());
    for_each_task(&d, |b, points| {
        position_grad_at_simd(&table, phi, grad, out, d, b, points)
    });
}

/// [`position_grad`] at the points `points` of image `b`.
#[inline(always)]
fn position_grad_at<T: Real>(
    table: &[T],
    phi: &[T],
    grad: &[T],
    out: Shared<T>,
    d: Dims,
    b: usize,
    points: Range<usize>,
) {
    let (plane, count) = (d.h * d.w, d.points());
    let table = &table[b * plane * QUAD..(b + 1) * plane * QUAD];
    for (p, rows, cols) in Points::new(phi, &d, b, points) {
        let (wr, sr) = (&rows.weight, &rows.slope);
        let (wc, sc) = (&cols.weight, &cols.slope);
        // ∂/∂p₀ = Σ_a β'_a (Σ_b β_b c_ab), ∂/∂p₁ = Σ_a β_a (Σ_b β'_b c_ab), per channel.
        let (t0, t1) = if let Some((ro, j0)) = contiguous(&rows, &cols, d.w) {
            (
                T::quad_stencil(table, &ro, j0, sr, wc),
                T::quad_stencil(table, &ro, j0, wr, sc),
            )
        } else {
            let (mut t0, mut t1) = ([T::default(); QUAD], [T::default(); QUAD]);
            for a in 0..4 {
                let line = &table[rows.index[a] * d.w * QUAD..];
                let (u, v) = (
                    folded_row(line, &cols.index, wc),
                    folded_row(line, &cols.index, sc),
                );
                for ch in 0..QUAD {
                    t0[ch] += sr[a] * u[ch];
                    t1[ch] += wr[a] * v[ch];
                }
            }
            (t0, t1)
        };
        let (mut g0, mut g1) = (T::default(), T::default());
        for ch in 0..d.c {
            let g = grad[(b * d.c + ch) * count + p];
            g0 += g * t0[ch];
            g1 += g * t1[ch];
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

simd_dispatch!(fn position_grad_at_simd<T: Real>(
    table: &[T], phi: &[T], grad: &[T], out: Shared<T>, d: Dims, b: usize, points: Range<usize>
) => position_grad_at);

#[cfg(test)]
mod tests {
    use super::super::{position_grad_planar, sample_planar, sample_position_grad};
    use super::*;

    /// Three and four channels go through quad tables: the same sums in the same order as
    /// the planar kernels, so the same bits, in float32 where reordered arithmetic would
    /// show; at points inside, outside and on the edges of the clamp range (both the
    /// contiguous and the folded stencils), with more points than a task.
    #[test]
    fn quads_are_the_planar_kernels_bit_for_bit() {
        let ramp = |n: usize, seed: f64| -> Vec<f32> {
            (0..n)
                .map(|i| ((i as f64 * 0.37 + seed).sin() + 0.1 * i as f64 % 3.0) as f32)
                .collect()
        };
        for c in [3, 4] {
            let d = Dims {
                n: 2,
                c,
                h: 23,
                w: 29,
                ho: 41,
                wo: 37,
            };
            let coeffs = ramp(d.n * c * d.h * d.w, 0.3);
            let phi: Vec<f32> = (0..d.n * 2 * d.points())
                .map(|i| {
                    let hi = if (i / d.points()) % 2 == 0 { d.h } else { d.w } as f64;
                    ((i as f64 * 0.618).rem_euclid(hi + 4.0) - 2.0) as f32
                })
                .collect();
            let g = ramp(d.n * c * d.points(), 1.7);
            let (mut quads, mut planar) = (vec![0f32; g.len()], vec![f32::NAN; g.len()]);
            super::super::sample(&coeffs, &phi, &mut quads, d);
            let (mut quad_grad, mut planar_grad) =
                (vec![0f32; phi.len()], vec![f32::NAN; phi.len()]);
            sample_position_grad(&coeffs, &phi, &g, &mut quad_grad, d);
            for b in 0..d.n {
                let all = 0..d.points();
                sample_planar(
                    &coeffs,
                    &phi,
                    Shared(planar.as_mut_ptr()),
                    d,
                    b,
                    all.clone(),
                );
                let out = Shared(planar_grad.as_mut_ptr());
                position_grad_planar(&coeffs, &phi, &g, out, d, b, all);
            }
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&quads), bits(&planar), "{c} channels: evaluation");
            assert_eq!(
                bits(&quad_grad),
                bits(&planar_grad),
                "{c} channels: position gradient"
            );
        }
    }

    /// The AVX stencil is the generic one bit for bit (where the CPU has AVX).
    #[test]
    fn the_avx_stencil_is_the_generic_one() {
        if !has_avx2() {
            return;
        }
        let table: Vec<f32> = (0..6 * 7 * QUAD)
            .map(|i| ((i as f32) * 0.731).sin() * 1e3_f32.powi(i as i32 % 3 - 1))
            .collect();
        let (wr, wc) = ([0.1f32, 0.6, 0.29, 0.01], [0.02f32, 0.47, 0.5, 0.01]);
        for (rows, j0) in [
            ([0, 7, 14, 21], 0),
            ([7, 14, 21, 28], 3),
            ([14, 7, 0, 7], 2),
        ] {
            let generic = stencil(&table, &rows, j0, &wr, &wc);
            // SAFETY: the CPU has AVX2 (checked above).
            let avx = unsafe { stencil_avx(&table, &rows, j0, &wr, &wc) };
            assert_eq!(
                generic.map(f32::to_bits),
                avx.map(f32::to_bits),
                "{rows:?}, {j0}"
            );
        }
    }
}
