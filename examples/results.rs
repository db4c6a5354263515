//! The paper's experiments at a chosen scale (`docs/results.md`): every team pair morphed
//! with the RGB and the deep model, a contact sheet of each morph with a ×4 zoom inset, and
//! the table of numbers (time, peak memory, data share, `det J`, path smoothness, endpoint
//! error on the stereo pair).
//!
//! ```sh
//! cargo run --release --example results -- --size 256                 # every pair, both models
//! cargo run --release --example results -- --size 512 --pairs faces --models deep
//! cargo run --release --example results -- --size 128 --pairs cat_lion --vary delta=1,0.1,0.01
//! cargo run --release --example results -- --size 288 --pairs motorcycle --models deep \
//!     --vary tau=0.05,0.1,0.25
//! cargo run --release --example results -- --size 256 --backend wgpu  # on a GPU
//! cargo run --release --example results -- --size 256 --report         # what is done so far
//! ```
//!
//! Each morph runs in a child process of this program (so its peak resident memory is its
//! own, read from `/proc/self/status`), into `--work` (default `target/results/NAME/`, with
//! `NAME.json` beside it holding the run's settings and numbers). A run whose `NAME.json`
//! holds the same settings is not repeated: an interrupted study resumes where it stopped,
//! and a finished one only rewrites the sheets and the table. The table goes into
//! `docs/results.md` between the markers `<!-- results:KEY -->` and `<!-- /results:KEY -->`
//! (KEY names the study and the size; the text around them is left alone; a missing
//! section is appended), the sheets into `docs/results/`, and a copy of each record into
//! `docs/results/records/`: committed with the document, it keeps a run's row (and its
//! sheet) when the morph folder is gone, so a fresh checkout does not repeat the study.
//!
//! Reads the team's `../shared/data` (pairs and the stand-in VGG19); says so and exits when
//! they are absent.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::AtomicBool;
use std::time::Instant;

use anyhow::{Context, Result, bail, ensure};
use clap::{Parser, ValueEnum};
use deepmorph::app::config::{Inputs, MorphConfig, WorkingSize};
use deepmorph::app::job::MorphJob;
use deepmorph::app::memory::peak_resident_bytes;
use deepmorph::eval::folder::MorphFolder;
use deepmorph::eval::metrics::Metrics;
use deepmorph::io::animation::VideoFormat;
use deepmorph::io::truth::Correspondence;
use deepmorph::solver::ipalm::Schedule;
use deepmorph::solver::observer::{Observer, Phase, SweepEvent};
use deepmorph::{Backend, Precision};
use image::{Rgb, RgbImage, imageops};
use serde::{Deserialize, Serialize};

/// The CLI's allocator (see `src/bin/deepmorph/main.rs`), so the figures are the program's.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// The team's pairs (`shared/data/images/pairs`), in the order of the table.
const PAIRS: [&str; 6] = [
    "cat_lion",
    "cat_dog",
    "faces",
    "cars",
    "shapes",
    "motorcycle",
];
/// Frames the sheets show: `k = round(i·K/4)`, `i = 0..4`.
const SHEET_FRAMES: usize = 5;
/// Side of a sheet's frame thumbnail, pixels.
const THUMB: u32 = 112;
/// Side of the zoomed region in working pixels (×4 → one thumbnail).
const ZOOM_REGION: u32 = THUMB / 4;

#[derive(Parser, Clone)]
struct Args {
    /// Longest side of the working size (SPEC §9 works at 512; the CLI's default is 256).
    #[arg(long, default_value_t = 256)]
    size: usize,
    /// Pairs, comma-separated (default: all six team pairs).
    #[arg(long, value_delimiter = ',', default_values_t = PAIRS.map(String::from))]
    pairs: Vec<String>,
    /// Models, comma-separated: rgb, deep.
    #[arg(long, value_delimiter = ',', default_values_t = ["rgb".to_string(), "deep".to_string()])]
    models: Vec<String>,
    /// A parameter study: `NAME=v1,v2,…` with NAME one of delta, xi1, K, tau (the deep
    /// model's feature RMS); every pair × model runs once per value.
    #[arg(long)]
    vary: Option<String>,
    /// Steps K (SPEC §9: 15).
    #[arg(short = 'K', default_value_t = 15)]
    steps: usize,
    /// Pyramid levels (SPEC §9: 5).
    #[arg(long, default_value_t = 5)]
    levels: usize,
    /// Joint sweeps per level (SPEC §9: 250).
    #[arg(long, default_value_t = 250)]
    sweeps: usize,
    /// iPALM's block order (SPEC §6).
    #[arg(long, value_enum, default_value_t = Schedule::Sequential)]
    schedule: Schedule,
    /// Backend: flex, ndarray or wgpu.
    #[arg(long, default_value = "flex")]
    backend: Backend,
    /// VGG19 weights for the deep model.
    #[arg(long)]
    vgg19: Option<PathBuf>,
    /// Where the morphs and their records go.
    #[arg(long, default_value = "target/results")]
    work: PathBuf,
    /// The document the table goes into (the sheets into `results/` beside it).
    #[arg(long, default_value = "docs/results.md")]
    doc: PathBuf,
    /// Plan and print the runs, run nothing.
    #[arg(long)]
    dry_run: bool,
    /// Run nothing: the table and sheets of the runs done so far (a study still running in
    /// another process, or stopped part way).
    #[arg(long)]
    report: bool,
    /// Internal: run this one morph (a child process of the study).
    #[arg(long, hide = true)]
    one: Option<String>,
}

