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
    let mut out = zeros(planar.len());
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

/// Outputs of [`sample_channels_last`](super::evaluate) from this many bytes on are written
/// around the caches ([`tile_to_planes`]'s `stream`): about one core's second-level cache
/// (2 MiB on the Xeon of docs/benchmarks.md). A smaller warp stays in the caches for the
/// kernel that reads it next, and streamed it cost that kernel a trip to memory (the sweep
/// bench's 64² frame of 67 channels, 1.1 MB: +13 % a sweep). The levels of a deep morph lie
/// well to either side: 0.5 MB at 16², 2.1 MB and more from 32² on (float32).
pub(super) const STREAM_FROM_BYTES: usize = 3 << 19;

/// Writes the channels-last `tile` (`count × c`) into `c` planes `plane` values apart from
/// `out`: `out[ch·plane + i] = tile[i·c + ch]`, in blocks of 8 channels (one value at a time,
/// the gather with a stride of `c` cost half as much as the evaluation itself).
///
/// With `stream`, blocks of 16 points ([`SplineReal::transpose16x8`]): each block writes a
/// whole cache line of each of its planes, around the caches for float32. With the planes a
/// power of two apart, more lines of them compete for a cache set than it has ways, and
/// written through the caches every line was read first, often twice (once per half).
/// Streamed, a deep sweep cost 12–18 % less on the 32²…128² levels and the same at 256²,
/// where the next kernel then reads the warp from memory instead of the last-level cache
/// (docs/benchmarks.md, "Streaming the warp's planes"); an output that fits a core's cache
/// is better written through it ([`STREAM_FROM_BYTES`]).
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
    stream: bool,
) {
    let count = tile.len() / c;
    // SAFETY: a block of the tile into its planes, as `blocks_to_planes` promises.
    let lines = |s: *const T, ss, d: *mut T, ds| unsafe { T::transpose16x8(s, ss, d, ds) };
    // SAFETY: as for `lines`.
    let halves = |s: *const T, ss, d: *mut T, ds| unsafe { T::transpose8(s, ss, d, ds) };
    let mut done = 0;
    if stream {
        // SAFETY: the caller's promise, passed on.
        done = unsafe { blocks_to_planes::<T, 16>(tile, c, out, plane, lines) };
    }
    // SAFETY: the caller's promise, passed on, for the points from `done`.
    done += unsafe {
        blocks_to_planes::<T, 8>(&tile[done * c..], c, Shared(out.get(done)), plane, halves)
    };
    for ch in 0..c {
        for i in done..count {
            // SAFETY: the caller's promise, for channel ch's point i.
            unsafe { out.write(ch * plane + i, tile[i * c + ch]) };
        }
    }
    T::store_fence();
}

/// The first whole blocks of `P` points of [`tile_to_planes`], `P × 8` values at a time by
/// `transpose` (`P` rows of 8 from a row stride to 8 rows of `P` to another), the channels
/// past the last 8 one at a time. Returns how many points it wrote.
///
/// # Safety
///
/// As [`tile_to_planes`]; `transpose` is sound for a `P × 8` block of the tile into 8 of
/// the planes.
#[inline(always)]
unsafe fn blocks_to_planes<T: SplineReal, const P: usize>(
    tile: &[T],
    c: usize,
    out: Shared<T>,
    plane: usize,
    transpose: impl Fn(*const T, usize, *mut T, usize),
) -> usize {
    let count = tile.len() / c;
    let (whole_points, whole_channels) = (count - count % P, c - c % 8);
    for i0 in (0..whole_points).step_by(P) {
        for ch0 in (0..whole_channels).step_by(8) {
            // SAFETY: the P rows of 8 from (i0, ch0) lie in the tile; the 8 columns of P are
            // the caller's promise.
            transpose(
                tile[i0 * c + ch0..].as_ptr(),
                c,
                unsafe { out.get(ch0 * plane + i0) },
                plane,
            );
        }
        for ch in whole_channels..c {
            for i in i0..i0 + P {
                // SAFETY: the caller's promise, for channel ch's point i.
                unsafe { out.write(ch * plane + i, tile[i * c + ch]) };
            }
        }
    }
    whole_points
}

simd_dispatch!(
    /// [`tile_to_planes`], compiled for AVX2 where the CPU has it.
    ///
    /// # Safety
    ///
    /// As [`tile_to_planes`].
    pub(super) unsafe fn tile_to_planes_simd<T: SplineReal>(tile: &[T], c: usize, out: Shared<T>, plane: usize, stream: bool)
        => tile_to_planes
);
