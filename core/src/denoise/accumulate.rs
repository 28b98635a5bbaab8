//! Temporal accumulation of denoised frames: the denoise stage's output
//! blended with the previous accumulated frame, reprojected into the
//! current view, so what flickers from frame to frame after a per-frame
//! denoiser (its residual noise, its blotches that move with the sample
//! pattern) averages away.
//!
//! Per pixel, in YCoCg of `log1p(color)` (a perceptual-ish space where a
//! bright highlight's noise does not dominate its neighbors' statistics):
//! 1. the previous accumulation is sampled where the pixel was in the
//!    previous frame (the host's motion vectors; else its depth and both
//!    cameras; else the same pixel when the camera did not move) with a
//!    Catmull-Rom kernel (bilinear blurs: each frame resamples the history
//!    once more, and the blur compounds);
//! 2. it is clipped to the mean ± [`GAMMA`] standard deviations of the
//!    current frame's 3x3 neighborhood (variance clipping): what the
//!    current frame cannot have (the ghost of a moved object, a
//!    disocclusion the depth test missed, a changed light) is pulled to
//!    what it can;
//! 3. it is blended with weight `1 - ALPHA` (the current frame weighs
//!    [`ALPHA`]).
//!
//! No history is used where the pixel was outside the previous frame, where
//! the previous depth there is not the expected one
//! ([`crate::temporal::reproject::depth_match`]), or where this or the
//! previous frame is not fully covered. A reset (cut, gap, size or setting
//! change) starts the accumulation again from the frame itself.
//!
//! Measured on the out-of-domain noisy sequences (`scripts/quality.sh`):
//! see `training/experiments/temporal_denoise.py` for the reference and
//! `docs/model_card.md` for the numbers.

use rayon::prelude::*;

use crate::error::Result;
use crate::frame::{Camera, Image, PreparedFrame, Recycler};
use crate::ops::inpaint::FULL;
use crate::temporal::reproject::{depth_match, CameraMap};
use crate::temporal::{camera_mode, consecutive, ReprojectionMode};

/// Weight of the current frame in the blend. Chosen on the out-of-domain
/// noisy sequences among 0.3 to 0.7 (`training/experiments/temporal_denoise.py`
/// fixed 0.5 beforehand): more history lowers the PSNR there (each frame's
/// resampled, clipped history is a little off), less lets more flicker
/// through; 0.6 gave 34.33 dB against 34.17 at 0.5 on the raw 4-spp
/// sequence, and 0.08 dB less than 0.5 on the in-domain noisy one.
pub const ALPHA: f32 = 0.6;

/// Half-width of the clipping box in standard deviations.
pub const GAMMA: f32 = 2.0;

/// The accumulated frame, kept in the session's temporal state (replaced
/// only when a frame succeeds).
#[derive(Debug, Clone)]
pub struct Accumulation {
    width: usize,
    height: usize,
    /// Premultiplied RGB, 3 planes: what the stage handed the backend.
    rgb: Vec<f32>,
    /// The frame's planar depth, when it had one.
    depth: Option<Vec<f32>>,
    /// The frame's coverage, when it had one.
    coverage: Option<Vec<f32>>,
    camera: Option<Camera>,
    frame_index: Option<i64>,
}

impl Accumulation {
    /// Bytes held.
    pub fn bytes(&self) -> usize {
        4 * (self.rgb.len()
            + self.depth.as_ref().map_or(0, Vec::len)
            + self.coverage.as_ref().map_or(0, Vec::len))
    }

    /// Gives the buffers to `rec`.
    pub fn recycle(self, rec: &Recycler) {
        rec.give(self.rgb);
        for b in [self.depth, self.coverage].into_iter().flatten() {
            rec.give(b);
        }
    }

    /// Frame-sized f32 planes an accumulation keeps (RGB, and the depth
    /// and coverage when the frames have them) plus the 3 it works in.
    pub fn planes(depth: bool, coverage: bool) -> usize {
        6 + usize::from(depth) + usize::from(coverage)
    }
}

/// How the previous accumulation is found from the current frame.
enum Map<'a> {
    /// `p + motion(p)`, expected depth the current depth.
    Motion { mx: &'a [f32], my: &'a [f32] },
    /// Unprojected with the current depth and camera, projected with the
    /// previous camera.
    Camera(Box<CameraMap>),
    /// The same pixel (the camera did not move, or nothing says it did).
    Identity,
}

impl Map<'_> {
    /// Position in the previous frame (pixel centers at `+0.5`) and the
    /// depth expected there (NaN: unknown) of pixel (`i`, `j`) with
    /// current depth `d` (NaN: none).
    #[inline]
    fn at(&self, w: usize, i: usize, j: usize, d: f32) -> Option<(f32, f32, f32)> {
        let p = i * w + j;
        match self {
            Map::Motion { mx, my } => Some((j as f32 + 0.5 + mx[p], i as f32 + 0.5 + my[p], d)),
            Map::Camera(map) => map.position_at(i, j, d),
            Map::Identity => Some((j as f32 + 0.5, i as f32 + 0.5, d)),
        }
    }
}

