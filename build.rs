//! Imports the VGG19 feature graph (SPEC §4) into Burn with burn-import.
//!
//! `onnx/vgg19_graph.rs` writes the ONNX graph (architecture with zero weights: the
//! repository does not ship 80 MB of weights; the real ones are loaded at run time from the
//! user's `--vgg19` file) into `OUT_DIR`, and burn-import's `ModelGen` turns it into
//! `OUT_DIR/model/vgg19.rs`, which `src/features/vgg/model.rs` includes untouched.
#![allow(deprecated)] // burn-import 0.22 is the deprecated wrapper of burn-onnx; it is the design card's tool.

#[path = "src/features/vgg/architecture.rs"]
#[allow(dead_code)]
mod architecture;
#[path = "onnx/vgg19_graph.rs"]
mod vgg19_graph;

use std::path::PathBuf;

use burn_import::onnx::ModelGen;

fn main() {
    println!("cargo:rerun-if-changed=onnx/vgg19_graph.rs");
    println!("cargo:rerun-if-changed=src/features/vgg/architecture.rs");
    println!("cargo:rerun-if-changed=build.rs");
    let out = PathBuf::from(std::env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    let onnx = out.join("vgg19.onnx");
    let mut file =
        std::io::BufWriter::new(std::fs::File::create(&onnx).expect("create vgg19.onnx"));
    vgg19_graph::write(&mut file, |_, [o, i, kh, kw]| {
        (vec![0.0; o * i * kh * kw], vec![0.0; o])
    })
    .expect("write vgg19.onnx");
    drop(file);
    ModelGen::new()
        .input(onnx.to_str().expect("OUT_DIR is UTF-8"))
        .out_dir("model/")
        .run_from_script();
    // The zero weights are not needed after code generation.
    let _ = std::fs::remove_file(&onnx);
}
