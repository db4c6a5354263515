//! Morphing through more than two images: each consecutive pair is one morph, all at one
//! working size (the first image's, as `--size`/`--max-side` resolve it), each written to
//! its own subfolder `segment_01`, `segment_02`, … exactly as `deepmorph morph` writes a
//! morph, and the whole chain as one continuous animation beside them (`morph.mp4`,
//! `morph.apng`, `morph.gif`: segment 1's frames, then each later segment's without its
//! first, which is the previous segment's last). Landmarks go to the segment they name
//! ([`split_by_segment`]); `--align` estimates each segment's own map.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Mutex, PoisonError};

use image::RgbImage as Rgb8;

use crate::app::config::{Inputs, MorphConfig, WorkingSize};
use crate::app::job::{MorphJob, MorphResult};
use crate::app::memory;
use crate::error::{Error, Result};
use crate::eval::metrics::Metrics;
use crate::io::animation::VideoFormat;
use crate::io::output_folder::{OutputFolder, mark_as_output};
use crate::io::outputs::{is_morph_output, written_name};
use crate::io::points::{PointPair, split_by_segment};
use crate::model::inbetween::MAX_FRAMES;
use crate::solver::observer::{Observer, Termination};

/// The most images a chain takes (a bound on the work a typo can start).
pub const MAX_IMAGES: usize = 100;

/// The subfolder of segment `i` (0-based) of a chain: `segment_01`, … (wider past 99).
pub fn segment_name(i: usize, segments: usize) -> String {
    let digits = segments.to_string().len().max(2);
    format!("segment_{:0digits$}", i + 1)
}

/// Whether `name` is something a chain writes into its output folder: a segment subfolder
/// (`segment_NN/`) and the morph files in it (`segment_NN/frame_00.png`), or the chain's
/// animations (and their temporary files).
pub fn is_chain_output(name: &str) -> bool {
    match name.split_once('/') {
        Some((dir, rest)) => {
            let segment = dir
                .strip_prefix("segment_")
                .is_some_and(|n| n.len() >= 2 && n.bytes().all(|b| b.is_ascii_digit()));
            segment && (rest.is_empty() || is_morph_output(rest))
        }
        None => {
            let name = written_name(name);
            VideoFormat::ALL.iter().any(|f| f.file_name() == name)
        }
    }
}

/// A chain ready to run: one prepared morph per consecutive pair of images.
#[derive(Clone, Debug)]
pub struct ChainJob {
    segments: Vec<MorphJob>,
    images: Vec<PathBuf>,
}

/// How a chain ended.
#[derive(Debug)]
pub struct ChainOutcome {
    /// Each segment that ran: its result's termination and metrics.
    pub segments: Vec<(Termination, Metrics)>,
    /// Where the chain was written.
    pub folder: PathBuf,
    /// Whether the chain's own animation was written (every segment completed at the
    /// working size).
    pub animation: bool,
}

impl ChainOutcome {
    /// One line for a person after the run of a chain of `count` segments.
    pub fn summary(&self, count: usize) -> String {
        format!(
            "chain of {count} segments: {} run, {}; wrote them to {}{}",
            self.segments.len(),
            self.segments
                .last()
                .map_or("none".into(), |(t, _)| t.to_string()),
            self.folder.display(),
            if self.animation {
                ", with the whole chain's animations"
            } else {
                " (no chain animation: not every segment completed)"
            }
        )
    }
}

impl ChainJob {
    /// Checks `config`, reads the images, resolves the working size from the first and
    /// prepares every segment at that size (refusing what would not fit in memory), each
    /// with the landmark pairs that name it.
    ///
    /// # Errors
    ///
    /// Fewer than 3 or more than [`MAX_IMAGES`] images, a landmark pair of no segment or of
    /// one the images do not give, or what [`MorphJob::prepare`] refuses.
    pub fn prepare(config: MorphConfig, images: Vec<PathBuf>) -> Result<Self> {
        if !(3..=MAX_IMAGES).contains(&images.len()) {
            return Err(Error::invalid(
                "images",
                images.len(),
                format!("3 to {MAX_IMAGES} for a chain (two images are one morph)"),
            ));
        }
        let mut config = config;
        let count = images.len() - 1;
        config.animation_frames =
            segment_frames(config.animation_frames, count, config.solver.steps)?;
        let mut per_segment = match &config.points {
            Some(points) => split_by_segment(points, images.len() - 1)?,
            None => vec![None; images.len() - 1],
        };
        let pair = |config: MorphConfig, i: usize| {
            MorphJob::prepare(
                config,
                Inputs::Files {
                    a: images[i].clone(),
                    b: images[i + 1].clone(),
                },
            )
        };
        let with_points = |config: &MorphConfig, points: &mut Option<Vec<PointPair>>| {
            let mut config = config.clone();
            config.points = points.take();
            config
        };
        let first = pair(with_points(&config, &mut per_segment[0]), 0)?;
        let (height, width) = first.working_size();
        let mut exact = config;
        exact.size = WorkingSize::Exact { height, width };
        let mut segments = vec![first];
        for (i, points) in per_segment.iter_mut().enumerate().skip(1) {
            segments.push(pair(with_points(&exact, points), i)?);
        }
        // The segments run one at a time, but the chain holds every segment's images and
        // the whole animation's frames until it is written.
        let steps = exact.solver.steps;
        let frames = count * (exact.animation_frames.unwrap_or(steps + 1) - 1) + 1;
        let pixels = height * width;
        let held = frames * pixels * 3 + count * 2 * pixels * 3 * size_of::<f32>();
        let largest = segments.iter().map(MorphJob::estimated_peak_bytes).max();
        memory::check_bytes(
            largest.unwrap_or(0) + held as u64,
            &format!(
                "a chain of {count} segments, {width}x{height}, K = {steps}, {frames} animation \
                 frames"
            ),
            exact.max_memory_gib,
            exact.backend != crate::Backend::Wgpu,
        )?;
        Ok(Self { segments, images })
    }

