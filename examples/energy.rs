//! Evaluates the path energy `E` (SPEC §5) of a synthetic image pair and its gradient by
//! autodiff: a soft coloured disc and the same disc moved by a few pixels, on the initial
//! path of SPEC §7 (frames interpolated linearly, `φ_k = Id`).
//!
//! ```text
//! cargo run --release --example energy [-- [BACKEND] [SIZE] [K]]
//! ```
//!
//! `BACKEND` is `flex`, `ndarray` or `wgpu` (default: the first compiled one), `SIZE` the
//! side of the square images (default 64), `K` the number of steps (default 4).

use std::time::Instant;

use burn::tensor::Tensor;
use deepmorph::model::energy::path::PathEnergy;
use deepmorph::model::grid::to_host;
use deepmorph::{Backend, EnergyParams, Grid, Precision};

/// A soft disc of radius `0.3·size` centred at `(cy, cx)` (in pixels), red on a blue-grey
/// background, `[3, size, size]` row-major.
fn disc(size: usize, cy: f64, cx: f64) -> Vec<f64> {
    let radius = 0.3 * size as f64;
    let inside: Vec<f64> = (0..size * size)
        .map(|p| {
            let (i, j) = ((p / size) as f64, (p % size) as f64);
            let r = ((i - cy).powi(2) + (j - cx).powi(2)).sqrt();
            1.0 / (1.0 + ((r - radius) / 1.5).exp())
        })
        .collect();
    let (fg, bg) = ([0.9, 0.2, 0.15], [0.25, 0.3, 0.45]);
    (0..3)
        .flat_map(|c| inside.iter().map(move |&s| s * fg[c] + (1.0 - s) * bg[c]))
        .collect()
}

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let backend = match args.next() {
        Some(name) => name.parse::<Backend>()?,
        None => Backend::default_compiled().ok_or("no backend compiled")?,
    };
    let size: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(64);
    let k: usize = args.next().map(|s| s.parse()).transpose()?.unwrap_or(4);
    if k < 1 {
        return Err("K must be at least 1".into());
    }

    let precision = Precision::F32;
    let device = backend.device_for(precision)?.autodiff();
    let grid = Grid::new(size, size, &device, precision.dtype())?;
    let centre = 0.5 * (size - 1) as f64;
    let shift = 0.08 * size as f64;
    let a = disc(size, centre, centre - shift);
    let b = disc(size, centre, centre + shift);

    // f_k = A + (k/K)(B − A): the initial path of SPEC §7.
    let frames: Vec<f64> = (0..=k)
        .flat_map(|step| {
            let t = step as f64 / k as f64;
            a.iter().zip(&b).map(move |(x, y)| x + t * (y - x))
        })
        .collect();
    let f: Tensor<4> = grid.tensor(frames, [k + 1, 3, size, size]).require_grad();
    let phi = grid.identity(k).require_grad();

    let energy = PathEnergy::new(&grid, EnergyParams::rgb(), 3)?;
    let started = Instant::now();
    let anisotropy = energy.anisotropy().compute(f.clone().narrow(0, 1, k));
    let value = energy.value(f.clone(), phi.clone(), anisotropy);
    let grads = value.total.backward();
    let grad_f = f
        .grad(&grads)
        .ok_or("no gradient for f")?
        .narrow(0, 1, k - 1);
    let grad_phi = phi.grad(&grads).ok_or("no gradient for phi")?;
    let norm = |t: Tensor<4>| -> f64 { t.square().sum().sqrt().into_scalar::<f64>() };
    let (norm_f, norm_phi) = (norm(grad_f), norm(grad_phi));
    let elapsed = started.elapsed();

    println!(
        "deepmorph: path energy of a moving disc, {size}x{size}, K = {k}, {backend} backend, float32"
    );
    println!("initial path: f_k linear between A and B, phi_k = Id (SPEC §7)");
    println!("  E           = {:.6e}", to_host(value.total)[0]);
    println!("  R_k         = {:?}", to_host(value.regularizer));
    println!("  D_k         = {:?}", to_host(value.data));
    println!(
        "  |dE/df|     = {norm_f:.6e}   (free frames f_1..f_{})",
        k - 1
    );
    println!("  |dE/dphi|   = {norm_phi:.6e}");
    println!("value + gradient in {:.1} ms", elapsed.as_secs_f64() * 1e3);
    Ok(())
}
