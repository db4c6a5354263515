//! Reading VGG19's 16 convolutions from a user's weights file (ONNX or safetensors) and
//! checking them by order and shape (names differ between exporters), with errors that say
//! what the file holds instead (VGG16, vgg19_bn, a missing bias, a wrong shape, truncation).

use std::path::Path;

use burn::tensor::TensorData;

use super::architecture::{CONV_NAMES, conv_shapes};
use super::proto;
use crate::error::{Error, Result};

/// One convolution's parameters as found in a file.
#[derive(Clone, Debug)]
pub struct ConvWeights {
    /// Where it came from (initializer or key name).
    pub source: String,
    /// Kernel shape `[out, in, kh, kw]`.
    pub shape: Vec<usize>,
    /// Kernel, row-major.
    pub weight: Vec<f32>,
    /// Bias, `out` values.
    pub bias: Vec<f32>,
}

impl ConvWeights {
    /// The kernel and bias as Burn tensor data.
    pub fn into_data(self) -> (TensorData, TensorData) {
        let out = self.shape[0];
        (
            TensorData::new(self.weight, self.shape),
            TensorData::new(self.bias, [out]),
        )
    }
}

/// The 16 convolutions of VGG19, in `features` order.
#[derive(Clone, Debug)]
pub struct Vgg19Weights {
    /// `conv1_1 … conv5_4`.
    pub convs: Vec<ConvWeights>,
}

/// What kind of file a weights path is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Onnx,
    Safetensors,
}

fn format_error(path: &Path, detail: impl Into<String>) -> Error {
    Error::Format {
        path: path.to_path_buf(),
        detail: detail.into(),
    }
}

impl Vgg19Weights {
    /// Reads `path`: an ONNX model (`.onnx`) or a safetensors file (`.safetensors`); other
    /// extensions are recognised by their first bytes.
    ///
    /// # Errors
    ///
    /// [`Error::Io`] if the file cannot be read; [`Error::Format`] naming what is wrong
    /// with it (not VGG19, which convolution is missing or has which shape, truncation).
    pub fn read(path: &Path) -> Result<Self> {
        // The whole VGG19 with its classifier is 548 MB in float32; the limit leaves room
        // for a file with more beside it, not for one that would need gigabytes to parse.
        let bytes = crate::read::read_bytes(path, 1 << 30, "VGG19 weights file")?;
        Self::parse(path, bytes)
    }

    /// What [`Vgg19Weights::read`] does with the bytes of `path`.
    pub(crate) fn parse(path: &Path, bytes: Vec<u8>) -> Result<Self> {
        let kind = match path.extension().and_then(|e| e.to_str()) {
            Some("onnx") => Kind::Onnx,
            Some("safetensors") => Kind::Safetensors,
            _ if looks_like_safetensors(&bytes) => Kind::Safetensors,
            _ => Kind::Onnx,
        };
        let convs = match kind {
            Kind::Onnx => onnx_convs(&bytes).map_err(|d| format_error(path, d))?,
            Kind::Safetensors => safetensors_convs(path, bytes)?,
        };
        check(convs).map_err(|d| format_error(path, d))
    }
}

/// A safetensors file starts with an 8-byte header length and a JSON header `{`.
fn looks_like_safetensors(bytes: &[u8]) -> bool {
    bytes.len() > 9 && bytes[8] == b'{'
}

/// Whatever convolutions a file holds, in order, plus a note on batch normalisation.
type Found = (Vec<ConvWeights>, bool);

fn onnx_convs(bytes: &[u8]) -> std::result::Result<Found, String> {
    let graph = proto::parse_model(bytes).map_err(|e| format!("not a readable ONNX model: {e}"))?;
    let batch_norm = graph
        .nodes
        .iter()
        .any(|n| n.op_type == "BatchNormalization")
        || graph
            .initializers
            .iter()
            .any(|i| i.name.contains("running_mean"));
    let by_name = |name: &str| graph.initializers.iter().find(|i| i.name == name);
    let mut convs = Vec::new();
    let conv_nodes: Vec<_> = graph.nodes.iter().filter(|n| n.op_type == "Conv").collect();
    if conv_nodes.is_empty() {
        // A weights-only graph: 4-D kernels in file order, each with the 1-D bias after it.
        let inits = &graph.initializers;
        for (i, init) in inits.iter().enumerate() {
            if init.dims.len() == 4 {
                let bias = inits.get(i + 1).filter(|b| b.dims.len() == 1);
                convs.push(conv_from(init, bias)?);
            }
        }
    } else {
        for node in conv_nodes {
            let weight_name = node
                .inputs
                .get(1)
                .ok_or("a Conv node without a weight input")?;
            let weight = by_name(weight_name).ok_or_else(|| {
                format!(
                    "the weight `{weight_name}` of convolution {} is not an initializer of the \
                     graph (computed weights are not supported)",
                    convs.len() + 1
                )
            })?;
            let bias = node
                .inputs
                .get(2)
                .filter(|n| !n.is_empty())
                .and_then(|n| by_name(n));
            convs.push(conv_from(weight, bias)?);
        }
    }
    Ok((convs, batch_norm))
}

fn conv_from(
    weight: &proto::Initializer<'_>,
    bias: Option<&proto::Initializer<'_>>,
) -> std::result::Result<ConvWeights, String> {
    let bias = match bias {
        Some(b) => b.values()?,
        // Missing biases are reported by `check` with the convolution's name.
        None => Vec::new(),
    };
    Ok(ConvWeights {
        source: weight.name.clone(),
        shape: weight.dims.clone(),
        weight: weight.values()?,
        bias,
    })
}

