//! Everything a morph is run with, as one serialisable record: the solver's and the model's
//! settings (each defined beside the code it configures), the working size, the backend and
//! the outputs. `config.json` is this record plus the inputs, the version and the outcome
//! ([`RunRecord`]), so a finished morph can be run again from its folder.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::backend::Backend;
use crate::error::{Error, Result};
use crate::io::animation::{DEFAULT_QUALITY, Playback, VideoFormat};
use crate::io::points::PointPair;
use crate::model::alignment::{AlignKind, MapSummary};
use crate::model::feature_model::DeepConfig;
use crate::model::params::EnergyParams;
use crate::solver::multilevel::MultilevelConfig;

/// Which model compares the frames (SPEC §4).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Model {
    /// Images compared by colour.
    Rgb,
    /// Images compared by VGG19 features (needs the weights).
    Deep,
}

/// A named set of the settings that trade time for quality (`--quality`): the working size,
/// levels, sweeps per level, the deep model's feature-only sweeps and the tolerance. Flags
/// given beside it override its values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "cli", derive(clap::ValueEnum))]
pub enum Quality {
    /// A quick look: at most 128 px, 3 levels × 60 sweeps, 15 feature-only sweeps, tolerance
    /// 1e-3.
    Draft,
    /// The defaults: at most 256 px, 5 levels × 250 sweeps, 50 feature-only sweeps,
    /// tolerance 1e-4.
    Standard,
    /// The paper's setting (SPEC §9) at 512 px: 5 levels × 250 sweeps, 50 feature-only
    /// sweeps, every sweep run (no tolerance).
    Paper,
}

impl Quality {
    /// `(longest side, levels, sweeps, feature-only sweeps, tolerance)`.
    fn settings(self) -> (usize, usize, usize, usize, f64) {
        match self {
            Quality::Draft => (128, 3, 60, 15, 1e-3),
            Quality::Standard => (256, 5, 250, 50, 1e-4),
            Quality::Paper => (512, 5, 250, 50, 0.0),
        }
    }

    /// Sets this preset's values in `config` (the deep model's only if it is the deep model).
    pub fn apply(self, config: &mut MorphConfig) {
        let (max_side, levels, sweeps, pre_sweeps, tolerance) = self.settings();
        config.size = WorkingSize::Fit { max_side };
        config.solver.levels = levels;
        config.solver.sweeps = sweeps;
        config.solver.tolerance = tolerance;
        if let Some(deep) = &mut config.deep {
            deep.features.pre_sweeps = pre_sweeps;
        }
    }
}

/// The deep model's settings: the weights file and the feature settings.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DeepModel {
    /// VGG19 weights: ONNX (torchvision export, ONNX model zoo) or safetensors with
    /// torchvision key names.
    pub vgg19: PathBuf,
    /// `η`, `τ`, `J_pre`.
    #[serde(flatten)]
    pub features: DeepConfig,
}

/// The size the inputs are brought to before the pyramid is built (SPEC §7: outside the
/// model). Both sides must be multiples of `2^(levels−1)`, and of 16 in the deep model
/// (VGG19's four max-pools halve exactly).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum WorkingSize {
    /// A's size scaled (never up) so its longer side is at most `max_side`, each side then
    /// rounded to the nearest allowed multiple.
    Fit {
        /// The longest side in pixels.
        max_side: usize,
    },
    /// Exactly this size.
    Exact {
        /// Rows.
        height: usize,
        /// Columns.
        width: usize,
    },
}

pub use crate::model::grid::MAX_SIDE;

impl WorkingSize {
    /// The working size for an input of `height × width` whose sides must be multiples of
    /// `multiple`.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] if an exact size does not fit the pyramid, a side is above
    /// [`MAX_SIDE`], or `max_side` is below four multiples.
    pub fn resolve(&self, height: usize, width: usize, multiple: usize) -> Result<(usize, usize)> {
        match *self {
            WorkingSize::Exact { height, width } => {
                for (name, side) in [("height", height), ("width", width)] {
                    if side % multiple != 0 || side < 4 * multiple || side > MAX_SIDE {
                        return Err(Error::invalid(
                            "size",
                            format!("{width}x{height}"),
                            format!(
                                "WxH with both sides multiples of {multiple} (2^(levels-1), and \
                                 16 for the deep model), at least {} and at most {MAX_SIDE}; \
                                 the {name} is not",
                                4 * multiple
                            ),
                        ));
                    }
                }
                Ok((height, width))
            }
            WorkingSize::Fit { max_side } => {
                if max_side < 4 * multiple || max_side > MAX_SIDE {
                    return Err(Error::invalid(
                        "max-side",
                        max_side,
                        format!(
                            "at least {} (4 multiples of 2^(levels-1), and of 16 for the deep \
                             model) and at most {MAX_SIDE}",
                            4 * multiple
                        ),
                    ));
                }
                let scale = (max_side as f64 / height.max(width) as f64).min(1.0);
                let round = |v: usize| {
                    ((v as f64 * scale / multiple as f64).round() as usize).max(4) * multiple
                };
                Ok((round(height), round(width)))
            }
        }
    }
}

