//! Quality metrics end to end: a synthetic pair with a known deformation (`deepmorph warp`),
//! morphed and evaluated (`deepmorph eval --truth`); the endpoint error must be small for
//! the solver's deformations and large for deliberately wrong ones.
//!
//! Needs `../shared/data/images/single/chelsea.png`; skipped with a printed reason without
//! (a failure where `DEEPMORPH_REQUIRE_SHARED_DATA` is set, as in CI).

use std::path::{Path, PathBuf};

use assert_cmd::Command;
use deepmorph::eval::metrics::Metrics;

use crate::common;

use common::fails;

fn scratch(name: &str) -> PathBuf {
    common::scratch("quality", name)
}

fn deepmorph() -> Command {
    Command::cargo_bin("deepmorph").unwrap()
}

fn shared_image(name: &str) -> Option<PathBuf> {
    common::shared_data(&format!("images/single/{name}"))
}

/// `deepmorph eval OUT --truth TRUTH --write`, which must succeed.
fn eval_against(out: &Path, truth: &Path) {
    deepmorph()
        .arg("eval")
        .arg(out)
        .arg("--truth")
        .arg(truth)
        .args(["--backend", "flex", "-q", "--write"])
        .assert()
        .success();
}

fn metrics(dir: &Path) -> Metrics {
    serde_json::from_slice(&std::fs::read(dir.join("metrics.json")).unwrap()).unwrap()
}

