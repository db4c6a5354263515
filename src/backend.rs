//! Backend and device selection: which Burn backends were compiled in (cargo features
//! `flex`, `ndarray`, `wgpu`) and how a choice of one becomes a device.
//!
//! The numerical code names no backend, except the custom ops' kernel files, which hold a
//! kernel per backend (listed in `docs/architecture.md`, "Custom ops"). Burn 0.22 tensors are backend-erased
//! (`Tensor<D>`); the backend is a property of the [`Device`] they live on, and this module
//! is what turns a [`Backend`] choice into such a device.
#![allow(deprecated)] // `Device::ndarray` is deprecated upstream in favour of flex.

use std::fmt;

use burn::tensor::{DType, Device};

use crate::error::{Error, Result};

/// How the cubic B-spline warp is computed: fused, or as composed tensor ops that read the
/// 4 × 4 spline coefficients around each sample point by gathers. All give the same result on
/// every backend (to rounding); they differ in speed:
///
/// - [`Gather::Elements`]: 16 `gather`s of `[N, C, P]` scalars, one thread per output
///   element, and a scatter-add backward. Right for GPUs.
/// - [`Gather::Rows`]: the coefficients laid out channels-last (`[N·H·W, C]`) and one
///   `select` of `16·N·P` whole rows of `C` contiguous values; its backward adds rows
///   (`select_assign`). On a CPU a row is one memory copy, where `gather` pays for an index
///   computation per scalar: 3.2× faster on flex for the deep model's 67 channels
///   (docs/benchmarks.md). Not for wgpu: its `select_assign` runs one thread per channel over all
///   indices, and on lavapipe it lost updates beyond 65,535 indices (BURN-NOTES).
/// - [`Gather::RowsFrom`]`(c)`: rows for `c` channels or more, elements below. On ndarray the
///   row select's fixed cost (the permute to channels-last and the row-wise backward) only
///   pays off for wide tensors: for a warp and its gradient at 128², rows lose 6× for 3
///   channels and win 1.7× for 67.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Gather {
    /// No gathers: the fused spline op, native kernels for the prefilter (a tridiagonal
    /// solve per line) and the evaluation, with a hand-written backward
    /// ([`crate::model::warp::op`]). flex and wgpu.
    Fused,
    /// Scalar gathers, channels-first.
    Elements,
    /// Row selects, channels-last.
    Rows,
    /// Row selects for at least this many channels, scalar gathers below.
    RowsFrom(usize),
}

impl Gather {
    /// Whether `channels` channels are read as rows.
    pub fn reads_rows(self, channels: usize) -> bool {
        match self {
            Gather::Elements | Gather::Fused => false,
            Gather::Rows => true,
            Gather::RowsFrom(min) => channels >= min,
        }
    }
}

/// What the numerical code needs to know about the device it runs on; a
/// [`crate::model::grid::Grid`] carries it, so nothing below this module names a backend.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Capabilities {
    /// Whether the backend computes in float64 (decision sums are accumulated in it).
    pub float64: bool,
    /// How the warp reads spline coefficients fastest.
    pub gather: Gather,
    /// Whether a deformation step's linearisation is reduced over the channels by the fused
    /// host kernel ([`crate::model::slopes`]): flex. The others compose it from tensor ops.
    pub fused_linearisation: bool,
    /// Whether the regulariser's weighted density `a · W(J(φ))` and its gradient are the fused
    /// host kernels of [`crate::model::energy::density_op`]: flex. The others compose them.
    pub fused_density: bool,
    /// Whether the anisotropy's edge weight after its two separable operators is the fused
    /// host kernel of [`crate::model::energy::anisotropy_op`]: flex. The others compose it.
    pub fused_anisotropy: bool,
    /// Whether the fused spline kernels keep many-channel coefficients channels-last and
    /// read them so in place ([`crate::model::warp::op`]): flex. A channel block narrowed
    /// from a frame's coefficients is read in place too.
    pub channels_last_coefficients: bool,
}