/// A whole morph's settings. [`Default`] is SPEC §9's RGB column at a working size of at
/// most 256 px; [`MorphConfig::deep`] the deep column; [`MorphConfig::demo`] the demo.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MorphConfig {
    /// `K`, levels, `J`, the energy's parameters and iPALM's settings.
    pub solver: MultilevelConfig,
    /// The deep model's settings; `None` is the RGB model.
    pub deep: Option<DeepModel>,
    /// The size the inputs are brought to.
    pub size: WorkingSize,
    /// The compute backend.
    pub backend: Backend,
    /// Whether the animations play forward and back.
    pub pingpong: bool,
    /// Which animations are written (`--video`); runs recorded before it existed wrote the
    /// GIF and APNG and read back as every format this build has.
    #[serde(default = "VideoFormat::defaults")]
    pub video: Vec<VideoFormat>,
    /// Frames per second of the animations; `None`: each lasts
    /// [`crate::io::animation::DEFAULT_SECONDS`].
    #[serde(default)]
    pub fps: Option<f64>,
    /// The MP4's H.264 quantiser, 0 (best) to 51 (smallest) (`--crf`).
    #[serde(default = "default_quality")]
    pub crf: u8,
    /// Frames of the animations (GIF, APNG): `None` plays the `K + 1` computed frames, more
    /// adds frames between them ([`crate::model::inbetween`]).
    #[serde(default)]
    pub animation_frames: Option<usize>,
    /// A finished morph's folder to start from instead of the coarsest level (`--init`):
    /// its frames and deformations are prolongated to the first larger level.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub init: Option<PathBuf>,
    /// Refuse to start when the estimated peak memory exceeds this many GiB; `None`: the
    /// memory available now (CPU backends), no limit on wgpu.
    pub max_memory_gib: Option<f64>,
    /// SPEC §11's landmark pairs (`--points`), each point in its own input's pixels; `None`:
    /// the path finds its correspondences through the energy alone.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub points: Option<Vec<PointPair>>,
    /// SPEC §11's initial alignment (`--align`): the global map the coarsest level starts
    /// from, estimated from the landmarks when there are any, otherwise from the images.
    #[serde(default, skip_serializing_if = "AlignKind::is_none")]
    pub align: AlignKind,
}

/// How SPEC §11's global map `G` of a run was estimated, for `config.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AlignmentRecord {
    /// `similarity` or `affine`.
    pub kind: AlignKind,
    /// `landmarks` (least squares) or `images` (normalised cross-correlation on the coarsest
    /// level).
    pub source: String,
    /// `G` on the working grid in working pixels, `x` = column, `y` = row:
    /// `x' = m[0][0] x + m[0][1] y + m[0][2]`, `y' = m[1][0] x + m[1][1] y + m[1][2]`.
    pub matrix: [[f64; 3]; 2],
    /// Its parts: translation of the centre, rotation, scale, anisotropy.
    pub summary: MapSummary,
    /// From the images: the correlation reached and that of no alignment.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ncc: Option<[f64; 2]>,
}

impl AlignmentRecord {
    /// One line for a person: "initial alignment (similarity, from the images): shift
    /// (+12.0, -3.5) px, rotation +4.0°, scale 1.08; correlation 0.41 -> 0.83".
    pub fn describe(&self) -> String {
        let s = &self.summary;
        let mut line = format!(
            "initial alignment ({}, from the {}): shift ({:+.1}, {:+.1}) px, rotation \
             {:+.1} deg (counter-clockwise), scale {:.3}",
            self.kind.name(),
            self.source,
            s.translation[0],
            s.translation[1],
            s.rotation_degrees,
            s.scale
        );
        if self.kind == AlignKind::Affine {
            line.push_str(&format!(", anisotropy {:.3}", s.anisotropy));
        }
        if let Some([reached, identity]) = self.ncc {
            line.push_str(&format!("; correlation {identity:.3} -> {reached:.3}"));
        }
        line
    }
}