/// One morph of the study.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
struct RunSpec {
    pair: String,
    model: String,
    max_side: usize,
    steps: usize,
    levels: usize,
    sweeps: usize,
    schedule: String,
    backend: String,
    /// The varied parameter and its value, if any.
    vary: Option<(String, f64)>,
}

impl RunSpec {
    /// The run's folder name: pair, model, size and the varied value.
    fn name(&self) -> String {
        let mut name = format!("{}_{}_{}", self.pair, self.model, self.max_side);
        if let Some((param, value)) = &self.vary {
            write!(name, "_{param}{value}").unwrap();
        }
        if self.schedule != "sequential" {
            write!(name, "_{}", self.schedule).unwrap();
        }
        if self.backend != "flex" {
            write!(name, "_{}", self.backend).unwrap();
        }
        name
    }
}

/// What a finished run left: its settings and numbers (`NAME.json` beside the folder).
#[derive(Clone, Debug, Serialize, Deserialize)]
struct RunRecord {
    spec: RunSpec,
    /// The working size `(H, W)`.
    size: [usize; 2],
    /// Seconds of the solver, and of the whole child process (reading, VGG, writing).
    solver_seconds: f64,
    process_seconds: f64,
    /// Peak resident memory of the child process, bytes (`VmHWM`).
    peak_bytes: u64,
    /// Joint sweeps run on each level.
    sweeps: Vec<usize>,
    metrics: Metrics,
    /// The machine it ran on (`/proc/cpuinfo`'s model name, cores).
    machine: String,
    /// The date it finished (UTC, from the system clock).
    finished: String,
}

fn main() -> Result<()> {
    // Small pages and the solver's thread on a worker of the kernels' pool, as the CLI runs.
    deepmorph::host_memory::prefer_small_pages();
    deepmorph::backend::on_a_worker(run)
}

fn run() -> Result<()> {
    let args = Args::parse();
    let data = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
    if !data.join("images/pairs").is_dir() {
        println!(
            "skipped: {} is absent (the team's test data)",
            data.display()
        );
        return Ok(());
    }
    let vgg19 = args
        .vgg19
        .clone()
        .unwrap_or_else(|| data.join("vgg19/vgg19_hed_stand_in.onnx"));
    let runs = plan(&args)?;
    if let Some(name) = &args.one {
        let spec = runs
            .iter()
            .find(|r| &r.name() == name)
            .with_context(|| format!("no run named {name} in this study"))?;
        return run_one(spec, &data, &vgg19, &args.work);
    }
    std::fs::create_dir_all(&args.work)
        .with_context(|| format!("cannot create {}", args.work.display()))?;
    let sheets = args.doc.parent().unwrap_or(Path::new(".")).join("results");
    let kept = sheets.join("records");
    std::fs::create_dir_all(&kept).with_context(|| format!("cannot create {}", kept.display()))?;
    let mut records = Vec::new();
    for (i, spec) in runs.iter().enumerate() {
        let name = spec.name();
        let record_path = args.work.join(format!("{name}.json"));
        let kept_path = kept.join(format!("{name}.json"));
        let previous = read_record(&record_path, spec)
            .filter(|_| args.work.join(&name).join("config.json").is_file());
        let record = match previous {
            Some(record) => {
                println!("[{}/{}] {name}: done before, kept", i + 1, runs.len());
                record
            }
            // The morph folder is gone (a fresh checkout, a cleaned target): the committed
            // record still holds the row, and the committed sheet stays as it is.
            None if let Some(record) = read_record(&kept_path, spec) => {
                println!(
                    "[{}/{}] {name}: done before, kept from {}",
                    i + 1,
                    runs.len(),
                    kept_path.display()
                );
                records.push(record);
                continue;
            }
            None if args.dry_run || args.report => {
                println!("[{}/{}] {name}: not run yet, left out", i + 1, runs.len());
                continue;
            }
            None => {
                println!("[{}/{}] {name}: running", i + 1, runs.len());
                let status = Command::new(std::env::current_exe()?)
                    .args(std::env::args_os().skip(1))
                    .arg("--one")
                    .arg(&name)
                    .status()
                    .context("cannot start the run's child process")?;
                ensure!(status.success(), "{name} failed ({status})");
                serde_json::from_slice(&std::fs::read(&record_path)?)
                    .with_context(|| format!("{} is unreadable", record_path.display()))?
            }
        };
        if !args.dry_run && !args.report {
            std::fs::copy(&record_path, &kept_path)
                .with_context(|| format!("cannot copy the record to {}", kept_path.display()))?;
        }
        records.push(record);
    }
    if args.dry_run || records.is_empty() {
        return Ok(());
    }
    for record in &records {
        let dir = args.work.join(record.spec.name());
        if !dir.join("config.json").is_file() {
            continue;
        }
        let mut image = sheet(&dir, record.spec.steps)?;
        if matches!(&record.spec.vary, Some((p, _)) if p == "xi1") {
            image = below(&image, &field_row(&dir, record.spec.steps, image.width())?);
        }
        let path = sheets.join(format!("{}.jpg", record.spec.name()));
        let mut file = std::io::BufWriter::new(std::fs::File::create(&path)?);
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut file, 88)
            .encode_image(&image)
            .with_context(|| format!("cannot write {}", path.display()))?;
    }
    let key = study_key(&args);
    let table = table(&records, &key);
    update_doc(&args.doc, &key, &table)?;
    println!(
        "{} runs; table {key} in {}, sheets in {}",
        records.len(),
        args.doc.display(),
        sheets.display()
    );
    Ok(())
}

