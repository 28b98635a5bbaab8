//! Hole filling: first from the reprojected history (composited under the
//! missing part of each pixel, weighted by validity), then spatial pyramid
//! push-pull inpainting (Gortler et al., "The Lumigraph", 1996) for what is
//! still missing.
//!
//! A hole is a pixel with coverage A < 1. The color is premultiplied, so a
//! soft border pixel holds `A * true color` and is completed as
//! `out = premult + (1 - A) * fill`, with A = 1 afterwards. Pixels with
//! coverage 1 (sky and empty background included) are never touched.

use rayon::prelude::*;

use super::{bbox_below, par_bands_mut, rgba_planes_mut, Rect};
use crate::frame::Image;
use crate::temporal::ReprojectedFrame;

pub(crate) mod edge;
pub(crate) mod far;
mod sparse;

pub use far::{push_pull_far, OwnCoverage, FAR_TOLERANCE};

/// Coverage at or above this counts as complete (snaps to exactly 1).
pub const FULL: f32 = 1.0 - 1e-5;

/// One channel of a pixel covered `coverage` of the way by what was
/// rendered (`rendered`, premultiplied by it), the rest by a fill (`fill`,
/// premultiplied by the result's `alpha`): the render over the fill, the
/// result premultiplied by `alpha`. An inserted object's soft edge over a
/// reconstruction's hole keeps the share it covers this way.
pub fn over_fill(rendered: f32, coverage: f32, fill: f32, alpha: f32) -> f32 {
    if alpha > 0.0 {
        rendered + (alpha - coverage).max(0.0) * (fill / alpha)
    } else {
        fill
    }
}

/// Where the holes of an image are.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Holes {
    /// Bounding box of the pixels with A below [`FULL`].
    pub rect: Rect,
    /// Number of such pixels.
    pub count: usize,
}

/// Finds the pixels of a 4-plane image whose alpha (plane 3) is below [`FULL`].
pub fn find_holes(img: &Image) -> Option<Holes> {
    bbox_below(img.plane(3), img.width, img.height, FULL).map(|(rect, count)| Holes { rect, count })
}

/// Drops the color of every pixel of `rect` whose coverage is below
/// `floor` (the `coverage_floor` parameter): RGB and A become 0, so the
/// fill completes it whole. A reconstruction's faintly covered pixels
/// hold the edges of splats, mostly from the wrong surface, and weigh in
/// the fill with their coverage; the fill from the confidently covered
/// ones (and the history) is closer.
/// The set of hole pixels does not change.
pub fn drop_faint(img: &mut Image, rect: Rect, floor: f32) {
    if floor <= 0.0 {
        return;
    }
    let w = img.width;
    par_bands_mut(img, rect.y0, rect.y1).for_each(|(_, [r, g, b, a])| {
        for row in 0..a.len() / w {
            for x in row * w + rect.x0..row * w + rect.x1 {
                if a[x] < floor {
                    (r[x], g[x], b[x], a[x]) = (0.0, 0.0, 0.0, 0.0);
                }
            }
        }
    });
}

/// How many pixels of an image have at least a given coverage, counted
/// over any square of it in constant time (a summed-area table over a
/// rectangle grown by the squares' radius).
pub struct KnownCounts {
    /// Counts of the pixels above `outer`'s rows and left of its columns:
    /// `(outer.height() + 1) x (outer.width() + 1)`, row-major.
    sat: Vec<u32>,
    outer: Rect,
    radius: usize,
    size: (usize, usize),
}

impl KnownCounts {
    /// The counts for the squares of `radius` around the pixels of `rect`,
    /// of the pixels whose coverage (plane 3) is at least `floor`.
    pub fn new(img: &Image, rect: Rect, radius: usize, floor: f32) -> KnownCounts {
        let (w, h) = (img.width, img.height);
        let a = img.plane(3);
        let outer = rect.expand(radius, w, h);
        let stride = outer.width() + 1;
        let mut sat = vec![0u32; stride * (outer.height() + 1)];
        // Prefix sums along each row (in parallel), then down the columns.
        sat[stride..]
            .par_chunks_mut(stride)
            .enumerate()
            .for_each(|(y, row)| {
                let src = &a[(outer.y0 + y) * w + outer.x0..(outer.y0 + y) * w + outer.x1];
                let mut run = 0u32;
                for (o, &c) in row[1..].iter_mut().zip(src) {
                    run += u32::from(c >= floor);
                    *o = run;
                }
            });
        for y in 1..=outer.height() {
            let (above, here) = sat.split_at_mut(y * stride);
            for (o, &u) in here[..stride].iter_mut().zip(&above[(y - 1) * stride..]) {
                *o += u;
            }
        }
        KnownCounts {
            sat,
            outer,
            radius,
            size: (w, h),
        }
    }

    /// The share of the pixels within the radius of (`x`, `y`) (a square,
    /// clipped to the image) that are known. (`x`, `y`) must be inside the
    /// rectangle the counts were made for.
    pub fn share(&self, x: usize, y: usize) -> f32 {
        let (w, h) = self.size;
        let r = self.radius;
        let o = self.outer;
        let (ya, yb) = (y.saturating_sub(r) - o.y0, (y + r + 1).min(h) - o.y0);
        let (xa, xb) = (x.saturating_sub(r) - o.x0, (x + r + 1).min(w) - o.x0);
        let stride = o.width() + 1;
        let at = |yy: usize, xx: usize| self.sat[yy * stride + xx];
        let known = at(yb, xb) + at(ya, xa) - at(ya, xb) - at(yb, xa);
        known as f32 / ((yb - ya) * (xb - xa)) as f32
    }
}

/// Composites a reprojected history frame under the missing part of every
/// hole pixel inside `rect`: `C += (1 - A) * v * H`, `A += (1 - A) * v * H.a`
/// with `v` the history's validity. Returns the holes that remain.
pub fn fill_from_history(img: &mut Image, history: &ReprojectedFrame, rect: Rect) -> Option<Holes> {
    let n = img.len();
    assert_eq!(history.color.len(), n, "history and frame sizes differ");
    let w = img.width;
    let (hist, valid) = (&history.color.data, &history.valid);
    fill_from_history_with(
        img,
        rect,
        |y, x| {
            let p = y * w + x;
            (
                [hist[p], hist[n + p], hist[2 * n + p], hist[3 * n + p]],
                valid[p],
            )
        },
        |y, x0, out| {
            let s = y * w + x0..y * w + x0 + out[0].len();
            let [o0, o1, o2, o3, ov] = out;
            for (c, o) in [o0, o1, o2, o3].into_iter().enumerate() {
                o.copy_from_slice(&hist[c * n + s.start..c * n + s.end]);
            }
            ov.copy_from_slice(&valid[s]);
        },
    )
}

/// Hole runs at least this long take the history as a run
/// (`fill_from_history_with`'s `span`), shorter ones pixel by pixel.
const MIN_RUN: usize = 8;

