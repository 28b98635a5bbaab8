//! Insert harmonization: match the color statistics of an inserted object
//! to a ring of surrounding background with a few global filter parameters
//! ([`Tone`]: exposure, white balance, saturation).
//!
//! Statistics are taken in log2 space on unpremultiplied color
//! (`l_k = log2(c_k + 1e-3)`): per pixel a brightness `mu = mean_k l_k` and a
//! log chroma `chi_k = l_k - mu`. Over a region: the mean of each `l_k`, the
//! mean of `mu`, and the mean chroma magnitude
//! `sqrt(mean_k chi_k^2)`. The ring is a band around the insert (its width a
//! quarter of the insert's size, 8 to 128 pixels), built on a mask
//! downsampled by [`RING_CELL`] and excluding the insert and one cell around
//! its edge; empty-depth pixels (sky) do not count.
//!
//! The filter is conservative, because an object's own colors legitimately
//! differ from its surroundings (a yellow ball on a grey floor is not a
//! lighting error): only the part of a difference that exceeds what object
//! albedo explains is corrected. Exposure and white balance have a dead zone
//! ([`EXPOSURE_DEAD_ZONE`], [`CHROMA_DEAD_ZONE`]) with a soft knee beyond,
//! and only a share of the excess is taken (the `*_STRENGTH` constants).
//! The brightness evidence is the smaller of the differences in mean
//! brightness and in the brightest channel, so a saturated object (whose
//! geometric-mean brightness is low) is not brightened. A chroma difference
//! larger than any plausible illuminant cast ([`MAX_CAST`]) is taken to be
//! the object's own color and left alone. Saturation stays at identity
//! unless the evidence is strong: it is only ever reduced, when the insert
//! is far more saturated than its ring and its chroma points away from the
//! ring's illuminant. There is no contrast term: matching the insert's
//! brightness spread to its ring's cost 0.9-1.3 dB in the insert
//! on the generator's tone-shifted inserts and left out-of-domain inserts
//! unchanged (`docs/inserts.md`).

use rayon::prelude::*;

use super::{bbox_above, fast_exp2, fast_log2, fmax, par_bands_mut, Rect, EMPTY_DEPTH};
use crate::frame::Image;

/// Cell size (pixels) of the downsampled mask the ring is built on.
pub const RING_CELL: usize = 4;
/// Share of the brightness difference beyond the dead zone corrected by the exposure.
pub const EXPOSURE_STRENGTH: f32 = 0.6;
/// Brightness differences up to this many stops are object albedo: left alone.
pub const EXPOSURE_DEAD_ZONE: f32 = 1.5;
/// Width (stops) of the soft knee beyond [`EXPOSURE_DEAD_ZONE`].
pub const EXPOSURE_KNEE: f32 = 1.0;
/// Share of the chroma difference beyond the dead zone corrected by the white balance.
pub const WHITE_BALANCE_STRENGTH: f32 = 0.5;
/// RMS log-chroma differences up to this many stops are left alone.
pub const CHROMA_DEAD_ZONE: f32 = 0.5;
/// Width (stops) of the soft knee beyond [`CHROMA_DEAD_ZONE`].
pub const CHROMA_KNEE: f32 = 0.25;
/// RMS log-chroma differences fade from a correctable cast at this value to
/// the object's own color (no correction) at `MAX_CAST + 0.4`.
pub const MAX_CAST: f32 = 1.0;
/// Saturation is only reduced when the insert's mean chroma magnitude
/// exceeds the ring's by more than this (stops).
pub const SATURATION_EVIDENCE: f32 = 1.0;
/// Exponent on the chroma ratio beyond the evidence threshold (saturation).
pub const SATURATION_STRENGTH: f32 = 0.3;
/// Largest exposure change, stops.
pub const MAX_EXPOSURE: f32 = 3.0;
/// Largest white-balance shift per channel, stops.
pub const MAX_WHITE_BALANCE: f32 = 1.0;
/// The saturation factor stays at or above `1/MAX_FACTOR`.
pub const MAX_FACTOR: f32 = 1.6;

/// Offset inside the logarithm (scene-linear units).
const EPS: f32 = 1e-3;
/// Minimum summed weight (in sampled pixels) for a region to count.
const MIN_WEIGHT: f64 = 12.0;

/// A global color filter for the insert, in log2 space.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tone {
    /// Brightness change in stops.
    pub exposure: f32,
    /// Per-channel shift in stops; sums to 0 (brightness unchanged).
    pub white_balance: [f32; 3],
    /// Factor on the log chroma.
    pub saturation: f32,
}

impl Tone {
    /// The filter that changes nothing.
    pub const IDENTITY: Tone = Tone {
        exposure: 0.0,
        white_balance: [0.0; 3],
        saturation: 1.0,
    };

    /// Number of values in [`Tone::to_vec`].
    pub const LEN: usize = 5;

    /// The parameters as a flat vector (for the backend's carry).
    pub fn to_vec(&self) -> Vec<f32> {
        let wb = self.white_balance;
        vec![self.exposure, wb[0], wb[1], wb[2], self.saturation]
    }

    /// Reads [`Tone::to_vec`]'s layout; `None` for a wrong length or non-finite values.
    pub fn from_slice(v: &[f32]) -> Option<Tone> {
        if v.len() != Self::LEN || v.iter().any(|x| !x.is_finite()) || v[4] <= 0.0 {
            return None;
        }
        Some(Tone {
            exposure: v[0],
            white_balance: [v[1], v[2], v[3]],
            saturation: v[4],
        })
    }