/// The record at `path` when it is readable and holds `spec`'s settings.
fn read_record(path: &Path, spec: &RunSpec) -> Option<RunRecord> {
    std::fs::read(path)
        .ok()
        .and_then(|bytes| serde_json::from_slice::<RunRecord>(&bytes).ok())
        .filter(|r| &r.spec == spec)
}

/// Every run of the study, in table order: pairs, then the varied value, then models.
fn plan(args: &Args) -> Result<Vec<RunSpec>> {
    let vary = match &args.vary {
        None => vec![None],
        Some(text) => {
            let (param, values) = text
                .split_once('=')
                .with_context(|| format!("--vary {text}: expected NAME=v1,v2,…"))?;
            ensure!(
                ["delta", "xi1", "K", "tau"].contains(&param),
                "--vary {param}: expected one of delta, xi1, K, tau"
            );
            values
                .split(',')
                .map(|v| {
                    let value: f64 = v
                        .trim()
                        .parse()
                        .with_context(|| format!("--vary {param}: {v} is not a number"))?;
                    Ok(Some((param.to_string(), value)))
                })
                .collect::<Result<Vec<_>>>()?
        }
    };
    let mut runs = Vec::new();
    for pair in &args.pairs {
        ensure!(
            PAIRS.contains(&pair.as_str()),
            "--pairs: {pair} is not one of {}",
            PAIRS.join(", ")
        );
        for vary in &vary {
            for model in &args.models {
                ensure!(
                    model == "rgb" || model == "deep",
                    "--models: {model} is not rgb or deep"
                );
                if model == "rgb" && matches!(vary, Some((p, _)) if p == "tau") {
                    continue;
                }
                let steps = match vary {
                    Some((p, v)) if p == "K" => *v as usize,
                    _ => args.steps,
                };
                runs.push(RunSpec {
                    pair: pair.clone(),
                    model: model.clone(),
                    max_side: args.size,
                    steps,
                    levels: args.levels,
                    sweeps: args.sweeps,
                    schedule: value_name(args.schedule),
                    backend: args.backend.to_string(),
                    vary: vary.clone(),
                });
            }
        }
    }
    Ok(runs)
}

/// The command-line name of a schedule.
fn value_name(schedule: Schedule) -> String {
    schedule
        .to_possible_value()
        .map_or_else(|| format!("{schedule:?}"), |v| v.get_name().to_string())
}

/// The pair's two images (`a.png` or `a.jpg`).
fn pair_inputs(data: &Path, pair: &str) -> Result<Inputs> {
    let dir = data.join("images/pairs").join(pair);
    let find = |stem: &str| {
        ["png", "jpg"]
            .iter()
            .map(|ext| dir.join(format!("{stem}.{ext}")))
            .find(|p| p.is_file())
            .with_context(|| format!("{}: no {stem}.png or {stem}.jpg", dir.display()))
    };
    Ok(Inputs::Files {
        a: find("a")?,
        b: find("b")?,
    })
}

