//! The native part of the `deepmorph` Python package: NumPy arrays in, a `Morph` out, on the
//! library's own code paths (`MorphJob::prepare` / `from_images`, `run`, `write`), so a morph
//! made here is the morph `deepmorph morph` makes, and `Morph.save` writes what it writes.
//!
//! Like the program, the module allocates with mimalloc and runs the solver on a worker of
//! its thread pool (`src/bin/deepmorph/main.rs` and `deepmorph::backend::on_a_worker` say
//! why: without them a default morph took 48–53 s instead of 35–37 s).
//!
//! Settings start from the library's defaults (`MorphConfig::default`, `MorphConfig::deep`,
//! `Quality::apply`) and are overridden by name through `config.json`'s own serialisation:
//! no default is written twice. The solve runs with the GIL released; after every sweep the
//! observer takes the GIL back for a moment to check for Ctrl-C and to call the progress
//! callback.

use std::path::PathBuf;
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, Ordering};

use deepmorph::app::config::{Inputs, Model, MorphConfig, Quality, WorkingSize};
use deepmorph::app::evaluate::evaluate as evaluate_folder;
use deepmorph::app::job::{MorphJob, MorphResult};
use deepmorph::eval::metrics::compose;
use deepmorph::eval::synthetic::{Field, warped_pair};
use deepmorph::io::images::RgbImage;
use deepmorph::io::points::{PointPair, read_points};
use deepmorph::model::grid::host_values;
use deepmorph::solver::observer::{Initialisation, Observer, Phase, SweepEvent};
use deepmorph::{Backend, Error, Precision};
use numpy::ndarray::{Array, ArrayView3};
use numpy::{IntoPyArray, PyReadonlyArray2, PyReadonlyArray3, PyUntypedArrayMethods};
use pyo3::create_exception;
use pyo3::exceptions::{
    PyFileNotFoundError, PyKeyboardInterrupt, PyMemoryError, PyOSError, PyRuntimeError,
    PyValueError,
};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyString};
use serde_json::Value;

/// The program's allocator (see `src/bin/deepmorph/main.rs`): glibc's malloc returns the
/// solver's megabyte tensors to the kernel and page-faults them in again at every sweep.
/// NumPy arrays made from Rust buffers free them through Rust, hence through this allocator
/// too.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

create_exception!(
    _native,
    Interrupted,
    PyKeyboardInterrupt,
    "Ctrl-C stopped a morph after its current step; `.morph` holds the path reached (a \
     `Morph`, which `.save` writes like any other)."
);

/// The library's error as the Python exception a caller expects, with its message.
fn py_error(error: Error) -> PyErr {
    let message = error.to_string();
    match &error {
        Error::Io { cause, .. } if cause.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(message)
        }
        Error::Image {
            cause: image::ImageError::IoError(cause),
            ..
        } if cause.kind() == std::io::ErrorKind::NotFound => PyFileNotFoundError::new_err(message),
        Error::Io { .. } => PyOSError::new_err(message),
        Error::Memory { .. } => PyMemoryError::new_err(message),
        Error::BackendUnavailable { .. } => PyRuntimeError::new_err(message),
        Error::BackendNotCompiled { .. }
        | Error::UnsupportedPrecision { .. }
        | Error::InvalidParameter { .. }
        | Error::Image { .. }
        | Error::Overwrite { .. }
        | Error::OutputFolder { .. }
        | Error::NonFinite { .. }
        | Error::Format { .. }
        | Error::Shape { .. } => PyValueError::new_err(message),
    }
}

/// Runs `work`, turning a panic (a bug of ours) into a `RuntimeError` instead of letting it
/// reach Python as pyo3's `PanicException`, which `except Exception` does not catch.
fn guarded<T>(what: &str, work: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(work)).unwrap_or_else(|panic| {
        let detail = panic
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| panic.downcast_ref::<&str>().copied())
            .unwrap_or("no message");
        Err(PyRuntimeError::new_err(format!(
            "internal error in {what} (a bug of deepmorph; please report it): {detail}"
        )))
    })
}

/// A path (`str` or `os.PathLike`), or `None` for anything else.
fn as_path(value: &Bound<'_, PyAny>) -> Option<PathBuf> {
    if value.is_instance_of::<PyString>() || value.hasattr("__fspath__").unwrap_or(false) {
        value.extract::<PathBuf>().ok()
    } else {
        None
    }
}

