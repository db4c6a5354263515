//! The evaluation's setup shared by every kernel: where each point of `φ` falls on the
//! coefficient grid, its clamped 4 × 4 stencil and the B-spline weights and slopes, eight
//! lanes at a time.

use super::*;

/// Where a sample point falls along one axis: the 4 mirrored indices, the B-spline weights
/// `β(t+1), β(t), β(t−1), β(t−2)` of the fractional part and their derivatives `β'`, and
/// whether the point lies inside the clamp range (else the clamped function is flat).
#[derive(Clone, Copy, Debug)]
pub(super) struct Axis<T> {
    pub(super) index: [usize; 4],
    pub(super) weight: [T; 4],
    pub(super) slope: [T; 4],
    pub(super) inside: bool,
}

/// Points whose setup is computed together: one AVX2 register of float32 values.
pub(super) const LANES: usize = 8;

/// [`Axis`] of `LANES` points at once, structure of arrays, in the kernels' precision: the
/// setup is a few dozen arithmetic operations per point with no data-dependent branch, so
/// across points it vectorises (it cost as much as the 48 multiply-adds of a 3-channel
/// evaluation when done a point at a time in float64).
pub(super) struct AxisLanes<T> {
    pub(super) index: [[u32; LANES]; 4],
    pub(super) weight: [[T; LANES]; 4],
    pub(super) slope: [[T; LANES]; 4],
    pub(super) inside: [bool; LANES],
}

impl<T: SplineReal> AxisLanes<T> {
    /// The axes of the points `p` (coordinates along an axis of `n ≥ 4` samples).
    #[inline(always)]
    pub(super) fn new(p: &[T; LANES], n: usize) -> Self {
        let zero = T::default();
        let one = T::from_f64(1.0);
        let hi = T::from_f64((n - 1) as f64);
        let last = n as i32 - 1;
        let (sixth, half, minus_half) = (T::from_f64(SIXTH), T::from_f64(0.5), T::from_f64(-0.5));
        let (two, one_and_half, two_thirds) =
            (T::from_f64(2.0), T::from_f64(1.5), T::from_f64(2.0 / 3.0));
        let mut lanes = Self {
            index: [[0; LANES]; 4],
            weight: [[zero; LANES]; 4],
            slope: [[zero; LANES]; 4],
            inside: [false; LANES],
        };
        for (l, &p) in p.iter().enumerate() {
            // `!(p > hi)` and `!(p < 0)` so that a NaN lands inside and stays NaN in the
            // output (the clamp keeps it too).
            lanes.inside[l] = !(p < zero) && !(p > hi);
            let q = if p < zero {
                zero
            } else if p > hi {
                hi
            } else {
                p
            };
            // `q ≥ 0`, so truncation is the floor; a NaN truncates to 0 and stays NaN in `t`.
            let base = q.truncate();
            let t = q - T::from_i32(base);
            let s = one - t;
            let (t2, s2) = (t * t, s * s);
            for a in 0..4 {
                // Whole-sample mirror (SPEC §0) of an index in `[−1, n + 1]`.
                let i = base + a as i32 - 1;
                lanes.index[a][l] = (last - (i.abs() - last).abs()) as u32;
            }
            lanes.weight[0][l] = s2 * s * sixth;
            lanes.weight[1][l] = half * t2 * t - t2 + two_thirds;
            lanes.weight[2][l] = half * s2 * s - s2 + two_thirds;
            lanes.weight[3][l] = t2 * t * sixth;
            lanes.slope[0][l] = minus_half * s2;
            lanes.slope[1][l] = one_and_half * t2 - two * t;
            lanes.slope[2][l] = two * s - one_and_half * s2;
            lanes.slope[3][l] = half * t2;
        }
        lanes
    }

    /// The row and column axes of the `n ≤ LANES` points from `first` of an image whose
    /// deformation planes are `(p0, p1)` ([`deformation_planes`]), on an `h × w` grid.
    #[inline(always)]
    pub(super) fn block(
        (p0, p1): (&[T], &[T]),
        first: usize,
        n: usize,
        h: usize,
        w: usize,
    ) -> (Self, Self) {
        let load = |axis: &[T]| {
            let mut v = [T::default(); LANES];
            v[..n].copy_from_slice(&axis[first..first + n]);
            v
        };
        (Self::new(&load(p0), h), Self::new(&load(p1), w))
    }

