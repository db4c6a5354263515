//! Channels-last tables: which layout a kernel reads ([`Layout`]), the transposes between
//! planar and channels-last, and the tile writes back to planes.

use super::*;

/// From this many channels on, the evaluation and its position gradient read the coefficients
/// channels-last: a point's 16 neighbours are then 16 contiguous runs of `C` values (vector
/// loads, a few cache lines) instead of `16·C` reads spread over `C` planes. The transposition
/// costs one pass over the coefficients per call; below this it does not pay.
pub(super) const CHANNELS_LAST_FROM: usize = 8;

/// Points (or pixels) per tile of a layout change between planar and channels-last: a tile
/// of `C` values per point stays in the second-level cache even at `C = 515`, and each plane
/// is read or written in runs of this many contiguous values. Writing a point's `C` values
/// straight into `C` planes, a plane apart, cost more than evaluating them (measured: about
/// 60 % of the evaluation's profile samples in a deep morph at 256²).
pub(super) const TILE: usize = 64;

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
pub(super) fn check_table<T>(values: &[T], stride: usize, d: &Dims) {
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

/// `out` as a slice of possibly uninitialised values, for the kernels that write every value
/// of their output and read none.
///
/// # Safety
///
/// The caller writes only initialised values through the result (a `T` slice must stay
/// initialised).
pub(super) unsafe fn as_uninit<T>(out: &mut [T]) -> &mut [MaybeUninit<T>] {
    // SAFETY: `MaybeUninit<T>` has `T`'s layout; the caller's promise keeps `out` valid.
    unsafe { &mut *(out as *mut [T] as *mut [MaybeUninit<T>]) }
}

/// One image's `C` planes of `plane` values, channels-last: `out[p·C + c] = planar[c·plane + p]`.
pub(super) fn channels_last<T: SplineReal>(planar: &[T], c: usize, plane: usize) -> Vec<T> {
    let mut out = vec![T::default(); planar.len()];
    channels_last_into(planar, c, plane, &mut out);
    out
}

/// `Σ_i a[i] · b[i]` in eight interleaved partial sums (vectorisable, and short dependency
/// chains).
#[inline]
pub(super) fn dot<T: SplineReal>(a: &[T], b: &[T]) -> T {
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
pub(super) fn image_table<T: SplineReal>(
    values: &[T],
    layout: Layout,
    d: Dims,
    b: usize,
) -> (Cow<'_, [T]>, usize) {
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

/// Writes the channels-last `tile` (`count × c`) into `c` planes `plane` values apart from
/// `out`: `out[ch·plane + i] = tile[i·c + ch]`, in blocks of 16 points × 8 channels
/// ([`SplineReal::transpose16x8`]; one value at a time, the gather with a stride of `c` cost
/// half as much as the evaluation itself). Each block writes a whole cache line of each of
/// its planes, around the caches for float32: with the planes a power of two apart, more
/// lines of them compete for a cache set than it has ways, and written through the caches
/// every line was read first, often twice (once per half). Streamed, a deep sweep cost
/// 12–18 % less on the 32²…128² levels and the same at 256², where the next kernel then reads
/// the warp from memory instead of the last-level cache (docs/benchmarks.md, "Streaming the
/// warp's planes").
///
/// # Safety
///
/// `out` is valid for the `count` values from each `ch·plane`, which no other thread
/// touches meanwhile.
#[inline(always)]
pub(super) unsafe fn tile_to_planes<T: SplineReal>(
    tile: &[T],
    c: usize,
    out: Shared<T>,
    plane: usize,
) {
    const B: usize = 8;
    let count = tile.len() / c;
    let column = |ch: usize, from: usize, len: usize| -> &mut [T] {
        // SAFETY: the caller's promise, for channel ch's points from..from + len.
        unsafe { std::slice::from_raw_parts_mut(out.get(ch * plane + from), len) }
    };
    let (whole_points, whole_channels) = (count - count % B, c - c % B);
    // Sixteen points at a time first: each plane's 16 values are a whole cache line, written
    // around the caches where the type can ([`SplineReal::transpose16x8`]).
    let pairs = count - count % (2 * B);
    for i0 in (0..pairs).step_by(2 * B) {
        for ch0 in (0..whole_channels).step_by(B) {
            // SAFETY: the 16 rows of 8 from (i0, ch0) lie in the tile; the 8 columns of 16
            // are the caller's promise.
            unsafe {
                T::transpose16x8(
                    tile[i0 * c + ch0..].as_ptr(),
                    c,
                    out.get(ch0 * plane + i0),
                    plane,
                )
            };
        }
        for ch in whole_channels..c {
            for (i, v) in column(ch, i0, 2 * B).iter_mut().enumerate() {
                *v = tile[(i0 + i) * c + ch];
            }
        }
    }
    for i0 in (pairs..whole_points).step_by(B) {
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
    T::store_fence();
}

simd_dispatch!(
    /// [`tile_to_planes`], compiled for AVX2 where the CPU has it.
    ///
    /// # Safety
    ///
    /// As [`tile_to_planes`].
    pub(super) unsafe fn tile_to_planes_simd<T: SplineReal>(tile: &[T], c: usize, out: Shared<T>, plane: usize)
        => tile_to_planes
);