impl Capabilities {
    /// The capabilities of the backend `device` belongs to (those of wgpu for a device of no
    /// known CPU backend).
    pub fn of(device: &Device) -> Self {
        match Backend::of(device) {
            Some(backend) => Self {
                float64: backend.supports(Precision::F64),
                gather: backend.warp_gather(),
                fused_linearisation: backend == Backend::Flex,
                fused_density: backend == Backend::Flex,
                fused_anisotropy: backend == Backend::Flex,
                channels_last_coefficients: backend == Backend::Flex,
            },
            None => Self {
                float64: false,
                gather: Gather::Elements,
                fused_linearisation: false,
                fused_density: false,
                fused_anisotropy: false,
                channels_last_coefficients: false,
            },
        }
    }
}

/// A Burn backend this program can run on. Every variant exists in every build, so a
/// request for a backend that was not compiled in is an error with a remedy, not a
/// compile-time hole.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Backend {
    /// Burn's pure-Rust CPU backend (SIMD, rayon, gemm); feature `flex`.
    Flex,
    /// The ndarray CPU backend; feature `ndarray` (deprecated by Burn 0.22).
    #[cfg_attr(feature = "cli", value(name = "ndarray"))]
    NdArray,
    /// wgpu on Vulkan, Metal or DX12 (or lavapipe without a GPU); feature `wgpu`.
    Wgpu,
}

/// Floating-point precision of a computation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Precision {
    /// float32: what the program computes in.
    F32,
    /// float64: for finite-difference gradient checks (CPU backends only).
    F64,
}

impl Precision {
    /// The tensor dtype.
    pub fn dtype(self) -> DType {
        match self {
            Precision::F32 => DType::F32,
            Precision::F64 => DType::F64,
        }
    }
}

impl Backend {
    /// All backends, compiled in or not, in order of preference for the default.
    pub const ALL: [Backend; 3] = [Backend::Flex, Backend::NdArray, Backend::Wgpu];

    /// The name used on the command line and in reports.
    pub fn name(self) -> &'static str {
        match self {
            Backend::Flex => "flex",
            Backend::NdArray => "ndarray",
            Backend::Wgpu => "wgpu",
        }
    }

    /// The cargo feature that compiles this backend in.
    pub fn feature(self) -> &'static str {
        self.name()
    }

    /// Whether this build contains the backend.
    pub fn is_compiled(self) -> bool {
        match self {
            Backend::Flex => cfg!(feature = "flex"),
            Backend::NdArray => cfg!(feature = "ndarray"),
            Backend::Wgpu => cfg!(feature = "wgpu"),
        }
    }

    /// The backends compiled into this build.
    pub fn compiled() -> Vec<Backend> {
        Self::ALL.into_iter().filter(|b| b.is_compiled()).collect()
    }

    /// The default backend: the first compiled one of [`Backend::ALL`]. Flex comes first: it
    /// needs half of ndarray's memory at the deep model's sizes and is maintained upstream,
    /// though ndarray sweeps the RGB model faster today (docs/benchmarks.md).
    pub fn default_compiled() -> Option<Backend> {
        Self::ALL.into_iter().find(|b| b.is_compiled())
    }

    /// The backend a device belongs to, if it is one of this build's.
    pub fn of(device: &Device) -> Option<Backend> {
        // Device equality ignores autodiff: an autodiff device answers for the one it wraps.
        Self::compiled()
            .into_iter()
            .find(|b| b.device_unchecked_cpu().is_some_and(|d| d == *device))
            .or_else(|| cfg!(feature = "wgpu").then_some(Backend::Wgpu))
    }

    /// How the warp is computed on this backend ([`Gather`]): the fused op on flex; rows for
    /// wide tensors only on ndarray, whose channels-last permute and row backward cost more
    /// than scalar gathers save below ~32 channels; scalar gathers on wgpu, whose row
    /// scatter runs one thread per channel.
    pub fn warp_gather(self) -> Gather {
        match self {
            Backend::Flex => Gather::Fused,
            Backend::NdArray => Gather::RowsFrom(32),
            Backend::Wgpu => Gather::Elements,
        }
    }

    /// Whether the fused spline op ([`Gather::Fused`]) has kernels on this backend: native
    /// loops on flex, CubeCL on wgpu; ndarray has none (it keeps the composed ops).
    pub fn has_fused_warp(self) -> bool {
        matches!(self, Backend::Flex | Backend::Wgpu)
    }

    /// The device of a CPU backend, built without probing anything; `None` for wgpu.
    fn device_unchecked_cpu(self) -> Option<Device> {
        match self {
            #[cfg(feature = "flex")]
            Backend::Flex => Some(Device::flex()),
            #[cfg(feature = "ndarray")]
            Backend::NdArray => Some(Device::ndarray()),
            _ => None,
        }
    }

    /// Whether the backend computes in `precision`.
    pub fn supports(self, precision: Precision) -> bool {
        // wgpu has no float64: on lavapipe exp/log/pow in f64 returned garbage silently.
        !(self == Backend::Wgpu && precision == Precision::F64)
    }

    /// The device of this backend (without autodiff).
    pub fn device(self) -> Result<Device> {
        if !self.is_compiled() {
            return Err(Error::BackendNotCompiled {
                backend: self.name(),
                feature: self.feature(),
            });
        }
        self.device_unchecked()
    }

    /// Checks that `precision` is available and returns the device.
    pub fn device_for(self, precision: Precision) -> Result<Device> {
        let device = self.device()?;
        if !self.supports(precision) {
            return Err(Error::UnsupportedPrecision {
                backend: self.name(),
                dtype: "float64",
            });
        }
        Ok(device)
    }

    fn device_unchecked(self) -> Result<Device> {
        match self {
            #[cfg(feature = "flex")]
            Backend::Flex => Ok(Device::flex()),
            #[cfg(feature = "ndarray")]
            Backend::NdArray => Ok(Device::ndarray()),
            #[cfg(feature = "wgpu")]
            Backend::Wgpu => {
                let device = Device::wgpu(Default::default());
                probe_wgpu(&device)?;
                Ok(device)
            }
            #[allow(unreachable_patterns)]
            _ => unreachable!("device() checks is_compiled first"),
        }
    }
}

