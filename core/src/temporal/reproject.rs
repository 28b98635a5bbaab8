//! Reprojection of history frames into the current view.
//!
//! Two ways, chosen per history frame by [`super::HistoryView::mode`]:
//! - **motion vectors**, chained frame to frame without resampling the image
//!   more than once: the current pixel centre `p0` moves to
//!   `p1 = p0 + mv_t(p0)` in frame t-1, then `p2 = p1 + mv_{t-1}(p1)` (the
//!   stored motion of history frame 0, looked up bilinearly) in frame t-2, and
//!   so on; the color of history frame k is sampled once, at the final position;
//! - **depth + cameras** (static scene, no motion vectors): the current pixel
//!   is unprojected with its planar depth and the current camera and projected
//!   into history frame k's camera; empty depth (sky) is projected as a
//!   direction (rotation only).
//!
//! Validity: every bilinear lookup (each hop and the final color sample) drops
//! the taps outside the image and, when depth is known on both sides, the taps
//! whose depth differs from the expected depth by more than
//! [`DEPTH_TOLERANCE`] (relative). The kept weights are renormalized, so a
//! silhouette never mixes foreground and background; their sum before
//! renormalizing is the validity of that lookup (soft at image borders and
//! depth edges), and the validities of the hops multiply.
//!
//! Every output pixel depends only on the inputs, never on how rows are split
//! between threads, so results are bit-identical for any pool size.

use glam::{DMat4, DVec4};
use rayon::prelude::*;

use super::{HistoryFrame, ReprojectedFrame};
use crate::frame::{Image, PreparedFrame, Recycler};
use crate::ops::{fmin, prefetch};

/// Depth at or beyond this is empty (sky, holes): it only matches other empty depth.
pub const FAR_DEPTH: f32 = 1e9;

/// Relative tolerance of the disocclusion depth test: a history sample is the
/// same surface when `seen` lies in `[expected / (1 + DEPTH_TOLERANCE),
/// expected * (1 + DEPTH_TOLERANCE)]` (that is, `|expected - seen| <=
/// DEPTH_TOLERANCE * min(expected, seen)`), see [`depth_window`].
pub const DEPTH_TOLERANCE: f32 = 0.1;

/// The largest depth below [`FAR_DEPTH`].
const NEAR_MAX: f32 = f32::from_bits(FAR_DEPTH.to_bits() - 1);

/// The depths that are the surface expected at depth `expected`, as the
/// closed interval `(lo, hi)`: `[FAR_DEPTH, inf]` for empty depth (it only
/// matches empty depth), else `expected` divided and multiplied by `1 +
/// DEPTH_TOLERANCE` (below [`FAR_DEPTH`]). NaN bounds for a NaN `expected`
/// (nothing matches).
#[inline(always)]
pub fn depth_window(expected: f32) -> (f32, f32) {
    let far = expected >= FAR_DEPTH;
    let lo = expected * (1.0 / (1.0 + DEPTH_TOLERANCE));
    let hi = fmin(expected * (1.0 + DEPTH_TOLERANCE), NEAR_MAX);
    // Selects, not branches: the window is taken in vectorized loops.
    (
        if far { FAR_DEPTH } else { lo },
        if far { f32::INFINITY } else { hi },
    )
}

/// True when depth `seen` in a history frame is the surface expected at
/// depth `expected` (inside [`depth_window`]; false when either is NaN).
#[inline]
pub fn depth_match(expected: f32, seen: f32) -> bool {
    let (lo, hi) = depth_window(expected);
    (seen >= lo) & (seen <= hi)
}

/// True when the four depths at `i`, `i + 1`, `i + w`, `i + w + 1` of `d`
/// (a 2x2 block of bilinear taps, rows of `w`) all lie in the window
/// `lo..=hi` (false for a NaN).
#[inline(always)]
fn block_in_window(d: &[f32], i: usize, w: usize, lo: f32, hi: f32) -> bool {
    // One bounds check for the block; the four reads are then in range.
    let q = &d[i..i + w + 2];
    let inside = |s: f32| (s >= lo) & (s <= hi);
    inside(q[0]) & inside(q[1]) & inside(q[w]) & inside(q[w + 1])
}

/// The bilinear taps at one position that passed the frame and depth tests,
/// with renormalized weights; `sum` is the weight they had before (validity).
#[derive(Clone, Copy)]
struct Taps {
    idx: [usize; 4],
    w: [f32; 4],
    sum: f32,
}

impl Taps {
    const NONE: Taps = Taps {
        idx: [0; 4],
        w: [0.0; 4],
        sum: 0.0,
    };

    /// Renormalizes the kept weights to sum 1; `sum` keeps their sum before.
    #[inline(always)]
    fn normalized(mut self) -> Taps {
        if self.sum > 0.0 {
            let inv = 1.0 / self.sum;
            for v in &mut self.w {
                *v *= inv;
            }
            self.sum = self.sum.min(1.0);
        }
        self
    }

    #[inline(always)]
    fn sample(&self, plane: &[f32]) -> f32 {
        self.w[0] * plane[self.idx[0]]
            + self.w[1] * plane[self.idx[1]]
            + self.w[2] * plane[self.idx[2]]
            + self.w[3] * plane[self.idx[3]]
    }

    /// [`Taps::sample`] of each channel of an interleaved RGBA image (the
    /// same sums, channel by channel).
    #[inline(always)]
    fn sample4(&self, rgba: &[[f32; 4]]) -> [f32; 4] {
        let px = |k: usize| rgba[self.idx[k]];
        let (a, b, c, d) = (px(0), px(1), px(2), px(3));
        std::array::from_fn(|ch| {
            self.w[0] * a[ch] + self.w[1] * b[ch] + self.w[2] * c[ch] + self.w[3] * d[ch]
        })
    }
}

/// Bilinear taps at pixel position (`x`, `y`) (pixel centres at +0.5) in a
/// `w` x `h` image. With `depth`, taps whose depth does not match `expected`
/// are dropped.
#[inline(always)]
fn taps(x: f32, y: f32, w: usize, h: usize, depth: Option<&[f32]>, expected: f32) -> Taps {
    let fx = x - 0.5;
    let fy = y - 0.5;
    // Written so that NaN positions fail too.
    if !(fx > -1.0 && fy > -1.0 && fx < w as f32 && fy < h as f32) {
        return Taps::NONE;
    }
    // floor() of values > -1 without a libm call: truncate the shifted value.
    let x0 = (fx + 1.0) as isize - 1;
    let y0 = (fy + 1.0) as isize - 1;
    let ax = fx - x0 as f32;
    let ay = fy - y0 as f32;
    let wt = [
        (1.0 - ax) * (1.0 - ay),
        ax * (1.0 - ay),
        (1.0 - ax) * ay,
        ax * ay,
    ];
    if x0 >= 0 && y0 >= 0 && (x0 as usize) + 1 < w && (y0 as usize) + 1 < h {
        // Interior: all four taps exist.
        let i = y0 as usize * w + x0 as usize;
        let idx = [i, i + 1, i + w, i + w + 1];
        let Some(d) = depth else {
            return Taps {
                idx,
                w: wt,
                sum: 1.0,
            };
        };
        let pass = [
            depth_match(expected, d[idx[0]]),
            depth_match(expected, d[idx[1]]),
            depth_match(expected, d[idx[2]]),
            depth_match(expected, d[idx[3]]),
        ];
        if pass == [true; 4] {
            return Taps {
                idx,
                w: wt,
                sum: 1.0,
            };
        }
        let mut t = Taps {
            idx,
            w: wt,
            sum: 0.0,
        };
        for n in 0..4 {
            if !pass[n] || wt[n] <= 0.0 {
                t.w[n] = 0.0;
            }
            t.sum += t.w[n];
        }
        return t.normalized();
    }
    // Border: drop the taps outside the image.
    let cand = [(x0, y0), (x0 + 1, y0), (x0, y0 + 1), (x0 + 1, y0 + 1)];
    let mut t = Taps::NONE;
    for (n, &(xi, yi)) in cand.iter().enumerate() {
        if wt[n] <= 0.0 || xi < 0 || yi < 0 || xi >= w as isize || yi >= h as isize {
            continue;
        }
        let i = yi as usize * w + xi as usize;
        if let Some(d) = depth {
            if !depth_match(expected, d[i]) {
                continue;
            }
        }
        t.idx[n] = i;
        t.w[n] = wt[n];
        t.sum += wt[n];
    }
    t.normalized()
}

