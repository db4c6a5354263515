//! How much memory a morph will need, estimated before anything large is allocated, so a
//! run that cannot fit is refused with a clear message instead of being killed an hour in.
//!
//! The model is empirical: peak resident memory (GNU time's max RSS) of the release binary,
//! flex backend, mimalloc, 2-core AMD EPYC, 2026-12-03, on `faces` unless said
//! (docs/reliability.md, "Memory", has the table). Past a fixed part (the program; for the deep model also VGG19's
//! weights, read at the start and again after the solve for the feature-space path metric,
//! while the morph is still held) it grows with the finest level's pixels (RGB: 650 bytes
//! each; deep: VGG19's activations and the warp's channels-last copies of a 64-channel
//! block, about 4 kB) and with `K · H · W · C`: 56 bytes per step, pixel and channel for
//! RGB, 16.2 for the deep model. That part includes what a sequential sweep carries to the
//! next (`P f_k` and `T[f_k, φ_k]`, `solver::ipalm::SweepCarry`: 8 bytes per step, pixel and
//! channel of tensors; measured +400 MB for 491 MB of them on a deep 2-level 256² run, +25 MB
//! for 5.5 MB on an RGB 128² run). The batched
//! schedule carries nothing but holds every step's temporaries at once: its `K`-part is
//! 1.85× (RGB) and 2.1× (deep) the sequential one. The peak also creeps up with the number
//! of sweeps (transients meeting by chance), so the constants cover runs of 2–250 sweeps.
//! Over the 44 measured runs the estimate is never below the peak; the deep model's at most
//! 22 % above it (5 % batched); RGB's at most 55 % (44 % batched), where a model of the plan
//! cannot follow the measurements: per pixel, RGB at 512² costs less than at 256²; the few
//! long-lived carried tensors pin more of the allocator's pages at 128² (a 128² run peaks
//! 30 MB above the same run without them, for 5.5 MB of tensors); at 64² the peak is not
//! even monotone in `K` (K 8: 61–63 MB, K 15: 41–46 MB, each measured three times); and
//! runs of the same plan differ by up to 10 % with the images and the sweeps run (default
//! 256² morphs of six pairs: 196–218 MB). Where the RGB model's memory matters, 256² and
//! up, the estimate is 9–40 % above the peak (44 % batched).

use crate::error::{Error, Result};
pub use crate::host_memory::{available_bytes, host_limit, peak_resident_bytes};

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
    base: 57e6,
    per_pixel: 650.0,
    per_step_pixel_channel: 56.0,
    batched_factor: 1.85,
};

const DEEP: Coefficients = Coefficients {
    base: 260e6,
    per_pixel: 3950.0,
    per_step_pixel_channel: 16.2,
    batched_factor: 2.1,
};

/// The estimated peak memory in bytes of a morph planned as `plan`.
pub fn estimate_peak_bytes(plan: &Plan) -> u64 {
    let c = if plan.deep { &DEEP } else { &RGB };
    let pixels = (plan.height * plan.width) as f64;
    let schedule = if plan.batched { c.batched_factor } else { 1.0 };
    let steps = schedule * c.per_step_pixel_channel * (plan.steps * plan.channels) as f64 * pixels;
    (c.base + c.per_pixel * pixels + steps) as u64
}

/// Refuses a morph planned as `plan` whose estimated peak exceeds the least of `max_gib`
/// and, on a CPU backend, the memory this process may still take ([`host_limit`]: the
/// available memory, the address-space limit and the control group's limit); returns the
/// estimate. Runs before anything large is allocated (the images are not even resized yet).
///
/// # Errors
///
/// [`Error::Memory`] with the estimate, the limit and what to change.
pub fn check(plan: &Plan, max_gib: Option<f64>, host_memory: bool) -> Result<u64> {
    let estimate = estimate_peak_bytes(plan);
    let what = format!(
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
    );
    check_bytes(estimate, &what, max_gib, host_memory)?;
    Ok(estimate)
}

/// Refuses `needed` bytes (an estimated peak, `what` in words for the message) if they exceed
/// the least of `max_gib` and, on a CPU backend, [`host_limit`].
///
/// # Errors
///
/// [`Error::Memory`] with the estimate, the limit and what to change.
pub fn check_bytes(needed: u64, what: &str, max_gib: Option<f64>, host_memory: bool) -> Result<()> {
    let requested = max_gib.map(|gib| ((gib * (1u64 << 30) as f64) as u64, "--max-memory"));
    // On wgpu the tensors live in GPU memory, which the host's limits do not see.
    let host = host_memory.then(host_limit).flatten();
    let limit = match (requested, host) {
        (Some(r), Some(h)) => Some(if h.0 < r.0 { h } else { r }),
        (r, h) => r.or(h),
    };
    match limit {
        Some((limit, limit_name)) if needed > limit => Err(Error::Memory {
            needed_gib: gib(needed),
            limit_gib: gib(limit),
            limit_name,
            what: what.to_string(),
        }),
        _ => Ok(()),
    }
}

