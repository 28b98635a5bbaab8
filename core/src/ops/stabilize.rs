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

use super::{fmax, fmin, par_bands_mut, row_max, simd, Rect, BAND_ROWS};
use crate::frame::{Image, RgbaImage};
use crate::temporal::{HistoryView, LatticeRows, ReprojectedFrame};

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
#[inline(always)]
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

/// Vertical 3-tap min and max of three YCoCg rows (3 planes of `w`), into
/// planes of `w + 2` padded by repeating the first and last value, so the
/// horizontal 3-tap is three shifted slices with edges clamped.
#[inline(always)]
fn vertical_min_max(rows: [&[f32]; 3], w: usize, lo: &mut [f32], hi: &mut [f32]) {
    let [a0, a1, a2] = rows;
    for c in 0..3 {
        let s = c * w..(c + 1) * w;
        let (r0, r1, r2) = (&a0[s.clone()], &a1[s.clone()], &a2[s]);
        let p = c * (w + 2);
        let (l, hh) = (&mut lo[p + 1..p + w + 1], &mut hi[p + 1..p + w + 1]);
        for x in 0..w {
            l[x] = fmin(fmin(r0[x], r1[x]), r2[x]);
            hh[x] = fmax(fmax(r0[x], r1[x]), r2[x]);
        }
        lo[p] = lo[p + 1];
        hi[p] = hi[p + 1];
        lo[p + w + 1] = lo[p + w];
        hi[p + w + 1] = hi[p + w];
    }
}

/// Horizontal 3-tap minimum at `x` of a padded plane.
#[inline(always)]
fn min3_at(p: (&[f32], &[f32], &[f32]), x: usize) -> f32 {
    fmin(fmin(p.0[x], p.1[x]), p.2[x])
}

/// Horizontal 3-tap maximum at `x` of a padded plane.
#[inline(always)]
fn max3_at(p: (&[f32], &[f32], &[f32]), x: usize) -> f32 {
    fmax(fmax(p.0[x], p.1[x]), p.2[x])
}

/// The three shifted views (`x - 1`, `x`, `x + 1`) of padded plane `c`.
fn shifted(v: &[f32], c: usize, w: usize) -> (&[f32], &[f32], &[f32]) {
    let p = c * (w + 2);
    (&v[p..p + w], &v[p + 1..p + w + 1], &v[p + 2..p + w + 2])
}

/// Columns `o..o + m` of the three shifted views [`shifted`] gives.
fn columns<'v>(
    v: (&'v [f32], &'v [f32], &'v [f32]),
    o: usize,
    m: usize,
) -> (&'v [f32], &'v [f32], &'v [f32]) {
    (&v.0[o..o + m], &v.1[o..o + m], &v.2[o..o + m])
}

/// Where [`stabilize_rows`] takes the history from, row by row.
pub trait HistoryRows: Sync {
    /// Writes columns `x0..x0 + rgba.len()` of row `y` of the reprojected
    /// history's RGBA (interleaved) and validity into `rgba` and `valid`
    /// (at least as long). A row [`HistoryRows::needed`] names is read
    /// whole (`x0` 0, the frame's width).
    fn row(&self, y: usize, x0: usize, rgba: &mut [[f32; 4]], valid: &mut [f32]);

    /// Whether row `y` must still be read when nothing on it is blended
    /// (outside the area of [`stabilize_rows_in`]): true when reading it
    /// records something besides the blend (the scene probe's rows).
    #[inline(always)]
    fn needed(&self, _y: usize) -> bool {
        false
    }
}

/// A whole reprojected frame, row by row.
impl HistoryRows for ReprojectedFrame {
    #[inline(always)]
    fn row(&self, y: usize, x0: usize, rgba: &mut [[f32; 4]], valid: &mut [f32]) {
        let (w, n) = (self.color.width, self.color.len());
        let (s, m) = (y * w + x0, rgba.len());
        for (x, px) in rgba.iter_mut().enumerate() {
            *px = std::array::from_fn(|c| self.color.data[c * n + s + x]);
        }
        valid[..m].copy_from_slice(&self.valid[s..s + m]);
    }
}

/// History frame `k` of a view, reprojected row by row
/// ([`HistoryView::reproject_span_rgba`]), as [`HistoryRows`]; inlined into
/// the blend pass (and vectorized with it).
pub struct ViewRows<'v, 'a> {
    /// The view.
    pub view: &'v HistoryView<'a>,
    /// Which history frame.
    pub k: usize,
    /// Where the rows at the scene-cut detector's lattice are recorded as
    /// they are made (RGB and validity), so the detector needs no
    /// reprojection of its own.
    pub probe: Option<&'v LatticeRows<'v>>,
}