/// Stretches of a row without holes are skipped this many pixels at a time.
const SKIP: usize = 16;

/// [`fill_from_history`] with the history given pixel by pixel or in runs
/// of a row: `sample(row, column)` is the reprojected history's RGBA and
/// validity there, and `span(row, x0, out)` writes the same for columns
/// `x0..x0 + out[0].len()` into `out` (RGBA, validity), as
/// [`crate::temporal::Sampler`] gives them; asked only at hole pixels, once
/// each, from the pool's threads (runs of 8 or more hole pixels
/// through `span`). Holes are usually a small part of the frame, so this
/// costs far less than reprojecting the whole frame.
pub fn fill_from_history_with<F, S>(
    img: &mut Image,
    rect: Rect,
    sample: F,
    span: S,
) -> Option<Holes>
where
    F: Fn(usize, usize) -> ([f32; 4], f32) + Sync,
    S: Fn(usize, usize, [&mut [f32]; 5]) + Sync,
{
    fill_from_history_on(img, rect, sample, span, false).map(|(holes, _)| holes)
}

/// [`fill_from_history_with`], also returning the pixels still missing
/// ((column, row), in row order), as [`push_pull_at`] takes them.
pub fn fill_from_history_listing<F, S>(
    img: &mut Image,
    rect: Rect,
    sample: F,
    span: S,
) -> Option<(Holes, Vec<(u32, u32)>)>
where
    F: Fn(usize, usize) -> ([f32; 4], f32) + Sync,
    S: Fn(usize, usize, [&mut [f32]; 5]) + Sync,
{
    fill_from_history_on(img, rect, sample, span, true)
}

/// [`fill_from_history_with`]; with `listing`, the remaining hole pixels
/// too (else an empty list).
fn fill_from_history_on<F, S>(
    img: &mut Image,
    rect: Rect,
    sample: F,
    span: S,
    listing: bool,
) -> Option<(Holes, Vec<(u32, u32)>)>
where
    F: Fn(usize, usize) -> ([f32; 4], f32) + Sync,
    S: Fn(usize, usize, [&mut [f32]; 5]) + Sync,
{
    let w = img.width;
    let parts: Vec<_> = par_bands_mut(img, rect.y0, rect.y1)
        .map(|(y0, [r, g, b, a])| {
            let mut found: Option<(Rect, usize)> = None;
            let mut list = Vec::new();
            let rows = a.len() / w;
            // One run of history: R, G, B, A, validity (`w` each).
            let mut run = Vec::new();
            for dy in 0..rows {
                let y = y0 + dy;
                if super::row_min(&a[dy * w + rect.x0..dy * w + rect.x1]) >= FULL {
                    continue;
                }
                let mut first = None;
                let mut last = 0;
                let mut count = 0;
                // Columns `run_at..run_end` of the row are in `run`; the
                // short run being sampled pixel by pixel ends at `short_end`.
                let (mut run_at, mut run_end, mut short_end) = (0, 0, 0);
                let mut x = rect.x0;
                while x < rect.x1 {
                    let i = dy * w + x;
                    let cov = a[i];
                    if cov >= FULL {
                        // Stretches without holes are skipped a chunk at a
                        // time (a test that vectorizes).
                        x += 1;
                        while x + SKIP <= rect.x1 {
                            let s = dy * w + x;
                            if super::row_min(&a[s..s + SKIP]) < FULL {
                                break;
                            }
                            x += SKIP;
                        }
                        continue;
                    }
                    if x >= run_end && x >= short_end {
                        // A new run of holes: taken as a run when long enough.
                        let end = a[i..dy * w + rect.x1]
                            .iter()
                            .position(|&c| c >= FULL)
                            .map_or(rect.x1, |e| x + e);
                        if end - x >= MIN_RUN {
                            if run.is_empty() {
                                run = vec![0.0f32; 5 * w];
                            }
                            let n = end - x;
                            let mut parts = run.chunks_mut(w).map(|p| &mut p[..n]);
                            let out = std::array::from_fn(|_| parts.next().expect("5 planes"));
                            span(y, x, out);
                            (run_at, run_end) = (x, end);
                        } else {
                            short_end = end;
                        }
                    }
                    let (hc, v) = if x < run_end {
                        let t = x - run_at;
                        let q = |c: usize| run[c * w + t];
                        ([q(0), q(1), q(2), q(3)], q(4))
                    } else {
                        sample(y, x)
                    };
                    let ha = hc[3];
                    let mut cov_new = cov;
                    if v > 0.0 && ha > 0.0 {
                        let k = (1.0 - cov) * v;
                        r[i] += k * hc[0];
                        g[i] += k * hc[1];
                        b[i] += k * hc[2];
                        cov_new = (cov + k * ha).min(1.0);
                    }
                    if cov_new >= FULL {
                        a[i] = 1.0;
                    } else {
                        a[i] = cov_new;
                        if listing {
                            list.push((x as u32, y as u32));
                        }
                        first.get_or_insert(x);
                        last = x;
                        count += 1;
                    }
                    x += 1;
                }
                if let Some(x0) = first {
                    let r = Rect {
                        x0,
                        y0: y,
                        x1: last + 1,
                        y1: y + 1,
                    };
                    found = Some(match found {
                        Some((o, c)) => (o.union(&r), c + count),
                        None => (r, count),
                    });
                }
            }
            (found, list)
        })
        .collect();
    let mut all = Vec::new();
    let mut found: Option<(Rect, usize)> = None;
    for (f, list) in parts {
        found = crate::ops::merge_boxes(found, f);
        all.extend(list);
    }
    found.map(|(rect, count)| (Holes { rect, count }, all))
}

/// A frame's own spatial fill of its holes, without history, at half
/// resolution: the holes' window ([`fill_window`]) in 2x2 box sums of its
/// pixels covered at least a floor (as [`drop_faint`] leaves them; the
/// weight clamped to 1, as the push-pull's pull step does), then
/// [`push_pull_sqrt`] over it. Where history fills a hole it is first
/// pulled toward this fill by a share ([`SpatialFill::pull`]): a fill
/// carried from frame to frame in a hole that stays in view otherwise
/// remembers the frame it was first made in, however long ago (what a
/// chunk of a sequence started with a pre-roll cannot know: docs/farm.md,
/// "Which pre-roll"). Half resolution because the fill is smooth anyway
/// and the whole window is filled: at full resolution it cost more than
/// the rest of the hole fill on frame-wide holes.
#[derive(Debug, Clone)]
pub struct SpatialFill {
    /// The window at half resolution: 3 planes of fill (RGB, straight),
    /// then the share of the refresh each pixel takes.
    img: Image,
    window: Rect,
}

