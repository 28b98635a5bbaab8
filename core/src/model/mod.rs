//! Model manifests and the embedded default model.
//!
//! A model is an ONNX file plus its JSON [`Manifest`]. The build embeds
//! `core/models/default.onnx` with `core/models/default.json` when both exist
//! (the build script sets the `harmonizer_embedded_model` cfg); otherwise
//! [`embedded`] returns `None` and the library runs the classical backend.

mod manifest;
pub mod onnx;

pub use manifest::{
    Encoding, Exposure, InputChannel, Manifest, PriorSpec, TensorSpec, MANIFEST_FORMAT_VERSION,
    MAX_CONTEXT_FRAMES, MAX_REPAIR_MARGIN, REPAIR_EDGE_SHARE,
};

/// The model embedded in this build, if any.
#[derive(Debug, Clone, Copy)]
pub struct EmbeddedModel {
    /// The ONNX protobuf.
    pub onnx: &'static [u8],
    /// The manifest JSON text.
    pub manifest: &'static str,
}

/// The embedded default model (`core/models/default.onnx` + `default.json` at build time).
#[cfg(harmonizer_embedded_model)]
pub fn embedded() -> Option<EmbeddedModel> {
    Some(EmbeddedModel {
        onnx: include_bytes!(concat!(env!("CARGO_MANIFEST_DIR"), "/models/default.onnx")),
        manifest: include_str!(concat!(env!("CARGO_MANIFEST_DIR"), "/models/default.json")),
    })
}

/// The embedded default model; this build embeds none.
#[cfg(not(harmonizer_embedded_model))]
pub fn embedded() -> Option<EmbeddedModel> {
    None
}
