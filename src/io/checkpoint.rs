//! The checkpoint an interrupted morph leaves beside its outputs, so that `--resume` can
//! continue it exactly: `checkpoint.json` (where it stopped, within a sweep too, the
//! Lipschitz estimates, the tolerance's window, the finished levels) and `checkpoint.f32` (the whole iPALM state of
//! the level it stopped on: `f`, `f_prev`, `φ`, `φ_prev`, little-endian float32).

use std::path::Path;

use burn::tensor::Tensor;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::io::images::write_atomically;
use crate::model::grid::{Grid, host_values};
use crate::read::read_bytes;
use crate::solver::ipalm::{LevelState, PartialSweep};
use crate::solver::multilevel::{Morph, Resume};
use crate::solver::observer::{LevelSummary, Termination};

/// The checkpoint's header.
pub const CHECKPOINT_HEADER: &str = "checkpoint.json";
/// The checkpoint's values.
pub const CHECKPOINT_DATA: &str = "checkpoint.f32";

/// What `checkpoint.json` holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Header {
    level: usize,
    sweeps: usize,
    steps: usize,
    channels: usize,
    height: usize,
    width: usize,
    l_phi: Vec<f64>,
    l_f: Vec<Vec<f64>>,
    /// The deformation searches' streaks (SPEC §6); absent in checkpoints written before the
    /// accelerating shrink, which resume with `m = 0`.
    #[serde(default)]
    phi_streak: Vec<u32>,
    history: Vec<f64>,
    levels: Vec<LevelSummary>,
    /// The blocks of joint sweep `sweeps + 1` that ran before the interrupt; absent when it
    /// stopped between sweeps (and in checkpoints written before interrupts within a sweep).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    partial: Option<PartialSweep>,
    /// [`inputs_digest`] of the inputs at the working size the run started from; absent in
    /// checkpoints written before it was recorded (not checked then).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    inputs: Option<String>,
}

