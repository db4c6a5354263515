//! The `deepmorph` binary end to end on tiny inputs: outputs written and reloadable, inputs of
//! two sizes resized, and every kind of bad input rejected with one clear line, a non-zero
//! exit and no panic.

use crate::common;

use std::path::{Path, PathBuf};

use assert_cmd::Command;
use common::fails;
use deepmorph::Backend;
use deepmorph::io::energy_log::EnergyLog;
use deepmorph::io::images::{RgbImage, write_png};
use deepmorph::io::outputs::load_deformations;

fn scratch(name: &str) -> PathBuf {
    common::scratch("cli", name)
}

fn deepmorph() -> Command {
    Command::cargo_bin("deepmorph").unwrap()
}

/// A smooth test image of `h × w` with a bright spot at `(cy, cx)` (fractions).
fn write_image(path: &Path, h: usize, w: usize, cy: f64, cx: f64) {
    let n = h * w;
    let mut data = vec![0.0f32; 3 * n];
    for i in 0..h {
        for j in 0..w {
            let (y, x) = (i as f64 / h as f64 - cy, j as f64 / w as f64 - cx);
            let v = (-(x * x + y * y) / 0.02).exp() as f32;
            for c in 0..3 {
                data[c * n + i * w + j] = 0.2 + 0.6 * v * (1.0 - 0.2 * c as f32);
            }
        }
    }
    write_png(path, &RgbImage::new(h, w, data).unwrap().to_rgb8()).unwrap();
}

/// Every frame of an animated PNG, as 8-bit RGB bytes, in play order.
fn apng_frames(path: &Path) -> Vec<Vec<u8>> {
    let bytes = std::fs::read(path).unwrap();
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes))
        .read_info()
        .unwrap();
    let count = reader.info().animation_control.unwrap().num_frames;
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    (0..count)
        .map(|_| {
            let info = reader.next_frame(&mut buf).unwrap();
            buf[..info.buffer_size()].to_vec()
        })
        .collect()
}

const TINY: [&str; 8] = [
    "-K",
    "3",
    "--levels",
    "2",
    "--sweeps",
    "3",
    "--backend",
    "flex",
];

