//! Deep features (SPEC §4): VGG19 imported from ONNX by burn-import, its weights read at run
//! time, and the deep model's per-level feature maps computed from it.
//!
//! - [`vgg`]: the network (generated code, included untouched), its architecture table, the
//!   weight loader (ONNX or safetensors) and the ImageNet normalisation.
//! - [`deep`]: both inputs through VGG19 once, each tap scaled to RMS `τ`.

pub mod deep;
pub mod vgg;
