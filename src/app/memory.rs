//! How much memory a morph will need, estimated before anything large is allocated, so a
//! run that cannot fit is refused with a clear message instead of being killed an hour in.
//!
//! The model is empirical: peak resident memory (GNU time's max RSS) of the release binary,
//! flex backend, mimalloc, fused spline warp, 2-core Xeon, 2026-12-02, on `faces`
//! (README, "Memory", has the table). Past a fixed part (the program; for the deep model
//! also the VGG19 weights while they are read and loaded) it grows with the finest level's
//! pixels (RGB: 400 bytes each; deep: VGG19's activations on the inputs and the warp's
//! channels-last copies of a 64-channel block, about 1.5 kB) and with
//! `K · H · W · C`: 58 bytes per step, pixel and channel for RGB, 18.4 for the deep model
//! (whose 64 feature channels go through the same few temporaries). The batched schedule
//! holds every step's temporaries at once: its `K`-part is 4× (RGB) and 3× (deep) the
//! sequential one. The peak also creeps up with the number of sweeps (transients meeting by
//! chance; no leak seen: a 64² run's resident memory stayed within 20–34 MB over its first
//! 80 s of a 600-sweep run), so the constants cover
//! runs of 20–250 sweeps (a default RGB morph, 5 levels of up to 250), not only 2-sweep ones.
//! Over the 28 measured runs the estimate is never below the peak and, for the sequential
//! schedule, at most 31 % above it for runs of 20 sweeps or more and 35 % for 2-sweep runs
//! (RGB at 512² costs less per pixel than at 256², which a linear model cannot follow; the
//! spread between images and sweep counts alone is ±7 %); for the batched schedule at most
//! 2.6× above. The RGB rows at 256² and 512² were re-measured after the 2026-12-02 evening
//! kernels (faster code holds more freed memory within mimalloc's purge delay: the same
//! 256² run peaked at 189–199 MB before and 201–240 MB after), and the RGB constant raised
//! from 51 to 58 bytes to stay above them.

use crate::error::{Error, Result};

/// What the estimate depends on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Plan {
    /// The finest level's rows.
    pub height: usize,
    /// The finest level's columns.
    pub width: usize,
    /// `K`.
    pub steps: usize,
    /// Feature channels: 3 for RGB, 3 + 64 for the deep model.
    pub channels: usize,
    /// The deep model (VGG19 is loaded and run).
    pub deep: bool,
    /// The batched schedule.
    pub batched: bool,
}

/// One model's constants of the estimate (bytes).
struct Coefficients {
    /// The program; for the deep model also VGG19's weights while they are read and loaded.
    base: f64,
    /// Per pixel of the finest level: RGB's images, pyramid and per-frame buffers; the deep
    /// model's VGG19 activations on both inputs.
    per_pixel: f64,
    /// Per step, pixel and channel of the finest level, sequential schedule.
    per_step_pixel_channel: f64,
    /// The batched schedule's `K`-part over the sequential one's.
    batched_factor: f64,
}

const RGB: Coefficients = Coefficients {
    base: 45e6,
    per_pixel: 400.0,
    per_step_pixel_channel: 58.0,
    batched_factor: 4.0,
};

const DEEP: Coefficients = Coefficients {
    base: 160e6,
    per_pixel: 1500.0,
    per_step_pixel_channel: 18.4,
    batched_factor: 3.0,
};

/// The estimated peak memory in bytes of a morph planned as `plan`.
pub fn estimate_peak_bytes(plan: &Plan) -> u64 {
    let c = if plan.deep { &DEEP } else { &RGB };
    let pixels = (plan.height * plan.width) as f64;
    let schedule = if plan.batched { c.batched_factor } else { 1.0 };
    let steps = schedule * c.per_step_pixel_channel * (plan.steps * plan.channels) as f64 * pixels;
    (c.base + c.per_pixel * pixels + steps) as u64
}