/// Runs one tiny operation on a fresh wgpu device. Without a usable adapter wgpu panics on
/// the first operation (or, with only a GL driver, on the first atomic add); that becomes
/// [`Error::BackendUnavailable`] here instead of a panic deep in a morph.
#[cfg(feature = "wgpu")]
fn probe_wgpu(device: &Device) -> Result<()> {
    use burn::tensor::Tensor;
    use std::sync::Mutex;

    // The panic hook is process-wide: serialise probes and restore it afterwards.
    static PROBE: Mutex<()> = Mutex::new(());
    let _guard = PROBE.lock().unwrap_or_else(|e| e.into_inner());
    let hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(|_| {}));
    let outcome = std::panic::catch_unwind(|| {
        let x = Tensor::<1>::ones([4], device);
        let idx = Tensor::<1, burn::tensor::Int>::zeros([4], device);
        // A scatter-add: the atomic the warp's backward needs.
        let y =
            Tensor::<1>::zeros([4], device).scatter(0, idx, x, burn::tensor::IndexingUpdateOp::Add);
        y.into_data()
    });
    std::panic::set_hook(hook);
    match outcome {
        Ok(data) if data.try_to_vec_as::<f64>().is_ok_and(|v| v[0] == 4.0) => Ok(()),
        Ok(_) => Err(Error::BackendUnavailable {
            backend: "wgpu",
            detail: "a scatter-add returned a wrong result".into(),
        }),
        Err(payload) => {
            let detail = payload
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_else(|| "no message".into());
            Err(Error::BackendUnavailable {
                backend: "wgpu",
                detail: format!("no usable adapter (wgpu stopped with: {detail})"),
            })
        }
    }
}

/// A rayon pool of one thread per core (the CPU backends' kernels split their work over the
/// pool of the thread that calls them), whose threads have the main thread's stack size:
/// the generated VGG19 code has large frames, and compute subnormal numbers as zero
/// ([`flush_subnormals_on_this_thread`]). `None` if the threads cannot be started.
pub fn solver_pool() -> Option<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .stack_size(8 << 20)
        .start_handler(|_| flush_subnormals_on_this_thread())
        .build()
        .ok()
}