impl HistoryRows for ViewRows<'_, '_> {
    #[inline(always)]
    fn needed(&self, y: usize) -> bool {
        self.probe.is_some_and(|p| p.lattice().row_of(y).is_some())
    }

    #[inline(always)]
    fn row(&self, y: usize, x0: usize, rgba: &mut [[f32; 4]], valid: &mut [f32]) {
        self.view.reproject_span_rgba(self.k, y, x0, rgba, valid);
        // The probe's rows are read whole (`needed`); a part of a row
        // records nothing.
        if let Some(p) = self
            .probe
            .filter(|_| x0 == 0 && rgba.len() == self.view.current().width())
        {
            p.set(y, |x| {
                let c = rgba[x];
                [c[0], c[1], c[2], valid[x]]
            });
        }
    }
}

/// Blends `img` (4 planes, premultiplied) with `history` in place: weight
/// `blend * validity`, history clamped to the 3x3 YCoCg range of `img`.
/// Alpha is kept; pixels with A = 0 or without usable history keep their
/// color (negative values become 0 in rows that hold some history).
///
/// See [`stabilize_rows`], which takes the history row by row.
pub fn stabilize(img: &mut Image, history: &ReprojectedFrame, blend: f32) {
    assert_eq!(
        (history.color.width, history.color.len()),
        (img.width, img.len()),
        "history and frame sizes differ"
    );
    stabilize_rows(img, blend, None, history);
}

/// [`stabilize`] with the history given row by row: `history.row(y, 0,
/// rgba, valid)` writes row `y` of the reprojected history's RGBA
/// (interleaved) and validity into the row-long slices `rgba` and `valid`
/// (as [`HistoryView::reproject_span_rgba`] does, [`ViewRows`]), once per row,
/// from the pool's threads. The history is never held as a whole frame.
///
/// One pass over the image: each band keeps a sliding window of three YCoCg
/// rows, and the horizontal min/max is taken inside the blend loop. Rows
/// without valid history are skipped (only the window rolls on). With
/// `kept` (`4 * width * height` samples), the result is also written there
/// interleaved (pixel `p` at `4 * p..4 * p + 4`, as
/// [`crate::frame::RgbaImage::set_planes`] writes it), every row, from the
/// same pass.
pub fn stabilize_rows<H: HistoryRows>(
    img: &mut Image,
    blend: f32,
    kept: Option<&mut [f32]>,
    history: &H,
) {
    stabilize_rows_on(img, blend, kept, history, None, true)
}

/// [`stabilize_rows`] blending only the pixels inside `area`; the others
/// keep their color (and are still written to `kept`). The history is read
/// for the area's columns of its rows alone, and whole for the rows
/// [`HistoryRows::needed`] names; the color range, for the area's columns
/// and one on either side. An empty `area` blends nothing.
pub fn stabilize_rows_in<H: HistoryRows>(
    img: &mut Image,
    blend: f32,
    kept: Option<&mut [f32]>,
    history: &H,
    area: Rect,
) {
    stabilize_rows_on(img, blend, kept, history, Some(area), true)
}

