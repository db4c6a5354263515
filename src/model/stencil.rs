//! One-dimensional linear operators on a grid line with mirror boundary, built on the host in
//! float64.
//!
//! Every stencil of the model (the cubic B-spline prefilter, the Gaussians, the central and
//! Sobel differences, bilinear resizing) acts separably on rows and columns. Here each 1-D
//! operator is written out as a dense `n_out × n_in` matrix with the whole-sample mirror
//! extension (SPEC §0) folded into its entries, so a stencil wider than the grid (the 13-tap
//! Gaussian on 10 rows reflects twice) needs no special case. [`crate::model::separable`] applies
//! a pair of them to tensors.

/// Whole-sample symmetric mirror index (SPEC §0): period `P = 2(n−1)`, `m(−1) = 1`,
/// `m(n) = n−2`.
///
/// # Panics
///
/// If `n < 2` (a mirror needs two samples).
pub fn mirror_index(i: i64, n: usize) -> usize {
    assert!(n >= 2, "mirror_index needs n >= 2, got {n}");
    let period = 2 * (n as i64 - 1);
    let r = i.rem_euclid(period);
    if r < n as i64 {
        r as usize
    } else {
        (period - r) as usize
    }
}

/// A dense row-major `rows × cols` matrix of float64 entries.
#[derive(Clone, Debug, PartialEq)]
pub struct Matrix {
    /// Number of rows (output length).
    pub rows: usize,
    /// Number of columns (input length).
    pub cols: usize,
    /// Row-major entries, `rows * cols` of them.
    pub data: Vec<f64>,
}

impl Matrix {
    /// The `rows × cols` zero matrix.
    pub fn zeros(rows: usize, cols: usize) -> Self {
        Self {
            rows,
            cols,
            data: vec![0.0; rows * cols],
        }
    }

    /// The `n × n` identity.
    pub fn identity(n: usize) -> Self {
        let mut m = Self::zeros(n, n);
        for i in 0..n {
            m.data[i * n + i] = 1.0;
        }
        m
    }

    /// Entry `(i, j)`.
    pub fn get(&self, i: usize, j: usize) -> f64 {
        self.data[i * self.cols + j]
    }

    fn add(&mut self, i: usize, j: usize, v: f64) {
        self.data[i * self.cols + j] += v;
    }

    /// A square operator from a centred stencil `taps[t]` at offset `t − radius`, reading
    /// mirrored samples: `(M x)(i) = Σ_t taps[t] · x(m(i + t − radius))`.
    pub fn from_stencil(n: usize, taps: &[f64]) -> Self {
        assert!(
            taps.len() % 2 == 1,
            "a centred stencil has an odd number of taps"
        );
        let radius = (taps.len() / 2) as i64;
        let mut m = Self::zeros(n, n);
        for i in 0..n {
            for (t, &w) in taps.iter().enumerate() {
                let j = mirror_index(i as i64 + t as i64 - radius, n);
                m.add(i, j, w);
            }
        }
        m
    }

    /// The matrix product `self · rhs`.
    pub fn matmul(&self, rhs: &Matrix) -> Matrix {
        assert_eq!(self.cols, rhs.rows, "matmul: inner dimensions differ");
        let mut out = Matrix::zeros(self.rows, rhs.cols);
        for i in 0..self.rows {
            for k in 0..self.cols {
                let a = self.get(i, k);
                if a == 0.0 {
                    continue;
                }
                for j in 0..rhs.cols {
                    out.data[i * rhs.cols + j] += a * rhs.get(k, j);
                }
            }
        }
        out
    }

    /// The transpose.
    pub fn transpose(&self) -> Matrix {
        let mut out = Matrix::zeros(self.cols, self.rows);
        for i in 0..self.rows {
            for j in 0..self.cols {
                out.data[j * self.rows + i] = self.get(i, j);
            }
        }
        out
    }
}

/// `z = √3 − 2`, the pole of the cubic B-spline interpolation filter.
pub const BSPLINE_POLE: f64 = -0.267_949_192_431_122_7;

/// Exact 1-D interpolating prefilter for the cubic B-spline with mirror boundary (SPEC §1).
///
/// It is the inverse of the mirrored tridiagonal matrix `A` with `A x (i) =
/// (x(m(i−1)) + 4 x(i) + x(m(i+1))) / 6`, i.e. the coefficients `c = P f` reproduce `f` at
/// every grid point. The folded matrix is still tridiagonal (`m(−1) = 1` is a neighbour of
/// 0), so the Thomas algorithm on the identity gives `P` in `O(n²)`.
///
/// Entries below [`PREFILTER_FLUSH`] in magnitude are set to zero: they decay like
/// `0.268^|i−j|` and from `|i − j| ≈ 65` on are float32 subnormals, which x86 multiplies
/// about 16× slower (a 67-channel 128² prefilter took 57 ms per pass instead of 3.5 ms). The
/// dropped mass is ten orders of magnitude below float32 resolution.
pub fn bspline_prefilter(n: usize) -> Matrix {
    let a = Matrix::from_stencil(n, &[1.0 / 6.0, 4.0 / 6.0, 1.0 / 6.0]);
    let mut p = solve_tridiagonal(&a, &Matrix::identity(n));
    for x in &mut p.data {
        if x.abs() < PREFILTER_FLUSH {
            *x = 0.0;
        }
    }
    p
}

/// Prefilter entries smaller than this are dropped (see [`bspline_prefilter`]).
pub const PREFILTER_FLUSH: f64 = 1e-18;

