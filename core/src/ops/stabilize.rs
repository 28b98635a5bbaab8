//! Temporal stabilization: blend the current result with the reprojected
//! previous result where it is valid, after clamping the history into the
//! current frame's local color range (the 3x3 min/max box in YCoCg, as in
//! temporal anti-aliasing), so stale colors (ghosts of moved objects,
//! disocclusions the validity test missed) are rejected while noise and
//! flicker are averaged away.
//!
//! Runs in place, band by band: the rows just outside each band are copied
//! before the parallel pass, so every pixel sees the unmodified 3x3
//! neighborhood whatever the thread count.

use rayon::prelude::*;

use super::{fmax, fmin, par_bands_mut, BAND_ROWS};
use crate::frame::Image;
use crate::temporal::ReprojectedFrame;

/// History alpha below this carries no usable color.
const MIN_HISTORY_ALPHA: f32 = 1e-4;

#[inline]
fn to_ycocg(r: f32, g: f32, b: f32) -> [f32; 3] {
    [
        0.25 * r + 0.5 * g + 0.25 * b,
        0.5 * (r - b),
        0.5 * g - 0.25 * (r + b),
    ]
}

#[inline]
fn from_ycocg(y: f32, co: f32, cg: f32) -> [f32; 3] {
    let t = y - cg;
    [t + co, y + cg, t - co]
}

/// One row in YCoCg (3 planes of `w`).
fn row_ycocg(r: &[f32], g: &[f32], b: &[f32], out: &mut [f32]) {
    let w = r.len();
    let (oy, rest) = out.split_at_mut(w);
    let (oco, ocg) = rest.split_at_mut(w);
    for x in 0..w {
        let [y, co, cg] = to_ycocg(r[x], g[x], b[x]);
        oy[x] = y;
        oco[x] = co;
        ocg[x] = cg;
    }
}