    /// The segments' jobs, in order.
    pub fn segments(&self) -> &[MorphJob] {
        &self.segments
    }

    /// Each segment estimates its time before it runs, as [`MorphJob::estimate_time`].
    pub fn estimate_time(mut self, yes: bool) -> Self {
        self.segments = self
            .segments
            .into_iter()
            .map(|s| s.estimate_time(yes))
            .collect();
        self
    }

    /// Begins the output folder `dir` for the chain (see [`OutputFolder::begin`]).
    ///
    /// # Errors
    ///
    /// As [`MorphJob::output_folder`].
    pub fn output_folder(&self, dir: &Path, force: bool) -> Result<OutputFolder> {
        let inputs: Vec<&Path> = self.images.iter().map(PathBuf::as_path).collect();
        OutputFolder::begin(dir, &inputs, is_chain_output, force)
    }

    /// Runs the segments in order into `folder` and moves it into place. `start(i)` is called
    /// before segment `i` (to announce it); `observer` sees every sweep; `writing` is held
    /// while files are written (a signal handler must not remove the staging folder under
    /// the writer). A segment stopped by `interrupt` or a non-finite value is written as a
    /// lone morph would be, and the chain stops there; its animation is then written only if
    /// every segment completed.
    ///
    /// # Errors
    ///
    /// A segment fails to run or a file cannot be written (the folder is then left as it
    /// was before the run).
    pub fn run(
        &self,
        folder: OutputFolder,
        observer: &mut dyn Observer,
        interrupt: &AtomicBool,
        mut start: impl FnMut(usize, &MorphJob),
        writing: &Mutex<()>,
    ) -> Result<ChainOutcome> {
        let lock = || writing.lock().unwrap_or_else(PoisonError::into_inner);
        let count = self.segments.len();
        let mut outcomes = Vec::with_capacity(count);
        let mut frames: Vec<Rgb8> = Vec::new();
        let mut complete = true;
        for (i, job) in self.segments.iter().enumerate() {
            start(i, job);
            let result: MorphResult = job.run(observer, interrupt)?;
            let dir = folder.path().join(segment_name(i, count));
            std::fs::create_dir(&dir).map_err(|cause| Error::Io {
                path: dir.clone(),
                cause,
            })?;
            mark_as_output(&dir)?;
            let guard = lock();
            let metrics = result.write_files(job, &dir)?;
            let animation = result.animation(job)?;
            drop(guard);
            let completed = result.completed();
            frames.extend(animation.into_iter().skip(usize::from(i > 0)));
            outcomes.push((result.morph.termination.clone(), metrics));
            if !completed || interrupt.load(Ordering::Relaxed) {
                complete = completed && i + 1 == count;
                break;
            }
        }
        let guard = lock();
        if complete {
            self.segments[0]
                .config()
                .playback()
                .write(folder.path(), &frames)?;
        }
        let path = folder.commit()?;
        drop(guard);
        Ok(ChainOutcome {
            segments: outcomes,
            folder: path,
            animation: complete,
        })
    }
}

/// Each segment's frame count for a chain whose animation should hold `total` frames
/// (`--frames`: the whole animation's, as for one morph), `None` for the computed ones.
/// The animation then holds `count · (n − 1) + 1 ≤ total` frames.
///
/// # Errors
///
/// A `total` below the frames the model computes (`count · K + 1`) or above
/// [`MAX_FRAMES`] (issue 43 #12: `--frames 600` gave each of 99 segments 600 frames).
fn segment_frames(total: Option<usize>, count: usize, steps: usize) -> Result<Option<usize>> {
    let Some(total) = total else {
        return Ok(None);
    };
    let computed = count * steps + 1;
    let most = MAX_FRAMES.max(computed);
    if !(computed..=most).contains(&total) {
        return Err(Error::invalid(
            "frames",
            total,
            format!(
                "for a chain of {count} segments with K = {steps}: at least {computed} (the \
                 frames the model computes) and at most {most}"
            ),
        ));
    }
    let each = (total - 1) / count + 1;
    Ok((each > steps + 1).then_some(each))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_chains_frames_are_its_whole_animations() {
        // 99 segments of K = 15 compute 1486 frames: no more may be asked for.
        assert_eq!(segment_frames(None, 99, 15).unwrap(), None);
        let err = segment_frames(Some(600), 99, 15).unwrap_err().to_string();
        assert!(err.contains("at least 1486"), "{err}");
        assert_eq!(segment_frames(Some(1486), 99, 15).unwrap(), None);
        // 3 segments of K = 10 and 600 frames: 200 each, 3 · 199 + 1 = 598 in all.
        assert_eq!(segment_frames(Some(600), 3, 10).unwrap(), Some(200));
        let err = segment_frames(Some(601), 3, 10).unwrap_err().to_string();
        assert!(err.contains("at most 600"), "{err}");
    }

    #[test]
    fn chain_folders_hold_segments_and_animations_only() {
        assert_eq!(segment_name(0, 3), "segment_01");
        assert_eq!(segment_name(104, 150), "segment_105");
        for name in [
            "segment_01/",
            "segment_01/frame_00.png",
            "segment_12/config.json",
            "morph.mp4",
            ".morph.apng.tmp-77",
        ] {
            assert!(is_chain_output(name), "{name}");
        }
        for name in [
            "segment_1/",
            "segment_01/notes.txt",
            "segment_01/sub/",
            "frame_00.png",
            "other/",
        ] {
            assert!(!is_chain_output(name), "{name}");
        }
    }
}
