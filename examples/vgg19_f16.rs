//! Writes a VGG19 weights file (ONNX or safetensors, as `--vgg19` reads it) again as a
//! float16 safetensors file with torchvision key names: half the bytes, for carrying the
//! weights where size is limited (the one-shot GPU check, `scripts/gpu-check.sh`, whose
//! working tree travels in at most 64 MiB). `--vgg19` reads it back as float32; the
//! features differ from the original's by float16 rounding of the weights (relative
//! 2⁻¹¹ per weight), which changes no cost.
//!
//! ```sh
//! cargo run --release --example vgg19_f16 -- ../shared/data/vgg19/vgg19_hed_stand_in.onnx vgg19_f16.safetensors
//! ```

use std::path::PathBuf;

use anyhow::{Context, Result, bail};
use deepmorph::features::vgg::weights::Vgg19Weights;

/// The index of each convolution in torchvision's `vgg19.features`.
const FEATURE_INDEX: [usize; 16] = [0, 2, 5, 7, 10, 12, 14, 16, 19, 21, 23, 25, 28, 30, 32, 34];

fn main() -> Result<()> {
    let args: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    let [input, output] = args.as_slice() else {
        bail!("usage: vgg19_f16 WEIGHTS(.onnx|.safetensors) OUT.safetensors");
    };
    if output.exists() {
        bail!("{} exists: not overwritten", output.display());
    }
    let weights = Vgg19Weights::read(input)?;
    let mut header = serde_json::Map::new();
    let mut data: Vec<u8> = Vec::new();
    let mut put = |key: String, shape: &[usize], values: &[f32]| {
        let start = data.len();
        data.extend(
            values
                .iter()
                .flat_map(|&v| half::f16::from_f32(v).to_le_bytes()),
        );
        header.insert(
            key,
            serde_json::json!({"dtype": "F16", "shape": shape, "data_offsets": [start, data.len()]}),
        );
    };
    for (conv, index) in weights.convs.iter().zip(FEATURE_INDEX) {
        put(
            format!("features.{index}.weight"),
            &conv.shape,
            &conv.weight,
        );
        put(
            format!("features.{index}.bias"),
            &[conv.bias.len()],
            &conv.bias,
        );
    }
    let mut json = serde_json::to_vec(&header)?;
    // The data starts on an 8-byte boundary, as the format recommends.
    json.resize(json.len().next_multiple_of(8), b' ');
    let mut file = (json.len() as u64).to_le_bytes().to_vec();
    file.extend(json);
    file.extend(data);
    std::fs::write(output, &file).with_context(|| format!("writing {}", output.display()))?;
    // Read back as the program reads it: the same 16 convolutions.
    let back = Vgg19Weights::read(output)?;
    let worst = weights
        .convs
        .iter()
        .zip(&back.convs)
        .flat_map(|(a, b)| a.weight.iter().zip(&b.weight))
        .map(|(a, b)| ((a - b).abs() / a.abs().max(1e-3)) as f64)
        .fold(0.0, f64::max);
    println!(
        "{}: {} bytes, 16 convolutions, largest relative change of a weight {worst:.2e}",
        output.display(),
        file.len()
    );
    Ok(())
}
