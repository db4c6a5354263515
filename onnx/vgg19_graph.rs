//! Writes the VGG19 feature graph of SPEC §4 as an ONNX model.
//!
//! Shared, through `#[path]`, by `build.rs` (which writes the graph with zero weights and
//! hands it to burn-import) and by the tests (which write the same graph with known weights
//! to check the run-time weight loader). Both include it next to a module `architecture`,
//! the table in `src/features/vgg/architecture.rs`. It is a few dozen lines of protobuf wire format
//! instead of a Python toolchain: ONNX is a protobuf message, and this graph needs only
//! nodes, initializers, one input and five outputs.
//!
//! The graph is torchvision's `vgg19.features` up to `relu5_4`: 16 3×3 convolutions
//! (stride 1, padding 1), each followed by a ReLU, with a 2×2 max-pool (stride 2) after
//! relu1_2, relu2_2, relu3_4 and relu4_4. Input `input` `[1, 3, H, W]` (ImageNet-normalised
//! RGB), outputs the five post-ReLU taps `relu1_2 … relu5_4`.

#![allow(dead_code)]

use std::io::Write;

use super::architecture::{LAYERS, TAPS, TORCHVISION_INDEX, conv_shapes};

/// A protobuf message under construction (wire format: varint keys, varints and
/// length-delimited fields; ONNX uses nothing else here).
#[derive(Default)]
struct Message(Vec<u8>);

impl Message {
    fn varint(&mut self, mut v: u64) {
        loop {
            let byte = (v & 0x7f) as u8;
            v >>= 7;
            if v == 0 {
                self.0.push(byte);
                return;
            }
            self.0.push(byte | 0x80);
        }
    }

    fn key(&mut self, field: u32, wire: u8) {
        self.varint(((field as u64) << 3) | wire as u64);
    }

    fn int(mut self, field: u32, v: i64) -> Self {
        self.key(field, 0);
        self.varint(v as u64);
        self
    }

    fn bytes(mut self, field: u32, b: &[u8]) -> Self {
        self.key(field, 2);
        self.varint(b.len() as u64);
        self.0.extend_from_slice(b);
        self
    }

    fn string(self, field: u32, s: &str) -> Self {
        self.bytes(field, s.as_bytes())
    }

    fn message(self, field: u32, m: Message) -> Self {
        self.bytes(field, &m.0)
    }
}

// Field numbers of onnx.proto (ModelProto, GraphProto, NodeProto, AttributeProto,
// TensorProto, ValueInfoProto, TypeProto, TensorShapeProto).
const ATTR_INT: i64 = 2;
const ATTR_INTS: i64 = 7;
const FLOAT: i64 = 1;

fn attribute_ints(name: &str, values: &[i64]) -> Message {
    let mut m = Message::default().string(1, name);
    for &v in values {
        m = m.int(8, v);
    }
    m.int(20, ATTR_INTS)
}

fn attribute_int(name: &str, value: i64) -> Message {
    Message::default()
        .string(1, name)
        .int(3, value)
        .int(20, ATTR_INT)
}

fn node(op: &str, name: &str, inputs: &[&str], output: &str, attributes: Vec<Message>) -> Message {
    let mut m = Message::default();
    for input in inputs {
        m = m.string(1, input);
    }
    m = m.string(2, output).string(3, name).string(4, op);
    for a in attributes {
        m = m.message(5, a);
    }
    m
}

fn initializer(name: &str, dims: &[usize], values: &[f32]) -> Message {
    let mut m = Message::default();
    for &d in dims {
        m = m.int(1, d as i64);
    }
    let raw: Vec<u8> = values.iter().flat_map(|v| v.to_le_bytes()).collect();
    m.int(2, FLOAT).string(8, name).bytes(9, &raw)
}

/// A float tensor value `[1, channels, H, W]` with symbolic `H`, `W`.
fn value_info(name: &str, channels: usize) -> Message {
    let dim_value = |v: i64| Message::default().int(1, v);
    let dim_param = |p: &str| Message::default().string(2, p);
    let shape = Message::default()
        .message(1, dim_value(1))
        .message(1, dim_value(channels as i64))
        .message(1, dim_param("height"))
        .message(1, dim_param("width"));
    let tensor = Message::default().int(1, FLOAT).message(2, shape);
    Message::default()
        .string(1, name)
        .message(2, Message::default().message(1, tensor))
}

/// Writes the graph to `out` with the weights and biases `weights(i, shape)` of
/// convolution `i` (0-based): weight shape `[out, in, 3, 3]` (row-major), bias `[out]`.
/// Initializers are named as in a torchvision export (`features.N.weight`).
pub fn write(
    out: &mut impl Write,
    mut weights: impl FnMut(usize, [usize; 4]) -> (Vec<f32>, Vec<f32>),
) -> std::io::Result<()> {
    let mut graph = Message::default().string(2, "vgg19_features");
    let mut initializers = Vec::new();
    let mut current = "input".to_string();
    let (mut conv, mut pool) = (0, 0);
    let shapes = conv_shapes();
    for layer in LAYERS {
        match layer {
            Some(_) => {
                let shape = shapes[conv];
                let (w, b) = weights(conv, shape);
                assert_eq!(
                    w.len(),
                    shape.iter().product::<usize>(),
                    "weight of conv {conv}"
                );
                assert_eq!(b.len(), shape[0], "bias of conv {conv}");
                let index = TORCHVISION_INDEX[conv];
                let (wn, bn) = (
                    format!("features.{index}.weight"),
                    format!("features.{index}.bias"),
                );
                initializers.push(initializer(&wn, &shape, &w));
                initializers.push(initializer(&bn, &shape[..1], &b));
                let conv_out = format!("conv{conv}");
                graph = graph.message(
                    1,
                    node(
                        "Conv",
                        &format!("Conv_{conv}"),
                        &[&current, &wn, &bn],
                        &conv_out,
                        vec![
                            attribute_ints("kernel_shape", &[3, 3]),
                            attribute_ints("pads", &[1, 1, 1, 1]),
                            attribute_ints("strides", &[1, 1]),
                            attribute_ints("dilations", &[1, 1]),
                            attribute_int("group", 1),
                        ],
                    ),
                );
                let relu_out = TAPS
                    .iter()
                    .find(|(_, c)| *c == conv)
                    .map_or_else(|| format!("relu{conv}"), |(name, _)| name.to_string());
                graph = graph.message(
                    1,
                    node(
                        "Relu",
                        &format!("Relu_{conv}"),
                        &[&conv_out],
                        &relu_out,
                        vec![],
                    ),
                );
                current = relu_out;
                conv += 1;
            }
            None => {
                let pool_out = format!("pool{pool}");
                graph = graph.message(
                    1,
                    node(
                        "MaxPool",
                        &format!("MaxPool_{pool}"),
                        &[&current],
                        &pool_out,
                        vec![
                            attribute_ints("kernel_shape", &[2, 2]),
                            attribute_ints("strides", &[2, 2]),
                            attribute_ints("pads", &[0, 0, 0, 0]),
                        ],
                    ),
                );
                current = pool_out;
                pool += 1;
            }
        }
    }
    for init in initializers {
        graph = graph.message(5, init);
    }
    graph = graph.message(11, value_info("input", 3));
    for (name, conv) in TAPS {
        graph = graph.message(12, value_info(name, shapes[conv][0]));
    }
    let opset = Message::default().string(1, "").int(2, 17);
    let model = Message::default()
        .int(1, 8)
        .string(2, "deepmorph onnx/vgg19_graph.rs")
        .message(7, graph)
        .message(8, opset);
    out.write_all(&model.0)
}
