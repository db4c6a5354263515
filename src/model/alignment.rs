//! SPEC §11's initial alignment: a global map `G` of the working domain (A's coordinates to
//! B's), estimated from the landmarks by least squares or from the images by normalised
//! cross-correlation, and its `K`-th root `G_{1/K} = exp(log(G)/K)`, the fraction of it each
//! step starts from.
//!
//! Points are `[row, col]` in pixel units, like the deformations (SPEC §0); a map is the
//! homogeneous 3 × 3 matrix acting on `[row, col, 1]`. What a user reads (translation,
//! rotation, scale) is said in image terms: `x` = column, `y` = row, a positive angle turns
//! counter-clockwise as seen on the screen.

use crate::error::{Error, Result};
use crate::model::energy::landmarks::Landmarks;
use crate::model::stencil::{Matrix, gaussian};

/// A 3 × 3 matrix, row-major.
pub type Matrix3 = [[f64; 3]; 3];

/// Which global map `--align` estimates.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum AlignKind {
    /// No alignment: the coarsest level starts at `φ = Id` (the paper).
    #[default]
    None,
    /// Translation, rotation and one scale (4 parameters; at least 2 landmarks).
    Similarity,
    /// A general orientation-preserving affine map (6 parameters; at least 3 landmarks not on
    /// one line).
    Affine,
}

impl AlignKind {
    /// Whether this is [`AlignKind::None`].
    pub fn is_none(&self) -> bool {
        *self == Self::None
    }

    /// The name the CLI and `config.json` use.
    pub fn name(self) -> &'static str {
        match self {
            Self::None => "none",
            Self::Similarity => "similarity",
            Self::Affine => "affine",
        }
    }
}

/// An orientation-preserving affine map of the plane, `[row, col, 1] ↦ M [row, col, 1]`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GlobalMap {
    matrix: Matrix3,
}

/// What a user reads of a [`GlobalMap`]: its parts in image terms.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct MapSummary {
    /// Where the centre of the domain goes, minus the centre: `[dx, dy]` in pixels.
    pub translation: [f64; 2],
    /// The rotation of the map's polar factor, degrees, counter-clockwise on screen.
    pub rotation_degrees: f64,
    /// `sqrt(det)`: the change of area's square root (the scale of a similarity).
    pub scale: f64,
    /// The ratio of the larger to the smaller singular value of the linear part (1 for a
    /// similarity): how far from a similarity the map is.
    pub anisotropy: f64,
}

impl GlobalMap {
    /// The identity.
    pub fn identity() -> Self {
        Self { matrix: IDENTITY }
    }

