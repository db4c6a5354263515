//! Bilinear resizing of images and prolongation of deformations between pyramid levels
//! (SPEC §7).

use burn::tensor::Tensor;

use crate::model::deformation::{admissible_each, with_identity_boundary};
use crate::model::grid::Grid;
use crate::model::separable::Separable;
use crate::model::stencil::bilinear_resize;

/// Bilinear, align-corners resampling from `from`'s grid to `to`'s: output pixel `i`
/// reads the input at `i (H_from − 1)/(H_to − 1)`, likewise for columns.
#[derive(Clone, Debug)]
pub struct Resize {
    op: Separable,
}

impl Resize {
    /// The resampling operator between two grids (on `to`'s device and dtype).
    pub fn new(from: &Grid, to: &Grid) -> Self {
        Self {
            op: Separable::new(
                to,
                &bilinear_resize(from.height(), to.height()),
                &bilinear_resize(from.width(), to.width()),
            ),
        }
    }

    /// Resamples every map.
    ///
    /// # Shapes
    /// - `x`: `[N, C, H_from, W_from]`
    /// - output: `[N, C, H_to, W_to]`
    pub fn apply(&self, x: Tensor<4>) -> Tensor<4> {
        self.op.apply(x)
    }
}

/// Prolongates deformations from `coarse` to `fine` (SPEC §7): bilinear in domain units
/// (`[0, 1]²`), back to fine pixel units, `Id` on the boundary; a deformation that comes out
/// inadmissible is replaced by `Id`.
///
/// # Shapes
/// - `phi`: `[N, 2, h, w]` on `coarse`
/// - output: `[N, 2, H, W]` on `fine`
pub fn prolongate_deformation(coarse: &Grid, fine: &Grid, phi: Tensor<4>) -> Tensor<4> {
    let n = phi.dims()[0];
    let to_domain = fine.tensor(
        vec![
            1.0 / (coarse.height() - 1) as f64,
            1.0 / (coarse.width() - 1) as f64,
        ],
        [1, 2, 1, 1],
    );
    let to_pixels = fine.tensor(
        vec![(fine.height() - 1) as f64, (fine.width() - 1) as f64],
        [1, 2, 1, 1],
    );
    let domain = phi * to_domain;
    let fine_phi = Resize::new(coarse, fine).apply(domain) * to_pixels;
    let fine_phi = with_identity_boundary(fine, fine_phi);
    let admissible = admissible_each(fine, fine_phi.clone());
    if admissible.iter().all(|&ok| ok) {
        return fine_phi;
    }
    let identity = fine.identity(1);
    let per_k: Vec<Tensor<4>> = admissible
        .iter()
        .enumerate()
        .map(|(k, &ok)| {
            if ok {
                fine_phi.clone().narrow(0, k, 1)
            } else {
                identity.clone()
            }
        })
        .collect();
    debug_assert_eq!(per_k.len(), n);
    Tensor::cat(per_k, 0)
}