/// The fast path of [`taps`]: when all four bilinear taps at (`x`, `y`) are
/// inside the image and pass the depth test, the index of the top-left tap
/// and the weights (top-left, top-right, bottom-left, bottom-right), exactly
/// as [`taps`] gives them; `None` otherwise (use [`taps`]).
#[inline(always)]
fn interior(
    x: f32,
    y: f32,
    w: usize,
    h: usize,
    depth: Option<&[f32]>,
    expected: f32,
) -> Option<(usize, [f32; 4])> {
    let fx = x - 0.5;
    let fy = y - 0.5;
    // Also false for NaN positions.
    if !(fx >= 0.0 && fy >= 0.0 && fx < w as f32 && fy < h as f32) {
        return None;
    }
    // The same floor as `taps` (bit-identical weights).
    let x0 = (fx + 1.0) as usize - 1;
    let y0 = (fy + 1.0) as usize - 1;
    if x0 + 1 >= w || y0 + 1 >= h {
        return None;
    }
    let ax = fx - x0 as f32;
    let ay = fy - y0 as f32;
    let i = y0 * w + x0;
    if let Some(d) = depth {
        // All four taps pass the test (`depth_match`) or none is taken here.
        let (lo, hi) = depth_window(expected);
        if !block_in_window(d, i, w, lo, hi) {
            return None;
        }
    }
    Some((
        i,
        [
            (1.0 - ax) * (1.0 - ay),
            ax * (1.0 - ay),
            (1.0 - ax) * ay,
            ax * ay,
        ],
    ))
}

/// The bilinear sample of `plane` (row length `w`) with top-left tap `i` and
/// weights `wt` from [`interior`]; the same sum, in the same order, as
/// [`Taps::sample`].
#[inline(always)]
fn bilerp(plane: &[f32], i: usize, w: usize, wt: &[f32; 4]) -> f32 {
    let q = &plane[i..i + w + 2];
    wt[0] * q[0] + wt[1] * q[1] + wt[2] * q[w] + wt[3] * q[w + 1]
}

/// [`bilerp`] of each channel of an interleaved RGBA image: one 16-byte
/// run per tap, the same sums channel by channel.
#[inline(always)]
fn bilerp4(rgba: &[[f32; 4]], i: usize, w: usize, wt: &[f32; 4]) -> [f32; 4] {
    let q = &rgba[i..i + w + 2];
    let (a, b, c, d) = (q[0], q[1], q[w], q[w + 1]);
    std::array::from_fn(|ch| wt[0] * a[ch] + wt[1] * b[ch] + wt[2] * c[ch] + wt[3] * d[ch])
}

/// 1.5 * 2^23: an f32 in `(-2^22, 2^22)` plus this is rounded to an
/// integer, which the sum's low mantissa bits hold.
const ROUND_MAGIC: f32 = 12_582_912.0;

/// Frame sides from this up never take [`Batch`]'s fast path
/// ([`floor_small`] needs positions below 2^22).
const SMALL_SIDE: usize = (1 << 22) - 1;

/// `u as i32` (the floor) for `0 <= u < 2^22`, from float adds and a bit
/// cast, so that a loop of it vectorizes (the saturating `as` is converted
/// lane by lane); some `i32` for any other `u`, NaN included.
#[inline(always)]
fn floor_small(u: f32) -> i32 {
    let t = u + ROUND_MAGIC;
    // `u` rounded to the nearest integer, as f32 (exact) and as i32.
    let r = t - ROUND_MAGIC;
    let n = (t.to_bits() as i32).wrapping_sub(ROUND_MAGIC.to_bits() as i32);
    n.wrapping_sub(i32::from(r > u))
}

/// Pixels per [`Batch`].
const BATCH: usize = 64;

/// How many rows below its taps a batch asks the CPU to fetch the history
/// ahead ([`Batch::prefetch_ahead`]): rows are hopped one after the other,
/// so the taps of the row after next (the history row that row reads for
/// the first time, as its bottom taps) arrive while this one is computed,
/// not one cache miss at a time when they are used.
const PREFETCH_ROWS: usize = 3;

/// `0.0, 1.0, .., BATCH - 1` (offsets of a batch's columns).
const COLUMNS: [f32; BATCH] = {
    let mut c = [0.0; BATCH];
    let mut t = 0;
    while t < BATCH {
        c[t] = t as f32;
        t += 1;
    }
    c
};

/// One run of up to [`BATCH`] pixels of a row: where they land in the
/// history frame and, for those that take the interior fast path (all four
/// taps inside, validity so far > 0, and all four passing the depth test of
/// [`Batch::depth_test`]: `fast`), the top-left tap and the fractions the
/// weights come from, exactly as [`interior`] gives them. The arithmetic
/// runs in short loops over the run, which vectorize; the gathers are per
/// pixel.
struct Batch {
    x: [f32; BATCH],
    y: [f32; BATCH],
    d: [f32; BATCH],
    v: [f32; BATCH],
    fast: [bool; BATCH],
    idx: [u32; BATCH],
    ax: [f32; BATCH],
    ay: [f32; BATCH],
    lo: [f32; BATCH],
    hi: [f32; BATCH],
    /// The four depth taps (top-left, top-right, bottom-left, bottom-right)
    /// of each pixel, gathered for the test in [`Batch::fill`].
    taps: [[f32; BATCH]; 4],
}

impl Batch {
    fn new() -> Batch {
        Batch {
            x: [0.0; BATCH],
            y: [0.0; BATCH],
            d: [0.0; BATCH],
            v: [0.0; BATCH],
            fast: [false; BATCH],
            idx: [0; BATCH],
            ax: [0.0; BATCH],
            ay: [0.0; BATCH],
            lo: [0.0; BATCH],
            hi: [0.0; BATCH],
            taps: [[0.0; BATCH]; 4],
        }
    }