/// Makes the calling thread's float arithmetic treat subnormal numbers (below 1.2e-38 in
/// float32) as zero, on input and on output (x86-64's MXCSR bits DAZ and FTZ; elsewhere
/// nothing). Intel cores take a microcode assist for each operation that meets one (a probe
/// with 30 % subnormal coefficients evaluated 18× slower), and the deep model makes them:
/// ReLU features are runs of exact zeros, and every decay towards such a run (the
/// prefilter's recurrences, a spline weight times a small coefficient, a gradient step)
/// passes through the subnormal range (docs/benchmarks.md, "Subnormal coefficients"). A
/// subnormal value is below every tolerance the solver has by 30 orders of magnitude, so
/// flushing it changes no decision (the A/B's final energies: 9e-9 relative apart).
///
/// Only the [`solver_pool`]'s own threads call this: a caller's threads (a Python
/// interpreter's, an application's) keep their floating-point environment.
pub fn flush_subnormals_on_this_thread() {
    #[cfg(target_arch = "x86_64")]
    {
        /// MXCSR's flush-to-zero (bit 15) and denormals-are-zero (bit 6).
        const FTZ_DAZ: u32 = 0x8040;
        let mut csr = 0u32;
        // SAFETY: stmxcsr / ldmxcsr read and write this thread's SSE control register
        // through a valid u32; setting FTZ and DAZ changes only how subnormal values round.
        unsafe {
            std::arch::asm!("stmxcsr [{}]", in(reg) &mut csr, options(nostack, preserves_flags));
            csr |= FTZ_DAZ;
            std::arch::asm!("ldmxcsr [{}]", in(reg) &csr, options(nostack, preserves_flags));
        }
    }
}

/// Runs `job` on a worker of a [`solver_pool`] (on the calling thread if there is none).
///
/// The solver is a serial loop of parallel kernels. Driven from a thread outside the pool,
/// each kernel is injected into the pool, wakes its workers and puts the solver's thread to
/// sleep until they are done: on two cores three threads, a sleep and a wake-up per kernel.
/// On a worker the solver's thread takes its share of each kernel itself and the other
/// workers steal the rest (deep 2-level runs at 128²: wall −9 %, system time −35 %).
pub fn on_a_worker<R: Send>(job: impl FnOnce() -> R + Send) -> R {
    match solver_pool() {
        Some(pool) => pool.install(job),
        None => job(),
    }
}

impl fmt::Display for Backend {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Backend {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<Self, Self::Err> {
        Self::ALL
            .into_iter()
            .find(|b| b.name().eq_ignore_ascii_case(s))
            .ok_or_else(|| format!("unknown backend `{s}`: expected flex, ndarray or wgpu"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `x · 0.5` for the smallest normal float32 `x`: subnormal where subnormals are kept.
    fn half_of_the_smallest_normal() -> f32 {
        std::hint::black_box(f32::MIN_POSITIVE) * std::hint::black_box(0.5f32)
    }

    #[test]
    fn the_solver_pool_flushes_subnormals_and_the_caller_keeps_them() {
        let on_a_worker = on_a_worker(half_of_the_smallest_normal);
        if cfg!(target_arch = "x86_64") {
            assert_eq!(on_a_worker, 0.0, "FTZ on the solver's threads");
        }
        let here = half_of_the_smallest_normal();
        assert!(
            here > 0.0 && here < f32::MIN_POSITIVE,
            "the calling thread's environment is left alone: {here:e}"
        );
    }

    #[test]
    fn a_device_knows_its_backend_with_or_without_autodiff() {
        for backend in Backend::compiled() {
            if backend == Backend::Wgpu {
                continue; // needs a driver; covered by the gather parity tests
            }
            let device = backend.device().unwrap();
            assert_eq!(Backend::of(&device), Some(backend));
            assert_eq!(Backend::of(&device.clone().autodiff()), Some(backend));
            assert_eq!(Capabilities::of(&device).gather, backend.warp_gather());
        }
    }
}