    /// Moves a share `t` of the way to `target` (the saturation factor
    /// interpolates in log space).
    pub fn toward(&self, target: &Tone, t: f32) -> Tone {
        let lerp = |a: f32, b: f32| a + t * (b - a);
        let glerp = |a: f32, b: f32| (a.ln() + t * (b.ln() - a.ln())).exp();
        Tone {
            exposure: lerp(self.exposure, target.exposure),
            white_balance: [
                lerp(self.white_balance[0], target.white_balance[0]),
                lerp(self.white_balance[1], target.white_balance[1]),
                lerp(self.white_balance[2], target.white_balance[2]),
            ],
            saturation: glerp(self.saturation, target.saturation),
        }
    }

    /// True when no parameter moves by more than `tol` (stops for exposure
    /// and white balance, a ratio for saturation).
    pub fn is_near_identity(&self, tol: f32) -> bool {
        self.exposure.abs() <= tol
            && self.white_balance.iter().all(|w| w.abs() <= tol)
            && (self.saturation - 1.0).abs() <= tol
    }

    /// True when the filter changes nothing.
    pub fn is_identity(&self) -> bool {
        self.exposure == 0.0 && self.white_balance == [0.0; 3] && self.saturation == 1.0
    }
}

/// Log2 color statistics of one region.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Stats {
    /// Summed weight (sampled pixels).
    pub weight: f64,
    /// Mean of `log2(c_k + eps)` per channel.
    pub log_mean: [f64; 3],
    /// Mean brightness `mu`.
    pub brightness: f64,
    /// Mean chroma magnitude.
    pub chroma: f64,
}

/// Weighted sums: w, w*l_r, w*l_g, w*l_b, w*mu, w*chroma.
type Sums = [f64; 6];

fn add(s: &mut Sums, wt: f32, l: [f32; 3], mu: f32, chroma: f32) {
    let wt = wt as f64;
    s[0] += wt;
    s[1] += wt * l[0] as f64;
    s[2] += wt * l[1] as f64;
    s[3] += wt * l[2] as f64;
    s[4] += wt * mu as f64;
    s[5] += wt * chroma as f64;
}

fn finish(s: &Sums) -> Option<Stats> {
    if s[0] < MIN_WEIGHT {
        return None;
    }
    let w = s[0];
    Some(Stats {
        weight: w,
        log_mean: [s[1] / w, s[2] / w, s[3] / w],
        brightness: s[4] / w,
        chroma: s[5] / w,
    })
}

#[inline]
fn log_color(r: f32, g: f32, b: f32) -> ([f32; 3], f32, [f32; 3]) {
    let l = [fast_log2(r + EPS), fast_log2(g + EPS), fast_log2(b + EPS)];
    let mu = (l[0] + l[1] + l[2]) * (1.0 / 3.0);
    (l, mu, [l[0] - mu, l[1] - mu, l[2] - mu])
}

/// Binary square dilation of a `gw x gh` grid by `r` cells (separable box counts).
fn dilate(src: &[bool], gw: usize, gh: usize, r: usize) -> Vec<bool> {
    let mut tmp = vec![false; gw * gh];
    let mut prefix = vec![0u32; gw.max(gh) + 1];
    for y in 0..gh {
        for x in 0..gw {
            prefix[x + 1] = prefix[x] + src[y * gw + x] as u32;
        }
        for x in 0..gw {
            let lo = x.saturating_sub(r);
            let hi = (x + r + 1).min(gw);
            tmp[y * gw + x] = prefix[hi] > prefix[lo];
        }
    }
    let mut out = vec![false; gw * gh];
    for x in 0..gw {
        for y in 0..gh {
            prefix[y + 1] = prefix[y] + tmp[y * gw + x] as u32;
        }
        for y in 0..gh {
            let lo = y.saturating_sub(r);
            let hi = (y + r + 1).min(gh);
            out[y * gw + x] = prefix[hi] > prefix[lo];
        }
    }
    out
}

/// The background ring around an insert, on a grid of [`RING_CELL`] cells.
#[derive(Debug, Clone, PartialEq)]
pub struct Ring {
    /// The pixel area the grid covers (the insert plus the ring).
    pub area: Rect,
    /// Grid width in cells.
    pub grid_width: usize,
    /// Grid height in cells.
    pub grid_height: usize,
    /// Ring cells, row-major.
    pub cells: Vec<bool>,
    /// Bounding box of the insert (mask above 0).
    pub insert: Rect,
}

impl Ring {
    /// True when pixel `(x, y)` (inside `area`) lies in a ring cell.
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> bool {
        let cx = (x - self.area.x0) / RING_CELL;
        let cy = (y - self.area.y0) / RING_CELL;
        self.cells[cy * self.grid_width + cx]
    }
}

/// The bounding box of an insert mask (pixels with mask > 0).
pub fn insert_rect(mask: &[f32], width: usize, height: usize) -> Option<Rect> {
    bbox_above(mask, width, height, 0.0).map(|(r, _)| r)
}

/// Builds the ring around the insert mask whose bounding box is `insert`
/// (see [`insert_rect`]); `None` when no cell of the mask exceeds 0.02.
pub fn ring(mask: &[f32], insert: Rect, width: usize, height: usize) -> Option<Ring> {
    let size = insert.width().max(insert.height());
    let ring_px = (size / 4).clamp(8, 128);
    let r_cells = ring_px.div_ceil(RING_CELL);
    let area = insert.expand((r_cells + 1) * RING_CELL, width, height);
    let gw = area.width().div_ceil(RING_CELL);
    let gh = area.height().div_ceil(RING_CELL);
    let inside: Vec<bool> = (0..gh)
        .into_par_iter()
        .flat_map_iter(|cy| {
            let y0 = area.y0 + cy * RING_CELL;
            let y1 = (y0 + RING_CELL).min(area.y1);
            (0..gw).map(move |cx| {
                let x0 = area.x0 + cx * RING_CELL;
                let x1 = (x0 + RING_CELL).min(area.x1);
                (y0..y1).any(|y| {
                    mask[y * width + x0..y * width + x1]
                        .iter()
                        .any(|&m| m > 0.02)
                })
            })
        })
        .collect();
    let inner = dilate(&inside, gw, gh, 1);
    let outer = dilate(&inside, gw, gh, r_cells);
    if !inside.iter().any(|&v| v) {
        return None;
    }
    let cells = outer.iter().zip(&inner).map(|(&o, &i)| o && !i).collect();
    Some(Ring {
        area,
        grid_width: gw,
        grid_height: gh,
        cells,
        insert,
    })
}

