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

/// Coverage at or above this counts as complete (snaps to exactly 1).
pub const FULL: f32 = 1.0 - 1e-5;

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

/// Composites a reprojected history frame under the missing part of every
/// hole pixel inside `rect`: `C += (1 - A) * v * H`, `A += (1 - A) * v * H.a`
/// with `v` the history's validity. Returns the holes that remain.
pub fn fill_from_history(img: &mut Image, history: &ReprojectedFrame, rect: Rect) -> Option<Holes> {
    let w = img.width;
    let n = img.len();
    assert_eq!(history.color.len(), n, "history and frame sizes differ");
    let hist = &history.color.data;
    let valid = &history.valid;
    let parts: Vec<Option<(Rect, usize)>> = par_bands_mut(img, rect.y0, rect.y1)
        .map(|(y0, [r, g, b, a])| {
            let mut found: Option<(Rect, usize)> = None;
            let rows = a.len() / w;
            for dy in 0..rows {
                let y = y0 + dy;
                let mut first = None;
                let mut last = 0;
                let mut count = 0;
                for x in rect.x0..rect.x1 {
                    let i = dy * w + x;
                    let cov = a[i];
                    if cov >= FULL {
                        continue;
                    }
                    let p = y * w + x;
                    let v = valid[p];
                    let ha = hist[3 * n + p];
                    let mut cov_new = cov;
                    if v > 0.0 && ha > 0.0 {
                        let k = (1.0 - cov) * v;
                        r[i] += k * hist[p];
                        g[i] += k * hist[n + p];
                        b[i] += k * hist[2 * n + p];
                        cov_new = (cov + k * ha).min(1.0);
                    }
                    if cov_new >= FULL {
                        a[i] = 1.0;
                    } else {
                        a[i] = cov_new;
                        first.get_or_insert(x);
                        last = x;
                        count += 1;
                    }
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
            found
        })
        .collect();
    parts
        .into_iter()
        .flatten()
        .reduce(|(a, n), (b, m)| (a.union(&b), n + m))
        .map(|(rect, count)| Holes { rect, count })
}

/// The window push-pull works in for holes inside `holes`: the holes' box
/// grown by its own size (at least 64 pixels) so large holes see enough
/// surroundings, clipped to the image.
pub fn fill_window(holes: Rect, width: usize, height: usize) -> Rect {
    let margin = holes.width().max(holes.height()).max(64);
    holes.expand(margin, width, height)
}

/// One pyramid level: 4 planes, RGB premultiplied by the weight in plane 3.
type Level = Image;

/// Pull step: 2x2 box sums with the weight clamped to 1 (a coarse pixel is
/// complete as soon as one fine pixel's worth of data falls into it).
fn pull(src: &[&[f32]; 4], sw: usize, sh: usize) -> Level {
    let (dw, dh) = (sw.div_ceil(2), sh.div_ceil(2));
    let mut dst = Image::zeros(dw, dh, 4);
    par_bands_mut(&mut dst, 0, dh).for_each(|(y0, [r, g, b, a])| {
        let rows = a.len() / dw;
        for dy in 0..rows {
            let y = y0 + dy;
            let ys = 2 * y..(2 * y + 2).min(sh);
            for x in 0..dw {
                let mut s = [0.0f32; 4];
                for sy in ys.clone() {
                    for sx in 2 * x..(2 * x + 2).min(sw) {
                        let i = sy * sw + sx;
                        for (c, acc) in s.iter_mut().enumerate() {
                            *acc += src[c][i];
                        }
                    }
                }
                let wsum = s[3];
                let o = dy * dw + x;
                if wsum > 0.0 {
                    let wc = wsum.min(1.0);
                    let k = wc / wsum;
                    r[o] = s[0] * k;
                    g[o] = s[1] * k;
                    b[o] = s[2] * k;
                    a[o] = wc;
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

/// Push step at a coarse level: completes `level` in place with the
/// bilinearly upsampled, already complete `coarser` level.
fn push_level(level: &mut Level, coarser: &Level) {
    let (w, h) = (level.width, level.height);
    let tx = taps(w, coarser.width);
    let ty = taps(h, coarser.height);
    let cw = coarser.width;
    let cp: [&[f32]; 3] = [coarser.plane(0), coarser.plane(1), coarser.plane(2)];
    par_bands_mut(level, 0, h).for_each(|(y0, [r, g, b, a])| {
        let rows = a.len() / w;
        for dy in 0..rows {
            let (j0, j1, fy) = ty[y0 + dy];
            for x in 0..w {
                let o = dy * w + x;
                let cov = a[o];
                if cov >= FULL {
                    continue;
                }
                let (i0, i1, fx) = tx[x];
                let m = 1.0 - cov;
                for (c, out) in [&mut *r, &mut *g, &mut *b].into_iter().enumerate() {
                    let p = cp[c];
                    let top = p[j0 * cw + i0] + fx * (p[j0 * cw + i1] - p[j0 * cw + i0]);
                    let bot = p[j1 * cw + i0] + fx * (p[j1 * cw + i1] - p[j1 * cw + i0]);
                    out[o] += m * (top + fy * (bot - top));
                }
                a[o] = 1.0;
            }
        }
    });
}

/// Fills every pixel with A < 1 inside `window` by push-pull over that window
/// (weights = coverage, so soft borders blend: `out = premult + (1 - A) * fill`);
/// A becomes 1 there. The pyramid sees the window alone; pixels outside it
/// are neither read nor written.
pub fn push_pull(img: &mut Image, window: Rect) {
    if window.is_empty() {
        return;
    }
    let (w0, h0) = (window.width(), window.height());
    let width = img.width;
    // Level 0 is the window; copy it out when it is not the whole image so the
    // pyramid code works on packed planes.
    let whole = window == Rect::full(img.width, img.height);
    let packed: Option<Level> = (!whole).then(|| {
        let mut lv = Image::zeros(w0, h0, 4);
        for c in 0..4 {
            let src = img.plane(c);
            let dst = lv.plane_mut(c);
            for y in 0..h0 {
                let s = (window.y0 + y) * width + window.x0;
                dst[y * w0..(y + 1) * w0].copy_from_slice(&src[s..s + w0]);
            }
        }
        lv
    });
    let base: &Image = packed.as_ref().unwrap_or(img);
    let src = [base.plane(0), base.plane(1), base.plane(2), base.plane(3)];

    // Pull until a level has no holes or is a single pixel.
    let mut levels: Vec<Level> = vec![pull(&src, w0, h0)];
    loop {
        let last = levels.last().expect("one level");
        let complete = last.plane(3).iter().all(|&a| a >= FULL);
        if complete || (last.width == 1 && last.height == 1) {
            break;
        }
        let s = [last.plane(0), last.plane(1), last.plane(2), last.plane(3)];
        let next = pull(&s, last.width, last.height);
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
    let cw = l1.width;
    let cp: [&[f32]; 3] = [l1.plane(0), l1.plane(1), l1.plane(2)];
    par_bands_mut(img, window.y0, window.y1).for_each(|(y0, [r, g, b, a])| {
        let rows = a.len() / width;
        for dy in 0..rows {
            let (j0, j1, fy) = ty[y0 + dy - window.y0];
            for x in window.x0..window.x1 {
                let o = dy * width + x;
                let cov = a[o];
                if cov >= FULL {
                    continue;
                }
                let (i0, i1, fx) = tx[x - window.x0];
                let m = 1.0 - cov;
                for (c, out) in [&mut *r, &mut *g, &mut *b].into_iter().enumerate() {
                    let p = cp[c];
                    let top = p[j0 * cw + i0] + fx * (p[j0 * cw + i1] - p[j0 * cw + i0]);
                    let bot = p[j1 * cw + i0] + fx * (p[j1 * cw + i1] - p[j1 * cw + i0]);
                    out[o] += m * (top + fy * (bot - top));
                }
                a[o] = 1.0;
            }
        }
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
}
