//! The prefilter `c = P f` (and `Pᵀ g`) of SPEC §1: the exact interpolating cubic
//! B-spline prefilter with whole-sample mirror boundary, as tridiagonal solves along each
//! axis, planar or channels-last.

use super::*;

/// The factorisation of one mirrored tridiagonal system of size `n` (SPEC §1: the matrix `A`
/// with `(A x)(i) = (x(m(i−1)) + 4 x(i) + x(m(i+1))) / 6`, whose inverse is the prefilter), or
/// of its transpose: the Thomas algorithm's multipliers, computed once per line length.
#[derive(Clone, Debug)]
pub(super) struct Tridiagonal {
    /// `A[i][i−1]`, `i ≥ 1`.
    pub(super) lower: Vec<f64>,
    /// `1 / (A[i][i] − A[i][i−1] c'[i−1])`.
    pub(super) inverse_pivot: Vec<f64>,
    /// `c'[i] = A[i][i+1] · inverse_pivot[i]`.
    pub(super) upper_ratio: Vec<f64>,
}

impl Tridiagonal {
    /// `A` (or `Aᵀ`) for lines of `n ≥ 2` samples. Folding the mirror into `A` doubles the
    /// coupling of the end samples to their neighbours: `A[0][1] = A[n−1][n−2] = 2/6`.
    pub(super) fn mirrored(n: usize, transpose: bool) -> Self {
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
    pub(super) fn cast<T: SplineReal>(&self) -> (Vec<T>, Vec<T>, Vec<T>) {
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

/// Lines of one register: eight, float32 in one AVX register (float64 in two).
const LANES: usize = 8;

/// Lines solved side by side along the rows, as the lanes of four registers: the Thomas
/// recurrence is a chain of dependent steps (a multiply, a subtraction, a multiply and the
/// flush), so one register of lines waits on each step's latency; four independent
/// registers keep the pipeline full. (Before: eight lines as eight scalar chains, each step
/// a value at a time, 7 % of a deep sweep's samples in `solve_plane` alone.)
pub(super) const LINES_TOGETHER: usize = 4 * LANES;

/// The rows of a group of lines, transposed sample-major: entry `i` holds sample `i` of
/// every line of the group, one line per lane. Reused from group to group.
pub(super) type LineLanes<T> = Vec<[T; LINES_TOGETHER]>;

/// Solves the system in place on each of the contiguous lines of `n` samples in `group`.
/// A whole group of [`LINES_TOGETHER`] lines (with `n ≥ 8`) is transposed into `lanes`
/// by 8 × 8 blocks and solved with the lines as vector lanes, then transposed back; a
/// smaller group is solved eight lines at a time, interleaved step by step. Per value the
/// same operations in the same order either way: the same bits.
#[inline(always)]
pub(super) fn solve_lines<T: SplineReal>(
    group: &mut [T],
    n: usize,
    factors: &(Vec<T>, Vec<T>, Vec<T>),
    lanes: &mut LineLanes<T>,
) {
    let lines = group.len() / n;
    debug_assert_eq!(group.len(), lines * n);
    debug_assert!(factors.0.len() == n && factors.1.len() == n && factors.2.len() == n);
    if lines == LINES_TOGETHER && n >= LANES {
        if lanes.len() < n {
            lanes.resize(n, [T::default(); LINES_TOGETHER]);
        }
        solve_lines_as_lanes(group, n, factors, &mut lanes[..n]);
    } else {
        for few in group.chunks_mut(LANES * n) {
            solve_lines_interleaved(few, n, factors);
        }
    }
}

simd_dispatch!(pub(super) fn solve_lines_simd<T: SplineReal>(
    group: &mut [T], n: usize, factors: &(Vec<T>, Vec<T>, Vec<T>), lanes: &mut LineLanes<T>
) => solve_lines);

/// [`solve_lines`] of a whole group: `lanes` (`n` entries) holds the group transposed.
#[inline(always)]
fn solve_lines_as_lanes<T: SplineReal>(
    group: &mut [T],
    n: usize,
    (lower, pivot, upper): &(Vec<T>, Vec<T>, Vec<T>),
    lanes: &mut [[T; LINES_TOGETHER]],
) {
    assert!(group.len() == LINES_TOGETHER * n && lanes.len() == n && n >= LANES);
    let blocks = n / LANES;
    let rows = group.as_mut_ptr();
    let table = lanes.as_mut_ptr().cast::<T>();
    for r in (0..LINES_TOGETHER).step_by(LANES) {
        for b in 0..blocks {
            // SAFETY: lines r..r + 8 of `group` hold samples 8b..8b + 8 (b < n / 8), and
            // entries 8b..8b + 8 of `lanes` lanes r..r + 8, each 8 values at its stride.
            unsafe {
                T::transpose8(
                    rows.add(r * n + b * LANES),
                    n,
                    table.add(b * LANES * LINES_TOGETHER + r),
                    LINES_TOGETHER,
                )
            };
        }
    }
    for (i, entry) in lanes.iter_mut().enumerate().skip(blocks * LANES) {
        for (r, value) in entry.iter_mut().enumerate() {
            *value = group[r * n + i];
        }
    }
    // The recurrences of `solve_lines_interleaved`, a whole entry at a time.
    for value in lanes[0].iter_mut() {
        *value = (*value * pivot[0]).flush_tiny();
    }
    for i in 1..n {
        let (l, p) = (lower[i], pivot[i]);
        let above = lanes[i - 1];
        for (value, &a) in lanes[i].iter_mut().zip(&above) {
            *value = ((*value - l * a) * p).flush_tiny();
        }
    }
    for i in (0..n - 1).rev() {
        let u = upper[i];
        let below = lanes[i + 1];
        for (value, &b) in lanes[i].iter_mut().zip(&below) {
            *value = (*value - u * b).flush_tiny();
        }
    }
    let table = lanes.as_ptr().cast::<T>();
    for r in (0..LINES_TOGETHER).step_by(LANES) {
        for b in 0..blocks {
            // SAFETY: as above, the other way round.
            unsafe {
                T::transpose8(
                    table.add(b * LANES * LINES_TOGETHER + r),
                    LINES_TOGETHER,
                    rows.add(r * n + b * LANES),
                    n,
                )
            };
        }
    }
    for (i, entry) in lanes.iter().enumerate().skip(blocks * LANES) {
        for (r, &value) in entry.iter().enumerate() {
            group[r * n + i] = value;
        }
    }
}

/// [`solve_lines`] of up to eight lines, one value at a time, the lines interleaved step
/// by step (independent chains).
#[inline(always)]
pub(super) fn solve_lines_interleaved<T: SplineReal>(
    group: &mut [T],
    n: usize,
    (lower, pivot, upper): &(Vec<T>, Vec<T>, Vec<T>),
) {
    let lines = group.len() / n;
    // Every step flushed as in `eliminate` and `substitute`: the same bits either way.
    for r in 0..lines {
        group[r * n] = (group[r * n] * pivot[0]).flush_tiny();
    }
    for i in 1..n {
        let (l, p) = (lower[i], pivot[i]);
        for r in 0..lines {
            let at = r * n + i;
            group[at] = ((group[at] - l * group[at - 1]) * p).flush_tiny();
        }
    }
    for i in (0..n - 1).rev() {
        let u = upper[i];
        for r in 0..lines {
            let at = r * n + i;
            group[at] = (group[at] - u * group[at + 1]).flush_tiny();
        }
    }
}

/// The forward elimination of step `i` of the system along a line, on a whole row of lanes
/// at once (lane by lane the Thomas recurrence): `here` is row `i`, `above` row `i − 1`
/// already eliminated (`None` for `i = 0`). Each value is flushed ([`Real::flush_tiny`]):
/// in a run of zeros the recurrence decays geometrically into subnormal numbers, which slow
/// every later operation that reads them; flushed, the run stays exact zeros.
#[inline(always)]
pub(super) fn eliminate<T: SplineReal>(
    here: &mut [T],
    above: Option<&[T]>,
    i: usize,
    (lower, pivot, _): &(Vec<T>, Vec<T>, Vec<T>),
) {
    if let Some(above) = above {
        let (l, p) = (lower[i], pivot[i]);
        by_registers(here, above, |x, a| ((x - l * a) * p).flush_tiny());
    } else {
        for x in here.iter_mut() {
            *x = (*x * pivot[0]).flush_tiny();
        }
    }
}

/// The back substitution of step `i` (after [`eliminate`] of every step): `below` is row
/// `i + 1`, already solved; flushed as [`eliminate`].
#[inline(always)]
pub(super) fn substitute<T: SplineReal>(
    here: &mut [T],
    below: &[T],
    i: usize,
    (_, _, upper): &(Vec<T>, Vec<T>, Vec<T>),
) {
    let u = upper[i];
    by_registers(here, below, |x, b| (x - u * b).flush_tiny());
}

/// `here[j] = step(here[j], other[j])` for every `j` of `here` (`other` at least as long),
/// a register of 8 values at a time: each block's values are read before any is written,
/// so the loop vectorises without a check that the rows overlap (the compiler's check sent
/// the column solves of one image down their one-value-at-a-time loop).
#[inline(always)]
fn by_registers<T: SplineReal>(here: &mut [T], other: &[T], step: impl Fn(T, T) -> T) {
    let other = &other[..here.len()];
    let done = here.len() - here.len() % 8;
    for (x, o) in here.chunks_exact_mut(8).zip(other.chunks_exact(8)) {
        let o: [T; 8] = o.try_into().expect("eight values");
        let mut v: [T; 8] = (&*x).try_into().expect("eight values");
        for j in 0..8 {
            v[j] = step(v[j], o[j]);
        }
        x.copy_from_slice(&v);
    }
    for (x, &o) in here[done..].iter_mut().zip(&other[done..]) {
        *x = step(*x, o);
    }
}

/// Solves the system along the first axis of a `[rows, width]` block of columns `cols` of a
/// plane, one whole row segment at a time (unit stride, vectorisable).
///
/// # Safety
///
/// `plane` points to a `rows × width` plane whose columns `cols` no other thread touches.
#[inline(always)]
pub(super) unsafe fn solve_columns<T: SplineReal>(
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

simd_dispatch!(
    /// [`solve_columns`], compiled for AVX2 where the CPU has it.
    ///
    /// # Safety
    ///
    /// As [`solve_columns`].
    unsafe fn solve_columns_simd<T: SplineReal>(
        plane: Shared<T>, width: usize, rows: usize, cols: std::ops::Range<usize>,
        factors: &(Vec<T>, Vec<T>, Vec<T>)
    ) => solve_columns
);

/// The interpolating prefilter `c = P f` of every `height × width` plane of `data`, in place
/// (SPEC §1, exact); with `transpose`, its adjoint `Pᵀ g`. `P` is separable: the same 1-D
/// solve along each axis, in either order.
pub fn prefilter<T: SplineReal>(data: &mut [T], height: usize, width: usize, transpose: bool) {
    prefilter_from(None, data, height, width, transpose);
}

/// [`prefilter()`] of `source` into `data` (same length), without a separate copy pass: each
/// group of lines is copied just before it is solved, while it is in cache.
pub fn prefilter_into<T: SplineReal>(
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

pub(super) fn prefilter_from<T: SplineReal>(
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
            .for_each_init(Vec::new, |lanes, (p, values)| {
                if let Some(source) = source {
                    values.copy_from_slice(&source[p * plane..(p + 1) * plane]);
                }
                solve_plane_simd(values, width, &along_w, &along_h, lanes);
            });
        return;
    }
    // Fewer planes than threads: rows, then columns, each pass split finely enough that
    // every thread has work even for one plane.
    let group = width * LINES_TOGETHER;
    data.par_chunks_mut(group)
        .enumerate()
        .with_min_len((PIXELS_PER_TASK / group).max(1))
        .for_each_init(Vec::new, |lanes, (g, lines)| {
            if let Some(source) = source {
                lines.copy_from_slice(&source[g * group..g * group + lines.len()]);
            }
            solve_lines_simd(lines, width, &along_w, lanes)
        });
    // Columns in blocks that keep a task's rows in cache.
    solve_all_columns(data, width, height, 64, &along_h);
}

/// Solves the system along both axes of one `[height, width]` plane, in place.
#[inline(always)]
pub(super) fn solve_plane<T: SplineReal>(
    plane: &mut [T],
    width: usize,
    along_w: &(Vec<T>, Vec<T>, Vec<T>),
    along_h: &(Vec<T>, Vec<T>, Vec<T>),
    lanes: &mut LineLanes<T>,
) {
    for lines in plane.chunks_mut(width * LINES_TOGETHER) {
        solve_lines(lines, width, along_w, lanes);
    }
    solve_interleaved(plane, width, along_h);
}

simd_dispatch!(fn solve_plane_simd<T: SplineReal>(
    plane: &mut [T], width: usize,
    along_w: &(Vec<T>, Vec<T>, Vec<T>), along_h: &(Vec<T>, Vec<T>, Vec<T>),
    lanes: &mut LineLanes<T>
) => solve_plane);

/// Solves the system along the first axis of every `[height, width]` plane of `data`, in
/// parallel tasks of `block` columns of one plane each.
pub(super) fn solve_all_columns<T: SplineReal>(
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
            unsafe {
                solve_columns_simd(Shared(base.get(p * plane)), width, height, cols, along_h)
            };
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
/// the same operations in the same order as [`prefilter()`]: the same bits.
pub fn prefilter_channels_last<T: SplineReal>(
    source: &[T],
    out: &mut [T],
    shape: (usize, usize, usize, usize),
) {
    // SAFETY: the kernel writes only initialised values.
    prefilter_channels_last_uninit(source, unsafe { as_uninit(out) }, shape);
}

/// [`prefilter_channels_last`] into an output not yet initialised: each row is gathered
/// (every value written) before anything reads it.
pub fn prefilter_channels_last_uninit<T: SplineReal>(
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
    // Rows of `C` values a pixel: as many rows a task as the pixel kernels' tasks hold.
    out.par_chunks_mut(line)
        .enumerate()
        .with_min_len((pixels_per_task(c) / width).max(1))
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
pub(super) fn gather_row<'a, T: SplineReal>(
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
pub(super) unsafe fn assume_init<T>(values: &mut [MaybeUninit<T>]) -> &mut [T] {
    // SAFETY: `MaybeUninit<T>` has `T`'s layout, and the caller's promise.
    unsafe { &mut *(values as *mut [MaybeUninit<T>] as *mut [T]) }
}

/// The channels-last prefilter of one image (`source` `[C, H, W]` planar, `image`
/// `[H, W, C]`): each row gathered, solved along `W`, and eliminated down the columns
/// against the row above; then the back substitution up the columns.
#[inline(always)]
pub(super) fn image_channels_last<T: SplineReal>(
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

simd_dispatch!(fn image_channels_last_simd<T: SplineReal>(
    source: &[T], image: &mut [MaybeUninit<T>], shape: (usize, usize),
    along_w: &(Vec<T>, Vec<T>, Vec<T>), along_h: &(Vec<T>, Vec<T>, Vec<T>)
) => image_channels_last);

/// [`eliminate`] of row `i` of a `[n, lanes]` block.
#[inline(always)]
pub(super) fn eliminate_row<T: SplineReal>(
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
pub(super) fn substitute_row<T: SplineReal>(
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
pub(super) fn solve_interleaved<T: SplineReal>(
    values: &mut [T],
    lanes: usize,
    factors: &(Vec<T>, Vec<T>, Vec<T>),
) {
    let n = values.len() / lanes;
    debug_assert!(factors.0.len() == n && factors.1.len() == n && factors.2.len() == n);
    for i in 0..n {
        eliminate_row(values, lanes, i, factors);
    }
    for i in (0..n - 1).rev() {
        substitute_row(values, lanes, i, factors);
    }
}

simd_dispatch!(fn solve_interleaved_simd<T: SplineReal>(
    values: &mut [T], lanes: usize, factors: &(Vec<T>, Vec<T>, Vec<T>)
) => solve_interleaved);
