//! Files: EXR sequences in the `generic`, `blender` and user-mapped layouts,
//! frame patterns, and the sequence runner behind `harmonize run`.

pub mod pattern;

pub use pattern::{FramePattern, FrameRange};
