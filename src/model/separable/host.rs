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

use crate::model::cpu::{Real, channels_last_into, simd_dispatch};

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
    /// The band of the matrix with entries `entry(i, j)`, `i < rows`, `j < cols`.
    ///
    /// # Panics
    ///
    /// If the matrix is empty.
    pub fn new(rows: usize, cols: usize, entry: impl Fn(usize, usize) -> T) -> Self {
        assert!(
            rows > 0 && cols > 0,
            "a band of an empty {rows} × {cols} matrix"
        );
        // A NaN entry counts as nonzero, so it still reaches the output.
        let nonzero = |i: usize, j: usize| entry(i, j).to_f64() != 0.0;
        let spans: Vec<(usize, usize)> = (0..rows)
            .map(|i| match (0..cols).find(|&j| nonzero(i, j)) {
                Some(first) => {
                    let last = (first..cols)
                        .rev()
                        .find(|&j| nonzero(i, j))
                        .unwrap_or(first);
                    (first, last + 1 - first)
                }
                None => (0, 0),
            })
            .collect();
        let width = spans.iter().map(|&(_, len)| len).max().unwrap_or(0).max(1);
        let start: Vec<usize> = spans
            .iter()
            .map(|&(first, _)| first.min(cols - width))
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

    /// Columns read per row.
    pub fn width(&self) -> usize {
        self.width
    }
}

/// One output row of a pass along the first axis: `Σ_t taps[t] · source row (first + t)`, as
/// whole-row multiply-adds (unit stride, vectorised).
#[inline(always)]
fn combine_rows<T: Real>(taps: &[T], source: &[T], first: usize, out_row: &mut [T]) {
    let len = out_row.len();
    for (t, &weight) in taps.iter().enumerate() {
        let src = (first + t) * len;
        for (o, &v) in out_row.iter_mut().zip(&source[src..src + len]) {
            *o += weight * v;
        }
    }
}

simd_dispatch!(fn combine_rows_simd<T: Real>(
    taps: &[T], source: &[T], first: usize, out_row: &mut [T]
) => combine_rows);

/// `M · x` of every `n × m` plane of `x` (`M` is `band`, `n' × n`): each output row a weighted
/// sum of whole input rows, `[planes, n', m]`.
fn along_first_axis<T: Real>(x: &[T], band: &Band<T>, m: usize) -> Vec<T> {
    let (n, n_out) = (band.cols, band.rows);
    let planes = x.len() / (n * m);
    let mut out = vec![T::default(); planes * n_out * m];
    out.par_chunks_mut(m)
        .enumerate()
        .with_min_len((VALUES_PER_TASK / m).max(1))
        .for_each(|(r, out_row)| {
            let (p, i) = (r / n_out, r % n_out);
            let taps = &band.values[i * band.width..(i + 1) * band.width];
            combine_rows_simd(taps, &x[p * n * m..(p + 1) * n * m], band.start[i], out_row);
        });
    out
}

/// Every `n × m` plane of `x` transposed, `[planes, m, n]`: a plane's `n` rows laid out
/// channels-last.
fn transpose<T: Real>(x: &[T], n: usize, m: usize) -> Vec<T> {
    let mut out = vec![T::default(); x.len()];
    out.par_chunks_mut(n * m)
        .zip(x.par_chunks(n * m))
        .for_each(|(target, plane)| channels_last_into(plane, n, m, target));
    out
}

/// `R · x · Cᵀ` of every plane of `x`.
///
/// # Shapes
/// - `x`: `planes × H × W` values, row-major; `rows` (`R`): `H' × H`; `cols` (`C`): `W' × W`
/// - output: `planes × H' × W'`
pub fn apply<T: Real>(x: &[T], rows: &Band<T>, cols: &Band<T>) -> Vec<T> {
    let (h, w, ho, wo) = (rows.cols, cols.cols, rows.rows, cols.rows);
    assert_eq!(
        x.len() % (h * w),
        0,
        "separable: input is not whole {h} × {w} planes"
    );
    // Both passes as whole-row multiply-adds, along the columns, then along the rows of the
    // transposed planes, transposed back: a sum over taps along a row was a chain of dependent
    // adds per value (the two anisotropy operators on 3 × 256² took twice as long). Each
    // intermediate is dropped as soon as the next exists: two plane-sized buffers at a time,
    // as before the transposes (the path energy runs this on all `K` frames at once).
    let transposed = transpose(&along_first_axis(x, rows, w), ho, w);
    let along_w = along_first_axis(&transposed, cols, ho);
    drop(transposed);
    transpose(&along_w, wo, ho)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::stencil::{Matrix, central_difference_domain, gaussian};

    fn band(m: &Matrix) -> Band<f64> {
        Band::new(m.rows, m.cols, |i, j| m.get(i, j))
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