/// Statistics of the insert and of its ring in a 4-plane image, sampling
/// every other pixel in both directions (sparser for large inserts, about
/// 32k samples at most). `coverage` (the renderer's, before
/// hole filling) down-weights filled pixels; `depth` excludes empty pixels
/// from the ring. `None` when either region has too few samples.
pub fn measure(
    img: &Image,
    mask: &[f32],
    ring: &Ring,
    coverage: Option<&[f32]>,
    depth: Option<&[f32]>,
) -> Option<(Stats, Stats)> {
    measure_among(img, mask, None, ring, coverage, depth)
}

/// [`measure`] of one of several inserted objects: `inserts`, the whole
/// insert mask, keeps the other objects out of its ring (a ring pixel
/// weighs `1 - max(mask, inserts)`). With `inserts` equal to `mask`, or
/// `None`, the same as [`measure`].
pub fn measure_among(
    img: &Image,
    mask: &[f32],
    inserts: Option<&[f32]>,
    ring: &Ring,
    coverage: Option<&[f32]>,
    depth: Option<&[f32]>,
) -> Option<(Stats, Stats)> {
    let w = img.width;
    let area = ring.area;
    let planes = [img.plane(0), img.plane(1), img.plane(2), img.plane(3)];
    // Every `step`-th pixel in both directions: at least every other one,
    // at most about 32k samples.
    let step = ((area.width() * area.height()) as f64 / 32768.0)
        .sqrt()
        .ceil()
        .clamp(2.0, 16.0) as usize;
    let rows: Vec<usize> = (area.y0..area.y1).step_by(step).collect();
    let partial: Vec<(Sums, Sums)> = rows
        .par_iter()
        .map(|&y| {
            let mut si = [0.0; 6];
            let mut sb = [0.0; 6];
            for x in (area.x0..area.x1).step_by(step) {
                let p = y * w + x;
                let a = planes[3][p];
                if a <= 1e-3 {
                    continue;
                }
                let cov = coverage.map_or(1.0, |c| c[p]);
                let m = mask[p];
                let wi = (2.0 * m - 1.0).clamp(0.0, 1.0) * cov;
                let in_ring = ring.at(x, y) && depth.is_none_or(|d| d[p] < EMPTY_DEPTH);
                let taken = inserts.map_or(m, |a| m.max(a[p]));
                let wb = if in_ring { (1.0 - taken) * cov } else { 0.0 };
                if wi <= 0.0 && wb <= 0.0 {
                    continue;
                }
                let k = 1.0 / a;
                let (l, mu, chi) = log_color(planes[0][p] * k, planes[1][p] * k, planes[2][p] * k);
                let chroma =
                    ((chi[0] * chi[0] + chi[1] * chi[1] + chi[2] * chi[2]) * (1.0 / 3.0)).sqrt();
                if wi > 0.0 {
                    add(&mut si, wi, l, mu, chroma);
                }
                if wb > 0.0 {
                    add(&mut sb, wb, l, mu, chroma);
                }
            }
            (si, sb)
        })
        .collect();
    // Sequential sum in row order: independent of the thread count.
    let mut si = [0.0; 6];
    let mut sb = [0.0; 6];
    for (a, b) in &partial {
        for k in 0..6 {
            si[k] += a[k];
            sb[k] += b[k];
        }
    }
    Some((finish(&si)?, finish(&sb)?))
}

/// The part of a signed difference `d` beyond a dead zone `dead`, with a
/// quadratic knee of width `knee` (continuous with a continuous slope).
pub fn beyond_dead_zone(d: f32, dead: f32, knee: f32) -> f32 {
    let a = d.abs() - dead;
    let e = if a <= 0.0 {
        0.0
    } else if a < knee {
        a * a / (2.0 * knee)
    } else {
        a - 0.5 * knee
    };
    e.copysign(d)
}