/// Runs one morph in this (child) process and writes its folder and record.
fn run_one(spec: &RunSpec, data: &Path, vgg19: &Path, work: &Path) -> Result<()> {
    let started = Instant::now();
    let mut config = match spec.model.as_str() {
        "deep" => MorphConfig::deep(vgg19),
        _ => MorphConfig::default(),
    };
    config.size = WorkingSize::Fit {
        max_side: spec.max_side,
    };
    config.backend = spec.backend.parse().map_err(anyhow::Error::msg)?;
    config.solver.steps = spec.steps;
    config.solver.levels = spec.levels;
    config.solver.sweeps = spec.sweeps;
    config.solver.ipalm.schedule =
        Schedule::from_str(&spec.schedule, false).map_err(anyhow::Error::msg)?;
    // The sheets and the table need the frames and numbers; one animation to watch.
    config.video = vec![VideoFormat::Gif];
    match &spec.vary {
        Some((p, v)) if p == "delta" => config.solver.params.delta = *v,
        Some((p, v)) if p == "xi1" => config.solver.params.xi1 = *v,
        Some((p, v)) if p == "tau" => {
            let deep = config.deep.as_mut().context("tau needs the deep model")?;
            deep.features.feature_rms = *v;
        }
        _ => {}
    }
    let job = MorphJob::prepare(config, pair_inputs(data, &spec.pair)?)?;
    let (h, w) = job.working_size();
    let name = spec.name();
    println!(
        "  {name}: {w}x{h}, K = {}, {} levels x {} sweeps, {} schedule, {}; estimated peak {:.2} GiB",
        spec.steps,
        spec.levels,
        spec.sweeps,
        spec.schedule,
        spec.backend,
        job.estimated_peak_bytes() as f64 / f64::from(1u32 << 30)
    );
    let out = work.join(&name);
    // The study's own folder: a previous morph of the same name is replaced.
    let folder = job.output_folder(&out, true)?;
    let result = job.run(&mut LevelLog, &AtomicBool::new(false))?;
    ensure!(result.completed(), "{name} stopped early");
    let (mut metrics, out) = result.write(&job, folder)?;
    if spec.pair == "motorcycle" {
        let truth_path = data.join("images/pairs/motorcycle/disparity_a.png");
        let truth = Correspondence::load(&truth_path)?;
        let folder = MorphFolder::read(&out, &job.config().backend.device_for(Precision::F32)?)?;
        let scored = folder.metrics(folder.composed(), Some((&truth, "disparity_a.png")))?;
        metrics.endpoint_error = scored.endpoint_error;
        metrics.truth = scored.truth;
    }
    let record = RunRecord {
        spec: spec.clone(),
        size: [h, w],
        solver_seconds: result.seconds,
        process_seconds: started.elapsed().as_secs_f64(),
        peak_bytes: peak_resident_bytes().context("no VmHWM in /proc/self/status")?,
        sweeps: metrics.levels.iter().map(|l| l.sweeps).collect(),
        metrics,
        machine: machine(),
        finished: utc_now(),
    };
    let path = work.join(format!("{name}.json"));
    std::fs::write(&path, serde_json::to_vec_pretty(&record)?)
        .with_context(|| format!("cannot write {}", path.display()))?;
    println!(
        "  {name}: {:.0} s, peak {:.0} MiB",
        record.process_seconds,
        record.peak_bytes as f64 / f64::from(1u32 << 20)
    );
    Ok(())
}

/// Prints a line at the end of each level.
struct LevelLog;

impl Observer for LevelLog {
    fn sweep(&mut self, event: &SweepEvent<'_>) {
        if event.phase == Phase::Joint && event.stop.is_some() {
            println!(
                "    level {}/{} ({}x{}): {} sweeps, E = {:.6e}, {:.0} s",
                event.level + 1,
                event.levels,
                event.grid.width(),
                event.grid.height(),
                event.sweep,
                event.energy,
                event.seconds
            );
        }
    }
}

/// The CPU model and the cores this process may use.
fn machine() -> String {
    let model = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|c| {
            c.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    format!("{model}, {cores} cores")
}

/// `YYYY-MM-DD` of the system clock, UTC.
fn utc_now() -> String {
    let days = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs() / 86_400) as i64;
    let (year, month, day) = civil_date(days);
    format!("{year:04}-{month:02}-{day:02}")
}

/// The proleptic Gregorian date of `days` since 1970-01-01 (Howard Hinnant's algorithm).
fn civil_date(days: i64) -> (i64, i64, i64) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    (year, month, day)
}

