//! The built-in demo pair: three soft-edged shapes that move, rotate and change colour, drawn
//! at any size (no files, no downloads).

use crate::io::images::RgbImage;

/// One shape of the scene.
#[derive(Clone, Copy, Debug)]
enum Shape {
    /// Centre (row, column) and radius, as fractions of the side.
    Disc { centre: [f64; 2], radius: f64 },
    /// Centre, half-side and rotation (radians).
    Square {
        centre: [f64; 2],
        half: f64,
        angle: f64,
    },
    /// Centre, circumradius and rotation (radians).
    Triangle {
        centre: [f64; 2],
        radius: f64,
        angle: f64,
    },
}

impl Shape {
    /// Signed distance (negative inside) of the point `p` (fractions of the side).
    fn distance(self, p: [f64; 2]) -> f64 {
        let rotate = |centre: [f64; 2], angle: f64| {
            let (dy, dx) = (p[0] - centre[0], p[1] - centre[1]);
            let (s, c) = angle.sin_cos();
            [c * dy + s * dx, -s * dy + c * dx]
        };
        match self {
            Shape::Disc { centre, radius } => (p[0] - centre[0]).hypot(p[1] - centre[1]) - radius,
            Shape::Square {
                centre,
                half,
                angle,
            } => {
                let q = rotate(centre, angle);
                q[0].abs().max(q[1].abs()) - half
            }
            Shape::Triangle {
                centre,
                radius,
                angle,
            } => {
                let q = rotate(centre, angle);
                // The largest signed distance to the three edge lines (inradius r/2).
                (0..3)
                    .map(|i| {
                        let t = std::f64::consts::TAU * i as f64 / 3.0;
                        let normal = [-(t.cos()), t.sin()];
                        q[0] * normal[0] + q[1] * normal[1] - radius / 2.0
                    })
                    .fold(f64::NEG_INFINITY, f64::max)
            }
        }
    }
}

/// Draws `shapes` (painted in order) over a soft vertical gradient, `size × size`.
fn draw(size: usize, shapes: &[(Shape, [f32; 3])]) -> RgbImage {
    let n = size * size;
    let mut data = vec![0.0f32; 3 * n];
    let edge = 1.2 / size as f64; // about one pixel of anti-aliasing
    for i in 0..size {
        for j in 0..size {
            let p = [i as f64 / size as f64, j as f64 / size as f64];
            let t = p[0] as f32;
            let mut colour = [0.93 - 0.1 * t, 0.92 - 0.05 * t, 0.85 + 0.05 * t];
            for &(shape, rgb) in shapes {
                let d = shape.distance(p);
                let cover = (0.5 - d / (2.0 * edge)).clamp(0.0, 1.0) as f32;
                for c in 0..3 {
                    colour[c] = cover * rgb[c] + (1.0 - cover) * colour[c];
                }
            }
            for c in 0..3 {
                data[c * n + i * size + j] = colour[c];
            }
        }
    }
    RgbImage::new(size, size, data).expect("finite values of the right count")
}

/// The demo pair `(A, B)` at `size × size`: a red disc moves right, a blue square moves
/// down-left and turns by 30°, a green triangle moves up and turns orange.
pub fn demo_pair(size: usize) -> (RgbImage, RgbImage) {
    let a = draw(
        size,
        &[
            (
                Shape::Disc {
                    centre: [0.3, 0.28],
                    radius: 0.14,
                },
                [0.85, 0.15, 0.12],
            ),
            (
                Shape::Square {
                    centre: [0.32, 0.7],
                    half: 0.11,
                    angle: 0.0,
                },
                [0.15, 0.3, 0.8],
            ),
            (
                Shape::Triangle {
                    centre: [0.72, 0.5],
                    radius: 0.17,
                    angle: 0.0,
                },
                [0.2, 0.65, 0.25],
            ),
        ],
    );
    let b = draw(
        size,
        &[
            (
                Shape::Disc {
                    centre: [0.3, 0.42],
                    radius: 0.14,
                },
                [0.85, 0.15, 0.12],
            ),
            (
                Shape::Square {
                    centre: [0.42, 0.64],
                    half: 0.11,
                    angle: 30f64.to_radians(),
                },
                [0.15, 0.3, 0.8],
            ),
            (
                Shape::Triangle {
                    centre: [0.65, 0.45],
                    radius: 0.17,
                    angle: 20f64.to_radians(),
                },
                [0.95, 0.55, 0.1],
            ),
        ],
    );
    (a, b)
}
