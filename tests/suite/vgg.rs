//! The imported VGG19 (burn-import's code from `onnx/`) with weights loaded at run time:
//! against onnxruntime's taps of the stand-in weights (SPEC §4 golden case), against a naive
//! float64 reference with known weights written to a self-made ONNX file, and the weight
//! loader's errors for files that are not VGG19.

use crate::common;

// The ONNX writer build.rs uses, beside the architecture table it reads.
#[path = "../../onnx/vgg19_graph.rs"]
mod vgg19_graph;
mod architecture {
    pub use deepmorph::features::vgg::architecture::*;
}

use std::path::Path;

use burn::tensor::{DType, Tensor};
use common::{
    Golden, assert_close, assert_golden, device, reference_backend, scratch, tensor, values,
};
use deepmorph::Backend;
use deepmorph::Precision;
use deepmorph::features::vgg::{TAPS, Vgg19, Vgg19Weights};

on_each_backend!(stand_in_taps_match_onnxruntime);

fn stand_in_taps_match_onnxruntime(backend: Backend) {
    let Some(path) = common::stand_in_vgg19() else {
        return;
    };
    let golden = Golden::load("vgg19_stand_in_taps");
    let device = device(backend, Precision::F32, false);
    let vgg = Vgg19::load(&path, &device).unwrap();
    let u: Tensor<4> = tensor(golden.input("u"), &device, DType::F32);
    for (tap, got) in TAPS.iter().zip(vgg.taps(u)) {
        let want = golden.output(tap);
        assert_eq!(got.dims()[1..], want.shape[..], "{tap} shape");
        assert_golden(&format!("vgg19_stand_in_taps.{tap}"), &values(got), want);
    }
}

/// Deterministic weights in roughly He scale, so activations stay O(1) through 16 layers.
fn known_weights(conv: usize, [o, i, kh, kw]: [usize; 4]) -> (Vec<f32>, Vec<f32>) {
    let mut state =
        0x9e37_79b9_7f4a_7c15u64 ^ (conv as u64 + 1).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
    };
    let scale = (6.0 / (i * kh * kw) as f64).sqrt();
    let w = (0..o * i * kh * kw)
        .map(|_| (next() * scale) as f32)
        .collect();
    let b = (0..o).map(|_| (next() * 0.1) as f32).collect();
    (w, b)
}

/// Naive float64 VGG19: 3×3 convolutions with zero padding, ReLU, 2×2 max-pools.
fn reference_taps(u: &[f64], h: usize, w: usize) -> Vec<Vec<f64>> {
    let mean = [0.485, 0.456, 0.406];
    let std = [0.229, 0.224, 0.225];
    let mut x: Vec<f64> = u
        .iter()
        .enumerate()
        .map(|(n, v)| (v - mean[n / (h * w)]) / std[n / (h * w)])
        .collect();
    let (mut c, mut h, mut w) = (3, h, w);
    let mut taps = Vec::new();
    let mut conv = 0;
    for layer in architecture::LAYERS {
        match layer {
            Some(o) => {
                let (kw_, kb) = known_weights(conv, [o, c, 3, 3]);
                let mut y = vec![0.0; o * h * w];
                for oc in 0..o {
                    for r in 0..h {
                        for s in 0..w {
                            let mut acc = f64::from(kb[oc]);
                            for ic in 0..c {
                                for dr in 0..3 {
                                    let rr = r as isize + dr as isize - 1;
                                    if rr < 0 || rr >= h as isize {
                                        continue;
                                    }
                                    for ds in 0..3 {
                                        let ss = s as isize + ds as isize - 1;
                                        if ss < 0 || ss >= w as isize {
                                            continue;
                                        }
                                        acc += f64::from(kw_[((oc * c + ic) * 3 + dr) * 3 + ds])
                                            * x[(ic * h + rr as usize) * w + ss as usize];
                                    }
                                }
                            }
                            y[(oc * h + r) * w + s] = acc.max(0.0);
                        }
                    }
                }
                x = y;
                c = o;
                if architecture::TAPS.iter().any(|(_, t)| *t == conv) {
                    taps.push(x.clone());
                }
                conv += 1;
            }
            None => {
                let (ph, pw) = (h / 2, w / 2);
                let mut y = vec![0.0; c * ph * pw];
                for ch in 0..c {
                    for r in 0..ph {
                        for s in 0..pw {
                            let at = |a: usize, b: usize| x[(ch * h + 2 * r + a) * w + 2 * s + b];
                            y[(ch * ph + r) * pw + s] =
                                at(0, 0).max(at(0, 1)).max(at(1, 0)).max(at(1, 1));
                        }
                    }
                }
                x = y;
                (h, w) = (ph, pw);
            }
        }
    }
    taps
}

