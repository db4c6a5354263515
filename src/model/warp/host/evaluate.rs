//! The evaluation `T = B(φ) c` and its position gradient `Σ_c g_c ∂T_c/∂p`, planar (few
//! channels) and channels-last (many), tiled over pixels.

use super::*;

/// [`sample`] from channels-last coefficients (`layout` [`Layout::ChannelsLast`]): `values`
/// starts at image 0's first channel.
pub fn sample_from_table<T: SplineReal>(
    values: &[T],
    stride: usize,
    phi: &[T],
    out: &mut [T],
    d: Dims,
) {
    // SAFETY: the kernel writes only initialised values.
    sample_from_table_uninit(values, stride, phi, unsafe { as_uninit(out) }, d);
}

/// [`sample_from_table`] into an output not yet initialised: every value is written.
pub fn sample_from_table_uninit<T: SplineReal>(
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

/// [`sample_position_grad`] from channels-last coefficients, as [`sample_from_table`].
pub fn position_grad_from_table<T: SplineReal>(
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

/// [`sample`] for many channels: writes every value of `out`.
pub(super) fn sample_channels_last<T: SplineReal>(
    coeffs: &[T],
    layout: Layout,
    phi: &[T],
    out: &mut [MaybeUninit<T>],
    d: Dims,
) {
    let (points, c) = (d.points(), d.c);
    let per_task = pixels_per_task(c);
    let tasks = points.div_ceil(per_task);
    let stream = std::mem::size_of_val(out) >= STREAM_FROM_BYTES;
    let out = Shared(out.as_mut_ptr().cast::<T>());
    for b in 0..d.n {
        let (table, stride) = image_table(coeffs, layout, d, b);
        (0..tasks).into_par_iter().for_each(|chunk| {
            let mut tile = vec![T::default(); c * TILE];
            let end = ((chunk + 1) * per_task).min(points);
            for first in (chunk * per_task..end).step_by(TILE) {
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
                        stream,
                    )
                };
            }
        });
    }
}

/// The points `points` of image `b` evaluated from the channels-last `table` into `tile`,
/// channels-last (`C` values per point).
#[inline(always)]
pub(super) fn evaluate_tile<T: SplineReal>(
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
pub(super) fn neighbour_sums<T: SplineReal, const R: usize>(
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
pub(super) fn neighbour_runs<T: SplineReal, const R: usize>(
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
pub(super) const CHANNEL_LANES: usize = 8;

simd_dispatch!(fn evaluate_tile_simd<T: SplineReal>(
    table: &[T], stride: usize, phi: &[T], d: Dims, b: usize, points: std::ops::Range<usize>,
    tile: &mut [T]
) => evaluate_tile);

/// The position gradient at the points `points` of image `b` from the channels-last
/// coefficients `table` and output gradient `g`, written into `out` (`[N, 2, H', W']`).
#[inline(always)]
pub(super) fn position_grad_tile<T: SplineReal>(
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

simd_dispatch!(fn position_grad_tile_simd<T: SplineReal>(
    table: &[T], stride: usize, phi: &[T], g: &[T], out: Shared<T>, d: Dims, b: usize,
    points: std::ops::Range<usize>
) => position_grad_tile);

/// [`sample_position_grad`] for many channels.
pub(super) fn position_grad_channels_last<T: SplineReal>(
    coeffs: &[T],
    layout: Layout,
    phi: &[T],
    grad: &[T],
    out: &mut [T],
    d: Dims,
) {
    let (points, c) = (d.points(), d.c);
    let per_task = pixels_per_task(c);
    let tasks = points.div_ceil(per_task);
    let out = Shared(out.as_mut_ptr());
    for b in 0..d.n {
        let (table, stride) = image_table(coeffs, layout, d, b);
        let g = channels_last(&grad[b * c * points..(b + 1) * c * points], c, points);
        (0..tasks).into_par_iter().for_each(|chunk| {
            let range = chunk * per_task..((chunk + 1) * per_task).min(points);
            position_grad_tile_simd(&table, stride, phi, &g, out, d, b, range);
        });
    }
}

/// `Σ_b weight[b] · line[index[b]]` as two independent pairs.
#[inline]
pub(super) fn dot4<T: SplineReal>(line: &[T], index: &[usize; 4], weight: &[T; 4]) -> T {
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
pub(super) fn contiguous<T>(
    rows: &Axis<T>,
    cols: &Axis<T>,
    w: usize,
) -> Option<([usize; 4], usize)> {
    let (r, j0) = (&rows.index, cols.index[0]);
    // Mirrored neighbours differ by ±1, so a rise of 3 over 3 steps means +1 each time.
    (cols.index[3] == j0 + 3).then_some(([r[0] * w, r[1] * w, r[2] * w, r[3] * w], j0))
}

/// `v[k] = Σ_a weight[a] · c[rows[a] + j0 + k]`, `k < 4`: the four columns summed down the four
/// rows side by side (one vector of four lanes), before the sum across them.
#[inline(always)]
pub(super) fn down_rows<T: SplineReal>(
    c: &[T],
    rows: &[usize; 4],
    j0: usize,
    weight: &[T; 4],
) -> [T; 4] {
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
pub(super) fn sum4<T: SplineReal>(a: &[T; 4], b: &[T; 4]) -> T {
    (a[0] * b[0] + a[1] * b[1]) + (a[2] * b[2] + a[3] * b[3])
}

/// `T = B(φ) c`: the spline with coefficients `coeffs` at the clamped points `phi`.
pub fn sample<T: SplineReal>(coeffs: &[T], phi: &[T], out: &mut [T], d: Dims) {
    // SAFETY: the kernels write only initialised values.
    sample_uninit(coeffs, phi, unsafe { as_uninit(out) }, d);
}

/// [`sample`] into an output not yet initialised: every value is written (a zeroed output
/// was a serial memset, or page clearing, of a whole frame before each parallel warp).
pub fn sample_uninit<T: SplineReal>(coeffs: &[T], phi: &[T], out: &mut [MaybeUninit<T>], d: Dims) {
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
pub(super) fn sample_planar<T: SplineReal>(
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

simd_dispatch!(fn sample_planar_simd<T: SplineReal>(
    coeffs: &[T], phi: &[T], out: Shared<T>, d: Dims, b: usize, points: std::ops::Range<usize>
) => sample_planar);

/// `Σ_c g_c ∂T_c/∂p` at every point: the gradient of `⟨g, B(φ) c⟩` w.r.t. `φ`, `[N, 2, H', W']`.
pub fn sample_position_grad<T: SplineReal>(
    coeffs: &[T],
    phi: &[T],
    grad: &[T],
    out: &mut [T],
    d: Dims,
) {
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
pub(super) fn position_grad_planar<T: SplineReal>(
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

simd_dispatch!(fn position_grad_planar_simd<T: SplineReal>(
    coeffs: &[T], phi: &[T], grad: &[T], out: Shared<T>, d: Dims, b: usize,
    points: std::ops::Range<usize>
) => position_grad_planar);