    /// The map with homogeneous matrix `matrix` (bottom row `[0, 0, 1]`).
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] if the bottom row is not `[0, 0, 1]`, an entry is not
    /// finite, or the map does not preserve orientation (`det ≤ 0`: a reflection or a
    /// collapse).
    pub fn new(matrix: Matrix3) -> Result<Self> {
        if matrix.iter().flatten().any(|v| !v.is_finite()) || matrix[2] != [0.0, 0.0, 1.0] {
            return Err(Error::invalid(
                "global map",
                format!("{matrix:?}"),
                "finite entries and the bottom row [0, 0, 1]",
            ));
        }
        let det = matrix[0][0] * matrix[1][1] - matrix[0][1] * matrix[1][0];
        if det <= 0.0 {
            return Err(Error::invalid(
                "global map",
                format!("a linear part with determinant {det:.4}"),
                "a positive determinant: a reflection or a collapse cannot start a \
                 diffeomorphic path (are the points of A and B listed in the same order?)",
            ));
        }
        Ok(Self { matrix })
    }

    /// The homogeneous matrix.
    pub fn matrix(&self) -> Matrix3 {
        self.matrix
    }

    /// The map in image terms `x` = column, `y` = row: `[[a, b, t_x], [c, d, t_y]]` with
    /// `x' = a x + b y + t_x`, `y' = c x + d y + t_y`.
    pub fn matrix_xy(&self) -> [[f64; 3]; 2] {
        let m = &self.matrix;
        [[m[1][1], m[1][0], m[1][2]], [m[0][1], m[0][0], m[0][2]]]
    }

    /// Whether this is exactly the identity.
    pub fn is_identity(&self) -> bool {
        self.matrix == IDENTITY
    }

    /// The image of `[row, col]`.
    pub fn apply(&self, [r, c]: [f64; 2]) -> [f64; 2] {
        let m = &self.matrix;
        [
            m[0][0] * r + m[0][1] * c + m[0][2],
            m[1][0] * r + m[1][1] * c + m[1][2],
        ]
    }

    /// The same map in the pixel coordinates of a grid of `to` = `(rows, cols)` pixels, the
    /// map being given on a grid of `from` pixels, by SPEC §7's align-corners rule
    /// (`row_ℓ = row · (H_ℓ − 1)/(H − 1)`, the same for columns).
    pub fn on_grid(&self, from: (usize, usize), to: (usize, usize)) -> Self {
        let ratio = |to: usize, from: usize| {
            if from > 1 {
                (to as f64 - 1.0) / (from as f64 - 1.0)
            } else {
                1.0
            }
        };
        let (sr, sc) = (ratio(to.0, from.0), ratio(to.1, from.1));
        let scale = [[sr, 0.0, 0.0], [0.0, sc, 0.0], [0.0, 0.0, 1.0]];
        let unscale = [[1.0 / sr, 0.0, 0.0], [0.0, 1.0 / sc, 0.0], [0.0, 0.0, 1.0]];
        Self {
            matrix: mul(&mul(&scale, &self.matrix), &unscale),
        }
    }

    /// The principal `k`-th root `G_{1/k} = exp(log(G)/k)` (SPEC §11): the map each of `k`
    /// equal steps applies, so that their composition is `G`. Computed by inverse scaling
    /// and squaring (Denman–Beavers square roots until the map is near the identity, a
    /// series for the logarithm there) and the exponential by scaling and squaring.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] if the linear part has a negative real eigenvalue (a half
    /// turn, or a flip along one axis): no real principal root exists.
    pub fn root(&self, k: usize) -> Result<Self> {
        if k <= 1 || self.is_identity() {
            return Ok(*self);
        }
        let m = &self.matrix;
        let (tr, det) = (m[0][0] + m[1][1], m[0][0] * m[1][1] - m[0][1] * m[1][0]);
        let disc = tr * tr - 4.0 * det;
        if disc >= 0.0 && (tr - disc.sqrt()) <= 0.0 {
            return Err(Error::invalid(
                "global map",
                format!(
                    "a linear part with the real eigenvalues {:.4} and {:.4}",
                    (tr - disc.sqrt()) / 2.0,
                    (tr + disc.sqrt()) / 2.0
                ),
                "no negative eigenvalue (a half turn has no principal root to share among \
                 the steps)",
            ));
        }
        let log = logm(&self.matrix);
        let mut root = expm(&scaled(&log, 1.0 / k as f64));
        // The bottom row is exactly [0, 0, 1] in exact arithmetic.
        root[2] = [0.0, 0.0, 1.0];
        Ok(Self { matrix: root })
    }

    /// The map in image terms, about the centre of a domain of `size` = `(rows, cols)`.
    pub fn summary(&self, (rows, cols): (usize, usize)) -> MapSummary {
        let centre = [(rows as f64 - 1.0) / 2.0, (cols as f64 - 1.0) / 2.0];
        let moved = self.apply(centre);
        let m = &self.matrix;
        // In (x, y) = (col, row): x' = a x + b y, y' = c x + d y.
        let (a, b, c, d) = (m[1][1], m[1][0], m[0][1], m[0][0]);
        let det = a * d - b * c;
        // The polar factor's angle; on screen (y down) a counter-clockwise turn by θ has
        // b = sin θ, c = −sin θ.
        let rotation = (b - c).atan2(a + d).to_degrees();
        let frobenius = a * a + b * b + c * c + d * d;
        let gap = (frobenius * frobenius - 4.0 * det * det).max(0.0).sqrt();
        let (s_max, s_min) = (
            ((frobenius + gap) / 2.0).sqrt(),
            ((frobenius - gap) / 2.0).max(0.0).sqrt(),
        );
        MapSummary {
            translation: [moved[1] - centre[1], moved[0] - centre[0]],
            rotation_degrees: rotation,
            scale: det.max(0.0).sqrt(),
            anisotropy: if s_min > 0.0 {
                s_max / s_min
            } else {
                f64::INFINITY
            },
        }
    }

    /// The least-squares map of `kind` taking the landmarks' points of A to those of B
    /// (SPEC §11): a similarity in closed form (complex least squares, which cannot
    /// reflect), an affine map from the normal equations.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] for too few pairs (similarity 2, affine 3), points of A
    /// that are all one point or (affine) on one line, or a fit that reflects.
    pub fn from_landmarks(landmarks: &Landmarks, kind: AlignKind) -> Result<Self> {
        let (a, b) = landmarks.pairs();
        let n = a.len() as f64;
        let mean = |p: &[[f64; 2]]| {
            let s = p.iter().fold([0.0, 0.0], |s, q| [s[0] + q[0], s[1] + q[1]]);
            [s[0] / n, s[1] / n]
        };
        let (ma, mb) = (mean(a), mean(b));
        let spread: f64 = a
            .iter()
            .map(|p| (p[0] - ma[0]).powi(2) + (p[1] - ma[1]).powi(2))
            .sum();
        let needed = match kind {
            AlignKind::None => return Ok(Self::identity()),
            AlignKind::Similarity => 2,
            AlignKind::Affine => 3,
        };
        if a.len() < needed || spread <= 1e-12 {
            return Err(Error::invalid(
                "--align",
                format!("{} from {} landmark pair(s)", kind.name(), a.len()),
                format!(
                    "at least {needed} pairs whose points in A are not all one point (or \
                     --align without --points, to estimate the map from the images)"
                ),
            ));
        }
        match kind {
            AlignKind::Similarity => {
                // z = col + i·row; w = α z + β with α complex is orientation-preserving.
                let (mut re, mut im) = (0.0, 0.0);
                for (p, q) in a.iter().zip(b) {
                    let (zx, zy) = (p[1] - ma[1], p[0] - ma[0]);
                    let (wx, wy) = (q[1] - mb[1], q[0] - mb[0]);
                    // conj(z) · w
                    re += zx * wx + zy * wy;
                    im += zx * wy - zy * wx;
                }
                let (ar, ai) = (re / spread, im / spread);
                // x' = ar x − ai y + tx, y' = ai x + ar y + ty, in [row, col] rows.
                let linear = [[ar, ai], [-ai, ar]];
                Self::with_linear(linear, ma, mb)
            }
            AlignKind::Affine => {
                let mut cov = [[0.0; 2]; 2];
                let mut cross = [[0.0; 2]; 2];
                for (p, q) in a.iter().zip(b) {
                    let dp = [p[0] - ma[0], p[1] - ma[1]];
                    let dq = [q[0] - mb[0], q[1] - mb[1]];
                    for i in 0..2 {
                        for j in 0..2 {
                            cov[i][j] += dp[i] * dp[j];
                            cross[i][j] += dq[i] * dp[j];
                        }
                    }
                }
                let det = cov[0][0] * cov[1][1] - cov[0][1] * cov[1][0];
                if det <= 1e-9 * spread * spread {
                    return Err(Error::invalid(
                        "--align",
                        format!("affine from {} landmark pairs on one line", a.len()),
                        "at least 3 points of A not on one line (or --align similarity)",
                    ));
                }
                let inv = [
                    [cov[1][1] / det, -cov[0][1] / det],
                    [-cov[1][0] / det, cov[0][0] / det],
                ];
                let mut linear = [[0.0; 2]; 2];
                for i in 0..2 {
                    for j in 0..2 {
                        linear[i][j] = cross[i][0] * inv[0][j] + cross[i][1] * inv[1][j];
                    }
                }
                Self::with_linear(linear, ma, mb).map_err(|_| {
                    Error::invalid(
                        "--align",
                        "affine: the landmarks' best affine map reflects the image",
                        "pairs listed in the same order in A and B, or --align similarity",
                    )
                })
            }
            AlignKind::None => unreachable!("returned above"),
        }
    }

    /// The map with linear part `linear` (on `[row, col]`) taking `from` to `to`.
    fn with_linear(linear: [[f64; 2]; 2], from: [f64; 2], to: [f64; 2]) -> Result<Self> {
        let t = [
            to[0] - linear[0][0] * from[0] - linear[0][1] * from[1],
            to[1] - linear[1][0] * from[0] - linear[1][1] * from[1],
        ];
        Self::new([
            [linear[0][0], linear[0][1], t[0]],
            [linear[1][0], linear[1][1], t[1]],
            [0.0, 0.0, 1.0],
        ])
    }

    /// The similarity turning by `degrees` (counter-clockwise on screen) and scaling by
    /// `scale` about `centre`, then translating by `[dx, dy]`.
    pub fn similarity(centre: [f64; 2], degrees: f64, scale: f64, [dx, dy]: [f64; 2]) -> Self {
        let (s, c) = degrees.to_radians().sin_cos();
        // x' = scale (c x + s y), y' = scale (−s x + c y), written on [row, col].
        let linear = [[scale * c, -scale * s], [scale * s, scale * c]];
        Self::with_linear(linear, centre, [centre[0] + dy, centre[1] + dx])
            .expect("a similarity with a positive scale preserves orientation")
    }
}

