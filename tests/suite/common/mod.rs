//! Shared test support: golden vectors, tensor conversion, tolerant comparison, and the
//! macro that runs one test body on every compiled backend.
#![allow(dead_code)] // each test binary uses a different subset

use std::collections::HashMap;
use std::path::PathBuf;

use burn::tensor::{DType, Device, Tensor, TensorData};
use deepmorph::{Backend, Grid, Precision};
use serde::Deserialize;

/// Runs the listed test bodies (`fn(Backend)`) once per compiled backend, as
/// `flex::name`, `ndarray::name`, `wgpu::name`. `cargo test wgpu::` selects one backend.
#[macro_export]
macro_rules! on_each_backend {
    ($($name:ident),* $(,)?) => {
        $crate::on_each_cpu_backend!($($name),*);
        #[cfg(feature = "wgpu")]
        mod wgpu {
            $(
                #[test]
                fn $name() {
                    let _alone = $crate::common::wgpu_alone();
                    match $crate::common::wgpu_unavailable() {
                        None => super::$name(deepmorph::Backend::Wgpu),
                        Some(why) => eprintln!("skipped on wgpu: {why}"),
                    }
                }
            )*
        }
    };
}

/// Holds the wgpu tests to one at a time (CPU tests still run beside them). CubeCL's
/// client spins while the device queue is full (half the samples of a profile of two wgpu
/// solver tests were that spin); two of them on a 2-core machine leave lavapipe's own
/// threads little to run on.
pub fn wgpu_alone() -> std::sync::MutexGuard<'static, ()> {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    LOCK.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Why the wgpu tests cannot run on this machine (no Vulkan/Metal/DX12 driver), or `None`
/// when they can. A user's `cargo test --features ndarray,flex,wgpu` then skips them with
/// that reason printed; CI sets `DEEPMORPH_REQUIRE_WGPU=1`, which turns a missing driver into
/// a failure, so the parity suite can never be skipped there unnoticed.
pub fn wgpu_unavailable() -> Option<String> {
    static WHY: std::sync::OnceLock<Option<String>> = std::sync::OnceLock::new();
    WHY.get_or_init(|| match Backend::Wgpu.device() {
        Ok(_) => None,
        Err(e) if std::env::var_os("DEEPMORPH_REQUIRE_WGPU").is_some() => {
            panic!("DEEPMORPH_REQUIRE_WGPU is set, but {e}")
        }
        Err(e) => Some(e.to_string()),
    })
    .clone()
}

