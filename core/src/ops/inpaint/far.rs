//! Push-pull filled from the background side, with the frame's depth: the
//! fill of [`super::push_pull_sqrt`] (square roots of the straight color,
//! weights = coverage, the weight clamped to one per coarse pixel), with two
//! changes where the depth tells a near surface from a far one:
//!
//! - **pull**: before each halving, a pixel with data of its own (the
//!   frame's coverage, not what the history filled) whose disparity
//!   `1 / (1 + depth)` exceeds its 2x2 block's smallest by more than
//!   [`FAR_TOLERANCE`] (relative) is left out of the block's sum: a coarse
//!   pixel across a silhouette holds the surface behind it. The coarse
//!   disparity is the own-weighted mean of what was kept;
//! - **push**: the levels are completed from the coarser ones as in plain
//!   push-pull (color and disparity), but the last step, into the full
//!   resolution, takes of each hole pixel's four bilinear taps only those
//!   within [`FAR_TOLERANCE`] of the farthest, renormalized.
//!
//! The holes a reconstruction leaves where an object moved off its
//! background are that background; the plain fill spreads the object into
//! them. The same fill is the neural models' in-graph prior from 1.4
//! (`training/model.py`, `push_pull_depth`); measured there on the
//! held-out reconstructions (the fill alone, one frame at a time), it was
//! 1.1 dB closer than the plain fill in the holes on average and 0.2 dB
//! further at worst; taking the far taps at every level of the push
//! instead gained 0.7 dB on average but lost 2.3 and 0.5 dB on two
//! sequences, where a wide unseen area took the far wall behind it.

use rayon::prelude::*;

use super::{sqrt_encode, taps, Rect, FULL};
use crate::frame::Image;

/// Relative disparity within which two surfaces count as one.
pub const FAR_TOLERANCE: f32 = 0.05;

/// The frame's own coverage, as it was before the history filled some of
/// its holes: a copy of the coverage inside the holes' box (the only
/// pixels the history fill changes), the image's coverage outside it.
pub struct OwnCoverage {
    rect: Rect,
    plane: Vec<f32>,
}

impl OwnCoverage {
    /// The coverage (plane 3) of `img` inside `holes`, taken before the
    /// history fill.
    pub fn capture(img: &Image, holes: Rect) -> OwnCoverage {
        let a = img.plane(3);
        let mut plane = Vec::with_capacity(holes.width() * holes.height());
        for y in holes.y0..holes.y1 {
            plane.extend_from_slice(&a[y * img.width + holes.x0..y * img.width + holes.x1]);
        }
        OwnCoverage { rect: holes, plane }
    }

    /// Nothing filled by history: the own coverage is the image's.
    pub fn unfilled() -> OwnCoverage {
        OwnCoverage {
            rect: Rect::full(0, 0),
            plane: Vec::new(),
        }
    }

    /// The own coverage at (`x`, `y`), `a` the image's coverage there.
    #[inline]
    fn at(&self, x: usize, y: usize, a: f32) -> f32 {
        if self.rect.contains(x, y) {
            let r = self.rect;
            self.plane[(y - r.y0) * r.width() + x - r.x0].min(a)
        } else {
            a
        }
    }
}

/// Larger than any disparity (`1 / (1 + depth) <= 1`): no depth of its own.
const NO_DISPARITY: f32 = 4.0;

/// A pixel of a level: color (premultiplied by the weight; here square
/// roots), weight, own weight, disparity (meaningful where the own weight
/// is > 0).
pub(crate) type Px = [f32; 6];

/// A level of the pyramid.
#[derive(Default)]
pub(crate) struct Level {
    pub(crate) w: usize,
    pub(crate) h: usize,
    pub(crate) px: Vec<Px>,
}

/// What a halving reads of a level (a [`Level`], or planes laid out
/// otherwise by its caller).
pub(crate) trait Pixels: Sync {
    /// Width and height.
    fn size(&self) -> (usize, usize);
    /// Pixel `i` (row-major).
    fn px(&self, i: usize) -> Px;
}

impl Pixels for Level {
    fn size(&self) -> (usize, usize) {
        (self.w, self.h)
    }

    #[inline]
    fn px(&self, i: usize) -> Px {
        self.px[i]
    }
}

/// The disparity of a planar depth (0 for empty depth, as far as it gets).
#[inline]
fn disparity(d: f32) -> f32 {
    if d.is_finite() {
        1.0 / (1.0 + d.max(0.0))
    } else if d > 0.0 {
        0.0
    } else {
        // NaN or -inf: taken as near (the conservative side: never preferred).
        1.0
    }
}