const IDENTITY: Matrix3 = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

fn mul(a: &Matrix3, b: &Matrix3) -> Matrix3 {
    let mut m = [[0.0; 3]; 3];
    for (i, row) in m.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = (0..3).map(|l| a[i][l] * b[l][j]).sum();
        }
    }
    m
}

fn add(a: &Matrix3, b: &Matrix3) -> Matrix3 {
    let mut m = *a;
    for (row, brow) in m.iter_mut().zip(b) {
        for (v, w) in row.iter_mut().zip(brow) {
            *v += w;
        }
    }
    m
}

fn scaled(a: &Matrix3, s: f64) -> Matrix3 {
    a.map(|row| row.map(|v| v * s))
}

/// The maximum absolute row sum.
fn norm(a: &Matrix3) -> f64 {
    a.iter()
        .map(|row| row.iter().map(|v| v.abs()).sum::<f64>())
        .fold(0.0, f64::max)
}

fn inverse(a: &Matrix3) -> Matrix3 {
    let cof = |i: usize, j: usize| {
        let (r0, r1) = ((i + 1) % 3, (i + 2) % 3);
        let (c0, c1) = ((j + 1) % 3, (j + 2) % 3);
        a[r0][c0] * a[r1][c1] - a[r0][c1] * a[r1][c0]
    };
    let det: f64 = (0..3).map(|j| a[0][j] * cof(0, j)).sum();
    let mut inv = [[0.0; 3]; 3];
    for (i, row) in inv.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = cof(j, i) / det;
        }
    }
    inv
}