/// `bytes` in GiB for messages.
pub fn gib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 30) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Measured peaks in MB (docs/reliability.md, "Memory"): rows, columns, K, sweeps per level, deep,
    /// batched. `faces` with 3 levels (deep: 2 feature-only sweeps) unless said; 4 levels and
    /// 60 sweeps: K = 8, `--pre-sweeps 30`, and 80 × 128 / 88 × 128 is the motorcycle.
    const MEASURED: [(usize, usize, usize, usize, bool, bool, f64); 44] = [
        (64, 64, 15, 2, false, false, 48.1),
        (128, 128, 15, 20, false, false, 106.9),
        (256, 256, 15, 2, false, false, 203.5),
        (256, 256, 15, 20, false, false, 204.7),
        (256, 256, 15, 250, false, false, 215.0), // default RGB morph: 5 levels, --tol 1e-4
        (512, 512, 15, 2, false, false, 651.8),
        (512, 512, 15, 20, false, false, 632.3),
        (256, 256, 4, 2, false, false, 126.3),
        (256, 256, 30, 2, false, false, 337.2),
        (128, 128, 8, 60, false, false, 63.5),
        (128, 128, 8, 60, false, false, 63.1), // cat_lion
        (88, 128, 8, 60, false, false, 73.2),
        (256, 256, 15, 2, false, true, 281.7),
        (128, 128, 8, 60, false, true, 94.9),
        (128, 128, 8, 60, false, true, 97.7), // cat_lion
        (88, 128, 8, 60, false, true, 90.0),
        // 2026-12-03 (later), 3 levels × 20 sweeps, VmHWM of `/usr/bin/time`.
        (64, 64, 4, 20, false, false, 44.8),
        (64, 64, 8, 20, false, false, 63.3),
        (64, 64, 15, 20, false, false, 46.3),
        (64, 64, 30, 20, false, false, 63.0),
        (128, 128, 4, 20, false, false, 50.9),
        (128, 128, 8, 20, false, false, 63.3),
        (128, 128, 15, 20, false, false, 98.9),
        (128, 128, 30, 20, false, false, 123.7),
        // The results study: default morphs (5 levels × ≤ 250, `--tol 1e-4`), each pair,
        // the peak (`VmHWM`) of the child process that ran it.
        (256, 256, 15, 250, false, false, 218.4), // faces, the ξ₁ study's 1000
        (256, 256, 30, 250, false, false, 368.2), // faces, the K study
        (256, 256, 5, 250, false, false, 141.4),  // faces, the K study
        (256, 256, 15, 250, false, false, 197.7), // cars
        (224, 224, 15, 250, false, false, 169.7), // cat_dog
        (224, 224, 15, 250, false, false, 155.8), // cat_lion
        (176, 256, 15, 250, false, false, 165.7), // motorcycle
        (128, 128, 15, 250, false, false, 103.1), // faces, the δ study
        (64, 64, 15, 2, true, false, 340.2),      // VGG19 read again after the solve
        (128, 128, 15, 2, true, false, 486.5),
        (256, 256, 15, 2, true, false, 1480.7),
        (256, 256, 15, 4, true, false, 1550.8), // 2 levels
        (512, 512, 15, 2, true, false, 5482.6),
        (128, 128, 4, 2, true, false, 386.5),
        (128, 128, 30, 2, true, false, 794.5),
        (128, 128, 8, 60, true, false, 410.0),
        (128, 128, 8, 60, true, false, 429.0), // cat_lion
        (80, 128, 8, 60, true, false, 389.3),
        (128, 128, 8, 60, true, true, 620.8),
        (80, 128, 8, 60, true, true, 462.9),
    ];

    #[test]
    fn the_estimate_covers_every_measurement_and_is_not_far_above() {
        for (h, w, k, sweeps, deep, batched, megabytes) in MEASURED {
            let measured = megabytes * 1e6;
            let most = match (deep, batched) {
                (true, false) => 1.22,
                (true, true) => 1.06,
                (false, false) => 1.55,
                (false, true) => 1.44,
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