/// The next coarser level: 2x2 sums of the kept pixels (see the module docs).
fn down(fine: &Level) -> Level {
    let mut out = Level::default();
    halve(fine, Some(FAR_TOLERANCE), &mut out);
    out
}

/// One halving into `out` (resized to `ceil(size / 2)`): each coarse pixel
/// sums its 2x2 block (in row order; past an odd edge there is nothing),
/// leaving out, with a tolerance `tol`, the pixels with data of their own
/// whose disparity exceeds the block's smallest own one by more than it
/// (without, every pixel counts); the weight is clamped to one with the
/// color scaled alike, and the disparity is the own-weighted mean of what
/// was kept. Also the neural runtime's prior
/// (`crate::backend::neural::prior`).
pub(crate) fn halve(fine: &impl Pixels, tol: Option<f32>, out: &mut Level) {
    let (fw, fh) = fine.size();
    let (w, h) = (fw.div_ceil(2), fh.div_ceil(2));
    out.w = w;
    out.h = h;
    out.px.clear();
    out.px.resize(w * h, [0.0; 6]);
    out.px.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, out) in row.iter_mut().enumerate() {
            let mut kids = [[0.0f32; 6]; 4];
            let mut n = 0;
            for yy in 2 * y..(2 * y + 2).min(fh) {
                for xx in 2 * x..(2 * x + 2).min(fw) {
                    kids[n] = fine.px(yy * fw + xx);
                    n += 1;
                }
            }
            let limit = match tol {
                Some(tol) => {
                    let far = kids[..n]
                        .iter()
                        .filter(|p| p[4] > 0.0)
                        .fold(NO_DISPARITY, |m, p| m.min(p[5]));
                    far * (1.0 + tol)
                }
                None => f32::INFINITY,
            };
            let mut s = [0.0f32; 6];
            for p in &kids[..n] {
                if p[4] > 0.0 && p[5] > limit {
                    continue;
                }
                for k in 0..4 {
                    s[k] += p[k];
                }
                s[4] += p[4];
                s[5] += p[4] * p[5];
            }
            let k = if s[3] > 0.0 {
                s[3].min(1.0) / s[3]
            } else {
                0.0
            };
            let disp = if s[4] > 0.0 { s[5] / s[4] } else { 0.0 };
            *out = [s[0] * k, s[1] * k, s[2] * k, s[3].min(1.0), s[4], disp];
        }
    });
}

/// Completes `fine` from `coarse` (complete: weight 1 everywhere): the
/// missing part of every pixel takes the coarse color interpolated, and a
/// pixel without data of its own the coarse disparity interpolated.
fn complete(fine: &mut Level, coarse: &Level) {
    let tx = taps(fine.w, coarse.w);
    let ty = taps(fine.h, coarse.h);
    let cw = coarse.w;
    fine.px
        .par_chunks_mut(fine.w)
        .enumerate()
        .for_each(|(y, row)| {
            let (j0, j1, fy) = ty[y];
            for (x, p) in row.iter_mut().enumerate() {
                let needs_color = p[3] < FULL;
                let needs_depth = p[4] <= 0.0;
                if !needs_color && !needs_depth {
                    continue;
                }
                let (i0, i1, fx) = tx[x];
                let lerp = |k: usize| {
                    let at = |j: usize, i: usize| coarse.px[j * cw + i][k];
                    let top = at(j0, i0) + fx * (at(j0, i1) - at(j0, i0));
                    let bot = at(j1, i0) + fx * (at(j1, i1) - at(j1, i0));
                    top + fy * (bot - top)
                };
                if needs_color {
                    let m = 1.0 - p[3];
                    for (k, v) in p[..3].iter_mut().enumerate() {
                        *v += m * lerp(k);
                    }
                    p[3] = 1.0;
                }
                if needs_depth {
                    p[5] = lerp(5);
                }
            }
        });
}