/// A channel-major image from `[H, W, 3]` values in `[0, 1]`.
fn image_from_hwc(name: &str, view: ArrayView3<'_, f32>) -> PyResult<RgbImage> {
    let (h, w, c) = view.dim();
    if c != 3 || h == 0 || w == 0 {
        return Err(PyValueError::new_err(format!(
            "{name}: an array of shape [H, W, 3] (RGB), not {:?}",
            view.shape()
        )));
    }
    if let Some(bad) = view.iter().find(|v| !(0.0..=1.0).contains(*v)) {
        return Err(PyValueError::new_err(format!(
            "{name}: float values must lie in [0, 1] (as uint8 / 255), found {bad}"
        )));
    }
    let mut planes = vec![0.0f32; 3 * h * w];
    for ((i, j, k), &v) in view.indexed_iter() {
        planes[k * h * w + i * w + j] = v;
    }
    RgbImage::new(h, w, planes).map_err(py_error)
}

/// An input image: a path (read as the CLI reads it) or a `uint8` / floating `[H, W, 3]`
/// array.
enum ImageArg {
    Path(PathBuf),
    Image(RgbImage),
}

impl ImageArg {
    fn extract(name: &str, value: &Bound<'_, PyAny>) -> PyResult<Self> {
        if let Some(path) = as_path(value) {
            return Ok(Self::Path(path));
        }
        if let Ok(bytes) = value.extract::<PyReadonlyArray3<'_, u8>>() {
            let view = bytes.as_array().mapv(|v| f32::from(v) / 255.0);
            return image_from_hwc(name, view.view()).map(Self::Image);
        }
        if let Ok(floats) = value.extract::<PyReadonlyArray3<'_, f32>>() {
            return image_from_hwc(name, floats.as_array()).map(Self::Image);
        }
        if let Ok(doubles) = value.extract::<PyReadonlyArray3<'_, f64>>() {
            let view = doubles.as_array().mapv(|v| v as f32);
            return image_from_hwc(name, view.view()).map(Self::Image);
        }
        Err(PyValueError::new_err(format!(
            "{name}: a path or a NumPy array [H, W, 3] of uint8 (0..255) or float32 / float64 \
             (0..1), not {}",
            describe(value)
        )))
    }

    fn into_image(self) -> PyResult<RgbImage> {
        match self {
            Self::Path(path) => RgbImage::load(&path).map_err(py_error),
            Self::Image(image) => Ok(image),
        }
    }
}

/// What a Python value is, for an error message.
fn describe(value: &Bound<'_, PyAny>) -> String {
    if let Ok(array) = value.cast::<numpy::PyUntypedArray>() {
        let dtype = array
            .dtype()
            .str()
            .map(|s| s.to_string())
            .unwrap_or_default();
        return format!("an array of shape {:?} and dtype {dtype}", array.shape());
    }
    value
        .get_type()
        .name()
        .map(|n| format!("a {n}"))
        .unwrap_or_else(|_| "this value".into())
}

/// Landmark pairs: a points file (CSV or JSON, as `--points`), or rows `(x_a, y_a, x_b,
/// y_b)` in each image's own pixels (a sequence, or an array `[N, 4]`).
fn points_arg(value: &Bound<'_, PyAny>) -> PyResult<Vec<PointPair>> {
    if let Some(path) = as_path(value) {
        return read_points(&path).map_err(py_error);
    }
    let rows: Vec<[f64; 4]> = match value.extract::<PyReadonlyArray2<'_, f64>>() {
        Ok(array) => {
            let array = array.as_array();
            if array.ncols() != 4 {
                return Err(PyValueError::new_err(format!(
                    "points: an array [N, 4] of (x_a, y_a, x_b, y_b), not of shape {:?}",
                    array.shape()
                )));
            }
            array
                .rows()
                .into_iter()
                .map(|r| [r[0], r[1], r[2], r[3]])
                .collect()
        }
        Err(_) => value.extract().map_err(|_| {
            PyValueError::new_err(format!(
                "points: a points file, or rows (x_a, y_a, x_b, y_b) as a list or an [N, 4] \
                 array, not {}",
                describe(value)
            ))
        })?,
    };
    Ok(rows
        .into_iter()
        .map(|[xa, ya, xb, yb]| PointPair::new([xa, ya], [xb, yb]))
        .collect())
}

/// A setting named by a string, read by its `config.json` spelling (`"batched"`,
/// `"wgpu"`, `"similarity"`), with the valid names in the error.
fn named<T: serde::de::DeserializeOwned>(what: &str, value: &str, valid: &str) -> PyResult<T> {
    serde_json::from_value(Value::String(value.to_lowercase())).map_err(|_| {
        PyValueError::new_err(format!(
            "invalid {what} = {value:?}: must be one of {valid}"
        ))
    })
}

/// A backend by name; `None`: the library's default (the first compiled of flex, ndarray,
/// wgpu).
fn backend_arg(backend: Option<&str>) -> PyResult<Backend> {
    match backend {
        Some(name) => named("backend", name, "'flex', 'ndarray', 'wgpu'"),
        None => Ok(MorphConfig::default().backend),
    }
}