/// The principal square root by the Denman–Beavers iteration.
fn sqrtm(a: &Matrix3) -> Matrix3 {
    let (mut y, mut z) = (*a, IDENTITY);
    for _ in 0..100 {
        let y_next = scaled(&add(&y, &inverse(&z)), 0.5);
        let z_next = scaled(&add(&z, &inverse(&y)), 0.5);
        let change = norm(&add(&y_next, &scaled(&y, -1.0)));
        (y, z) = (y_next, z_next);
        if change <= 1e-15 * norm(&y) {
            break;
        }
    }
    y
}

/// The principal logarithm by inverse scaling and squaring.
fn logm(a: &Matrix3) -> Matrix3 {
    let mut x = *a;
    let mut halvings = 0;
    while norm(&add(&x, &scaled(&IDENTITY, -1.0))) > 0.25 && halvings < 40 {
        x = sqrtm(&x);
        halvings += 1;
    }
    // log(I + E) = Σ (−1)^{j+1} E^j / j; ‖E‖ ≤ 1/4, so 40 terms are below 1e-24.
    let e = add(&x, &scaled(&IDENTITY, -1.0));
    let (mut power, mut sum) = (e, e);
    for j in 2..=40 {
        power = mul(&power, &e);
        let sign = if j % 2 == 0 { -1.0 } else { 1.0 };
        sum = add(&sum, &scaled(&power, sign / j as f64));
    }
    scaled(&sum, (1u64 << halvings) as f64)
}

/// The exponential by scaling and squaring.
fn expm(a: &Matrix3) -> Matrix3 {
    let mut squarings = 0;
    while norm(a) / (1u64 << squarings) as f64 > 0.5 && squarings < 60 {
        squarings += 1;
    }
    let x = scaled(a, 1.0 / (1u64 << squarings) as f64);
    let (mut term, mut sum) = (IDENTITY, IDENTITY);
    for j in 1..=24 {
        term = scaled(&mul(&term, &x), 1.0 / j as f64);
        sum = add(&sum, &term);
    }
    for _ in 0..squarings {
        sum = mul(&sum, &sum);
    }
    sum
}

/// The search of [`estimate_from_images`]: its ranges, on the grid it runs on.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SearchRanges {
    /// The largest shift tried, as a fraction of each side (both directions, in steps of
    /// one pixel).
    pub shift: f64,
    /// The largest turn tried, degrees (both directions, in steps of `rotation_step`).
    pub rotation: f64,
    /// The step of the turns tried, degrees.
    pub rotation_step: f64,
    /// The scales tried: `2^(j/4)` for `|j| ≤ scale_steps`.
    pub scale_steps: i32,
    /// The least part of A's pixels that must land inside B for a map to count.
    pub overlap: f64,
}

impl Default for SearchRanges {
    /// Shifts up to 30 % of each side, turns up to ±30° in 5° steps, scales 2^(±1/2)
    /// (0.71–1.41) in steps of 2^(1/4), at least half of A overlapping B.
    fn default() -> Self {
        Self {
            shift: 0.3,
            rotation: 30.0,
            rotation_step: 5.0,
            scale_steps: 2,
            overlap: 0.5,
        }
    }
}

/// What [`estimate_from_images`] found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImageAlignment {
    /// The map, in the pixel coordinates of the grid the images were given on.
    pub map: GlobalMap,
    /// The normalised cross-correlation it reaches.
    pub ncc: f64,
    /// The normalised cross-correlation of the identity (no alignment).
    pub ncc_identity: f64,
}

/// A grey image on a small grid, for the search.
#[derive(Clone, Debug)]
pub struct GreyImage {
    values: Vec<f64>,
    rows: usize,
    cols: usize,
}