/// The filter that corrects the part of the insert's difference to the ring
/// that object albedo does not explain (see the module documentation).
pub fn tone_from_stats(insert: &Stats, ring: &Stats) -> Tone {
    // Brightness: the smaller of the mean and brightest-channel differences
    // (0 when they disagree in sign).
    let top = |s: &Stats| s.log_mean.iter().copied().fold(f64::MIN, f64::max);
    let d_mean = (ring.brightness - insert.brightness) as f32;
    let d_top = (top(ring) - top(insert)) as f32;
    let d = if d_mean * d_top <= 0.0 {
        0.0
    } else {
        d_mean.abs().min(d_top.abs()).copysign(d_mean)
    };
    let exposure = (EXPOSURE_STRENGTH * beyond_dead_zone(d, EXPOSURE_DEAD_ZONE, EXPOSURE_KNEE))
        .clamp(-MAX_EXPOSURE, MAX_EXPOSURE);

    // White balance: the mean log-chroma difference, shrunk as a vector.
    let chroma = |s: &Stats, k: usize| (s.log_mean[k] - s.brightness) as f32;
    let diff: [f32; 3] = std::array::from_fn(|k| chroma(ring, k) - chroma(insert, k));
    let rms = ((diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2]) / 3.0).sqrt();
    let plausible = ((MAX_CAST + 0.4 - rms) / 0.4).clamp(0.0, 1.0);
    let scale = if rms > 0.0 {
        WHITE_BALANCE_STRENGTH * plausible * beyond_dead_zone(rms, CHROMA_DEAD_ZONE, CHROMA_KNEE)
            / rms
    } else {
        0.0
    };
    let mut wb = diff.map(|v| (scale * v).clamp(-MAX_WHITE_BALANCE, MAX_WHITE_BALANCE));
    let mean = (wb[0] + wb[1] + wb[2]) / 3.0;
    wb.iter_mut().for_each(|v| *v -= mean);

    // Saturation: never raised; lowered only when the insert is far more
    // saturated than its ring and its chroma points away from the ring's.
    let ci: [f32; 3] = std::array::from_fn(|k| chroma(insert, k));
    let cr: [f32; 3] = std::array::from_fn(|k| chroma(ring, k));
    let dot = ci[0] * cr[0] + ci[1] * cr[1] + ci[2] * cr[2];
    let excess = (insert.chroma - ring.chroma) as f32 - SATURATION_EVIDENCE;
    let saturation = if excess > 0.0 && dot < 0.0 && insert.chroma > 1e-3 {
        let target = (ring.chroma as f32 + SATURATION_EVIDENCE) / insert.chroma as f32;
        target
            .powf(SATURATION_STRENGTH)
            .clamp(1.0 / MAX_FACTOR, 1.0)
    } else {
        1.0
    };

    Tone {
        exposure,
        white_balance: wb,
        saturation,
    }
}

/// One inserted object: the insert pixels of one of the host's object ids
/// ([`objects`]), or a connected part of the insert mask (cells of
/// [`RING_CELL`] pixels with mask above 0.02, 8-connected).
#[derive(Debug, Clone, PartialEq)]
pub struct Component {
    /// Bounding box of its pixels.
    pub rect: Rect,
    /// Centre of its cells, pixels.
    pub centroid: [f32; 2],
    /// Its mask, frame-sized: the insert mask on its cells, 0 elsewhere
    /// (only the cells around `rect` are ever written, the rest of the
    /// zeroed allocation is never touched).
    pub mask: Vec<f32>,
    /// The host's object id; 0 for a connected part of the mask.
    pub id: f32,
}

/// The inserted objects of `mask` (bounding box `insert`), in the order of
/// their centroid's x then y. A single object is not split off: one
/// component with an empty `mask` stands for the whole insert mask.
pub fn components(mask: &[f32], insert: Rect, width: usize, height: usize) -> Vec<Component> {
    if insert.is_empty() {
        return Vec::new();
    }
    let gw = insert.width().div_ceil(RING_CELL);
    let gh = insert.height().div_ceil(RING_CELL);
    let cell_rect = |cx: usize, cy: usize| Rect {
        x0: insert.x0 + cx * RING_CELL,
        y0: insert.y0 + cy * RING_CELL,
        x1: (insert.x0 + (cx + 1) * RING_CELL).min(insert.x1),
        y1: (insert.y0 + (cy + 1) * RING_CELL).min(insert.y1),
    };
    let on: Vec<bool> = (0..gh)
        .into_par_iter()
        .flat_map_iter(|cy| {
            (0..gw).map(move |cx| {
                let r = cell_rect(cx, cy);
                (r.y0..r.y1).any(|y| {
                    mask[y * width + r.x0..y * width + r.x1]
                        .iter()
                        .any(|&m| m > 0.02)
                })
            })
        })
        .collect();
    let mut label = vec![u32::MAX; gw * gh];
    let mut parts: Vec<Vec<usize>> = Vec::new();
    for start in 0..gw * gh {
        if !on[start] || label[start] != u32::MAX {
            continue;
        }
        let id = parts.len() as u32;
        let mut cells = vec![start];
        label[start] = id;
        let mut k = 0;
        while k < cells.len() {
            let c = cells[k];
            k += 1;
            let (cx, cy) = ((c % gw) as isize, (c / gw) as isize);
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (nx, ny) = (cx + dx, cy + dy);
                    if nx < 0 || ny < 0 || nx >= gw as isize || ny >= gh as isize {
                        continue;
                    }
                    let n = ny as usize * gw + nx as usize;
                    if on[n] && label[n] == u32::MAX {
                        label[n] = id;
                        cells.push(n);
                    }
                }
            }
        }
        parts.push(cells);
    }
    let centroid = |cells: &[usize]| {
        let (sx, sy) = cells.iter().fold((0.0f64, 0.0f64), |(sx, sy), &c| {
            let r = cell_rect(c % gw, c / gw);
            (
                sx + (r.x0 + r.x1) as f64 / 2.0,
                sy + (r.y0 + r.y1) as f64 / 2.0,
            )
        });
        let n = cells.len().max(1) as f64;
        [(sx / n) as f32, (sy / n) as f32]
    };
    if parts.len() <= 1 {
        return parts
            .iter()
            .map(|cells| Component {
                rect: insert,
                centroid: centroid(cells),
                mask: Vec::new(),
                id: 0.0,
            })
            .collect();
    }
    let mut out: Vec<Component> = parts
        .iter()
        .map(|cells| {
            let mut m = vec![0.0f32; width * height];
            let mut rect = Rect::default();
            for &c in cells {
                let r = cell_rect(c % gw, c / gw);
                for y in r.y0..r.y1 {
                    let s = y * width + r.x0..y * width + r.x1;
                    m[s.clone()].copy_from_slice(&mask[s]);
                }
                rect = rect.union(&r);
            }
            Component {
                rect,
                centroid: centroid(cells),
                mask: m,
                id: 0.0,
            }
        })
        .collect();
    out.sort_by(|a, b| {
        a.centroid
            .partial_cmp(&b.centroid)
            .unwrap_or(std::cmp::Ordering::Equal)
    });
    out
}

