//! The VGG19 feature network as burn-import generated it from `onnx/` (see `build.rs`):
//! included untouched. Its parameters are named `conv2d1 … conv2d16` in graph order.
#![allow(missing_docs, clippy::all, unused_imports, dead_code)]

include!(concat!(env!("OUT_DIR"), "/model/vgg19.rs"));
