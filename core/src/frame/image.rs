//! The planar f32 image the pipeline works on (channel-major, like the
//! network's NCHW tensors).

/// A planar f32 image: `channels` planes of `width * height` samples.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Number of planes.
    pub channels: usize,
    /// Samples, plane after plane, rows top to bottom.
    pub data: Vec<f32>,
}

impl Image {
    /// A zero-filled image.
    pub fn zeros(width: usize, height: usize, channels: usize) -> Image {
        Image { width, height, channels, data: vec![0.0; width * height * channels] }
    }

    /// A constant image.
    pub fn filled(width: usize, height: usize, channels: usize, value: f32) -> Image {
        Image { width, height, channels, data: vec![value; width * height * channels] }
    }

    /// Pixels per plane.
    #[inline]
    pub fn len(&self) -> usize {
        self.width * self.height
    }

    /// True when the image has no pixels.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// One plane.
    #[inline]
    pub fn plane(&self, c: usize) -> &[f32] {
        let n = self.len();
        &self.data[c * n..(c + 1) * n]
    }

    /// One plane, mutable.
    #[inline]
    pub fn plane_mut(&mut self, c: usize) -> &mut [f32] {
        let n = self.len();
        &mut self.data[c * n..(c + 1) * n]
    }

    /// All planes, mutable, split.
    pub fn planes_mut(&mut self) -> Vec<&mut [f32]> {
        let n = self.len();
        self.data.chunks_mut(n.max(1)).collect()
    }

    /// One sample.
    #[inline]
    pub fn at(&self, x: usize, y: usize, c: usize) -> f32 {
        self.data[c * self.len() + y * self.width + x]
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.data.len() * std::mem::size_of::<f32>()
    }
}