/// The inserted objects of `mask` (bounding box `insert`) told apart by the
/// host's object ids `ids` (a frame-sized plane, 0 where a pixel has none):
/// the insert pixels (mask above 0) of each distinct id above 0 are one
/// object, in increasing order of id, whether or not they touch another
/// object's or are split apart; the insert pixels without an id follow as
/// [`components`] groups them. Without `ids`, or when no insert pixel has
/// one, exactly [`components`]. A single object is not split off: one
/// component with an empty `mask` stands for the whole insert mask.
pub fn objects(
    mask: &[f32],
    ids: Option<&[f32]>,
    insert: Rect,
    width: usize,
    height: usize,
) -> Vec<Component> {
    let Some(ids) = ids.filter(|_| !insert.is_empty()) else {
        return components(mask, insert, width, height);
    };
    // Per id (its bits: ids are positive, so they order as the values):
    // bounding box, summed pixel centres and count.
    // Walked in runs of one id along each row (an id's pixels lie in
    // runs, so the map is touched once per run, not per pixel).
    let mut found: std::collections::BTreeMap<u32, (Rect, [f64; 2], usize)> =
        std::collections::BTreeMap::new();
    let mut rest: Option<Rect> = None;
    // The run `xs..xe` of row `y` with id bits `key` (`None`: no id).
    let mut flush = |key: Option<u32>, xs: usize, xe: usize, y: usize| {
        let run = Rect {
            x0: xs,
            y0: y,
            x1: xe,
            y1: y + 1,
        };
        match key {
            Some(bits) => {
                let n = xe - xs;
                let e = found.entry(bits).or_insert((run, [0.0; 2], 0));
                e.0 = e.0.union(&run);
                // The pixel centres x + 0.5 of the run, summed.
                e.1[0] += n as f64 * (xs + xe) as f64 / 2.0;
                e.1[1] += n as f64 * (y as f64 + 0.5);
                e.2 += n;
            }
            None => rest = Some(rest.map_or(run, |r| r.union(&run))),
        }
    };
    for y in insert.y0..insert.y1 {
        let row = y * width;
        let mut run: Option<(Option<u32>, usize)> = None;
        for x in insert.x0..insert.x1 {
            let p = row + x;
            let key = (mask[p] > 0.0).then(|| (ids[p] > 0.0).then(|| ids[p].to_bits()));
            match (run, key) {
                (Some((k, _)), Some(now)) if k == now => {}
                _ => {
                    if let Some((k, xs)) = run {
                        flush(k, xs, x, y);
                    }
                    run = key.map(|k| (k, x));
                }
            }
        }
        if let Some((k, xs)) = run {
            flush(k, xs, insert.x1, y);
        }
    }
    if found.is_empty() {
        return components(mask, insert, width, height);
    }
    let centroid = |s: [f64; 2], n: usize| [(s[0] / n as f64) as f32, (s[1] / n as f64) as f32];
    if found.len() == 1 && rest.is_none() {
        let (&bits, &(_, sum, n)) = found.iter().next().expect("one id");
        return vec![Component {
            rect: insert,
            centroid: centroid(sum, n),
            mask: Vec::new(),
            id: f32::from_bits(bits),
        }];
    }
    // The part of `mask` inside `rect` where `keep(id)` holds, frame-sized.
    let part = |rect: Rect, keep: &dyn Fn(f32) -> bool| {
        let mut m = vec![0.0f32; width * height];
        for y in rect.y0..rect.y1 {
            let s = y * width + rect.x0..y * width + rect.x1;
            for ((o, &v), &id) in m[s.clone()].iter_mut().zip(&mask[s.clone()]).zip(&ids[s]) {
                *o = if keep(id) { v } else { 0.0 };
            }
        }
        m
    };
    let mut out: Vec<Component> = found
        .iter()
        .map(|(&bits, &(rect, sum, n))| {
            let id = f32::from_bits(bits);
            Component {
                rect,
                centroid: centroid(sum, n),
                mask: part(rect, &|v| v == id),
                id,
            }
        })
        .collect();
    if let Some(rect) = rest {
        let without = part(rect, &|v| v <= 0.0);
        let parts = components(&without, rect, width, height);
        let single = parts.len() == 1;
        for mut c in parts {
            if single {
                c.mask = without.clone();
                c.rect = rect;
            }
            out.push(c);
        }
    }
    out
}

/// The harmonization filters carried from frame to frame, one per inserted
/// object, each with the centroid it was last seen at: a flat vector of
/// `[cx, cy, Tone::to_vec()...]` per object.
pub fn tracks_to_vec(tracks: &[([f32; 2], Tone)]) -> Vec<f32> {
    tracks
        .iter()
        .flat_map(|(c, t)| c.iter().copied().chain(t.to_vec()))
        .collect()
}

/// Reads [`tracks_to_vec`]'s layout; `None` for a malformed vector.
pub fn tracks_from_slice(v: &[f32]) -> Option<Vec<([f32; 2], Tone)>> {
    const N: usize = 2 + Tone::LEN;
    if !v.len().is_multiple_of(N) {
        return None;
    }
    v.chunks(N)
        .map(|c| {
            let t = Tone::from_slice(&c[2..])?;
            (c[0].is_finite() && c[1].is_finite()).then_some(([c[0], c[1]], t))
        })
        .collect()
}