fn write_known_onnx(path: &Path) {
    let mut file = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    vgg19_graph::write(&mut file, known_weights).unwrap();
}

#[test]
fn self_made_onnx_with_known_weights_matches_a_naive_reference() {
    let dir = scratch("vgg", "known");
    let path = dir.join("known.onnx");
    write_known_onnx(&path);
    let (h, w) = (16, 32);
    let u: Vec<f64> = (0..3 * h * w)
        .map(|n| 0.5 + 0.45 * ((n as f64) * 0.37).sin() * ((n % w) as f64 * 0.2).cos())
        .collect();
    let want = reference_taps(&u, h, w);
    let device = device(reference_backend(), Precision::F32, false);
    let vgg = Vgg19::load(&path, &device).unwrap();
    let input = Tensor::<4>::from_data(
        burn::tensor::TensorData::new(u, [1, 3, h, w]),
        (&device, DType::F32),
    );
    for ((tap, got), want) in TAPS.iter().zip(vgg.taps(input)).zip(&want) {
        let got = values(got);
        assert!(
            want.iter().any(|v| *v > 0.0),
            "{tap}: the reference is all zero"
        );
        assert_close(&format!("known weights, {tap}"), &got, want, 1e-4, 0.0);
    }

    // The same file cut short is a precise error, not a panic.
    let bytes = std::fs::read(&path).unwrap();
    let cut = dir.join("cut.onnx");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let err = Vgg19Weights::read(&cut).unwrap_err().to_string();
    assert!(
        err.contains("cut.onnx") && err.contains("truncated"),
        "{err}"
    );
    std::fs::remove_dir_all(dir).ok();
}

/// A safetensors file with the given `(key, shape)` tensors (values 0.01).
fn write_safetensors(path: &Path, tensors: &[(String, Vec<usize>)]) {
    let mut header = serde_json::Map::new();
    let mut offset = 0usize;
    for (key, shape) in tensors {
        let bytes = 4 * shape.iter().product::<usize>();
        header.insert(
            key.clone(),
            serde_json::json!({"dtype": "F32", "shape": shape, "data_offsets": [offset, offset + bytes]}),
        );
        offset += bytes;
    }
    let header = serde_json::to_vec(&header).unwrap();
    let mut out = (header.len() as u64).to_le_bytes().to_vec();
    out.extend(header);
    out.extend(std::iter::repeat_n(0.01f32.to_le_bytes(), offset / 4).flatten());
    std::fs::write(path, out).unwrap();
}

/// torchvision-style keys for convolutions of the given `[out, in]` at the given indices.
fn convs(indices: &[usize], shapes: &[[usize; 2]]) -> Vec<(String, Vec<usize>)> {
    indices
        .iter()
        .zip(shapes)
        .flat_map(|(n, [o, i])| {
            [
                (format!("features.{n}.weight"), vec![*o, *i, 3, 3]),
                (format!("features.{n}.bias"), vec![*o]),
            ]
        })
        .collect()
}

fn vgg19_shapes() -> Vec<[usize; 2]> {
    deepmorph::features::vgg::architecture::conv_shapes()
        .iter()
        .map(|s| [s[0], s[1]])
        .collect()
}

