//! The last K enhanced frames with the AOVs needed to reproject them.

use std::collections::VecDeque;

use crate::frame::{Camera, Image, Recycler, RgbaImage};

/// One enhanced frame kept for the future.
#[derive(Debug, Clone)]
pub struct HistoryFrame {
    /// The enhanced output: RGB premultiplied by A, A coverage, interleaved
    /// (one bilinear tap of a reprojection reads 16 contiguous bytes).
    pub color: RgbaImage,
    /// Planar depth of the frame, if the host gave one.
    pub depth: Option<Vec<f32>>,
    /// The frame's motion vectors (to its own previous frame), if any.
    pub motion: Option<Image>,
    /// The frame's camera, if any.
    pub camera: Option<Camera>,
    /// The host's frame number.
    pub frame_index: Option<i64>,
}

impl HistoryFrame {
    /// Gives the frame's buffers to `rec`.
    pub fn recycle(self, rec: &Recycler) {
        rec.give(self.color.data);
        if let Some(d) = self.depth {
            rec.give(d);
        }
        if let Some(m) = self.motion {
            rec.give(m.data);
        }
    }

    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.color.bytes()
            + self.depth.as_ref().map_or(0, |d| d.len() * 4)
            + self.motion.as_ref().map_or(0, Image::bytes)
    }
}

/// The last K enhanced frames, newest first.
#[derive(Debug, Clone, Default)]
pub struct History {
    frames: VecDeque<HistoryFrame>,
}

impl History {
    /// Frames held.
    pub fn len(&self) -> usize {
        self.frames.len()
    }
    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }
    /// Drops everything.
    pub fn clear(&mut self) {
        self.frames.clear();
    }
    /// Adds the newest frame, keeping at most `capacity`; returns the frames
    /// that no longer fit (oldest last), so their buffers can be reused.
    pub fn push(&mut self, frame: HistoryFrame, capacity: usize) -> Vec<HistoryFrame> {
        self.frames.push_front(frame);
        let keep = capacity.min(self.frames.len());
        self.frames.split_off(keep).into()
    }
    /// Frame `k` (0 = previous).
    pub fn get(&self, k: usize) -> Option<&HistoryFrame> {
        self.frames.get(k)
    }
    /// The frames, newest first.
    pub fn iter(&self) -> impl Iterator<Item = &HistoryFrame> {
        self.frames.iter()
    }
    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.frames.iter().map(HistoryFrame::bytes).sum()
    }
}