/// [`stabilize_rows`], its bands through [`simd`] when `vectorized` (else
/// compiled for the baseline instruction set, which gives the same bits).
fn stabilize_rows_on<H: HistoryRows>(
    img: &mut Image,
    blend: f32,
    kept: Option<&mut [f32]>,
    history: &H,
    area: Option<Rect>,
    vectorized: bool,
) {
    let (w, h) = (img.width, img.height);
    let area = area.map_or(Rect::full(w, h), |a| Rect {
        x0: a.x0.min(w),
        y0: a.y0.min(h),
        x1: a.x1.min(w),
        y1: a.y1.min(h),
    });
    if w * h == 0 {
        return;
    }
    if let Some(k) = kept.as_deref() {
        assert_eq!(k.len(), 4 * w * h, "kept holds 4 samples per pixel");
    }
    if blend <= 0.0 {
        if let Some(k) = kept {
            let planes = [0, 1, 2, 3].map(|c| img.plane(c));
            RgbaImage::interleave(planes, k.as_chunks_mut::<4>().0);
        }
        return;
    }
    let bands = h.div_ceil(BAND_ROWS);
    let band_rows = |bi: usize| bi * BAND_ROWS..((bi + 1) * BAND_ROWS).min(h);
    // The columns the blend reads: the area's and one on either side (the
    // 3x3 range); the YCoCg rows and their minima and maxima are made for
    // these only.
    let cols = match area.x1 > area.x0 {
        true => area.x0.saturating_sub(1)..(area.x1 + 1).min(w),
        false => 0..0,
    };
    // YCoCg of the first and last row of every band, taken before any change.
    let edges: Vec<(Vec<f32>, Vec<f32>)> = {
        let src = &*img;
        let cols = &cols;
        (0..bands)
            .into_par_iter()
            .map(|bi| {
                let rows = band_rows(bi);
                let row = |y: usize| {
                    let mut out = vec![0.0; 3 * cols.len()];
                    let s = y * w + cols.start..y * w + cols.end;
                    row_ycocg(
                        &src.plane(0)[s.clone()],
                        &src.plane(1)[s.clone()],
                        &src.plane(2)[s],
                        &mut out,
                    );
                    out
                };
                (row(rows.start), row(rows.end - 1))
            })
            .collect()
    };
    // The kept copy in the same bands as the image (or none for any band).
    let kept_bands: Vec<Option<&mut [[f32; 4]]>> = match kept {
        Some(k) => k
            .as_chunks_mut::<4>()
            .0
            .chunks_mut(BAND_ROWS * w)
            .map(Some)
            .collect(),
        None => (0..bands).map(|_| None).collect(),
    };
    par_bands_mut(img, 0, h)
        .zip(kept_bands)
        .for_each(|((y0, [r, g, b, a]), kept)| {
            let job = BandJob {
                y0,
                w,
                h,
                blend,
                edges: &edges,
                planes: [r, g, b, a],
                kept,
                history,
                area,
                cols: cols.clone(),
            };
            if vectorized {
                simd(job)
            } else {
                pulp::WithSimd::with_simd(job, pulp::Scalar::new())
            }
        });
}