impl GreyImage {
    /// The luma (Rec. 601) of an RGB image given as planes `[3, rows, cols]`, blurred by a
    /// Gaussian of `sigma` pixels (mirror boundary), which smooths the correlation's
    /// landscape for the search.
    ///
    /// # Errors
    ///
    /// If `rgb` does not hold `3 · rows · cols` values, or a side is below 2.
    pub fn from_rgb_planes(rgb: &[f64], rows: usize, cols: usize, sigma: f64) -> Result<Self> {
        let n = rows * cols;
        if rgb.len() != 3 * n || rows < 2 || cols < 2 {
            return Err(Error::Shape {
                op: "grey image",
                detail: format!("{} values for 3 x {rows} x {cols}", rgb.len()),
            });
        }
        let luma: Vec<f64> = (0..n)
            .map(|i| 0.299 * rgb[i] + 0.587 * rgb[n + i] + 0.114 * rgb[2 * n + i])
            .collect();
        // SPEC §3's Gaussian with its mirror boundary, along columns then rows.
        let image = Matrix {
            rows,
            cols,
            data: luma,
        };
        let values = gaussian(rows, sigma)
            .matmul(&image)
            .matmul(&gaussian(cols, sigma).transpose())
            .data;
        Ok(Self { values, rows, cols })
    }

    /// Bilinear value at `[row, col]`, `None` outside the image.
    fn at(&self, [r, c]: [f64; 2]) -> Option<f64> {
        let (hr, hc) = ((self.rows - 1) as f64, (self.cols - 1) as f64);
        if !(0.0..=hr).contains(&r) || !(0.0..=hc).contains(&c) {
            return None;
        }
        // Both sides are at least 2 (`from_rgb_planes`): the cell's far corner is inside.
        let (r0, c0) = (
            (r.floor() as usize).min(self.rows - 2),
            (c.floor() as usize).min(self.cols - 2),
        );
        let (fr, fc) = (r - r0 as f64, c - c0 as f64);
        let v = |i: usize, j: usize| self.values[i * self.cols + j];
        Some(
            (1.0 - fr) * ((1.0 - fc) * v(r0, c0) + fc * v(r0, c0 + 1))
                + fr * ((1.0 - fc) * v(r0 + 1, c0) + fc * v(r0 + 1, c0 + 1)),
        )
    }

    /// The normalised cross-correlation of `self(x)` and `other(G(x))` over the pixels `x`
    /// that `G` keeps inside `other`; `None` when fewer than `overlap` of them do or either
    /// side is flat there.
    fn ncc(&self, other: &Self, map: &GlobalMap, overlap: f64) -> Option<f64> {
        let (mut n, mut sa, mut sb, mut saa, mut sbb, mut sab) = (0usize, 0.0, 0.0, 0.0, 0.0, 0.0);
        for r in 0..self.rows {
            for c in 0..self.cols {
                let Some(b) = other.at(map.apply([r as f64, c as f64])) else {
                    continue;
                };
                let a = self.values[r * self.cols + c];
                n += 1;
                (sa, sb) = (sa + a, sb + b);
                (saa, sbb, sab) = (saa + a * a, sbb + b * b, sab + a * b);
            }
        }
        if (n as f64) < overlap * (self.rows * self.cols) as f64 || n < 4 {
            return None;
        }
        let nf = n as f64;
        let (va, vb) = (saa - sa * sa / nf, sbb - sb * sb / nf);
        let cov = sab - sa * sb / nf;
        (va > 1e-12 && vb > 1e-12).then(|| cov / (va * vb).sqrt())
    }
}