/// For each of `centroids` (this frame's objects), the index in `previous`
/// of the track it continues: the nearest unclaimed one within
/// `max_distance` pixels, nearest pairs first.
pub fn match_tracks(
    centroids: &[[f32; 2]],
    previous: &[[f32; 2]],
    max_distance: f32,
) -> Vec<Option<usize>> {
    let mut pairs: Vec<(f32, usize, usize)> = Vec::new();
    for (i, c) in centroids.iter().enumerate() {
        for (j, p) in previous.iter().enumerate() {
            let d = ((c[0] - p[0]).powi(2) + (c[1] - p[1]).powi(2)).sqrt();
            if d <= max_distance {
                pairs.push((d, i, j));
            }
        }
    }
    pairs.sort_by(|a, b| a.partial_cmp(b).unwrap_or(std::cmp::Ordering::Equal));
    let mut out = vec![None; centroids.len()];
    let mut used = vec![false; previous.len()];
    for (_, i, j) in pairs {
        if out[i].is_none() && !used[j] {
            out[i] = Some(j);
            used[j] = true;
        }
    }
    out
}

/// For each of this frame's objects (`current`: id and centroid, see
/// [`Component`]), the index in `previous` (the tracks' ids and
/// centroids) of the track it continues: an object with an id (above 0)
/// the track of the same id, wherever it moved; one without the nearest
/// unclaimed track without an id within `max_distance` pixels
/// ([`match_tracks`]).
pub fn match_objects(
    current: &[(f32, [f32; 2])],
    previous: &[(f32, [f32; 2])],
    max_distance: f32,
) -> Vec<Option<usize>> {
    let mut out: Vec<Option<usize>> = current
        .iter()
        .map(|(id, _)| {
            (*id > 0.0)
                .then(|| previous.iter().position(|(p, _)| p == id))
                .flatten()
        })
        .collect();
    let free =
        |v: &[(f32, [f32; 2])]| -> Vec<usize> { (0..v.len()).filter(|&i| v[i].0 <= 0.0).collect() };
    let (cur, prev) = (free(current), free(previous));
    let centroids = |v: &[(f32, [f32; 2])], at: &[usize]| -> Vec<[f32; 2]> {
        at.iter().map(|&i| v[i].1).collect()
    };
    let matched = match_tracks(
        &centroids(current, &cur),
        &centroids(previous, &prev),
        max_distance,
    );
    for (&i, m) in cur.iter().zip(matched) {
        out[i] = m.map(|j| prev[j]);
    }
    out
}

/// Ring, statistics and filter in one call; `None` when there is no insert
/// or too little of it or of its surroundings is visible.
pub fn estimate(
    img: &Image,
    mask: &[f32],
    insert: Rect,
    coverage: Option<&[f32]>,
    depth: Option<&[f32]>,
) -> Option<Tone> {
    estimate_among(img, mask, None, insert, coverage, depth)
}

/// [`estimate`] of one of several inserted objects (`inserts`: the whole
/// insert mask, kept out of its ring, see [`measure_among`]).
pub fn estimate_among(
    img: &Image,
    mask: &[f32],
    inserts: Option<&[f32]>,
    insert: Rect,
    coverage: Option<&[f32]>,
    depth: Option<&[f32]>,
) -> Option<Tone> {
    let ring = ring(mask, insert, img.width, img.height)?;
    let (si, sb) = measure_among(img, mask, inserts, &ring, coverage, depth)?;
    Some(tone_from_stats(&si, &sb))
}

