//! The adjoint `B(φ)ᵀ g` of the evaluation: a scatter-add of each pixel's 4 × 4 stencil
//! into the coefficients (the gradient w.r.t. them). Many channels go through a
//! channels-last table per block of channels; a few planes by groups of channels, with
//! per-task partial planes summed at the end when there are fewer planes than cores.

use super::*;

/// Adds `B(φ)ᵀ g` of the points `points` of image `b` into `target`, the planes of the
/// channels `channels` of that image.
#[inline(always)]
pub(super) fn scatter<T: SplineReal>(
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

/// Adds `B(φ)ᵀ g` of every point of image `b` into `table`, the channels-last coefficients
/// (`H·W × cb`) of a block of `cb` channels whose output gradient planes start at `grad`
/// (`cb` planes of `H'·W'` values, then anything). Each point's stencil is set up once for
/// the whole block, and each of its 16 neighbours takes `cb` contiguous adds (vectors),
/// where [`scatter`] set it up once per group of 4 channels and added 4 values a plane apart.
/// Per coefficient the products and their order are [`scatter`]'s: the same bits.
#[inline(always)]
fn scatter_channels_last<T: SplineReal>(
    grad: &[T],
    phi: &[T],
    table: &mut [T],
    cb: usize,
    d: Dims,
    b: usize,
) {
    let points = d.points();
    let mut tile = vec![T::default(); TILE * cb];
    for first in (0..points).step_by(TILE) {
        let count = TILE.min(points - first);
        // The tile's output gradient channels-last: one point's `cb` values side by side.
        // SAFETY: `tile` holds `count` rows of `cb` values and is this task's alone.
        unsafe {
            transpose_pixels(
                &grad[first..],
                cb,
                points,
                Shared(tile.as_mut_ptr()),
                0..count,
            )
        };
        for (p, rows, cols) in Points::new(phi, &d, b, first..first + count) {
            let v = &tile[(p - first) * cb..(p - first + 1) * cb];
            if let Some((ro, j0)) = contiguous(&rows, &cols, d.w) {
                // Four rows of four contiguous columns: 4·cb contiguous values per row.
                let (wr, wc) = (rows.weight, cols.weight);
                for a in 0..4 {
                    let line = &mut table[(ro[a] + j0) * cb..(ro[a] + j0 + 4) * cb];
                    for (k, column) in line.chunks_exact_mut(cb).enumerate() {
                        for (t, &x) in column.iter_mut().zip(v) {
                            *t += wr[a] * x * wc[k];
                        }
                    }
                }
                continue;
            }
            let (offset, weight) = stencil::<T>(&rows, &cols, d.w);
            for k in 0..16 {
                let column = &mut table[offset[k] * cb..(offset[k] + 1) * cb];
                for (t, &x) in column.iter_mut().zip(v) {
                    *t += weight[k] * x;
                }
            }
        }
    }
}

simd_dispatch!(fn scatter_channels_last_simd<T: SplineReal>(
    grad: &[T], phi: &[T], table: &mut [T], cb: usize, d: Dims, b: usize
) => scatter_channels_last);

/// [`sample_adjoint_uninit`] for many channels ([`reads_channels_last`]) and enough planes:
/// a task per block of an image's channels (one block per core for a single image) scatters
/// into a channels-last table ([`scatter_channels_last`]) and writes it into its planes.
pub(super) fn sample_adjoint_channels_last<T: SplineReal>(
    grad: &[T],
    phi: &[T],
    out: &mut [MaybeUninit<T>],
    d: Dims,
) {
    let plane = d.h * d.w;
    let threads = rayon::current_num_threads();
    // As many blocks as cores share an image, but at least a register's width of channels
    // each: each block sets up every point's stencil again.
    let per_image = threads.div_ceil(d.n);
    let width = d.c.div_ceil(per_image).max(CHANNEL_LANES).min(d.c);
    let blocks = d.c.div_ceil(width);
    let stream = std::mem::size_of_val(out) >= STREAM_FROM_BYTES;
    let base = Shared(out.as_mut_ptr().cast::<T>());
    (0..d.n * blocks).into_par_iter().for_each(|task| {
        let (b, first) = (task / blocks, (task % blocks) * width);
        let cb = width.min(d.c - first);
        let mut table = vec![T::default(); plane * cb];
        let grad = &grad[(b * d.c + first) * d.points()..];
        scatter_channels_last_simd(grad, phi, &mut table, cb, d, b);
        for i in (0..plane).step_by(TILE) {
            let count = TILE.min(plane - i);
            // SAFETY: task (b, block) owns the block's planes of image b; tasks differ in one
            // or the other.
            unsafe {
                tile_to_planes_simd(
                    &table[i * cb..(i + count) * cb],
                    cb,
                    Shared(base.get((b * d.c + first) * plane + i)),
                    plane,
                    stream,
                )
            };
        }
    });
}

/// The most channels one [`scatter`] adds at once. The planes of a 256² image are 256 KiB
/// apart, so the same pixel of every plane falls in the same cache set: with 8 channels, 8
/// gradient and 8 target lines competed for each set of the 8-way caches (measured, deep
/// 256² sweeps: the scatter's share of the profile 15.6 % with 8, 12.9 % with 4, 15.0 % with
/// 2, where the stencil is shared by fewer channels).
pub(super) const MAX_GROUP: usize = 4;

simd_dispatch!(fn scatter_simd<T: SplineReal>(
    grad: &[T], phi: &[T], target: &mut [T], d: Dims, b: usize,
    channels: std::ops::Range<usize>, points: std::ops::Range<usize>
) => scatter);

/// [`sample_adjoint_uninit`] for many planes: a task scatters a group of `group ≤
/// MAX_GROUP` channels of an image, so that each point's stencil serves the whole group
/// instead of being recomputed for every channel.
pub(super) fn sample_adjoint_groups<T: SplineReal>(
    grad: &[T],
    phi: &[T],
    out: &mut [MaybeUninit<T>],
    d: Dims,
    group: usize,
) {
    let plane = d.h * d.w;
    let groups = d.c.div_ceil(group);
    let base = Shared(out.as_mut_ptr());
    (0..d.n * groups).into_par_iter().for_each(|task| {
        let (b, first) = (task / groups, (task % groups) * group);
        let channels = first..(first + group).min(d.c);
        let planes_at = (b * d.c + channels.start) * plane;
        // SAFETY: task (b, group) owns these planes of image b; tasks differ in one or
        // the other.
        let target =
            unsafe { std::slice::from_raw_parts_mut(base.get(planes_at), channels.len() * plane) };
        target.fill(MaybeUninit::new(T::default()));
        // SAFETY: cleared just now.
        let target = unsafe { assume_init(target) };
        scatter_simd(grad, phi, target, d, b, channels, 0..d.points());
    });
}

/// `B(φ)ᵀ g`: the gradient of `⟨g, B(φ) c⟩` w.r.t. the coefficients, `[N, C, H, W]`.
///
/// A scatter-add: each point adds into 16 coefficients, and points collide. The planes
/// `(image, channel)` are independent: many channels of an image go in blocks, one per core,
/// through channels-last tables; with many planes of a few channels, tasks take groups of
/// up to 4 channels of one image; when there are fewer planes than twice the
/// threads, each plane's points are split into parts that add into private copies, summed
/// at the end, so that 3 RGB channels still keep every core busy.
pub fn sample_adjoint<T: SplineReal>(grad: &[T], phi: &[T], out: &mut [T], d: Dims) {
    // SAFETY: the kernel writes only initialised values.
    sample_adjoint_uninit(grad, phi, unsafe { as_uninit(out) }, d);
}

/// [`sample_adjoint`] into an output not yet initialised: each task clears (or first
/// copies) the planes it owns before adding to them.
pub fn sample_adjoint_uninit<T: SplineReal>(
    grad: &[T],
    phi: &[T],
    out: &mut [MaybeUninit<T>],
    d: Dims,
) {
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
    if parts == 1 && reads_channels_last(d.c) {
        return sample_adjoint_channels_last(grad, phi, out, d);
    }
    if parts == 1 {
        let group = (planes / (2 * threads)).clamp(1, MAX_GROUP);
        return sample_adjoint_groups(grad, phi, out, d, group);
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
    let mut partial = zeros(planes * parts * plane);
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
