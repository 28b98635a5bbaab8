//! harmonizer-core: a temporal post-render enhancer.
//!
//! A host hands the [`Session`] one rendered frame at a time (scene-linear
//! Linear Rec.709 color plus AOVs: depth, motion vectors, normals, coverage,
//! insert mask, albedo, camera). When `denoise` is on for the sequence it
//! first denoises the color ([`denoise`], Open Image Denoise). The session
//! reprojects its last K enhanced frames into the current view, runs a
//! [`backend`] (the embedded neural model or the classical pipeline) and
//! returns the enhanced frame.
//!
//! Conventions (see `ARCHITECTURE.md` and `../shared/CONVENTIONS.md`):
//! - color is scene-linear Linear Rec.709, premultiplied by coverage;
//! - depth is planar (distance along the view axis), empty pixels very large;
//! - motion vectors are pixels from the current pixel to where the same surface
//!   point was in the **previous** frame, x right, **y down**;
//! - camera matrices are OpenEXR row-vector matrices, camera space +z forward,
//!   NDC (0,0) top-left, (1,1) bottom-right.
// `deny`, not `forbid`: `denoise/oidn.rs` (the Open Image Denoise C API)
// allows it for itself; no other module may.
#![deny(unsafe_code)]
#![deny(missing_docs)]

pub mod backend;
pub mod denoise;
pub mod device;
pub mod error;
pub mod frame;
pub mod io;
pub mod model;
pub mod ops;
pub mod params;
pub mod session;
pub mod synth;
pub mod temporal;

pub use device::{Device, DeviceOptions, ModelSource};
pub use error::{Error, Result};
pub use frame::{
    Camera, DepthKind, FrameInput, FrameShape, Image, ImageView, ImageViewMut, PixelFormat,
};
pub use params::{ParamValue, Params};
pub use session::{FrameReport, Session};

/// The library version, from `Cargo.toml`.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");
