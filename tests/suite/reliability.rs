//! What README's "Reliability" section promises, tried as a hostile user would: an output
//! folder never holds two runs' files and never loses the previous morph (whatever signal
//! stops a run), every limit is checked before anything large is allocated, and untrusted
//! files are read only as far as their declared, checked size.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::time::{Duration, Instant};

use assert_cmd::Command;
use common::fails;
use deepmorph::io::output_folder::OUTPUT_MARKER;
use deepmorph::io::outputs::output_names;
use deepmorph::io::truth::Correspondence;

fn scratch(name: &str) -> PathBuf {
    common::scratch("reliability", name)
}

fn deepmorph() -> Command {
    Command::cargo_bin("deepmorph").unwrap()
}

/// A demo morph of `k` steps at 32² into `out` that takes well under a second.
fn quick_demo(out: &Path, k: usize, extra: &[&str]) -> Command {
    let mut cmd = deepmorph();
    cmd.args([
        "demo", "--size", "32", "-q", "--levels", "2", "--sweeps", "2",
    ])
    .args(["--backend", "flex", "-K", &k.to_string(), "-o"])
    .arg(out)
    .args(extra);
    cmd
}

/// A demo morph of 3 steps into `out` that runs until it is signalled (no tolerance stop).
fn endless_demo(out: &Path, extra: &[&str]) -> Child {
    std::process::Command::new(assert_cmd::cargo::cargo_bin("deepmorph"))
        .args(["demo", "--size", "32", "-K", "3", "--levels", "2", "-q"])
        .args([
            "--sweeps",
            "1000000",
            "--tol",
            "0",
            "--backend",
            "flex",
            "-o",
        ])
        .arg(out)
        .args(extra)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// A folder `dir/out` holding a 6-step morph, and a forced 3-step run into it, two seconds in
/// (solving, the staging folder beside `out`).
fn running_over_a_previous_morph(name: &str) -> (PathBuf, PathBuf, Child) {
    let dir = scratch(name);
    let out = dir.join("out");
    quick_demo(&out, 6, &[]).assert().success();
    let child = endless_demo(&out, &["--force"]);
    std::thread::sleep(Duration::from_secs(2));
    (dir, out, child)
}

fn signal(child: &Child, name: &str) {
    let sent = std::process::Command::new("kill")
        .args([&format!("-{name}"), &child.id().to_string()])
        .status()
        .unwrap();
    assert!(sent.success(), "kill -{name}");
}

fn exit_code(child: &mut Child) -> Option<i32> {
    let deadline = Instant::now() + Duration::from_secs(120);
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status.code();
        }
        assert!(Instant::now() < deadline, "no exit 120 s after the signal");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// The sorted file names in `dir`.
fn listing(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// Asserts that `dir` holds exactly the outputs of one complete morph of `k` steps (with
/// its checkpoint when it was interrupted).
fn holds_one_morph(dir: &Path, k: usize) {
    let record: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.join("config.json")).unwrap()).unwrap();
    assert_eq!(record["config"]["solver"]["steps"], k);
    let mut expected = output_names(k);
    expected.push(OUTPUT_MARKER.into());
    let termination = record["outcome"]["termination"].as_str().unwrap();
    if termination.starts_with("interrupted") {
        expected.extend(["checkpoint.json", "checkpoint.f32"].map(String::from));
    }
    expected.sort();
    assert_eq!(listing(dir), expected, "{}", dir.display());
}

/// Asserts that `parent` holds nothing but `names` (no staging folder, no temporary file).
fn nothing_else_in(parent: &Path, names: &[&str]) {
    assert_eq!(listing(parent), names, "{}", parent.display());
}