/// Catmull-Rom weights at fractional offset `t`.
#[inline]
fn catmull_rom(t: f32) -> [f32; 4] {
    let (t2, t3) = (t * t, t * t * t);
    [
        -0.5 * t3 + t2 - 0.5 * t,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * t,
        0.5 * t3 - 0.5 * t2,
    ]
}

#[inline]
fn log_ycocg(r: f32, g: f32, b: f32) -> [f32; 3] {
    let (r, g, b) = (r.max(0.0).ln_1p(), g.max(0.0).ln_1p(), b.max(0.0).ln_1p());
    [
        0.25 * r + 0.5 * g + 0.25 * b,
        0.5 * (r - b),
        0.5 * g - 0.25 * (r + b),
    ]
}

#[inline]
fn from_log_ycocg(c: [f32; 3]) -> [f32; 3] {
    let t = c[0] - c[2];
    [t + c[1], c[0] + c[2], t - c[1]].map(|v| v.exp_m1().max(0.0))
}

/// Blends the premultiplied RGB of `frame` (its first 3 planes) in place
/// with `prev` reprojected (see the module docs); `prev` `None` (a reset,
/// the first frame) or of another size leaves the color as it is. Returns
/// the new accumulation (buffers from `rec`), to be kept when the frame
/// succeeds.
///
/// Errors: [`crate::Error::OutOfMemory`] when a buffer cannot be
/// allocated; the frame is unchanged then.
pub fn accumulate(
    prev: Option<&Accumulation>,
    frame: &mut PreparedFrame,
    pool: &rayon::ThreadPool,
    rec: &Recycler,
) -> Result<Accumulation> {
    let (w, h) = (frame.width(), frame.height());
    let n = w * h;
    let prev = prev.filter(|p| p.width == w && p.height == h && n > 0);
    let PreparedFrame {
        color,
        motion,
        depth: cur_depth,
        coverage: cur_coverage,
        camera,
        frame_index,
        ..
    } = frame;
    let (cur_depth, cur_coverage) = (cur_depth.as_deref(), cur_coverage.as_deref());
    // As the history is reprojected (`HistoryView::mode` for frame 0).
    let map = prev.and_then(|p| {
        if let Some(m) = motion
            .as_ref()
            .filter(|_| consecutive(*frame_index, p.frame_index))
        {
            return Some(Map::Motion {
                mx: m.plane(0),
                my: m.plane(1),
            });
        }
        match camera_mode(*camera, p.camera, cur_depth.is_some()) {
            ReprojectionMode::DepthCamera => {
                let (c, pc) = (camera.as_ref()?, p.camera.as_ref()?);
                Some(Map::Camera(Box::new(CameraMap::from_cameras(c, pc, w, h))))
            }
            ReprojectionMode::Identity => Some(Map::Identity),
            _ => None,
        }
    });
    // The new accumulation keeps the frame's depth and coverage as they are
    // (a buffer dropped on an allocation error is freed, not recycled).
    let copy = |src: &[f32]| -> Result<Vec<f32>> {
        let mut v = rec.try_take(src.len())?;
        v.copy_from_slice(src);
        Ok(v)
    };
    let mut rgb = rec.try_take(3 * n)?;
    let depth = cur_depth.map(copy).transpose()?;
    let coverage = cur_coverage.map(copy).transpose()?;
    if let (Some(prev), Some(map)) = (prev, map) {
        // The current frame in log-YCoCg (read by the 3x3 statistics while
        // the color is written in place).
        let mut cur = rgb; // reused: 3 planes, filled below
        pool.install(|| {
            let c = &color.data;
            let (y0, rest) = cur.split_at_mut(n);
            let (co, cg) = rest.split_at_mut(n);
            y0.par_chunks_mut(w)
                .zip(co.par_chunks_mut(w))
                .zip(cg.par_chunks_mut(w))
                .enumerate()
                .for_each(|(i, ((a, b), d))| {
                    for j in 0..w {
                        let p = i * w + j;
                        let v = log_ycocg(c[p], c[n + p], c[2 * n + p]);
                        (a[j], b[j], d[j]) = (v[0], v[1], v[2]);
                    }
                })
        });
        let aovs = (cur_depth, cur_coverage);
        blend(prev, color, aovs, &map, &cur, pool);
        rgb = cur;
    }
    rgb.copy_from_slice(&color.data[..3 * n]);
    Ok(Accumulation {
        width: w,
        height: h,
        rgb,
        depth,
        coverage,
        camera: *camera,
        frame_index: *frame_index,
    })
}

