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

/// The most memory this process may still take, in bytes, and what sets it: the least of
/// the memory available now (`MemAvailable`), the room left under the address-space limit
/// (`ulimit -v`, `RLIMIT_AS`, less what the process has mapped already: past it an
/// allocation fails and the program aborts) and the room left in its control group
/// (cgroup v2 `memory.max`, v1 `memory.limit_in_bytes`, less the group's usage: past it
/// the kernel kills the process). `None` where none of them is known.
pub fn host_limit() -> Option<(u64, &'static str)> {
    let address_space = rustix::process::getrlimit(rustix::process::Resource::As)
        .current
        .map(|limit| limit.saturating_sub(mapped_bytes().unwrap_or(0)));
    [
        (available_bytes(), "the memory available"),
        (
            address_space,
            "the room under the address-space limit (ulimit -v)",
        ),
        (
            cgroup_room(),
            "the room under the control group's memory limit",
        ),
    ]
    .into_iter()
    .filter_map(|(bytes, name)| Some((bytes?, name)))
    .min_by_key(|&(bytes, _)| bytes)
}

/// The memory the operating system says is available now (`MemAvailable` on Linux), or
/// `None` where that is unknown.
pub fn available_bytes() -> Option<u64> {
    status_kib(
        &std::fs::read_to_string("/proc/meminfo").ok()?,
        "MemAvailable:",
    )
}

/// This process's mapped address space now (`VmSize`).
fn mapped_bytes() -> Option<u64> {
    status_kib(
        &std::fs::read_to_string("/proc/self/status").ok()?,
        "VmSize:",
    )
}

/// The value in bytes of the `key:  N kB` line of a `/proc` status file.
fn status_kib(text: &str, key: &str) -> Option<u64> {
    let line = text.lines().find(|l| l.starts_with(key))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib * 1024)
}

/// The room left under this process's control group's memory limit, if it has one.
fn cgroup_room() -> Option<u64> {
    let membership = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    let read = |path: String| std::fs::read_to_string(path).ok();
    cgroup_room_from(&membership, read)
}

/// [`cgroup_room`] from the text of `/proc/self/cgroup` and a reader of files by path. A
/// group's path as seen from inside a container may not exist under the mount (the
/// container's own group is the mount's root), so the root is tried after it.
fn cgroup_room_from(membership: &str, read: impl Fn(String) -> Option<String>) -> Option<u64> {
    // "No limit" is written as "max" (v2) or as a number near 2^63 (v1).
    let number =
        |text: String| -> Option<u64> { text.trim().parse::<u64>().ok().filter(|&b| b < 1 << 60) };
    let room = |limit: Option<u64>, usage: Option<u64>| Some(limit?.saturating_sub(usage?));
    for line in membership.lines() {
        let mut fields = line.splitn(3, ':');
        let (Some(id), Some(controllers), Some(path)) =
            (fields.next(), fields.next(), fields.next())
        else {
            continue;
        };
        let path = path.trim_end_matches('/');
        let found = if id == "0" && controllers.is_empty() {
            [format!("/sys/fs/cgroup{path}"), "/sys/fs/cgroup".into()]
                .into_iter()
                .find_map(|dir| {
                    room(
                        read(format!("{dir}/memory.max")).and_then(number),
                        read(format!("{dir}/memory.current")).and_then(number),
                    )
                })
        } else if controllers.split(',').any(|c| c == "memory") {
            let mount = "/sys/fs/cgroup/memory";
            [format!("{mount}{path}"), mount.into()]
                .into_iter()
                .find_map(|dir| {
                    room(
                        read(format!("{dir}/memory.limit_in_bytes")).and_then(number),
                        read(format!("{dir}/memory.usage_in_bytes")).and_then(number),
                    )
                })
        } else {
            None
        };
        if found.is_some() {
            return found;
        }
    }
    None
}

/// This process's peak resident memory so far (`VmHWM` on Linux), for reports.
pub fn peak_resident_bytes() -> Option<u64> {
    status_kib(
        &std::fs::read_to_string("/proc/self/status").ok()?,
        "VmHWM:",
    )
}

/// `bytes` in GiB for messages.
pub fn gib(bytes: u64) -> f64 {
    bytes as f64 / (1u64 << 30) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn control_group_limits_are_read_for_v1_and_v2_and_inside_a_container() {
        let files = |pairs: &'static [(&'static str, &'static str)]| {
            move |path: String| {
                pairs
                    .iter()
                    .find(|(p, _)| *p == path)
                    .map(|(_, text)| text.to_string())
            }
        };
        // v2, the group's own folder.
        let v2 = files(&[
            ("/sys/fs/cgroup/user/job/memory.max", "1073741824\n"),
            ("/sys/fs/cgroup/user/job/memory.current", "73741824\n"),
        ]);
        assert_eq!(cgroup_room_from("0::/user/job\n", v2), Some(1_000_000_000));
        // v2 without a limit.
        let v2_max = files(&[
            ("/sys/fs/cgroup/memory.max", "max\n"),
            ("/sys/fs/cgroup/memory.current", "5\n"),
        ]);
        assert_eq!(cgroup_room_from("0::/\n", v2_max), None);
        // v1 inside a container: the listed path is not under the mount, its root is the group.
        let v1 = files(&[
            ("/sys/fs/cgroup/memory/memory.limit_in_bytes", "2000\n"),
            ("/sys/fs/cgroup/memory/memory.usage_in_bytes", "500\n"),
        ]);
        let membership = "5:devices:/\n4:memory,foo:/process_api/abc\n0::/\n";
        assert_eq!(cgroup_room_from(membership, v1), Some(1500));
        // v1 without a limit (this machine's case).
        let v1_none = files(&[
            (
                "/sys/fs/cgroup/memory/memory.limit_in_bytes",
                "9223372036854771712\n",
            ),
            (
                "/sys/fs/cgroup/memory/memory.usage_in_bytes",
                "3346096128\n",
            ),
        ]);
        assert_eq!(cgroup_room_from("4:memory:/x\n", v1_none), None);
        // Usage above the limit leaves no room, not a wrapped number.
        let full = files(&[
            ("/sys/fs/cgroup/memory.max", "100"),
            ("/sys/fs/cgroup/memory.current", "200"),
        ]);
        assert_eq!(cgroup_room_from("0::/\n", full), Some(0));
    }

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