#[test]
fn a_previous_morph_is_replaced_whole_and_only_with_force() {
    let dir = scratch("replace");
    let out = dir.join("out");
    quick_demo(&out, 6, &[]).assert().success();
    holds_one_morph(&out, 6);
    let err = fails(&mut quick_demo(&out, 2, &[]));
    assert!(err.contains("--force"), "{err}");
    holds_one_morph(&out, 6);
    // Fewer steps: no stale frame_03..06; more than 99: no two-digit frames left over.
    quick_demo(&out, 2, &["--force"]).assert().success();
    holds_one_morph(&out, 2);
    nothing_else_in(&dir, &["out"]);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_folder_of_other_files_is_never_replaced() {
    let dir = scratch("foreign");
    let out = dir.join("out");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("notes.txt"), b"precious").unwrap();
    let err = fails(&mut quick_demo(&out, 2, &["--force"]));
    assert!(err.contains("notes.txt"), "{err}");
    assert_eq!(listing(&out), ["notes.txt"]);
    nothing_else_in(&dir, &["out"]);
    // A file where the folder should be.
    let err = fails(&mut quick_demo(&out.join("notes.txt"), 2, &[]));
    assert!(err.contains("not a folder"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Files that merely carry the names deepmorph writes are not a previous output: without
/// the marker every output folder holds, `--force` refuses them and they stay (issue 43
/// #15: a user's `frame_00.png` and `config.json` were deleted by `morph --force`, their
/// `a.png` and `b.png` by `warp --force`).
#[test]
fn files_named_like_outputs_are_not_replaced_without_the_marker() {
    let dir = scratch("named");
    let out = dir.join("out");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("frame_00.png"), b"mine").unwrap();
    std::fs::write(out.join("config.json"), b"{}").unwrap();
    let err = fails(&mut quick_demo(&out, 2, &["--force"]));
    assert!(err.contains(OUTPUT_MARKER), "{err}");
    assert_eq!(listing(&out), ["config.json", "frame_00.png"]);
    let pair = dir.join("pair");
    std::fs::create_dir(&pair).unwrap();
    std::fs::write(pair.join("a.png"), b"mine").unwrap();
    std::fs::write(pair.join("b.png"), b"mine too").unwrap();
    let image = dir.join("in.png");
    image::RgbImage::from_pixel(32, 32, image::Rgb([9, 99, 199]))
        .save(&image)
        .unwrap();
    let err = fails(
        deepmorph()
            .args([
                "warp", "--field", "smooth", "--amount", "2", "--force", "-o",
            ])
            .arg(&pair)
            .arg(&image),
    );
    assert!(err.contains(OUTPUT_MARKER), "{err}");
    assert_eq!(std::fs::read(pair.join("a.png")).unwrap(), b"mine");
    // What deepmorph wrote is replaced as before.
    quick_demo(&out.with_file_name("ours"), 2, &[])
        .assert()
        .success();
    quick_demo(&out.with_file_name("ours"), 3, &["--force"])
        .assert()
        .success();
    holds_one_morph(&out.with_file_name("ours"), 3);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// An output folder that cannot be written is refused before the solve (this run would
/// never end if it started solving), and a failed run leaves no folder behind.
#[test]
fn an_unwritable_output_is_refused_before_any_work() {
    let err = fails(
        deepmorph()
            .args(["demo", "--size", "32", "--sweeps", "1000000", "-o"])
            .arg("/proc/self/deepmorph-out"),
    );
    assert!(
        err.contains("/proc/self/deepmorph-out") && err.contains("cannot be written"),
        "{err}"
    );
    let dir = scratch("failed");
    let out = dir.join("out");
    let err = fails(&mut quick_demo(&out, 2, &["--beta", "1.5"]));
    assert!(err.contains("beta = 1.5"), "{err}");
    let err = fails(&mut quick_demo(&out, 2, &["--eta", "nan"]));
    assert!(err.contains("eta"), "{err}");
    nothing_else_in(&dir, &[]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A working size the H.264 encoder cannot take (a side below 16) is refused before any
/// work when `morph.mp4` is asked for (issue 43 #7: it failed after the whole solve, nothing
/// written); without mp4 the same size morphs.
#[test]
fn a_frame_too_small_for_mp4_is_refused_before_any_work() {
    let dir = scratch("small_frames");
    let out = dir.join("out");
    for size in ["8", "12"] {
        let err = fails(
            deepmorph()
                .args(["demo", "--size", size, "--levels", "1", "--sweeps", "1"])
                .args(["--video", "mp4", "-o"])
                .arg(&out),
        );
        assert!(
            err.contains(&format!("{size}x{size}")) && err.contains("at least 16"),
            "{err}"
        );
        assert!(!out.exists());
    }
    deepmorph()
        .args([
            "demo", "--size", "8", "--levels", "1", "--sweeps", "1", "-K", "2", "-q",
        ])
        .args(["--backend", "flex", "--video", "gif", "-o"])
        .arg(&out)
        .assert()
        .success();
    assert!(out.join("morph.gif").is_file());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// SIGTERM and SIGHUP stop a run like Ctrl-C: after the sweep, every output written,
/// exit status 130, the previous morph replaced whole.
#[test]
fn sigterm_and_sighup_write_outputs_like_ctrl_c() {
    for name in ["TERM", "HUP"] {
        let (dir, out, mut child) = running_over_a_previous_morph(&format!("signal-{name}"));
        signal(&child, name);
        let code = exit_code(&mut child);
        let mut stderr = String::new();
        std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut stderr).unwrap();
        assert_eq!(code, Some(130), "SIG{name}: {stderr}");
        holds_one_morph(&out, 3);
        nothing_else_in(&dir, &["out"]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}

/// A second run into the folder a run is writing is refused before any work, even with
/// `--force`, and the first run's result arrives whole (issue 43 #1: both exited 0 and the
/// folder held only the last).
#[test]
fn a_second_run_into_a_folder_being_written_is_refused() {
    let (dir, out, mut child) = running_over_a_previous_morph("concurrent");
    let err = fails(&mut quick_demo(&out, 2, &["--force"]));
    assert!(
        err.contains("another deepmorph run") && err.contains(&child.id().to_string()),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
    signal(&child, "TERM");
    assert_eq!(exit_code(&mut child), Some(130));
    holds_one_morph(&out, 3);
    nothing_else_in(&dir, &["out"]);
    // Once the first has finished, the folder is free again.
    quick_demo(&out, 2, &["--force"]).assert().success();
    holds_one_morph(&out, 2);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A second signal aborts at once; the folder then holds either the previous morph or the
/// new one, complete, and no staging folder is left.
#[test]
fn a_second_signal_aborts_without_mixing_two_runs() {
    let (dir, out, mut child) = running_over_a_previous_morph("abort");
    signal(&child, "INT");
    signal(&child, "INT");
    assert_eq!(exit_code(&mut child), Some(130));
    let k = if listing(&out).len() == output_names(6).len() + 1 {
        6
    } else {
        3
    };
    holds_one_morph(&out, k);
    nothing_else_in(&dir, &["out"]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// SIGKILL cannot be caught: the previous morph stays whole, the killed run's staging folder
/// stays beside it, and the next run into the same place removes it.
#[test]
fn a_killed_run_leaves_the_previous_morph_and_is_cleaned_up_next_time() {
    let (dir, out, mut child) = running_over_a_previous_morph("kill");
    signal(&child, "KILL");
    assert_eq!(exit_code(&mut child), None);
    holds_one_morph(&out, 6);
    let staging = format!(".out.deepmorph-{}", child.id());
    nothing_else_in(&dir, &[&staging, "out"]);
    // A run into another folder of the same parent cleans it too (issue 43 #16).
    quick_demo(&dir.join("other"), 2, &[]).assert().success();
    nothing_else_in(&dir, &["other", "out"]);
    holds_one_morph(&out, 6);
    quick_demo(&out, 2, &["--force"]).assert().success();
    holds_one_morph(&out, 2);
    nothing_else_in(&dir, &["other", "out"]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Sizes and widths are bounded before anything is allocated: none of these may take
/// memory or time (the sizes would need terabytes).
#[test]
fn limits_are_checked_before_allocation() {
    let dir = scratch("limits");
    let out = dir.join("out");
    let demo = |size: &str, extra: &[&str]| {
        let mut cmd = deepmorph();
        cmd.args(["demo", "-q", "--backend", "flex", "--size", size, "-o"])
            .arg(&out)
            .args(extra);
        cmd
    };
    let err = fails(&mut demo("100000", &[]));
    assert!(err.contains("at most 8192"), "{err}");
    let err = fails(&mut demo("8192", &["--max-memory", "0.5"]));
    assert!(
        err.contains("needs about") && err.contains("--max-memory"),
        "{err}"
    );
    for (flag, value) in [("--sigma", "1e5"), ("--rho", "1e9")] {
        let err = fails(&mut quick_demo(&out, 2, &[flag, value]));
        assert!(err.contains("at most 100"), "{flag} {value}: {err}");
    }
    // A PNG whose header claims 20000² pixels: refused from the header, naming both sizes.
    let huge = dir.join("huge.png");
    std::fs::write(&huge, png_header(20000, 20000)).unwrap();
    let err = fails(
        deepmorph()
            .arg("morph")
            .args([&huge, &huge])
            .arg("-o")
            .arg(&out),
    );
    assert!(
        err.contains("20000x20000") && err.contains("16384"),
        "{err}"
    );
    nothing_else_in(&dir, &["huge.png"]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A PNG that claims `width × height` (8-bit RGB) in its header and holds no pixels: the
/// signature, IHDR, an empty IDAT and IEND.
fn png_header(width: u32, height: u32) -> Vec<u8> {
    let mut ihdr = width.to_be_bytes().to_vec();
    ihdr.extend(height.to_be_bytes());
    ihdr.extend([8, 2, 0, 0, 0]);
    let mut bytes = vec![0x89, b'P', b'N', b'G', 0x0d, 0x0a, 0x1a, 0x0a];
    for (kind, data) in [(b"IHDR", &ihdr[..]), (b"IDAT", &[]), (b"IEND", &[])] {
        let mut chunk = kind.to_vec();
        chunk.extend(data);
        bytes.extend((data.len() as u32).to_be_bytes());
        bytes.extend(&chunk);
        bytes.extend(crc32(&chunk).to_be_bytes());
    }
    bytes
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xedb8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// Inputs from a pipe (process substitution, `mkfifo`) are read like files.
#[test]
fn an_input_from_a_pipe_is_read() {
    let dir = scratch("fifo");
    let a = dir.join("a.png");
    image::RgbImage::from_fn(32, 32, |x, y| {
        image::Rgb([(x * 8) as u8, (y * 8) as u8, 90])
    })
    .save(&a)
    .unwrap();
    let fifo = dir.join("b.fifo");
    assert!(
        std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success()
    );
    let bytes = std::fs::read(&a).unwrap();
    let writer = {
        let fifo = fifo.clone();
        std::thread::spawn(move || std::fs::write(fifo, bytes).unwrap())
    };
    deepmorph()
        .arg("morph")
        .args([&a, &fifo])
        .args([
            "-K",
            "2",
            "--levels",
            "1",
            "--sweeps",
            "1",
            "-q",
            "--backend",
            "flex",
        ])
        .arg("-o")
        .arg(dir.join("out"))
        .assert()
        .success();
    writer.join().unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `eval` writes only with `--write`, checks that `config.json` describes the files, and
/// refuses a ground truth of another size unless told to resample it.
#[test]
fn eval_checks_the_folder_and_the_truth_and_writes_only_when_asked() {
    let dir = scratch("eval");
    let out = dir.join("out");
    quick_demo(&out, 2, &[]).assert().success();
    let metrics_before = std::fs::read(out.join("metrics.json")).unwrap();
    std::fs::remove_file(out.join("composed.json")).unwrap();
    deepmorph()
        .arg("eval")
        .arg(&out)
        .args(["--backend", "flex"])
        .assert()
        .success();
    assert!(
        !out.join("composed.json").exists(),
        "eval wrote without --write"
    );
    assert_eq!(
        std::fs::read(out.join("metrics.json")).unwrap(),
        metrics_before
    );

    let small = dir.join("small.flo");
    Correspondence::new(16, 16, vec![Some([0.0, 0.0]); 256])
        .unwrap()
        .write_flo(&small)
        .unwrap();
    let eval_small = |extra: &[&str]| {
        let mut cmd = deepmorph();
        cmd.arg("eval")
            .arg(&out)
            .arg("--truth")
            .arg(&small)
            .args(["--backend", "flex", "-q"])
            .args(extra);
        cmd
    };
    let err = fails(&mut eval_small(&[]));
    assert!(
        err.contains("16x16") && err.contains("--resample-truth"),
        "{err}"
    );
    eval_small(&["--resample-truth"]).assert().success();

    // A record that does not describe the files beside it: a mixed folder.
    let config = std::fs::read_to_string(out.join("config.json")).unwrap();
    let mut record: serde_json::Value = serde_json::from_str(&config).unwrap();
    record["config"]["solver"]["steps"] = 5.into();
    std::fs::write(out.join("config.json"), record.to_string()).unwrap();
    let err = fails(
        deepmorph()
            .arg("eval")
            .arg(&out)
            .args(["--backend", "flex"]),
    );
    assert!(
        err.contains("K = 5") && err.contains("different runs"),
        "{err}"
    );
    std::fs::write(out.join("config.json"), config).unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Readers of untrusted files read no more than the size they expect, follow no path out
/// of their folder, and name the file with what is wrong.
#[test]
fn untrusted_files_are_read_within_their_declared_size() {
    let dir = scratch("untrusted");
    let out = dir.join("out");
    quick_demo(&out, 2, &[]).assert().success();
    let eval = || {
        let mut cmd = deepmorph();
        cmd.arg("eval").arg(&out).args(["--backend", "flex", "-q"]);
        cmd
    };
    let header_path = out.join("deformations.json");
    let header = std::fs::read_to_string(&header_path).unwrap();
    for data in ["/dev/zero", "../../../etc/passwd", ".hidden"] {
        let mut edited: serde_json::Value = serde_json::from_str(&header).unwrap();
        edited["data"] = data.into();
        std::fs::write(&header_path, edited.to_string()).unwrap();
        let err = fails(&mut eval());
        assert!(err.contains("same folder"), "{data}: {err}");
    }
    let mut edited: serde_json::Value = serde_json::from_str(&header).unwrap();
    edited["shape"] = serde_json::json!([2, 2, 100000, 100000]);
    std::fs::write(&header_path, edited.to_string()).unwrap();
    let err = fails(&mut eval());
    assert!(err.contains("shape"), "{err}");
    std::fs::write(&header_path, &header).unwrap();
    // A NaN in the values names the file.
    let data = out.join("deformations.f32");
    let mut values = std::fs::read(&data).unwrap();
    values[..4].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&data, values).unwrap();
    let err = fails(&mut eval());
    assert!(
        err.contains("deformations.f32") && err.contains("NaN"),
        "{err}"
    );

    // Weights: a device that never ends is refused by its kind, before a byte is read.
    let err = fails(
        deepmorph()
            .args(["demo", "--size", "64", "--levels", "1", "--model", "deep"])
            .args(["--vgg19", "/dev/zero", "-o"])
            .arg(dir.join("deep")),
    );
    assert!(
        err.contains("/dev/zero") && err.contains("is a device"),
        "{err}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Unmounts a test's tmpfs whatever the test's outcome.
struct Mounted(PathBuf);

impl Drop for Mounted {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg(&self.0).status();
    }
}

/// A disk that fills up while the outputs are written (a 600 kB tmpfs, when the test runs as
/// root): the run fails naming the file and the cause, the previous morph stays whole and no
/// staging folder is left. Without root, a read-only parent is refused before any work.
#[test]
fn a_full_disk_fails_cleanly_and_keeps_the_previous_morph() {
    let dir = scratch("full");
    let root = std::process::Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0");
    let mounted = root
        && std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", "size=600k", "tmpfs"])
            .arg(&dir)
            .status()
            .is_ok_and(|s| s.success());
    if root && !mounted {
        // Root ignores permissions, so a read-only folder proves nothing either.
        eprintln!("skipped: running as root where tmpfs cannot be mounted");
        std::fs::remove_dir_all(&dir).unwrap();
        return;
    }
    if !mounted {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o555)).unwrap();
        let err = fails(&mut quick_demo(&dir.join("out"), 2, &[]));
        std::fs::set_permissions(&dir, std::fs::Permissions::from_mode(0o755)).unwrap();
        assert!(err.contains("cannot be written"), "{err}");
        nothing_else_in(&dir, &[]);
        std::fs::remove_dir_all(&dir).unwrap();
        return;
    }
    let unmount = Mounted(dir.clone());
    let out = dir.join("out");
    quick_demo(&out, 2, &[]).assert().success();
    // 31 frames and 30 fields of 64² (1 MB of deformations alone) do not fit.
    let err = fails(
        deepmorph()
            .args([
                "demo", "--size", "64", "-K", "30", "--levels", "1", "--sweeps", "1",
            ])
            .args(["-q", "--backend", "flex", "--force", "-o"])
            .arg(&out),
    );
    assert!(err.contains("No space left"), "{err}");
    holds_one_morph(&out, 2);
    nothing_else_in(&dir, &["out"]);
    drop(unmount);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `mkfifo path`.
fn fifo(path: &Path) {
    let made = std::process::Command::new("mkfifo").arg(path).status();
    assert!(made.unwrap().success(), "mkfifo {}", path.display());
}

/// The deep model's weights from a pipe are read once: the feature-space metric after the
/// solve uses the same weights instead of opening the pipe again, where no writer would
/// ever come (issue 43 #4: the run hung after the solve and ignored SIGTERM).
#[test]
fn weights_from_a_pipe_are_read_once() {
    let Some(vgg19) = common::stand_in_vgg19() else {
        return;
    };
    let dir = scratch("weights-fifo");
    let pipe = dir.join("vgg19.fifo");
    fifo(&pipe);
    let writer = {
        let (pipe, vgg19) = (pipe.clone(), vgg19.clone());
        // One writer, once; the pipe's read end closes after it.
        std::thread::spawn(move || std::fs::write(pipe, std::fs::read(vgg19).unwrap()))
    };
    let out = dir.join("out");
    let mut child = std::process::Command::new(assert_cmd::cargo::cargo_bin("deepmorph"))
        .args([
            "demo", "--size", "64", "-K", "2", "--levels", "1", "--sweeps", "1",
        ])
        .args([
            "--pre-sweeps",
            "1",
            "-q",
            "--backend",
            "flex",
            "--model",
            "deep",
        ])
        .arg("--vgg19")
        .arg(&pipe)
        .arg("-o")
        .arg(&out)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Generous: a hang would never end.
    let deadline = Instant::now() + Duration::from_secs(120);
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if Instant::now() > deadline {
            child.kill().unwrap();
            panic!("the run with weights from a pipe did not end in 120 s");
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut stderr).unwrap();
    assert!(status.success(), "{status:?}: {stderr}");
    writer.join().unwrap().unwrap();
    let metrics: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("metrics.json")).unwrap()).unwrap();
    assert!(
        metrics.to_string().contains("feature_path"),
        "the feature-space metric is missing: {metrics}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A signal before the solve began (here: the weights are a pipe nobody writes, so the run
/// waits in `open`) ends the run at once with nothing written (issue 43 #4 and #10: SIGTERM
/// was acted on only after the wait, or 26 s later in the time estimate's calibration).
#[test]
fn a_signal_before_the_solve_ends_the_run_at_once() {
    let dir = scratch("early-signal");
    let pipe = dir.join("never.fifo");
    fifo(&pipe);
    let out = dir.join("out");
    for name in ["TERM", "INT"] {
        let mut child = std::process::Command::new(assert_cmd::cargo::cargo_bin("deepmorph"))
            .args([
                "demo",
                "--size",
                "64",
                "-K",
                "2",
                "--levels",
                "1",
                "--backend",
                "flex",
            ])
            .args(["--model", "deep", "--vgg19"])
            .arg(&pipe)
            .arg("-o")
            .arg(&out)
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_millis(1500));
        let sent = Instant::now();
        signal(&child, name);
        let code = exit_code(&mut child);
        let mut stderr = String::new();
        std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut stderr).unwrap();
        assert_eq!(code, Some(130), "SIG{name}: {stderr}");
        assert!(
            sent.elapsed() < Duration::from_secs(5),
            "SIG{name} took {:?}",
            sent.elapsed()
        );
        assert!(stderr.contains("nothing written"), "{stderr}");
        nothing_else_in(&dir, &["never.fifo"]);
    }
    // The calibration of a path of thousands of steps is short: a signal right after it
    // started is acted on within seconds (it took 38 s at K = 4000 before).
    let took = terminated_after(thousand_step_demo(&out, &["--levels", "2"]), 300);
    // Debug build: the calibration's two 16-step sweeps, or one sweep of the solve.
    assert!(took < Duration::from_secs(60), "{took:?}");
    // During the solve, a signal is acted on after the step running, not after the sweep of
    // 4000 steps (a minute in this debug build): the checkpoint records the blocks run.
    let took = terminated_after(
        thousand_step_demo(&out, &["--levels", "1", "-q", "--force"]),
        4000,
    );
    let header: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("checkpoint.json")).unwrap()).unwrap();
    assert_eq!(header["sweeps"], 0, "{header}");
    let blocks = header["partial"]["blocks"].as_u64().unwrap_or(0);
    assert!(blocks > 0 && blocks < 7999, "{header}");
    // The outputs of 4001 frames are written after the stop.
    assert!(took < Duration::from_secs(30), "{took:?}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A demo morph of 32², `K` = 4000 on flex into `out`, with `extra` flags, started.
fn thousand_step_demo(out: &Path, extra: &[&str]) -> Child {
    std::process::Command::new(assert_cmd::cargo::cargo_bin("deepmorph"))
        .args(["demo", "--size", "32", "-K", "4000", "--backend", "flex"])
        .args(extra)
        .arg("-o")
        .arg(out)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

/// Sends SIGTERM to `child` `millis` ms after it started, checks that it exits 130, and
/// returns how long that took after the signal.
fn terminated_after(mut child: Child, millis: u64) -> Duration {
    std::thread::sleep(Duration::from_millis(millis));
    let sent = Instant::now();
    signal(&child, "TERM");
    assert_eq!(exit_code(&mut child), Some(130));
    sent.elapsed()
}

/// Devices are refused by their kind before a byte is read, and a regular file larger than
/// its kind may be by its size (issue 43 #5: `/dev/zero` as an image, a ground truth or the
/// weights took 2–6 GB before failing).
#[test]
fn devices_and_oversized_files_are_refused_before_reading() {
    let dir = scratch("devices");
    let a = dir.join("a.png");
    image::RgbImage::from_pixel(32, 32, image::Rgb([10, 20, 30]))
        .save(&a)
        .unwrap();
    let zero = Path::new("/dev/zero");
    let err = fails(
        deepmorph()
            .arg("morph")
            .arg(zero)
            .arg(&a)
            .arg("-o")
            .arg(dir.join("o1")),
    );
    assert!(
        err.contains("/dev/zero") && err.contains("a device"),
        "{err}"
    );
    let err = fails(
        deepmorph()
            .args(["demo", "--size", "64", "--model", "deep", "--vgg19"])
            .arg(zero)
            .arg("-o")
            .arg(dir.join("o2")),
    );
    assert!(
        err.contains("/dev/zero") && err.contains("a device"),
        "{err}"
    );
    // A 2 GiB sparse "weights" file: refused by its size, nothing read.
    let sparse = dir.join("huge.onnx");
    std::fs::File::create(&sparse)
        .unwrap()
        .set_len(2 << 30)
        .unwrap();
    let err = fails(
        deepmorph()
            .args(["demo", "--size", "64", "--model", "deep", "--vgg19"])
            .arg(&sparse)
            .arg("-o")
            .arg(dir.join("o3")),
    );
    assert!(err.contains("2147483648 bytes"), "{err}");
    nothing_else_in(&dir, &["a.png", "huge.onnx"]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The memory check takes the least of the memory available, the address-space limit
/// (`ulimit -v`) and the control group's limit (issue 43 #14: under `ulimit -v` a morph
/// that could not fit started and was aborted by a failed allocation, exit 134).
#[test]
fn the_address_space_limit_is_part_of_the_memory_check() {
    let dir = scratch("ulimit");
    let run = |side: &str, out: &str| {
        let mut cmd = std::process::Command::new("sh");
        cmd.arg("-c")
            .arg("ulimit -v 1572864 && exec \"$0\" \"$@\"")
            .arg(assert_cmd::cargo::cargo_bin("deepmorph"))
            .args([
                "demo", "--size", side, "-K", "15", "--levels", "2", "--sweeps", "1",
            ])
            .args(["-q", "--backend", "flex", "-o"])
            .arg(dir.join(out));
        cmd.output().unwrap()
    };
    // 1.5 GiB of address space (the debug program maps about 350 MiB before the check): a
    // 1024² morph (estimate 3.4 GB) is refused by name ...
    let big = run("1024", "big");
    let stderr = String::from_utf8_lossy(&big.stderr);
    assert_eq!(big.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("ulimit -v"), "{stderr}");
    // ... and a small one fits.
    let small = run("32", "small");
    assert!(
        small.status.success(),
        "{}",
        String::from_utf8_lossy(&small.stderr)
    );
    nothing_else_in(&dir, &["small"]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Model parameters outside what float32 energies hold are refused by name before any work
/// (issue 43 #11: they made NaN in the calibration, exit 1 with no level or sweep named).
#[test]
fn parameters_that_would_overflow_are_refused() {
    let dir = scratch("overflow");
    let out = dir.join("out");
    for (flag, value) in [
        ("--lambda", "1e308"),
        ("--mu", "1e308"),
        ("--xi2", "1e308"),
        ("--delta", "1e-320"),
        ("--sigma", "1e-320"),
        ("--rho", "1e-320"),
    ] {
        let err = fails(&mut quick_demo(&out, 2, &[flag, value]));
        let name = flag.trim_start_matches("--");
        assert!(
            err.contains(name) && err.contains("[1e-12, 1e12]"),
            "{flag} {value}: {err}"
        );
    }
    let err = fails(&mut quick_demo(
        &out,
        2,
        &[
            "--model",
            "deep",
            "--vgg19",
            "/nonexistent",
            "--eta",
            "1e308",
        ],
    ));
    assert!(err.contains("eta"), "{err}");
    nothing_else_in(&dir, &[]);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Messages say what happened (issue 43 #18): a symbolic link as `-o`, a name too long for
/// the staging folder, a checkpoint whose two files do not belong together or whose partial
/// sweep does not fit its `K`, a checkpoint holding a NaN (named), half a checkpoint (no
/// silent restart from scratch).
#[test]
fn messages_say_what_happened() {
    let dir = scratch("messages");
    let real = dir.join("real");
    std::fs::create_dir(&real).unwrap();
    let link = dir.join("link");
    std::os::unix::fs::symlink(&real, &link).unwrap();
    let err = fails(&mut quick_demo(&link, 2, &[]));
    assert!(err.contains("symbolic link"), "{err}");
    let long = dir.join("o".repeat(240));
    let err = fails(&mut quick_demo(&long, 2, &[]));
    assert!(
        err.contains("240 bytes") && err.contains("at most"),
        "{err}"
    );
    // An interrupted morph with a checkpoint.
    let out = dir.join("out");
    let mut child = endless_demo(&out, &[]);
    std::thread::sleep(Duration::from_millis(1500));
    signal(&child, "INT");
    assert_eq!(exit_code(&mut child), Some(130));
    let header = out.join("checkpoint.json");
    let data = out.join("checkpoint.f32");
    let (header_bytes, data_bytes) = (
        std::fs::read(&header).unwrap(),
        std::fs::read(&data).unwrap(),
    );
    let resume = |extra: &[&str]| {
        let mut cmd = deepmorph();
        cmd.args(["morph", "-q", "--resume"]).arg(&out).args(extra);
        fails(&mut cmd)
    };
    // Another K in the header: the sizes disagree.
    let json: serde_json::Value = serde_json::from_slice(&header_bytes).unwrap();
    let mut edited = json.clone();
    edited["steps"] = serde_json::json!(json["steps"].as_u64().unwrap() + 2);
    std::fs::write(&header, serde_json::to_vec(&edited).unwrap()).unwrap();
    let err = resume(&[]);
    assert!(err.contains("do not belong together"), "{err}");
    // A partial sweep of more blocks than a sweep has: named, not run.
    let mut edited = json.clone();
    edited["partial"] = serde_json::json!({
        "blocks": 99, "deformation": [], "features": [], "residual_norm2": [null, null, null]
    });
    std::fs::write(&header, serde_json::to_vec(&edited).unwrap()).unwrap();
    let err = resume(&[]);
    assert!(
        err.contains("partial sweep (99 blocks") && err.contains("K = 3"),
        "{err}"
    );
    std::fs::write(&header, &header_bytes).unwrap();
    // A NaN in the values: the file and the value named.
    let mut nan = data_bytes.clone();
    nan[40..44].copy_from_slice(&f32::NAN.to_le_bytes());
    std::fs::write(&data, &nan).unwrap();
    let err = resume(&[]);
    assert!(
        err.contains("checkpoint.f32") && err.contains("value 10 is NaN"),
        "{err}"
    );
    std::fs::write(&data, &data_bytes).unwrap();
    // The header gone: refused, not restarted from scratch.
    std::fs::remove_file(&header).unwrap();
    let err = resume(&[]);
    assert!(
        err.contains("checkpoint.json") && err.contains("missing"),
        "{err}"
    );
    // A chain's folder: its segments are the morphs to resume (it said "config.json: No
    // such file").
    let chain = dir.join("chain");
    std::fs::create_dir_all(chain.join("segment_01")).unwrap();
    let err = fails(deepmorph().args(["morph", "-q", "--resume"]).arg(&chain));
    assert!(err.contains("chain") && err.contains("segment_NN"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A decompression bomb (a small PNG of a large image of zeros) is refused before decoding
/// when reading and resizing it would not fit the memory the process may take, here under
/// `ulimit -v` (issue 43 #6: a 783 kB PNG of 16384² zeros took 7.1 GB, and under
/// `ulimit -v 3000000` the failed allocation was a panic, exit 101).
#[test]
fn a_decompression_bomb_is_refused_within_the_memory_limit() {
    let dir = scratch("bomb");
    let bomb = dir.join("zeros.png");
    image::GrayImage::new(8192, 8192).save(&bomb).unwrap();
    assert!(std::fs::metadata(&bomb).unwrap().len() < 1 << 20);
    let output = std::process::Command::new("sh")
        .arg("-c")
        .arg("ulimit -v 1572864 && exec \"$0\" \"$@\"")
        .arg(assert_cmd::cargo::cargo_bin("deepmorph"))
        .arg("morph")
        .args([&bomb, &bomb])
        .args([
            "--size", "32x32", "-K", "3", "--levels", "2", "--sweeps", "5", "-q",
        ])
        .arg("-o")
        .arg(dir.join("out"))
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("zeros.png")
            && stderr.contains("8192x8192")
            && stderr.contains("ulimit -v"),
        "{stderr}"
    );
    nothing_else_in(&dir, &["zeros.png"]);
    std::fs::remove_dir_all(&dir).unwrap();
}