/// Refuses a morph planned as `plan` whose estimated peak exceeds `max_gib`, or, without a
/// limit and on a CPU backend, the memory available now; returns the estimate. Runs before
/// anything large is allocated (the images are not even resized yet).
///
/// # Errors
///
/// [`Error::Memory`] with the estimate, the limit and what to change.
pub fn check(plan: &Plan, max_gib: Option<f64>, host_memory: bool) -> Result<u64> {
    let estimate = estimate_peak_bytes(plan);
    let limit = match max_gib {
        Some(gib) => Some(((gib * (1u64 << 30) as f64) as u64, "--max-memory")),
        // On wgpu the tensors live in GPU memory, which the host cannot see.
        None if host_memory => available_bytes().map(|b| (b, "available memory")),
        None => None,
    };
    if let Some((limit, limit_name)) = limit
        && estimate > limit
    {
        return Err(Error::Memory {
            needed_gib: gib(estimate),
            limit_gib: gib(limit),
            limit_name,
            what: format!(
                "{}x{}, K = {}, {} model{}",
                plan.width,
                plan.height,
                plan.steps,
                if plan.deep { "deep" } else { "rgb" },
                if plan.batched {
                    ", batched schedule"
                } else {
                    ""
                }
            ),
        });
    }
    Ok(estimate)
}

/// The memory the operating system says is available now (`MemAvailable` on Linux), or
/// `None` where that is unknown.
pub fn available_bytes() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = info.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// This process's peak resident memory so far (`VmHWM` on Linux), for reports.
pub fn peak_resident_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// `bytes` in GiB for messages.
pub fn gib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 30) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Measured peaks in MB (README, "Memory"): rows, columns, K, sweeps per level, deep,
    /// batched. `faces` unless the size says otherwise (80 × 128: the motorcycle).
    const MEASURED: [(usize, usize, usize, usize, bool, bool, f64); 28] = [
        (256, 256, 15, 250, false, false, 229.0), // default RGB morph: 5 levels, --tol 1e-4
        (64, 64, 15, 2, false, false, 42.5),
        (128, 128, 15, 2, false, false, 77.8),
        (128, 128, 15, 20, false, false, 76.1),
        (256, 256, 15, 2, false, false, 239.7),
        (256, 256, 15, 20, false, false, 242.2),
        (512, 512, 15, 2, false, false, 622.0),
        (512, 512, 15, 20, false, false, 678.8),
        (256, 256, 4, 2, false, false, 99.7),
        (256, 256, 30, 2, false, false, 324.8),
        (256, 256, 15, 2, false, true, 291.2),
        (128, 128, 8, 60, false, false, 57.0),
        (128, 128, 8, 60, false, false, 59.8), // cat_lion
        (80, 128, 8, 60, false, false, 60.7),
        (128, 128, 8, 60, false, true, 110.6),
        (128, 128, 8, 60, false, true, 100.9), // cat_lion
        (80, 128, 8, 60, false, true, 74.6),
        (64, 64, 15, 2, true, false, 232.3),
        (128, 128, 15, 2, true, false, 386.6),
        (256, 256, 15, 2, true, false, 1425.6), // channels-last warp buffers (+60 MB)
        (512, 512, 15, 2, true, false, 5262.9), // (+167 MB)
        (128, 128, 4, 2, true, false, 230.2),
        (128, 128, 30, 2, true, false, 675.5),
        (128, 128, 8, 60, true, false, 274.5),
        (128, 128, 8, 60, true, false, 273.5), // cat_lion
        (80, 128, 8, 60, true, false, 230.4),
        (128, 128, 8, 60, true, true, 542.2),
        (80, 128, 8, 60, true, true, 394.0),
    ];

    #[test]
    fn the_estimate_covers_every_measurement_and_is_not_far_above() {
        for (h, w, k, sweeps, deep, batched, megabytes) in MEASURED {
            let measured = megabytes * 1e6;
            let most = match (batched, sweeps >= 20) {
                (true, _) => 2.6,
                (false, true) => 1.31,
                (false, false) => 1.35,
            };
            let plan = Plan {
                height: h,
                width: w,
                steps: k,
                channels: if deep { 67 } else { 3 },
                deep,
                batched,
            };
            let estimate = estimate_peak_bytes(&plan) as f64;
            assert!(
                estimate >= measured && estimate <= most * measured,
                "{w}x{h} K {k} J {sweeps} deep {deep} batched {batched}: estimate {estimate:e}, \
                 measured {measured:e}"
            );
        }
    }
}