/// Where a keyword of `**params` lives in `config.json`'s `config` object, searched in this
/// order: the energy's parameters, iPALM's, the solver's, the deep model's, the top level.
const PARAM_HOMES: [&[&str]; 5] = [
    &["solver", "params"],
    &["solver", "ipalm"],
    &["solver"],
    &["deep"],
    &[],
];

/// Keys that name a group or a setting with its own argument, never a `**params` keyword.
const NOT_PARAMS: [&str; 10] = [
    "solver", "params", "ipalm", "deep", "size", "backend", "points", "align", "steps", "vgg19",
];

/// `**params` spelled as `config.json` spells them: `lambda_` (Python's keyword) is `lambda`,
/// `frames` is `animation_frames`, `max_memory` is `max_memory_gib`.
fn config_key(key: &str) -> &str {
    match key.trim_end_matches('_') {
        "frames" => "animation_frames",
        "max_memory" => "max_memory_gib",
        other => other,
    }
}

/// Every `**params` keyword that `config` takes, for an error message.
fn param_names(config: &Value) -> Vec<String> {
    let mut names = Vec::new();
    for home in PARAM_HOMES {
        let mut at = config;
        for key in home {
            at = &at[*key];
        }
        if let Value::Object(map) = at {
            for (key, value) in map {
                if !NOT_PARAMS.contains(&key.as_str()) && !value.is_object() {
                    names.push(if key == "lambda" {
                        "lambda_".into()
                    } else {
                        key.clone()
                    });
                }
            }
        }
    }
    names
}

/// `value` as JSON, through Python's `json` module (numbers, bools, strings, lists, None).
fn to_json(py: Python<'_>, key: &str, value: &Bound<'_, PyAny>) -> PyResult<Value> {
    let text: String = py
        .import("json")?
        .call_method1("dumps", (value,))
        .and_then(|t| t.extract())
        .map_err(|_| PyValueError::new_err(format!("{key}: not a number, bool, string or list")))?;
    serde_json::from_str(&text).map_err(|e| PyValueError::new_err(format!("{key}: {e}")))
}

/// The keyword arguments of `morph` as a [`MorphConfig`]: the library's defaults for the
/// model, the quality preset, then every setting given.
#[allow(non_snake_case, clippy::too_many_arguments)]
fn build_config(
    py: Python<'_>,
    model: &str,
    vgg19: Option<PathBuf>,
    quality: Option<&str>,
    K: Option<usize>,
    size: Option<&Bound<'_, PyAny>>,
    levels: Option<usize>,
    sweeps: Option<usize>,
    tol: Option<f64>,
    schedule: Option<&str>,
    backend: Option<&str>,
    points: Option<&Bound<'_, PyAny>>,
    align: Option<&str>,
    params: Option<&Bound<'_, PyDict>>,
) -> PyResult<MorphConfig> {
    let mut config = match (named::<Model>("model", model, "'rgb', 'deep'")?, vgg19) {
        (Model::Rgb, None) => MorphConfig::default(),
        (Model::Rgb, Some(_)) => {
            return Err(PyValueError::new_err("vgg19 is used only by model='deep'"));
        }
        (Model::Deep, Some(weights)) => MorphConfig::deep(weights),
        (Model::Deep, None) => {
            return Err(PyValueError::new_err(
                "model='deep' needs VGG19 weights: vgg19='path/to/vgg19.onnx' (an ONNX or \
                 safetensors VGG19; see the README for where to get one)",
            ));
        }
    };
    if let Some(quality) = quality {
        named::<Quality>("quality", quality, "'draft', 'standard', 'paper'")?.apply(&mut config);
    }
    let solver = &mut config.solver;
    solver.steps = K.unwrap_or(solver.steps);
    solver.levels = levels.unwrap_or(solver.levels);
    solver.sweeps = sweeps.unwrap_or(solver.sweeps);
    solver.tolerance = tol.unwrap_or(solver.tolerance);
    if let Some(schedule) = schedule {
        solver.ipalm.schedule = named("schedule", schedule, "'sequential', 'batched'")?;
    }
    if backend.is_some() {
        config.backend = backend_arg(backend)?;
    }
    if let Some(align) = align {
        config.align = named("align", align, "'none', 'similarity', 'affine'")?;
    }
    if let Some(size) = size {
        config.size = if let Ok(max_side) = size.extract::<usize>() {
            WorkingSize::Fit { max_side }
        } else if let Ok((height, width)) = size.extract::<(usize, usize)>() {
            WorkingSize::Exact { height, width }
        } else {
            return Err(PyValueError::new_err(format!(
                "size: an int (the longest side; the aspect is kept) or (height, width), not {}",
                describe(size)
            )));
        };
    }
    if let Some(points) = points {
        config.points = Some(points_arg(points)?);
    }
    let Some(params) = params else {
        return Ok(config);
    };
    let mut json = serde_json::to_value(&config).expect("configs serialise");
    for (key, value) in params.iter() {
        let key: String = key.extract()?;
        let name = config_key(&key);
        let value = to_json(py, &key, &value)?;
        let home = PARAM_HOMES.iter().find(|home| {
            let mut at = &json;
            for part in home.iter() {
                at = &at[*part];
            }
            !NOT_PARAMS.contains(&name) && at.get(name).is_some_and(|v| !v.is_object())
        });
        let Some(home) = home else {
            if json["deep"].is_null() && ["eta", "feature_rms", "pre_sweeps"].contains(&name) {
                return Err(PyValueError::new_err(format!(
                    "{key} is used only by model='deep'"
                )));
            }
            return Err(PyValueError::new_err(format!(
                "unknown parameter {key:?}: the parameters are {}",
                param_names(&json).join(", ")
            )));
        };
        let mut at = &mut json;
        for part in home.iter() {
            at = &mut at[*part];
        }
        at[name] = value;
    }
    let config: MorphConfig = serde_json::from_value(json)
        .map_err(|e| PyValueError::new_err(format!("invalid parameter: {e}")))?;
    Ok(config)
}