/// Solves `A X = B` for a tridiagonal `A` (only its three diagonals are read) by the
/// Thomas algorithm; `A` is diagonally dominant here, so no pivoting is needed.
fn solve_tridiagonal(a: &Matrix, b: &Matrix) -> Matrix {
    let n = a.rows;
    let (mut c_prime, mut x) = (vec![0.0; n], b.clone());
    let m = b.cols;
    let mut denom = a.get(0, 0);
    for j in 0..m {
        x.data[j] /= denom;
    }
    for i in 1..n {
        let upper = if i - 1 + 1 < n { a.get(i - 1, i) } else { 0.0 };
        c_prime[i - 1] = upper / denom;
        let lower = a.get(i, i - 1);
        denom = a.get(i, i) - lower * c_prime[i - 1];
        for j in 0..m {
            let prev = x.data[(i - 1) * m + j];
            x.data[i * m + j] = (x.data[i * m + j] - lower * prev) / denom;
        }
    }
    for i in (0..n - 1).rev() {
        for j in 0..m {
            let next = x.data[(i + 1) * m + j];
            x.data[i * m + j] -= c_prime[i] * next;
        }
    }
    x
}

/// Normalised discrete Gaussian taps `exp(−n²/(2s²))`, `|n| ≤ ⌈3s⌉` (SPEC §3).
pub fn gaussian_taps(s: f64) -> Vec<f64> {
    let radius = (3.0 * s).ceil() as i64;
    let raw: Vec<f64> = (-radius..=radius)
        .map(|k| (-((k * k) as f64) / (2.0 * s * s)).exp())
        .collect();
    let total: f64 = raw.iter().sum();
    raw.into_iter().map(|w| w / total).collect()
}

/// Gaussian smoothing `G_s ∗` with mirror boundary (SPEC §3).
pub fn gaussian(n: usize, s: f64) -> Matrix {
    Matrix::from_stencil(n, &gaussian_taps(s))
}

/// Central difference in domain units, `(g(m(i+1)) − g(m(i−1))) · (n−1)/2` (SPEC §3).
pub fn central_difference_domain(n: usize) -> Matrix {
    let s = (n as f64 - 1.0) / 2.0;
    Matrix::from_stencil(n, &[-s, 0.0, s])
}

/// The differencing half of the Sobel derivative in pixel units, `(g(i+1) − g(i−1)) / 2`
/// (SPEC §6). Combined with [`sobel_smoothing`] on the other axis it gives the SPEC's
/// `Σ_s w_s (g(i+1, j+s) − g(i−1, j+s)) / 8`.
pub fn sobel_difference(n: usize) -> Matrix {
    Matrix::from_stencil(n, &[-0.5, 0.0, 0.5])
}

/// The smoothing half of the Sobel derivative, `(1, 2, 1) / 4` (SPEC §6).
pub fn sobel_smoothing(n: usize) -> Matrix {
    Matrix::from_stencil(n, &[0.25, 0.5, 0.25])
}

/// Bilinear resampling with aligned corners from `n_in` to `n_out` samples (SPEC §7):
/// output sample `i` reads the input at `i · (n_in − 1)/(n_out − 1)`.
pub fn bilinear_resize(n_in: usize, n_out: usize) -> Matrix {
    assert!(
        n_in >= 2 && n_out >= 2,
        "bilinear_resize needs at least 2 samples"
    );
    let mut m = Matrix::zeros(n_out, n_in);
    let scale = (n_in - 1) as f64 / (n_out - 1) as f64;
    for i in 0..n_out {
        let x = i as f64 * scale;
        let i0 = (x.floor() as usize).min(n_in - 2);
        let t = x - i0 as f64;
        m.add(i, i0, 1.0 - t);
        m.add(i, i0 + 1, t);
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mirror_examples() {
        assert_eq!(mirror_index(-1, 5), 1);
        assert_eq!(mirror_index(5, 5), 3);
        assert_eq!(mirror_index(-9, 4), 3);
        assert_eq!(mirror_index(3, 2), 1);
    }

    #[test]
    fn prefilter_inverts_the_spline_sampling() {
        for n in [4, 9, 33] {
            let a = Matrix::from_stencil(n, &[1.0 / 6.0, 4.0 / 6.0, 1.0 / 6.0]);
            let p = bspline_prefilter(n);
            let id = a.matmul(&p);
            for i in 0..n {
                for j in 0..n {
                    let want = if i == j { 1.0 } else { 0.0 };
                    assert!((id.get(i, j) - want).abs() < 1e-13, "n={n} ({i},{j})");
                }
            }
        }
    }

    #[test]
    fn gaussian_rows_sum_to_one() {
        let g = gaussian(10, 2.0);
        for i in 0..10 {
            let s: f64 = (0..10).map(|j| g.get(i, j)).sum();
            assert!((s - 1.0).abs() < 1e-14);
        }
    }

    #[test]
    fn resize_keeps_corners_and_ramps() {
        let r = bilinear_resize(20, 10);
        let ramp: Vec<f64> = (0..20).map(|i| 3.0 * i as f64 + 1.0).collect();
        for i in 0..10 {
            let v: f64 = (0..20).map(|j| r.get(i, j) * ramp[j]).sum();
            let x = i as f64 * 19.0 / 9.0;
            assert!((v - (3.0 * x + 1.0)).abs() < 1e-12);
        }
    }
}