    /// Positions of pixels `j0..j0 + mx.len()` of row `i` of the current
    /// frame with motion `mx`, `my` (row slices) into `x`, `y`, validity 1
    /// into `v`: the values of [`Source::at`], bit for bit.
    #[inline(always)]
    fn current_span(&mut self, i: usize, j0: usize, mx: &[f32], my: &[f32]) {
        let m = mx.len();
        let yc = i as f32 + 0.5;
        if j0 + BATCH <= 1 << 23 {
            // Column + 0.5 is exact in f32 below 2^23, so it can be summed
            // from the batch's first column (vectorizes).
            let x0 = j0 as f32;
            for ((x, &c), &d) in self.x[..m].iter_mut().zip(&COLUMNS).zip(mx) {
                *x = (x0 + c) + 0.5 + d;
            }
        } else {
            for (t, (x, &d)) in self.x[..m].iter_mut().zip(mx).enumerate() {
                *x = (j0 + t) as f32 + 0.5 + d;
            }
        }
        for (y, &d) in self.y[..m].iter_mut().zip(my) {
            *y = yc + d;
        }
        self.v[..m].fill(1.0);
    }

    /// The bilinear weights of pixel `t` (top-left, top-right, bottom-left,
    /// bottom-right), as [`taps`] computes them.
    #[inline(always)]
    fn weights(&self, t: usize) -> [f32; 4] {
        let (ax, ay) = (self.ax[t], self.ay[t]);
        [
            (1.0 - ax) * (1.0 - ay),
            ax * (1.0 - ay),
            (1.0 - ax) * ay,
            ax * ay,
        ]
    }

    /// Fills the batch with pixels `j0..j0 + m` of row `i` (`m <= BATCH`)
    /// of a source whose positions `at` gives, looking into a `w` x `h`
    /// history frame with depth `depth`.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn fill<S: Positions>(
        &mut self,
        at: &S,
        i: usize,
        j0: usize,
        m: usize,
        w: usize,
        h: usize,
        depth: Option<&[f32]>,
    ) {
        at.fill(i, j0, m, self);
        let (wf, hf) = (w as f32, h as f32);
        // 32-bit integer arithmetic vectorizes on every x86-64; frames of 4
        // G pixels or more (or sides of 4 M, see `floor_small`) never take
        // the fast path.
        let small = w < SMALL_SIDE && h < SMALL_SIDE && w * h < u32::MAX as usize;
        let (wi, hi) = (
            w.min(i32::MAX as usize) as i32,
            h.min(i32::MAX as usize) as i32,
        );
        let (xmax, ymax) = (wi.wrapping_sub(1), hi.wrapping_sub(1));
        for t in 0..BATCH {
            let fx = self.x[t] - 0.5;
            let fy = self.y[t] - 0.5;
            // Also false for NaN positions; the same floor as `taps`.
            let inside = (fx >= 0.0) & (fy >= 0.0) & (fx < wf) & (fy < hf);
            let x0 = floor_small(fx + 1.0).wrapping_sub(1);
            let y0 = floor_small(fy + 1.0).wrapping_sub(1);
            self.ax[t] = fx - x0 as f32;
            self.ay[t] = fy - y0 as f32;
            self.fast[t] = inside & (x0 < xmax) & (y0 < ymax) & (self.v[t] > 0.0) & (t < m) & small;
            // Meaningful (and in range) for `fast` pixels only, which alone
            // read it; wrapping, so the others compute no overflow.
            self.idx[t] = (y0 as u32).wrapping_mul(w as u32).wrapping_add(x0 as u32);
        }
        let Some(depth) = depth else {
            return;
        };
        for t in 0..BATCH {
            let e = self.d[t];
            let (lo, hi) = depth_window(e);
            // Unknown expected depth: no depth test (every depth passes; a
            // NaN history depth, which the library does not make, fails and
            // takes the general path, which gives the same values).
            let unknown = e.is_nan();
            self.lo[t] = if unknown { f32::NEG_INFINITY } else { lo };
            self.hi[t] = if unknown { f32::INFINITY } else { hi };
        }
        self.depth_test(depth, w);
    }

    /// Asks for the history's colour and depth [`PREFETCH_ROWS`] rows below
    /// the taps of the batch's `fast` pixels (one request per cache line:
    /// every 4th pixel of interleaved RGBA, every 16th of depth); a hint
    /// that changes no value.
    #[inline(always)]
    fn prefetch_ahead(&self, planes: &Planes<'_>, m: usize) {
        let ahead = PREFETCH_ROWS * planes.w;
        for t in (0..m).step_by(4) {
            if self.fast[t] {
                let k = self.idx[t] as usize + ahead;
                prefetch(planes.rgba, k);
                if t % 16 == 0 {
                    if let Some(d) = planes.depth {
                        prefetch(d, k);
                    }
                }
            }
        }
    }

    /// The depth test of the `fast` pixels, which stay `fast` only when all
    /// four taps in `depth` (the history frame's, rows of `w`) lie inside
    /// their window (as [`block_in_window`]); with `fast` after it, the
    /// interior fast path of [`taps`] applies. The taps are gathered first
    /// (independent loads, no branches), then compared in a loop that
    /// vectorizes.
    #[inline(always)]
    fn depth_test(&mut self, depth: &[f32], w: usize) {
        let Some(last) = depth.len().checked_sub(w + 2) else {
            // Fewer than two rows: no pixel has four taps inside.
            self.fast = [false; BATCH];
            return;
        };
        let [t0, t1, t2, t3] = &mut self.taps;
        for t in 0..BATCH {
            // `fast` pixels are in range (their block is inside the frame);
            // the others read the first block and are not tested.
            let i = if self.fast[t] {
                self.idx[t] as usize
            } else {
                0
            };
            let q = &depth[i.min(last)..i.min(last) + w + 2];
            (t0[t], t1[t], t2[t], t3[t]) = (q[0], q[1], q[w], q[w + 1]);
        }
        for t in 0..BATCH {
            let (lo, hi) = (self.lo[t], self.hi[t]);
            let inside = |s: f32| (s >= lo) & (s <= hi);
            self.fast[t] &= inside(t0[t]) & inside(t1[t]) & inside(t2[t]) & inside(t3[t]);
        }
    }
}

/// Runs `f(row, [row slices of each plane])` over all rows, in parallel on
/// `pool` when given. Each row is written by exactly one call, so the result
/// does not depend on the number of threads.
pub(crate) fn par_rows<const N: usize, F>(
    pool: Option<&rayon::ThreadPool>,
    planes: [&mut [f32]; N],
    w: usize,
    f: F,
) where
    F: Fn(usize, [&mut [f32]; N]) + Send + Sync,
{
    if w == 0 || N == 0 {
        return;
    }
    let h = planes[0].len() / w;
    let mut iters = planes.map(|p| p.chunks_mut(w));
    let rows: Vec<[&mut [f32]; N]> = (0..h)
        .map(|_| std::array::from_fn(|c| iters[c].next().expect("planes of equal size")))
        .collect();
    match pool {
        Some(pool) => pool.install(|| {
            rows.into_par_iter()
                .enumerate()
                .with_min_len(4)
                .for_each(|(i, r)| f(i, r));
        }),
        None => rows.into_iter().enumerate().for_each(|(i, r)| f(i, r)),
    }
}