impl SpatialFill {
    /// The fill of the holes inside `holes` of an image given as its 4
    /// planes (`rgba`: RGB premultiplied, A coverage, `width` pixels a
    /// row), from its pixels covered at least `floor`. `None` when the
    /// window has no fully covered pixel.
    ///
    /// With `depth` (the frame's planar depth), the fill takes the
    /// background side of silhouettes ([`push_pull_far`], each half-resolution
    /// pixel at the farthest depth of its covered pixels), as the spatial
    /// fill of the holes does.
    pub fn new(
        rgba: [&[f32]; 4],
        width: usize,
        holes: Rect,
        floor: f32,
        depth: Option<&[f32]>,
    ) -> Option<SpatialFill> {
        let height = rgba[3].len() / width.max(1);
        let window = fill_window(holes, width, height);
        let (hw, hh) = (window.width().div_ceil(2), window.height().div_ceil(2));
        let mut img = Image::try_zeros(hw, hh, 4).ok()?;
        let known: usize = par_bands_mut(&mut img, 0, hh)
            .map(|(y0, [r, g, b, a])| {
                let mut known = 0;
                for dy in 0..a.len() / hw {
                    let y = window.y0 + 2 * (y0 + dy);
                    for x in 0..hw {
                        let mut sum = [0f32; 4];
                        let mut full = 0;
                        for yy in y..(y + 2).min(window.y1) {
                            let xa = window.x0 + 2 * x;
                            for xx in xa..(xa + 2).min(window.x1) {
                                let p = yy * width + xx;
                                let c = rgba[3][p];
                                if c >= floor && c > 0.0 {
                                    for k in 0..3 {
                                        sum[k] += rgba[k][p];
                                    }
                                    sum[3] += c;
                                    full += usize::from(c >= FULL);
                                }
                            }
                        }
                        if sum[3] > 1.0 {
                            let k = 1.0 / sum[3];
                            sum = [sum[0] * k, sum[1] * k, sum[2] * k, 1.0];
                        }
                        let o = dy * hw + x;
                        (r[o], g[o], b[o], a[o]) = (sum[0], sum[1], sum[2], sum[3]);
                        known += full;
                    }
                }
                known
            })
            .sum();
        if known == 0 {
            return None;
        }
        // How much each pixel's fill is an interpolation from data near it:
        // the share of complete half-resolution pixels within
        // `NEAR_RADIUS` (full-resolution pixels), over `NEAR_SHARE` (1 from
        // there on).
        let counts = KnownCounts::new(&img, Rect::full(hw, hh), NEAR_RADIUS / 2, FULL);
        let mut near = vec![0f32; hw * hh];
        near.par_chunks_mut(hw).enumerate().for_each(|(y, row)| {
            for (x, v) in row.iter_mut().enumerate() {
                *v = (counts.share(x, y) / NEAR_SHARE).min(1.0);
            }
        });
        // Each half-resolution pixel's depth: the farthest of its covered pixels.
        let far = depth.map(|d| {
            let mut far = vec![f32::NEG_INFINITY; hw * hh];
            far.par_chunks_mut(hw).enumerate().for_each(|(y, row)| {
                let y = window.y0 + 2 * y;
                for (x, f) in row.iter_mut().enumerate() {
                    let xa = window.x0 + 2 * x;
                    for yy in y..(y + 2).min(window.y1) {
                        for xx in xa..(xa + 2).min(window.x1) {
                            let p = yy * width + xx;
                            let c = rgba[3][p];
                            if c >= floor && c > 0.0 {
                                *f = f.max(d[p]);
                            }
                        }
                    }
                }
            });
            far
        });
        match far {
            // No history is in this fill: all its data is the frame's own.
            Some(far) => {
                push_pull_far(&mut img, Rect::full(hw, hh), &OwnCoverage::unfilled(), &far)
            }
            None => push_pull_sqrt(&mut img, Rect::full(hw, hh), None),
        }
        img.plane_mut(3).copy_from_slice(&near);
        Some(SpatialFill { img, window })
    }

    /// `c` (a history sample, RGBA premultiplied) moved by `share` toward
    /// the fill at (row `i`, column `j`) (of coverage 1); `c` unchanged
    /// outside the window.
    #[inline]
    pub fn pull(&self, i: usize, j: usize, c: [f32; 4], share: f32) -> [f32; 4] {
        let w = self.window;
        if !w.contains(j, i) {
            return c;
        }
        let n = self.img.width * self.img.height;
        let o = (i - w.y0) / 2 * self.img.width + (j - w.x0) / 2;
        let share = share * self.img.data[3 * n + o];
        let f = |k: usize| {
            if k == 3 {
                1.0
            } else {
                self.img.data[k * n + o]
            }
        };
        std::array::from_fn(|k| c[k] + share * (f(k) - c[k]))
    }
}

/// Radius of the square whose fully covered share says how near a hole
/// pixel's own fill is to data ([`SpatialFill`]).
pub const NEAR_RADIUS: usize = 16;

/// Share of fully covered pixels within [`NEAR_RADIUS`] from which a hole
/// pixel's own fill takes the whole refresh (less in proportion below):
/// a fill across a wide empty area (a reconstruction's uncovered edge)
/// is an extrapolation, further from the truth than the history it would
/// replace (recon_hall, `scripts/quality.sh`: 19.98 -> 19.56 dB with the
/// whole refresh everywhere, 20.11 dB with this weight).
pub const NEAR_SHARE: f32 = 0.5;

/// The window push-pull works in for holes inside `holes`: the holes' box
/// grown by an eighth of its size (32 to 128 pixels), clipped to the image.
/// Every hole inside the box is surrounded by data inside the window, so
/// the fill only loses the weak far-field influence of the rest of the frame.
pub fn fill_window(holes: Rect, width: usize, height: usize) -> Rect {
    let margin = (holes.width().max(holes.height()) / 8).clamp(32, 128);
    holes.expand(margin, width, height)
}

/// One pyramid level: 4 planes, RGB premultiplied by the weight in plane 3.
type Level = Image;

/// A window of a 4-plane image: planes with a row stride and an origin.
#[derive(Clone, Copy)]
struct View<'a> {
    planes: [&'a [f32]; 4],
    stride: usize,
    x0: usize,
    y0: usize,
    width: usize,
    height: usize,
}

impl<'a> View<'a> {
    fn of(img: &'a Image, window: Rect) -> View<'a> {
        View {
            planes: [img.plane(0), img.plane(1), img.plane(2), img.plane(3)],
            stride: img.width,
            x0: window.x0,
            y0: window.y0,
            width: window.width(),
            height: window.height(),
        }
    }

    fn row(&self, c: usize, y: usize) -> &'a [f32] {
        let s = (self.y0 + y) * self.stride + self.x0;
        &self.planes[c][s..s + self.width]
    }
}