/// The first exception of a morph (Ctrl-C, or the progress callback's): it stops the
/// morph after the current step, through the interrupt flag, and is raised when the solve
/// returns.
struct Stop<'a> {
    interrupt: &'a AtomicBool,
    error: Mutex<Option<PyErr>>,
}

impl Stop<'_> {
    fn raise(&self, error: PyErr) {
        let mut first = self.error.lock().unwrap_or_else(|p| p.into_inner());
        if first.is_none() {
            *first = Some(error);
        }
        self.interrupt.store(true, Ordering::SeqCst);
    }

    fn take(&self) -> Option<PyErr> {
        self.error.lock().unwrap_or_else(|p| p.into_inner()).take()
    }
}

/// Reports every sweep to the progress callback, on the solver's thread.
struct Watch<'a> {
    callback: Option<Py<PyAny>>,
    stop: &'a Stop<'a>,
    warnings: Vec<String>,
}

impl Observer for Watch<'_> {
    fn sweep(&mut self, event: &SweepEvent<'_>) {
        let Some(callback) = &self.callback else {
            return;
        };
        if self.stop.interrupt.load(Ordering::SeqCst) {
            return;
        }
        let outcome = Python::attach(|py| -> PyResult<()> {
            let info = PyDict::new(py);
            info.set_item("level", event.level)?;
            info.set_item("levels", event.levels)?;
            info.set_item("size", (event.grid.height(), event.grid.width()))?;
            info.set_item(
                "phase",
                match event.phase {
                    Phase::Features => "features",
                    Phase::Joint => "joint",
                },
            )?;
            info.set_item("sweep", event.sweep)?;
            info.set_item("sweeps", event.sweeps)?;
            info.set_item("energy", event.energy)?;
            info.set_item("regularizer", event.regularizer)?;
            info.set_item("data", event.data)?;
            info.set_item("landmarks", event.landmarks)?;
            info.set_item("seconds", event.seconds)?;
            info.set_item("stop", event.stop.map(|s| s.name()))?;
            callback.call1(py, (info,))?;
            Ok(())
        });
        if let Err(error) = outcome {
            self.stop.raise(error);
        }
    }

    fn initialised(&mut self, initialisation: &Initialisation) {
        self.warnings.extend(initialisation.warning());
    }
}

/// A finished (or interrupted) morph: its frames, deformations and records as NumPy arrays
/// and dicts, and `save` to write it as the CLI does.
#[pyclass(module = "deepmorph", frozen)]
struct Morph {
    // Boxed: Burn's tensors are over-aligned (64 bytes), more than Python's allocator
    // guarantees for the object that holds a pyclass inline.
    job: Box<MorphJob>,
    /// Locked only with the GIL released (see [`Morph::with_result`]).
    result: Mutex<Box<MorphResult>>,
    termination: String,
    seconds: f64,
    frames: Py<PyAny>,
    deformations: Py<PyAny>,
    composed: Py<PyAny>,
    energy: Py<PyAny>,
    config: Py<PyAny>,
    metrics: Mutex<Option<Py<PyAny>>>,
    notes: Vec<String>,
}

