//! What a frame holds, without its pixels: its size and which AOVs it has.
//! Enough to estimate the memory a frame will take before any buffer is
//! allocated or any host sample is read (`Session::check_memory`).

use super::FrameInput;

/// A frame's size and the set of optional inputs it has.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct FrameShape {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Depth given.
    pub depth: bool,
    /// Motion vectors given.
    pub motion: bool,
    /// Normals given.
    pub normal: bool,
    /// Albedo given.
    pub albedo: bool,
    /// The denoise stage's own normals given.
    pub denoise_normal: bool,
    /// Coverage given.
    pub coverage: bool,
    /// Insert mask given.
    pub insert_mask: bool,
    /// Insert object ids given.
    pub insert_id: bool,
}

impl FrameShape {
    /// A frame of `width` x `height` with color only.
    pub fn new(width: usize, height: usize) -> FrameShape {
        FrameShape {
            width,
            height,
            ..FrameShape::default()
        }
    }

    /// The shape of `input`.
    pub fn of(input: &FrameInput<'_>) -> FrameShape {
        FrameShape {
            width: input.width(),
            height: input.height(),
            depth: input.depth.is_some(),
            motion: input.motion.is_some(),
            normal: input.normal.is_some(),
            albedo: input.albedo.is_some(),
            denoise_normal: input.denoise_normal.is_some(),
            coverage: input.coverage.is_some(),
            insert_mask: input.insert_mask.is_some(),
            insert_id: input.insert_id.is_some(),
        }
    }
}