/// The contact sheet of a morph: five frames (`k = 0, K/4, K/2, 3K/4, K`) with the zoomed
/// region outlined, and under each the region magnified ×4 (nearest neighbour, so the
/// pixels of the working size are seen as they are).
///
/// The region is [`most_structured_window`] of `u_0` and `u_K`: the same for every model of
/// a pair at one size.
fn sheet(dir: &Path, steps: usize) -> Result<RgbImage> {
    let digits = if steps >= 100 { 3 } else { 2 };
    let frame = |k: usize| -> Result<RgbImage> {
        let path = dir.join(format!("frame_{k:0digits$}.png"));
        Ok(image::open(&path)
            .with_context(|| format!("cannot read {}", path.display()))?
            .to_rgb8())
    };
    let (first, last) = (frame(0)?, frame(steps)?);
    let (w, h) = first.dimensions();
    if w < ZOOM_REGION || h < ZOOM_REGION {
        bail!("{}: frames smaller than the zoom region", dir.display());
    }
    let (zx, zy) = most_structured_window(&first, &last);
    let scale = f64::from(THUMB) / f64::from(w.max(h));
    let (tw, th) = (
        ((f64::from(w) * scale).round() as u32).max(1),
        ((f64::from(h) * scale).round() as u32).max(1),
    );
    let gap = 4;
    let cols = SHEET_FRAMES as u32;
    let mut out = RgbImage::from_pixel(
        cols * THUMB + (cols - 1) * gap,
        th + gap + THUMB,
        Rgb([255, 255, 255]),
    );
    for i in 0..SHEET_FRAMES {
        let k = (i * steps + (SHEET_FRAMES - 1) / 2) / (SHEET_FRAMES - 1);
        let full = frame(k)?;
        let mut thumb = imageops::resize(&full, tw, th, imageops::FilterType::Triangle);
        let rect = |v: u32| (f64::from(v) * scale).round() as u32;
        outline(
            &mut thumb,
            (rect(zx), rect(zy)),
            (
                rect(zx + ZOOM_REGION).min(tw - 1),
                rect(zy + ZOOM_REGION).min(th - 1),
            ),
        );
        let x0 = i as u32 * (THUMB + gap);
        imageops::replace(&mut out, &thumb, i64::from(x0), 0);
        let region = imageops::crop_imm(&full, zx, zy, ZOOM_REGION, ZOOM_REGION).to_image();
        let zoom = imageops::resize(&region, THUMB, THUMB, imageops::FilterType::Nearest);
        imageops::replace(&mut out, &zoom, i64::from(x0), i64::from(th + gap));
    }
    Ok(out)
}

/// The step whose anisotropy and displacement a ξ₁ study shows: `k = 12` of `K = 15` (the
/// paper's Figure of `ξ₁ = 200`), scaled to other `K`.
fn field_step(steps: usize) -> usize {
    ((12 * steps + 7) / 15).clamp(1, steps)
}

/// The anisotropy weight `a_k` (grey, `0` black to `1 + ξ₂` white) and the displacement
/// `φ_k − Id` (colour-coded, the wheel's rim the largest displacement of the run) of step
/// [`field_step`], side by side with the colour wheel, `width` wide: cut from the
/// `sheet.png` the CLI writes into every morph's folder (rows 2 and 3, column `k`), so the
/// study shows what a user's own morph shows.
fn field_row(dir: &Path, steps: usize, width: u32) -> Result<RgbImage> {
    let path = dir.join("sheet.png");
    let cli_sheet = image::open(&path)
        .with_context(|| format!("cannot read {}", path.display()))?
        .to_rgb8();
    let first = dir.join(if steps >= 100 {
        "frame_000.png"
    } else {
        "frame_00.png"
    });
    let (w, h) = image::image_dimensions(&first)
        .with_context(|| format!("cannot read {}", first.display()))?;
    let gap = 4;
    let expected = ((steps as u32 + 1) * w + steps as u32 * gap, 3 * h + 2 * gap);
    ensure!(
        cli_sheet.dimensions() == expected,
        "{}: {:?}, expected {expected:?} for K = {steps} frames of {w}x{h}",
        path.display(),
        cli_sheet.dimensions()
    );
    let k = field_step(steps) as u32;
    let cut = |col: u32, row: u32, cw: u32, ch: u32| {
        imageops::crop_imm(&cli_sheet, col * (w + gap), row * (h + gap), cw, ch).to_image()
    };
    // Two panels as wide as two thumbnails each, the wheel as one.
    let panel = 2 * THUMB + gap;
    let scale = f64::from(panel) / f64::from(w.max(h));
    let (pw, ph) = (
        ((f64::from(w) * scale).round() as u32).max(1),
        ((f64::from(h) * scale).round() as u32).max(1),
    );
    let side = h.min(w);
    let mut out = RgbImage::from_pixel(width, ph, Rgb([255, 255, 255]));
    let panels = [
        imageops::resize(&cut(k, 1, w, h), pw, ph, imageops::FilterType::Triangle),
        imageops::resize(&cut(k, 2, w, h), pw, ph, imageops::FilterType::Triangle),
        imageops::resize(
            &cut(0, 2, side, side),
            THUMB.min(ph),
            THUMB.min(ph),
            imageops::FilterType::Triangle,
        ),
    ];
    let mut x = 0;
    for p in &panels {
        imageops::replace(&mut out, p, i64::from(x), 0);
        x += p.width() + gap;
    }
    Ok(out)
}