/// `[N, H, W, 3]` float32 from channel-major images, in one buffer NumPy then owns.
fn frames_array<'py>(py: Python<'py>, frames: &[RgbImage]) -> PyResult<Bound<'py, PyAny>> {
    let (h, w) = frames.first().map_or((0, 0), RgbImage::size);
    let mut out = Vec::with_capacity(frames.len() * h * w * 3);
    for frame in frames {
        let data = frame.data();
        for p in 0..h * w {
            out.extend([data[p], data[h * w + p], data[2 * h * w + p]]);
        }
    }
    let array =
        Array::from_shape_vec((frames.len(), h, w, 3), out).expect("the frames fill the shape");
    Ok(read_only(array.into_pyarray(py).into_any()))
}

/// Marks an array read-only: the morph's arrays are its record, shared by every access.
fn read_only(array: Bound<'_, PyAny>) -> Bound<'_, PyAny> {
    let kwargs = PyDict::new(array.py());
    // Setting a flag on an array we just made cannot fail.
    let _ = kwargs
        .set_item("write", false)
        .and_then(|()| array.call_method("setflags", (), Some(&kwargs)));
    array
}

/// A JSON-serialisable value as the dict `json.loads` makes of it.
fn to_python<'py>(py: Python<'py>, value: &impl serde::Serialize) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(value).expect("records serialise");
    py.import("json")?.call_method1("loads", (text,))
}

/// `energy.csv` as a dict of columns: one value per sweep (NumPy arrays for the numbers,
/// a list for `stop`), per-step columns as lists of per-step lists.
fn energy_columns<'py>(py: Python<'py>, result: &MorphResult) -> PyResult<Bound<'py, PyAny>> {
    let records = &result.energy.records;
    let columns = PyDict::new(py);
    let ints = |f: &dyn Fn(&deepmorph::io::energy_log::EnergyRecord) -> usize| {
        records.iter().map(f).map(|v| v as i64).collect::<Vec<_>>()
    };
    let floats = |f: &dyn Fn(&deepmorph::io::energy_log::EnergyRecord) -> f64| {
        records.iter().map(f).collect::<Vec<_>>()
    };
    for (name, values) in [
        ("level", ints(&|r| r.level)),
        ("height", ints(&|r| r.height)),
        ("width", ints(&|r| r.width)),
        ("sweep", ints(&|r| r.sweep)),
        ("restarts", ints(&|r| r.restarts)),
        ("drops_phi", ints(&|r| r.drops_phi)),
        ("drops_f", ints(&|r| r.drops_f)),
        ("trials_phi", ints(&|r| r.trials_phi)),
        ("trials_f", ints(&|r| r.trials_f)),
    ] {
        columns.set_item(name, values.into_pyarray(py))?;
    }
    for (name, values) in [
        ("E", floats(&|r| r.energy)),
        ("sum_R", floats(&|r| r.regularizer)),
        ("sum_D", floats(&|r| r.data)),
        ("E_lm", floats(&|r| r.landmarks)),
        ("seconds", floats(&|r| r.seconds)),
    ] {
        columns.set_item(name, values.into_pyarray(py))?;
    }
    columns.set_item(
        "L_phi",
        records
            .iter()
            .map(|r| r.lipschitz_phi.clone())
            .collect::<Vec<_>>(),
    )?;
    columns.set_item(
        "L_f",
        records
            .iter()
            .map(|r| r.lipschitz_f.clone())
            .collect::<Vec<_>>(),
    )?;
    columns.set_item(
        "m_phi",
        records
            .iter()
            .map(|r| r.streak_phi.clone())
            .collect::<Vec<_>>(),
    )?;
    columns.set_item(
        "stop",
        PyList::new(py, records.iter().map(|r| r.stop.map(|s| s.name())))?,
    )?;
    Ok(columns.into_any())
}

impl Morph {
    fn new(
        py: Python<'_>,
        job: MorphJob,
        result: MorphResult,
        notes: Vec<String>,
    ) -> PyResult<Self> {
        let deformations = result.morph.state.deformations();
        let shape = deformations.dims();
        let composed = compose(&result.morph.grid, deformations.clone());
        let as_f32 = |values: Vec<f64>| values.into_iter().map(|v| v as f32).collect::<Vec<_>>();
        let phi = as_f32(host_values(deformations).map_err(py_error)?);
        let big_phi = as_f32(host_values(composed).map_err(py_error)?);
        let phi = Array::from_shape_vec(shape, phi).expect("the deformations fill their shape");
        let big_phi = Array::from_shape_vec((2, shape[2], shape[3]), big_phi)
            .expect("the composed map fills its shape");
        Ok(Self {
            frames: frames_array(py, &result.frames)?.unbind(),
            deformations: read_only(phi.into_pyarray(py).into_any()).unbind(),
            composed: read_only(big_phi.into_pyarray(py).into_any()).unbind(),
            energy: energy_columns(py, &result)?.unbind(),
            config: to_python(py, &result.record(&job))?.unbind(),
            metrics: Mutex::new(None),
            termination: result.morph.termination.to_string(),
            seconds: result.seconds,
            job: Box::new(job),
            result: Mutex::new(Box::new(result)),
            notes,
        })
    }