impl Default for MorphConfig {
    fn default() -> Self {
        Self {
            solver: MultilevelConfig::default(),
            deep: None,
            size: WorkingSize::Fit { max_side: 256 },
            backend: Backend::default_compiled().unwrap_or(Backend::Flex),
            pingpong: false,
            video: VideoFormat::defaults(),
            fps: None,
            crf: DEFAULT_QUALITY,
            animation_frames: None,
            init: None,
            max_memory_gib: None,
            points: None,
            align: AlignKind::None,
        }
    }
}

fn default_quality() -> u8 {
    DEFAULT_QUALITY
}

impl MorphConfig {
    /// How the animations are written.
    pub fn playback(&self) -> Playback {
        Playback {
            formats: self.video.clone(),
            pingpong: self.pingpong,
            fps: self.fps,
            quality: self.crf,
        }
    }

    /// The deep model with SPEC §9's deep column and the weights in `vgg19`.
    pub fn deep(vgg19: impl Into<PathBuf>) -> Self {
        let mut config = Self::default();
        config.solver.params = EnergyParams::deep();
        config.deep = Some(DeepModel {
            vgg19: vgg19.into(),
            features: DeepConfig::default(),
        });
        config
    }

    /// The built-in demo: 96², K = 10, 3 levels × 60 sweeps, about a minute on 2 CPU cores.
    pub fn demo() -> Self {
        let mut config = Self::default();
        config.solver.steps = 10;
        config.solver.levels = 3;
        config.solver.sweeps = 60;
        config.size = WorkingSize::Exact {
            height: 96,
            width: 96,
        };
        config
    }

    /// Which model this is.
    pub fn model(&self) -> Model {
        if self.deep.is_some() {
            Model::Deep
        } else {
            Model::Rgb
        }
    }

    /// What working-size sides must be multiples of: `2^(levels−1)`, and 16 in the deep model
    /// (VGG19's four max-pools must halve exactly).
    pub fn size_multiple(&self) -> usize {
        let levels = match self.deep {
            Some(_) => self.solver.levels.max(5),
            None => self.solver.levels,
        };
        1 << (levels - 1)
    }

    /// Checks every setting, before any file is read.
    ///
    /// # Errors
    ///
    /// [`Error::InvalidParameter`] naming the first bad value and its range.
    pub fn validate(&self) -> Result<()> {
        self.solver.validate()?;
        if let Some(deep) = &self.deep {
            deep.features.validate()?;
            if self.solver.levels > 5 {
                return Err(Error::invalid(
                    "levels",
                    self.solver.levels,
                    "at most 5 for the deep model: VGG19 has taps at 1, 1/2, 1/4, 1/8 and 1/16 \
                     of the input size",
                ));
            }
        }
        self.playback().validate()?;
        if !self.align.is_none() && self.init.is_some() {
            return Err(Error::invalid(
                "align",
                self.align.name(),
                "none with --init: the alignment starts the coarsest level, which a draft \
                 replaces",
            ));
        }
        if let Some(n) = self.animation_frames {
            crate::model::inbetween::check_count(self.solver.steps, n)?;
        }
        if let Some(gib) = self.max_memory_gib
            && !(gib.is_finite() && gib > 0.0)
        {
            return Err(Error::invalid("max-memory", gib, "a number of GiB > 0"));
        }
        // The size rules need an input size for `Fit`; a 4×4 input checks the bounds.
        self.size.resolve(4, 4, self.size_multiple()).map(|_| ())
    }
}

/// What a morph morphs.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum Inputs {
    /// Two image files, A then B.
    Files {
        /// The first image.
        a: PathBuf,
        /// The last image.
        b: PathBuf,
    },
    /// The built-in synthetic pair ([`crate::app::demo`]).
    Demo,
    /// Two images handed over in memory (the Python module's arrays,
    /// [`MorphJob::from_images`](crate::app::job::MorphJob::from_images)): nothing to read
    /// again, so a run of these cannot be resumed or rerun from its `config.json` alone.
    Arrays {
        /// A's size, `[H, W]`.
        a: [usize; 2],
        /// B's size, `[H, W]`.
        b: [usize; 2],
    },
}

impl Inputs {
    /// The input files (none for the demo).
    pub fn files(&self) -> Vec<&Path> {
        match self {
            Inputs::Files { a, b } => vec![a.as_path(), b.as_path()],
            Inputs::Demo | Inputs::Arrays { .. } => Vec::new(),
        }
    }
}