/// The blend pass: rows in parallel, each pixel from `cur` (the frame's
/// log-YCoCg planes, unchanged) and `prev`, into `color`, with the frame's
/// depth and coverage (`aovs`).
fn blend(
    prev: &Accumulation,
    color: &mut Image,
    aovs: (Option<&[f32]>, Option<&[f32]>),
    map: &Map<'_>,
    cur: &[f32],
    pool: &rayon::ThreadPool,
) {
    let (w, h) = (color.width, color.height);
    let n = w * h;
    let (depth, coverage) = aovs;
    let (rgb, _) = color.data.split_at_mut(3 * n);
    let (r, gb) = rgb.split_at_mut(n);
    let (g, b) = gb.split_at_mut(n);
    let planes = [&cur[..n], &cur[n..2 * n], &cur[2 * n..3 * n]];
    pool.install(|| {
        r.par_chunks_mut(w)
            .zip(g.par_chunks_mut(w))
            .zip(b.par_chunks_mut(w))
            .enumerate()
            .for_each(|(i, ((r, g), b))| {
                for j in 0..w {
                    let p = i * w + j;
                    if coverage.is_some_and(|c| c[p] < FULL) {
                        continue;
                    }
                    let d = depth.map_or(f32::NAN, |d| d[p]);
                    let Some(hist) = map
                        .at(w, i, j, d)
                        .and_then(|(x, y, e)| sample(prev, x, y, e))
                    else {
                        continue;
                    };
                    // 3x3 statistics of the current frame (edges clamped).
                    let mut m = [0.0f32; 3];
                    let mut m2 = [0.0f32; 3];
                    for di in [i.saturating_sub(1), i, (i + 1).min(h - 1)] {
                        for dj in [j.saturating_sub(1), j, (j + 1).min(w - 1)] {
                            let q = di * w + dj;
                            for c in 0..3 {
                                let v = planes[c][q];
                                m[c] += v;
                                m2[c] += v * v;
                            }
                        }
                    }
                    let hist = log_ycocg(hist[0], hist[1], hist[2]);
                    let mut out = [0.0f32; 3];
                    for c in 0..3 {
                        let mean = m[c] / 9.0;
                        let sd = (m2[c] / 9.0 - mean * mean).max(0.0).sqrt();
                        let hc = hist[c].clamp(mean - GAMMA * sd, mean + GAMMA * sd);
                        out[c] = ALPHA * planes[c][p] + (1.0 - ALPHA) * hc;
                    }
                    let [vr, vg, vb] = from_log_ycocg(out);
                    if vr.is_finite() && vg.is_finite() && vb.is_finite() {
                        (r[j], g[j], b[j]) = (vr, vg, vb);
                    }
                }
            })
    });
}