/// `top` above `bottom`, a white gap between, as wide as the wider.
fn below(top: &RgbImage, bottom: &RgbImage) -> RgbImage {
    let gap = 4;
    let mut out = RgbImage::from_pixel(
        top.width().max(bottom.width()),
        top.height() + gap + bottom.height(),
        Rgb([255, 255, 255]),
    );
    imageops::replace(&mut out, top, 0, 0);
    imageops::replace(&mut out, bottom, 0, i64::from(top.height() + gap));
    out
}

/// Top-left corner of the `ZOOM_REGION²` window (stride 4) with the most structure in both
/// `a` and `b`: the largest product of the two images' summed gradient magnitudes (grey
/// level, forward differences) over the window; the first such window on ties. Where both
/// endpoints have edges, a cross-fade shows two sets of them and a transport one.
fn most_structured_window(a: &RgbImage, b: &RgbImage) -> (u32, u32) {
    let (w, h) = a.dimensions();
    let gradient = |img: &RgbImage| -> Vec<f64> {
        let grey = |x: u32, y: u32| -> f64 {
            img.get_pixel(x, y)
                .0
                .iter()
                .map(|&v| f64::from(v))
                .sum::<f64>()
                / 3.0
        };
        (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| {
                let dx = if x + 1 < w {
                    grey(x + 1, y) - grey(x, y)
                } else {
                    0.0
                };
                let dy = if y + 1 < h {
                    grey(x, y + 1) - grey(x, y)
                } else {
                    0.0
                };
                dx.abs() + dy.abs()
            })
            .collect()
    };
    let (ga, gb) = (gradient(a), gradient(b));
    let window = |g: &[f64], x: u32, y: u32| -> f64 {
        (y..y + ZOOM_REGION)
            .map(|yy| {
                let row = (yy * w) as usize;
                g[row + x as usize..row + (x + ZOOM_REGION) as usize]
                    .iter()
                    .sum::<f64>()
            })
            .sum()
    };
    let mut best = (f64::NEG_INFINITY, (0, 0));
    for y in (0..=h - ZOOM_REGION).step_by(4) {
        for x in (0..=w - ZOOM_REGION).step_by(4) {
            let score = window(&ga, x, y) * window(&gb, x, y);
            if score > best.0 {
                best = (score, (x, y));
            }
        }
    }
    best.1
}

/// A one-pixel yellow rectangle from `(x0, y0)` to `(x1, y1)`, inclusive.
fn outline(img: &mut RgbImage, (x0, y0): (u32, u32), (x1, y1): (u32, u32)) {
    let yellow = Rgb([255, 220, 0]);
    for x in x0..=x1 {
        img.put_pixel(x, y0, yellow);
        img.put_pixel(x, y1, yellow);
    }
    for y in y0..=y1 {
        img.put_pixel(x0, y, yellow);
        img.put_pixel(x1, y, yellow);
    }
}

/// The study's key: `main` or the varied parameter, the size, and a schedule or backend
/// other than the default.
fn study_key(args: &Args) -> String {
    let mut key = match &args.vary {
        Some(text) => text.split('=').next().unwrap_or("vary").to_string(),
        None => "main".to_string(),
    };
    write!(key, "-{}", args.size).unwrap();
    if args.schedule != Schedule::Sequential {
        write!(key, "-{}", value_name(args.schedule)).unwrap();
    }
    if args.backend != Backend::Flex {
        write!(key, "-{}", args.backend).unwrap();
    }
    key
}