/// Fills every pixel with A < 1 inside `window` of `img` (RGB premultiplied,
/// A coverage) from the background side (see the module docs); A becomes 1
/// there and the other pixels are not touched, bit for bit. `own` is the
/// frame's own coverage (what the history filled has none) and `depth`
/// its planar depth (a plane of the image's size).
pub fn push_pull_far(img: &mut Image, window: Rect, own: &OwnCoverage, depth: &[f32]) {
    if window.is_empty() {
        return;
    }
    let w = img.width;
    assert_eq!(depth.len(), img.width * img.height, "depth size");
    let (ww, wh) = (window.width(), window.height());
    let mut base = Level {
        w: ww,
        h: wh,
        px: vec![[0.0f32; 6]; ww * wh],
    };
    {
        let planes = [img.plane(0), img.plane(1), img.plane(2), img.plane(3)];
        base.px.par_chunks_mut(ww).enumerate().for_each(|(y, row)| {
            let s = (window.y0 + y) * w + window.x0;
            for (x, p) in row.iter_mut().enumerate() {
                let i = s + x;
                let a = planes[3][i];
                let o = own.at(window.x0 + x, window.y0 + y, a).max(0.0);
                *p = [
                    sqrt_encode(planes[0][i], a),
                    sqrt_encode(planes[1][i], a),
                    sqrt_encode(planes[2][i], a),
                    a.max(0.0),
                    o,
                    disparity(depth[i]),
                ];
            }
        });
    }
    let mut levels = vec![down(&base)];
    loop {
        let last = levels.last().expect("one level");
        let complete = last.px.iter().all(|p| p[3] >= FULL);
        if complete || (last.w == 1 && last.h == 1) {
            break;
        }
        let next = down(last);
        levels.push(next);
    }
    // The coarsest level: opaque color (0 where nothing at all); where it
    // has no depth of its own, the farthest there is.
    for p in &mut levels.last_mut().expect("one level").px {
        if p[3] < FULL {
            let k = if p[3] > 0.0 { 1.0 / p[3] } else { 0.0 };
            for c in &mut p[..3] {
                *c *= k;
            }
            p[3] = 1.0;
        }
        if p[4] <= 0.0 {
            p[5] = 0.0;
        }
    }
    for l in (0..levels.len() - 1).rev() {
        let (fine, coarse) = levels.split_at_mut(l + 1);
        complete(&mut fine[l], &coarse[0]);
    }
    // Level 0: the hole pixels take the far taps of level 1.
    let l1 = &levels[0];
    let tx = taps(ww, l1.w);
    let ty = taps(wh, l1.h);
    let base = &base;
    let [r, g, b, a] = super::rgba_planes_mut(img);
    let rows = r[window.y0 * w..window.y1 * w]
        .par_chunks_mut(w)
        .zip(g[window.y0 * w..window.y1 * w].par_chunks_mut(w))
        .zip(b[window.y0 * w..window.y1 * w].par_chunks_mut(w))
        .zip(a[window.y0 * w..window.y1 * w].par_chunks_mut(w));
    rows.enumerate().for_each(|(y, (((r, g), b), a))| {
        let (j0, j1, fy) = ty[y];
        for (x, &(i0, i1, fx)) in tx.iter().enumerate() {
            let p = base.px[y * ww + x];
            if p[3] >= FULL {
                continue;
            }
            let t = [
                (j0, i0, (1.0 - fy) * (1.0 - fx)),
                (j0, i1, (1.0 - fy) * fx),
                (j1, i0, fy * (1.0 - fx)),
                (j1, i1, fy * fx),
            ];
            let q = t.map(|(j, i, wt)| (l1.px[j * l1.w + i], wt));
            let far = q.iter().fold(NO_DISPARITY, |m, (c, _)| m.min(c[5]));
            let limit = far * (1.0 + FAR_TOLERANCE);
            let (mut sum, mut wsum) = ([0.0f32; 3], 0.0f32);
            for (c, wt) in q {
                if c[5] <= limit {
                    for k in 0..3 {
                        sum[k] += wt * c[k];
                    }
                    wsum += wt;
                }
            }
            let m = (1.0 - p[3]) / wsum.max(1e-12);
            let o = window.x0 + x;
            let enc = |k: usize| p[k] + m * sum[k];
            (r[o], g[o], b[o], a[o]) = (enc(0) * enc(0), enc(1) * enc(1), enc(2) * enc(2), 1.0);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A near object (columns below `lo`, dark, depth 1) and the far
    /// background (bright, depth 9), a hole in columns `lo..hi`.
    fn scene(w: usize, h: usize, lo: usize, hi: usize) -> (Image, OwnCoverage, Vec<f32>) {
        let mut img = Image::zeros(w, h, 4);
        let mut depth = vec![9.0f32; w * h];
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let (c, a) = if (lo..hi).contains(&x) {
                    (0.0, 0.0)
                } else if x < lo {
                    (0.04, 1.0)
                } else {
                    (0.64, 1.0)
                };
                for k in 0..3 {
                    img.plane_mut(k)[i] = c;
                }
                img.plane_mut(3)[i] = a;
                if x < lo {
                    depth[i] = 1.0;
                } else if x < hi {
                    depth[i] = 1e10;
                }
            }
        }
        (img, OwnCoverage::unfilled(), depth)
    }

    #[test]
    fn a_crack_beside_an_object_takes_the_background() {
        let (w, h) = (64, 48);
        let (mut img, own, depth) = scene(w, h, 29, 31);
        let before = img.clone();
        let mut plain = img.clone();
        push_pull_far(&mut img, Rect::full(w, h), &own, &depth);
        super::super::push_pull_sqrt(&mut plain, Rect::full(w, h), None);
        for y in 0..h {
            for x in 29..31 {
                let i = y * w + x;
                assert!(
                    (img.plane(0)[i] - 0.64).abs() < 1e-5,
                    "({x}, {y}): {}",
                    img.plane(0)[i]
                );
                assert_eq!(img.plane(3)[i], 1.0);
            }
            // The plain fill mixes the object in.
            assert!(plain.plane(0)[y * w + 29] < 0.3);
        }
        // Covered pixels are not touched, bit for bit.
        for i in 0..w * h {
            if before.plane(3)[i] >= 1.0 {
                for k in 0..4 {
                    assert_eq!(img.plane(k)[i].to_bits(), before.plane(k)[i].to_bits());
                }
            }
        }
    }

    #[test]
    fn without_depth_differences_it_is_the_plain_fill() {
        let (w, h) = (67, 45);
        let (mut img, own, _) = scene(w, h, 20, 40);
        // Uneven coverage and color, one depth everywhere.
        for i in 0..w * h {
            let v = ((i * 7919) % 97) as f32 / 97.0;
            if img.plane(3)[i] > 0.0 {
                img.plane_mut(3)[i] = if v < 0.2 { 0.6 } else { 1.0 };
                img.plane_mut(1)[i] *= img.plane(3)[i] * (0.5 + v);
            }
        }
        let depth = vec![3.0f32; w * h];
        let mut plain = img.clone();
        let window = Rect {
            x0: 5,
            y0: 3,
            x1: 60,
            y1: 44,
        };
        push_pull_far(&mut img, window, &own, &depth);
        super::super::push_pull_sqrt(&mut plain, window, None);
        for k in 0..4 {
            for (i, (a, b)) in img.plane(k).iter().zip(plain.plane(k)).enumerate() {
                assert!(
                    (a - b).abs() <= 1e-5 * b.abs().max(1.0),
                    "plane {k} pixel {i}: {a} vs {b}"
                );
            }
        }
    }

    #[test]
    fn a_few_hole_pixels_take_the_plain_sparse_fill_and_many_the_far_side() {
        let (w, h) = (64, 48);
        let window = Rect::full(w, h);
        // One crack pixel a row: under 1/32 of the window.
        let (few, own, depth) = scene(w, h, 29, 30);
        let mut a = few.clone();
        let mut b = few.clone();
        super::super::push_pull_sqrt_or_far(&mut a, window, None, Some((&own, &depth)));
        super::super::push_pull_sqrt(&mut b, window, None);
        assert!(a == b, "not the plain fill");
        // A hole a quarter of the window wide: the far side.
        let (many, own, depth) = scene(w, h, 24, 40);
        let mut a = many.clone();
        let mut b = many.clone();
        super::super::push_pull_sqrt_or_far(&mut a, window, None, Some((&own, &depth)));
        push_pull_far(&mut b, window, &own, &depth);
        assert!(a == b, "not the far side");
    }

    #[test]
    fn what_the_history_filled_is_kept_whatever_its_depth() {
        // The crack's pixels hold history (A = 1 from the history, none of
        // their own, empty depth): they are not holes and keep their color;
        // a half-filled pixel completes from the background side.
        let (w, h) = (32, 16);
        let (mut img, _, depth) = scene(w, h, 14, 18);
        // Taken before the history fill, over the holes' box.
        let holes = Rect {
            x0: 14,
            y0: 0,
            x1: 18,
            y1: h,
        };
        let own = OwnCoverage::capture(&img, holes);
        for y in 0..h {
            for x in 14..18 {
                let i = y * w + x;
                let a = if x == 14 { 0.5 } else { 1.0 };
                for k in 0..3 {
                    img.plane_mut(k)[i] = 0.3 * a;
                }
                img.plane_mut(3)[i] = a;
            }
        }
        push_pull_far(&mut img, Rect::full(w, h), &own, &depth);
        for y in 0..h {
            assert_eq!(img.plane(0)[y * w + 15], 0.3);
            let v = img.plane(0)[y * w + 14];
            assert!(
                v > 0.15 && v.is_finite() && img.plane(3)[y * w + 14] == 1.0,
                "{v}"
            );
        }
    }
}