/// How a morph ended, as `config.json` records it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Outcome {
    /// `"completed"`, where it was interrupted, or where a non-finite value stopped it.
    pub termination: String,
    /// The finest level's grid reached, `[H, W]`: the working size unless the run stopped
    /// on a coarser level.
    pub grid: [usize; 2],
    /// Wall-clock seconds of the solver.
    pub seconds: f64,
    /// What each level reached did: its size, the joint sweeps it ran, and why it stopped
    /// (`sweeps`: all `J` of them; `converged`: the tolerance; `interrupted`; `non_finite`).
    pub levels: Vec<crate::solver::observer::LevelSummary>,
    /// The deep model: RMS of each VGG tap of the inputs before scaling, relu1_2 first.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tap_rms: Option<Vec<f64>>,
    /// The time printed before the solve, level by level (compare each level's
    /// `seconds`); absent when the run was not asked to estimate it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub estimate: Option<crate::solver::estimate::TimeEstimate>,
}

/// `config.json`: everything needed to reproduce a run, and how it ended.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RunRecord {
    /// `"deepmorph"`.
    pub program: String,
    /// The program's version.
    pub version: String,
    /// What was morphed (files as absolute paths).
    pub inputs: Inputs,
    /// The working size the run was set up for, `[H, W]`; a run stopped on a coarser level
    /// reached only `outcome.grid`, the size of its outputs.
    pub working_size: [usize; 2],
    /// The settings.
    pub config: MorphConfig,
    /// The landmark pairs on the working grid (`[x, y]` in working pixels), as the solver
    /// used them (SPEC §11); absent without landmarks.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub landmarks: Option<Vec<PointPair>>,
    /// SPEC §11's global map the coarsest level started from (`--align`); absent without.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub alignment: Option<AlignmentRecord>,
    /// How it ended.
    pub outcome: Outcome,
}

impl RunRecord {
    /// Reads a `config.json`.
    ///
    /// # Errors
    ///
    /// [`Error::Io`] or [`Error::Format`] naming the file.
    pub fn read(path: &Path) -> Result<Self> {
        let bytes = crate::read::read_bytes(path, 16 << 20, "run record")?;
        serde_json::from_slice(&bytes).map_err(|e| Error::Format {
            path: path.to_path_buf(),
            detail: format!("not a deepmorph run record: {e}"),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_round_trip_through_json() {
        for config in [
            MorphConfig::default(),
            MorphConfig::deep("vgg19.onnx"),
            MorphConfig::demo(),
        ] {
            config.validate().unwrap();
            let json = serde_json::to_string(&config).unwrap();
            let back: MorphConfig = serde_json::from_str(&json).unwrap();
            assert_eq!(back, config);
        }
    }

    /// `standard` is the defaults; `paper` is SPEC §9 at 512 px with every sweep run.
    #[test]
    fn presets_set_what_they_say() {
        let mut standard = MorphConfig::deep("vgg19.onnx");
        Quality::Standard.apply(&mut standard);
        assert_eq!(standard, MorphConfig::deep("vgg19.onnx"));
        let mut paper = MorphConfig::deep("vgg19.onnx");
        Quality::Paper.apply(&mut paper);
        assert_eq!(paper.size, WorkingSize::Fit { max_side: 512 });
        assert_eq!(
            (paper.solver.steps, paper.solver.levels, paper.solver.sweeps),
            (15, 5, 250)
        );
        assert_eq!(paper.solver.tolerance, 0.0);
        assert_eq!(paper.deep.as_ref().unwrap().features.pre_sweeps, 50);
        let mut draft = MorphConfig::default();
        Quality::Draft.apply(&mut draft);
        draft.validate().unwrap();
        assert_eq!((draft.solver.levels, draft.solver.sweeps), (3, 60));
    }

    #[test]
    fn working_sizes_fit_the_pyramid() {
        let fit = WorkingSize::Fit { max_side: 32 };
        // 48x40 scaled to a longest side of 32 is 32x26.7, rounded to multiples of 2.
        assert_eq!(fit.resolve(40, 48, 2).unwrap(), (26, 32));
        assert_eq!(fit.resolve(10, 10, 2).unwrap(), (10, 10));
        let exact = WorkingSize::Exact {
            height: 48,
            width: 40,
        };
        assert_eq!(exact.resolve(1, 1, 8).unwrap(), (48, 40));
        let err = exact.resolve(1, 1, 16).unwrap_err().to_string();
        assert!(
            err.contains("40x48") && err.contains("multiples of 16"),
            "{err}"
        );
        let huge = WorkingSize::Exact {
            height: 16384,
            width: 16384,
        };
        assert!(
            huge.resolve(1, 1, 16)
                .unwrap_err()
                .to_string()
                .contains("8192")
        );
    }
}