/// Sums pairs: `out[i] = a[2i] + a[2i+1] (+ b[2i] + b[2i+1])`, a lone last sample alone.
fn pair_sums(a: &[f32], b: Option<&[f32]>, out: &mut [f32]) {
    let pairs = a.len() / 2;
    match b {
        Some(b) => {
            for ((o, p), q) in out.iter_mut().zip(a.chunks_exact(2)).zip(b.chunks_exact(2)) {
                *o = (p[0] + p[1]) + (q[0] + q[1]);
            }
            if a.len() % 2 == 1 {
                out[pairs] = a[a.len() - 1] + b[b.len() - 1];
            }
        }
        None => {
            for (o, p) in out.iter_mut().zip(a.chunks_exact(2)) {
                *o = p[0] + p[1];
            }
            if a.len() % 2 == 1 {
                out[pairs] = a[a.len() - 1];
            }
        }
    }
}

/// Pull step: 2x2 box sums with the weight clamped to 1 (a coarse pixel is
/// complete as soon as one fine pixel's worth of data falls into it).
fn pull(src: &View<'_>) -> Level {
    let (sw, sh) = (src.width, src.height);
    let (dw, dh) = (sw.div_ceil(2), sh.div_ceil(2));
    let mut dst = Image::zeros(dw, dh, 4);
    par_bands_mut(&mut dst, 0, dh).for_each(|(y0, [r, g, b, a])| {
        let rows = a.len() / dw;
        let mut k = vec![0.0f32; dw];
        for dy in 0..rows {
            let y = y0 + dy;
            let (sy0, sy1) = (2 * y, 2 * y + 1);
            let two = |c: usize| (src.row(c, sy0), (sy1 < sh).then(|| src.row(c, sy1)));
            let out = dy * dw..(dy + 1) * dw;
            let (p, q) = two(3);
            let ao = &mut a[out.clone()];
            pair_sums(p, q, ao);
            for (kk, wa) in k.iter_mut().zip(ao.iter_mut()) {
                let wsum = *wa;
                let wc = wsum.min(1.0);
                *kk = if wsum > 0.0 { wc / wsum } else { 0.0 };
                *wa = if wsum > 0.0 { wc } else { 0.0 };
            }
            for (c, plane) in [&mut *r, &mut *g, &mut *b].into_iter().enumerate() {
                let (p, q) = two(c);
                let o = &mut plane[out.clone()];
                pair_sums(p, q, o);
                for (v, kk) in o.iter_mut().zip(&k) {
                    *v *= kk;
                }
            }
        }
    });
    dst
}

/// Bilinear taps from a fine axis of `fine` samples into a coarse axis of
/// `coarse` samples (pixel centres at +0.5): `(i0, i1, f)` per fine index.
fn taps(fine: usize, coarse: usize) -> Vec<(usize, usize, f32)> {
    (0..fine)
        .map(|x| {
            let u = (x as f32 + 0.5) * 0.5 - 0.5;
            let u = u.clamp(0.0, (coarse - 1) as f32);
            let i0 = u.floor() as usize;
            let i1 = (i0 + 1).min(coarse - 1);
            (i0, i1, u - i0 as f32)
        })
        .collect()
}

/// Push into one band of rows: every pixel of columns `xs` with A < 1 gets
/// `C += (1 - A) * up(coarser)` and A = 1. `planes` hold whole rows of
/// `stride` samples; `first` is the band's first row in the window's
/// coordinates (the index into `ty`).
#[allow(clippy::too_many_arguments)]
fn push_band(
    planes: [&mut [f32]; 4],
    stride: usize,
    xs: std::ops::Range<usize>,
    first: usize,
    tx: &[(usize, usize, f32)],
    ty: &[(usize, usize, f32)],
    coarser: &Level,
    up: &mut [f32],
) {
    let [r, g, b, a] = planes;
    let cw = coarser.width;
    let rows = a.len() / stride;
    for dy in 0..rows {
        let row = dy * stride;
        if super::row_min(&a[row + xs.start..row + xs.end]) >= FULL {
            continue;
        }
        // The coarse level interpolated to this row, then per hole pixel across.
        let (j0, j1, fy) = ty[first + dy];
        for c in 0..3 {
            let p = coarser.plane(c);
            let (t, bt) = (&p[j0 * cw..(j0 + 1) * cw], &p[j1 * cw..(j1 + 1) * cw]);
            for ((u, t), bt) in up[c * cw..(c + 1) * cw].iter_mut().zip(t).zip(bt) {
                *u = t + fy * (bt - t);
            }
        }
        for x in xs.clone() {
            let o = row + x;
            let cov = a[o];
            if cov >= FULL {
                continue;
            }
            let (i0, i1, fx) = tx[x - xs.start];
            let m = 1.0 - cov;
            for (c, out) in [&mut *r, &mut *g, &mut *b].into_iter().enumerate() {
                let u = &up[c * cw..(c + 1) * cw];
                out[o] += m * (u[i0] + fx * (u[i1] - u[i0]));
            }
            a[o] = 1.0;
        }
    }
}

/// Completes every pixel with A < 1 of `level` (all of it) from `coarser`.
fn push_level(level: &mut Level, coarser: &Level) {
    let (w, h) = (level.width, level.height);
    let tx = taps(w, coarser.width);
    let ty = taps(h, coarser.height);
    par_bands_mut(level, 0, h).for_each(|(y0, planes)| {
        let mut up = vec![0.0f32; 3 * coarser.width];
        push_band(planes, w, 0..w, y0, &tx, &ty, coarser, &mut up);
    });
}

/// [`push_pull`] (or [`push_pull_at`] with the holes listed) on the square
/// root of the straight color: the pyramid averages and interpolates
/// `A * sqrt(C / A)`, and the hole pixels get the square of the result
/// (pixels with A = 1 are not touched, bit for bit). Averaging linear light
/// across a hole lets its bright side dominate; out of domain the fill in
/// square roots was closer to the truth (`scripts/quality.sh`, classical:
/// reconstruction holes +0.25 dB outdoors and +0.23 dB indoors; the cube
/// root gave 0.04-0.07 dB more but is a library call per sample where the
/// square root is one instruction, and a log a little more again but
/// depends on the scene's exposure). The square root, like any power,
/// commutes with exposure.
pub fn push_pull_sqrt(img: &mut Image, window: Rect, holes: Option<&[(u32, u32)]>) {
    push_pull_sqrt_or_far(img, window, holes, None);
}

/// [`push_pull_sqrt`], but where the holes are a large part of `window`
/// (the dense pyramid either way) and `far` gives the frame's own coverage
/// and depth (a plane of the image's size), [`push_pull_far`]: a few
/// slivers keep the plain sparse evaluation (the far side's window-sized
/// pyramid is not paid for them). `holes`: the window's hole pixels as
/// [`push_pull_at`] takes them, when known.
pub fn push_pull_sqrt_or_far(
    img: &mut Image,
    window: Rect,
    holes: Option<&[(u32, u32)]>,
    far: Option<(&OwnCoverage, &[f32])>,
) {
    if window.is_empty() {
        return;
    }
    // Few holes in the window: the lazy pyramid reads the square roots where
    // it needs them (as `push_pull` does; the same bits as the copy below).
    let listed;
    let list = match holes {
        Some(l) => l,
        None => {
            listed = window_holes(img, window);
            &listed
        }
    };
    if list.len() * SPARSE_RATIO < window.width() * window.height() {
        push_pull_sparse(img, window, list, true);
    } else if let Some((own, depth)) = far {
        push_pull_far(img, window, own, depth);
    } else {
        push_pull_sqrt_copy(img, window, list);
    }
}