    /// The axis of point `l`.
    #[inline(always)]
    pub(super) fn lane(&self, l: usize) -> Axis<T> {
        // Written out: `array::map` is not inlined here and cost a tenth of a sweep.
        let (i, w, s) = (&self.index, &self.weight, &self.slope);
        Axis {
            index: [
                i[0][l] as usize,
                i[1][l] as usize,
                i[2][l] as usize,
                i[3][l] as usize,
            ],
            weight: [w[0][l], w[1][l], w[2][l], w[3][l]],
            slope: [s[0][l], s[1][l], s[2][l], s[3][l]],
            inside: self.inside[l],
        }
    }
}

/// Image `b`'s deformation `φ_b` as its two planes (row and column coordinates).
#[inline(always)]
pub(super) fn deformation_planes<'a, T>(phi: &'a [T], d: &Dims, b: usize) -> (&'a [T], &'a [T]) {
    let plane = d.points();
    phi[b * 2 * plane..(b + 1) * 2 * plane].split_at(plane)
}

/// `1/6`, a product where a division would stall the point's setup.
pub(super) const SIXTH: f64 = 1.0 / 6.0;

/// The points `p` of a range of image `b` with their axes `(p, rows, cols)`, set up `LANES`
/// points at a time. An iterator, not a callback, so that the caller's loop body stays in
/// the caller (and in its AVX2 copy): a closure was compiled apart and called per point.
pub(super) struct Points<'a, T> {
    pub(super) p0: &'a [T],
    pub(super) p1: &'a [T],
    pub(super) h: usize,
    pub(super) w: usize,
    pub(super) next: usize,
    pub(super) end: usize,
    /// The first point of the block set up in `rows` and `cols`.
    pub(super) first: usize,
    pub(super) rows: AxisLanes<T>,
    pub(super) cols: AxisLanes<T>,
}

impl<'a, T: SplineReal> Points<'a, T> {
    #[inline(always)]
    pub(super) fn new(phi: &'a [T], d: &Dims, b: usize, points: std::ops::Range<usize>) -> Self {
        let zero = [T::default(); LANES];
        let (p0, p1) = deformation_planes(phi, d, b);
        Self {
            p0,
            p1,
            h: d.h,
            w: d.w,
            next: points.start,
            end: points.end,
            first: points.start,
            // Set up on the first call of `next`.
            rows: AxisLanes::new(&zero, d.h),
            cols: AxisLanes::new(&zero, d.w),
        }
    }
}

impl<T: SplineReal> Iterator for Points<'_, T> {
    type Item = (usize, Axis<T>, Axis<T>);

    #[inline(always)]
    fn next(&mut self) -> Option<Self::Item> {
        let p = self.next;
        if p >= self.end {
            return None;
        }
        if (p - self.first).is_multiple_of(LANES) {
            let count = LANES.min(self.end - p);
            self.first = p;
            (self.rows, self.cols) = AxisLanes::block((self.p0, self.p1), p, count, self.h, self.w);
        }
        self.next = p + 1;
        let l = p - self.first;
        Some((p, self.rows.lane(l), self.cols.lane(l)))
    }
}

/// The shapes of an evaluation: `n` images of `c` channels on a `h × w` coefficient grid,
/// sampled at `ho × wo` points each.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Dims {
    /// Batch `N`.
    pub n: usize,
    /// Channels `C`.
    pub c: usize,
    /// Coefficient rows `H`.
    pub h: usize,
    /// Coefficient columns `W`.
    pub w: usize,
    /// Sample rows `H'`.
    pub ho: usize,
    /// Sample columns `W'`.
    pub wo: usize,
}

impl Dims {
    pub(super) fn points(&self) -> usize {
        self.ho * self.wo
    }

    pub(super) fn check<T>(&self, coeffs: usize, phi: &[T], samples: usize) {
        assert!(self.h >= 4 && self.w >= 4, "the spline needs 4 × 4 samples");
        assert_eq!(coeffs, self.n * self.c * self.h * self.w, "coefficients");
        assert_eq!(phi.len(), self.n * 2 * self.points(), "deformation");
        assert_eq!(samples, self.n * self.c * self.points(), "samples");
    }
}

/// The 16 offsets and weights `β(p₀ − i) β(p₁ − j)` of a point.
#[inline(always)]
pub(super) fn stencil<T: SplineReal>(
    rows: &Axis<T>,
    cols: &Axis<T>,
    w: usize,
) -> ([usize; 16], [T; 16]) {
    let mut offset = [0; 16];
    let mut weight = [T::default(); 16];
    for a in 0..4 {
        for b in 0..4 {
            offset[4 * a + b] = rows.index[a] * w + cols.index[b];
            weight[4 * a + b] = rows.weight[a] * cols.weight[b];
        }
    }
    (offset, weight)
}
