//! How much memory a morph will need, estimated before anything large is allocated, so a
//! run that cannot fit is refused with a clear message instead of being killed an hour in.
//!
//! The model is empirical: peak resident memory was measured (GNU time's max RSS, flex
//! backend, mimalloc, row-gather warp, 2-core Xeon, 2026-11-24) for deep morphs on `faces`
//! at 64² K 4 (224 MB), 128² K 4 (421 MB), 128² K 8 (495 MB) and 256² K 15 (1.28 GiB;
//! estimate 3.4 GiB), and for RGB morphs. Past the fixed part (program, VGG19 weights, the
//! network's activations on both inputs) it grows with `K · H · W · C_tot` at the finest
//! level (coarser levels have a quarter of the pixels and at most twice the channels), at
//! about 17 bytes per step, pixel and channel (128² K 4 → K 8); the estimate uses 48 to cover
//! the transients too: a feature step's row gather holds 16 values per feature value of one
//! frame, and its backward as many again (128 B per pixel and channel, by that count 2.2 GB
//! at 512² with 67 channels).

use crate::error::{Error, Result};

/// Bytes per step, pixel and channel of the finest level (measured about 17, see above).
const BYTES_PER_STEP_PIXEL_CHANNEL: f64 = 48.0;
/// The program, the VGG19 weights (80 MB) while they are read and loaded.
const DEEP_BASE: f64 = 200e6;
/// The program alone.
const RGB_BASE: f64 = 30e6;
/// VGG19 on both inputs at full size: the first block's activations and convolution
/// buffers, per input pixel (2 images × 64 channels × ~9 floats).
const VGG_BYTES_PER_PIXEL: f64 = 2.0 * 64.0 * 9.0 * 4.0;

/// The estimated peak memory in bytes of a morph with `steps` steps whose finest level is
/// `height × width` with `channels` feature channels (3 for RGB, 3 + 64 for the deep model).
pub fn estimate_peak_bytes(
    height: usize,
    width: usize,
    steps: usize,
    channels: usize,
    deep: bool,
) -> u64 {
    let pixels = (height * width) as f64;
    let solver = steps as f64 * pixels * channels as f64 * BYTES_PER_STEP_PIXEL_CHANNEL;
    let (base, vgg) = if deep {
        (DEEP_BASE, pixels * VGG_BYTES_PER_PIXEL)
    } else {
        (RGB_BASE, 0.0)
    };
    (base + vgg + solver) as u64
}

/// Refuses a morph of `steps` steps on a `height × width` working size with `channels`
/// feature channels whose estimated peak exceeds `max_gib`, or, without a limit and on a CPU
/// backend, the memory available now; returns the estimate. Runs before anything large is
/// allocated (the images are not even resized yet).
///
/// # Errors
///
/// [`Error::Memory`] with the estimate, the limit and what to change.
pub fn check(
    height: usize,
    width: usize,
    steps: usize,
    channels: usize,
    deep: bool,
    max_gib: Option<f64>,
    host_memory: bool,
) -> Result<u64> {
    let estimate = estimate_peak_bytes(height, width, steps, channels, deep);
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
                "{width}x{height}, K = {steps}, {} model",
                if deep { "deep" } else { "rgb" }
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

    #[test]
    fn estimate_covers_the_measured_runs_and_scales() {
        // Measured max RSS (bytes) of deep morphs: (side, K, bytes).
        for (side, k, measured) in [(64, 4, 224e6), (128, 4, 421e6), (128, 8, 495e6)] {
            let est = estimate_peak_bytes(side, side, k, 67, true) as f64;
            assert!(
                est >= measured && est < 2.5 * measured,
                "{side}² K {k}: {est:e} vs {measured:e}"
            );
        }
        // The paper's setting at 256² fits in 8 GB; at 512² it needs about four times that.
        let e256 = estimate_peak_bytes(256, 256, 15, 67, true);
        assert!(e256 as f64 >= 1.38e9, "{e256}: measured 1.38e9");
        let e512 = estimate_peak_bytes(512, 512, 15, 67, true);
        assert!(e256 < 8_000_000_000, "{e256}");
        assert!(e512 > 3 * e256);
    }
}
