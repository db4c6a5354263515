//! Banded application of a separable operator `x ↦ R · x · Cᵀ` on host slices: the native
//! CPU kernel behind [`super::op`], threaded with rayon over lines.
//!
//! Every 1-D operator of the model is a short stencil with the mirror folded into its
//! boundary rows, so each row of `R` (and of `C`) has its nonzeros within a few taps: the
//! 13-tap Gaussian, the 3-tap Sobel, `G_ρ D G_σ` of the anisotropy (`2⌈3ρ⌉ + 2⌈3σ⌉ + 3`
//! taps), a bilinear resize. A [`Band`] keeps, per row, the columns from its first to its last
//! nonzero: applying it costs `taps` multiply-adds per value instead of the dense product's
//! `n`, and gives the same sums (the skipped entries are exact zeros).

use rayon::prelude::*;

use std::mem::MaybeUninit;

use crate::model::cpu::{Real, simd_dispatch};

/// Output values per task: enough that a task outweighs rayon's overhead.
const VALUES_PER_TASK: usize = 4096;

/// The nonzero band of a `rows × cols` matrix: row `i` reads columns
/// `start[i] .. start[i] + width`, with the entries `values[i·width ..][..width]`.
///
/// `width` is the widest row's span (first to last nonzero); narrower rows are padded with
/// their matrix's own (zero) entries, and a row whose span would run past the last column
/// starts earlier instead, so every row reads exactly `width` columns in bounds.
#[derive(Clone, Debug, PartialEq)]
pub struct Band<T> {
    rows: usize,
    cols: usize,
    width: usize,
    start: Vec<usize>,
    values: Vec<T>,
}

impl<T: Real> Band<T> {
    /// The band of the `rows × cols` matrix stored row-major in `data`.
    ///
    /// # Panics
    ///
    /// If the matrix is empty or `data` does not hold `rows · cols` values.
    pub fn from_row_major(rows: usize, cols: usize, data: &[T]) -> Self {
        Self::from_dense(rows, cols, data, false)
    }

    /// The band of the `rows × cols` matrix whose transpose is stored row-major in `data`:
    /// read in its own order, not down its strided rows (a 512-point operator's were 262 k
    /// cache-missing reads per call).
    ///
    /// # Panics
    ///
    /// As [`from_row_major`](Self::from_row_major).
    pub fn from_column_major(rows: usize, cols: usize, data: &[T]) -> Self {
        Self::from_dense(rows, cols, data, true)
    }

    /// The band of a dense matrix, `data` read in storage order.
    fn from_dense(rows: usize, cols: usize, data: &[T], column_major: bool) -> Self {
        assert!(
            rows > 0 && cols > 0 && data.len() == rows * cols,
            "a band of {} values as a {rows} × {cols} matrix",
            data.len()
        );
        let line = if column_major { rows } else { cols };
        let mut spans = Spans::new(rows);
        for (l, values) in data.chunks(line).enumerate() {
            for (k, &v) in values.iter().enumerate() {
                let (i, j) = if column_major { (k, l) } else { (l, k) };
                spans.see(i, j, v);
            }
        }
        let index = |i: usize, j: usize| {
            if column_major {
                j * rows + i
            } else {
                i * cols + j
            }
        };
        Self::from_spans(cols, &spans, |i, j| data[index(i, j)])
    }

    /// The band of rows with nonzeros within `spans`, entries `entry(i, j)`.
    fn from_spans(cols: usize, spans: &Spans, entry: impl Fn(usize, usize) -> T) -> Self {
        let rows = spans.first.len();
        let width = (0..rows)
            .filter_map(|i| spans.span(i).map(|(_, len)| len))
            .max()
            .unwrap_or(0)
            .max(1);
        let start: Vec<usize> = (0..rows)
            .map(|i| {
                spans
                    .span(i)
                    .map_or(0, |(first, _)| first)
                    .min(cols - width)
            })
            .collect();
        let values = (0..rows * width)
            .map(|at| {
                let (i, t) = (at / width, at % width);
                entry(i, start[i] + t)
            })
            .collect();
        Self {
            rows,
            cols,
            width,
            start,
            values,
        }
    }