#[test]
fn synthetic_pair_is_recovered_and_a_wrong_map_scores_badly() {
    let Some(image) = shared_image("chelsea.png") else {
        return;
    };
    let dir = scratch("synthetic");
    let pair = dir.join("pair");
    // chelsea is 451x300; a swirl of 30 px is ~4.3 px at the 64-pixel working width.
    deepmorph()
        .arg("warp")
        .arg(&image)
        .args(["--field", "smooth", "--amount", "30", "-o"])
        .arg(&pair)
        .assert()
        .success();
    let out = dir.join("morph");
    // δ = 0.1 makes intensity change 10x dearer than at the RGB default δ = 1, where the
    // minimiser of a textured pair is still largely a cross-fade (data share 77 %, EPE
    // 0.88 px at these settings); here it is mostly transport (data share 32 %).
    deepmorph()
        .arg("morph")
        .args([pair.join("a.png"), pair.join("b.png")])
        .args([
            "--max-side",
            "64",
            "-K",
            "4",
            "--levels",
            "3",
            "--sweeps",
            "40",
            "-q",
        ])
        .args(["--delta", "0.1"])
        .args(["--backend", "flex", "-o"])
        .arg(&out)
        .assert()
        .success();
    let at_end = metrics(&out);
    assert!(at_end.endpoint_error.is_none());
    assert_eq!(at_end.composed.folded_share, 0.0);

    eval_against(&out, &pair.join("truth.flo"));
    let m = metrics(&out);
    assert_eq!(
        m.deformations, at_end.deformations,
        "eval and morph disagree"
    );
    assert_eq!(m.path, at_end.path, "eval and morph disagree on the path");
    // Both of those ran the same code on the same files; these are computed here, from the
    // written files alone: det J of each step (SPEC §2, forward differences) and the RMS
    // distances between adjacent 8-bit frames.
    let (shape, phi) = deepmorph::io::outputs::load_deformations(&out).unwrap();
    let [k, _, h, w] = shape;
    for (step, got) in m.deformations.iter().enumerate() {
        let v = |axis: usize, i: usize, j: usize| {
            let id = if axis == 0 { i } else { j } as f64;
            f64::from(phi[((step * 2 + axis) * h + i) * w + j]) - id
        };
        let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
        for i in 0..h {
            for j in 0..w {
                let d0 = |a| {
                    if i + 1 < h {
                        v(a, i + 1, j) - v(a, i, j)
                    } else {
                        0.0
                    }
                };
                let d1 = |a| {
                    if j + 1 < w {
                        v(a, i, j + 1) - v(a, i, j)
                    } else {
                        0.0
                    }
                };
                let det = (1.0 + d0(0)) * (1.0 + d1(1)) - d1(0) * d0(1);
                (lo, hi) = (lo.min(det), hi.max(det));
            }
        }
        assert!(
            (got.min_det - lo).abs() < 1e-4 && (got.max_det - hi).abs() < 1e-4,
            "step {}: eval's det J in [{}, {}], the files' in [{lo}, {hi}]",
            step + 1,
            got.min_det,
            got.max_det
        );
    }
    let frames: Vec<Vec<f64>> = (0..=k)
        .map(|i| {
            let path = out.join(deepmorph::io::outputs::frame_name(i, k));
            let image = image::open(&path).unwrap().to_rgb8();
            image
                .as_raw()
                .iter()
                .map(|&b| f64::from(b) / 255.0)
                .collect()
        })
        .collect();
    for (i, got) in m.path.morph.adjacent.iter().enumerate() {
        let (a, b) = (&frames[i], &frames[i + 1]);
        let want =
            (a.iter().zip(b).map(|(x, y)| (y - x).powi(2)).sum::<f64>() / a.len() as f64).sqrt();
        assert!(
            (got - want).abs() <= 1e-6 * want.max(1e-3),
            "step {}: eval's distance {got}, the frames' {want}",
            i + 1
        );
    }
    // K steps; the cross-fade is the straight line in pixel space, so no path of frames
    // between the same (8-bit) endpoints is shorter, and its steps are even.
    assert_eq!(m.path.morph.adjacent.len(), 4);
    assert!(
        m.path.morph.length >= m.path.crossfade.length * (1.0 - 1e-6),
        "morph {:.5} vs cross-fade {:.5}",
        m.path.morph.length,
        m.path.crossfade.length
    );
    assert!(
        m.path.crossfade.relative_std < 0.05,
        "{:?}",
        m.path.crossfade
    );
    let epe = m.endpoint_error.clone().expect("endpoint error");
    eprintln!("{m}");
    assert_eq!(epe.pixels, 64 * 44);
    assert!(
        epe.identity_mean > 1.2,
        "the truth moves: {}",
        epe.identity_mean
    );
    // Measured: mean 0.39 px, 92 % under 1 px, identity 1.48 px.
    assert!(
        epe.mean < 0.6 && epe.under_1px > 0.8,
        "EPE mean {:.3} px, {:.1} % under 1 px (identity {:.3} px)",
        epe.mean,
        100.0 * epe.under_1px,
        epe.identity_mean
    );

    // The same steps reversed (Id − v instead of Id + v) must score worse than no motion.
    let (shape, phi) = deepmorph::io::outputs::load_deformations(&out).unwrap();
    let [k, _, h, w] = shape;
    let reversed: Vec<u8> = phi
        .iter()
        .enumerate()
        .map(|(p, &value)| {
            let (axis, i, j) = ((p / (h * w)) % 2, (p / w) % h, p % w);
            let id = if axis == 0 { i } else { j } as f32;
            2.0 * id - value
        })
        .flat_map(f32::to_le_bytes)
        .collect();
    assert_eq!(reversed.len(), 4 * k * 2 * h * w);
    std::fs::write(out.join("deformations.f32"), reversed).unwrap();
    eval_against(&out, &pair.join("truth.flo"));
    let wrong = metrics(&out).endpoint_error.unwrap();
    assert!(
        wrong.mean > epe.identity_mean,
        "reversed map EPE {:.3} px should exceed the identity's {:.3} px",
        wrong.mean,
        epe.identity_mean
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn eval_and_warp_reject_bad_input_clearly() {
    let dir = scratch("bad");
    let err = fails(deepmorph().arg("eval").arg(&dir));
    assert!(err.contains("config.json"), "{err}");

    let image = dir.join("img.png");
    image::RgbImage::from_fn(32, 24, |x, y| {
        image::Rgb([(x * 8) as u8, (y * 10) as u8, 90])
    })
    .save(&image)
    .unwrap();
    let warp = |field: &str, amount: &str| {
        fails(
            deepmorph()
                .arg("warp")
                .arg(&image)
                .args(["--field", field, "--amount", amount, "-o"])
                .arg(dir.join("pair")),
        )
    };
    let err = warp("rotate", "170");
    assert!(err.contains("amount = 170"), "{err}");
    let err = warp("rotate", "360");
    assert!(
        err.contains("amount = 360") && err.contains("-180 and 180"),
        "{err}"
    );
    let err = warp("twist", "1");
    assert!(err.contains("twist"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}