/// Blends `img` (4 planes, premultiplied) with `history` in place: weight
/// `blend * validity`, history clamped to the 3x3 YCoCg range of `img`.
/// Alpha is kept; pixels with A = 0 are left alone.
pub fn stabilize(img: &mut Image, history: &ReprojectedFrame, blend: f32) {
    let (w, h) = (img.width, img.height);
    let n = w * h;
    assert_eq!(history.color.len(), n, "history and frame sizes differ");
    if blend <= 0.0 || n == 0 {
        return;
    }
    let bands = h.div_ceil(BAND_ROWS);
    // YCoCg of the first and last row of every band, taken before any change.
    let edges: Vec<(Vec<f32>, Vec<f32>)> = {
        let src = &*img;
        (0..bands)
            .into_par_iter()
            .map(|bi| {
                let first = bi * BAND_ROWS;
                let last = (first + BAND_ROWS).min(h) - 1;
                let row = |y: usize| {
                    let mut out = vec![0.0; 3 * w];
                    let s = y * w..(y + 1) * w;
                    row_ycocg(
                        &src.plane(0)[s.clone()],
                        &src.plane(1)[s.clone()],
                        &src.plane(2)[s],
                        &mut out,
                    );
                    out
                };
                (row(first), row(last))
            })
            .collect()
    };
    let hist = &history.color.data;
    let valid = &history.valid;
    par_bands_mut(img, 0, h).for_each(|(y0, [r, g, b, a])| {
        let bi = y0 / BAND_ROWS;
        let rows = a.len() / w;
        // Rolling YCoCg rows of the unmodified image: above, centre, below.
        let mut above = if y0 > 0 {
            edges[bi - 1].1.clone()
        } else {
            edges[bi].0.clone()
        };
        let mut centre = edges[bi].0.clone();
        let mut below = vec![0.0; 3 * w];
        let mut vlo = vec![0.0; 3 * w];
        let mut vhi = vec![0.0; 3 * w];
        let mut lo = vec![0.0; 3 * w];
        let mut hi = vec![0.0; 3 * w];
        for dy in 0..rows {
            let y = y0 + dy;
            if dy + 1 < rows {
                let s = (dy + 1) * w..(dy + 2) * w;
                row_ycocg(&r[s.clone()], &g[s.clone()], &b[s], &mut below);
            } else if y + 1 < h {
                below.copy_from_slice(&edges[bi + 1].0);
            } else {
                below.copy_from_slice(&centre);
            }
            // Vertical then horizontal 3-tap min/max.
            for (((l, hh), (a0, a1)), a2) in vlo
                .iter_mut()
                .zip(vhi.iter_mut())
                .zip(above.iter().zip(centre.iter()))
                .zip(below.iter())
            {
                *l = fmin(fmin(*a0, *a1), *a2);
                *hh = fmax(fmax(*a0, *a1), *a2);
            }
            for c in 0..3 {
                let span = c * w..(c + 1) * w;
                min3(&vlo[span.clone()], &mut lo[span.clone()]);
                max3(&vhi[span.clone()], &mut hi[span]);
            }
            let row = dy * w..(dy + 1) * w;
            let prow = y * w;
            let (rr, gr, br, ar) = (
                &mut r[row.clone()],
                &mut g[row.clone()],
                &mut b[row.clone()],
                &a[row],
            );
            let hr = &hist[prow..prow + w];
            let hg = &hist[n + prow..n + prow + w];
            let hb = &hist[2 * n + prow..2 * n + prow + w];
            let ha = &hist[3 * n + prow..3 * n + prow + w];
            let vv = &valid[prow..prow + w];
            let (ly, lco, lcg) = (&lo[..w], &lo[w..2 * w], &lo[2 * w..]);
            let (hy, hco, hcg) = (&hi[..w], &hi[w..2 * w], &hi[2 * w..]);
            for x in 0..w {
                let (cov, v, hav) = (ar[x], vv[x], ha[x]);
                let ok = (cov > 0.0) & (v > 0.0) & (hav > MIN_HISTORY_ALPHA);
                let k = cov / fmax(hav, MIN_HISTORY_ALPHA);
                let [ty, tco, tcg] = to_ycocg(hr[x] * k, hg[x] * k, hb[x] * k);
                let [cr, cg, cb] = from_ycocg(
                    fmin(fmax(ty, ly[x]), hy[x]),
                    fmin(fmax(tco, lco[x]), hco[x]),
                    fmin(fmax(tcg, lcg[x]), hcg[x]),
                );
                // Branch-free (vectorizable): weight 0 where the history is unusable.
                let wt = blend * v * fmin(hav, 1.0) * (ok as u32 as f32);
                rr[x] = fmax(rr[x] + wt * (cr - rr[x]), 0.0);
                gr[x] = fmax(gr[x] + wt * (cg - gr[x]), 0.0);
                br[x] = fmax(br[x] + wt * (cb - br[x]), 0.0);
            }
            std::mem::swap(&mut above, &mut centre);
            std::mem::swap(&mut centre, &mut below);
        }
    });
}

/// `dst[x] = min(src[x-1], src[x], src[x+1])`, edges clamped.
fn min3(src: &[f32], dst: &mut [f32]) {
    let w = src.len();
    if w < 2 {
        dst.copy_from_slice(src);
        return;
    }
    dst[0] = fmin(src[0], src[1]);
    for (d, s) in dst[1..w - 1].iter_mut().zip(src.windows(3)) {
        *d = fmin(fmin(s[0], s[1]), s[2]);
    }
    dst[w - 1] = fmin(src[w - 2], src[w - 1]);
}