/// [`push_pull_sqrt`] on an encoded copy of the window (the dense pyramid
/// when the holes are a large part of it).
fn push_pull_sqrt_copy(img: &mut Image, window: Rect, holes: &[(u32, u32)]) {
    let w = img.width;
    let (ww, wh) = (window.width(), window.height());
    let mut enc = Image::zeros(ww, wh, 4);
    {
        let src = [img.plane(0), img.plane(1), img.plane(2), img.plane(3)];
        par_bands_mut(&mut enc, 0, wh).for_each(|(y0, [r, g, b, a])| {
            for dy in 0..a.len() / ww {
                let s =
                    (window.y0 + y0 + dy) * w + window.x0..(window.y0 + y0 + dy) * w + window.x1;
                let o = dy * ww..(dy + 1) * ww;
                let alpha = &src[3][s.clone()];
                a[o.clone()].copy_from_slice(alpha);
                for (dst, c) in [&mut r[o.clone()], &mut g[o.clone()], &mut b[o.clone()]]
                    .into_iter()
                    .zip(&src[..3])
                {
                    for ((d, &v), &al) in dst.iter_mut().zip(&c[s.clone()]).zip(alpha) {
                        *d = sqrt_encode(v, al);
                    }
                }
            }
        });
    }
    // The holes are a large part of the window here: the whole pyramid.
    push_pull_dense(&mut enc, Rect::full(ww, wh));
    let [r, g, b, a] = rgba_planes_mut(img);
    for &(x, y) in holes {
        let (x, y) = (x as usize, y as usize);
        let (i, o) = (y * w + x, (y - window.y0) * ww + x - window.x0);
        let sq = |c: usize| enc.plane(c)[o] * enc.plane(c)[o];
        (r[i], g[i], b[i], a[i]) = (sq(0), sq(1), sq(2), 1.0);
    }
}

/// How [`push_pull_sqrt`] encodes a premultiplied sample `c` of coverage
/// `a`: `A * sqrt(C / A) = sqrt(A * C)` (0 where A is 0: C is too). The
/// sparse and dense pyramids both read level 0 through it, so they agree
/// bit for bit.
#[inline(always)]
pub(super) fn sqrt_encode(c: f32, a: f32) -> f32 {
    (a.max(0.0) * c.max(0.0)).sqrt()
}

/// The sparse evaluation ([`sparse`]) is taken when the window holds more
/// than this many pixels per hole pixel.
const SPARSE_RATIO: usize = 32;

/// Fills every pixel with A < 1 inside `window` by push-pull over that window
/// (weights = coverage, so soft borders blend: `out = premult + (1 - A) * fill`);
/// A becomes 1 there. The pyramid sees the window alone; pixels outside it
/// are neither read nor written.
///
/// When the holes are a small part of the window, the pyramid is evaluated
/// only where they need it (the same values, bit for bit); else whole.
pub fn push_pull(img: &mut Image, window: Rect) {
    if window.is_empty() {
        return;
    }
    let holes = window_holes(img, window);
    push_pull_in(img, window, &holes);
}

/// [`push_pull`] with the hole pixels given: `holes` are all the pixels of
/// `window` with A below [`FULL`], (column, row) in the image (as
/// [`fill_from_history_listing`] lists them), so the window is not searched.
///
/// # Panics
/// When a pixel of `holes` is outside `window`.
pub fn push_pull_at(img: &mut Image, window: Rect, holes: &[(u32, u32)]) {
    if window.is_empty() {
        return;
    }
    if let Some(&(x, y)) = holes
        .iter()
        .find(|&&(x, y)| !window.contains(x as usize, y as usize))
    {
        panic!("hole ({x}, {y}) outside the window {window:?}");
    }
    push_pull_in(img, window, holes);
}

/// [`push_pull`] with the window's holes (in the image's coordinates):
/// sparse or dense by their share of the window.
fn push_pull_in(img: &mut Image, window: Rect, holes: &[(u32, u32)]) {
    if holes.len() * SPARSE_RATIO < window.width() * window.height() {
        push_pull_sparse(img, window, holes, false);
    } else {
        push_pull_dense(img, window);
    }
}

/// The pixels of `window` with A below [`FULL`]: (column, row) in the
/// image, in row order.
fn window_holes(img: &Image, window: Rect) -> Vec<(u32, u32)> {
    let a = img.plane(3);
    let w = img.width;
    let rows: Vec<usize> = (window.y0..window.y1).collect();
    let parts: Vec<Vec<(u32, u32)>> = rows
        .par_chunks(64)
        .map(|ys| {
            let mut out = Vec::new();
            for &y in ys {
                let row = &a[y * w + window.x0..y * w + window.x1];
                if super::row_min(row) >= FULL {
                    continue;
                }
                // Stretches without holes are skipped by a test that vectorizes.
                for (i, run) in row.chunks(SKIP).enumerate() {
                    if super::row_min(run) >= FULL {
                        continue;
                    }
                    let x0 = window.x0 + SKIP * i;
                    out.extend(
                        run.iter()
                            .enumerate()
                            .filter(|(_, &c)| c < FULL)
                            .map(|(x, _)| ((x0 + x) as u32, y as u32)),
                    );
                }
            }
            out
        })
        .collect();
    parts.concat()
}

/// [`push_pull`] by the sparse evaluation ([`sparse::Pyramid`]) at `holes`
/// (all of the window's, in the image's coordinates, [`window_holes`]);
/// the holes are split among the pool's threads, each with its own memo.
fn push_pull_sparse(img: &mut Image, window: Rect, holes: &[(u32, u32)], sqrt: bool) {
    let parts = rayon::current_num_threads().max(1);
    let w = img.width;
    let fills: Vec<[f32; 3]> = {
        let view = View::of(img, window);
        let cov = img.plane(3);
        holes
            .par_chunks(holes.len().div_ceil(parts).max(1))
            .flat_map_iter(|part| {
                let mut pyramid = sparse::Pyramid::new(view, sqrt);
                part.iter()
                    .map(|&(x, y)| {
                        let (x, y) = (x as usize, y as usize);
                        pyramid.fill(x - window.x0, y - window.y0, cov[y * w + x])
                    })
                    .collect::<Vec<_>>()
            })
            .collect()
    };
    let [r, g, b, a] = rgba_planes_mut(img);
    for (&(x, y), f) in holes.iter().zip(&fills) {
        let o = y as usize * w + x as usize;
        let f = if sqrt { f.map(|v| v * v) } else { *f };
        (r[o], g[o], b[o], a[o]) = (f[0], f[1], f[2], 1.0);
    }
}