/// SPEC §11's alignment from the images: maximise the normalised cross-correlation of
/// `a(x)` and `b(G(x))` (blurred grey images, on the coarsest level) by a grid search over
/// `ranges` (translation, rotation about the centre, scale), then a Nelder–Mead refinement
/// over the map's parameters (4 for a similarity, 6 for an affine map, kept
/// orientation-preserving). The map is in `a`'s pixel coordinates.
///
/// # Errors
///
/// If the images differ in size, or either is flat (nothing to correlate).
pub fn estimate_from_images(
    a: &GreyImage,
    b: &GreyImage,
    kind: AlignKind,
    ranges: &SearchRanges,
) -> Result<ImageAlignment> {
    if (a.rows, a.cols) != (b.rows, b.cols) {
        return Err(Error::Shape {
            op: "alignment",
            detail: format!(
                "A is {}x{} and B {}x{} (rows x columns)",
                a.rows, a.cols, b.rows, b.cols
            ),
        });
    }
    let ncc_identity = a
        .ncc(b, &GlobalMap::identity(), ranges.overlap)
        .ok_or_else(|| {
            Error::invalid(
                "--align",
                "images without contrast on the coarsest level",
                "images with some structure to correlate (or --points)",
            )
        })?;
    if kind == AlignKind::None {
        return Ok(ImageAlignment {
            map: GlobalMap::identity(),
            ncc: ncc_identity,
            ncc_identity,
        });
    }
    let centre = [(a.rows as f64 - 1.0) / 2.0, (a.cols as f64 - 1.0) / 2.0];
    let (max_dy, max_dx) = (
        (ranges.shift * a.rows as f64).floor() as i64,
        (ranges.shift * a.cols as f64).floor() as i64,
    );
    let turns = (ranges.rotation / ranges.rotation_step).floor() as i64;
    // Ties go to the smallest map: the candidates are visited outward from the identity
    // and only a strictly better one replaces the best.
    let mut best = (ncc_identity, [0.0, 0.0, 0.0, 0.0]);
    let order = |m: i64| {
        let mut v: Vec<i64> = (-m..=m).collect();
        v.sort_by_key(|x| x.abs());
        v
    };
    for j in order(ranges.scale_steps as i64) {
        let scale = 2f64.powf(j as f64 / 4.0);
        for t in order(turns) {
            let degrees = t as f64 * ranges.rotation_step;
            for dy in order(max_dy) {
                for dx in order(max_dx) {
                    let map = GlobalMap::similarity(centre, degrees, scale, [dx as f64, dy as f64]);
                    if let Some(ncc) = a.ncc(b, &map, ranges.overlap)
                        && ncc > best.0
                    {
                        best = (ncc, [dx as f64, dy as f64, degrees, scale.ln()]);
                    }
                }
            }
        }
    }
    let similarity = |p: &[f64]| GlobalMap::similarity(centre, p[2], p[3].exp(), [p[0], p[1]]);
    let cost = |map: Option<GlobalMap>| {
        map.and_then(|m| a.ncc(b, &m, ranges.overlap))
            .map_or(f64::INFINITY, |ncc| -ncc)
    };
    // The refinement stays within a step of the searched ranges: beyond them the
    // correlation of small blurred images has directions it barely sees (a turn about a
    // round object), and the search said nothing of them.
    let bounds = [
        max_dx as f64 + 1.0,
        max_dy as f64 + 1.0,
        ranges.rotation + ranges.rotation_step,
        (ranges.scale_steps as f64 + 1.0) / 4.0 * std::f64::consts::LN_2,
    ];
    let inside = |p: &[f64]| p.iter().zip(&bounds).all(|(v, b)| v.abs() <= *b);
    let start = best.1;
    let steps = [0.5, 0.5, ranges.rotation_step / 2.0, 0.05];
    let refined = nelder_mead(
        &start,
        &steps,
        |p| {
            if inside(p) {
                cost(Some(similarity(p)))
            } else {
                f64::INFINITY
            }
        },
        400,
    );
    let mut map = similarity(&refined);
    if kind == AlignKind::Affine {
        let base = map.matrix();
        // The six entries as offsets from the similarity, each scaled to about a pixel's
        // effect across the domain.
        let unit = 1.0 / (a.rows.max(a.cols) as f64);
        let affine = |p: &[f64]| {
            let mut m = base;
            m[0][0] += p[0] * unit;
            m[0][1] += p[1] * unit;
            m[1][0] += p[2] * unit;
            m[1][1] += p[3] * unit;
            m[0][2] += p[4];
            m[1][2] += p[5];
            GlobalMap::new(m).ok()
        };
        let refined = nelder_mead(
            &[0.0; 6],
            &[2.0, 2.0, 2.0, 2.0, 0.5, 0.5],
            |p| cost(affine(p)),
            800,
        );
        if let Some(m) = affine(&refined) {
            map = m;
        }
    }
    let ncc = -cost(Some(map));
    Ok(ImageAlignment {
        map,
        ncc,
        ncc_identity,
    })
}