    /// Runs `work` on the result with the GIL released, the lock taken and dropped there:
    /// a thread that waited for the lock holding the GIL, while the lock's holder waits for
    /// the GIL, would deadlock. A panic becomes a `RuntimeError`.
    fn with_result<T: Send>(
        &self,
        py: Python<'_>,
        what: &str,
        work: impl FnOnce(&MorphResult) -> deepmorph::Result<T> + Send,
    ) -> PyResult<T> {
        guarded(what, || {
            py.detach(|| {
                // A panic in an earlier call leaves the result as it was: the poison is moot.
                let result = self.result.lock().unwrap_or_else(|p| p.into_inner());
                work(&result)
            })
            .map_err(py_error)
        })
    }
}

#[pymethods]
impl Morph {
    /// `u_0 .. u_K`, float32 `[K+1, H, W, 3]` in `[0, 1]` (read-only).
    #[getter]
    fn frames(&self, py: Python<'_>) -> Py<PyAny> {
        self.frames.clone_ref(py)
    }

    /// `φ_1 .. φ_K`, float32 `[K, 2, H, W]` (SPEC §0: pixel units, `[:, 0]` the row,
    /// `[:, 1]` the column): `φ_k(x)` is where pixel `x` of frame `k − 1` lies in frame `k`
    /// (`u_{k−1} ≈ u_k ∘ φ_k`) (read-only).
    #[getter]
    fn deformations(&self, py: Python<'_>) -> Py<PyAny> {
        self.deformations.clone_ref(py)
    }

    /// `Φ = φ_K ∘ … ∘ φ_1`, float32 `[2, H, W]`: `Φ(x)` is where pixel `x` of A lies in B
    /// (`u_0 ≈ u_K ∘ Φ`) (read-only).
    #[getter]
    fn composed(&self, py: Python<'_>) -> Py<PyAny> {
        self.composed.clone_ref(py)
    }

    /// `energy.csv` as a dict of columns (one entry per sweep).
    #[getter]
    fn energy(&self, py: Python<'_>) -> Py<PyAny> {
        self.energy.clone_ref(py)
    }

    /// `config.json`: the settings, the inputs, how the run ended.
    #[getter]
    fn config(&self, py: Python<'_>) -> Py<PyAny> {
        self.config.clone_ref(py)
    }

    /// `metrics.json`'s numbers, computed on first access (the deep model's feature path
    /// loads VGG19 once more).
    #[getter]
    fn metrics(&self, py: Python<'_>) -> PyResult<Py<PyAny>> {
        // The cache's lock is held with the GIL only, never across a release of it.
        let cache = || self.metrics.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(metrics) = &*cache() {
            return Ok(metrics.clone_ref(py));
        }
        let metrics = self.with_result(py, "Morph.metrics", |r| r.metrics(&self.job))?;
        let metrics = to_python(py, &metrics)?.unbind();
        *cache() = Some(metrics.clone_ref(py));
        Ok(metrics)
    }

    /// How the run ended: `"completed"`, or where it was interrupted or stopped.
    #[getter]
    fn termination(&self) -> String {
        self.termination.clone()
    }

    /// Seconds the solver ran.
    #[getter]
    fn seconds(&self) -> f64 {
        self.seconds
    }

    /// What preparing and starting the morph told (inputs resized, the alignment found,
    /// warnings).
    #[getter]
    fn notes(&self) -> Vec<String> {
        self.notes.clone()
    }

    /// Writes the morph into the folder `dir` exactly as `deepmorph morph -o dir` does
    /// (frames, animations, sheet, deformations, energy.csv, config.json, metrics.json), in
    /// one transaction; a folder holding a previous morph is replaced only with `force`,
    /// one holding other files never. Returns the folder's path.
    #[pyo3(signature = (dir, *, force = false))]
    fn save(&self, py: Python<'_>, dir: PathBuf, force: bool) -> PyResult<String> {
        let (_, path) = self.with_result(py, "Morph.save", |result| {
            let folder = self.job.output_folder(&dir, force)?;
            result.write(&self.job, folder)
        })?;
        Ok(path.display().to_string())
    }