/// Splits a 4-plane image into its planes.
fn planes4(img: &mut Image) -> [&mut [f32]; 4] {
    let n = img.len();
    let (a, rest) = img.data.split_at_mut(n);
    let (b, rest) = rest.split_at_mut(n);
    let (c, d) = rest.split_at_mut(n);
    [a, b, c, d]
}

/// Positions of the current pixels in history frame h, after following the
/// motion vectors hop by hop, with the surface's depth there (NaN: unknown)
/// and the validity so far.
#[derive(Debug, Clone)]
pub(crate) struct Chain {
    x: Vec<f32>,
    y: Vec<f32>,
    depth: Vec<f32>,
    valid: Vec<f32>,
}

impl Chain {
    /// A chain of one row of `w` pixels (for [`Source::ChainRow`]); its
    /// values are written by [`hop_chain_row`].
    pub(crate) fn row(w: usize) -> Chain {
        Chain {
            x: vec![0.0; w],
            y: vec![0.0; w],
            depth: vec![0.0; w],
            valid: vec![0.0; w],
        }
    }

    /// Gives the chain's buffers to `rec`.
    pub(crate) fn recycle(self, rec: &Recycler) {
        for b in [self.x, self.y, self.depth, self.valid] {
            rec.give(b);
        }
    }
}

/// Where a hop starts: the current frame (positions from its motion vectors)
/// or a chain into a history frame.
#[derive(Clone, Copy)]
pub(crate) enum Source<'a> {
    /// The current frame: `p1 = p0 + mv_t(p0)` exactly, no lookup.
    Current {
        /// The current frame's motion vectors.
        motion: &'a Image,
        /// The current frame's depth.
        depth: Option<&'a [f32]>,
    },
    /// A chain into a history frame.
    Chain(&'a Chain),
    /// A run of one row of a chain into a history frame ([`Chain::row`],
    /// written by [`hop_chain_row`]) starting at the column given: the
    /// values of that run of the whole [`Chain`], for the row and columns
    /// it was computed for only.
    ChainRow(&'a Chain, usize),
}

impl Source<'_> {
    /// For pixel (row `i`, column `j`): the position in the next frame, the
    /// expected depth there (NaN: unknown) and the validity so far.
    #[inline(always)]
    fn at(self, w: usize, i: usize, j: usize) -> (f32, f32, f32, f32) {
        let p = i * w + j;
        match self {
            Source::Current { motion, depth } => (
                j as f32 + 0.5 + motion.plane(0)[p],
                i as f32 + 0.5 + motion.plane(1)[p],
                depth.map_or(f32::NAN, |d| d[p]),
                1.0,
            ),
            Source::Chain(c) => (c.x[p], c.y[p], c.depth[p], c.valid[p]),
            Source::ChainRow(c, o) => {
                let q = j - o;
                (c.x[q], c.y[q], c.depth[q], c.valid[q])
            }
        }
    }

    /// Runs `f` with a [`Positions`] that writes, for the pixels `j0..j0 +
    /// m` of row `i` (`m <= BATCH`), what [`Source::at`] gives into
    /// `batch.x`, `.y`, `.d` and `.v` (the same values, a row slice at a
    /// time); one monomorphized loop per kind of source.
    #[inline(always)]
    fn with<R>(self, w: usize, f: impl SourceUser<R>) -> R {
        match self {
            Source::Current { motion, depth } => {
                let (mx, my) = (motion.plane(0), motion.plane(1));
                match depth {
                    Some(d) => f.run(&CurrentAt { mx, my, d, w }),
                    None => f.run(&CurrentAt { mx, my, d: (), w }),
                }
            }
            Source::Chain(c) => f.run(&ChainAt { c, w, first: 0 }),
            Source::ChainRow(c, first) => f.run(&ChainAt { c, w: 0, first }),
        }
    }
}

/// Fills a [`Batch`]'s positions, expected depths and validities for pixels
/// `j0..j0 + m` of row `i` (see [`Source::with`]). Every method is inlined,
/// so the loops are vectorized with the pass they run in.
trait Positions: Sync {
    fn fill(&self, i: usize, j0: usize, m: usize, b: &mut Batch);
}

/// The current frame's motion vectors, with its depth `d` (a slice) or
/// without (`()`: unknown expected depth).
struct CurrentAt<'a, D> {
    mx: &'a [f32],
    my: &'a [f32],
    d: D,
    w: usize,
}

impl Positions for CurrentAt<'_, &[f32]> {
    #[inline(always)]
    fn fill(&self, i: usize, j0: usize, m: usize, b: &mut Batch) {
        let p = i * self.w + j0;
        b.current_span(i, j0, &self.mx[p..p + m], &self.my[p..p + m]);
        b.d[..m].copy_from_slice(&self.d[p..p + m]);
    }
}

impl Positions for CurrentAt<'_, ()> {
    #[inline(always)]
    fn fill(&self, i: usize, j0: usize, m: usize, b: &mut Batch) {
        let p = i * self.w + j0;
        b.current_span(i, j0, &self.mx[p..p + m], &self.my[p..p + m]);
        b.d[..m].fill(f32::NAN);
    }
}

/// A chain into a history frame (`w` its row length; 0 for a run of one
/// row, [`Source::ChainRow`], read at the columns alone, less `first`).
struct ChainAt<'a> {
    c: &'a Chain,
    w: usize,
    first: usize,
}

impl Positions for ChainAt<'_> {
    #[inline(always)]
    fn fill(&self, i: usize, j0: usize, m: usize, b: &mut Batch) {
        let (c, w) = (self.c, self.w);
        let p0 = i * w + j0 - self.first;
        let p = p0..p0 + m;
        b.x[..m].copy_from_slice(&c.x[p.clone()]);
        b.y[..m].copy_from_slice(&c.y[p.clone()]);
        b.d[..m].copy_from_slice(&c.depth[p.clone()]);
        b.v[..m].copy_from_slice(&c.valid[p]);
    }
}

/// A loop generic over how positions are found (see [`Source::with`]).
trait SourceUser<R> {
    fn run<S: Positions>(self, at: &S) -> R;
}

/// Samples history frame `frame`'s color at the positions of `src`; buffers
/// come from `rec` when given.
pub(crate) fn hop_color(
    src: Source<'_>,
    frame: &HistoryFrame,
    pool: Option<&rayon::ThreadPool>,
    rec: Option<&Recycler>,
) -> ReprojectedFrame {
    src.with(frame.color.width, ColorHop { frame, pool, rec })
}

/// The color hop at one pixel: position (`x`, `y`) in `frame`, expected depth
/// `d` (NaN: unknown), validity so far `v`; returns RGBA and validity.
#[inline(always)]
fn color_pixel(frame: &HistoryFrame, x: f32, y: f32, d: f32, v: f32) -> ([f32; 4], f32) {
    Planes::of(frame).color(x, y, d, v)
}

/// A history frame's interleaved color and depth, split once per loop.
#[derive(Clone, Copy)]
struct Planes<'a> {
    rgba: &'a [[f32; 4]],
    depth: Option<&'a [f32]>,
    w: usize,
    h: usize,
}