    /// Rows of the matrix (outputs per line).
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// Columns of the matrix (inputs per line).
    pub fn cols(&self) -> usize {
        self.cols
    }

    /// Columns read per row.
    pub fn width(&self) -> usize {
        self.width
    }

    /// For each row `i`, the end of the stretch of rows from `i` that read row `i`'s taps,
    /// each one column further on than the row before (a stencil's interior, away from the
    /// folded mirror): there a pass along a line computes neighbouring outputs as lanes.
    pub fn shifted_runs(&self) -> Vec<usize> {
        let taps = |i: usize| &self.values[i * self.width..(i + 1) * self.width];
        let same = |a: &[T], b: &[T]| {
            a.iter()
                .zip(b)
                .all(|(x, y)| x.to_f64().to_bits() == y.to_f64().to_bits())
        };
        let mut end = vec![self.rows; self.rows];
        for i in (0..self.rows.saturating_sub(1)).rev() {
            let continues = self.start[i + 1] == self.start[i] + 1 && same(taps(i), taps(i + 1));
            end[i] = if continues { end[i + 1] } else { i + 1 };
        }
        end
    }
}

/// The first and last nonzero column of each row of a matrix, as its entries are seen in
/// any order.
struct Spans {
    first: Vec<usize>,
    last: Vec<usize>,
}

impl Spans {
    fn new(rows: usize) -> Self {
        Self {
            first: vec![usize::MAX; rows],
            last: vec![0; rows],
        }
    }

    /// Entry `(i, j)` is `v`; a NaN counts as nonzero, so it still reaches the output.
    #[inline(always)]
    fn see<T: Real>(&mut self, i: usize, j: usize, v: T) {
        if v.to_f64() != 0.0 {
            self.first[i] = self.first[i].min(j);
            self.last[i] = self.last[i].max(j);
        }
    }

    /// Row `i`'s first nonzero column and the columns from it to its last, `None` for a
    /// row of zeros.
    fn span(&self, i: usize) -> Option<(usize, usize)> {
        (self.first[i] != usize::MAX).then(|| (self.first[i], self.last[i] + 1 - self.first[i]))
    }
}

/// One output row of a pass along the first axis: `Σ_t taps[t] · source row (first + t)`, as
/// whole-row multiply-adds (unit stride, vectorised), summed from zero in tap order.
#[inline(always)]
fn combine_rows<T: Real>(taps: &[T], source: &[T], first: usize, out_row: &mut [MaybeUninit<T>]) {
    let len = out_row.len();
    // The row is zeroed here, in cache, by the task that fills it: a zeroed buffer was a
    // serial memset (and its page faults) on the solver's thread.
    for o in out_row.iter_mut() {
        o.write(T::default());
    }
    // SAFETY: every value of the row was written just now.
    let out_row = unsafe { &mut *(std::ptr::from_mut(out_row) as *mut [T]) };
    for (t, &weight) in taps.iter().enumerate() {
        let src = (first + t) * len;
        for (o, &v) in out_row.iter_mut().zip(&source[src..src + len]) {
            *o += weight * v;
        }
    }
}

simd_dispatch!(fn combine_rows_simd<T: Real>(
    taps: &[T], source: &[T], first: usize, out_row: &mut [MaybeUninit<T>]
) => combine_rows);

/// `M · x` of every `n × m` plane of `x` (`M` is `band`, `n' × n`): each output row a weighted
/// sum of whole input rows, `[planes, n', m]`.
fn along_first_axis<T: Real>(x: &[T], band: &Band<T>, m: usize) -> Vec<T> {
    let (n, n_out) = (band.cols, band.rows);
    let len = x.len() / (n * m) * n_out * m;
    let mut out = Vec::with_capacity(len);
    out.spare_capacity_mut()[..len]
        .par_chunks_mut(m)
        .enumerate()
        .with_min_len((VALUES_PER_TASK / m).max(1))
        .for_each(|(r, out_row)| {
            let (p, i) = (r / n_out, r % n_out);
            let taps = &band.values[i * band.width..(i + 1) * band.width];
            combine_rows_simd(taps, &x[p * n * m..(p + 1) * n * m], band.start[i], out_row);
        });
    // SAFETY: every row of the `len` values was written above.
    unsafe { out.set_len(len) };
    out
}

