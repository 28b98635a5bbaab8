//! Temporal state: the last K enhanced frames with their depth, motion and
//! camera, and their reprojection into the current view with validity masks.

use std::collections::VecDeque;
use std::sync::OnceLock;

use crate::frame::{Camera, Image, PreparedFrame};

/// One enhanced frame kept for the future.
#[derive(Debug, Clone)]
pub struct HistoryFrame {
    /// The enhanced output: RGB premultiplied by A, A coverage (4 planes).
    pub color: Image,
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
    /// Adds the newest frame, keeping at most `capacity`.
    pub fn push(&mut self, frame: HistoryFrame, capacity: usize) {
        self.frames.push_front(frame);
        self.frames.truncate(capacity);
    }
    /// Frame `k` (0 = previous).
    pub fn get(&self, k: usize) -> Option<&HistoryFrame> {
        self.frames.get(k)
    }
    /// Bytes held.
    pub fn bytes(&self) -> usize {
        self.frames.iter().map(HistoryFrame::bytes).sum()
    }
}

/// History frame `k` aligned to the current view.
#[derive(Debug, Clone)]
pub struct ReprojectedFrame {
    /// RGBA premultiplied, resampled into the current view (0 where invalid).
    pub color: Image,
    /// Validity in [0,1]: 0 for disocclusions and out-of-frame samples.
    pub valid: Vec<f32>,
}

/// The history as seen from the current frame; reprojects lazily, once per k.
pub struct HistoryView<'a> {
    history: &'a History,
    current: &'a PreparedFrame,
    count: usize,
    cache: Vec<OnceLock<ReprojectedFrame>>,
}

impl<'a> HistoryView<'a> {
    /// A view of the first `count` history frames from `current`.
    pub fn new(history: &'a History, current: &'a PreparedFrame, count: usize) -> Self {
        let count = count.min(history.len());
        HistoryView { history, current, count, cache: (0..count).map(|_| OnceLock::new()).collect() }
    }

    /// An empty view (cold start).
    pub fn empty(history: &'a History, current: &'a PreparedFrame) -> Self {
        Self::new(history, current, 0)
    }

    /// Usable history frames.
    pub fn len(&self) -> usize {
        self.count
    }

    /// True when there is no usable history.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// History frame `k` (0 = previous) reprojected into the current view.
    pub fn reproject(&self, k: usize) -> &ReprojectedFrame {
        self.cache[k].get_or_init(|| reproject_naive(self.history, self.current, k))
    }
}

/// Placeholder reprojection: identity alignment, valid everywhere.
fn reproject_naive(history: &History, current: &PreparedFrame, k: usize) -> ReprojectedFrame {
    let h = history.get(k).expect("history index in range");
    let n = current.width() * current.height();
    ReprojectedFrame { color: h.color.clone(), valid: vec![1.0; n] }
}

/// True when the current frame does not continue the history (a cut).
pub fn is_scene_cut(_view: &HistoryView<'_>, _current: &PreparedFrame, _threshold: f32) -> bool {
    false
}