impl<'a> Planes<'a> {
    #[inline(always)]
    fn of(frame: &'a HistoryFrame) -> Planes<'a> {
        let hist = &frame.color;
        Planes {
            rgba: hist.data.as_chunks::<4>().0,
            depth: frame.depth.as_deref(),
            w: hist.width,
            h: hist.height,
        }
    }

    /// [`Planes::color`] as a call: the few pixels off the fast path keep
    /// the batch loop small enough to be inlined whole (into the vectorized
    /// pass of [`crate::ops::simd`]).
    #[inline(never)]
    fn color_out_of_line(&self, x: f32, y: f32, d: f32, v: f32) -> ([f32; 4], f32) {
        self.color(x, y, d, v)
    }

    /// See [`color_pixel`].
    #[inline(always)]
    fn color(&self, x: f32, y: f32, d: f32, v: f32) -> ([f32; 4], f32) {
        if v <= 0.0 {
            return ([0.0; 4], 0.0);
        }
        let hdepth = if d.is_nan() { None } else { self.depth };
        if let Some((i, wt)) = interior(x, y, self.w, self.h, hdepth, d) {
            // The common case, bit-identical to the general one below.
            return (bilerp4(self.rgba, i, self.w, &wt), v);
        }
        let t = taps(x, y, self.w, self.h, hdepth, d);
        if t.sum <= 0.0 {
            return ([0.0; 4], 0.0);
        }
        (t.sample4(self.rgba), v * t.sum)
    }
}

/// The color hop of `src` into `frame` at pixel (row `i`, column `j`) alone;
/// equal to that pixel of [`hop_color`].
pub(crate) fn hop_color_pixel(
    src: Source<'_>,
    frame: &HistoryFrame,
    i: usize,
    j: usize,
) -> ([f32; 4], f32) {
    let (x, y, d, v) = src.at(frame.color.width, i, j);
    color_pixel(frame, x, y, d, v)
}

struct ColorHop<'a> {
    frame: &'a HistoryFrame,
    pool: Option<&'a rayon::ThreadPool>,
    rec: Option<&'a Recycler>,
}

/// A 4-plane image and a validity plane whose samples are all to be written.
fn outputs(w: usize, h: usize, rec: Option<&Recycler>) -> (Image, Vec<f32>) {
    match rec {
        Some(r) => (r.image(w, h, 4), r.take(w * h)),
        None => (Image::zeros(w, h, 4), vec![0.0; w * h]),
    }
}

impl SourceUser<ReprojectedFrame> for ColorHop<'_> {
    fn run<S: Positions>(self, at: &S) -> ReprojectedFrame {
        let frame = self.frame;
        let (w, h) = (frame.color.width, frame.color.height);
        let (mut color, mut valid) = outputs(w, h, self.rec);
        let [c0, c1, c2, c3] = planes4(&mut color);
        let planes = Planes::of(frame);
        par_rows(self.pool, [c0, c1, c2, c3, &mut valid], w, |i, out| {
            color_row(at, &planes, i, 0..w, &mut Planar(out))
        });
        ReprojectedFrame { color, valid }
    }
}

/// Where a row (or a run of a row) of reprojected color goes: pixel `t`
/// of the run gets RGBA `c` and validity `v`.
pub(crate) trait RowOut {
    /// Pixels in the run.
    fn len(&self) -> usize;
    /// Writes pixels `o..o + m` with `f(t)` for pixel `o + t` (`o + m <=
    /// len()`), the run checked once rather than pixel by pixel.
    fn put_run(&mut self, o: usize, m: usize, f: impl Pixels);
}

/// The RGBA and validity of pixel `t` of a run ([`RowOut::put_run`]).
pub(crate) trait Pixels {
    fn get(&mut self, t: usize) -> ([f32; 4], f32);
}

/// A function of the pixel as [`Pixels`].
pub(crate) struct PixFn<F>(pub(crate) F);

impl<F: FnMut(usize) -> ([f32; 4], f32)> Pixels for PixFn<F> {
    #[inline(always)]
    fn get(&mut self, t: usize) -> ([f32; 4], f32) {
        (self.0)(t)
    }
}

/// The pixels of a filled [`Batch`]: the fast path inline, the others
/// through [`Planes::color_out_of_line`].
struct BatchPixels<'b, 'p> {
    b: &'b Batch,
    planes: &'b Planes<'p>,
}

impl Pixels for BatchPixels<'_, '_> {
    #[inline(always)]
    fn get(&mut self, t: usize) -> ([f32; 4], f32) {
        let (b, planes) = (self.b, self.planes);
        if b.fast[t] {
            let (k, wt) = (b.idx[t] as usize, &b.weights(t));
            (bilerp4(planes.rgba, k, planes.w, wt), b.v[t])
        } else {
            planes.color_out_of_line(b.x[t], b.y[t], b.d[t], b.v[t])
        }
    }
}

/// A run written as five planes: R, G, B, A and validity.
pub(crate) struct Planar<'o>(pub(crate) [&'o mut [f32]; 5]);

impl RowOut for Planar<'_> {
    #[inline(always)]
    fn len(&self) -> usize {
        self.0.iter().map(|p| p.len()).min().unwrap_or(0)
    }
    #[inline(always)]
    fn put_run(&mut self, o: usize, m: usize, mut f: impl Pixels) {
        let [o0, o1, o2, o3, ov] = &mut self.0;
        let s = o..o + m;
        let (o0, o1, o2, o3, ov) = (
            &mut o0[s.clone()],
            &mut o1[s.clone()],
            &mut o2[s.clone()],
            &mut o3[s.clone()],
            &mut ov[s],
        );
        for t in 0..m {
            let (c, v) = f.get(t);
            (o0[t], o1[t], o2[t], o3[t], ov[t]) = (c[0], c[1], c[2], c[3], v);
        }
    }
}

/// A run written as interleaved RGBA pixels and a validity plane.
pub(crate) struct Interleaved<'o> {
    pub(crate) rgba: &'o mut [[f32; 4]],
    pub(crate) valid: &'o mut [f32],
}

impl RowOut for Interleaved<'_> {
    #[inline(always)]
    fn len(&self) -> usize {
        self.rgba.len().min(self.valid.len())
    }
    #[inline(always)]
    fn put_run(&mut self, o: usize, m: usize, mut f: impl Pixels) {
        let (rgba, valid) = (&mut self.rgba[o..o + m], &mut self.valid[o..o + m]);
        for t in 0..m {
            (rgba[t], valid[t]) = f.get(t);
        }
    }
}

/// Row `i` of the color hop with positions from `at` into the history
/// frame `planes`, columns `cols`, into `out` (at least `cols.len()` long;
/// that many pixels are written). Every pixel's values depend on that pixel
/// alone (not on where a batch starts).
#[inline(always)]
fn color_row<S: Positions, O: RowOut>(
    at: &S,
    planes: &Planes<'_>,
    i: usize,
    cols: std::ops::Range<usize>,
    out: &mut O,
) {
    let (w, h) = (planes.w, planes.h);
    assert!(cols.end <= w, "columns {cols:?} outside a row of {w}");
    assert!(out.len() >= cols.len(), "an output shorter than the run");
    let mut b = Batch::new();
    for j0 in cols.clone().step_by(BATCH) {
        let m = BATCH.min(cols.end - j0);
        b.fill(at, i, j0, m, w, h, planes.depth);
        b.prefetch_ahead(planes, m);
        out.put_run(j0 - cols.start, m, BatchPixels { b: &b, planes });
    }
}