#[test]
fn safetensors_with_torchvision_keys_load_and_wrong_files_are_named() {
    let dir = scratch("vgg", "safetensors");
    let file = |name: &str, tensors: Vec<(String, Vec<usize>)>| {
        let path = dir.join(name);
        write_safetensors(&path, &tensors);
        path
    };
    let error = |path: &Path| Vgg19Weights::read(path).unwrap_err().to_string();

    // The genuine layout, with a classifier to ignore and a `model.` prefix.
    let mut tensors = convs(&architecture::TORCHVISION_INDEX, &vgg19_shapes());
    tensors
        .iter_mut()
        .for_each(|(k, _)| *k = format!("model.{k}"));
    tensors.push(("model.classifier.0.weight".into(), vec![8, 4]));
    let weights = Vgg19Weights::read(&file("vgg19.safetensors", tensors)).unwrap();
    assert_eq!(weights.convs.len(), 16);
    assert_eq!(weights.convs[15].source, "model.features.34.weight");
    let device = device(reference_backend(), Precision::F32, false);
    let vgg = Vgg19::from_weights(weights, &device).unwrap();
    let u = Tensor::<4>::zeros([1, 3, 16, 16], (&device, DType::F32));
    assert_eq!(vgg.taps(u)[4].dims(), [1, 512, 1, 1]);

    // VGG16: 13 convolutions.
    let vgg16 = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28];
    let shapes16 = [
        [64, 3],
        [64, 64],
        [128, 64],
        [128, 128],
        [256, 128],
        [256, 256],
        [256, 256],
        [512, 256],
        [512, 512],
        [512, 512],
        [512, 512],
        [512, 512],
        [512, 512],
    ];
    let msg = error(&file("vgg16.safetensors", convs(&vgg16, &shapes16)));
    assert!(
        msg.contains("VGG16") && msg.contains("vgg16.safetensors"),
        "{msg}"
    );

    // vgg19_bn: batch-norm statistics beside the convolutions.
    let mut bn = convs(&[0, 3], &[[64, 3], [64, 64]]);
    bn.push(("features.1.running_mean".into(), vec![64]));
    let msg = error(&file("bn.safetensors", bn));
    assert!(
        msg.contains("batch normalisation") && msg.contains("vgg19_bn"),
        "{msg}"
    );

    // A wrong shape is named with the convolution.
    let mut shapes = vgg19_shapes();
    shapes[4] = [256, 64];
    let msg = error(&file(
        "shape.safetensors",
        convs(&architecture::TORCHVISION_INDEX, &shapes),
    ));
    assert!(
        msg.contains("convolution 5 (conv3_1")
            && msg.contains("[256, 64, 3, 3]")
            && msg.contains("[256, 128, 3, 3]"),
        "{msg}"
    );

    // Missing convolutions and a missing bias.
    let msg = error(&file(
        "short.safetensors",
        convs(
            &architecture::TORCHVISION_INDEX[..10],
            &vgg19_shapes()[..10],
        ),
    ));
    assert!(
        msg.contains("only 10 convolutions") && msg.contains("conv4_3"),
        "{msg}"
    );
    let mut no_bias = convs(&architecture::TORCHVISION_INDEX, &vgg19_shapes());
    no_bias.retain(|(k, _)| k != "features.7.bias");
    let msg = error(&file("bias.safetensors", no_bias));
    assert!(
        msg.contains("conv2_2") && msg.contains("0 bias values"),
        "{msg}"
    );

    // Not a weights file at all, and no file.
    let junk = dir.join("junk.onnx");
    std::fs::write(&junk, b"this is not a network").unwrap();
    let msg = error(&junk);
    assert!(
        msg.contains("junk.onnx") && msg.contains("not a readable ONNX model"),
        "{msg}"
    );
    let msg = error(&dir.join("absent.onnx"));
    assert!(msg.contains("absent.onnx"), "{msg}");
    std::fs::remove_dir_all(dir).ok();
}