/// Minimises `f` from `start` by the Nelder–Mead simplex (standard coefficients), the
/// initial simplex spanned by `steps` along each axis; at most `evaluations` calls.
fn nelder_mead(
    start: &[f64],
    steps: &[f64],
    f: impl Fn(&[f64]) -> f64,
    evaluations: usize,
) -> Vec<f64> {
    let n = start.len();
    let mut simplex: Vec<(Vec<f64>, f64)> = (0..=n)
        .map(|i| {
            let mut p = start.to_vec();
            if i > 0 {
                p[i - 1] += steps[i - 1];
            }
            let v = f(&p);
            (p, v)
        })
        .collect();
    let mut calls = n + 1;
    let point = |from: &[f64], to: &[f64], t: f64| -> Vec<f64> {
        from.iter().zip(to).map(|(a, b)| a + t * (b - a)).collect()
    };
    while calls < evaluations {
        simplex.sort_by(|x, y| x.1.total_cmp(&y.1));
        let spread = simplex[n].1 - simplex[0].1;
        if spread.is_finite() && spread.abs() < 1e-10 {
            break;
        }
        let centroid: Vec<f64> = (0..n)
            .map(|j| simplex[..n].iter().map(|(p, _)| p[j]).sum::<f64>() / n as f64)
            .collect();
        let worst = simplex[n].clone();
        let reflected = point(&centroid, &worst.0, -1.0);
        let fr = f(&reflected);
        calls += 1;
        if fr < simplex[0].1 {
            let expanded = point(&centroid, &worst.0, -2.0);
            let fe = f(&expanded);
            calls += 1;
            simplex[n] = if fe < fr {
                (expanded, fe)
            } else {
                (reflected, fr)
            };
        } else if fr < simplex[n - 1].1 {
            simplex[n] = (reflected, fr);
        } else {
            let contracted = point(&centroid, &worst.0, 0.5);
            let fc = f(&contracted);
            calls += 1;
            if fc < worst.1 {
                simplex[n] = (contracted, fc);
            } else {
                let best = simplex[0].0.clone();
                for item in simplex.iter_mut().skip(1) {
                    let p = point(&best, &item.0, 0.5);
                    let v = f(&p);
                    *item = (p, v);
                }
                calls += n;
            }
        }
    }
    simplex.sort_by(|x, y| x.1.total_cmp(&y.1));
    simplex.swap_remove(0).0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: &Matrix3, b: &Matrix3, tol: f64) -> bool {
        a.iter()
            .flatten()
            .zip(b.iter().flatten())
            .all(|(x, y)| (x - y).abs() <= tol)
    }

    fn power(m: &Matrix3, k: usize) -> Matrix3 {
        (1..k).fold(*m, |p, _| mul(&p, m))
    }

    #[test]
    fn the_root_composes_back_to_the_map() {
        let maps = [
            GlobalMap::similarity([20.0, 30.0], 25.0, 1.3, [7.0, -4.0]),
            GlobalMap::similarity([0.0, 0.0], -170.0, 0.8, [0.0, 0.0]),
            GlobalMap::new([[1.2, 0.3, 5.0], [-0.1, 0.9, -2.0], [0.0, 0.0, 1.0]]).unwrap(),
        ];
        for map in maps {
            for k in [2, 7, 15] {
                let root = map.root(k).unwrap();
                assert!(
                    close(&power(&root.matrix(), k), &map.matrix(), 1e-10),
                    "{map:?} k={k}"
                );
            }
        }
        // A translation's root is the k-th of it; a turn's root turns by the k-th angle.
        let shift = GlobalMap::similarity([0.0, 0.0], 0.0, 1.0, [6.0, 3.0])
            .root(3)
            .unwrap();
        assert!(close(
            &shift.matrix(),
            &[[1.0, 0.0, 1.0], [0.0, 1.0, 2.0], [0.0, 0.0, 1.0]],
            1e-12
        ));
        let turn = GlobalMap::similarity([5.0, 5.0], 60.0, 1.0, [0.0, 0.0])
            .root(4)
            .unwrap();
        assert!((turn.summary((11, 11)).rotation_degrees - 15.0).abs() < 1e-9);
    }

    #[test]
    fn a_half_turn_and_a_reflection_are_refused() {
        let half = GlobalMap::new([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]).unwrap();
        assert!(half.root(3).unwrap_err().to_string().contains("half turn"));
        let flip = GlobalMap::new([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]);
        assert!(flip.unwrap_err().to_string().contains("reflection"));
    }

    #[test]
    fn the_summary_reads_the_parts_back() {
        let map = GlobalMap::similarity([15.0, 20.0], 12.0, 1.25, [3.0, -2.0]);
        let s = map.summary((31, 41));
        assert!((s.rotation_degrees - 12.0).abs() < 1e-12, "{s:?}");
        assert!((s.scale - 1.25).abs() < 1e-12);
        assert!((s.translation[0] - 3.0).abs() < 1e-12 && (s.translation[1] + 2.0).abs() < 1e-12);
        assert!((s.anisotropy - 1.0).abs() < 1e-12);
        // Counter-clockwise on screen: the point right of the centre moves up (smaller row).
        let right = map.apply([15.0, 21.0]);
        let centre = map.apply([15.0, 20.0]);
        assert!(right[0] < centre[0]);
    }

    #[test]
    fn landmarks_give_the_map_they_were_made_with() {
        let truth = GlobalMap::similarity([30.0, 40.0], -20.0, 0.9, [5.0, 3.0]);
        let a = vec![[20.0, 25.0], [40.0, 30.0], [35.0, 60.0], [22.0, 50.0]];
        let b = a.iter().map(|&p| truth.apply(p)).collect();
        let landmarks = Landmarks::new(a.clone(), b, (64, 80)).unwrap();
        for kind in [AlignKind::Similarity, AlignKind::Affine] {
            let fit = GlobalMap::from_landmarks(&landmarks, kind).unwrap();
            assert!(close(&fit.matrix(), &truth.matrix(), 1e-9), "{kind:?}");
        }
        let affine = GlobalMap::new([[1.1, 0.2, 3.0], [-0.1, 0.95, 1.0], [0.0, 0.0, 1.0]]).unwrap();
        let b = a.iter().map(|&p| affine.apply(p)).collect();
        let landmarks = Landmarks::new(a.clone(), b, (64, 80)).unwrap();
        let fit = GlobalMap::from_landmarks(&landmarks, AlignKind::Affine).unwrap();
        assert!(close(&fit.matrix(), &affine.matrix(), 1e-9));
        // Mirrored pairs, too few pairs and collinear pairs are refused.
        let mirrored = a.iter().map(|&[r, c]| [r, 79.0 - c]).collect();
        let landmarks = Landmarks::new(a.clone(), mirrored, (64, 80)).unwrap();
        let err = GlobalMap::from_landmarks(&landmarks, AlignKind::Affine).unwrap_err();
        assert!(err.to_string().contains("reflects"), "{err}");
        let one = Landmarks::new(vec![a[0]], vec![a[1]], (64, 80)).unwrap();
        let err = GlobalMap::from_landmarks(&one, AlignKind::Similarity).unwrap_err();
        assert!(err.to_string().contains("at least 2"), "{err}");
        let line = vec![[10.0, 10.0], [20.0, 20.0], [30.0, 30.0]];
        let landmarks = Landmarks::new(line.clone(), line, (64, 80)).unwrap();
        let err = GlobalMap::from_landmarks(&landmarks, AlignKind::Affine).unwrap_err();
        assert!(err.to_string().contains("one line"), "{err}");
    }

    #[test]
    fn on_grid_conjugates_by_the_align_corners_scaling() {
        let map = GlobalMap::similarity([10.0, 10.0], 10.0, 1.1, [4.0, 2.0]);
        let coarse = map.on_grid((65, 65), (17, 17));
        let p = [3.0, 5.0];
        let fine = map.apply([p[0] * 4.0, p[1] * 4.0]);
        let q = coarse.apply(p);
        assert!((q[0] * 4.0 - fine[0]).abs() < 1e-12 && (q[1] * 4.0 - fine[1]).abs() < 1e-12);
    }

    /// A blob pattern moved by a known similarity is found again to a fraction of a pixel
    /// and a degree.
    #[test]
    fn the_image_search_finds_a_known_similarity() {
        let (rows, cols) = (32, 32);
        let pattern = |r: f64, c: f64| {
            let blob = |r0: f64, c0: f64, s: f64| {
                (-((r - r0).powi(2) + (c - c0).powi(2)) / (2.0 * s * s)).exp()
            };
            blob(12.0, 13.0, 3.0) + 0.7 * blob(19.0, 18.0, 2.5) + 0.5 * blob(14.0, 21.0, 2.0)
        };
        let truth = GlobalMap::similarity([15.5, 15.5], 12.0, 1.1, [3.0, -2.0]);
        let inverse_truth = GlobalMap::new(inverse(&truth.matrix())).unwrap();
        let mut planes_a = vec![0.0; 3 * rows * cols];
        let mut planes_b = vec![0.0; 3 * rows * cols];
        for r in 0..rows {
            for c in 0..cols {
                let a = pattern(r as f64, c as f64);
                // b(G(x)) = a(x): b(y) = a(G⁻¹(y)).
                let [ri, ci] = inverse_truth.apply([r as f64, c as f64]);
                let b = pattern(ri, ci);
                for ch in 0..3 {
                    planes_a[ch * rows * cols + r * cols + c] = a;
                    planes_b[ch * rows * cols + r * cols + c] = b;
                }
            }
        }
        let a = GreyImage::from_rgb_planes(&planes_a, rows, cols, 0.5).unwrap();
        let b = GreyImage::from_rgb_planes(&planes_b, rows, cols, 0.5).unwrap();
        let found =
            estimate_from_images(&a, &b, AlignKind::Similarity, &SearchRanges::default()).unwrap();
        let (s, t) = (found.map.summary((rows, cols)), truth.summary((rows, cols)));
        assert!(
            found.ncc > 0.99 && found.ncc > found.ncc_identity,
            "{found:?}"
        );
        assert!(
            (s.rotation_degrees - t.rotation_degrees).abs() < 1.0,
            "{s:?} vs {t:?}"
        );
        assert!((s.scale - t.scale).abs() < 0.02, "{s:?} vs {t:?}");
        assert!(
            (s.translation[0] - t.translation[0]).abs() < 0.3
                && (s.translation[1] - t.translation[1]).abs() < 0.3,
            "{s:?} vs {t:?}"
        );
        let affine =
            estimate_from_images(&a, &b, AlignKind::Affine, &SearchRanges::default()).unwrap();
        assert!(affine.ncc >= found.ncc - 1e-9, "{affine:?}");
    }
}
