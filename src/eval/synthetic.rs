//! Synthetic pairs with a known correspondence: an image and a warped copy of it.
//!
//! For an image `I` and a deformation `Ψ`, the pair `A = T[I, Ψ]` (SPEC §1's warp), `B = I`
//! satisfies `A = B ∘ Ψ` exactly, which is what a morph's composed map claims
//! (`u_0 ≈ u_K ∘ Φ`): the ground truth for `Φ` is `Ψ` itself, no inverse needed.
//!
//! Every field is `Ψ = Id + v` with `v` faded out towards the border by the window
//! `ω = sin(π y) sin(π x)` (`y, x ∈ [0, 1]` the normalised position), so `Ψ = Id` on the
//! boundary like every admissible deformation of the model (SPEC §0).

use std::fmt;
use std::str::FromStr;

use burn::tensor::Device;

use crate::backend::Precision;
use crate::error::{Error, Result};
use crate::io::images::RgbImage;
use crate::io::truth::Correspondence;
use crate::model::deformation::is_admissible;
use crate::model::grid::Grid;
use crate::model::warp::BSpline;

/// The kind of synthetic deformation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Field {
    /// A smooth swirl; `amount` = its largest displacement in pixels.
    Smooth,
    /// A rotation about the centre, faded towards the border; `amount` = angle in degrees
    /// at the centre (the sample points turn by it; positive = from the row axis towards
    /// the column axis).
    Rotate,
    /// A horizontal shear, faded towards the border; `amount` = columns moved per row at
    /// the centre (`v₁ = ω · amount · (row − centre row)`).
    Shear,
}

impl Field {
    /// Every field, for help texts.
    pub const ALL: [Field; 3] = [Field::Smooth, Field::Rotate, Field::Shear];

    /// The name the CLI uses.
    pub fn name(self) -> &'static str {
        match self {
            Field::Smooth => "smooth",
            Field::Rotate => "rotate",
            Field::Shear => "shear",
        }
    }
}

impl fmt::Display for Field {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for Field {
    type Err = Error;

    fn from_str(s: &str) -> Result<Self> {
        Field::ALL
            .into_iter()
            .find(|f| f.name() == s)
            .ok_or_else(|| Error::invalid("field", s, "one of smooth, rotate, shear"))
    }
}

/// The displacement `v = Ψ − Id` of `field` with `amount` on an `h × w` grid, row-major
/// `[2, H, W]` in pixels.
///
/// # Errors
///
/// If `amount` is not finite or the grid is smaller than 4 × 4.
pub fn displacement(field: Field, amount: f64, h: usize, w: usize) -> Result<Vec<f64>> {
    if !amount.is_finite() {
        return Err(Error::invalid("amount", amount, "a finite number"));
    }
    // An angle is not taken modulo 360: 360° would be "applied" and move nothing.
    if field == Field::Rotate && amount.abs() >= 180.0 {
        return Err(Error::invalid(
            "amount",
            amount,
            "an angle strictly between -180 and 180 degrees",
        ));
    }
    if h < 4 || w < 4 {
        return Err(Error::invalid(
            "image size",
            format!("{w}x{h}"),
            "at least 4x4",
        ));
    }
    let pi = std::f64::consts::PI;
    let (cy, cx) = ((h - 1) as f64 / 2.0, (w - 1) as f64 / 2.0);
    let mut v = vec![0.0; 2 * h * w];
    for i in 0..h {
        for j in 0..w {
            let (y, x) = (i as f64 / (h - 1) as f64, j as f64 / (w - 1) as f64);
            let window = (pi * y).sin() * (pi * x).sin();
            let (dy, dx) = (i as f64 - cy, j as f64 - cx);
            let [v0, v1] = match field {
                Field::Smooth => [
                    window * (pi * (x - 0.3 * y)).cos(),
                    window * (pi * (y + 0.5 * x)).sin(),
                ],
                Field::Rotate => {
                    let (s, c) = amount.to_radians().sin_cos();
                    [
                        window * (c * dy - s * dx - dy),
                        window * (s * dy + c * dx - dx),
                    ]
                }
                Field::Shear => [0.0, window * amount * dy],
            };
            v[i * w + j] = v0;
            v[h * w + i * w + j] = v1;
        }
    }
    if field == Field::Smooth {
        let n = h * w;
        let peak = (0..n).map(|p| v[p].hypot(v[n + p])).fold(0.0, f64::max);
        v.iter_mut().for_each(|x| *x *= amount / peak);
    }
    // Exactly the identity on the border (sin(π) is 1e-16, not 0).
    for i in 0..h {
        for j in 0..w {
            if i == 0 || j == 0 || i == h - 1 || j == w - 1 {
                v[i * w + j] = 0.0;
                v[h * w + i * w + j] = 0.0;
            }
        }
    }
    Ok(v)
}

/// The pair `(A, truth)` for `B = image`: `A = T[image, Ψ]` and the correspondence `Ψ − Id`,
/// computed on `device` at the image's own size.
///
/// # Errors
///
/// If `amount` is not finite or so large that `Ψ` folds (`det J ≤ 0` somewhere).
pub fn warped_pair(
    image: &RgbImage,
    field: Field,
    amount: f64,
    device: &Device,
) -> Result<(RgbImage, Correspondence)> {
    let (h, w) = (image.height(), image.width());
    let v = displacement(field, amount, h, w)?;
    let grid = Grid::new(h, w, device, Precision::F32.dtype())?;
    let psi = grid.identity(1) + grid.tensor(v.clone(), [1, 2, h, w]);
    if !is_admissible(&grid, psi.clone()) {
        return Err(Error::invalid(
            "amount",
            amount,
            "small enough that the deformation does not fold (det J > 0 everywhere); try a smaller one",
        ));
    }
    let warped = BSpline::new(&grid).warp(image.to_tensor(&grid)?, psi);
    let n = h * w;
    let truth = Correspondence::new(h, w, (0..n).map(|p| Some([v[p], v[n + p]])).collect())?;
    Ok((RgbImage::from_tensor(warped)?, truth))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn smooth_amount_is_the_largest_displacement_and_the_border_is_fixed() {
        let (h, w) = (20, 30);
        let v = displacement(Field::Smooth, 3.5, h, w).unwrap();
        let n = h * w;
        let peak = (0..n).map(|p| v[p].hypot(v[n + p])).fold(0.0, f64::max);
        assert!((peak - 3.5).abs() < 1e-12);
        for j in 0..w {
            assert_eq!((v[j], v[n + j], v[(h - 1) * w + j]), (0.0, 0.0, 0.0));
        }
    }

    #[test]
    fn rotation_turns_the_centre_and_shear_moves_columns_only() {
        let (h, w) = (21, 21);
        let n = h * w;
        let v = displacement(Field::Rotate, 90.0, h, w).unwrap();
        // One row below the centre (dy = 1, dx = 0): a quarter turn sends (1, 0) to (0, 1).
        let p = 11 * w + 10;
        let window = (std::f64::consts::PI * 11.0 / 20.0).sin();
        assert!((v[p] + window).abs() < 1e-12 && (v[n + p] - window).abs() < 1e-12);
        let v = displacement(Field::Shear, 0.2, h, w).unwrap();
        assert!(v[..n].iter().all(|&x| x == 0.0));
        assert!((v[n + p] - 0.2 * window).abs() < 1e-12);
        assert!("twist".parse::<Field>().is_err());
    }
}
