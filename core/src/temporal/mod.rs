//! Temporal state: the last K enhanced frames with their depth, motion and
//! camera ([`History`]), their reprojection into the current view with
//! validity masks ([`HistoryView`], see [`reproject`]) and scene-cut
//! detection ([`is_scene_cut`]).

mod history;
pub mod reproject;
pub mod scene_cut;

use std::sync::OnceLock;

pub use history::{History, HistoryFrame};
pub use scene_cut::{is_scene_cut, scene_cut_score, SceneCutScore};

use crate::frame::{Image, PreparedFrame};
use reproject::{Chain, Source};

/// History frame `k` aligned to the current view.
#[derive(Debug, Clone)]
pub struct ReprojectedFrame {
    /// RGBA premultiplied, resampled into the current view from the valid
    /// bilinear taps only (renormalized, so not scaled by `valid`); 0 where
    /// `valid` is 0.
    pub color: Image,
    /// Validity in [0,1]: 0 for disocclusions and out-of-frame samples, soft
    /// at image borders and depth edges.
    pub valid: Vec<f32>,
}

/// How a history frame is aligned to the current view.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReprojectionMode {
    /// Motion vectors of the current frame and of the newer history frames, chained.
    MotionVectors,
    /// Current depth and camera, projected into the history frame's camera.
    DepthCamera,
    /// No motion vectors and no depth: the camera is taken as static (the
    /// cameras are equal or unknown), the history is used as it is.
    Identity,
    /// The cameras differ but there is no depth nor motion to align: nothing is valid.
    Unavailable,
}

/// The history as seen from the current frame; reprojects lazily, once per k.
pub struct HistoryView<'a> {
    history: &'a History,
    current: &'a PreparedFrame,
    count: usize,
    pool: Option<&'a rayon::ThreadPool>,
    cache: Vec<OnceLock<ReprojectedFrame>>,
    /// `chains[h]`: positions in history frame `h + 1` (motion vectors).
    chains: Vec<OnceLock<Chain>>,
}

impl std::fmt::Debug for HistoryView<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("HistoryView")
            .field("count", &self.count)
            .finish_non_exhaustive()
    }
}

impl<'a> HistoryView<'a> {
    /// A view of the first `count` history frames from `current`; reprojection
    /// runs on `pool` (row-parallel, results independent of the pool size).
    /// History frames of another size than `current` are not used.
    pub fn new(
        history: &'a History,
        current: &'a PreparedFrame,
        count: usize,
        pool: &'a rayon::ThreadPool,
    ) -> Self {
        let (w, h) = (current.width(), current.height());
        let usable = history
            .iter()
            .take_while(|f| f.color.width == w && f.color.height == h && f.color.channels == 4)
            .count();
        let count = count.min(usable);
        HistoryView {
            history,
            current,
            count,
            pool: Some(pool),
            cache: (0..count).map(|_| OnceLock::new()).collect(),
            chains: (0..count.saturating_sub(1))
                .map(|_| OnceLock::new())
                .collect(),
        }
    }

    /// An empty view (cold start).
    pub fn empty(history: &'a History, current: &'a PreparedFrame) -> Self {
        HistoryView {
            history,
            current,
            count: 0,
            pool: None,
            cache: Vec::new(),
            chains: Vec::new(),
        }
    }

    /// Usable history frames.
    pub fn len(&self) -> usize {
        self.count
    }

    /// True when there is no usable history.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// The current frame.
    pub fn current(&self) -> &'a PreparedFrame {
        self.current
    }

    /// History frame `k` (0 = previous) as stored, not reprojected.
    ///
    /// # Panics
    /// When `k >= self.len()`.
    pub fn frame(&self, k: usize) -> &'a HistoryFrame {
        assert!(
            k < self.count,
            "history frame {k} requested, {} usable",
            self.count
        );
        self.history.get(k).expect("history index in range")
    }

    /// The pool reprojection runs on (`None` for an empty view).
    pub fn pool(&self) -> Option<&'a rayon::ThreadPool> {
        self.pool
    }

    /// How history frame `k` is aligned: motion vectors when the current frame
    /// and history frames `0..k` all have them and the frame numbers (where
    /// known) are consecutive, since motion vectors only reach one frame back;
    /// else depth + cameras when the current frame has depth and a camera and
    /// frame `k` a camera; else the identity when the cameras are equal or
    /// unknown; else unavailable.
    ///
    /// # Panics
    /// When `k >= self.len()`.
    pub fn mode(&self, k: usize) -> ReprojectionMode {
        let hk = self.frame(k);
        let cur = self.current;
        let consecutive = |newer: Option<i64>, older: Option<i64>| match (newer, older) {
            (Some(a), Some(b)) => a == b.wrapping_add(1),
            _ => true,
        };
        let chain_ok = cur.motion.is_some()
            && consecutive(cur.frame_index, self.frame(0).frame_index)
            && (0..k).all(|h| {
                let f = self.frame(h);
                f.motion.is_some() && consecutive(f.frame_index, self.frame(h + 1).frame_index)
            });
        if chain_ok {
            return ReprojectionMode::MotionVectors;
        }
        match (cur.camera, hk.camera) {
            (Some(_), Some(_)) if cur.depth.is_some() => ReprojectionMode::DepthCamera,
            (Some(a), Some(b)) if a != b => ReprojectionMode::Unavailable,
            _ => ReprojectionMode::Identity,
        }
    }

    /// History frame `k` (0 = previous) reprojected into the current view;
    /// computed on first use and cached.
    ///
    /// # Panics
    /// When `k >= self.len()`.
    pub fn reproject(&self, k: usize) -> &ReprojectedFrame {
        assert!(
            k < self.count,
            "history frame {k} requested, {} usable",
            self.count
        );
        self.cache[k].get_or_init(|| {
            let frame = self.frame(k);
            match self.mode(k) {
                ReprojectionMode::MotionVectors => {
                    reproject::hop_color(self.source(k), frame, self.pool)
                }
                ReprojectionMode::DepthCamera => {
                    reproject::reproject_camera(self.current, frame, self.pool)
                }
                ReprojectionMode::Identity => ReprojectedFrame {
                    color: frame.color.clone(),
                    valid: vec![1.0; frame.color.len()],
                },
                ReprojectionMode::Unavailable => ReprojectedFrame {
                    color: Image::zeros(frame.color.width, frame.color.height, 4),
                    valid: vec![0.0; frame.color.len()],
                },
            }
        })
    }

    /// Where the motion-vector chain into history frame `k` starts its last hop.
    fn source(&self, k: usize) -> Source<'_> {
        if k == 0 {
            let motion = self
                .current
                .motion
                .as_ref()
                .expect("motion mode needs motion vectors");
            return Source::Current {
                motion,
                depth: self.current.depth.as_deref(),
            };
        }
        Source::Chain(self.chain(k))
    }

    /// Positions of the current pixels in history frame `k >= 1`.
    fn chain(&self, k: usize) -> &Chain {
        self.chains[k - 1]
            .get_or_init(|| reproject::hop_chain(self.source(k - 1), self.frame(k - 1), self.pool))
    }
}
