//! Temporal state: the last K enhanced frames with their depth, motion and
//! camera ([`History`]), their reprojection into the current view with
//! validity masks ([`HistoryView`], see [`reproject`]) and scene-cut
//! detection ([`is_scene_cut`]).

mod history;
pub mod reproject;
pub mod scene_cut;

use std::sync::OnceLock;

pub use history::{History, HistoryFrame};
pub use scene_cut::{is_scene_cut, scene_cut_score, Lattice, LatticeRows, SceneCutScore};

use crate::frame::{Image, PreparedFrame, Recycler};
use crate::ops;
use reproject::{Chain, Source};

/// History frame `k` aligned to the current view.
#[derive(Debug, Clone)]
pub struct ReprojectedFrame {
    /// RGBA premultiplied, resampled into the current view from the valid
    /// bilinear taps only (renormalized, so not scaled by `valid`); 0 where
    /// `valid` is 0.
    pub color: Image,
    /// Validity in `[0,1]`: 0 for disocclusions and out-of-frame samples, soft
    /// at image borders and depth edges.
    pub valid: Vec<f32>,
}

/// Whether frame numbers `newer` and `older` follow each other (an unknown
/// one counts as yes): motion vectors lead from a frame to the one before
/// it only.
pub(crate) fn consecutive(newer: Option<i64>, older: Option<i64>) -> bool {
    match (newer, older) {
        (Some(a), Some(b)) => b.checked_add(1) == Some(a),
        _ => true,
    }
}

/// How an earlier frame is aligned to the current one without motion
/// vectors: with the current depth and both cameras; else the identity
/// when the cameras are equal or unknown; else not at all.
pub(crate) fn camera_mode(
    current: Option<crate::frame::Camera>,
    earlier: Option<crate::frame::Camera>,
    depth: bool,
) -> ReprojectionMode {
    match (current, earlier) {
        (Some(_), Some(_)) if depth => ReprojectionMode::DepthCamera,
        (Some(a), Some(b)) if a != b => ReprojectionMode::Unavailable,
        _ => ReprojectionMode::Identity,
    }
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
    /// Where buffers come from and go back to when the view is dropped.
    recycler: Option<&'a Recycler>,
    /// `maps[k]`: depth + camera map into history frame `k` (for [`HistoryView::sample`]).
    maps: Vec<OnceLock<reproject::CameraMap>>,
}

/// Samples of one history frame reprojected into the current view
/// ([`HistoryView::sampler`]): [`Sampler::at`] one pixel, [`Sampler::span`]
/// a run of a row, the same values as [`HistoryView::sample`] bit for bit.
pub struct Sampler<'v> {
    view: &'v HistoryView<'v>,
    k: usize,
    hop: Option<(Source<'v>, &'v HistoryFrame)>,
}

impl Sampler<'_> {
    /// RGBA and validity at pixel (row `i`, column `j`).
    ///
    /// # Panics
    /// When the pixel is outside the frame.
    pub fn at(&self, i: usize, j: usize) -> ([f32; 4], f32) {
        match self.hop {
            Some((src, frame)) => {
                let (w, h) = (self.view.current.width(), self.view.current.height());
                assert!(i < h && j < w, "pixel ({j}, {i}) outside the {w}x{h} frame");
                reproject::hop_color_pixel(src, frame, i, j)
            }
            None => self.view.sample(self.k, i, j),
        }
    }

    /// Pixels `j0..j0 + n` of row `i`, `n` the length of `out[0]`: RGBA
    /// into `out[0..4]`, validity into `out[4]` (each at least `n` long).
    /// Cheaper per pixel than [`Sampler::at`] for runs of more than a few
    /// pixels (the hop's batched row path).
    ///
    /// # Panics
    /// When the run is outside the frame.
    pub fn span(&self, i: usize, j0: usize, out: [&mut [f32]; 5]) {
        let n = out[0].len();
        let (w, h) = (self.view.current.width(), self.view.current.height());
        assert!(
            i < h && j0 + n <= w,
            "row {i}, columns {j0}..{} outside the {w}x{h} frame",
            j0 + n
        );
        match self.hop {
            Some((src, frame)) => crate::ops::simd(SpanJob {
                src,
                frame,
                i,
                j0,
                out,
            }),
            None => {
                let [o0, o1, o2, o3, ov] = out;
                for t in 0..n {
                    let (c, v) = self.view.sample(self.k, i, j0 + t);
                    (o0[t], o1[t], o2[t], o3[t], ov[t]) = (c[0], c[1], c[2], c[3], v);
                }
            }
        }
    }
}