/// Applies `tone` to the insert in place, weighted by the mask: per pixel
/// `l'_k = mu + exposure + saturation * chi_k + wb_k`, then
/// `c'_k = c_k * 2^(l'_k - l_k)`
/// (so black stays black). Only pixels inside `insert` (the mask's bounding
/// box, [`insert_rect`]) are touched.
pub fn apply(img: &mut Image, mask: &[f32], insert: Rect, tone: &Tone) {
    let w = img.width;
    let rect = insert;
    if tone.is_identity() || rect.is_empty() {
        return;
    }
    let t = *tone;
    par_bands_mut(img, rect.y0, rect.y1).for_each(|(y0, [r, g, b, a])| {
        let rows = a.len() / w;
        for dy in 0..rows {
            let span = dy * w + rect.x0..dy * w + rect.x1;
            let mrow = &mask[(y0 + dy) * w + rect.x0..(y0 + dy) * w + rect.x1];
            let (rr, gr, br) = (
                &mut r[span.clone()],
                &mut g[span.clone()],
                &mut b[span.clone()],
            );
            let ar = &a[span];
            // Branch-free so it vectorizes; m = 0 leaves a pixel exactly as it was.
            for x in 0..mrow.len() {
                let m = mrow[x];
                let k = 1.0 / fmax(ar[x], 1e-6);
                let (l, mu, chi) = log_color(rr[x] * k, gr[x] * k, br[x] * k);
                let mu2 = mu + t.exposure;
                let gain = |ch: usize| {
                    let l2 = mu2 + t.saturation * chi[ch] + t.white_balance[ch];
                    1.0 + m * (fast_exp2(l2 - l[ch]) - 1.0)
                };
                let (g0, g1, g2) = (gain(0), gain(1), gain(2));
                rr[x] *= g0;
                gr[x] *= g1;
                br[x] *= g2;
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A textured background and a square insert; `insert_color` maps the
    /// background texture value at a pixel to the insert's color.
    fn scene(w: usize, h: usize, insert_color: impl Fn(f32) -> [f32; 3]) -> (Image, Vec<f32>) {
        let n = w * h;
        let mut img = Image::filled(w, h, 4, 1.0);
        let mut mask = vec![0.0; n];
        for y in 0..h {
            for x in 0..w {
                let p = y * w + x;
                let t = 0.5 + 0.4 * ((x as f32 * 0.21).sin() * (y as f32 * 0.17).cos());
                let inside = (40..90).contains(&x) && (30..80).contains(&y);
                let c = if inside {
                    insert_color(t)
                } else {
                    [0.6 * t, 0.5 * t, 0.4 * t]
                };
                for (k, v) in c.iter().enumerate() {
                    img.data[k * n + p] = *v;
                }
                mask[p] = if inside { 1.0 } else { 0.0 };
            }
        }
        (img, mask)
    }

    #[test]
    fn ring_surrounds_the_insert_without_touching_it() {
        let (_, mask) = scene(160, 120, |t| [t; 3]);
        let ring = ring(&mask, insert_rect(&mask, 160, 120).unwrap(), 160, 120).unwrap();
        assert_eq!(
            ring.insert,
            Rect {
                x0: 40,
                y0: 30,
                x1: 90,
                y1: 80
            }
        );
        for y in ring.area.y0..ring.area.y1 {
            for x in ring.area.x0..ring.area.x1 {
                if ring.at(x, y) {
                    assert_eq!(mask[y * 160 + x], 0.0, "ring on the insert at ({x},{y})");
                }
            }
        }
        // Pixels 8..12 left of the insert are ring; the insert's direct
        // neighbors (one cell) are not.
        assert!(ring.at(30, 50) && !ring.at(39, 50));
    }

    #[test]
    fn a_tone_shifted_insert_moves_toward_the_background_grade() {
        // The insert's true colors follow the background's grade; the render
        // made it 8x (3 stops) too bright, 4x too blue, and flatter: far
        // beyond what the object's albedo could explain.
        let truth = |t: f32| [0.6 * t, 0.5 * t, 0.4 * t];
        let shifted = |t: f32| {
            let c = truth(0.5 + 0.3 * (t - 0.5));
            [8.0 * c[0], 8.0 * c[1], 8.0 * 4.0 * c[2]]
        };
        let (mut img, mask) = scene(160, 120, shifted);
        let (want, _) = scene(160, 120, truth);
        let err = |img: &Image| -> f64 {
            let mut e = 0.0;
            for (i, &m) in mask.iter().enumerate() {
                if m > 0.0 {
                    for c in 0..3 {
                        let n = 160 * 120;
                        e += ((img.data[c * n + i] + 1e-3).log2()
                            - (want.data[c * n + i] + 1e-3).log2())
                        .abs() as f64;
                    }
                }
            }
            e
        };
        let before = err(&img);
        let rect = insert_rect(&mask, 160, 120).unwrap();
        let tone = estimate(&img, &mask, rect, None, None).unwrap();
        assert!(tone.exposure < -0.5, "{tone:?}");
        assert!(tone.white_balance[2] < -0.1, "{tone:?}");
        assert_eq!(tone.saturation, 1.0, "{tone:?}");
        apply(&mut img, &mask, rect, &tone);
        let after = err(&img);
        // Conservative: only the excess beyond the dead zones is corrected.
        assert!(after < 0.85 * before, "log error {before} -> {after}");
        // The background is untouched.
        assert_eq!(img.at(5, 5, 0), want.at(5, 5, 0));
    }

    #[test]
    fn a_matching_insert_stays_nearly_unchanged() {
        let (mut img, mask) = scene(160, 120, |t| [0.6 * t, 0.5 * t, 0.4 * t]);
        let orig = img.clone();
        let rect = insert_rect(&mask, 160, 120).unwrap();
        let tone = estimate(&img, &mask, rect, None, None).unwrap();
        assert!(
            tone.exposure.abs() < 0.1 && tone.white_balance.iter().all(|v| v.abs() < 0.05),
            "{tone:?}"
        );
        apply(&mut img, &mask, rect, &tone);
        for (a, b) in img.data.iter().zip(&orig.data) {
            assert!((a - b).abs() <= 0.1 * b.abs() + 1e-4);
        }
    }

    #[test]
    fn a_correctly_lit_saturated_insert_is_left_alone() {
        // Regression: harmonization pulled a correctly lit yellow (or red)
        // object toward its grey surroundings. Same lighting as the floor,
        // only the albedo differs: the filter must be the identity.
        for albedo in [[1.3, 1.0, 0.08], [1.2, 0.12, 0.1]] {
            let (img, mask) = scene(160, 120, |t| albedo.map(|a| a * 0.5 * t));
            let rect = insert_rect(&mask, 160, 120).unwrap();
            let tone = estimate(&img, &mask, rect, None, None).unwrap();
            assert!(tone.is_identity(), "albedo {albedo:?}: {tone:?}");
        }
    }

    #[test]
    fn dead_zone_is_continuous_and_signed() {
        assert_eq!(beyond_dead_zone(1.0, 1.5, 1.0), 0.0);
        assert_eq!(beyond_dead_zone(-1.5, 1.5, 1.0), 0.0);
        assert!((beyond_dead_zone(2.0, 1.5, 1.0) - 0.125).abs() < 1e-6);
        assert!((beyond_dead_zone(-2.5, 1.5, 1.0) + 0.5).abs() < 1e-6);
        assert!((beyond_dead_zone(3.5, 1.5, 1.0) - 1.5).abs() < 1e-6);
    }

    #[test]
    fn tone_round_trips_and_interpolates() {
        let t = Tone {
            exposure: 1.0,
            white_balance: [0.1, 0.0, -0.1],
            saturation: 0.5,
        };
        assert_eq!(Tone::from_slice(&t.to_vec()), Some(t));
        assert_eq!(Tone::from_slice(&[1.0; 3]), None);
        let half = Tone::IDENTITY.toward(&t, 0.5);
        assert!((half.exposure - 0.5).abs() < 1e-6);
        assert!((half.saturation - 0.5f32.sqrt()).abs() < 1e-5);
        assert!(Tone::IDENTITY.is_identity() && !t.is_identity());
    }

    #[test]
    fn empty_mask_means_no_estimate() {
        let img = Image::filled(32, 32, 4, 0.5);
        assert!(insert_rect(&[0.0; 32 * 32], 32, 32).is_none());
        let faint = vec![0.01; 32 * 32];
        assert!(estimate(&img, &faint, Rect::full(32, 32), None, None).is_none());
    }

    #[test]
    fn objects_are_found_apart_and_followed_by_where_they_are() {
        let (w, h) = (120, 80);
        let mut mask = vec![0.0; w * h];
        for y in 20..50 {
            for x in 70..100 {
                mask[y * w + x] = 1.0;
            }
            for x in 10..30 {
                mask[y * w + x] = 0.5;
            }
        }
        let rect = insert_rect(&mask, w, h).unwrap();
        let parts = components(&mask, rect, w, h);
        assert_eq!(parts.len(), 2);
        // Ordered by x: the left object first, each mask its own pixels only.
        assert_eq!((parts[0].rect.x0, parts[0].rect.x1), (10, 30));
        assert_eq!((parts[1].rect.x0, parts[1].rect.x1), (70, 100));
        assert_eq!(parts[0].mask[25 * w + 15], 0.5);
        assert_eq!(parts[0].mask[25 * w + 80], 0.0);
        assert_eq!(parts[1].mask[25 * w + 80], 1.0);
        // One object: the whole mask stands for it (no copy).
        let one: Vec<f32> = mask
            .iter()
            .enumerate()
            .map(|(i, &m)| if i % w >= 60 { m } else { 0.0 })
            .collect();
        let parts = components(&one, insert_rect(&one, w, h).unwrap(), w, h);
        assert_eq!(parts.len(), 1);
        assert!(parts[0].mask.is_empty());
        // Tracks follow the nearest centroid; a far one starts anew.
        let m = match_tracks(
            &[[20.0, 30.0], [85.0, 35.0], [200.0, 0.0]],
            &[[84.0, 34.0], [21.0, 31.0]],
            20.0,
        );
        assert_eq!(m, vec![Some(1), Some(0), None]);
        let t = vec![(
            [1.0, 2.0],
            Tone {
                exposure: 0.5,
                ..Tone::IDENTITY
            },
        )];
        assert_eq!(tracks_from_slice(&tracks_to_vec(&t)), Some(t));
        assert_eq!(tracks_from_slice(&[1.0, 2.0, 3.0]), None);
    }

    #[test]
    fn objects_are_told_apart_by_their_ids() {
        let (w, h) = (120, 80);
        let mut mask = vec![0.0; w * h];
        let mut ids = vec![0.0; w * h];
        for y in 20..50 {
            // Touching: id 4 at 10..40, id 9 at 40..60; id 4 again at
            // 80..90 (the same object seen on both sides of an occluder);
            // a part without an id at 100..110.
            for x in (10..60).chain(80..90).chain(100..110) {
                mask[y * w + x] = 1.0;
                ids[y * w + x] = match x {
                    40..60 => 9.0,
                    100.. => 0.0,
                    _ => 4.0,
                };
            }
        }
        let rect = insert_rect(&mask, w, h).unwrap();
        // Without ids, or ids that name no insert pixel: the connected parts.
        let parts = components(&mask, rect, w, h);
        assert_eq!(parts.len(), 3);
        assert_eq!(objects(&mask, None, rect, w, h), parts);
        assert_eq!(objects(&mask, Some(&vec![0.0; w * h]), rect, w, h), parts);
        let found = objects(&mask, Some(&ids), rect, w, h);
        let got: Vec<(f32, usize, usize)> =
            found.iter().map(|c| (c.id, c.rect.x0, c.rect.x1)).collect();
        assert_eq!(got, vec![(4.0, 10, 90), (9.0, 40, 60), (0.0, 100, 110)]);
        // Centroids of the pixel centres: id 4 has 30 columns at 10..40
        // and 10 at 80..90.
        assert_eq!(found[1].centroid, [50.0, 35.0]);
        assert_eq!(
            found[0].centroid,
            [(30.0 * 25.0 + 10.0 * 85.0) / 40.0, 35.0]
        );
        assert_eq!(found[0].mask[30 * w + 85], 1.0);
        assert_eq!(found[0].mask[30 * w + 45], 0.0);
        assert_eq!(found[1].mask[30 * w + 45], 1.0);
        assert_eq!(found[2].mask[30 * w + 105], 1.0);
        assert_eq!(found[2].mask[30 * w + 15], 0.0);
        // One id for the whole insert: the whole mask stands for it.
        let one = objects(&mask, Some(&vec![5.0; w * h]), rect, w, h);
        assert_eq!(one.len(), 1);
        assert!(one[0].mask.is_empty() && one[0].id == 5.0);
        // Objects with ids follow their ids wherever they moved; those
        // without, the nearest track without an id.
        let m = match_objects(
            &[
                (9.0, [20.0, 30.0]),
                (4.0, [85.0, 35.0]),
                (0.0, [100.0, 30.0]),
            ],
            &[
                (4.0, [20.0, 30.0]),
                (0.0, [95.0, 30.0]),
                (9.0, [85.0, 35.0]),
            ],
            20.0,
        );
        assert_eq!(m, vec![Some(2), Some(0), Some(1)]);
        assert_eq!(
            match_objects(&[(3.0, [0.0, 0.0])], &[(0.0, [0.0, 0.0])], 20.0),
            vec![None]
        );
    }
}