    /// `count` frames evenly spaced in time along the path (the `K + 1` computed frames
    /// among them, in-betweens following the deformations), float32 `[count, H, W, 3]`.
    fn inbetween<'py>(&self, py: Python<'py>, count: usize) -> PyResult<Bound<'py, PyAny>> {
        let frames = self.with_result(py, "Morph.inbetween", |r| r.inbetween(count))?;
        frames_array(py, &frames)
    }

    fn __repr__(&self, py: Python<'_>) -> PyResult<String> {
        let shape: (usize, usize, usize, usize) =
            self.frames.bind(py).getattr("shape")?.extract()?;
        let (frames, h, w, _) = shape;
        Ok(format!(
            "<deepmorph.Morph K={} {w}x{h} (WxH), {}, {:.1} s>",
            frames.saturating_sub(1),
            self.termination,
            self.seconds
        ))
    }
}

/// Runs the morph on a worker of the solver's pool, as the program does
/// ([`deepmorph::backend::on_a_worker`]), while this thread, which Python delivers signals
/// to, checks for them every 50 ms: Python runs signal handlers on the main thread only,
/// never on the solver's. Called with the GIL released.
fn solve_watching_signals(
    job: &MorphJob,
    watch: &mut Watch<'_>,
    stop: &Stop<'_>,
) -> deepmorph::Result<MorphResult> {
    std::thread::scope(|scope| {
        let solver =
            scope.spawn(|| deepmorph::backend::on_a_worker(|| job.run(watch, stop.interrupt)));
        while !solver.is_finished() {
            std::thread::sleep(std::time::Duration::from_millis(50));
            if let Err(error) = Python::attach(|py| py.check_signals()) {
                stop.raise(error);
            }
        }
        solver
            .join()
            .unwrap_or_else(|panic| std::panic::resume_unwind(panic))
    })
}

/// The native `morph`; `deepmorph.morph` (Python) documents it and adds `progress=True`.
#[pyfunction]
#[pyo3(signature = (a, b, *, K=None, model="rgb", vgg19=None, size=None, levels=None, sweeps=None, tol=None, quality=None, schedule=None, backend=None, points=None, align=None, progress=None, **params))]
#[allow(non_snake_case, clippy::too_many_arguments)]
fn morph(
    py: Python<'_>,
    a: &Bound<'_, PyAny>,
    b: &Bound<'_, PyAny>,
    K: Option<usize>,
    model: &str,
    vgg19: Option<PathBuf>,
    size: Option<&Bound<'_, PyAny>>,
    levels: Option<usize>,
    sweeps: Option<usize>,
    tol: Option<f64>,
    quality: Option<&str>,
    schedule: Option<&str>,
    backend: Option<&str>,
    points: Option<&Bound<'_, PyAny>>,
    align: Option<&str>,
    progress: Option<Py<PyAny>>,
    params: Option<&Bound<'_, PyDict>>,
) -> PyResult<Py<PyAny>> {
    let config = build_config(
        py, model, vgg19, quality, K, size, levels, sweeps, tol, schedule, backend, points, align,
        params,
    )?;
    let (a, b) = (ImageArg::extract("a", a)?, ImageArg::extract("b", b)?);
    let job = guarded("morph", || {
        py.detach(|| match (a, b) {
            (ImageArg::Path(a), ImageArg::Path(b)) => {
                MorphJob::prepare(config, Inputs::Files { a, b }).map_err(py_error)
            }
            (a, b) => {
                MorphJob::from_images(config, a.into_image()?, b.into_image()?).map_err(py_error)
            }
        })
    })?;
    let interrupt = AtomicBool::new(false);
    let stop = Stop {
        interrupt: &interrupt,
        error: Mutex::new(None),
    };
    let mut watch = Watch {
        callback: progress,
        stop: &stop,
        warnings: Vec::new(),
    };
    let result = guarded("morph", || {
        py.detach(|| solve_watching_signals(&job, &mut watch, &stop))
            .map_err(py_error)
    })?;
    let mut notes = job.notes().to_vec();
    notes.append(&mut watch.warnings);
    let error = stop.take();
    let morph = Py::new(py, Morph::new(py, job, result, notes)?)?;
    match error {
        None => Ok(morph.into_any()),
        Some(error) if error.is_instance_of::<PyKeyboardInterrupt>(py) => {
            let interrupted = Interrupted::new_err(
                "interrupted (Ctrl-C): the morph stopped after its current step; the path \
                 reached is in this exception's .morph",
            );
            interrupted.value(py).setattr("morph", morph)?;
            Err(interrupted)
        }
        Some(error) => Err(error),
    }
}