/// [`push_pull`] over the whole pyramid.
fn push_pull_dense(img: &mut Image, window: Rect) {
    let (w0, h0) = (window.width(), window.height());
    let width = img.width;

    // Pull until a level has no holes or is a single pixel.
    let mut levels: Vec<Level> = vec![pull(&View::of(img, window))];
    loop {
        let last = levels.last().expect("one level");
        let complete = super::row_min(last.plane(3)) >= FULL;
        if complete || (last.width == 1 && last.height == 1) {
            break;
        }
        let next = pull(&View::of(last, Rect::full(last.width, last.height)));
        levels.push(next);
    }
    // The coarsest level: normalize to opaque color (0 where nothing at all).
    {
        let top = levels.last_mut().expect("one level");
        let [r, g, b, a] = rgba_planes_mut(top);
        for i in 0..a.len() {
            if a[i] < FULL {
                let k = if a[i] > 0.0 { 1.0 / a[i] } else { 0.0 };
                r[i] *= k;
                g[i] *= k;
                b[i] *= k;
                a[i] = 1.0;
            }
        }
    }
    // Push down to level 1.
    for l in (0..levels.len() - 1).rev() {
        let (fine, coarse) = levels.split_at_mut(l + 1);
        push_level(&mut fine[l], &coarse[0]);
    }
    // Level 0: only the hole pixels of the window change.
    let l1 = &levels[0];
    let tx = taps(w0, l1.width);
    let ty = taps(h0, l1.height);
    par_bands_mut(img, window.y0, window.y1).for_each(|(y0, planes)| {
        let mut up = vec![0.0f32; 3 * l1.width];
        push_band(
            planes,
            width,
            window.x0..window.x1,
            y0 - window.y0,
            &tx,
            &ty,
            l1,
            &mut up,
        );
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rgba(w: usize, h: usize, f: impl Fn(usize, usize) -> [f32; 4]) -> Image {
        let mut img = Image::zeros(w, h, 4);
        let n = w * h;
        for y in 0..h {
            for x in 0..w {
                let v = f(x, y);
                for (c, v) in v.iter().enumerate() {
                    img.data[c * n + y * w + x] = *v;
                }
            }
        }
        img
    }

    /// The windows the pyramid tests fill: the whole image and an inner part.
    fn windows(w: usize, h: usize) -> [Rect; 2] {
        [
            Rect::full(w, h),
            Rect {
                x0: w / 5,
                y0: h / 4,
                x1: w - w / 7,
                y1: h - h / 6,
            },
        ]
    }

    /// A frame with holes of every kind (single pixels, thin cracks, blobs,
    /// soft borders, a region with no data at all), from a seeded generator.
    fn holey(w: usize, h: usize, seed: u64, density: u64) -> Image {
        let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let noise: Vec<u64> = (0..w * h).map(|_| next()).collect();
        let (bx, by, br) = (
            (seed as usize * 7) % w.max(1),
            (seed as usize * 3) % h.max(1),
            1 + w / 9,
        );
        rgba(w, h, |x, y| {
            let n = noise[y * w + x];
            let blob = (x as f32 - bx as f32).hypot(y as f32 - by as f32) / br as f32;
            let mut cov = if n % 1000 < density {
                // Scattered holes, some partial.
                if n.is_multiple_of(3) {
                    0.0
                } else {
                    (n >> 20) as f32 % 97.0 / 97.0
                }
            } else {
                1.0
            };
            if (x + 2 * y) % 41 == 0 {
                cov = 0.0; // a thin crack
            }
            cov = cov.min((blob - 1.0).clamp(0.0, 1.0)); // a blob with a soft edge
            let c = |k: u64| ((n >> (8 * k)) & 0xff) as f32 / 64.0 + (x + y) as f32 * 0.01;
            [c(1) * cov, c(2) * cov, c(3) * cov, cov]
        })
    }

    #[test]
    fn sparse_push_pull_equals_the_dense_pyramid_bit_for_bit() {
        let sizes = [
            (1, 1),
            (2, 1),
            (1, 7),
            (5, 3),
            (37, 23),
            (64, 64),
            (200, 151),
            (333, 97),
        ];
        for (i, &(w, h)) in sizes.iter().enumerate() {
            for density in [0, 2, 30, 400] {
                let img = holey(w, h, i as u64 + 1, density);
                for window in windows(w, h).into_iter().filter(|r| !r.is_empty()) {
                    let holes = window_holes(&img, window);
                    let mut dense = img.clone();
                    push_pull_dense(&mut dense, window);
                    let mut sparse = img.clone();
                    push_pull_sparse(&mut sparse, window, &holes, false);
                    for (k, (a, b)) in dense.data.iter().zip(&sparse.data).enumerate() {
                        assert_eq!(
                            a.to_bits(),
                            b.to_bits(),
                            "{w}x{h}, density {density}, window {window:?}: sample {k}: dense {a}, sparse {b}"
                        );
                    }
                    // `push_pull` picks one of the two: the same result.
                    let mut picked = img.clone();
                    push_pull(&mut picked, window);
                    assert!(picked
                        .data
                        .iter()
                        .zip(&dense.data)
                        .all(|(a, b)| a.to_bits() == b.to_bits()));
                }
            }
        }
    }

    #[test]
    fn listed_holes_are_the_missing_pixels_and_push_pull_at_them_is_push_pull() {
        let (w, h) = (301, 173);
        for density in [2, 30, 400] {
            let img = holey(w, h, 5, density);
            // Valid history on a checkerboard of 7x7 cells, partly transparent.
            let hist = ReprojectedFrame {
                color: rgba(w, h, |x, y| {
                    [0.1 * (x % 5) as f32, 0.3, 0.05 * (y % 9) as f32, 0.75]
                }),
                valid: (0..w * h)
                    .map(|i| {
                        if (i % w / 7 + i / w / 7) % 2 == 0 {
                            0.8
                        } else {
                            0.0
                        }
                    })
                    .collect(),
            };
            let rect = find_holes(&img).unwrap().rect;
            let mut filled = img.clone();
            let n = filled.len();
            let (hc, hv) = (&hist.color.data, &hist.valid);
            let sample = |y: usize, x: usize| {
                let p = y * w + x;
                ([hc[p], hc[n + p], hc[2 * n + p], hc[3 * n + p]], hv[p])
            };
            let span = |y: usize, x0: usize, out: [&mut [f32]; 5]| {
                let [o0, o1, o2, o3, ov] = out;
                for (t, o) in [o0, o1, o2, o3].into_iter().enumerate() {
                    for (k, v) in o.iter_mut().enumerate() {
                        *v = sample(y, x0 + k).0[t];
                    }
                }
                for (k, v) in ov.iter_mut().enumerate() {
                    *v = sample(y, x0 + k).1;
                }
            };
            let (left, list) = fill_from_history_listing(&mut filled, rect, sample, span).unwrap();
            // The same fill and holes as without the list.
            let mut plain = img.clone();
            assert_eq!(fill_from_history(&mut plain, &hist, rect), Some(left));
            assert!(plain
                .data
                .iter()
                .zip(&filled.data)
                .all(|(a, b)| a.to_bits() == b.to_bits()));
            // And as the compositing written pixel by pixel.
            let mut naive = img.clone();
            for p in 0..n {
                let cov = naive.data[3 * n + p];
                let ([hr, hg, hb, ha], v) = sample(p / w, p % w);
                if cov >= FULL || v <= 0.0 || ha <= 0.0 {
                    continue;
                }
                let k = (1.0 - cov) * v;
                for (c, hv) in [hr, hg, hb].into_iter().enumerate() {
                    naive.data[c * n + p] += k * hv;
                }
                let c = (cov + k * ha).min(1.0);
                naive.data[3 * n + p] = if c >= FULL { 1.0 } else { c };
            }
            assert!(naive
                .data
                .iter()
                .zip(&filled.data)
                .all(|(a, b)| a.to_bits() == b.to_bits()));
            // The list is every pixel still missing, in row order.
            let expected: Vec<(u32, u32)> = (0..h)
                .flat_map(|y| (0..w).map(move |x| (x, y)))
                .filter(|&(x, y)| filled.at(x, y, 3) < FULL)
                .map(|(x, y)| (x as u32, y as u32))
                .collect();
            assert_eq!(list, expected, "density {density}");
            assert_eq!(list.len(), left.count);
            let window = fill_window(left.rect, w, h);
            let mut at = filled.clone();
            push_pull_at(&mut at, window, &list);
            push_pull(&mut filled, window);
            assert!(at
                .data
                .iter()
                .zip(&filled.data)
                .all(|(a, b)| a.to_bits() == b.to_bits()));
            assert!(find_holes(&at).is_none());
        }
    }

    #[test]
    fn push_pull_fills_a_constant_image_exactly() {
        // A constant color with a hole and soft borders must come back constant.
        let (w, h) = (61, 45);
        let mut img = rgba(w, h, |x, y| {
            let d = ((x as f32 - 30.0).powi(2) + (y as f32 - 20.0).powi(2)).sqrt();
            let cov = ((d - 8.0) / 3.0).clamp(0.0, 1.0);
            [0.3 * cov, 0.6 * cov, 0.9 * cov, cov]
        });
        let holes = find_holes(&img).unwrap();
        push_pull(&mut img, fill_window(holes.rect, w, h));
        assert!(find_holes(&img).is_none());
        for i in 0..w * h {
            assert!((img.data[i] - 0.3).abs() < 1e-5, "r {}", img.data[i]);
            assert!((img.data[w * h + i] - 0.6).abs() < 1e-5);
            assert!((img.data[2 * w * h + i] - 0.9).abs() < 1e-5);
            assert_eq!(img.data[3 * w * h + i], 1.0);
        }
    }

    #[test]
    fn push_pull_interpolates_between_sides() {
        // Left half 0, right half 1, a vertical hole band in the middle: the
        // fill must be monotonic and between the two sides.
        let (w, h) = (64, 32);
        let mut img = rgba(w, h, |x, _| {
            let v = if x < 32 { 0.0 } else { 1.0 };
            if (24..40).contains(&x) {
                [0.0; 4]
            } else {
                [v, v, v, 1.0]
            }
        });
        push_pull(&mut img, Rect::full(w, h));
        let row: Vec<f32> = (0..w).map(|x| img.at(x, 16, 0)).collect();
        for x in 24..40 {
            assert!((0.0..=1.0).contains(&row[x]), "{row:?}");
            assert!(row[x + 1] >= row[x] - 1e-6, "not monotonic at {x}: {row:?}");
        }
        assert!(row[25] < 0.35 && row[38] > 0.65, "{row:?}");
        // Pixels that were covered are untouched.
        assert_eq!(row[10], 0.0);
        assert_eq!(row[50], 1.0);
    }

    #[test]
    fn empty_image_fills_with_zero_and_full_alpha() {
        let mut img = Image::zeros(9, 7, 4);
        push_pull(&mut img, Rect::full(9, 7));
        assert!(img.plane(3).iter().all(|&a| a == 1.0));
        assert!(img.data[..3 * 63].iter().all(|&v| v == 0.0));
    }

    #[test]
    fn history_fills_where_valid_only() {
        let (w, h) = (20, 10);
        let mut img = rgba(w, h, |x, _| {
            if x < 10 {
                [0.0; 4]
            } else {
                [0.5, 0.5, 0.5, 1.0]
            }
        });
        let hist = ReprojectedFrame {
            color: rgba(w, h, |_, _| [0.2, 0.4, 0.6, 1.0]),
            valid: (0..w * h)
                .map(|i| if i % w < 5 { 1.0 } else { 0.0 })
                .collect(),
        };
        let rect = find_holes(&img).unwrap().rect;
        let left = fill_from_history(&mut img, &hist, rect).unwrap();
        assert_eq!(left.count, 5 * h);
        assert_eq!(
            left.rect,
            Rect {
                x0: 5,
                y0: 0,
                x1: 10,
                y1: h
            }
        );
        assert_eq!(img.at(2, 3, 1), 0.4);
        assert_eq!(img.at(2, 3, 3), 1.0);
        assert_eq!(img.at(7, 3, 3), 0.0);
        assert_eq!(img.at(15, 3, 0), 0.5);
    }

    #[test]
    fn window_fill_matches_whole_fill_for_a_small_hole_in_flat_color() {
        let (w, h) = (300, 200);
        let mk = || {
            rgba(w, h, |x, y| {
                if (140..150).contains(&x) && (90..96).contains(&y) {
                    [0.0; 4]
                } else {
                    [0.25, 0.5, 0.75, 1.0]
                }
            })
        };
        let mut a = mk();
        let holes = find_holes(&a).unwrap();
        let win = fill_window(holes.rect, w, h);
        assert!(win.width() < w);
        push_pull(&mut a, win);
        let mut b = mk();
        push_pull(&mut b, Rect::full(w, h));
        for (x, y) in a.data.iter().zip(&b.data) {
            assert!((x - y).abs() < 1e-5);
        }
    }

    #[test]
    fn faint_pixels_lose_their_color_inside_the_rect_only() {
        let img = holey(53, 31, 5, 300);
        let rect = Rect {
            x0: 7,
            y0: 4,
            x1: 40,
            y1: 29,
        };
        let mut out = img.clone();
        drop_faint(&mut out, rect, 0.6);
        let n = img.len();
        let mut dropped = 0;
        for y in 0..31 {
            for x in 0..53 {
                let i = y * 53 + x;
                let a = img.data[3 * n + i];
                let gone = rect.contains(x, y) && a < 0.6;
                for c in 0..4 {
                    let want = if gone { 0.0 } else { img.data[c * n + i] };
                    assert_eq!(
                        out.data[c * n + i].to_bits(),
                        want.to_bits(),
                        "({x}, {y}) plane {c}"
                    );
                }
                dropped += usize::from(gone && a > 0.0);
            }
        }
        assert!(
            dropped > 20,
            "the test image has faint pixels in the rect: {dropped}"
        );
        // The same holes remain, and a floor of 0 changes nothing.
        assert_eq!(find_holes(&out), find_holes(&img));
        let mut same = img.clone();
        drop_faint(&mut same, rect, 0.0);
        assert_eq!(same.data, img.data);
    }

    #[test]
    fn known_share_counts_the_covered_pixels_around_each_pixel() {
        let img = holey(41, 27, 9, 250);
        let (w, h) = (41, 27);
        let a = img.plane(3);
        for (rect, radius, floor) in [
            (Rect::full(w, h), 3, 0.5),
            (
                Rect {
                    x0: 2,
                    y0: 20,
                    x1: 41,
                    y1: 27,
                },
                5,
                0.95,
            ),
            (
                Rect {
                    x0: 0,
                    y0: 0,
                    x1: 1,
                    y1: 1,
                },
                0,
                0.5,
            ),
        ] {
            let counts = KnownCounts::new(&img, rect, radius, floor);
            for y in rect.y0..rect.y1 {
                for x in rect.x0..rect.x1 {
                    let (mut k, mut t) = (0, 0);
                    for yy in y.saturating_sub(radius)..(y + radius + 1).min(h) {
                        for xx in x.saturating_sub(radius)..(x + radius + 1).min(w) {
                            t += 1;
                            k += usize::from(a[yy * w + xx] >= floor);
                        }
                    }
                    let got = counts.share(x, y);
                    assert!(
                        (got - k as f32 / t as f32).abs() < 1e-6,
                        "({x}, {y}) r {radius}: {got} vs {k}/{t}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_square_root_fill_leaves_covered_pixels_and_averages_in_square_roots() {
        let img = holey(61, 37, 3, 200);
        let window = Rect::full(61, 37);
        let mut a = img.clone();
        push_pull_sqrt(&mut a, window, None);
        let mut b = img.clone();
        let list = window_holes(&img, window);
        push_pull_sqrt(&mut b, window, Some(&list));
        assert_eq!(a.data, b.data, "listed holes give the same bits");
        let n = img.len();
        for i in 0..n {
            if img.data[3 * n + i] >= FULL {
                for c in 0..4 {
                    assert_eq!(a.data[c * n + i].to_bits(), img.data[c * n + i].to_bits());
                }
            } else {
                assert_eq!(a.data[3 * n + i], 1.0);
            }
        }
        // A gap between a dark (0.04) and a bright (1) side: the pyramid's
        // weights over the square roots (0.2, 1), squared; in linear light
        // the same weights on (0.04, 1) give a brighter fill.
        let gap = rgba(9, 1, |x, _| match x {
            0..=3 => [0.04, 0.04, 0.04, 1.0],
            4 => [0.0; 4],
            _ => [1.0; 4],
        });
        let mut lin = gap.clone();
        push_pull(&mut lin, Rect::full(9, 1));
        let mut sq = gap.clone();
        push_pull_sqrt(&mut sq, Rect::full(9, 1), None);
        // The linear fill is 0.04 + t (1 - 0.04); the square-root one (0.2 + t 0.8)^2.
        let t = (lin.data[4] - 0.04) / 0.96;
        let want = (0.2 + t * 0.8).powi(2);
        assert!(
            (sq.data[4] - want).abs() < 1e-5,
            "{} against {want} (t {t})",
            sq.data[4]
        );
        assert!(
            sq.data[4] < lin.data[4] - 0.05,
            "{} against linear {}",
            sq.data[4],
            lin.data[4]
        );
    }

    #[test]
    fn the_lazy_square_root_pyramid_equals_the_encoded_copy_bit_for_bit() {
        for (i, &(w, h)) in [(5, 3), (37, 23), (200, 151), (333, 97)].iter().enumerate() {
            for density in [2, 30, 400] {
                let img = holey(w, h, i as u64 + 7, density);
                for window in windows(w, h).into_iter().filter(|r| !r.is_empty()) {
                    let holes = window_holes(&img, window);
                    let mut lazy = img.clone();
                    push_pull_sparse(&mut lazy, window, &holes, true);
                    let mut copy = img.clone();
                    push_pull_sqrt_copy(&mut copy, window, &holes);
                    assert!(
                        lazy.data
                            .iter()
                            .zip(&copy.data)
                            .all(|(a, b)| a.to_bits() == b.to_bits()),
                        "{w}x{h} density {density} window {window:?}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_spatial_fill_pulls_history_toward_the_frames_own_fill_near_data_only() {
        // Flat color 0.5 with a small hole (a 5x5 square) and a wide empty
        // strip (the left 40 columns), a soft pixel of coverage 0.5.
        let (w, h) = (96, 64);
        let img = rgba(w, h, |x, y| {
            if x < 40 || ((60..65).contains(&x) && (30..35).contains(&y)) {
                [0.0; 4]
            } else if (x, y) == (70, 10) {
                [0.25, 0.25, 0.25, 0.5]
            } else {
                [0.5, 0.5, 0.5, 1.0]
            }
        });
        let planes = [img.plane(0), img.plane(1), img.plane(2), img.plane(3)];
        let holes = find_holes(&img).unwrap().rect;
        let fill = SpatialFill::new(planes, w, holes, 0.0, None).unwrap();
        let history = [0.1, 0.2, 0.3, 1.0];
        // In the small hole: the flat color, pulled by the whole share.
        let c = fill.pull(32, 62, history, 0.5);
        for k in 0..3 {
            assert!(
                (c[k] - (history[k] + 0.5 * (0.5 - history[k]))).abs() < 1e-4,
                "{c:?}"
            );
        }
        assert_eq!(c[3], 1.0);
        // Beside a soft pixel: the flat color.
        let c = fill.pull(10, 70, [0.0, 0.0, 0.0, 0.0], 1.0);
        assert!((c[0] - 0.5).abs() < 1e-3, "{c:?}");
        // Deep in the wide strip, far from data: unchanged.
        assert_eq!(fill.pull(32, 5, history, 0.5), history);
        // Share 0: unchanged everywhere.
        assert_eq!(fill.pull(32, 62, history, 0.0), history);
        // Nothing covered: no fill.
        let empty = Image::zeros(8, 8, 4);
        let planes = [
            empty.plane(0),
            empty.plane(1),
            empty.plane(2),
            empty.plane(3),
        ];
        assert!(SpatialFill::new(planes, 8, Rect::full(8, 8), 0.0, None).is_none());
    }
}
