//! Embeds `models/default.onnx` (with `models/default.json`) when both exist.

use std::path::Path;

fn main() {
    println!("cargo::rustc-check-cfg=cfg(harmonizer_embedded_model)");
    println!("cargo::rerun-if-changed=models");
    println!("cargo::rerun-if-changed=models/default.onnx");
    println!("cargo::rerun-if-changed=models/default.json");
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("models");
    let onnx = dir.join("default.onnx");
    let json = dir.join("default.json");
    match (onnx.is_file(), json.is_file()) {
        (true, true) => println!("cargo::rustc-cfg=harmonizer_embedded_model"),
        (true, false) => println!(
            "cargo::warning={} exists without its manifest {}; no model is embedded",
            onnx.display(),
            json.display()
        ),
        _ => {}
    }
}