/// Measures the morph saved in `dir` (`deepmorph eval`): the dict of `metrics.json`, with
/// the endpoint error against `truth` (a `.flo` or disparity file), the landmark residuals
/// on `points` (held-out points), the feature path with `vgg19`.
#[pyfunction]
#[pyo3(signature = (dir, truth=None, *, points=None, vgg19=None, resample_truth=false, backend=None))]
fn evaluate(
    py: Python<'_>,
    dir: PathBuf,
    truth: Option<PathBuf>,
    points: Option<PathBuf>,
    vgg19: Option<PathBuf>,
    resample_truth: bool,
    backend: Option<&str>,
) -> PyResult<Py<PyAny>> {
    let backend = backend_arg(backend)?;
    let metrics = guarded("evaluate", || {
        py.detach(|| {
            let device = backend.device_for(Precision::F32)?;
            evaluate_folder(
                &dir,
                truth.as_deref(),
                resample_truth,
                vgg19.as_deref(),
                points.as_deref(),
                &device,
            )
        })
        .map_err(py_error)
    })?;
    Ok(to_python(py, &metrics.metrics)?.unbind())
}

/// A synthetic pair with a known correspondence (`deepmorph warp`): returns `(a, flow)`,
/// `a` the image warped by `field` of size `amount` (float32 `[H, W, 3]`; morph it to the
/// image itself) and `flow` float32 `[H, W, 2]` the true displacement `(Δrow, Δcolumn)` from
/// each pixel of `a` to its match in the image.
#[pyfunction]
#[pyo3(signature = (image, field, amount, *, backend=None))]
fn warp<'py>(
    py: Python<'py>,
    image: &Bound<'py, PyAny>,
    field: &str,
    amount: f64,
    backend: Option<&str>,
) -> PyResult<(Bound<'py, PyAny>, Bound<'py, PyAny>)> {
    let field = match field {
        "smooth" => Field::Smooth,
        "rotate" => Field::Rotate,
        "shear" => Field::Shear,
        other => {
            return Err(PyValueError::new_err(format!(
                "invalid field = {other:?}: must be one of 'smooth', 'rotate', 'shear'"
            )));
        }
    };
    let backend = backend_arg(backend)?;
    let input = ImageArg::extract("image", image)?.into_image()?;
    let (warped, truth) = guarded("warp", || {
        py.detach(|| {
            let device = backend.device_for(Precision::F32)?;
            warped_pair(&input, field, amount, &device)
        })
        .map_err(py_error)
    })?;
    let (h, w) = warped.size();
    let mut flow = Vec::with_capacity(h * w * 2);
    for i in 0..h {
        for j in 0..w {
            let [dr, dc] = truth.at(i, j).unwrap_or([f64::NAN; 2]);
            flow.extend([dr as f32, dc as f32]);
        }
    }
    let flow = Array::from_shape_vec((h, w, 2), flow).expect("the flow fills its shape");
    let warped = frames_array(py, &[warped])?;
    let warped = warped.call_method1("__getitem__", (0,))?;
    Ok((warped, flow.into_pyarray(py).into_any()))
}

/// The settings a morph starts from (`config.json`'s `config` object) for `model` (`"rgb"`
/// or `"deep"`) and an optional `quality` preset: the library's own defaults, SPEC §9.
#[pyfunction]
#[pyo3(signature = (model="rgb", quality=None))]
fn defaults(py: Python<'_>, model: &str, quality: Option<&str>) -> PyResult<Py<PyAny>> {
    let mut config = match named::<Model>("model", model, "'rgb', 'deep'")? {
        Model::Rgb => MorphConfig::default(),
        Model::Deep => MorphConfig::deep("vgg19.onnx"),
    };
    if let Some(quality) = quality {
        named::<Quality>("quality", quality, "'draft', 'standard', 'paper'")?.apply(&mut config);
    }
    Ok(to_python(py, &config)?.unbind())
}

/// The backends compiled into this module that can run here (`"flex"`, `"ndarray"`,
/// `"wgpu"` where a Vulkan/Metal/DX12 driver is found).
#[pyfunction]
fn backends(py: Python<'_>) -> Vec<String> {
    py.detach(|| {
        [Backend::Flex, Backend::NdArray, Backend::Wgpu]
            .into_iter()
            .filter(|b| b.device_for(Precision::F32).is_ok())
            .map(|b| b.to_string())
            .collect()
    })
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    // As the program: mimalloc's huge pages cleared whole at every refault cost deep sweeps up
    // to 15 % (`deepmorph::host_memory::prefer_small_pages`; `MIMALLOC_ALLOW_THP=1` keeps them).
    deepmorph::host_memory::prefer_small_pages();
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("Interrupted", m.py().get_type::<Interrupted>())?;
    m.add_class::<Morph>()?;
    m.add_function(wrap_pyfunction!(morph, m)?)?;
    m.add_function(wrap_pyfunction!(evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(warp, m)?)?;
    m.add_function(wrap_pyfunction!(defaults, m)?)?;
    m.add_function(wrap_pyfunction!(backends, m)?)?;
    Ok(())
}