/// `prev`'s RGB at position (`x`, `y`) (pixel centers at `+0.5`) with
/// Catmull-Rom weights, or `None` where there is no usable history: the
/// position outside the frame's pixel centers, the nearest previous pixel
/// not fully covered, or its depth not `expected` (NaN: not tested).
#[inline]
fn sample(prev: &Accumulation, x: f32, y: f32, expected: f32) -> Option<[f32; 3]> {
    let (w, h) = (prev.width, prev.height);
    let (u, v) = (x - 0.5, y - 0.5);
    if !(u >= 0.0 && v >= 0.0 && u <= (w - 1) as f32 && v <= (h - 1) as f32) {
        return None;
    }
    let nearest = (v + 0.5) as usize * w + (u + 0.5) as usize;
    if prev.coverage.as_ref().is_some_and(|c| c[nearest] < FULL) {
        return None;
    }
    // (Empty depth, at or beyond `FAR_DEPTH`, only matches empty depth.)
    if let Some(d) = prev.depth.as_ref() {
        if !expected.is_nan() && !depth_match(expected, d[nearest]) {
            return None;
        }
    }
    let (x0, y0) = (u.floor(), v.floor());
    let (wx, wy) = (catmull_rom(u - x0), catmull_rom(v - y0));
    let (x0, y0) = (x0 as isize, y0 as isize);
    let n = w * h;
    let mut out = [0.0f32; 3];
    for (a, wya) in wy.iter().enumerate() {
        let yi = (y0 - 1 + a as isize).clamp(0, h as isize - 1) as usize;
        let mut row = [0.0f32; 3];
        for (b, wxb) in wx.iter().enumerate() {
            let xi = (x0 - 1 + b as isize).clamp(0, w as isize - 1) as usize;
            let q = yi * w + xi;
            for (c, r) in row.iter_mut().enumerate() {
                *r += wxb * prev.rgb[c * n + q];
            }
        }
        for (o, r) in out.iter_mut().zip(row) {
            *o += wya * r;
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pool() -> rayon::ThreadPool {
        rayon::ThreadPoolBuilder::new()
            .num_threads(2)
            .build()
            .unwrap()
    }

    fn frame(w: usize, h: usize, f: impl Fn(usize, usize, usize) -> f32) -> PreparedFrame {
        let mut data = vec![0.0; 3 * w * h];
        for c in 0..3 {
            for i in 0..h {
                for j in 0..w {
                    data[c * w * h + i * w + j] = f(c, i, j);
                }
            }
        }
        PreparedFrame::from_color(Image {
            width: w,
            height: h,
            channels: 3,
            data,
        })
    }

    fn noise(seed: u64, c: usize, i: usize, j: usize) -> f32 {
        let mut s = seed ^ ((c as u64) << 40) ^ ((i as u64) << 20) ^ j as u64;
        s = s.wrapping_mul(0x9E37_79B9_7F4A_7C15);
        s ^= s >> 29;
        s = s.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        s ^= s >> 32;
        (s % 10_000) as f32 / 10_000.0 - 0.5
    }

    #[test]
    fn a_static_noisy_sequence_converges_towards_its_mean() {
        let (w, h) = (24, 16);
        let (pool, rec) = (pool(), Recycler::default());
        let mut acc: Option<Accumulation> = None;
        let mut err_first = 0.0;
        let mut err_last = 0.0;
        for t in 0..12u64 {
            let mut f = frame(w, h, |c, i, j| 0.5 + 0.1 * noise(t, c, i, j));
            let next = accumulate(acc.as_ref(), &mut f, &pool, &rec).unwrap();
            let err: f32 = f.color.data.iter().map(|v| (v - 0.5).powi(2)).sum();
            if t == 0 {
                err_first = err;
            }
            err_last = err;
            acc = Some(next);
        }
        assert!(err_last < 0.5 * err_first, "{err_last} vs {err_first}");
    }

    #[test]
    fn a_changed_frame_is_not_ghosted() {
        let (w, h) = (16, 16);
        let (pool, rec) = (pool(), Recycler::default());
        let mut a = frame(w, h, |_, _, _| 0.1);
        let acc = accumulate(None, &mut a, &pool, &rec).unwrap();
        // Every pixel changes by far more than the new frame's spread.
        let mut b = frame(w, h, |c, i, j| 2.0 + 0.01 * noise(3, c, i, j));
        accumulate(Some(&acc), &mut b, &pool, &rec).unwrap();
        for v in &b.color.data {
            assert!((v - 2.0).abs() < 0.05, "{v}");
        }
    }

    #[test]
    fn motion_vectors_find_the_previous_pixel() {
        // A ramp moving right by 2 pixels a frame: the history of pixel j is
        // pixel j - 2 of the previous frame, the same value; the result is
        // the ramp itself (where the history exists), not a blend of
        // different values.
        let (w, h) = (20, 6);
        let (pool, rec) = (pool(), Recycler::default());
        let ramp =
            |shift: usize| move |_c: usize, _i: usize, j: usize| (j + 100 - shift) as f32 * 0.01;
        let mut a = frame(w, h, ramp(0));
        let acc = accumulate(None, &mut a, &pool, &rec).unwrap();
        let mut b = frame(w, h, ramp(2));
        b.motion = Some(Image {
            width: w,
            height: h,
            channels: 2,
            data: [vec![-2.0; w * h], vec![0.0; w * h]].concat(),
        });
        accumulate(Some(&acc), &mut b, &pool, &rec).unwrap();
        for j in 3..w - 2 {
            let want = (j + 98) as f32 * 0.01;
            assert!((b.color.data[2 * w + j] - want).abs() < 1e-4, "{j}");
        }
    }

    #[test]
    fn a_depth_mismatch_or_a_hole_keeps_the_current_color() {
        let (w, h) = (8, 8);
        let (pool, rec) = (pool(), Recycler::default());
        let mut a = frame(w, h, |_, _, _| 0.5);
        a.depth = Some(vec![1.0; w * h]);
        let acc = accumulate(None, &mut a, &pool, &rec).unwrap();
        let mut b = frame(w, h, |c, i, j| 0.5 + 0.2 * noise(1, c, i, j));
        let before = b.color.data.clone();
        b.depth = Some(vec![5.0; w * h]);
        accumulate(Some(&acc), &mut b, &pool, &rec).unwrap();
        assert_eq!(b.color.data, before);

        let mut c = frame(w, h, |c, i, j| 0.5 + 0.2 * noise(2, c, i, j));
        let before = c.color.data.clone();
        c.coverage = Some(vec![0.5; w * h]);
        accumulate(Some(&acc), &mut c, &pool, &rec).unwrap();
        assert_eq!(c.color.data, before);
    }
}
