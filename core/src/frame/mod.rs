//! Frames and AOVs: strided views of host buffers, the planar images the
//! pipeline works on, cameras, and one frame's inputs.

mod camera;
mod image;
mod input;
mod shape;
mod view;

pub use camera::Camera;
pub use image::{sample_count, try_zeros, Image, Recycler, RgbaImage};
pub(crate) use input::recycle_mask;
pub use input::{DepthKind, FrameInput, PrepareOptions, PreparedFrame, Scan};
pub use shape::FrameShape;
pub use view::{ImageView, ImageViewMut, PixelFormat};
