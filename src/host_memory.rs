//! How much memory this process may take and has taken, as the operating system says
//! (Linux's `/proc`, `getrlimit`, the control group's files): what the memory checks before
//! a morph (`app::memory`) and before decoding a large image (`io::images`) compare with.
//! And the one page setting the solver needs from the kernel ([`prefer_small_pages`]).

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

/// Turns transparent huge pages off for this process (`prctl(PR_SET_THP_DISABLE)`, Linux;
/// elsewhere nothing), as `MIMALLOC_ALLOW_THP=0` would, unless the user set that variable.
///
/// mimalloc asks for huge pages on its arenas (`MADV_HUGEPAGE`) and, after its purge delay,
/// hands free ranges of them back to the kernel. A solver that frees and allocates frames of
/// megabytes all the time then page-faults them in again as 2 MiB pages that the kernel
/// clears whole: measured on deep 2-level 256² runs (docs/benchmarks.md, "Huge pages"), the
/// system time was 12 s of a 52 s run and the sweeps ran 14 % faster with small pages at
/// no higher peak; whole default deep morphs gained 1–7 % (peak −6 % on one pair, +6 % on
/// another). The flag is the process's (its threads and children inherit it).
/// Call it before the work starts; returns whether it is off now.
pub fn prefer_small_pages() -> bool {
    if std::env::var_os("MIMALLOC_ALLOW_THP").is_some() {
        return false;
    }
    #[cfg(target_os = "linux")]
    {
        // SAFETY: PR_SET_THP_DISABLE takes plain integers and touches no memory of ours.
        unsafe { libc::prctl(libc::PR_SET_THP_DISABLE, 1, 0, 0, 0) == 0 }
    }
    #[cfg(not(target_os = "linux"))]
    {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_pages_are_asked_for_unless_the_user_chose() {
        let chosen = std::env::var_os("MIMALLOC_ALLOW_THP").is_some();
        let off = prefer_small_pages();
        if chosen {
            assert!(!off, "MIMALLOC_ALLOW_THP is set: the user's choice stands");
            return;
        }
        #[cfg(target_os = "linux")]
        {
            assert!(off, "prctl(PR_SET_THP_DISABLE) failed");
            // SAFETY: PR_GET_THP_DISABLE takes plain integers and touches no memory of ours.
            let flag = unsafe { libc::prctl(libc::PR_GET_THP_DISABLE, 0, 0, 0, 0) };
            assert_eq!(flag, 1, "the kernel reports THP still allowed");
            // A thread started after the call inherits the process's flag.
            let on_thread = std::thread::spawn(|| {
                // SAFETY: as above.
                unsafe { libc::prctl(libc::PR_GET_THP_DISABLE, 0, 0, 0, 0) }
            })
            .join()
            .unwrap();
            assert_eq!(on_thread, 1);
        }
    }

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
}