/// Row buffers of [`HistoryView::reproject_rows`].
pub struct RowScratch {
    out: [Vec<f32>; 5],
    chains: Vec<reproject::Chain>,
    done: Vec<bool>,
}

impl RowScratch {
    /// Scratch for rows of `width` pixels and up to `frames` history frames.
    pub fn new(width: usize, frames: usize) -> RowScratch {
        RowScratch {
            out: std::array::from_fn(|_| vec![0.0; width]),
            chains: (1..frames.max(1))
                .map(|_| reproject::Chain::row(width))
                .collect(),
            done: Vec::with_capacity(frames),
        }
    }
}

/// [`Sampler::span`]'s hop, compiled for the CPU's widest vectors
/// ([`crate::ops::simd`]).
struct SpanJob<'v, 'o> {
    src: Source<'v>,
    frame: &'v HistoryFrame,
    i: usize,
    j0: usize,
    out: [&'o mut [f32]; 5],
}

impl pulp::WithSimd for SpanJob<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let SpanJob {
            src,
            frame,
            i,
            j0,
            out,
        } = self;
        reproject::hop_color_row(src, frame, i, j0, &mut reproject::Planar(out))
    }
}

impl Drop for HistoryView<'_> {
    fn drop(&mut self) {
        let Some(rec) = self.recycler else {
            return;
        };
        for r in self.cache.iter_mut().filter_map(OnceLock::take) {
            rec.give(r.color.data);
            rec.give(r.valid);
        }
        for c in self.chains.iter_mut().filter_map(OnceLock::take) {
            c.recycle(rec);
        }
    }
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
        Self::build(history, current, count, pool, None)
    }

    /// Like [`HistoryView::new`], with the reprojected frames' buffers taken
    /// from `recycler` and given back to it when the view is dropped.
    pub fn new_recycled(
        history: &'a History,
        current: &'a PreparedFrame,
        count: usize,
        pool: &'a rayon::ThreadPool,
        recycler: &'a Recycler,
    ) -> Self {
        Self::build(history, current, count, pool, Some(recycler))
    }

    fn build(
        history: &'a History,
        current: &'a PreparedFrame,
        count: usize,
        pool: &'a rayon::ThreadPool,
        recycler: Option<&'a Recycler>,
    ) -> Self {
        let (w, h) = (current.width(), current.height());
        let usable = history
            .iter()
            .take_while(|f| f.color.width == w && f.color.height == h)
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
            recycler,
            maps: (0..count).map(|_| OnceLock::new()).collect(),
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
            recycler: None,
            maps: Vec::new(),
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

    /// Where the session's frame-sized buffers come from (`None` when the
    /// view was made without one): a backend may take its output from it.
    pub fn recycler(&self) -> Option<&'a Recycler> {
        self.recycler
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
        let chain_ok = cur.motion.is_some()
            && consecutive(cur.frame_index, self.frame(0).frame_index)
            && (0..k).all(|h| {
                let f = self.frame(h);
                f.motion.is_some() && consecutive(f.frame_index, self.frame(h + 1).frame_index)
            });
        if chain_ok {
            return ReprojectionMode::MotionVectors;
        }
        camera_mode(cur.camera, hk.camera, cur.depth.is_some())
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
            let rec = self.recycler;
            let (w, h) = (frame.color.width, frame.color.height);
            let take = |ch: usize| match rec {
                Some(r) => r.image(w, h, ch),
                None => Image::zeros(w, h, ch),
            };
            match self.mode(k) {
                ReprojectionMode::MotionVectors => {
                    reproject::hop_color(self.source(k), frame, self.pool, rec)
                }
                ReprojectionMode::DepthCamera => {
                    reproject::reproject_camera(self.current, frame, self.pool, rec)
                }
                ReprojectionMode::Identity => {
                    let mut color = take(4);
                    let n = w * h;
                    for (p, q) in frame.color.data.chunks_exact(4).enumerate() {
                        for (c, v) in q.iter().enumerate() {
                            color.data[c * n + p] = *v;
                        }
                    }
                    let mut valid = take(1).data;
                    valid.fill(1.0);
                    ReprojectedFrame { color, valid }
                }
                ReprojectionMode::Unavailable => {
                    let mut color = take(4);
                    color.data.fill(0.0);
                    let mut valid = take(1).data;
                    valid.fill(0.0);
                    ReprojectedFrame { color, valid }
                }
            }
        })
    }

    /// Keeps `frame` as history frame `k` reprojected, so the passes after
    /// the caller's copy it ([`HistoryView::reproject_span_rgba`] and the
    /// others read the cache first) instead of computing it again. The
    /// caller assembled `frame` from [`HistoryView::reproject_rows`] runs
    /// that cover every pixel once, so it holds the bits
    /// [`HistoryView::reproject`] would compute. When `k` is reprojected
    /// already, `frame`'s buffers go back to the recycler.
    ///
    /// # Panics
    /// When `k >= self.len()` or `frame` is not of the current frame's size.
    pub(crate) fn keep_reprojected(&self, k: usize, frame: ReprojectedFrame) {
        let (w, h) = (self.current.width(), self.current.height());
        assert!(
            (frame.color.width, frame.color.height, frame.color.channels) == (w, h, 4)
                && frame.valid.len() == w * h,
            "a reprojected frame of another size than the {w}x{h} frame"
        );
        if let Err(unused) = self.cache[k].set(frame) {
            if let Some(rec) = self.recycler {
                rec.give(unused.color.data);
                rec.give(unused.valid);
            }
        }
    }

    /// Row `i` of history frame `k` reprojected into the current view, the
    /// same bits as that row of [`HistoryView::reproject`]: R, G, B, A into
    /// `out[0..4]` and the validity into `out[4]`, each one row long.
    ///
    /// Computes only that row (nothing is cached) unless frame `k` is
    /// already reprojected, or is reached by chained motion vectors
    /// (`k >= 1` in [`ReprojectionMode::MotionVectors`]), where the whole
    /// frame is reprojected once and cached: call [`HistoryView::reproject`]
    /// for such a `k` before a parallel loop over rows. For `k = 0` this
    /// lets a pass over the image consume the reprojected history row by
    /// row without a frame-sized buffer being written and read back.
    ///
    /// # Panics
    /// When `k >= self.len()`, `i` is not a row of the frame or a slice of
    /// `out` is shorter than a row.
    pub fn reproject_row(&self, k: usize, i: usize, out: [&mut [f32]; 5]) {
        let w = self.current.width();
        let [o0, o1, o2, o3, ov] = out;
        let out = [
            &mut o0[..w],
            &mut o1[..w],
            &mut o2[..w],
            &mut o3[..w],
            &mut ov[..w],
        ];
        self.row_into(k, i, 0, &mut reproject::Planar(out));
    }

    /// Row `i`, columns `cols`, of history frames `0..n` reprojected into
    /// the current view, handed to `put(k, [r, g, b, a, valid])` (each
    /// `cols.len()` long) for each `k` in order: the same bits as that run
    /// of [`HistoryView::reproject`]`(k)`, but computed for it alone,
    /// nothing frame-sized written nor cached (frames already reprojected
    /// are copied from their cache): frames reached by chained motion
    /// vectors follow the chain for this run only, in `scratch`
    /// ([`RowScratch::new`] for at least `cols.len()` pixels and `n`
    /// frames; one per parallel task).
    ///
    /// # Panics
    /// When `n > self.len()`, the run is not inside the frame or longer
    /// than `scratch`'s.
    pub fn reproject_rows(
        &self,
        n: usize,
        i: usize,
        cols: std::ops::Range<usize>,
        scratch: &mut RowScratch,
        mut put: impl FnMut(usize, [&[f32]; 5]),
    ) {
        assert!(n <= self.count, "{n} history frames of {}", self.count);
        let (j0, w) = (cols.start, cols.len());
        let RowScratch { out, chains, done } = scratch;
        done.clear();
        done.resize(n.saturating_sub(1), false);
        for k in 0..n {
            let [o0, o1, o2, o3, ov] = out;
            let rows = [
                &mut o0[..w],
                &mut o1[..w],
                &mut o2[..w],
                &mut o3[..w],
                &mut ov[..w],
            ];
            let cached = self.cache[k].get().is_some();
            if !cached && self.mode(k) == ReprojectionMode::MotionVectors {
                // Positions of this row in frames 1..=k, hop by hop, where
                // the whole chain is not known already.
                for hop in 1..=k {
                    if self.chains[hop - 1].get().is_some() || done[hop - 1] {
                        continue;
                    }
                    let (before, rest) = chains.split_at_mut(hop - 1);
                    let src = self.row_source(hop - 1, before, j0);
                    let cols = cols.clone();
                    reproject::hop_chain_row(src, self.frame(hop - 1), i, cols, &mut rest[0]);
                    done[hop - 1] = true;
                }
                ops::simd(SpanJob {
                    src: self.row_source(k, chains, j0),
                    frame: self.frame(k),
                    i,
                    j0,
                    out: rows,
                });
            } else {
                self.row_into(k, i, j0, &mut reproject::Planar(rows));
            }
            put(k, [&o0[..w], &o1[..w], &o2[..w], &o3[..w], &ov[..w]]);
        }
    }

    /// The source of the last hop into history frame `k` (motion vectors)
    /// for [`HistoryView::reproject_rows`]: the current frame, the cached
    /// chain, else the run of it from column `j0` in `rows[k - 1]`.
    fn row_source<'s>(&'s self, k: usize, rows: &'s [reproject::Chain], j0: usize) -> Source<'s> {
        match k {
            0 => self.source(0),
            _ => match self.chains[k - 1].get() {
                Some(c) => Source::Chain(c),
                None => Source::ChainRow(&rows[k - 1], j0),
            },
        }
    }

    /// [`HistoryView::reproject_row`] for columns `j0..j0 + rgba.len()` of
    /// row `i`, the RGBA interleaved: pixel `j0 + j` into `rgba[j]`, its
    /// validity into `valid[j]` (the same values as the whole row's).
    ///
    /// # Panics
    /// When the columns leave the frame, or `valid` is shorter than `rgba`.
    #[inline(always)]
    pub fn reproject_span_rgba(
        &self,
        k: usize,
        i: usize,
        j0: usize,
        rgba: &mut [[f32; 4]],
        valid: &mut [f32],
    ) {
        let n = rgba.len();
        self.row_into(
            k,
            i,
            j0,
            &mut reproject::Interleaved {
                rgba,
                valid: &mut valid[..n],
            },
        );
    }

    /// Row `i` of history frame `k`, columns `j0..j0 + out.len()`, into `out`.
    #[inline(always)]
    fn row_into<O: reproject::RowOut>(&self, k: usize, i: usize, j0: usize, out: &mut O) {
        let (w, h) = (self.current.width(), self.current.height());
        let n = out.len();
        assert!(
            i < h && j0 + n <= w,
            "row {i}, columns {j0}..{} outside the {w}x{h} frame",
            j0 + n
        );
        let s = i * w + j0..i * w + j0 + n;
        let copy = |r: &ReprojectedFrame, out: &mut O| {
            let (c, v) = (&r.color, &r.valid[s.clone()]);
            let p: [&[f32]; 4] = std::array::from_fn(|ch| &c.plane(ch)[s.clone()]);
            out.put_run(
                0,
                n,
                reproject::PixFn(|j| ([p[0][j], p[1][j], p[2][j], p[3][j]], v[j])),
            );
        };
        if let Some(r) = self.cache.get(k).and_then(OnceLock::get) {
            return copy(r, out);
        }
        let frame = self.frame(k);
        match self.mode(k) {
            ReprojectionMode::MotionVectors if k == 0 => {
                reproject::hop_color_row(self.source(0), frame, i, j0, out)
            }
            ReprojectionMode::MotionVectors => copy(self.reproject(k), out),
            ReprojectionMode::DepthCamera => {
                let (map, depth) = self.camera_map(k);
                map.color_row(frame, depth, i, j0, out)
            }
            ReprojectionMode::Identity => {
                out.put_run(
                    0,
                    n,
                    reproject::PixFn(|j| (frame.color.pixel(i * w + j0 + j), 1.0)),
                );
            }
            ReprojectionMode::Unavailable => {
                out.put_run(0, n, reproject::PixFn(|_| ([0.0; 4], 0.0)));
            }
        }
    }

    /// The depth-and-cameras map of history frame `k` (built once) and the
    /// current depth it reads.
    fn camera_map(&self, k: usize) -> (&reproject::CameraMap, &[f32]) {
        let depth = self
            .current
            .depth
            .as_deref()
            .expect("depth mode needs depth");
        let map =
            self.maps[k].get_or_init(|| reproject::CameraMap::new(self.current, self.frame(k)));
        (map, depth)
    }

    /// Pixel (row `i`, column `j`) of history frame `k` reprojected into
    /// the current view: RGBA and validity, bit-identical to that pixel of
    /// [`HistoryView::reproject`]. Cheap for `k = 0` (or once `k` is
    /// reprojected): a sparse sample of the history costs only its pixels.
    ///
    /// # Panics
    /// When `k >= self.len()` or the pixel is outside the frame.
    pub fn sample(&self, k: usize, i: usize, j: usize) -> ([f32; 4], f32) {
        let (w, h) = (self.current.width(), self.current.height());
        assert!(i < h && j < w, "pixel ({j}, {i}) outside the {w}x{h} frame");
        let rep = |r: &ReprojectedFrame| {
            let p = i * w + j;
            let c = &r.color;
            (
                [c.plane(0)[p], c.plane(1)[p], c.plane(2)[p], c.plane(3)[p]],
                r.valid[p],
            )
        };
        if let Some(r) = self.cache.get(k).and_then(OnceLock::get) {
            return rep(r);
        }
        let frame = self.frame(k);
        match self.mode(k) {
            ReprojectionMode::MotionVectors if k == 0 => {
                reproject::hop_color_pixel(self.source(0), frame, i, j)
            }
            ReprojectionMode::MotionVectors => rep(self.reproject(k)),
            ReprojectionMode::DepthCamera => {
                let (map, depth) = self.camera_map(k);
                map.color_at(frame, depth, i, j)
            }
            ReprojectionMode::Identity => (frame.color.pixel(i * w + j), 1.0),
            ReprojectionMode::Unavailable => ([0.0; 4], 0.0),
        }
    }

    /// [`HistoryView::sample`] of history frame `k` for many pixels, one
    /// at a time or in runs of a row (see [`Sampler`]): what does not change
    /// from pixel to pixel (the reprojection mode, the source of the hop) is
    /// resolved once.
    ///
    /// # Panics
    /// When `k >= self.len()`.
    pub fn sampler(&self, k: usize) -> Sampler<'_> {
        assert!(k < self.len(), "history frame {k} of {}", self.len());
        // The common case: frame 0 by motion vectors, not reprojected whole.
        let hop = (k == 0
            && self.cache.first().and_then(OnceLock::get).is_none()
            && self.mode(0) == ReprojectionMode::MotionVectors)
            .then(|| (self.source(0), self.frame(0)));
        Sampler { view: self, k, hop }
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
        self.chains[k - 1].get_or_init(|| {
            reproject::hop_chain(
                self.source(k - 1),
                self.frame(k - 1),
                self.pool,
                self.recycler,
            )
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::frame::{Camera, RgbaImage};

    use super::reproject::tests::rnd;

    fn planes(w: usize, h: usize, c: usize, seed: &mut u64, f: fn(f32) -> f32) -> Image {
        let mut img = Image::zeros(w, h, c);
        for v in &mut img.data {
            *v = f(rnd(seed));
        }
        img
    }

    /// Depth layers with exact ties and empty sky, so every depth-test path runs.
    fn depth(n: usize, seed: &mut u64) -> Vec<f32> {
        (0..n)
            .map(|_| match (rnd(seed) * 5.0) as u32 {
                0 => 1e10,
                1 => 10.0,
                2 => 11.0,
                _ => 3.0 + 8.0 * rnd(seed),
            })
            .collect()
    }

    fn camera(x: f32) -> Camera {
        Camera::look_at(
            glam::Vec3::new(x, 0.2, -5.0),
            glam::Vec3::new(0.0, 0.0, 4.0),
            0.8,
            1.6,
        )
    }

    /// Row `i` of [`crate::ops::stabilize::ViewRows`], run through
    /// [`crate::ops::simd`].
    struct VectorizedRow<'r, 'v, 'a> {
        rows: crate::ops::stabilize::ViewRows<'v, 'a>,
        i: usize,
        rgba: &'r mut [[f32; 4]],
        valid: &'r mut [f32],
    }

    impl pulp::WithSimd for VectorizedRow<'_, '_, '_> {
        type Output = ();

        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _: S) {
            use crate::ops::stabilize::HistoryRows;
            self.rows.row(self.i, 0, self.rgba, self.valid)
        }
    }

    /// Rows ([`HistoryView::reproject_row`]) and pixels
    /// ([`HistoryView::sample`]) taken before and after the whole frame is
    /// reprojected equal [`HistoryView::reproject`] bit for bit, in every mode.
    #[test]
    fn rows_and_samples_equal_the_reprojected_frame_bit_for_bit() {
        let (w, h) = (97, 41);
        let n = w * h;
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap();
        let cases = [
            ("motion", true, true, Some((camera(0.0), camera(0.3)))),
            ("motion without depth", true, false, None),
            (
                "depth camera",
                false,
                true,
                Some((camera(0.0), camera(0.3))),
            ),
            ("identity", false, false, None),
            (
                "unavailable",
                false,
                false,
                Some((camera(0.0), camera(0.3))),
            ),
        ];
        for (name, motion, with_depth, cams) in cases {
            let mut seed = 11;
            let mut history = History::default();
            for _ in 0..3 {
                let frame = HistoryFrame {
                    color: RgbaImage::from_planes(&planes(w, h, 4, &mut seed, |r| r * 3.0), None),
                    depth: with_depth.then(|| depth(n, &mut seed)),
                    motion: Some(planes(w, h, 2, &mut seed, |r| (r - 0.5) * 7.0)),
                    camera: cams.map(|c| c.1),
                    frame_index: None,
                };
                history.push(frame, 4);
            }
            let color = planes(w, h, 3, &mut seed, |r| r);
            let current = PreparedFrame {
                depth: with_depth.then(|| depth(n, &mut seed)),
                motion: motion.then(|| planes(w, h, 2, &mut seed, |r| (r - 0.5) * 7.0)),
                camera: cams.map(|c| c.0),
                ..PreparedFrame::from_color(color)
            };
            let full = HistoryView::new(&history, &current, 3, &pool);
            for k in 0..full.len() {
                let want = full.reproject(k);
                let valid = want.valid.iter().filter(|&&v| v > 0.0).count();
                if name == "unavailable" {
                    assert_eq!(valid, 0, "{name}");
                } else {
                    assert!(valid > n / 10, "{name}: k {k}: {valid} valid of {n}");
                }
                for before in [true, false] {
                    let view = HistoryView::new(&history, &current, 3, &pool);
                    if !before {
                        view.reproject(k);
                    }
                    let mut row = vec![0.0f32; 5 * w];
                    for i in 0..h {
                        let (a, rest) = row.split_at_mut(w);
                        let (b, rest) = rest.split_at_mut(w);
                        let (c, rest) = rest.split_at_mut(w);
                        let (d, v) = rest.split_at_mut(w);
                        view.reproject_row(k, i, [a, b, c, d, v]);
                        // The same row interleaved.
                        let mut rgba = vec![[0.0f32; 4]; w];
                        let mut rv = vec![0.0f32; w];
                        view.reproject_span_rgba(k, i, 0, &mut rgba, &mut rv);
                        // And as the stabilization pass takes it: inlined
                        // into code vectorized for the CPU's widest vectors.
                        let mut vrgba = vec![[0.0f32; 4]; w];
                        let mut vrv = vec![0.0f32; w];
                        crate::ops::simd(VectorizedRow {
                            rows: crate::ops::stabilize::ViewRows {
                                view: &view,
                                k,
                                probe: None,
                            },
                            i,
                            rgba: &mut vrgba,
                            valid: &mut vrv,
                        });
                        let bits = |c: &[[f32; 4]], v: &[f32]| {
                            let all = c.iter().flatten().chain(v);
                            all.map(|x| x.to_bits()).collect::<Vec<_>>()
                        };
                        assert_eq!(
                            bits(&vrgba, &vrv),
                            bits(&rgba, &rv),
                            "{name}: k {k}: row {i} vectorized"
                        );
                        // A part of the row alone (what the stabilization
                        // of an area reads).
                        let (s0, s1) = (i % 7, w - i % 4);
                        let mut srgba = vec![[0.0f32; 4]; s1 - s0];
                        let mut sv = vec![0.0f32; s1 - s0];
                        view.reproject_span_rgba(k, i, s0, &mut srgba, &mut sv);
                        assert_eq!(
                            bits(&srgba, &sv),
                            bits(&rgba[s0..s1], &rv[s0..s1]),
                            "{name}: k {k}: row {i}, columns {s0}..{s1}"
                        );
                        // A run of the row through the sampler, at an offset.
                        let (j0, n) = (i % 5, w - i % 5 - i % 3);
                        let mut run = vec![0.0f32; 5 * n];
                        {
                            let (a, rest) = run.split_at_mut(n);
                            let (b, rest) = rest.split_at_mut(n);
                            let (c, rest) = rest.split_at_mut(n);
                            let (d, v) = rest.split_at_mut(n);
                            view.sampler(k).span(i, j0, [a, b, c, d, v]);
                        }
                        for t in 0..n {
                            let p = i * w + j0 + t;
                            let wc = [0, 1, 2, 3].map(|c| want.color.plane(c)[p].to_bits());
                            let got = [0, 1, 2, 3].map(|c| run[c * n + t].to_bits());
                            assert_eq!(got, wc, "{name}: k {k} span color at ({}, {i})", j0 + t);
                            assert_eq!(run[4 * n + t].to_bits(), want.valid[p].to_bits());
                        }
                        // The same run of every frame at once, as the
                        // neural backend takes it (chains followed for the
                        // run only, or from the cache where `k` is).
                        let mut scratch = RowScratch::new(n, full.len());
                        let mut seen = 0;
                        view.reproject_rows(full.len(), i, j0..j0 + n, &mut scratch, |kk, got| {
                            assert_eq!(kk, seen, "{name}: frames in order");
                            seen += 1;
                            let want = full.reproject(kk);
                            let p0 = i * w + j0;
                            let planes = [0, 1, 2, 3].map(|c| want.color.plane(c));
                            let planes = planes.iter().copied().chain([&want.valid[..]]);
                            let bits =
                                |s: &[f32]| s.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                            for (c, (g, p)) in got.iter().zip(planes).enumerate() {
                                assert_eq!(
                                    bits(&g[..n]),
                                    bits(&p[p0..p0 + n]),
                                    "{name}: k {k}: frame {kk}, channel {c} of the run in row {i}"
                                );
                            }
                        });
                        assert_eq!(seen, full.len(), "{name}");
                        for j in 0..w {
                            let p = i * w + j;
                            let wc = [0, 1, 2, 3].map(|c| want.color.plane(c)[p].to_bits());
                            let got = [0, 1, 2, 3].map(|c| row[c * w + j].to_bits());
                            assert_eq!(got, wc, "{name}: k {k} row color at ({j}, {i})");
                            assert_eq!(
                                row[4 * w + j].to_bits(),
                                want.valid[p].to_bits(),
                                "{name}: k {k} row validity at ({j}, {i})"
                            );
                            assert_eq!(rgba[j].map(f32::to_bits), wc, "{name}: k {k} rgba row");
                            assert_eq!(rv[j].to_bits(), want.valid[p].to_bits(), "{name}: k {k}");
                            let (c, v) = view.sample(k, i, j);
                            assert_eq!(
                                c.map(f32::to_bits),
                                wc,
                                "{name}: k {k} sample at ({j}, {i})"
                            );
                            assert_eq!(v.to_bits(), want.valid[p].to_bits(), "{name}: k {k}");
                            let (c, v) = view.sampler(k).at(i, j);
                            assert_eq!(c.map(f32::to_bits), wc, "{name}: k {k} sampler");
                            assert_eq!(v.to_bits(), want.valid[p].to_bits(), "{name}: k {k}");
                        }
                    }
                }
            }
            assert_eq!(
                full.mode(0),
                match name {
                    "motion" | "motion without depth" => ReprojectionMode::MotionVectors,
                    "depth camera" => ReprojectionMode::DepthCamera,
                    "identity" => ReprojectionMode::Identity,
                    _ => ReprojectionMode::Unavailable,
                },
                "{name}"
            );
        }
    }
}