/// Row `i` of [`hop_color`] alone (the same bits), columns `j0..j0 + n`
/// with `n` the length of `out` ([`Planar`] or [`Interleaved`]).
#[inline(always)]
pub(crate) fn hop_color_row<O: RowOut>(
    src: Source<'_>,
    frame: &HistoryFrame,
    i: usize,
    j0: usize,
    out: &mut O,
) {
    src.with(frame.color.width, ColorRow { frame, i, j0, out });
}

struct ColorRow<'a, 'o, O> {
    frame: &'a HistoryFrame,
    i: usize,
    j0: usize,
    out: &'o mut O,
}

impl<O: RowOut> SourceUser<()> for ColorRow<'_, '_, O> {
    #[inline(always)]
    fn run<S: Positions>(self, at: &S) {
        let cols = self.j0..self.j0 + self.out.len();
        color_row(at, &Planes::of(self.frame), self.i, cols, self.out);
    }
}

/// Follows the motion vectors of history frame `frame` one hop further.
/// `frame.motion` must be present.
pub(crate) fn hop_chain(
    src: Source<'_>,
    frame: &HistoryFrame,
    pool: Option<&rayon::ThreadPool>,
    rec: Option<&Recycler>,
) -> Chain {
    src.with(frame.color.width, ChainHop { frame, pool, rec })
}

struct ChainHop<'a> {
    frame: &'a HistoryFrame,
    pool: Option<&'a rayon::ThreadPool>,
    rec: Option<&'a Recycler>,
}

impl SourceUser<Chain> for ChainHop<'_> {
    fn run<S: Positions>(self, at: &S) -> Chain {
        let frame = self.frame;
        let (w, h) = (frame.color.width, frame.color.height);
        let n = w * h;
        let take = || self.rec.map_or_else(|| vec![0.0; n], |r| r.take(n));
        let mut chain = Chain {
            x: take(),
            y: take(),
            depth: take(),
            valid: take(),
        };
        let Chain { x, y, depth, valid } = &mut chain;
        par_rows(self.pool, [x, y, depth, valid], w, |i, [rx, ry, rd, rv]| {
            chain_row(at, frame, i, 0..w, [rx, ry, rd, rv])
        });
        chain
    }
}

/// Row `i` of [`hop_chain`] with positions from `at` into history frame
/// `frame`, columns `cols`: positions, expected depth and validity of
/// column `j` into `out[..][j - cols.start]` (each at least `cols.len()`
/// long). Every pixel's values depend on that pixel alone.
#[inline(always)]
fn chain_row<S: Positions>(
    at: &S,
    frame: &HistoryFrame,
    i: usize,
    cols: std::ops::Range<usize>,
    out: [&mut [f32]; 4],
) {
    let (w, h) = (frame.color.width, frame.color.height);
    assert!(cols.end <= w, "columns {cols:?} outside a row of {w}");
    let motion = frame
        .motion
        .as_ref()
        .expect("hop_chain needs the frame's motion vectors");
    let (mx, my) = (motion.plane(0), motion.plane(1));
    let hdepth = frame.depth.as_deref();
    let [rx, ry, rd, rv] = out;
    let n = cols.len();
    let (rx, ry, rd, rv) = (&mut rx[..n], &mut ry[..n], &mut rd[..n], &mut rv[..n]);
    let mut b = Batch::new();
    for q in 0..n {
        let (t, j) = (q % BATCH, cols.start + q);
        if t == 0 {
            b.fill(at, i, j, BATCH.min(cols.end - j), w, h, hdepth);
        }
        let (x, y, d, v) = (b.x[t], b.y[t], b.d[t], b.v[t]);
        if b.fast[t] {
            // The common case, bit-identical to the general one below.
            let (k, wt) = (b.idx[t] as usize, &b.weights(t));
            rx[q] = x + bilerp(mx, k, w, wt);
            ry[q] = y + bilerp(my, k, w, wt);
            rd[q] = match hdepth {
                Some(hd) => bilerp(hd, k, w, wt),
                None => f32::NAN,
            };
            rv[q] = v;
            continue;
        }
        rx[q] = 0.0;
        ry[q] = 0.0;
        rd[q] = f32::NAN;
        rv[q] = 0.0;
        if v <= 0.0 {
            continue;
        }
        let dt = if d.is_nan() { None } else { hdepth };
        let t = taps(x, y, w, h, dt, d);
        if t.sum <= 0.0 {
            continue;
        }
        rx[q] = x + t.sample(mx);
        ry[q] = y + t.sample(my);
        if let Some(hd) = hdepth {
            rd[q] = t.sample(hd);
        }
        rv[q] = v * t.sum;
    }
}

/// Row `i` of [`hop_chain`] alone (the same bits), columns `cols`, into
/// `out`, a run of one row ([`Chain::row`] at least `cols.len()` long),
/// compiled for the CPU's widest vectors ([`crate::ops::simd`]).
/// `frame.motion` must be present.
pub(crate) fn hop_chain_row(
    src: Source<'_>,
    frame: &HistoryFrame,
    i: usize,
    cols: std::ops::Range<usize>,
    out: &mut Chain,
) {
    crate::ops::simd(ChainRowJob {
        src,
        frame,
        i,
        cols,
        out,
    });
}

struct ChainRowJob<'a, 'o> {
    src: Source<'a>,
    frame: &'a HistoryFrame,
    i: usize,
    cols: std::ops::Range<usize>,
    out: &'o mut Chain,
}

impl pulp::WithSimd for ChainRowJob<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let ChainRowJob {
            src,
            frame,
            i,
            cols,
            out,
        } = self;
        src.with(
            frame.color.width,
            ChainRowUser {
                frame,
                i,
                cols,
                out,
            },
        );
    }
}

struct ChainRowUser<'a, 'o> {
    frame: &'a HistoryFrame,
    i: usize,
    cols: std::ops::Range<usize>,
    out: &'o mut Chain,
}

impl SourceUser<()> for ChainRowUser<'_, '_> {
    #[inline(always)]
    fn run<S: Positions>(self, at: &S) {
        let Chain { x, y, depth, valid } = self.out;
        chain_row(at, self.frame, self.i, self.cols, [x, y, depth, valid]);
    }
}

/// The map from a current pixel and its planar depth to a position and
/// expected depth in a history frame (static scene, both cameras known).
pub(crate) struct CameraMap {
    r0: DVec4,
    r1: DVec4,
    r3: DVec4,
    zrow: DVec4,
    to_clip: DMat4,
    wf: f64,
    hf: f64,
}

impl CameraMap {
    /// The map of `current` (depth and camera needed) into `frame` (camera needed).
    pub(crate) fn new(current: &PreparedFrame, frame: &HistoryFrame) -> CameraMap {
        let cc = current
            .camera
            .expect("camera reprojection needs the current camera");
        let hc = frame
            .camera
            .expect("camera reprojection needs the history camera");
        CameraMap::from_cameras(&cc, &hc, current.width(), current.height())
    }