#[test]
fn demo_writes_every_output() {
    let dir = scratch("demo");
    let out = dir.join("out");
    deepmorph()
        .args(["demo", "--size", "32", "-q", "-o"])
        .arg(&out)
        .args(TINY)
        .assert()
        .success();
    for name in deepmorph::io::outputs::output_names(3) {
        assert!(out.join(&name).is_file(), "missing {name}");
    }
    let frame = RgbImage::load(&out.join("frame_03.png")).unwrap();
    assert_eq!((frame.height(), frame.width()), (32, 32));
    let (shape, phi) = load_deformations(&out).unwrap();
    assert_eq!(shape, [3, 2, 32, 32]);
    assert!(phi.iter().all(|v| v.is_finite()));
    let csv = std::fs::read_to_string(out.join("energy.csv")).unwrap();
    assert_eq!(
        csv.lines().count(),
        1 + 2 * 4,
        "header + (1 + 3 sweeps) per level"
    );
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
    assert_eq!(config["config"]["solver"]["steps"], 3);
    assert_eq!(config["outcome"]["termination"], "completed");
    assert!(
        !std::fs::read_dir(&out)
            .unwrap()
            .any(|e| { e.unwrap().file_name().to_string_lossy().contains(".tmp-") })
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--frames N` makes the animations N frames long, starting and ending on the computed
/// frames; fewer than K + 1 is refused before any work.
#[test]
fn frames_sets_the_animation_length() {
    let dir = scratch("frames");
    let out = dir.join("out");
    deepmorph()
        .args(["demo", "--size", "32", "-q", "--frames", "10", "-o"])
        .arg(&out)
        .args(TINY)
        .assert()
        .success();
    let decoded = apng_frames(&out.join("morph.apng"));
    assert_eq!(decoded.len(), 10);
    for (j, k) in [(0, 0), (9, 3)] {
        let frame = RgbImage::load(&out.join(format!("frame_0{k}.png"))).unwrap();
        assert_eq!(
            decoded[j],
            frame.to_rgb8().into_raw(),
            "clip frame {j} is frame {k}"
        );
    }
    // In between, a clip frame differs from both computed frames around it.
    let first = RgbImage::load(&out.join("frame_00.png"))
        .unwrap()
        .to_rgb8()
        .into_raw();
    assert_ne!(decoded[1], first);
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
    assert_eq!(config["config"]["animation_frames"], 10);

    let err = fails(
        deepmorph()
            .args(["demo", "--size", "32", "-q", "--frames", "3", "-o"])
            .arg(dir.join("refused"))
            .args(TINY),
    );
    assert!(err.contains("frames") && err.contains("K + 1 = 4"), "{err}");
    assert!(!dir.join("refused").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn morph_resizes_inputs_of_two_sizes() {
    let dir = scratch("morph");
    let (a, b) = (dir.join("a.png"), dir.join("b.png"));
    write_image(&a, 40, 48, 0.5, 0.4);
    write_image(&b, 30, 36, 0.5, 0.6);
    let out = dir.join("out");
    let assert = deepmorph()
        .arg("morph")
        .args([&a, &b])
        .args(["--max-side", "32", "-o"])
        .arg(&out)
        .args(TINY)
        .assert()
        .success();
    let stderr = String::from_utf8_lossy(&assert.get_output().stderr).into_owned();
    // 48x40 scaled to a longest side of 32 is 32x26.7, rounded to multiples of 2.
    assert!(
        stderr.contains("A: 48x40 resized to the working size 32x26"),
        "{stderr}"
    );
    assert!(
        stderr.contains("B: 36x30 resized to the working size 32x26"),
        "{stderr}"
    );
    let frame = RgbImage::load(&out.join("frame_00.png")).unwrap();
    assert_eq!((frame.height(), frame.width()), (26, 32));
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn bad_inputs_fail_with_a_clear_message() {
    let dir = scratch("bad");
    let (a, b) = (dir.join("a.png"), dir.join("b.png"));
    write_image(&a, 16, 16, 0.5, 0.4);
    write_image(&b, 16, 16, 0.5, 0.6);
    let out = dir.join("out");
    let morph = |extra: &[&str]| {
        let mut cmd = deepmorph();
        cmd.arg("morph")
            .args([&a, &b])
            .arg("-o")
            .arg(&out)
            .args(extra);
        if !extra.contains(&"-K") {
            cmd.args(&TINY[..2]);
        }
        cmd.args(&TINY[2..]);
        cmd
    };

    let missing = dir.join("missing.png");
    let err = fails(
        deepmorph()
            .arg("morph")
            .args([&missing, &b])
            .arg("-o")
            .arg(&out),
    );
    assert!(err.contains("missing.png"), "{err}");

    let garbage = dir.join("garbage.png");
    std::fs::write(&garbage, b"not an image at all").unwrap();
    let err = fails(
        deepmorph()
            .arg("morph")
            .args([&garbage, &b])
            .arg("-o")
            .arg(&out),
    );
    assert!(err.contains("garbage.png"), "{err}");

    let err = fails(&mut morph(&["-K", "0"]));
    assert!(err.contains("K = 0"), "{err}");
    let err = fails(&mut morph(&["--delta", "-1"]));
    assert!(err.contains("delta = -1"), "{err}");
    let err = fails(&mut morph(&["--mu", "NaN"]));
    assert!(err.contains("mu = NaN"), "{err}");
    let err = fails(&mut morph(&["--beta", "1.5"]));
    assert!(err.contains("beta = 1.5"), "{err}");
    let err = fails(&mut morph(&["--size", "33x32"]));
    assert!(err.contains("multiples of 2"), "{err}");
    let err = fails(&mut morph(&["--backend", "cuda"]));
    assert!(err.contains("cuda"), "{err}");

    // An input that would be overwritten by an output: refused, and left intact.
    let frame0 = dir.join("frame_00.png");
    std::fs::copy(&a, &frame0).unwrap();
    let before = std::fs::read(&frame0).unwrap();
    let err = fails(
        deepmorph()
            .arg("morph")
            .args([&frame0, &b])
            .arg("-o")
            .arg(&dir)
            .args(TINY),
    );
    assert!(err.contains("holds the input"), "{err}");
    assert_eq!(std::fs::read(&frame0).unwrap(), before);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Ctrl-C stops after the current step and still writes every output (exit status 130).
#[test]
fn interrupt_writes_outputs() {
    let dir = scratch("interrupt");
    let out = dir.join("out");
    let binary = assert_cmd::cargo::cargo_bin("deepmorph");
    let mut child = std::process::Command::new(binary)
        .args([
            "demo", "--size", "32", "-K", "3", "--levels", "2", "--sweeps", "1000000", "--tol",
            "0", "-q",
        ])
        .args(["--backend", "flex", "-o"])
        .arg(&out)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_secs(2));
    let killed = std::process::Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(120);
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "no exit 120 s after Ctrl-C"
        );
        std::thread::sleep(std::time::Duration::from_millis(100));
    };
    assert_eq!(status.code(), Some(130));
    for name in deepmorph::io::outputs::output_names(3) {
        assert!(out.join(&name).is_file(), "missing {name}");
    }
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
    let termination = config["outcome"]["termination"].as_str().unwrap();
    assert!(
        termination.starts_with("interrupted at level 0"),
        "{termination}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A NaN met by the solver (injected after sweep 2 of level 1) still writes every output,
/// from the last finite iterate, says where it happened, and exits with status 3.
#[test]
fn a_nonfinite_value_writes_outputs_and_exits_3() {
    let dir = scratch("nonfinite");
    let out = dir.join("out");
    let output = deepmorph()
        .args(["demo", "--size", "32", "-o"])
        .arg(&out)
        .args([
            "-K",
            "3",
            "--levels",
            "2",
            "--sweeps",
            "4",
            "--backend",
            "flex",
        ])
        .env("DEEPMORPH_INJECT_NONFINITE", "1:2")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert_eq!(output.status.code(), Some(3), "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
    assert!(
        stderr.contains("non-finite value at level 1, sweep 2") && stderr.contains("NaN"),
        "{stderr}"
    );
    for name in deepmorph::io::outputs::output_names(3) {
        assert!(out.join(&name).is_file(), "missing {name}");
    }
    let (_, phi) = load_deformations(&out).unwrap();
    assert!(phi.iter().all(|v| v.is_finite()));
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
    let termination = config["outcome"]["termination"].as_str().unwrap();
    assert!(
        termination.contains("non-finite value at level 1, sweep 2"),
        "{termination}"
    );
    // The energy log ends with the last finite sweep.
    let log =
        EnergyLog::from_csv(&std::fs::read_to_string(out.join("energy.csv")).unwrap()).unwrap();
    let last = log.records.last().unwrap();
    assert_eq!((last.level, last.sweep), (1, 1));
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `energy.csv` and the `-v` log count the safeguard's restarts and the dropped steps of every
/// sweep (SPEC §6).
#[test]
fn restarts_and_drops_are_logged() {
    let dir = scratch("restarts");
    let out = dir.join("out");
    let output = deepmorph()
        .args(["demo", "--size", "32", "-v", "-o"])
        .arg(&out)
        .args(TINY)
        .output()
        .unwrap();
    assert!(output.status.success());
    let stderr = String::from_utf8_lossy(&output.stderr);
    let csv = std::fs::read_to_string(out.join("energy.csv")).unwrap();
    assert!(
        csv.lines()
            .next()
            .unwrap()
            .ends_with(",restarts,drops_phi,drops_f,stop,m_phi,E_lm,trials_phi,trials_f"),
        "{csv}"
    );
    let log = EnergyLog::from_csv(&csv).unwrap();
    // 2 levels × (the initial state and 3 sweeps).
    assert_eq!(log.records.len(), 8);
    // One `-v` line per row of the log, with the same counts.
    let count = |line: &str, label: &str| -> usize {
        let rest = &line[line
            .find(label)
            .unwrap_or_else(|| panic!("{label} in {line}"))
            + label.len()..];
        rest.split(|c: char| !c.is_ascii_digit())
            .next()
            .unwrap()
            .parse()
            .unwrap()
    };
    let sweep_lines: Vec<&str> = stderr.lines().filter(|l| l.contains("/3: E = ")).collect();
    assert_eq!(sweep_lines.len(), log.records.len(), "{stderr}");
    for (line, record) in sweep_lines.iter().zip(&log.records) {
        assert_eq!(count(line, "restarts "), record.restarts, "{line}");
        assert_eq!(count(line, "dropped phi "), record.drops_phi, "{line}");
        assert_eq!(count(line, " f "), record.drops_f, "{line}");
        assert_eq!(count(line, "phi trials "), record.trials_phi, "{line}");
        // Every search tries at least once: K = 3 deformation searches, and K − 1 = 2 feature
        // steps of the RGB model's one block each.
        if record.sweep > 0 {
            assert!(record.trials_phi >= 3, "{record:?}");
            assert!(record.trials_f >= 2, "{record:?}");
        }
        // Each joint sweep logs the streak each of the K = 3 deformation searches started with.
        let streaks = if record.sweep == 0 { 0 } else { 3 };
        assert_eq!(record.streak_phi.len(), streaks, "{record:?}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `config.json` is the record of a run: `morph --config OUT/config.json -o OUT2` runs the
/// same morph again (the demo's inputs are recorded as such) and gets the same deformations.
#[test]
fn a_recorded_config_reproduces_the_run() {
    let dir = scratch("reproduce");
    let (first, second) = (dir.join("first"), dir.join("second"));
    deepmorph()
        .args([
            "demo", "--size", "32", "-q", "--delta", "0.5", "--beta", "0.5", "-o",
        ])
        .arg(&first)
        .args(TINY)
        .assert()
        .success();
    deepmorph()
        .args(["morph", "-q", "--config"])
        .arg(first.join("config.json"))
        .arg("-o")
        .arg(&second)
        .assert()
        .success();
    let (shape, a) = load_deformations(&first).unwrap();
    let (shape_b, b) = load_deformations(&second).unwrap();
    assert_eq!(shape, shape_b);
    let worst = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert!(worst <= 1e-6, "deformations differ by {worst} px");
    let read = |d: &Path| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(d.join("config.json")).unwrap()).unwrap()
    };
    assert_eq!(read(&first)["config"], read(&second)["config"]);
    assert_eq!(read(&second)["config"]["solver"]["params"]["delta"], 0.5);
    assert_eq!(read(&second)["inputs"]["kind"], "demo");
    // A flag given with --config overrides the recorded value.
    let third = dir.join("third");
    deepmorph()
        .args(["morph", "-q", "-K", "2", "--config"])
        .arg(first.join("config.json"))
        .arg("-o")
        .arg(&third)
        .assert()
        .success();
    assert_eq!(read(&third)["config"]["solver"]["steps"], 2);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The defaults `--help` shows are the library's (they are written once, in its `Default`
/// impls), and the enums list their values.
#[test]
fn help_shows_the_librarys_defaults() {
    use deepmorph::EnergyParams;
    use deepmorph::app::config::MorphConfig;
    use deepmorph::model::feature_model::DeepConfig;
    // `-h`: the one-line form, where clap lists an enum's values as `[possible values: …]`.
    let out = deepmorph().args(["morph", "-h"]).output().unwrap();
    let help = String::from_utf8_lossy(&out.stdout)
        .split_whitespace()
        .collect::<Vec<_>>()
        .join(" ");
    let (paper, demo) = (MorphConfig::default(), MorphConfig::demo());
    let (rgb, deep) = (EnergyParams::rgb(), EnergyParams::deep());
    for want in [
        format!(
            "[default: {}; demo: {}]",
            paper.solver.steps, demo.solver.steps
        ),
        format!(
            "[default: {}; demo: {}]",
            paper.solver.levels, demo.solver.levels
        ),
        format!(
            "[default: {}; demo: {}]",
            paper.solver.sweeps, demo.solver.sweeps
        ),
        format!("[default: {}; deep model: {}]", rgb.lambda, deep.lambda),
        format!("[default: {}; deep model: {}]", rgb.mu, deep.mu),
        format!("[default: {}]", rgb.delta),
        format!("[default: {}]", rgb.xi1),
        format!("[default: {}]", rgb.xi2),
        format!("[default: {}]", rgb.sigma),
        format!("[default: {}]", rgb.rho),
        format!("[default: {}]", paper.solver.ipalm.beta),
        format!("[default: {}]", DeepConfig::default().eta),
        format!("[default: {}]", DeepConfig::default().feature_rms),
        format!("[default: {}]", DeepConfig::default().pre_sweeps),
        format!("[default: {}]", paper.solver.tolerance),
        format!(
            "[default: {}]",
            format!("{:?}", paper.solver.ipalm.schedule).to_lowercase()
        ),
        "[possible values: sequential, batched]".to_string(),
        "[possible values: rgb, deep]".to_string(),
        "[possible values: flex, ndarray, wgpu]".to_string(),
    ] {
        assert!(help.contains(&want), "--help lacks `{want}`:\n{help}");
    }
}

/// The backends compiled into this build that can run here, the reference first.
fn compiled_backends() -> Vec<Backend> {
    let reference = common::reference_backend();
    let usable = |&b: &Backend| {
        b != Backend::Wgpu
            || common::wgpu_unavailable()
                .inspect(|why| eprintln!("skipped on wgpu: {why}"))
                .is_none()
    };
    let others = Backend::compiled().into_iter().filter(|&b| b != reference);
    std::iter::once(reference)
        .chain(others.filter(usable))
        .collect()
}

/// Backend parity end to end: the tiny demo (2 levels × 3 sweeps) on every compiled backend
/// ends with the reference backend's energy (1e-4 relative) and deformations (1e-3 px).
/// Float32 rounding differs between backends, and a backtracking decision taken on a
/// near-tie could amplify it; these tolerances leave room for that and still catch a wrong op.
#[test]
fn every_backend_gives_the_same_morph() {
    let dir = scratch("backends");
    let run = |backend: Backend| {
        let out = dir.join(backend.name());
        deepmorph()
            .args(["demo", "--size", "32", "-q", "-o"])
            .arg(&out)
            .args(&TINY[..6])
            .args(["--backend", backend.name()])
            .assert()
            .success();
        let csv = std::fs::read_to_string(out.join("energy.csv")).unwrap();
        let energy = EnergyLog::from_csv(&csv)
            .unwrap()
            .records
            .last()
            .unwrap()
            .energy;
        let (_, phi) = load_deformations(&out).unwrap();
        (energy, phi)
    };
    let backends = compiled_backends();
    if backends.len() < 2 {
        // Nothing to compare against: say so instead of passing as if compared.
        eprintln!(
            "skipped: only {} is compiled and usable here (build with two or more of the \
             features ndarray, flex, wgpu to compare backends)",
            backends[0]
        );
        std::fs::remove_dir_all(&dir).ok();
        return;
    }
    let (e_ref, phi_ref) = run(backends[0]);
    for &backend in &backends[1..] {
        let (e, phi) = run(backend);
        let rel = (e - e_ref).abs() / e_ref;
        assert!(
            rel <= 1e-4,
            "{backend}: E = {e:e}, {} gives {e_ref:e} (relative {rel:.1e})",
            backends[0]
        );
        let worst = phi
            .iter()
            .zip(&phi_ref)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(
            worst <= 1e-3,
            "{backend}: deformations differ from {} by up to {worst:e} px",
            backends[0]
        );
        eprintln!("{backend}: |ΔE|/E = {rel:.1e}, max |Δφ| = {worst:.1e} px");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--backend wgpu` on a machine without a usable driver: one clear line naming what to
/// install, exit status 1, no panic. The machine's drivers are hidden from this one process:
/// every Vulkan driver through the loader's selection filter, and Mesa's GL through a
/// nonexistent EGL vendor file (wgpu falls back to GL when Vulkan has nothing).
#[cfg(all(feature = "wgpu", target_os = "linux"))]
#[test]
fn wgpu_without_a_driver_is_a_clear_error() {
    let dir = scratch("nodriver");
    let err = fails(
        deepmorph()
            .args(["demo", "--size", "32", "-q", "-o"])
            .arg(dir.join("out"))
            .args(&TINY[..6])
            .args(["--backend", "wgpu"])
            .env("VK_LOADER_DRIVERS_SELECT", "no-such-driver*")
            .env("__EGL_VENDOR_LIBRARY_FILENAMES", dir.join("none.json")),
    );
    assert!(
        err.contains("apt-get install mesa-vulkan-drivers libvulkan1"),
        "{err}"
    );
    assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn deep_model_options_are_checked_before_any_work() {
    let dir = scratch("deep-bad");
    let (a, b) = (dir.join("a.png"), dir.join("b.png"));
    write_image(&a, 32, 32, 0.4, 0.4);
    write_image(&b, 32, 32, 0.6, 0.6);
    let junk = dir.join("junk.onnx");
    std::fs::write(&junk, b"not a network").unwrap();
    let run = |extra: &[&str]| {
        let mut cmd = deepmorph();
        cmd.args(["morph", a.to_str().unwrap(), b.to_str().unwrap(), "-o"])
            .arg(dir.join("out"))
            .args(["-K", "3", "--sweeps", "3"])
            .args(extra);
        fails(&mut cmd)
    };
    let msg = run(&["--model", "deep"]);
    assert!(msg.contains("--vgg19 FILE"), "{msg}");
    let msg = run(&["--model", "deep", "--vgg19", "absent.onnx"]);
    assert!(
        msg.contains("absent.onnx") && msg.matches("os error").count() == 1,
        "{msg}"
    );
    let msg = run(&["--model", "deep", "--vgg19", junk.to_str().unwrap()]);
    assert!(
        msg.contains("junk.onnx") && msg.contains("not a readable ONNX model"),
        "{msg}"
    );
    let msg = run(&["--vgg19", junk.to_str().unwrap()]);
    assert!(msg.contains("only by --model deep"), "{msg}");
    let msg = run(&[
        "--model",
        "deep",
        "--vgg19",
        junk.to_str().unwrap(),
        "--levels",
        "6",
    ]);
    assert!(msg.contains("at most 5"), "{msg}");
    let msg = run(&[
        "--model",
        "deep",
        "--vgg19",
        junk.to_str().unwrap(),
        "--size",
        "40x40",
    ]);
    assert!(msg.contains("multiples of 16"), "{msg}");
    // Refused before allocating when the estimate exceeds the limit.
    let msg = run(&["--max-memory", "0.01"]);
    assert!(
        // In MiB below a GiB (issue 43 #18: "0.0 GiB").
        msg.contains("needs about") && msg.contains("--max-memory is 10 MiB"),
        "{msg}"
    );
    let msg = run(&["--max-memory", "-1"]);
    assert!(msg.contains("invalid --max-memory -1"), "{msg}");
    assert!(!dir.join("out").join("frame_00.png").exists());
    std::fs::remove_dir_all(dir).ok();
}

#[test]
fn deep_morph_with_the_stand_in_weights() {
    let Some(vgg19) = common::stand_in_vgg19() else {
        return;
    };
    let dir = scratch("deep");
    let (a, b) = (dir.join("a.png"), dir.join("b.png"));
    write_image(&a, 40, 36, 0.4, 0.4);
    write_image(&b, 40, 36, 0.55, 0.6);
    let out = dir.join("out");
    deepmorph()
        .args(["morph", a.to_str().unwrap(), b.to_str().unwrap(), "-o"])
        .arg(&out)
        .args([
            "-K",
            "3",
            "--levels",
            "2",
            "--sweeps",
            "3",
            "--pre-sweeps",
            "2",
            "-q",
        ])
        .args(["--model", "deep", "--vgg19"])
        .arg(&vgg19)
        .assert()
        .success();
    // 40x36 is brought to multiples of 16: 48x32 (rows x columns), nearest by scale.
    let frame = RgbImage::load(&out.join("frame_00.png")).unwrap();
    assert_eq!((frame.height() % 16, frame.width() % 16), (0, 0));
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
    assert!(config["config"]["deep"]["vgg19"].is_string());
    assert_eq!(config["config"]["solver"]["params"]["lambda"], 0.002);
    assert_eq!(config["config"]["deep"]["feature_rms"], 0.1);
    assert_eq!(config["outcome"]["tap_rms"].as_array().unwrap().len(), 5);
    // Frame 0 is A at the working size (RGB part / eta, not the eta-scaled channels).
    let a_work = RgbImage::load(&a)
        .unwrap()
        .resized(frame.height(), frame.width());
    let err = frame
        .data()
        .iter()
        .zip(a_work.data())
        .fold(0.0f32, |m, (x, y)| m.max((x - y).abs()));
    assert!(err <= 1.0 / 255.0 + 1e-6, "frame 0 differs from A by {err}");
    let log =
        EnergyLog::from_csv(&std::fs::read_to_string(out.join("energy.csv")).unwrap()).unwrap();
    assert_eq!(log.records.len(), 2 * 4);
    // The path in VGG19 feature space, measured at the end of a deep morph, and by eval.
    let metrics: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("metrics.json")).unwrap()).unwrap();
    let adjacent = metrics["feature_path"]["morph"]["adjacent"]
        .as_array()
        .unwrap();
    assert_eq!(adjacent.len(), 3);
    assert!(adjacent.iter().all(|d| d.as_f64().unwrap() > 0.0));
    let eval = deepmorph()
        .args([
            "eval",
            out.to_str().unwrap(),
            "--backend",
            "flex",
            "--vgg19",
        ])
        .arg(&vgg19)
        .assert()
        .success();
    let printed = String::from_utf8_lossy(&eval.get_output().stdout).to_string();
    let length = metrics["feature_path"]["morph"]["length"].as_f64().unwrap();
    assert!(
        printed.contains(&format!("path in VGG19 feature space: length {length:.4}")),
        "{printed}"
    );
    std::fs::remove_dir_all(dir).ok();
}

/// `--video`, `--fps` and `--crf`: only the chosen animations are written; the MP4 holds
/// one H.264 sample per frame, each lasting 1/fps; where `ffprobe` is installed (CI installs
/// it: `DEEPMORPH_REQUIRE_FFPROBE=1`), an independent decoder agrees.
#[test]
fn video_formats_rate_and_quality() {
    let dir = scratch("video");
    let out = dir.join("out");
    deepmorph()
        .args(["demo", "--size", "32", "-q", "--frames", "10"])
        .args(["--video", "mp4,apng", "--fps", "8", "--crf", "30", "-o"])
        .arg(&out)
        .args(TINY)
        .assert()
        .success();
    assert!(out.join("morph.apng").is_file() && !out.join("morph.gif").exists());
    let bytes = std::fs::read(out.join("morph.mp4")).unwrap();
    let mp4 = deepmorph::io::mp4::inspect(&bytes).unwrap();
    assert_eq!((mp4.width, mp4.height), (32, 32));
    assert_eq!(mp4.samples.len(), 10);
    assert!(mp4.durations.iter().all(|&d| d * 8 == mp4.timescale));
    assert_eq!(mp4.sync.first(), Some(&1));
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
    assert_eq!(
        config["config"]["video"],
        serde_json::json!(["mp4", "apng"])
    );
    assert_eq!(config["config"]["crf"], 30);

    let ffprobe = std::process::Command::new("ffprobe")
        .args(["-v", "error", "-count_frames", "-select_streams", "v:0"])
        .args([
            "-show_entries",
            "stream=codec_name,pix_fmt,width,height,nb_read_frames",
        ])
        .args(["-of", "default=noprint_wrappers=1"])
        .arg(out.join("morph.mp4"))
        .output();
    match ffprobe {
        Ok(probe) if probe.status.success() => {
            let text = String::from_utf8_lossy(&probe.stdout);
            for line in [
                "codec_name=h264",
                "pix_fmt=yuv420p",
                "width=32",
                "height=32",
                "nb_read_frames=10",
            ] {
                assert!(text.lines().any(|l| l == line), "ffprobe: {text}");
            }
        }
        other => {
            assert!(
                std::env::var_os("DEEPMORPH_REQUIRE_FFPROBE").is_none(),
                "ffprobe is required here: {other:?}"
            );
            eprintln!("ffprobe not available ({other:?}): checked by deepmorph's own reader only");
        }
    }

    for (flags, word) in [
        (["--fps", "0"], "fps"),
        (["--crf", "52"], "crf"),
        (["--video", "avi"], "avi"),
    ] {
        let err = fails(
            deepmorph()
                .args(["demo", "--size", "32", "-q"])
                .args(flags)
                .arg("-o")
                .arg(dir.join("refused"))
                .args(TINY),
        );
        assert!(err.contains(word), "{err}");
        assert!(!dir.join("refused").exists());
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--quality` sets its preset's levels, sweeps and tolerance; flags beside it win.
#[test]
fn quality_presets_and_the_flags_that_override_them() {
    let dir = scratch("quality");
    let out = dir.join("out");
    let run = deepmorph()
        .args([
            "demo",
            "--size",
            "32",
            "--quality",
            "draft",
            "--video",
            "gif",
        ])
        .args(["-K", "2", "--sweeps", "2", "--backend", "flex", "-o"])
        .arg(&out)
        .assert()
        .success();
    // The time estimate comes before the run (with the sweeps it assumes: draft has a
    // tolerance that may stop levels sooner).
    let stderr = String::from_utf8_lossy(&run.get_output().stderr).to_string();
    assert!(
        stderr.contains("estimated time: about") && stderr.contains("all its 2 sweeps"),
        "{stderr}"
    );
    let config: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
    let solver = &config["config"]["solver"];
    assert_eq!(
        (solver["levels"].as_u64(), solver["sweeps"].as_u64()),
        (Some(3), Some(2))
    );
    assert_eq!(solver["tolerance"].as_f64(), Some(1e-3));
    // The record keeps the estimate level by level beside what each level took.
    let outcome = &config["outcome"];
    let predicted = outcome["estimate"]["joint_sweep_seconds"]
        .as_array()
        .unwrap();
    let levels = outcome["levels"].as_array().unwrap();
    assert_eq!((predicted.len(), levels.len()), (3, 3));
    for (p, level) in predicted.iter().zip(levels) {
        assert!(p.as_f64().unwrap() > 0.0, "{outcome}");
        assert!(level["seconds"].as_f64().unwrap() > 0.0, "{outcome}");
    }
    assert_eq!(config["working_size"], serde_json::json!([32, 32]));
    assert!(out.join("morph.gif").is_file() && !out.join("morph.mp4").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `morph A B C`: one morph per consecutive pair in `segment_NN/`, at the first image's
/// working size, and one animation of the whole chain whose joints are the shared images.
#[test]
fn a_chain_of_three_images() {
    let dir = scratch("chain");
    let images: Vec<PathBuf> = (0..3).map(|i| dir.join(format!("{i}.png"))).collect();
    write_image(&images[0], 32, 32, 0.4, 0.35);
    write_image(&images[1], 48, 48, 0.5, 0.5);
    write_image(&images[2], 32, 32, 0.6, 0.65);
    let out = dir.join("out");
    let run = |force: bool| {
        let mut cmd = deepmorph();
        cmd.arg("morph")
            .args(&images)
            .args(["--video", "apng", "-q", "-o"])
            .arg(&out)
            .args(TINY);
        if force {
            cmd.arg("--force");
        }
        cmd
    };
    run(false).assert().success();
    for segment in ["segment_01", "segment_02"] {
        for name in deepmorph::io::outputs::output_names(3) {
            if !name.starts_with("morph.") || name == "morph.apng" {
                assert!(out.join(segment).join(&name).is_file(), "{segment}/{name}");
            }
        }
    }
    let frame = |segment: &str, k: usize| {
        RgbImage::load(&out.join(segment).join(format!("frame_0{k}.png")))
            .unwrap()
            .to_rgb8()
            .into_raw()
    };
    // The joint: segment 1 ends and segment 2 starts on the middle image, at 32x32.
    assert_eq!(frame("segment_01", 3), frame("segment_02", 0));
    assert_eq!(frame("segment_01", 3).len(), 3 * 32 * 32);
    let played = apng_frames(&out.join("morph.apng"));
    assert_eq!(played.len(), 7);
    assert_eq!(played[3], frame("segment_01", 3));
    assert_eq!(played[6], frame("segment_02", 3));
    assert!(!out.join("morph.gif").exists());

    // A chain's folder is replaced with --force, and never when it holds a foreign file.
    fails(&mut run(false));
    run(true).assert().success();
    std::fs::write(out.join("segment_01").join("notes.txt"), "mine").unwrap();
    let err = fails(&mut run(true));
    assert!(err.contains("segment_01"), "{err}");
    assert!(out.join("segment_01").join("notes.txt").is_file());

    let err = fails(
        deepmorph()
            .args(["morph", images[0].to_str().unwrap(), "-o"])
            .arg(dir.join("one")),
    );
    assert!(err.contains("two images"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--init DRAFT`: a morph refined from a finished draft skips the levels up to the draft's
/// size and starts from the draft's path prolongated, whose energy is below the cross-fade
/// start of a fresh run; a draft of another `K` is refused before any work.
#[test]
fn refining_a_draft() {
    let dir = scratch("init");
    let run = |size: &str, args: &[&str], out: &Path| {
        deepmorph()
            .args(["demo", "--size", size, "-q", "--backend", "flex", "-o"])
            .arg(out)
            .args(args)
            .assert()
            .success();
        let log = std::fs::read_to_string(out.join("energy.csv")).unwrap();
        let config: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
        (EnergyLog::from_csv(&log).unwrap(), config)
    };
    let draft = dir.join("draft");
    run("32", &["-K", "3", "--levels", "2", "--sweeps", "6"], &draft);
    let init = ["--init", draft.to_str().unwrap()];
    let (refined, config) = run(
        "64",
        &[&["-K", "3", "--levels", "3", "--sweeps", "3"][..], &init].concat(),
        &dir.join("fine"),
    );
    let levels = config["outcome"]["levels"].as_array().unwrap();
    assert_eq!(levels.len(), 1, "{levels:?}");
    assert_eq!(levels[0]["size"], serde_json::json!([64, 64]));
    assert!(config["config"]["init"].is_string());
    let (fresh, _) = run(
        "64",
        &["-K", "3", "--levels", "1", "--sweeps", "1"],
        &dir.join("fresh"),
    );
    let (start, fade) = (refined.records[0].energy, fresh.records[0].energy);
    assert!(
        start < fade,
        "draft start E {start} vs cross-fade start {fade}"
    );

    let err = fails(
        deepmorph()
            .args(["demo", "--size", "64", "-q", "-K", "4", "--init"])
            .arg(&draft)
            .arg("-o")
            .arg(dir.join("refused")),
    );
    assert!(err.contains("K is 3"), "{err}");

    // A draft whose deformations were edited into ones no path can start from (all zero: the
    // border moved; NaN; a step turned inside out) is refused, not silently dropped (issue
    // 43 #13).
    let bytes = std::fs::read(draft.join("deformations.f32")).unwrap();
    let values: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
        .collect();
    let plane = values.len() / 6; // K = 3 steps of 2 planes of 32²
    let mut folded = values.clone();
    for (i, v) in folded[..2 * plane].iter_mut().enumerate() {
        // Step 1 mirrored inside its border: φ(x) = 31 − x off the border rows/columns.
        let (r, c) = ((i % plane) / 32, (i % plane) % 32);
        if (1..31).contains(&r) && (1..31).contains(&c) {
            *v = 31.0 - *v;
        }
    }
    let edits: [(&str, Vec<f32>); 3] = [
        ("zero", vec![0.0; values.len()]),
        ("nan", vec![f32::NAN; values.len()]),
        ("folded", folded),
    ];
    for (name, edited) in edits {
        let bad = dir.join(format!("draft_{name}"));
        std::fs::create_dir(&bad).unwrap();
        for entry in std::fs::read_dir(&draft).unwrap() {
            let entry = entry.unwrap();
            std::fs::copy(entry.path(), bad.join(entry.file_name())).unwrap();
        }
        let raw: Vec<u8> = edited.iter().flat_map(|v| v.to_le_bytes()).collect();
        std::fs::write(bad.join("deformations.f32"), raw).unwrap();
        let out = dir.join(format!("from_{name}"));
        let err = fails(
            deepmorph()
                .args(["demo", "--size", "64", "-q", "-K", "3", "--levels", "3"])
                .args(["--sweeps", "1", "--backend", "flex", "--init"])
                .arg(&bad)
                .arg("-o")
                .arg(&out),
        );
        assert!(
            err.contains("not admissible") || err.contains("is NaN"),
            "{name}: {err}"
        );
        assert_eq!(err.trim().lines().count(), 1, "{name}: one line: {err}");
        assert!(!out.exists(), "{name}: nothing written");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The flags of the `--resume` tests' morph: 32², K 3, 3 levels × 4 sweeps, on flex.
const RESUMED: [&str; 15] = [
    "demo",
    "--size",
    "32",
    "-q",
    "-K",
    "3",
    "--levels",
    "3",
    "--sweeps",
    "4",
    "--tol",
    "0",
    "--backend",
    "flex",
    "-o",
];

/// Runs [`RESUMED`] into `whole`, then into `part` interrupted by the test hook
/// `DEEPMORPH_INTERRUPT_AT=at` (exit 130, a checkpoint left).
fn interrupted_and_whole(whole: &Path, part: &Path, at: &str) {
    deepmorph().args(RESUMED).arg(whole).assert().success();
    deepmorph()
        .env("DEEPMORPH_INTERRUPT_AT", at)
        .args(RESUMED)
        .arg(part)
        .assert()
        .code(130);
    assert!(part.join("checkpoint.json").is_file() && part.join("checkpoint.f32").is_file());
}

/// Resumes `part`, checks that its first sweep run is `first` (a line of `-v`), and that it
/// ends with the deformations, energies and level record of the uninterrupted run `whole`
/// (flex is deterministic here), its checkpoint gone.
fn resumes_as_uninterrupted(part: &Path, whole: &Path, first: &str) {
    let resumed_run = deepmorph()
        .args(["morph", "-v", "--resume"])
        .arg(part)
        .assert()
        .success();
    // It continued: nothing before `first` was run again.
    let log = String::from_utf8_lossy(&resumed_run.get_output().stderr).to_string();
    let sweeps: Vec<&str> = log.lines().filter(|l| l.contains(" sweep ")).collect();
    assert!(sweeps[0].starts_with(first), "{sweeps:?}");
    assert!(!part.join("checkpoint.json").exists());
    let (shape, resumed) = load_deformations(part).unwrap();
    let (_, uninterrupted) = load_deformations(whole).unwrap();
    assert_eq!(shape, [3, 2, 32, 32]);
    let diff = resumed
        .iter()
        .zip(&uninterrupted)
        .fold(0.0f32, |m, (a, b)| m.max((a - b).abs()));
    assert!(diff <= 1e-5, "resumed deformations differ by {diff} px");
    let log = |d: &Path| {
        EnergyLog::from_csv(&std::fs::read_to_string(d.join("energy.csv")).unwrap())
            .unwrap()
            .records
            .iter()
            .map(|r| (r.level, r.sweep, r.energy))
            .collect::<Vec<_>>()
    };
    let (a, b) = (log(part), log(whole));
    assert_eq!(a.len(), b.len());
    for ((la, sa, ea), (lb, sb, eb)) in a.iter().zip(&b) {
        assert_eq!((la, sa), (lb, sb));
        assert!(
            (ea - eb).abs() <= 1e-6 * eb.abs(),
            "level {la} sweep {sa}: {ea} vs {eb}"
        );
    }
    let record = |d: &Path| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(d.join("config.json")).unwrap()).unwrap()
    };
    // What each level did, not how long it took.
    let levels = |d: &Path| -> Vec<serde_json::Value> {
        let record = record(d);
        let mut levels = record["outcome"]["levels"].as_array().unwrap().clone();
        for level in &mut levels {
            level.as_object_mut().unwrap().remove("seconds");
        }
        levels
    };
    assert_eq!(levels(part), levels(whole));
    assert_eq!(record(part)["outcome"]["termination"], "completed");
}

/// `--resume`: a morph interrupted after joint sweep 2 of level 1 (of 3) leaves a checkpoint
/// beside its outputs; resumed, it ends as the uninterrupted run, and the checkpoint is gone.
#[test]
fn an_interrupted_morph_resumes_where_it_stopped() {
    let dir = scratch("resume");
    let (whole, part) = (dir.join("whole"), dir.join("part"));
    interrupted_and_whole(&whole, &part, "1:2");
    // Settings that change the plan are refused, the checkpoint kept (issue 43 #3).
    for flags in [&["-K", "5"][..], &["--sweeps", "10"], &["--size", "48x48"]] {
        let err = fails(
            deepmorph()
                .args(["morph", "--resume"])
                .arg(&part)
                .args(flags),
        );
        assert!(err.contains("--resume continues"), "{flags:?}: {err}");
        assert!(part.join("checkpoint.json").is_file(), "{flags:?}");
    }
    resumes_as_uninterrupted(&part, &whole, "level 1 (16x16) sweep    3/4");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// An interrupt within a sweep (issue 43 #10: a signal is acted on after the step running,
/// not the sweep of `K` steps): stopped after 3 of the 5 blocks of level 1's joint sweep 3,
/// the checkpoint records those blocks, and the resumed morph finishes that sweep and ends
/// as the uninterrupted one.
#[test]
fn an_interrupt_within_a_sweep_resumes_exactly() {
    let dir = scratch("resume_within");
    let (whole, part) = (dir.join("whole"), dir.join("part"));
    interrupted_and_whole(&whole, &part, "1:2:3");
    let header: serde_json::Value =
        serde_json::from_slice(&std::fs::read(part.join("checkpoint.json")).unwrap()).unwrap();
    assert_eq!(header["sweeps"], 2, "{header}");
    assert_eq!(header["partial"]["blocks"], 3, "{header}");
    // φ_1, φ_2 and f_1 ran: two deformation steps and one feature step recorded.
    assert_eq!(
        header["partial"]["deformation"].as_array().unwrap().len(),
        2
    );
    assert_eq!(header["partial"]["features"].as_array().unwrap().len(), 1);
    resumes_as_uninterrupted(&part, &whole, "level 1 (16x16) sweep    3/4");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// The landmark residual `|Φ(p) − q|` (`[row, col]`) of the morph in `out`, from its
/// deformations.
fn landmark_residual(out: &Path, p: [f64; 2], q: [f64; 2]) -> f64 {
    let device = Backend::Flex.device_for(deepmorph::Precision::F32).unwrap();
    let folder = deepmorph::eval::folder::MorphFolder::read(out, &device).unwrap();
    let (h, w) = (folder.grid.height(), folder.grid.width());
    let phi = common::values(folder.composed());
    deepmorph::eval::metrics::LandmarkResiduals::of(&phi, (h, w), &[(p, q)]).max
}

/// SPEC §11 from the command line: on a pair whose spots sit a third of the image apart,
/// plain metamorphosis leaves the spot's centre where it was (a cross-fade); one landmark
/// pair on it (`--points`, CSV or JSON, in each image's own pixels: B is twice the size of
/// A here, so its point maps by pixel centres) is met to within a working pixel, and the run
/// reports it (`metrics.json`, `config.json`, `energy.csv`'s `E_lm`).
#[test]
fn points_steer_the_morph_and_are_reported() {
    let dir = scratch("points");
    let (a, b) = (dir.join("a.png"), dir.join("b.png"));
    write_image(&a, 32, 32, 0.3, 0.28);
    write_image(&b, 64, 64, 0.68, 0.7);
    // Working grid 32²: A's spot at (9.6, 8.96), B's at row 43.52, column 44.8 of 64, i.e.
    // (43.52 + ½)/2 − ½ = 21.51 and (44.8 + ½)/2 − ½ = 22.15 of 32.
    let (p, q) = ([9.6, 8.96], [21.51, 22.15]);
    let csv = dir.join("points.csv");
    std::fs::write(&csv, "x_a,y_a,x_b,y_b\n8.96,9.6,44.8,43.52\n").unwrap();
    let json = dir.join("points.json");
    std::fs::write(&json, r#"[{"a": [8.96, 9.6], "b": [44.8, 43.52]}]"#).unwrap();
    let run = |out: &Path, extra: &[&std::ffi::OsStr]| {
        deepmorph()
            .arg("morph")
            .args([&a, &b])
            .arg("-o")
            .arg(out)
            .args(["-q", "-K", "4", "--levels", "3", "--sweeps", "60"])
            .args(["--size", "32x32", "--backend", "flex", "--video", "gif"])
            .args(extra)
            .assert()
            .success();
    };
    let plain = dir.join("plain");
    run(&plain, &[]);
    let missed = landmark_residual(&plain, p, q);
    assert!(
        missed > 8.0,
        "plain metamorphosis met the landmark: {missed} px"
    );

    for (name, file) in [("csv", &csv), ("json", &json)] {
        let out = dir.join(name);
        run(&out, &["--points".as_ref(), file.as_os_str()]);
        let met = landmark_residual(&out, p, q);
        assert!(met < 1.0, "{name}: |Φ(p) − q| = {met} px");
        let metrics: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("metrics.json")).unwrap()).unwrap();
        let reported = metrics["landmarks"]["max"].as_f64().unwrap();
        assert!((reported - met).abs() < 1e-6, "{reported} against {met}");
        let config: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("config.json")).unwrap()).unwrap();
        assert_eq!(config["config"]["points"][0]["b"][0], 44.8);
        let working = config["landmarks"][0]["b"].as_array().unwrap();
        assert!(
            (working[1].as_f64().unwrap() - q[0]).abs() < 1e-12,
            "{working:?}"
        );
        let log = EnergyLog::read(&out.join("energy.csv")).unwrap();
        let last = log.records.last().unwrap();
        assert!(
            last.landmarks > 0.0 && last.landmarks < last.energy,
            "{last:?}"
        );
        assert!(
            (last.regularizer + last.data + last.landmarks - last.energy).abs()
                <= 1e-6 * last.energy
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// Every kind of bad points file or point is refused before any work, in one line naming
/// what is wrong.
#[test]
fn bad_points_fail_with_a_clear_message() {
    let dir = scratch("bad_points");
    let (a, b, c) = (dir.join("a.png"), dir.join("b.png"), dir.join("c.png"));
    for image in [&a, &b, &c] {
        write_image(image, 16, 16, 0.5, 0.5);
    }
    let out = dir.join("out");
    let refused = |content: Option<&str>, expected: &str| {
        let file = dir.join("points.csv");
        match content {
            Some(text) => std::fs::write(&file, text).unwrap(),
            None => {
                let _ = std::fs::remove_file(&file);
            }
        }
        let err = fails(
            deepmorph()
                .arg("morph")
                .args([&a, &b])
                .arg("-o")
                .arg(&out)
                .arg("--points")
                .arg(&file)
                .args(TINY),
        );
        assert!(err.contains(expected), "{expected}: {err}");
        assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
        assert!(!out.exists(), "nothing written");
    };
    refused(None, "points.csv");
    refused(Some("x,y,u,v\n1,2,3,4\n"), "x_a,y_a,x_b,y_b");
    refused(Some("x_a,y_a,x_b,y_b\n"), "at least 1");
    refused(Some("x_a,y_a,x_b,y_b\n5,5,6\n"), "line 2: 3 values");
    refused(Some("x_a,y_a,x_b,y_b\n5,5,NaN,6\n"), "finite");
    refused(Some("x_a,y_a,x_b,y_b\n5,5,16,6\n"), "x in [0, 15]");
    refused(Some("x_a,y_a,x_b,y_b\n5,5,0.5,6\n"), "one pixel inside");
    refused(
        Some("x_a,y_a,x_b,y_b\n5,5,6,6\n5,5,7,7\n"),
        "points 1 and 2 of A",
    );
    // A chain needs the segment of every pair: a column, or one file per segment.
    let file = dir.join("points.csv");
    let chain = |files: &[&Path], expected: &str| {
        let mut command = deepmorph();
        command.arg("morph").args([&a, &b, &c]).arg("-o").arg(&out);
        for f in files {
            command.arg("--points").arg(f);
        }
        let err = fails(command.args(TINY));
        assert!(err.contains(expected), "{expected}: {err}");
        assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
        assert!(!out.exists(), "nothing written");
    };
    std::fs::write(&file, "x_a,y_a,x_b,y_b\n5,5,6,6\n").unwrap();
    chain(&[&file], "names no segment");
    chain(&[&file, &file, &file], "3 --points files for 3 images");
    std::fs::write(&file, "segment,x_a,y_a,x_b,y_b\n3,5,5,6,6\n").unwrap();
    chain(&[&file], "segment 3");
    chain(&[&file, &file], "takes no segment column");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A path that is not UTF-8 cannot be recorded in `config.json`: refused before any work,
/// in one line, instead of failing after the solve.
#[cfg(unix)]
#[test]
fn a_path_that_is_not_utf8_is_refused_before_any_work() {
    use std::os::unix::ffi::OsStrExt;
    let dir = scratch("not_utf8");
    let a = dir.join(std::ffi::OsStr::from_bytes(b"bad\xff.png"));
    let b = dir.join("b.png");
    write_image(&a, 16, 16, 0.5, 0.4);
    write_image(&b, 16, 16, 0.5, 0.6);
    let out = dir.join("out");
    let err = fails(
        deepmorph()
            .arg("morph")
            .arg(&a)
            .arg(&b)
            .arg("-o")
            .arg(&out)
            .args(TINY),
    );
    assert!(err.contains("UTF-8"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
    assert!(!out.exists());
    std::fs::remove_dir_all(&dir).unwrap();
}

/// SPEC §11's `--align` from the command line: from the images, the estimated map takes A's
/// spot onto B's (it is printed and recorded in `config.json`) and the morph ends with the
/// spot far nearer B's than plain metamorphosis leaves it (not on it: for so small a spot
/// the cross-fade has the lower energy, and the path drifts back towards it; solver.rs
/// `an_aligned_start_carries_the_blob`; `eval --points` measures that on the plain run);
/// from the landmarks, the least-squares map;
/// every combination that cannot work is refused in one line before any work.
#[test]
fn align_estimates_the_map_records_it_and_carries_the_spot() {
    let dir = scratch("align");
    let (a, b, c) = (dir.join("a.png"), dir.join("b.png"), dir.join("c.png"));
    write_image(&a, 48, 48, 0.3, 0.28);
    write_image(&b, 48, 48, 0.62, 0.64);
    write_image(&c, 48, 48, 0.5, 0.5);
    // The spots' centres in working pixels (row, col): 0.3·48 = 14.4 and so on.
    let (p, q) = ([14.4, 13.44], [29.76, 30.72]);
    let run = |out: &Path, extra: &[&str]| {
        let output = deepmorph()
            .arg("morph")
            .args([&a, &b])
            .arg("-o")
            .arg(out)
            .args(["-K", "4", "--levels", "2", "--sweeps", "40"])
            .args(["--size", "48x48", "--backend", "flex", "--video", "gif"])
            .args(extra)
            .assert()
            .success();
        String::from_utf8_lossy(&output.get_output().stderr).into_owned()
    };
    let aligned = dir.join("aligned");
    let stderr = run(&aligned, &["--align", "similarity"]);
    assert!(
        stderr.contains("initial alignment (similarity, from the images)"),
        "{stderr}"
    );
    let record: serde_json::Value =
        serde_json::from_slice(&std::fs::read(aligned.join("config.json")).unwrap()).unwrap();
    assert_eq!(record["config"]["align"], "similarity");
    assert_eq!(record["alignment"]["source"], "images");
    let m: Vec<Vec<f64>> = serde_json::from_value(record["alignment"]["matrix"].clone()).unwrap();
    // x' = m00 x + m01 y + m02, y' = m10 x + m11 y + m12 on (x, y) = (col, row).
    let (x, y) = (p[1], p[0]);
    let moved = [
        m[1][0] * x + m[1][1] * y + m[1][2],
        m[0][0] * x + m[0][1] * y + m[0][2],
    ];
    let miss = (moved[0] - q[0]).hypot(moved[1] - q[1]);
    assert!(miss < 1.5, "G(p) = {moved:?}, B's spot at {q:?}");
    let plain = dir.join("plain");
    run(&plain, &[]);
    let (carried, faded) = (
        landmark_residual(&aligned, p, q),
        landmark_residual(&plain, p, q),
    );
    assert!(
        carried < 0.5 * faded,
        "|Φ(p) − q| = {carried} px aligned, {faded} px plain"
    );
    // `eval --points` measures a run made without points.
    let spot = dir.join("spot.csv");
    std::fs::write(
        &spot,
        format!("x_a,y_a,x_b,y_b\n{},{},{},{}\n", p[1], p[0], q[1], q[0]),
    )
    .unwrap();
    deepmorph()
        .arg("eval")
        .arg(&plain)
        .arg("--points")
        .arg(&spot)
        .args(["--write", "-q"])
        .assert()
        .success();
    let metrics: serde_json::Value =
        serde_json::from_slice(&std::fs::read(plain.join("metrics.json")).unwrap()).unwrap();
    let measured = metrics["landmarks"]["max"].as_f64().unwrap();
    assert!(
        (measured - faded).abs() < 1e-6,
        "{measured} against {faded}"
    );

    // From two landmarks placed on a pure shift: that shift, exactly.
    let points = dir.join("points.csv");
    std::fs::write(&points, "x_a,y_a,x_b,y_b\n13,14,30,29\n20,14,37,29\n").unwrap();
    let from_points = dir.join("from_points");
    let points_arg = points.to_str().unwrap();
    let stderr = run(
        &from_points,
        &["--align", "similarity", "--points", points_arg],
    );
    assert!(stderr.contains("from the landmarks"), "{stderr}");
    let record: serde_json::Value =
        serde_json::from_slice(&std::fs::read(from_points.join("config.json")).unwrap()).unwrap();
    let summary = &record["alignment"]["summary"];
    assert!((summary["translation"][0].as_f64().unwrap() - 17.0).abs() < 1e-9);
    assert!((summary["translation"][1].as_f64().unwrap() - 15.0).abs() < 1e-9);
    assert!(summary["rotation_degrees"].as_f64().unwrap().abs() < 1e-9);

    let out = dir.join("refused");
    let refused = |extra: &[&std::ffi::OsStr], images: &[&Path], expected: &str| {
        let err = fails(
            deepmorph()
                .arg("morph")
                .args(images)
                .arg("-o")
                .arg(&out)
                .args(TINY)
                .args(extra),
        );
        assert!(err.contains(expected), "{expected}: {err}");
        assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
        assert!(!out.exists(), "nothing written");
    };
    let os = |s: &'static str| std::ffi::OsStr::new(s);
    let affine_on_points = |expected: &str| {
        refused(
            &[
                os("--align"),
                os("affine"),
                os("--points"),
                points.as_os_str(),
            ],
            &[&a, &b],
            expected,
        );
    };
    affine_on_points("at least 3");
    refused(
        &[
            os("--align"),
            os("similarity"),
            os("--init"),
            plain.as_os_str(),
        ],
        &[&a, &b],
        "--init",
    );
    std::fs::write(
        &points,
        "x_a,y_a,x_b,y_b\n10,10,37,10\n37,10,10,10\n10,37,10,37\n",
    )
    .unwrap();
    affine_on_points("reflect");
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A chain steered by landmarks: one file with a `segment` column, or one file per segment;
/// each segment meets its own pairs to within a working pixel and records only them.
#[test]
fn a_chain_takes_the_points_of_each_segment() {
    let dir = scratch("chain_points");
    let images: Vec<PathBuf> = ["a", "b", "c"]
        .iter()
        .map(|n| dir.join(format!("{n}.png")))
        .collect();
    // Spots at (row, col) 9.6/8.96, 21.44/22.08, 9.6/22.08 of 32.
    write_image(&images[0], 32, 32, 0.3, 0.28);
    write_image(&images[1], 32, 32, 0.67, 0.69);
    write_image(&images[2], 32, 32, 0.3, 0.69);
    let (p, q, r) = ([9.6, 8.96], [21.44, 22.08], [9.6, 22.08]);
    let column = dir.join("points.csv");
    std::fs::write(
        &column,
        format!(
            "segment,x_a,y_a,x_b,y_b\n2,{},{},{},{}\n1,{},{},{},{}\n",
            q[1], q[0], r[1], r[0], p[1], p[0], q[1], q[0]
        ),
    )
    .unwrap();
    let (first, second) = (dir.join("first.csv"), dir.join("second.csv"));
    let csv = |from: [f64; 2], to: [f64; 2]| {
        format!(
            "x_a,y_a,x_b,y_b\n{},{},{},{}\n",
            from[1], from[0], to[1], to[0]
        )
    };
    std::fs::write(&first, csv(p, q)).unwrap();
    std::fs::write(&second, csv(q, r)).unwrap();
    for (name, files) in [("column", vec![&column]), ("files", vec![&first, &second])] {
        let out = dir.join(name);
        let mut command = deepmorph();
        command.arg("morph").args(&images).arg("-o").arg(&out);
        for f in files {
            command.arg("--points").arg(f);
        }
        command
            .args(["-q", "-K", "4", "--levels", "3", "--sweeps", "60"])
            .args(["--size", "32x32", "--backend", "flex", "--video", "gif"])
            .assert()
            .success();
        for (segment, (from, to)) in [(1, (p, q)), (2, (q, r))] {
            let folder = out.join(format!("segment_0{segment}"));
            let met = landmark_residual(&folder, from, to);
            assert!(
                met < 1.0,
                "{name}, segment {segment}: |Φ(p) − q| = {met} px"
            );
            let record: serde_json::Value =
                serde_json::from_slice(&std::fs::read(folder.join("config.json")).unwrap())
                    .unwrap();
            let pairs = record["config"]["points"].as_array().unwrap();
            assert_eq!(pairs.len(), 1, "{name}, segment {segment}: {pairs:?}");
            assert_eq!(pairs[0]["a"][1].as_f64().unwrap(), from[0]);
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `--resume` after an input changed is refused (the checkpoint records a digest of the
/// inputs at the working size), the checkpoint kept; with the input restored it resumes
/// (issue 43 #2: it continued the old path with the new image).
#[test]
fn a_checkpoint_is_not_resumed_with_other_inputs() {
    let dir = scratch("resume_inputs");
    let (a, b) = (dir.join("a.png"), dir.join("b.png"));
    write_image(&a, 32, 32, 0.4, 0.4);
    write_image(&b, 32, 32, 0.6, 0.6);
    let part = dir.join("part");
    deepmorph()
        .env("DEEPMORPH_INTERRUPT_AT", "1:2")
        .arg("morph")
        .args([&a, &b])
        .args([
            "-q", "-K", "3", "--levels", "2", "--sweeps", "4", "--tol", "0",
        ])
        .args(["--backend", "flex", "--video", "gif", "-o"])
        .arg(&part)
        .assert()
        .code(130);
    let original = std::fs::read(&a).unwrap();
    write_image(&a, 32, 32, 0.45, 0.4);
    let err = fails(deepmorph().args(["morph", "-q", "--resume"]).arg(&part));
    assert!(err.contains("an input changed"), "{err}");
    assert_eq!(err.trim().lines().count(), 1, "one line: {err}");
    assert!(part.join("checkpoint.json").is_file());
    std::fs::write(&a, original).unwrap();
    deepmorph()
        .args(["morph", "-q", "--resume"])
        .arg(&part)
        .assert()
        .success();
    assert!(!part.join("checkpoint.json").exists());
    std::fs::remove_dir_all(&dir).unwrap();
}