/// One band of [`stabilize_rows`]: rows `y0..` (`planes`, and their place
/// in `kept`) of a `w` x `h` image, with the YCoCg edge rows of every band;
/// run by [`simd`], so its loops are vectorized for the CPU's widest
/// instructions.
struct BandJob<'e, 'p, H> {
    y0: usize,
    w: usize,
    h: usize,
    blend: f32,
    edges: &'e [(Vec<f32>, Vec<f32>)],
    planes: [&'p mut [f32]; 4],
    kept: Option<&'p mut [[f32; 4]]>,
    history: &'e H,
    area: Rect,
    /// The columns of the YCoCg rows (the area's, one more on either side).
    cols: std::ops::Range<usize>,
}

impl<H: HistoryRows> pulp::WithSimd for BandJob<'_, '_, H> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _: S) {
        let BandJob {
            y0,
            w,
            h,
            blend,
            edges,
            planes: [r, g, b, a],
            mut kept,
            history,
            area,
            cols,
        } = self;
        let (ax0, ax1) = (area.x0, area.x1.max(area.x0));
        // The window's width and where the area starts in it.
        let (cw, c0) = (cols.len(), cols.start);
        let bi = y0 / BAND_ROWS;
        let rows = a.len() / w;
        // Sliding window of YCoCg rows of the unmodified image.
        let mut above = if y0 > 0 {
            edges[bi - 1].1.clone()
        } else {
            edges[bi].0.clone()
        };
        let mut centre = edges[bi].0.clone();
        let mut below = vec![0.0; 3 * cw];
        let mut lo = vec![0.0; 3 * (cw + 2)];
        let mut hi = vec![0.0; 3 * (cw + 2)];
        // One row of the history: RGBA and validity (the window's columns
        // from `c0`, or the whole row from 0 where it is needed whole).
        let mut hrgba = vec![[0.0; 4]; w];
        let mut vv = vec![0.0; w];
        for dy in 0..rows {
            let y = y0 + dy;
            // The window's rows are needed for the rows of the area and
            // one on either side; the others only roll on.
            let windowed = y + 2 >= area.y0 && y < area.y1;
            if dy + 1 < rows {
                if windowed {
                    let s = (dy + 1) * w + c0..(dy + 1) * w + cols.end;
                    row_ycocg(&r[s.clone()], &g[s.clone()], &b[s], &mut below);
                }
            } else if y + 1 < h {
                below.copy_from_slice(&edges[bi + 1].0);
            } else {
                below.copy_from_slice(&centre);
            }
            let inside = y >= area.y0 && y < area.y1 && ax1 > ax0;
            // Column x of the frame is at `x - off` in the history's row.
            let off = if history.needed(y) {
                history.row(y, 0, &mut hrgba, &mut vv);
                0
            } else {
                if inside {
                    history.row(y, c0, &mut hrgba[..cw], &mut vv[..cw]);
                }
                c0
            };
            if inside && row_max(&vv[ax0 - off..ax1 - off]) > 0.0 {
                vertical_min_max([&above, &centre, &below], cw, &mut lo, &mut hi);
                // The area's columns in the window, the frame's and the history's.
                let row = dy * w + ax0..dy * w + ax1;
                let (rr, gr, br, ar) = (
                    &mut r[row.clone()],
                    &mut g[row.clone()],
                    &mut b[row.clone()],
                    &a[row],
                );
                let (m, o) = (ax1 - ax0, ax0 - c0);
                let part = |v| columns(v, o, m);
                let (ly, lco, lcg) = (
                    part(shifted(&lo, 0, cw)),
                    part(shifted(&lo, 1, cw)),
                    part(shifted(&lo, 2, cw)),
                );
                let (hy, hco, hcg) = (
                    part(shifted(&hi, 0, cw)),
                    part(shifted(&hi, 1, cw)),
                    part(shifted(&hi, 2, cw)),
                );
                let (hrgba, vv) = (&hrgba[ax0 - off..ax1 - off], &vv[ax0 - off..ax1 - off]);
                for x in 0..m {
                    let [hr, hg, hb, hav] = hrgba[x];
                    let (cov, v) = (ar[x], vv[x]);
                    let ok = (cov > 0.0) & (v > 0.0) & (hav > MIN_HISTORY_ALPHA);
                    let k = cov / fmax(hav, MIN_HISTORY_ALPHA);
                    let [ty, tco, tcg] = to_ycocg(hr * k, hg * k, hb * k);
                    let [cr, cg, cb] = from_ycocg(
                        fmin(fmax(ty, min3_at(ly, x)), max3_at(hy, x)),
                        fmin(fmax(tco, min3_at(lco, x)), max3_at(hco, x)),
                        fmin(fmax(tcg, min3_at(lcg, x)), max3_at(hcg, x)),
                    );
                    // Branch-free (vectorizable): weight 0 where the history is unusable.
                    let wt = blend * v * fmin(hav, 1.0) * (ok as u32 as f32);
                    rr[x] = fmax(rr[x] + wt * (cr - rr[x]), 0.0);
                    gr[x] = fmax(gr[x] + wt * (cg - gr[x]), 0.0);
                    br[x] = fmax(br[x] + wt * (cb - br[x]), 0.0);
                }
            }
            if let Some(kb) = kept.as_deref_mut() {
                // The finished row, still in cache, into the kept copy.
                let row = dy * w..(dy + 1) * w;
                let planes = [
                    &r[row.clone()],
                    &g[row.clone()],
                    &b[row.clone()],
                    &a[row.clone()],
                ];
                RgbaImage::interleave(planes, &mut kb[row]);
            }
            std::mem::swap(&mut above, &mut centre);
            std::mem::swap(&mut centre, &mut below);
        }
    }
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

    const REF_W: usize = 37;
    const REF_H: usize = 3 * BAND_ROWS + 5;

    #[test]
    fn in_place_bands_match_a_reference() {
        check_against_reference((0..REF_W * REF_H).map(|i| noise(i, 9)).collect());
    }

    #[test]
    fn bands_and_rows_without_history_are_skipped_like_the_reference() {
        // No valid history in band 1 and in a few single rows elsewhere.
        let valid = (0..REF_W * REF_H)
            .map(|i| {
                let y = i / REF_W;
                let skip = (BAND_ROWS..2 * BAND_ROWS).contains(&y) || y % 7 == 3;
                if skip {
                    0.0
                } else {
                    noise(i, 9)
                }
            })
            .collect();
        check_against_reference(valid);
    }

    /// Blending only an area gives the whole pass's bits inside it and the
    /// input outside, in the image and in the kept copy.
    #[test]
    fn an_area_is_blended_as_by_the_whole_pass_and_nothing_else() {
        let (w, h) = (REF_W, REF_H);
        let n = w * h;
        let cur = gray(w, h, |i| noise(i, 18) * 3.0);
        let rows = ReprojectedFrame {
            color: gray(w, h, |i| noise(i, 20) * 3.0),
            valid: (0..n).map(|i| noise(i, 19)).collect(),
        };
        let mut whole = cur.clone();
        stabilize_rows(&mut whole, 0.8, None, &rows);
        // Across a band edge: away from the image's edges, at the left and
        // right edges (the columns read stop there), one column, the whole.
        let rect = |x0, x1| Rect {
            x0,
            y0: BAND_ROWS - 3,
            x1,
            y1: BAND_ROWS + 9,
        };
        let areas = [
            (rect(5, w - 7), 100),
            (rect(0, 9), 20),
            (rect(w - 9, w), 20),
            (rect(11, 12), 3),
            (Rect::full(w, h), 1000),
        ];
        for (area, least) in areas {
            let mut part = cur.clone();
            let mut kept = vec![f32::NAN; 4 * n];
            stabilize_rows_in(&mut part, 0.8, Some(&mut kept), &rows, area);
            let mut changed = 0;
            for c in 0..4 {
                for y in 0..h {
                    for x in 0..w {
                        let i = c * n + y * w + x;
                        let inside = area.contains(x, y);
                        let want = if inside { whole.data[i] } else { cur.data[i] };
                        assert_eq!(
                            part.data[i].to_bits(),
                            want.to_bits(),
                            "{area:?}: plane {c} at ({x}, {y})"
                        );
                        assert_eq!(kept[4 * (y * w + x) + c].to_bits(), want.to_bits());
                        changed += usize::from(inside && want != cur.data[i]);
                    }
                }
            }
            assert!(changed >= least, "{area:?} was blended ({changed} samples)");
        }
        // An empty area blends nothing.
        let mut none = cur.clone();
        stabilize_rows_in(&mut none, 0.8, None, &rows, Rect::default());
        assert_eq!(none, cur);
    }

    /// The pass compiled for the CPU's widest vectors (AVX2 here, where
    /// present) and for the baseline give the same bits.
    #[test]
    fn vectorized_and_baseline_passes_agree_bit_for_bit() {
        let (w, h) = (REF_W, REF_H);
        let n = w * h;
        let valid: Vec<f32> = (0..n)
            .map(|i| if (i / w) % 6 == 1 { 0.0 } else { noise(i, 7) })
            .collect();
        let cur = gray(w, h, |i| noise(i, 8) * 3.0);
        let rows = ReprojectedFrame {
            color: gray(w, h, |i| noise(i, 10) * 3.0),
            valid,
        };
        let run = |vectorized| {
            let mut img = cur.clone();
            let mut kept = vec![f32::NAN; 4 * n];
            stabilize_rows_on(&mut img, 0.8, Some(&mut kept), &rows, None, vectorized);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            (bits(&img.data), bits(&kept))
        };
        assert_eq!(run(true), run(false), "{:?}", pulp::Arch::new());
    }

    #[test]
    fn the_kept_copy_is_the_interleaved_result() {
        let (w, h) = (REF_W, REF_H);
        let n = w * h;
        // Valid history in some rows only, so skipped rows are kept too.
        let valid: Vec<f32> = (0..n)
            .map(|i| if (i / w) % 5 == 2 { 0.0 } else { noise(i, 4) })
            .collect();
        let cur = gray(w, h, |i| noise(i, 5) * 2.0);
        let hist = gray(w, h, |i| noise(i, 6) * 2.0);
        let rows = ReprojectedFrame { color: hist, valid };
        for blend in [0.7, 0.0] {
            let mut plain = cur.clone();
            stabilize(&mut plain, &rows, blend);
            let mut fused = cur.clone();
            let mut kept = vec![f32::NAN; 4 * n];
            stabilize_rows(&mut fused, blend, Some(&mut kept), &rows);
            assert_eq!(fused, plain, "blend {blend}");
            let want = crate::frame::RgbaImage::from_planes(&plain, None);
            assert_eq!(
                kept.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                want.data.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "blend {blend}"
            );
        }
    }

    /// Compares with a straightforward out-of-place implementation.
    fn check_against_reference(valid: Vec<f32>) {
        let (w, h) = (REF_W, REF_H);
        let n = w * h;
        let cur = gray(w, h, |i| noise(i, 7) * 2.0);
        let hist = ReprojectedFrame {
            color: gray(w, h, |i| noise(i, 8) * 2.0),
            valid,
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