/// `dst[x] = max(src[x-1], src[x], src[x+1])`, edges clamped.
fn max3(src: &[f32], dst: &mut [f32]) {
    let w = src.len();
    if w < 2 {
        dst.copy_from_slice(src);
        return;
    }
    dst[0] = fmax(src[0], src[1]);
    for (d, s) in dst[1..w - 1].iter_mut().zip(src.windows(3)) {
        *d = fmax(fmax(s[0], s[1]), s[2]);
    }
    dst[w - 1] = fmax(src[w - 2], src[w - 1]);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn noise(i: usize, seed: u64) -> f32 {
        let mut z = (i as u64).wrapping_add(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    }

    fn gray(w: usize, h: usize, f: impl Fn(usize) -> f32) -> Image {
        let mut img = Image::filled(w, h, 4, 1.0);
        for c in 0..3 {
            for i in 0..w * h {
                img.data[c * w * h + i] = f(i);
            }
        }
        img
    }

    #[test]
    fn ycocg_round_trips() {
        let [y, co, cg] = to_ycocg(0.2, 0.7, 1.3);
        let [r, g, b] = from_ycocg(y, co, cg);
        assert!((r - 0.2).abs() < 1e-6 && (g - 0.7).abs() < 1e-6 && (b - 1.3).abs() < 1e-6);
    }

    #[test]
    fn noise_is_averaged_with_history() {
        let (w, h) = (64, 50);
        let mut cur = gray(w, h, |i| 0.5 + 0.2 * (noise(i, 1) - 0.5));
        let hist = ReprojectedFrame {
            color: gray(w, h, |_| 0.5),
            valid: vec![1.0; w * h],
        };
        let before: f32 = cur.plane(0).iter().map(|v| (v - 0.5).abs()).sum();
        stabilize(&mut cur, &hist, 0.6);
        let after: f32 = cur.plane(0).iter().map(|v| (v - 0.5).abs()).sum();
        assert!(after < 0.5 * before, "error {before} -> {after}");
    }

    #[test]
    fn ghosts_are_clamped_away_and_invalid_history_ignored() {
        let (w, h) = (40, 40);
        let mut cur = gray(w, h, |_| 0.2);
        // The history holds a bright object that is no longer there.
        let hist = ReprojectedFrame {
            color: gray(w, h, |i| if i % w < 20 { 5.0 } else { 0.2 }),
            valid: vec![1.0; w * h],
        };
        stabilize(&mut cur, &hist, 0.9);
        assert!(cur.data[..3 * w * h]
            .iter()
            .all(|&v| (v - 0.2).abs() < 1e-6));
        let mut cur = gray(w, h, |i| 0.2 + 0.1 * noise(i, 3));
        let orig = cur.clone();
        let hist = ReprojectedFrame {
            color: gray(w, h, |_| 0.25),
            valid: vec![0.0; w * h],
        };
        stabilize(&mut cur, &hist, 0.9);
        assert_eq!(cur, orig);
    }

    #[test]
    fn in_place_bands_match_a_reference() {
        // Compare with a straightforward out-of-place implementation.
        let (w, h) = (37, 3 * BAND_ROWS + 5);
        let n = w * h;
        let cur = gray(w, h, |i| noise(i, 7) * 2.0);
        let hist = ReprojectedFrame {
            color: gray(w, h, |i| noise(i, 8) * 2.0),
            valid: (0..n).map(|i| noise(i, 9)).collect(),
        };
        let mut fast = cur.clone();
        stabilize(&mut fast, &hist, 0.7);
        let yc = |x: usize, y: usize| to_ycocg(cur.at(x, y, 0), cur.at(x, y, 1), cur.at(x, y, 2));
        for y in 0..h {
            for x in 0..w {
                let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
                for yy in y.saturating_sub(1)..(y + 2).min(h) {
                    for xx in x.saturating_sub(1)..(x + 2).min(w) {
                        let v = yc(xx, yy);
                        for c in 0..3 {
                            lo[c] = lo[c].min(v[c]);
                            hi[c] = hi[c].max(v[c]);
                        }
                    }
                }
                let p = y * w + x;
                let hv = to_ycocg(
                    hist.color.data[p],
                    hist.color.data[n + p],
                    hist.color.data[2 * n + p],
                );
                let cl = [
                    hv[0].clamp(lo[0], hi[0]),
                    hv[1].clamp(lo[1], hi[1]),
                    hv[2].clamp(lo[2], hi[2]),
                ];
                let hr = from_ycocg(cl[0], cl[1], cl[2]);
                for (c, hc) in hr.iter().enumerate() {
                    let cv = cur.at(x, y, c);
                    let want = (cv + 0.7 * hist.valid[p] * (hc - cv)).max(0.0);
                    assert!((fast.at(x, y, c) - want).abs() < 1e-5, "({x},{y},{c})");
                }
            }
        }
    }
}