    /// The map from a `width` x `height` frame seen by camera `cc` into
    /// the frame seen by camera `hc`.
    pub(crate) fn from_cameras(
        cc: &crate::frame::Camera,
        hc: &crate::frame::Camera,
        width: usize,
        height: usize,
    ) -> CameraMap {
        let cam_to_world = cc.world_to_camera.as_dmat4().inverse();
        let cam_to_ndc: DMat4 = cc.world_to_ndc.as_dmat4() * cam_to_world;
        // Current camera space to the history frame's clip space and planar depth.
        let to_clip: DMat4 = hc.world_to_ndc.as_dmat4() * cam_to_world;
        let to_cam: DMat4 = hc.world_to_camera.as_dmat4() * cam_to_world;
        CameraMap {
            r0: cam_to_ndc.row(0),
            r1: cam_to_ndc.row(1),
            r3: cam_to_ndc.row(3),
            zrow: to_cam.row(2),
            to_clip,
            wf: width as f64,
            hf: height as f64,
        }
    }

    /// [`CameraMap::position`] of pixel (row `i`, column `j`) at planar
    /// depth `d`: the position in the history frame (pixel centers at
    /// `+0.5`) and the depth expected there.
    pub(crate) fn position_at(&self, i: usize, j: usize, d: f32) -> Option<(f32, f32, f32)> {
        self.position(self.row(i), j, d)
    }

    /// The row term of row `i` (see [`CameraMap::position`]).
    #[inline(always)]
    fn row(&self, i: usize) -> DVec4 {
        let v = (i as f64 + 0.5) / self.hf;
        self.r1 - v * self.r3
    }

    /// Position in the history frame and expected depth there of column `j`
    /// with row term `b` at planar depth `d`; `None` behind either camera.
    #[inline(always)]
    fn position(&self, b: DVec4, j: usize, d: f32) -> Option<(f32, f32, f32)> {
        let u = (j as f64 + 0.5) / self.wf;
        let a: DVec4 = self.r0 - u * self.r3;
        let det = a.x * b.y - a.y * b.x;
        if det.abs() < 1e-18 {
            return None;
        }
        // (a . X = 0, b . X = 0) with X = (x, y, d, 1), or the direction (x, y, 1, 0).
        let far = d >= FAR_DEPTH;
        let (ac, bc, dz, dw) = if far {
            (-a.z, -b.z, 1.0, 0.0)
        } else {
            let d = d as f64;
            (-(a.z * d + a.w), -(b.z * d + b.w), d, 1.0)
        };
        let p = DVec4::new(
            (ac * b.y - a.y * bc) / det,
            (a.x * bc - ac * b.x) / det,
            dz,
            dw,
        );
        let zk = self.zrow.dot(p);
        let clip = self.to_clip * p;
        if zk <= 1e-9 || clip.w <= 1e-12 {
            return None;
        }
        let px = (clip.x / clip.w * self.wf) as f32;
        let py = (clip.y / clip.w * self.hf) as f32;
        let expected = if far { f32::MAX } else { zk as f32 };
        Some((px, py, expected))
    }

    /// RGBA and validity of `frame` seen from column `j` of the row with term
    /// `b`, at planar depth `d`.
    #[inline(always)]
    fn color(&self, frame: &HistoryFrame, b: DVec4, j: usize, d: f32) -> ([f32; 4], f32) {
        match self.position(b, j, d) {
            // The expected depth is known: `color_pixel` tests it when the
            // history frame has depth.
            Some((px, py, expected)) => color_pixel(frame, px, py, expected, 1.0),
            None => ([0.0; 4], 0.0),
        }
    }

    /// Row `i` of [`reproject_camera`] (the same bits), columns `j0..j0 +
    /// out.len()`: RGBA and validity into `out`; `depth` is the current
    /// frame's.
    pub(crate) fn color_row<O: RowOut>(
        &self,
        frame: &HistoryFrame,
        depth: &[f32],
        i: usize,
        j0: usize,
        out: &mut O,
    ) {
        let w = self.wf as usize;
        let n = out.len();
        assert!(j0 + n <= w, "columns {j0}..{} outside a row of {w}", j0 + n);
        let b = self.row(i);
        let drow = &depth[i * w + j0..i * w + j0 + n];
        out.put_run(0, n, PixFn(|t| self.color(frame, b, j0 + t, drow[t])));
    }

    /// [`CameraMap::color`] at pixel (row `i`, column `j`) alone; equal to
    /// that pixel of [`reproject_camera`].
    pub(crate) fn color_at(
        &self,
        frame: &HistoryFrame,
        depth: &[f32],
        i: usize,
        j: usize,
    ) -> ([f32; 4], f32) {
        let w = self.wf as usize;
        self.color(frame, self.row(i), j, depth[i * w + j])
    }
}