fn safetensors_convs(path: &Path, bytes: Vec<u8>) -> Result<Found> {
    use burn_store::{ModuleStore, SafetensorsStore};
    let mut store = SafetensorsStore::from_bytes(Some(bytes));
    let tensors = store
        .get_all_tensors()
        .map_err(|e| format_error(path, format!("not a readable safetensors file: {e}")))?;
    let batch_norm = tensors.keys().any(|k| k.contains("running_mean"));
    // torchvision keys: `[prefix.]features.N.weight` / `.bias`, ordered by N.
    let mut indexed: Vec<(usize, &String)> = tensors
        .iter()
        .filter(|(_, t)| t.shape.len() == 4)
        .filter_map(|(k, _)| {
            let stem = k.strip_suffix(".weight")?;
            let (_, index) = stem.rsplit_once("features.")?;
            Some((index.parse().ok()?, k))
        })
        .collect();
    indexed.sort();
    let mut convs = Vec::new();
    for (_, key) in indexed {
        let read = |key: &str| -> Result<Option<(Vec<usize>, Vec<f32>)>> {
            let Some(t) = tensors.get(key) else {
                return Ok(None);
            };
            let data = burn_store::bridge::to_data(t)
                .map_err(|e| format_error(path, format!("`{key}` cannot be read: {e}")))?;
            let shape = data.shape().to_vec();
            let values = data
                .convert::<f32>()
                .try_into_vec::<f32>()
                .map_err(|e| format_error(path, format!("`{key}`: {e:?}")))?;
            Ok(Some((shape, values)))
        };
        let (shape, weight) = read(key)?.expect("listed key");
        let bias_key = format!("{}.bias", key.strip_suffix(".weight").expect("filtered"));
        let bias = read(&bias_key)?.map(|(_, b)| b).unwrap_or_default();
        convs.push(ConvWeights {
            source: key.clone(),
            shape,
            weight,
            bias,
        });
    }
    Ok((convs, batch_norm))
}

/// Checks the convolutions found against VGG19 by order and shape.
fn check((convs, batch_norm): Found) -> std::result::Result<Vgg19Weights, String> {
    let expected = conv_shapes();
    let three_by_three = convs
        .iter()
        .filter(|c| c.shape.len() == 4 && c.shape[2..] == [3, 3])
        .count();
    if batch_norm {
        return Err(format!(
            "this is a VGG with batch normalisation (vgg19_bn?): {three_by_three} convolutions \
             and BatchNorm layers; the deep model needs plain VGG19 (torchvision \
             `vgg19(weights=\"IMAGENET1K_V1\")`)"
        ));
    }
    if three_by_three == 13 {
        return Err("13 3x3 convolutions: this is VGG16; the deep model needs VGG19 (16)".into());
    }
    if convs.is_empty() {
        return Err("no convolution weights found (expected VGG19's 16 3x3 convolutions)".into());
    }
    for (i, want) in expected.iter().enumerate() {
        let Some(conv) = convs.get(i) else {
            return Err(format!(
                "only {} convolutions found: {} ({:?}) and later are missing (VGG19 has 16)",
                convs.len(),
                CONV_NAMES[i],
                want
            ));
        };
        if conv.shape != want {
            return Err(format!(
                "convolution {} ({}, `{}`) has shape {:?}, expected {:?} for VGG19",
                i + 1,
                CONV_NAMES[i],
                conv.source,
                conv.shape,
                want
            ));
        }
        if conv.bias.len() != want[0] {
            return Err(format!(
                "convolution {} ({}, `{}`) has {} bias values, expected {}",
                i + 1,
                CONV_NAMES[i],
                conv.source,
                conv.bias.len(),
                want[0]
            ));
        }
    }
    let mut convs = convs;
    convs.truncate(16);
    Ok(Vgg19Weights { convs })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A safetensors file with one torchvision-named convolution, `[2, 1, 3, 3]` and bias.
    fn seed_safetensors() -> Vec<u8> {
        let header = br#"{"features.0.weight":{"dtype":"F32","shape":[2,1,3,3],"data_offsets":[0,72]},"features.0.bias":{"dtype":"F32","shape":[2],"data_offsets":[72,80]}}"#;
        let mut bytes = (header.len() as u64).to_le_bytes().to_vec();
        bytes.extend(header);
        bytes.extend((0..20).flat_map(|i| (i as f32).to_le_bytes()));
        bytes
    }

    #[test]
    fn the_seeds_read_and_are_refused_as_not_vgg19() {
        for (name, bytes) in [
            ("w.onnx", proto::tests::seed_model()),
            ("w.safetensors", seed_safetensors()),
        ] {
            let err = Vgg19Weights::parse(Path::new(name), bytes).unwrap_err();
            assert!(
                err.to_string()
                    .contains("has shape [2, 1, 3, 3], expected [64, 3, 3, 3]"),
                "{err}"
            );
        }
    }

    fn parse_as(name: &'static str) -> impl Fn(&[u8]) {
        move |bytes| {
            let _ = Vgg19Weights::parse(Path::new(name), bytes.to_vec());
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig::with_cases(crate::fuzz::cases()))]

        #[test]
        fn fuzz_onnx(bytes in crate::fuzz::mutated(proto::tests::seed_model())) {
            crate::fuzz::within_allowance(&bytes, parse_as("w.onnx"));
        }

        #[test]
        fn fuzz_safetensors(bytes in crate::fuzz::mutated(seed_safetensors())) {
            crate::fuzz::within_allowance(&bytes, parse_as("w.safetensors"));
        }

        #[test]
        fn fuzz_unknown_extension(bytes in crate::fuzz::random_bytes()) {
            crate::fuzz::within_allowance(&bytes, parse_as("weights"));
        }
    }
}