/// The markdown table of the records, then their sheets.
fn table(records: &[RunRecord], key: &str) -> String {
    let mut t = String::new();
    let vary = records
        .iter()
        .find_map(|r| r.spec.vary.as_ref().map(|v| v.0.clone()));
    writeln!(
        t,
        "<!-- generated by `cargo run --release --example results` ({key}); do not edit -->\n"
    )
    .unwrap();
    write!(t, "| pair | model |").unwrap();
    if let Some(param) = &vary {
        write!(t, " {param} |").unwrap();
    }
    writeln!(
        t,
        " size | sweeps per level | data share | min det J of φ_k | det J of Φ | folded | mean / max of Φ−Id, px | path rel. std | feature path rel. std | EPE mean / median, px | time | peak |"
    )
    .unwrap();
    let columns = 14 + usize::from(vary.is_some());
    writeln!(t, "|{}", "---|".repeat(columns)).unwrap();
    for r in records {
        let m = &r.metrics;
        let finest = m.levels.last();
        let min_step = m
            .deformations
            .iter()
            .map(|d| d.min_det)
            .fold(f64::INFINITY, f64::min);
        write!(t, "| {} | {} |", r.spec.pair, r.spec.model).unwrap();
        if vary.is_some() {
            let value = r
                .spec
                .vary
                .as_ref()
                .map_or(String::new(), |v| v.1.to_string());
            write!(t, " {value} |").unwrap();
        }
        let epe = m.endpoint_error.as_ref().map_or("".into(), |e| {
            format!(
                "{:.2} / {:.2} (identity {:.2})",
                e.mean, e.median, e.identity_mean
            )
        });
        writeln!(
            t,
            " {}×{} | {} | {} | {:.2} | {:.2} – {:.2} | {} | {:.2} / {:.1} | {:.3} | {} | {} | {} | {:.0} MiB |",
            r.size[1],
            r.size[0],
            r.sweeps
                .iter()
                .map(ToString::to_string)
                .collect::<Vec<_>>()
                .join(" "),
            finest.map_or("".into(), |l| format!("{:.0} %", 100.0 * l.data_share)),
            min_step,
            m.composed.min_det,
            m.composed.max_det,
            share(m.composed.folded_share),
            m.composed_displacement.mean,
            m.composed_displacement.max,
            m.path.morph.relative_std,
            m.feature_path
                .as_ref()
                .map_or("".into(), |p| format!("{:.3}", p.morph.relative_std)),
            epe,
            minutes(r.process_seconds),
            r.peak_bytes as f64 / f64::from(1u32 << 20),
        )
        .unwrap();
    }
    let machines: std::collections::BTreeSet<_> =
        records.iter().map(|r| r.machine.as_str()).collect();
    let dates: std::collections::BTreeSet<_> =
        records.iter().map(|r| r.finished.as_str()).collect();
    writeln!(
        t,
        "\nMeasured on {} ({}); time = the whole process (reading, VGG19, solver, writing); \
         peak = its `VmHWM`.\n",
        machines.into_iter().collect::<Vec<_>>().join("; "),
        dates.into_iter().collect::<Vec<_>>().join(", ")
    )
    .unwrap();
    for r in records {
        let name = r.spec.name();
        let label = match &r.spec.vary {
            Some((p, v)) if p == "xi1" => format!(
                "{}, {} model, {p} = {v}; below: anisotropy a and displacement φ_k − Id of step k = {}, colour wheel",
                r.spec.pair,
                r.spec.model,
                field_step(r.spec.steps)
            ),
            Some((p, v)) => format!("{}, {} model, {p} = {v}", r.spec.pair, r.spec.model),
            None => format!("{}, {} model", r.spec.pair, r.spec.model),
        };
        writeln!(t, "![{label}](results/{name}.jpg)  \n*{label}*\n").unwrap();
    }
    t
}

/// A share as a percentage (`0` when none, scientific below 0.01 %: a few pixels).
fn share(x: f64) -> String {
    if x == 0.0 {
        "0".into()
    } else if x < 1e-4 {
        format!("{x:.1e}")
    } else {
        format!("{:.2} %", 100.0 * x)
    }
}

/// `12 min 05 s` or `48 s`.
fn minutes(seconds: f64) -> String {
    let s = seconds.round() as u64;
    if s < 60 {
        format!("{s} s")
    } else {
        format!("{} min {:02} s", s / 60, s % 60)
    }
}