/// Reprojects history frame `frame` with the current frame's depth and both
/// cameras (static scene). The current frame must have depth and a camera and
/// the history frame a camera.
pub(crate) fn reproject_camera(
    current: &PreparedFrame,
    frame: &HistoryFrame,
    pool: Option<&rayon::ThreadPool>,
    rec: Option<&Recycler>,
) -> ReprojectedFrame {
    let (w, h) = (current.width(), current.height());
    let depth = current
        .depth
        .as_deref()
        .expect("camera reprojection needs depth");
    let map = CameraMap::new(current, frame);
    let (mut color, mut valid) = outputs(w, h, rec);
    let [c0, c1, c2, c3] = planes4(&mut color);
    par_rows(pool, [c0, c1, c2, c3, &mut valid], w, |i, out| {
        map.color_row(frame, depth, i, 0, &mut Planar(out))
    });
    ReprojectedFrame { color, valid }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A deterministic pseudo-random value in `[0, 1)`.
    pub(crate) fn rnd(seed: &mut u64) -> f32 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*seed >> 40) as f32 / (1u64 << 24) as f32
    }

    /// A history frame with depth layers (near, far, empty sky, some exact
    /// tie values), motion leading partly out of the frame.
    fn frame(w: usize, h: usize, seed: &mut u64) -> HistoryFrame {
        let n = w * h;
        let mut color = Image::zeros(w, h, 4);
        for v in &mut color.data {
            *v = rnd(seed) * 4.0;
        }
        let depth = (0..n)
            .map(|_| match (rnd(seed) * 5.0) as u32 {
                0 => 1e10,
                1 => 10.0,
                2 => 11.0,
                3 => 10.0 + rnd(seed),
                _ => 3.0 + rnd(seed),
            })
            .collect();
        let mut motion = Image::zeros(w, h, 2);
        for v in &mut motion.data {
            *v = (rnd(seed) - 0.5) * 6.0;
        }
        HistoryFrame {
            color: crate::frame::RgbaImage::from_planes(&color, None),
            depth: Some(depth),
            motion: Some(motion),
            camera: None,
            frame_index: None,
        }
    }

    /// The batched fast paths of the color and chain hops give exactly what
    /// the general bilinear taps give, pixel by pixel, at borders, depth
    /// edges, empty depth, unknown depth and with invalid sources.
    #[test]
    fn fast_paths_equal_the_general_taps_bit_for_bit() {
        let (w, h) = (150, 37);
        let n = w * h;
        let mut seed = 7;
        let hist = frame(w, h, &mut seed);
        let older = frame(w, h, &mut seed);
        let mut motion = Image::zeros(w, h, 2);
        for v in &mut motion.data {
            *v = (rnd(&mut seed) - 0.5) * 8.0;
        }
        motion.data[5] = f32::NAN;
        let mut depth: Vec<f32> = (0..n)
            .map(|_| match (rnd(&mut seed) * 4.0) as u32 {
                0 => 1e10,
                1 => 10.5,
                _ => 3.0 + 8.0 * rnd(&mut seed),
            })
            .collect();
        depth[9] = f32::NAN;
        let hd = hist.depth.as_deref().unwrap();
        let hist_planes = hist.color.to_planes();
        let older_planes = older.color.to_planes();
        let [p0, p1, p2, p3] = [0, 1, 2, 3].map(|c| hist_planes.plane(c));
        let (mx, my) = (
            hist.motion.as_ref().unwrap().plane(0),
            hist.motion.as_ref().unwrap().plane(1),
        );
        for with_depth in [true, false] {
            let src = Source::Current {
                motion: &motion,
                depth: with_depth.then_some(&depth[..]),
            };
            let rep = hop_color(src, &hist, None, None);
            let chain = hop_chain(src, &hist, None, None);
            for i in 0..h {
                for j in 0..w {
                    let p = i * w + j;
                    let (x, y, d, v) = src.at(w, i, j);
                    let t = taps(x, y, w, h, if d.is_nan() { None } else { Some(hd) }, d);
                    let (c, vv) = if t.sum > 0.0 {
                        (
                            [t.sample(p0), t.sample(p1), t.sample(p2), t.sample(p3)],
                            v * t.sum,
                        )
                    } else {
                        ([0.0; 4], 0.0)
                    };
                    let got = [0, 1, 2, 3].map(|c| rep.color.plane(c)[p].to_bits());
                    assert_eq!(got, c.map(f32::to_bits), "color at ({j}, {i})");
                    assert_eq!(
                        rep.valid[p].to_bits(),
                        vv.to_bits(),
                        "validity at ({j}, {i})"
                    );
                    let (ex, ey, ed, ev) = if t.sum > 0.0 {
                        (x + t.sample(mx), y + t.sample(my), t.sample(hd), v * t.sum)
                    } else {
                        (0.0, 0.0, f32::NAN, 0.0)
                    };
                    assert_eq!(chain.x[p].to_bits(), ex.to_bits(), "chain x at ({j}, {i})");
                    assert_eq!(chain.y[p].to_bits(), ey.to_bits(), "chain y at ({j}, {i})");
                    assert_eq!(
                        chain.depth[p].to_bits(),
                        ed.to_bits(),
                        "chain depth at ({j}, {i})"
                    );
                    assert_eq!(
                        chain.valid[p].to_bits(),
                        ev.to_bits(),
                        "chain validity at ({j}, {i})"
                    );
                }
            }
            // The second hop starts from the chain (validity below 1, some 0).
            let rep2 = hop_color(Source::Chain(&chain), &older, None, None);
            for i in 0..h {
                for j in 0..w {
                    let p = i * w + j;
                    let (x, y, d, v) = (chain.x[p], chain.y[p], chain.depth[p], chain.valid[p]);
                    let expected = if v <= 0.0 {
                        ([0.0; 4], 0.0)
                    } else {
                        let od = older.depth.as_deref().unwrap();
                        let t = taps(x, y, w, h, if d.is_nan() { None } else { Some(od) }, d);
                        if t.sum > 0.0 {
                            let q = [0, 1, 2, 3].map(|c| t.sample(older_planes.plane(c)));
                            (q, v * t.sum)
                        } else {
                            ([0.0; 4], 0.0)
                        }
                    };
                    let got = [0, 1, 2, 3].map(|c| rep2.color.plane(c)[p].to_bits());
                    assert_eq!(
                        got,
                        expected.0.map(f32::to_bits),
                        "hop 2 color at ({j}, {i})"
                    );
                    assert_eq!(
                        rep2.valid[p].to_bits(),
                        expected.1.to_bits(),
                        "hop 2 validity at ({j}, {i})"
                    );
                }
            }
        }
    }

    #[test]
    fn depth_test_is_relative_and_far_matches_far() {
        assert!(depth_match(10.0, 10.5));
        assert!(!depth_match(10.0, 12.0));
        assert!(!depth_match(5.0, 1e10));
        assert!(depth_match(1e10, f32::MAX));
        assert!(!depth_match(1e10, 5.0));
        assert!(
            !depth_match(9.5e8, 1e9),
            "just below empty depth is not empty"
        );
        assert!(depth_match(0.0, 0.0) && !depth_match(0.0, 1e-6));
        assert!(!depth_match(f32::NAN, 1.0) && !depth_match(1.0, f32::NAN));
        // The window is `|expected - seen| <= DEPTH_TOLERANCE * min(expected,
        // seen)` up to rounding at its ends.
        let mut seed = 3;
        for _ in 0..100_000 {
            let e = 0.01 + 100.0 * rnd(&mut seed);
            let s = e * (0.8 + 0.4 * rnd(&mut seed));
            let ratio = (e - s).abs() / (DEPTH_TOLERANCE * e.min(s));
            if (ratio - 1.0).abs() > 1e-5 {
                assert_eq!(depth_match(e, s), ratio <= 1.0, "{e} {s}");
            }
        }
    }

    #[test]
    fn floor_small_is_the_truncating_cast_below_2_pow_22() {
        let mut seed = 5;
        let check = |u: f32| assert_eq!(floor_small(u), u as i32, "{u}");
        for k in 0..4096 {
            let base = k as f32 * 1023.0;
            for u in [base, base + 0.5, base + 0.999_999, base - 1e-3] {
                check(u.max(0.0));
            }
            // Just below and above integers, where rounding to nearest differs.
            check(f32::from_bits((k as f32 + 1.0).to_bits() - 1));
            check(f32::from_bits((k as f32 + 1.0).to_bits() + 1));
            check(rnd(&mut seed) * 4_194_303.0);
        }
        // The largest values it serves (positions in frames of sides below 2^22).
        check(4_194_303.0);
        check(f32::from_bits(4_194_304f32.to_bits() - 1));
        // Anything else gives some value without a panic.
        for u in [f32::NAN, f32::INFINITY, -1e30, 1e30, -5.5] {
            std::hint::black_box(floor_small(u));
        }
    }

    #[test]
    fn taps_drop_outside_and_mismatching_depth() {
        // 2x1 image; position between the two pixel centres.
        let d = [1.0f32, 5.0];
        let t = taps(1.0, 0.5, 2, 1, None, f32::NAN);
        assert!((t.sum - 1.0).abs() < 1e-6);
        let t = taps(1.0, 0.5, 2, 1, Some(&d), 1.0);
        assert!((t.sum - 0.5).abs() < 1e-6, "only the near tap is kept");
        assert_eq!(t.sample(&[3.0, 7.0]), 3.0);
        let t = taps(-0.6, 0.5, 2, 1, None, f32::NAN);
        assert_eq!(t.sum, 0.0);
        let t = taps(f32::NAN, 0.5, 2, 1, None, f32::NAN);
        assert_eq!(t.sum, 0.0);
    }
}