/// `N` consecutive outputs of a pass along a line that read the same taps at consecutive
/// starts (`line` from the first one's start): `N` lanes, each summed from zero in tap
/// order, the values a dot product per output gives, bit for bit.
#[inline(always)]
fn shifted_block<T: Real, const N: usize>(taps: &[T], line: &[T], out: &mut [MaybeUninit<T>]) {
    let mut acc = [T::default(); N];
    for (t, &weight) in taps.iter().enumerate() {
        let values: &[T; N] = line[t..t + N].try_into().expect("N values from the tap");
        for (a, &v) in acc.iter_mut().zip(values) {
            *a += weight * v;
        }
    }
    for (o, a) in out.iter_mut().zip(acc) {
        o.write(a);
    }
}

/// `N` consecutive outputs `j ..` of a pass along a line, each with its own taps and start
/// (near the folded mirror, or where a stretch ends): the `N` sums side by side, each from
/// zero in tap order. One output at a time, each sum was a chain of dependent adds.
#[inline(always)]
fn any_block<T: Real, const N: usize>(
    band: &Band<T>,
    j: usize,
    line: &[T],
    out: &mut [MaybeUninit<T>],
) {
    let width = band.width;
    let taps: [&[T]; N] = std::array::from_fn(|l| &band.values[(j + l) * width..][..width]);
    let from: [&[T]; N] = std::array::from_fn(|l| &line[band.start[j + l]..][..width]);
    let mut acc = [T::default(); N];
    for t in 0..width {
        for l in 0..N {
            acc[l] += taps[l][t] * from[l][t];
        }
    }
    for (o, a) in out.iter_mut().zip(acc) {
        o.write(a);
    }
}

/// One line of a pass along the last axis, `out[j] = Σ_t taps_j[t] · line[start_j + t]`:
/// across a stencil's interior (`runs`, [`Band::shifted_runs`]) as lanes of neighbouring
/// outputs, 32 then 8 at a time (four independent sums per tap keep the adder busy), a dot
/// product per output elsewhere. The pass works on the rows in place: the two transposes
/// around a pass of whole-row multiply-adds that it replaces were two more passes over the
/// planes and two fresh buffers.
#[inline(always)]
fn along_line<T: Real>(band: &Band<T>, runs: &[usize], line: &[T], out: &mut [MaybeUninit<T>]) {
    let width = band.width;
    let mut j = 0;
    while j < band.rows {
        let taps = &band.values[j * width..(j + 1) * width];
        let from = &line[band.start[j]..];
        match runs[j] - j {
            32.. => {
                shifted_block::<T, 32>(taps, from, &mut out[j..j + 32]);
                j += 32;
            }
            8.. => {
                shifted_block::<T, 8>(taps, from, &mut out[j..j + 8]);
                j += 8;
            }
            _ if j + 8 <= band.rows => {
                any_block::<T, 8>(band, j, line, &mut out[j..j + 8]);
                j += 8;
            }
            _ => {
                shifted_block::<T, 1>(taps, from, &mut out[j..=j]);
                j += 1;
            }
        }
    }
}

simd_dispatch!(fn along_line_simd<T: Real>(
    band: &Band<T>, runs: &[usize], line: &[T], out: &mut [MaybeUninit<T>]
) => along_line);

/// `x · Mᵀ` of every line of `m` values of `x` (`M` is `band`, `m' × m`), `[lines, m']`.
fn along_last_axis<T: Real>(x: &[T], band: &Band<T>) -> Vec<T> {
    let (m, m_out) = (band.cols, band.rows);
    let len = x.len() / m * m_out;
    let runs = band.shifted_runs();
    let mut out = Vec::with_capacity(len);
    out.spare_capacity_mut()[..len]
        .par_chunks_mut(m_out)
        .zip(x.par_chunks(m))
        .with_min_len((VALUES_PER_TASK / m_out).max(1))
        .for_each(|(out_line, line)| along_line_simd(band, &runs, line, out_line));
    // SAFETY: every line of the `len` values was written above.
    unsafe { out.set_len(len) };
    out
}