/// A digest of the inputs as the solver sees them (the working-size images' float32
/// values, FNV-1a 64, hex): `--resume` compares it, so that a checkpoint is never continued
/// with other images (issue 43 #2: an input overwritten between the interruption and the
/// resume gave a hybrid path).
pub fn inputs_digest<'a>(images: impl IntoIterator<Item = &'a [f32]>) -> String {
    let mut hash: u64 = 0xcbf2_9ce4_8422_2325;
    for image in images {
        for b in (image.len() as u64).to_le_bytes() {
            hash = (hash ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
        }
        for v in image {
            for b in v.to_bits().to_le_bytes() {
                hash = (hash ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
            }
        }
    }
    format!("{hash:016x}")
}

/// Writes the checkpoint of `morph` into `dir` if it was interrupted (nothing otherwise),
/// with the [`inputs_digest`] `inputs()` of what it morphed (computed only then).
///
/// # Errors
///
/// A file cannot be written.
pub fn save_checkpoint(dir: &Path, morph: &Morph, inputs: impl FnOnce() -> String) -> Result<()> {
    let Termination::Interrupted { level, sweep } = morph.termination else {
        return Ok(());
    };
    let state = &morph.state;
    let [_, channels, height, width] = state.f[0].dims();
    let header = Header {
        level,
        sweeps: sweep,
        steps: state.steps(),
        channels,
        height,
        width,
        l_phi: state.l_phi.clone(),
        l_f: state.l_f.clone(),
        phi_streak: state.phi_streak.clone(),
        history: morph.history.clone(),
        levels: morph
            .levels
            .iter()
            .filter(|l| l.level < level)
            .cloned()
            .collect(),
        inputs: Some(inputs()),
        partial: morph.partial.clone(),
    };
    let mut bytes = Vec::new();
    for part in [&state.f, &state.f_prev, &state.phi, &state.phi_prev] {
        for v in host_values(Tensor::cat(part.clone(), 0))? {
            // The state is float32: the round trip through f64 is exact.
            bytes.extend_from_slice(&(v as f32).to_le_bytes());
        }
    }
    write_atomically(&dir.join(CHECKPOINT_DATA), |w| w.write_all(&bytes))?;
    let json = serde_json::to_vec_pretty(&header).expect("checkpoints serialise");
    write_atomically(&dir.join(CHECKPOINT_HEADER), |w| w.write_all(&json))
}

/// Reads the checkpoint in `dir` for a morph of the inputs with [`inputs_digest`] `inputs`
/// whose levels are `grids` (`(H, W)`, coarse to fine), its state on the grid `grid(level)`
/// makes; `None` if the folder has no checkpoint (the morph was not interrupted).
///
/// # Errors
///
/// A malformed or truncated checkpoint, one whose level does not fit `grids`, or one made
/// from other inputs.
pub fn load_checkpoint(
    dir: &Path,
    inputs: &str,
    grids: &[(usize, usize)],
    grid: impl Fn(usize) -> Result<Grid>,
) -> Result<Option<Resume>> {
    let path = dir.join(CHECKPOINT_HEADER);
    let data_path = dir.join(CHECKPOINT_DATA);
    if !path.is_file() {
        if data_path.exists() {
            // Half a checkpoint: restarting from scratch would silently drop the work.
            return Err(Error::Format {
                path: path.clone(),
                detail: format!(
                    "is missing beside {CHECKPOINT_DATA}: the checkpoint cannot be read; \
                     restore it, or start a new morph without --resume"
                ),
            });
        }
        return Ok(None);
    }
    let bad = |detail: String| Error::Format {
        path: path.clone(),
        detail,
    };
    let header: Header = serde_json::from_slice(&read_bytes(&path, 16 << 20, "checkpoint")?)
        .map_err(|e| bad(format!("not a deepmorph checkpoint: {e}")))?;
    if let Some(recorded) = &header.inputs
        && recorded != inputs
    {
        return Err(bad(format!(
            "made from other images than the inputs now (digest {recorded}, now {inputs}): an \
             input changed since the run was interrupted; start a new morph"
        )));
    }
    let (k, c, h, w) = (header.steps, header.channels, header.height, header.width);
    if grids.get(header.level) != Some(&(h, w)) || k == 0 {
        return Err(bad(format!(
            "level {} of {h}x{w} does not fit this morph's levels {grids:?}",
            header.level
        )));
    }
    let frame = c * h * w;
    let deformation = 2 * h * w;
    let count = 2 * (k + 1) * frame + 2 * k * deformation;
    let mismatch = |bytes: String| {
        bad(format!(
            "says {CHECKPOINT_DATA} holds K = {k} steps of {c} channels at {h}x{w}, {} bytes, \
             but it holds {bytes}: the two files do not belong together",
            4 * count
        ))
    };
    if let Ok(meta) = std::fs::metadata(&data_path)
        && meta.is_file()
        && meta.len() != 4 * count as u64
    {
        return Err(mismatch(meta.len().to_string()));
    }
    let data = read_bytes(&data_path, 4 * count as u64, "checkpoint values")?;
    if data.len() != 4 * count {
        return Err(mismatch(data.len().to_string()));
    }
    let values: Vec<f64> = data
        .chunks_exact(4)
        .map(|b| f64::from(f32::from_le_bytes(b.try_into().expect("4 bytes"))))
        .collect();
    if let Some(at) = values.iter().position(|v| !v.is_finite()) {
        return Err(Error::Format {
            path: data_path.clone(),
            detail: format!(
                "value {at} is {}: a checkpoint holds finite numbers only (the file was \
                 changed or damaged); start a new morph without --resume",
                values[at]
            ),
        });
    }
    let grid = grid(header.level)?;
    let mut at = 0;
    let mut take = |n: usize, size: usize, channels: usize| -> Vec<Tensor<4>> {
        (0..n)
            .map(|_| {
                let t = grid.tensor(values[at..at + size].to_vec(), [1, channels, h, w]);
                at += size;
                t
            })
            .collect()
    };
    let f = take(k + 1, frame, c);
    let f_prev = take(k + 1, frame, c);
    let phi = take(k, deformation, 2);
    let phi_prev = take(k, deformation, 2);
    let mut state = LevelState::new(f, phi, header.l_phi, header.l_f)?;
    state.f_prev = f_prev;
    state.phi_prev = phi_prev;
    match header.phi_streak.len() {
        0 => {}
        n if n == k => state.phi_streak = header.phi_streak,
        n => {
            return Err(bad(format!(
                "{n} deformation streaks for K = {k} steps (phi_streak must have K entries)"
            )));
        }
    }
    if let Some(partial) = &header.partial {
        let joint_blocks = 2 * k - 1;
        let fits = partial.blocks >= 1
            && partial.blocks < joint_blocks
            && partial.deformation.len() <= k
            && partial.features.len() < k
            && partial.residual_norm2.len() == k;
        if !fits {
            return Err(bad(format!(
                "its partial sweep ({} blocks, {} deformation and {} feature steps, {} \
                 residuals) does not fit K = {k} steps",
                partial.blocks,
                partial.deformation.len(),
                partial.features.len(),
                partial.residual_norm2.len()
            )));
        }
    }
    Ok(Some(Resume {
        level: header.level,
        sweeps: header.sweeps,
        partial: header.partial,
        state,
        history: header.history,
        levels: header.levels,
    }))
}
