//! Files: EXR sequences in the `generic`, `blender` and user-mapped layouts,
//! frame patterns, and the sequence runner behind `harmonize run`.

pub mod exr;
pub mod guard;
pub mod layout;
pub mod pattern;
pub mod run;

pub use exr::{ExrFile, LoadedFrame, OutputMeta};
pub use guard::ReadLimits;
pub use layout::{ChannelMapping, LayoutOptions, LayoutPreset};
pub use pattern::{FramePattern, FrameRange};