/// Replaces the text between `<!-- results:KEY -->` and `<!-- /results:KEY -->` in `doc`
/// (appending the section when absent, creating the file when missing); written beside and
/// renamed, so an interrupted write leaves the old document.
fn update_doc(doc: &Path, key: &str, table: &str) -> Result<()> {
    let (open, close) = (
        format!("<!-- results:{key} -->"),
        format!("<!-- /results:{key} -->"),
    );
    let text = std::fs::read_to_string(doc).unwrap_or_else(|_| "# Results\n".into());
    let updated = match (text.find(&open), text.find(&close)) {
        (Some(start), Some(end)) if end > start => {
            format!("{}{open}\n{table}{}", &text[..start], &text[end..])
        }
        (None, None) => format!(
            "{}\n{open}\n{table}{close}\n",
            text.trim_end_matches('\n').to_owned() + "\n"
        ),
        _ => bail!("{}: unmatched markers for {key}", doc.display()),
    };
    let tmp = doc.with_extension("md.tmp");
    std::fs::write(&tmp, updated).with_context(|| format!("cannot write {}", tmp.display()))?;
    std::fs::rename(&tmp, doc).with_context(|| format!("cannot replace {}", doc.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn civil_dates() {
        assert_eq!(civil_date(0), (1970, 1, 1));
        assert_eq!(civil_date(59), (1970, 3, 1));
        assert_eq!(civil_date(11_016), (2000, 2, 29));
        assert_eq!(civil_date(20_790), (2026, 12, 3));
    }

    #[test]
    fn a_section_is_replaced_appended_or_refused() {
        let dir = std::env::temp_dir().join(format!("deepmorph-results-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let doc = dir.join("results.md");
        std::fs::write(
            &doc,
            "# R\nbefore\n<!-- results:a -->\nold\n<!-- /results:a -->\nafter\n",
        )
        .unwrap();
        update_doc(&doc, "a", "new\n").unwrap();
        update_doc(&doc, "b", "other\n").unwrap();
        assert_eq!(
            std::fs::read_to_string(&doc).unwrap(),
            "# R\nbefore\n<!-- results:a -->\nnew\n<!-- /results:a -->\nafter\n\n\
             <!-- results:b -->\nother\n<!-- /results:b -->\n"
        );
        std::fs::write(&doc, "<!-- results:a -->\n").unwrap();
        assert!(update_doc(&doc, "a", "x").is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn the_zoom_region_has_edges_in_both_images() {
        // Flat images, except a square edge in both at (64, 32) and one in `a` only.
        let mut a = RgbImage::from_pixel(128, 96, Rgb([100, 100, 100]));
        let mut b = a.clone();
        for y in 40..60 {
            for x in 70..90 {
                a.put_pixel(x, y, Rgb([250, 250, 250]));
                b.put_pixel(x + 2, y, Rgb([0, 0, 0]));
            }
        }
        for y in 0..20 {
            for x in 0..20 {
                a.put_pixel(x, y, Rgb([0, 0, 0]));
            }
        }
        let (x, y) = most_structured_window(&a, &b);
        assert!(
            (44..=72).contains(&x) && (12..=44).contains(&y),
            "({x}, {y})"
        );
    }

    #[test]
    fn the_field_row_cuts_step_k_from_the_cli_sheet() {
        let dir = std::env::temp_dir().join(format!("deepmorph-fields-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (steps, w, h, gap) = (15u32, 20u32, 10u32, 4u32);
        // Each cell of the CLI's sheet coloured by (column, row); the gaps white.
        let cli = RgbImage::from_fn((steps + 1) * w + steps * gap, 3 * h + 2 * gap, |x, y| {
            let (col, row) = (x / (w + gap), y / (h + gap));
            if x % (w + gap) >= w || y % (h + gap) >= h {
                Rgb([255, 255, 255])
            } else {
                Rgb([col as u8 * 10, row as u8 * 100, 7])
            }
        });
        cli.save(dir.join("sheet.png")).unwrap();
        RgbImage::new(w, h).save(dir.join("frame_00.png")).unwrap();
        let row = field_row(&dir, steps as usize, 600).unwrap();
        let panel = 2 * THUMB + 4;
        assert_eq!(row.dimensions(), (600, panel * h / w));
        let centre = |x0: u32, side: u32| *row.get_pixel(x0 + side / 2, row.height() / 3);
        assert_eq!(
            centre(0, panel),
            Rgb([120, 100, 7]),
            "anisotropy of step 12"
        );
        assert_eq!(
            centre(panel + 4, panel),
            Rgb([120, 200, 7]),
            "displacement of step 12"
        );
        assert_eq!(centre(2 * (panel + 4), h), Rgb([0, 200, 7]), "the wheel");
        assert_eq!((field_step(5), field_step(30)), (4, 24));
        // A sheet of another K is refused, not cut at the wrong place.
        assert!(field_row(&dir, 14, 600).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn names_and_plans() {
        let args = Args::parse_from([
            "results",
            "--size",
            "128",
            "--pairs",
            "faces",
            "--vary",
            "tau=0.1,0.2",
        ]);
        let runs = plan(&args).unwrap();
        // τ is the deep model's: the RGB model runs no τ study.
        let names: Vec<_> = runs.iter().map(RunSpec::name).collect();
        assert_eq!(names, ["faces_deep_128_tau0.1", "faces_deep_128_tau0.2"]);
        let bad = Args::parse_from(["results", "--pairs", "faces", "--vary", "sigma=1"]);
        assert!(plan(&bad).is_err());
        assert_eq!(minutes(48.4), "48 s");
        assert_eq!(minutes(725.0), "12 min 05 s");
        assert_eq!(share(0.0), "0");
        assert_eq!(share(2.2e-5), "2.2e-5");
        assert_eq!(share(0.0011), "0.11 %");
    }
}