/// Row `i` of `R · x · Cᵀ` for one plane `x` (`H × W`, row-major) into `out` (`W'`
/// values), through `down` (`W` values): the values [`apply`] gives for that row, bit for
/// bit. `runs` are `cols`' [`Band::shifted_runs`]. For kernels that use a row while it is in
/// cache (the anisotropy's weight) instead of a whole plane.
pub fn apply_row<T: Real>(
    x: &[T],
    rows: &Band<T>,
    cols: &Band<T>,
    runs: &[usize],
    i: usize,
    down: &mut [MaybeUninit<T>],
    out: &mut [MaybeUninit<T>],
) {
    let taps = &rows.values[i * rows.width..(i + 1) * rows.width];
    combine_rows_simd(taps, x, rows.start[i], down);
    // SAFETY: combine_rows wrote every value of `down` just now.
    let down = unsafe { &*(std::ptr::from_mut(down) as *const [T]) };
    along_line_simd(cols, runs, down, out);
}

/// `R · x · Cᵀ` of every plane of `x`.
///
/// # Shapes
/// - `x`: `planes × H × W` values, row-major; `rows` (`R`): `H' × H`; `cols` (`C`): `W' × W`
/// - output: `planes × H' × W'`
pub fn apply<T: Real>(x: &[T], rows: &Band<T>, cols: &Band<T>) -> Vec<T> {
    let (h, w) = (rows.cols, cols.cols);
    assert_eq!(
        x.len() % (h * w),
        0,
        "separable: input is not whole {h} × {w} planes"
    );
    // Along the columns as whole-row multiply-adds, then along each row as lanes of
    // neighbouring outputs: two passes, one intermediate.
    along_last_axis(&along_first_axis(x, rows, w), cols)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::stencil::{Matrix, central_difference_domain, gaussian};

    fn band(m: &Matrix) -> Band<f64> {
        let band = Band::from_row_major(m.rows, m.cols, &m.data);
        let transposed = m.transpose();
        assert_eq!(
            Band::from_column_major(m.rows, m.cols, &transposed.data),
            band,
            "the band read from the transpose"
        );
        band
    }

    fn dense(x: &[f64], planes: usize, r: &Matrix, c: &Matrix) -> Vec<f64> {
        let (h, w) = (r.cols, c.cols);
        let mut out = vec![0.0; planes * r.rows * c.rows];
        for p in 0..planes {
            for i in 0..r.rows {
                for j in 0..c.rows {
                    let mut acc = 0.0;
                    for k in 0..h {
                        for l in 0..w {
                            acc += r.get(i, k) * c.get(j, l) * x[(p * h + k) * w + l];
                        }
                    }
                    out[(p * r.rows + i) * c.rows + j] = acc;
                }
            }
        }
        out
    }

    /// The banded product equals the dense one for the model's stencils, including a
    /// Gaussian wider than its line (it reflects twice) and a rectangular operator.
    #[test]
    fn band_matches_the_dense_product() {
        let (h, w) = (10, 17);
        let x: Vec<f64> = (0..2 * h * w)
            .map(|i| ((i * 37) % 23) as f64 - 11.0)
            .collect();
        let wide = gaussian(h, 3.0);
        let derivative = gaussian(w, 1.0).matmul(&central_difference_domain(w));
        let shrink = Matrix::from_stencil(w, &[0.25, 0.5, 0.25]);
        let shrink = Matrix {
            rows: 8,
            cols: w,
            data: shrink.data[..8 * w].to_vec(),
        };
        for (r, c) in [(&wide, &derivative), (&wide, &shrink)] {
            let got = apply(&x, &band(r), &band(c));
            let want = dense(&x, 2, r, c);
            assert_eq!(got.len(), want.len());
            for (g, e) in got.iter().zip(&want) {
                assert!((g - e).abs() <= 1e-12 * (1.0 + e.abs()), "{g} vs {e}");
            }
        }
        assert!(
            band(&derivative).width() < w,
            "the band is narrower than the line"
        );
    }

    /// Both passes give, bit for bit, the banded sums taken one output at a time from zero
    /// in tap order (down the columns first, then along the rows): the lanes across a
    /// stencil's interior (blocks of 32 and 8) and the dot products near the folded mirror
    /// round alike. Float32, lines long enough for every block kind and shorter than a
    /// stencil, the anisotropy's operators and a rectangular one.
    #[test]
    fn the_passes_are_the_banded_sums_in_tap_order() {
        fn reference(x: &[f32], r: &Band<f32>, c: &Band<f32>) -> Vec<f32> {
            let (h, w, ho, wo) = (r.cols, c.cols, r.rows, c.rows);
            let mut out = Vec::new();
            for plane in x.chunks(h * w) {
                let mut down = vec![0.0f32; ho * w];
                for i in 0..ho {
                    for col in 0..w {
                        let mut acc = 0.0f32;
                        for u in 0..r.width {
                            acc += r.values[i * r.width + u] * plane[(r.start[i] + u) * w + col];
                        }
                        down[i * w + col] = acc;
                    }
                }
                for i in 0..ho {
                    for j in 0..wo {
                        let mut acc = 0.0f32;
                        for t in 0..c.width {
                            acc += c.values[j * c.width + t] * down[i * w + c.start[j] + t];
                        }
                        out.push(acc);
                    }
                }
            }
            out
        }
        let as_f32 = |m: &Matrix| {
            let data: Vec<f32> = m.data.iter().map(|&v| v as f32).collect();
            Band::from_row_major(m.rows, m.cols, &data)
        };
        for (h, w) in [(7, 5), (40, 83), (19, 300)] {
            let x: Vec<f32> = (0..3 * h * w)
                .map(|i| (((i * 7919) % 1009) as f32 / 1009.0 - 0.5) * 3.0)
                .collect();
            let smooth = |n| gaussian(n, 2.0).matmul(&gaussian(n, 0.5));
            let derivative = |n| {
                gaussian(n, 2.0).matmul(&central_difference_domain(n).matmul(&gaussian(n, 0.5)))
            };
            let half = Matrix::from_stencil(w, &[0.25, 0.5, 0.25]);
            let half = Matrix {
                rows: w / 2,
                cols: w,
                data: half.data[..(w / 2) * w].to_vec(),
            };
            for (r, c) in [
                (derivative(h), smooth(w)),
                (smooth(h), derivative(w)),
                (smooth(h), half),
            ] {
                let (r, c) = (as_f32(&r), as_f32(&c));
                let got = apply(&x, &r, &c);
                let want = reference(&x, &r, &c);
                assert!(
                    got.iter()
                        .zip(&want)
                        .all(|(g, e)| g.to_bits() == e.to_bits()),
                    "{h} × {w}: the passes round differently"
                );
                assert_eq!(got.len(), want.len());
            }
        }
    }

    /// The interior of a stencil is one stretch of shifted rows; the folded rows near
    /// either end stand alone.
    #[test]
    fn shifted_runs_cover_a_stencils_interior() {
        let b = band(&Matrix::from_stencil(12, &[0.25, 0.5, 0.25]));
        let runs = b.shifted_runs();
        assert_eq!(runs[0], 1, "the first row folds the mirror");
        assert_eq!(runs[1], 11, "rows 1 … 10 read the same taps, one column on");
        assert_eq!(runs[10], 11);
        assert_eq!(runs[11], 12, "the last row folds the mirror");
    }

    /// Rows whose span would run past the end start earlier, all-zero rows read zeros.
    #[test]
    fn band_keeps_every_row_in_bounds() {
        let m = Matrix {
            rows: 3,
            cols: 4,
            data: vec![1.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0, 0.0],
        };
        let b = band(&m);
        assert_eq!((b.width(), b.start.clone()), (2, vec![0, 2, 0]));
        assert_eq!(b.values, vec![1.0, 2.0, 0.0, 3.0, 0.0, 0.0]);
        let y = apply(&[1.0, 10.0, 100.0, 1000.0], &band(&Matrix::identity(1)), &b);
        assert_eq!(y, vec![21.0, 3000.0, 0.0]);
    }
}