/// Like [`on_each_backend`] for float64 tests: CPU backends only (wgpu has no float64).
#[macro_export]
macro_rules! on_each_cpu_backend {
    ($($name:ident),* $(,)?) => {
        #[cfg(feature = "flex")]
        mod flex {
            $( #[test] fn $name() { super::$name(deepmorph::Backend::Flex) } )*
        }
        #[cfg(feature = "ndarray")]
        mod ndarray {
            $( #[test] fn $name() { super::$name(deepmorph::Backend::NdArray) } )*
        }
    };
}

/// One tensor of a golden case: shape and row-major values (`+inf` decoded).
#[derive(Clone, Debug)]
pub struct Array {
    pub shape: Vec<usize>,
    pub data: Vec<f64>,
}

#[derive(Deserialize)]
struct RawArray {
    shape: Vec<usize>,
    data: Vec<serde_json::Value>,
}

impl From<RawArray> for Array {
    fn from(raw: RawArray) -> Self {
        let data = raw
            .data
            .iter()
            .map(|v| match v {
                serde_json::Value::Number(n) => n.as_f64().expect("finite number"),
                serde_json::Value::String(s) if s == "inf" => f64::INFINITY,
                other => panic!("unexpected golden datum {other}"),
            })
            .collect();
        Array {
            shape: raw.shape,
            data,
        }
    }
}

#[derive(Deserialize)]
struct RawCase {
    name: String,
    params: serde_json::Value,
    inputs: HashMap<String, RawArray>,
    outputs: HashMap<String, RawArray>,
}

/// A golden case from `tests/golden/NAME.json`.
pub struct Golden {
    pub name: String,
    pub params: serde_json::Value,
    pub inputs: HashMap<String, Array>,
    pub outputs: HashMap<String, Array>,
}

impl Golden {
    pub fn load(name: &str) -> Self {
        let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("tests/golden")
            .join(format!("{name}.json"));
        let text = std::fs::read_to_string(&path)
            .unwrap_or_else(|e| panic!("reading {}: {e}", path.display()));
        let raw: RawCase = serde_json::from_str(&text).expect("golden JSON");
        Golden {
            name: raw.name,
            params: raw.params,
            inputs: raw.inputs.into_iter().map(|(k, v)| (k, v.into())).collect(),
            outputs: raw
                .outputs
                .into_iter()
                .map(|(k, v)| (k, v.into()))
                .collect(),
        }
    }

    pub fn input(&self, name: &str) -> &Array {
        self.inputs
            .get(name)
            .unwrap_or_else(|| panic!("{}: no input {name}", self.name))
    }

    pub fn output(&self, name: &str) -> &Array {
        self.outputs
            .get(name)
            .unwrap_or_else(|| panic!("{}: no output {name}", self.name))
    }

    pub fn param(&self, name: &str) -> f64 {
        self.params[name]
            .as_f64()
            .unwrap_or_else(|| panic!("{}: no numeric param {name}", self.name))
    }
}

/// The backend the others are compared with: ndarray (the design card's CPU backend) when
/// compiled, else flex.
pub fn reference_backend() -> Backend {
    if cfg!(feature = "ndarray") {
        Backend::NdArray
    } else {
        Backend::Flex
    }
}

/// The faster CPU backend compiled in (flex's convolutions and kernels beat ndarray's), for
/// tests whose cost is mostly compute.
pub fn fast_cpu_backend() -> Backend {
    if cfg!(feature = "flex") {
        Backend::Flex
    } else {
        reference_backend()
    }
}

/// A fresh, empty scratch directory for one test (`group` and `name` keep tests apart).
pub fn scratch(group: &str, name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("deepmorph-{group}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Runs a command that must fail; returns its stderr.
pub fn fails(cmd: &mut assert_cmd::Command) -> String {
    let out = cmd.output().unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
    assert!(
        !out.status.success(),
        "expected failure, got success; stderr: {stderr}"
    );
    assert!(
        !stderr.contains("panicked"),
        "panic instead of an error: {stderr}"
    );
    stderr
}

/// The device of `backend` in `precision`, with autodiff enabled when asked.
pub fn device(backend: Backend, precision: Precision, autodiff: bool) -> Device {
    let device = backend
        .device_for(precision)
        .unwrap_or_else(|e| panic!("{e}"));
    if autodiff { device.autodiff() } else { device }
}

/// A grid matching the last two dimensions of `shape`.
pub fn grid_for(shape: &[usize], device: &Device, dtype: DType) -> Grid {
    let n = shape.len();
    Grid::new(shape[n - 2], shape[n - 1], device, dtype).expect("grid")
}

/// `array` as a tensor of rank `D`, with leading unit dimensions added as needed
/// (golden single images `[C, H, W]` become batches `[1, C, H, W]`).
pub fn tensor<const D: usize>(array: &Array, device: &Device, dtype: DType) -> Tensor<D> {
    assert!(array.shape.len() <= D, "rank {} > {D}", array.shape.len());
    let mut shape = vec![1; D - array.shape.len()];
    shape.extend(&array.shape);
    Tensor::from_data(TensorData::new(array.data.clone(), shape), (device, dtype))
}

/// The values of a tensor on the host.
pub fn values<const D: usize>(t: Tensor<D>) -> Vec<f64> {
    deepmorph::model::grid::to_host(t)
}

/// Asserts `max|got − want| ≤ rel · max|want| + abs` (SPEC "Golden vectors": relative to the
/// tensor's own largest magnitude). Infinite entries must match exactly.
pub fn assert_close(what: &str, got: &[f64], want: &[f64], rel: f64, abs: f64) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    let scale = want
        .iter()
        .filter(|v| v.is_finite())
        .fold(0.0f64, |m, v| m.max(v.abs()));
    let mut worst = (0.0f64, 0usize);
    for (i, (&g, &w)) in got.iter().zip(want).enumerate() {
        if w.is_infinite() || g.is_infinite() {
            assert_eq!(g, w, "{what}[{i}]: infinite entries must agree");
            continue;
        }
        assert!(g.is_finite(), "{what}[{i}] = {g} is not finite");
        let err = (g - w).abs();
        if err > worst.0 {
            worst = (err, i);
        }
    }
    let bound = rel * scale + abs;
    assert!(
        worst.0 <= bound,
        "{what}: max error {:.3e} at [{}] (got {}, want {}) exceeds {:.3e} = {rel:e}·{scale:.3e} + {abs:e}",
        worst.0,
        worst.1,
        got[worst.1],
        want[worst.1],
        bound
    );
}

/// [`assert_close`] against a golden array with the SPEC's float32 tolerance: 1e-4 relative
/// to the tensor's largest magnitude, plus an absolute floor of 1e-7 that matters only for
/// tensors that are zero up to rounding (e.g. `T[f, Id] − f`).
pub fn assert_golden(what: &str, got: &[f64], want: &Array) {
    assert_close(what, got, &want.data, 1e-4, 1e-7);
}

/// SplitMix64: a tiny, well-mixed generator, so the inputs never depend on a crate version.
pub struct Rng(pub u64);

impl Rng {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in `[−1, 1)`.
    pub fn symmetric(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }

    /// `c` smooth maps in `[0.5 − 0.5, 0.5 + 0.5]`: 9 cosine modes per channel.
    pub fn smooth_image(&mut self, c: usize, h: usize, w: usize) -> Vec<f64> {
        let mut out = Vec::with_capacity(c * h * w);
        for _ in 0..c {
            let modes: Vec<(f64, f64, f64)> = (0..9)
                .map(|m| ((m / 3) as f64, (m % 3) as f64, 0.12 * self.symmetric()))
                .collect();
            let phase = self.symmetric();
            for i in 0..h {
                for j in 0..w {
                    let (x, y) = (i as f64 / (h - 1) as f64, j as f64 / (w - 1) as f64);
                    let v: f64 = modes
                        .iter()
                        .map(|&(p, q, a)| {
                            a * (std::f64::consts::PI * (p * x + q * y) + phase).cos()
                        })
                        .sum();
                    out.push(0.5 + v);
                }
            }
        }
        out
    }

    /// `n` deformations `[n, 2, h, w]` in pixel units: `Id + v` with `v` a sine series that
    /// vanishes on the boundary, `|∂v| ≲ 1.05 · amplitude` (admissible for `amplitude < 0.9`).
    pub fn smooth_deformation(&mut self, n: usize, h: usize, w: usize, amplitude: f64) -> Vec<f64> {
        let mut out = Vec::with_capacity(n * 2 * h * w);
        for _ in 0..n {
            for axis in 0..2 {
                let modes: Vec<(f64, f64, f64)> = (0..4)
                    .map(|m| ((1 + m / 2) as f64, (1 + m % 2) as f64, self.symmetric()))
                    .collect();
                for i in 0..h {
                    for j in 0..w {
                        let (x, y) = (i as f64 / (h - 1) as f64, j as f64 / (w - 1) as f64);
                        let pi = std::f64::consts::PI;
                        // sin(π p) is 1e-16, not 0: the boundary must be Id exactly.
                        let edge = i == 0 || j == 0 || i == h - 1 || j == w - 1;
                        let v: f64 = if edge { 0.0 } else { 1.0 }
                            * modes
                                .iter()
                                .map(|&(p, q, a)| a * (pi * p * x).sin() * (pi * q * y).sin())
                                .sum::<f64>()
                            * amplitude
                            / 2.0;
                        let id = if axis == 0 { i } else { j } as f64;
                        out.push(id + v);
                    }
                }
            }
        }
        out
    }

    /// Anisotropy-like weights in `(0, 1]`.
    pub fn weights(&mut self, n: usize, h: usize, w: usize) -> Vec<f64> {
        self.smooth_image(n, h, w)
            .into_iter()
            .map(|v| v.clamp(0.05, 1.0))
            .collect()
    }
}

/// A file of the team's shared test data (`../shared/data/RELATIVE`), or `None` with the
/// reason printed: a user's fresh clone has no `../shared`. CI sets
/// `DEEPMORPH_REQUIRE_SHARED_DATA=1`, which turns a missing file into a failure, so that a
/// test that needs the data can never pass there without checking anything.
pub fn shared_data(relative: &str) -> Option<PathBuf> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data")
        .join(relative);
    if path.is_file() {
        return Some(path);
    }
    assert!(
        std::env::var_os("DEEPMORPH_REQUIRE_SHARED_DATA").is_none(),
        "DEEPMORPH_REQUIRE_SHARED_DATA is set, but {} is not a file",
        path.display()
    );
    eprintln!(
        "skipped: {} not found (the team's shared test data)",
        path.display()
    );
    None
}

/// The stand-in VGG19 of the team's shared data (`../shared/data/vgg19`), or `None` as
/// [`shared_data`] says.
pub fn stand_in_vgg19() -> Option<PathBuf> {
    shared_data("vgg19/vgg19_hed_stand_in.onnx")
}

/// Deterministic uniform numbers in `[−1, 1)` (xorshift), for known test weights.
pub fn uniform(seed: u64) -> impl FnMut() -> f64 {
    let mut state = seed | 1;
    move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    }
}
