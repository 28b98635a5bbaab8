//! Contact shadows: a soft darkening of the background just under and
//! around an inserted object's footprint.
//!
//! The footprint is the lowest insert pixel of every column (mask > 0.5) with
//! the insert's depth there. On a grid downsampled by up to 4, the footprint
//! is blurred horizontally (Gaussian, normalized) and vertically with an
//! asymmetric kernel of peak 1 that reaches further below the footprint than
//! above it, giving an occlusion `O` in 0..=1 that is 1 on a long footprint
//! line; the footprint depth is blurred the same way. A background pixel is
//! darkened by `strength * O * exp(-((d - D) / (0.1 D))^2) * (1 - mask)`:
//! only where its depth `d` is close to the footprint depth `D` (the ground
//! the object stands on, not a wall far behind it, not the sky) and never on
//! the insert itself. Sizes scale with the footprint width.
//!
//! With a camera, each footprint column counts by how much of the object
//! stands over it ([`standing`]): the ground at the foot of a wall is
//! occluded, the ground at the rim of a thin plate (a table's base disc)
//! hardly is.

use rayon::prelude::*;

use glam::DVec2;

use super::{fast_exp2, fmax, fmin, par_bands_mut, Rect, EMPTY_DEPTH};
use crate::frame::{Camera, Image};

/// Distance (share of the shadow map's larger edge) at which
/// [`existing_darkening`] looks for unshadowed background.
pub const PRESENCE_REACH: f32 = 0.08;
/// Darkening (stops) from which a shadow starts to count as already
/// rendered ([`missing_share`]); fully from twice this. Sunlit ground under
/// a bright sky darkens by about half a stop in shadow.
pub const PRESENT_FROM: f32 = 0.15;
/// Fewest shadowed/unshadowed pairs [`existing_darkening`] decides on.
pub const PRESENCE_MIN_PAIRS: usize = 16;
/// Coverage from which a pixel counts as rendered for [`existing_darkening`].
pub const COVERED: f32 = 0.95;

/// Rows below a footprint pixel at which the background's depth tells
/// whether the object stands there ([`shadow_map`]).
pub const BELOW_ROWS: usize = 2;
/// The background [`BELOW_ROWS`] under a footprint pixel farther than the
/// insert there by more than this share: the insert floats over it.
pub const FLOAT_TOLERANCE: f32 = 0.02;

/// Height of the object over a footprint column, as a share of the
/// shadow's reach below the footprint (`SIGMA_BELOW` of the footprint size,
/// in world units there), at which the column occludes fully ([`standing`]).
/// The darkening integrated away from the foot of a wall of height `H` is
/// about `H` (`1 - d / sqrt(d^2 + H^2)` over the distance `d`); the map's
/// profile integrates to about 1.25 reaches.
pub const STANDING_HEIGHT: f64 = 1.25;
/// Horizontal distance from the footprint point, in reaches, within which
/// the object's height counts ([`standing`]).
pub const STANDING_REACH: f64 = 2.0;

/// Relative depth difference at which the shadow falls to 1/e.
pub const DEPTH_TOLERANCE: f32 = 0.1;
/// Horizontal blur sigma as a share of the footprint size.
pub const SIGMA_SIDE: f32 = 0.06;
/// Reach below the footprint (sigma) as a share of the footprint size.
pub const SIGMA_BELOW: f32 = 0.08;
/// Reach above the footprint (sigma) as a share of the footprint size.
pub const SIGMA_ABOVE: f32 = 0.025;

/// The shadow of one insert before strength is applied.
#[derive(Debug, Clone, PartialEq)]
pub struct ShadowMap {
    /// Pixel area the map covers.
    pub area: Rect,
    /// Grid cell size in pixels.
    pub cell: usize,
    /// Grid width in cells.
    pub grid_width: usize,
    /// Grid height in cells.
    pub grid_height: usize,
    /// Occlusion per cell in 0..=1.
    pub occlusion: Vec<f32>,
    /// Footprint depth per cell (0 where the occlusion is 0).
    pub depth: Vec<f32>,
}

impl ShadowMap {
    /// Bilinear sample of (occlusion, footprint depth) at pixel `(x, y)` inside `area`.
    #[inline]
    pub fn sample(&self, x: usize, y: usize) -> (f32, f32) {
        let f = self.cell as f32;
        let u = ((x - self.area.x0) as f32 + 0.5) / f - 0.5;
        let v = ((y - self.area.y0) as f32 + 0.5) / f - 0.5;
        let u = u.clamp(0.0, (self.grid_width - 1) as f32);
        let v = v.clamp(0.0, (self.grid_height - 1) as f32);
        let (i0, j0) = (u as usize, v as usize);
        let (i1, j1) = (
            (i0 + 1).min(self.grid_width - 1),
            (j0 + 1).min(self.grid_height - 1),
        );
        let (fx, fy) = (u - i0 as f32, v - j0 as f32);
        let gw = self.grid_width;
        let bil = |p: &[f32]| {
            let top = p[j0 * gw + i0] + fx * (p[j0 * gw + i1] - p[j0 * gw + i0]);
            let bot = p[j1 * gw + i0] + fx * (p[j1 * gw + i1] - p[j1 * gw + i0]);
            top + fy * (bot - top)
        };
        (bil(&self.occlusion), bil(&self.depth))
    }
}

/// Gaussian taps of `sigma` (not normalized), `2 * ceil(3 sigma) + 1` of them.
pub(crate) fn gaussian(sigma: f32) -> Vec<f32> {
    let r = (3.0 * sigma).ceil().max(1.0) as usize;
    (0..=2 * r)
        .map(|i| {
            let d = i as f32 - r as f32;
            (-0.5 * d * d / (sigma * sigma)).exp()
        })
        .collect()
}

/// Builds the shadow map of the insert in `mask` (bounding box `insert`, see
/// [`super::harmonize::insert_rect`]) standing at `depth`. `None` when no
/// pixel of the mask exceeds 0.5 or no footprint pixel has a depth.
pub fn shadow_map(
    mask: &[f32],
    depth: &[f32],
    insert: Rect,
    width: usize,
    height: usize,
    camera: Option<&Camera>,
) -> Option<ShadowMap> {
    // Footprint: lowest insert pixel per column (row-major scan: the last
    // row that has the column inside wins) and the insert's depth there, one
    // pixel inside the edge when possible (edge depth may be background).
    let iw = insert.width();
    let mut lowest = vec![usize::MAX; iw];
    let mut above = vec![usize::MAX; iw];
    for y in insert.y0..insert.y1 {
        let row = &mask[y * width + insert.x0..y * width + insert.x1];
        for (i, &m) in row.iter().enumerate() {
            if m > 0.5 {
                if lowest[i] != usize::MAX && lowest[i] + 1 == y {
                    above[i] = lowest[i];
                } else {
                    above[i] = usize::MAX;
                }
                lowest[i] = y;
            }
        }
    }
    let mut foot: Vec<(usize, usize, f32)> = Vec::new();
    let (mut fx0, mut fx1) = (usize::MAX, 0);
    let (mut ymin, mut ymax) = (usize::MAX, 0);
    for i in 0..iw {
        let yb = lowest[i];
        if yb == usize::MAX {
            continue;
        }
        let x = insert.x0 + i;
        let yi = if above[i] != usize::MAX { above[i] } else { yb };
        let d = depth[yi * width + x];
        // A column whose lowest insert pixel floats (the edge of a table
        // top, the round side of an object): the background just below it
        // on screen lies farther away, on ground the object does not touch
        // there.
        let j = (yb + BELOW_ROWS).min(height - 1) * width + x;
        let floats =
            depth[j] < EMPTY_DEPTH && mask[j] <= 0.5 && depth[j] > d * (1.0 + FLOAT_TOLERANCE);
        if d.is_finite() && d > 0.0 && d < EMPTY_DEPTH && !floats {
            foot.push((x, yb, d));
            fx0 = fx0.min(x);
            fx1 = fx1.max(x + 1);
            ymin = ymin.min(yb);
            ymax = ymax.max(yb);
        }
    }
    if foot.is_empty() {
        return None;
    }
    let size = ((fx1 - fx0) as f32)
        .max(0.25 * insert.height() as f32)
        .max(8.0);
    let (sx, sb, sa) = (SIGMA_SIDE * size, SIGMA_BELOW * size, SIGMA_ABOVE * size);
    let weight = camera
        .and_then(|c| standing(mask, depth, &foot, sb, c, width, height))
        .unwrap_or_else(|| vec![1.0; foot.len()]);
    if weight.iter().all(|&r| r <= 0.0) {
        return None;
    }
    let cell = ((size / 48.0) as usize).clamp(1, 4);
    let area = Rect {
        x0: fx0.saturating_sub((3.0 * sx).ceil() as usize),
        x1: (fx1 + (3.0 * sx).ceil() as usize).min(width),
        y0: ymin.saturating_sub((3.0 * sa).ceil() as usize + 1),
        y1: (ymax + (3.0 * sb).ceil() as usize + 2).min(height),
    };
    let gw = area.width().div_ceil(cell);
    let gh = area.height().div_ceil(cell);
    let mut occ = vec![0.0f32; gw * gh];
    let mut dep = vec![0.0f32; gw * gh];
    let share = 1.0 / cell as f32;
    for (&(x, y, d), &r) in foot.iter().zip(&weight) {
        let g = ((y - area.y0) / cell) * gw + (x - area.x0) / cell;
        occ[g] += share * r;
        dep[g] += share * r * d;
    }
    // Horizontal: normalized Gaussian.
    let kx = gaussian(sx / cell as f32);
    let kx_sum: f32 = kx.iter().sum();
    let kx: Vec<f32> = kx.iter().map(|k| k / kx_sum).collect();
    let rx = kx.len() / 2;
    let mut tmp_o = vec![0.0f32; gw * gh];
    let mut tmp_d = vec![0.0f32; gw * gh];
    for y in 0..gh {
        let (so_row, sd_row) = (&occ[y * gw..(y + 1) * gw], &dep[y * gw..(y + 1) * gw]);
        if so_row.iter().all(|&v| v == 0.0) {
            continue;
        }
        for x in 0..gw {
            let (mut so, mut sd) = (0.0, 0.0);
            let lo = x.saturating_sub(rx);
            let hi = (x + rx + 1).min(gw);
            for xs in lo..hi {
                let k = kx[xs + rx - x];
                so += k * so_row[xs];
                sd += k * sd_row[xs];
            }
            tmp_o[y * gw + x] = so;
            tmp_d[y * gw + x] = sd;
        }
    }
    // Vertical: peak-1 asymmetric kernel; a source `dy` rows above the
    // target (the target below the footprint) uses the long reach.
    let (sbc, sac) = (sb / cell as f32, (sa / cell as f32).max(0.5));
    let rb = (3.0 * sbc).ceil() as isize;
    let ra = (3.0 * sac).ceil() as isize;
    let kv: Vec<f32> = (-ra..=rb)
        .map(|dy| {
            let s = if dy >= 0 { sbc } else { sac };
            (-0.5 * (dy * dy) as f32 / (s * s)).exp()
        })
        .collect();
    occ.fill(0.0);
    dep.fill(0.0);
    for ys in 0..gh {
        let (so_row, sd_row) = (
            &tmp_o[ys * gw..(ys + 1) * gw],
            &tmp_d[ys * gw..(ys + 1) * gw],
        );
        if so_row.iter().all(|&v| v == 0.0) {
            continue;
        }
        for (t, &k) in kv.iter().enumerate() {
            let y = ys as isize + t as isize - ra;
            if y < 0 || y >= gh as isize {
                continue;
            }
            let y = y as usize;
            for x in 0..gw {
                occ[y * gw + x] += k * so_row[x];
                dep[y * gw + x] += k * sd_row[x];
            }
        }
    }
    for (o, d) in occ.iter_mut().zip(dep.iter_mut()) {
        if *o > 1e-6 {
            *d /= *o;
            *o = o.min(1.0);
        } else {
            *o = 0.0;
            *d = 0.0;
        }
    }
    Some(ShadowMap {
        area,
        cell,
        grid_width: gw,
        grid_height: gh,
        occlusion: occ,
        depth: dep,
    })
}

/// How much each footprint column `(x, y, depth)` occludes the ground at its
/// foot, in 0..=1: the object's height over the ground plane within
/// [`STANDING_REACH`] reaches (`reach_px` pixels, in world units at the
/// column) of the footprint point, over [`STANDING_HEIGHT`] reaches. The
/// object's points are its pixels straight above the footprint on screen
/// (mask above 0.5, up to 4 reaches); the ground plane's normal is the mean
/// of the background's normals just below the footprint (camera space,
/// from depth). `None` without enough ground to tell its normal: every
/// column then counts fully.
pub fn standing(
    mask: &[f32],
    depth: &[f32],
    foot: &[(usize, usize, f32)],
    reach_px: f32,
    camera: &Camera,
    width: usize,
    height: usize,
) -> Option<Vec<f32>> {
    let un = camera.unprojector(width, height);
    let ground = |x: usize, y: usize| {
        let i = y * width + x;
        let d = depth[i];
        (mask[i] <= 0.5 && d.is_finite() && d > 0.0 && d < EMPTY_DEPTH)
            .then(|| un.camera_point(DVec2::new(x as f64 + 0.5, y as f64 + 0.5), d as f64))
    };
    // The ground's normal, toward the camera.
    let mut normal = glam::DVec3::ZERO;
    let mut count = 0usize;
    for &(x, y, _) in foot {
        let (yg, step) = (y + BELOW_ROWS + 1, 2);
        if x + step >= width || yg + step >= height {
            continue;
        }
        let (Some(a), Some(b), Some(c)) =
            (ground(x, yg), ground(x + step, yg), ground(x, yg + step))
        else {
            continue;
        };
        let n = (b - a).cross(c - a);
        let len = n.length();
        if len > 0.0 && len.is_finite() {
            let n = n / len;
            normal += if n.dot(-a) < 0.0 { -n } else { n };
            count += 1;
        }
    }
    if count < 3 || normal.length() < 0.5 * count as f64 {
        // Too few samples, or normals that disagree (no plane).
        return None;
    }
    let n = normal.normalize();
    let rows = (4.0 * reach_px).ceil() as usize + 2;
    Some(
        foot.par_iter()
            .map(|&(x, y, d)| {
                let px = |yy: usize| DVec2::new(x as f64 + 0.5, yy as f64 + 0.5);
                let p0 = un.camera_point(px(y), d as f64);
                // World size of one pixel at the footprint.
                let pixel = (un.camera_point(DVec2::new(x as f64 + 1.5, y as f64 + 0.5), d as f64)
                    - p0)
                    .length();
                let reach = reach_px as f64 * pixel;
                let (mut top, near) = (0.0f64, STANDING_REACH * reach);
                for yy in (y.saturating_sub(rows)..y).rev() {
                    let i = yy * width + x;
                    if mask[i] <= 0.5 {
                        break;
                    }
                    let dd = depth[i];
                    if !(dd.is_finite() && dd > 0.0 && dd < EMPTY_DEPTH) {
                        continue;
                    }
                    let v = un.camera_point(px(yy), dd as f64) - p0;
                    let up = v.dot(n);
                    if (v - up * n).length() <= near {
                        top = top.max(up);
                    }
                }
                ((top / (STANDING_HEIGHT * reach)) as f32).clamp(0.0, 1.0)
            })
            .collect(),
    )
}

/// Darkens the background of a 4-plane image under the insert (bounding box
/// `insert`) by `strength` at most. Returns the area touched, `None` when
/// nothing was.
pub fn contact_shadow(
    img: &mut Image,
    mask: &[f32],
    insert: Rect,
    depth: &[f32],
    strength: f32,
) -> Option<Rect> {
    if strength <= 0.0 || insert.is_empty() {
        return None;
    }
    let (w, h) = (img.width, img.height);
    let map = shadow_map(mask, depth, insert, w, h, None)?;
    Some(apply(img, mask, depth, &map, strength))
}

/// Stops by which the background where `map` says "shadow" (occlusion at
/// least 0.5) is already darker than the unshadowed background around it at
/// the same depth (within 10 %): each shadowed cell is compared with the
/// cells [`PRESENCE_REACH`] of the map's size away in eight directions that
/// are unshadowed (occlusion below 0.1), off the insert and not sky, on a
/// 3x3 mean of luminance. With `coverage`, only pixels covered at least
/// [`COVERED`] count, as cells and in the means (a hole's fill is not the
/// render's, and its pixels move the measure with whatever filled them, or
/// darken it where the render left them empty). `None` with fewer than
/// [`PRESENCE_MIN_PAIRS`] such pairs.
pub fn existing_darkening(
    img: &Image,
    mask: &[f32],
    depth: &[f32],
    map: &ShadowMap,
    coverage: Option<&[f32]>,
) -> Option<f32> {
    let (w, h) = (img.width, img.height);
    let (r, g, b) = (img.plane(0), img.plane(1), img.plane(2));
    let counts = |i: usize| coverage.is_none_or(|c| c[i] >= COVERED);
    // The mean over the 3x3 pixels that count (the centre always does).
    let lum = |x: usize, y: usize| -> f32 {
        let (mut s, mut n) = (0.0, 0.0);
        for yy in y.saturating_sub(1)..(y + 2).min(h) {
            for xx in x.saturating_sub(1)..(x + 2).min(w) {
                let i = yy * w + xx;
                if counts(i) {
                    s += super::LUMA[0] * r[i] + super::LUMA[1] * g[i] + super::LUMA[2] * b[i];
                    n += 1.0;
                }
            }
        }
        s / n
    };
    let occ_at = |x: usize, y: usize| -> f32 {
        let a = map.area;
        if x < a.x0 || x >= a.x1 || y < a.y0 || y >= a.y1 {
            0.0
        } else {
            map.sample(x, y).0
        }
    };
    let ground = |i: usize| mask[i] < 0.5 && depth[i] > 0.0 && depth[i] < EMPTY_DEPTH && counts(i);
    let reach = (PRESENCE_REACH * map.area.width().max(map.area.height()) as f32).max(3.0) as isize;
    let (mut sum, mut pairs) = (0.0f64, 0usize);
    for j in 0..map.grid_height {
        for i in 0..map.grid_width {
            if map.occlusion[j * map.grid_width + i] < 0.5 {
                continue;
            }
            let x = (map.area.x0 + i * map.cell + map.cell / 2).min(map.area.x1 - 1);
            let y = (map.area.y0 + j * map.cell + map.cell / 2).min(map.area.y1 - 1);
            let c = y * w + x;
            if !ground(c) {
                continue;
            }
            let lc = lum(x, y);
            for (dx, dy) in [
                (1, 0),
                (-1, 0),
                (0, 1),
                (0, -1),
                (1, 1),
                (1, -1),
                (-1, 1),
                (-1, -1),
            ] {
                let (nx, ny) = (x as isize + dx * reach, y as isize + dy * reach);
                if nx < 0 || ny < 0 || nx >= w as isize || ny >= h as isize {
                    continue;
                }
                let (nx, ny) = (nx as usize, ny as usize);
                let n = ny * w + nx;
                if !ground(n)
                    || occ_at(nx, ny) >= 0.1
                    || (depth[n] - depth[c]).abs() > 0.1 * depth[c]
                {
                    continue;
                }
                let ln = lum(nx, ny);
                if lc > 0.0 && ln > 0.0 {
                    sum += (ln / lc).log2() as f64;
                    pairs += 1;
                }
            }
        }
    }
    (pairs >= PRESENCE_MIN_PAIRS).then(|| (sum / pairs as f64) as f32)
}

/// Share of a shadow still to add when the background there is already
/// `existing` stops darker than around it ([`existing_darkening`]): 1 up to
/// [`PRESENT_FROM`] stops, 0 from twice that, linear between. A render that
/// already has the shadow keeps it as it is; texture alone moves the
/// measure by about a tenth of a stop where no shadow is.
pub fn missing_share(existing: Option<f32>) -> f32 {
    let Some(e) = existing else { return 1.0 };
    (1.0 - (e - PRESENT_FROM) / PRESENT_FROM).clamp(0.0, 1.0)
}

/// Darkens the background of a 4-plane image by `strength` times the
/// occlusion of `map`: only where its depth is near the map's depth there,
/// never on the insert nor the sky. Returns the area touched.
pub fn apply(img: &mut Image, mask: &[f32], depth: &[f32], map: &ShadowMap, strength: f32) -> Rect {
    let w = img.width;
    let area = map.area;
    let gw = map.grid_width;
    let f = map.cell as f32;
    // Horizontal bilinear taps per column of the area.
    let tx: Vec<(usize, usize, f32)> = (area.x0..area.x1)
        .map(|x| {
            let u = (((x - area.x0) as f32 + 0.5) / f - 0.5).clamp(0.0, (gw - 1) as f32);
            let i0 = u as usize;
            (i0, (i0 + 1).min(gw - 1), u - i0 as f32)
        })
        .collect();
    // -(z^2) in log2 units for fast_exp2.
    let k = -std::f32::consts::LOG2_E / (DEPTH_TOLERANCE * DEPTH_TOLERANCE);
    par_bands_mut(img, area.y0, area.y1).for_each(|(y0, [r, g, b, _a])| {
        let rows = r.len() / w;
        let mut orow = vec![0.0f32; gw];
        let mut drow = vec![0.0f32; gw];
        let mut ofull = vec![0.0f32; tx.len()];
        let mut dfull = vec![0.0f32; tx.len()];
        for dy in 0..rows {
            let y = y0 + dy;
            let v =
                (((y - area.y0) as f32 + 0.5) / f - 0.5).clamp(0.0, (map.grid_height - 1) as f32);
            let j0 = v as usize;
            let j1 = (j0 + 1).min(map.grid_height - 1);
            let fy = v - j0 as f32;
            let (o0, o1) = (
                &map.occlusion[j0 * gw..(j0 + 1) * gw],
                &map.occlusion[j1 * gw..(j1 + 1) * gw],
            );
            if o0.iter().chain(o1).all(|&o| o <= 1e-4) {
                continue;
            }
            let (d0, d1) = (
                &map.depth[j0 * gw..(j0 + 1) * gw],
                &map.depth[j1 * gw..(j1 + 1) * gw],
            );
            for i in 0..gw {
                orow[i] = o0[i] + fy * (o1[i] - o0[i]);
                drow[i] = d0[i] + fy * (d1[i] - d0[i]);
            }
            // Occlusion and footprint depth at full resolution (gathers),
            // then a branch-free pass that vectorizes.
            for (t, &(i0, i1, fx)) in tx.iter().enumerate() {
                ofull[t] = orow[i0] + fx * (orow[i1] - orow[i0]);
                dfull[t] = drow[i0] + fx * (drow[i1] - drow[i0]);
            }
            let span = dy * w + area.x0..dy * w + area.x1;
            let full = y * w + area.x0..y * w + area.x1;
            let (mrow, drow_px) = (&mask[full.clone()], &depth[full]);
            let (rr, gr, br) = (&mut r[span.clone()], &mut g[span.clone()], &mut b[span]);
            for x in 0..mrow.len() {
                let (o, fd, m, d) = (ofull[x], dfull[x], mrow[x], drow_px[x]);
                let ok = (o > 1e-4) & (m < 1.0) & (d < EMPTY_DEPTH) & (fd > 0.0);
                // fmin also maps a NaN to the bound.
                let z = fmin((d - fd) / fmax(fd, 1e-6), 1e3);
                let s = strength * o * fast_exp2(k * z * z) * (1.0 - m) * (ok as u32 as f32);
                let keep = 1.0 - s;
                rr[x] *= keep;
                gr[x] *= keep;
                br[x] *= keep;
            }
        }
    });
    area
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A floor (lower part, depth growing upward in the image) under a wall
    /// (upper part, far), with a box standing on the floor.
    fn scene() -> (Image, Vec<f32>, Vec<f32>) {
        let (w, h) = (200, 150);
        let n = w * h;
        let img = Image::filled(w, h, 4, 0.5);
        let horizon = 60;
        let mut depth = vec![0.0; n];
        let mut mask = vec![0.0; n];
        for y in 0..h {
            for x in 0..w {
                let floor = if y >= horizon {
                    2.0 + 400.0 / (y - horizon + 20) as f32
                } else {
                    100.0
                };
                depth[y * w + x] = floor;
            }
        }
        let bottom = 110;
        let d_box = depth[(bottom - 1) * w];
        for y in 70..bottom {
            for x in 80..120 {
                mask[y * w + x] = 1.0;
                depth[y * w + x] = d_box;
            }
        }
        (img, mask, depth)
    }

    #[test]
    fn darkens_below_not_above_nor_far_nor_the_insert() {
        let (mut img, mask, depth) = scene();
        let w = img.width;
        let rect = crate::ops::harmonize::insert_rect(&mask, w, img.height).unwrap();
        contact_shadow(&mut img, &mask, rect, &depth, 0.6).unwrap();
        let v = |x: usize, y: usize| img.at(x, y, 1);
        assert!(
            v(100, 111) < 0.5 * (1.0 - 0.4),
            "just below: {}",
            v(100, 111)
        );
        assert!(v(100, 113) < v(100, 150 - 1) - 0.05);
        assert!(v(100, 113) < 0.5);
        assert_eq!(v(100, 90), 0.5, "the insert itself");
        assert_eq!(v(100, 65), 0.5, "above the insert");
        assert_eq!(v(5, 140), 0.5, "far to the side");
        assert_eq!(v(100, 50), 0.5, "the wall behind");
        // Beside the footprint it fades.
        assert!(v(76, 111) > v(100, 111) && v(76, 111) < 0.5);
        let _ = w;
    }

    #[test]
    fn an_insert_floating_over_the_ground_casts_no_contact_shadow() {
        // The same box nearer the camera, over the floor 20 rows further
        // down the image: lifted off the floor, so the floor just below it
        // on screen lies farther away than the box.
        let (mut img, mut mask, mut depth) = scene();
        let w = img.width;
        let d_lifted = depth[(109 + 20) * w];
        for y in 70..110 {
            for x in 80..120 {
                mask[y * w + x] = 1.0;
                depth[y * w + x] = d_lifted;
            }
        }
        let orig = img.clone();
        let rect = crate::ops::harmonize::insert_rect(&mask, w, img.height).unwrap();
        assert!(shadow_map(&mask, &depth, rect, w, img.height, None).is_none());
        assert!(contact_shadow(&mut img, &mask, rect, &depth, 0.6).is_none());
        assert_eq!(img, orig);
    }

    /// A ground plane (world y = 0) seen from above at an angle, with a box
    /// 1 wide and deep and `height` tall standing on it (the insert),
    /// ray cast with the camera's planar depth.
    fn standing_box(height: f64) -> (Image, Vec<f32>, Vec<f32>, Camera) {
        let (w, h) = (200, 150);
        let (eye, target) = (
            glam::Vec3::new(0.0, 1.6, 4.0),
            glam::Vec3::new(0.0, 0.2, 0.0),
        );
        let camera = Camera::look_at(eye, target, 40f32.to_radians(), w as f32 / h as f32);
        let un = camera.unprojector(w, h);
        let (eye, fwd) = (eye.as_dvec3(), (target - eye).normalize().as_dvec3());
        let (mut depth, mut mask) = (vec![1e10f32; w * h], vec![0.0f32; w * h]);
        for y in 0..h {
            for x in 0..w {
                let dir = un.world_point(DVec2::new(x as f64 + 0.5, y as f64 + 0.5), 1.0) - eye;
                // Slab intersection of the box [-0.5, 0.5] x [0, height] x [-0.5, 0.5].
                let (lo, hi) = (
                    glam::DVec3::new(-0.5, 0.0, -0.5),
                    glam::DVec3::new(0.5, height, 0.5),
                );
                let (t0, t1) = ((lo - eye) / dir, (hi - eye) / dir);
                let (near, far) = (t0.min(t1).max_element(), t0.max(t1).min_element());
                let i = y * w + x;
                if near <= far && near > 0.0 {
                    depth[i] = ((dir * near).dot(fwd)) as f32;
                    mask[i] = 1.0;
                } else if dir.y < 0.0 {
                    depth[i] = ((dir * (-eye.y / dir.y)).dot(fwd)) as f32;
                }
            }
        }
        (Image::filled(w, h, 4, 0.5), mask, depth, camera)
    }

    /// Mean darkening of the ground within 6 rows below the insert.
    fn darkening_below(img: &Image, mask: &[f32]) -> f32 {
        let w = img.width;
        let (mut sum, mut n) = (0.0, 0);
        for x in 0..w {
            if let Some(yb) = (0..img.height).rev().find(|&y| mask[y * w + x] > 0.5) {
                for y in yb + 1..(yb + 7).min(img.height) {
                    sum += 0.5 - img.at(x, y, 1);
                    n += 1;
                }
            }
        }
        sum / n.max(1) as f32
    }

    #[test]
    fn a_thin_plate_occludes_the_ground_at_its_rim_far_less_than_a_box() {
        let shadowed = |height: f64, camera: bool| {
            let (mut img, mask, depth, cam) = standing_box(height);
            let rect = crate::ops::harmonize::insert_rect(&mask, img.width, img.height).unwrap();
            let map = shadow_map(
                &mask,
                &depth,
                rect,
                img.width,
                img.height,
                camera.then_some(&cam),
            )
            .unwrap();
            apply(&mut img, &mask, &depth, &map, 0.6);
            darkening_below(&img, &mask)
        };
        let (box_plain, box_seen) = (shadowed(0.6, false), shadowed(0.6, true));
        let (plate_plain, plate_seen) = (shadowed(0.02, false), shadowed(0.02, true));
        // Without a camera both darken alike; with one, the box as before
        // (its front rises straight from the footprint), the plate about
        // its height over 1.25 reaches (0.02 / 0.1 of the footprint).
        assert!(
            box_plain > 0.05 && plate_plain > 0.05,
            "{box_plain} {plate_plain}"
        );
        assert!(
            box_seen > 0.97 * box_plain,
            "box {box_seen} against {box_plain}"
        );
        assert!(
            plate_seen < 0.35 * plate_plain,
            "plate {plate_seen} against {plate_plain}"
        );
        assert!(plate_seen > 0.0, "a plate still touches the ground");
    }

    #[test]
    fn a_shadow_counts_as_rendered_only_where_the_render_covers_it() {
        // The floor under the box already as dark as a shadow: found when
        // rendered, not when those pixels are a hole's fill.
        let (mut img, mask, depth) = scene();
        let (w, h) = (img.width, img.height);
        let rect = crate::ops::harmonize::insert_rect(&mask, w, h).unwrap();
        let map = shadow_map(&mask, &depth, rect, w, h, None).unwrap();
        assert_eq!(
            existing_darkening(&img, &mask, &depth, &map, None),
            Some(0.0)
        );
        apply(&mut img, &mask, &depth, &map, 0.6);
        let rendered = existing_darkening(&img, &mask, &depth, &map, None).unwrap();
        assert!(rendered > 2.0 * PRESENT_FROM, "{rendered} stops");
        assert_eq!(missing_share(Some(rendered)), 0.0);
        let full = vec![1.0; w * h];
        let covered = existing_darkening(&img, &mask, &depth, &map, Some(&full));
        assert_eq!(covered, Some(rendered));
        // The darkened pixels uncovered (the fill made them): nothing
        // darker is left to compare, so the whole shadow is missing.
        let mut cov = full;
        for (i, c) in cov.iter_mut().enumerate() {
            if img.data[w * h + i] < 0.5 {
                *c = 0.0;
            }
        }
        let filled = existing_darkening(&img, &mask, &depth, &map, Some(&cov));
        assert!(filled.is_none_or(|e| e < PRESENT_FROM), "{filled:?}");
        assert_eq!(missing_share(filled), 1.0);
        // Scattered empty pixels (a reconstruction's holes, premultiplied
        // black) in unshadowed ground: they darken no 3x3 mean.
        let (mut img, _, _) = scene();
        let mut cov = vec![1.0; w * h];
        for i in (0..w * h).step_by(5) {
            cov[i] = 0.0;
            for c in 0..3 {
                img.data[c * w * h + i] = 0.0;
            }
        }
        assert_eq!(
            existing_darkening(&img, &mask, &depth, &map, Some(&cov)),
            Some(0.0)
        );
    }

    #[test]
    fn no_shadow_without_insert_or_depth_or_strength() {
        let (mut img, mask, depth) = scene();
        let orig = img.clone();
        let rect = crate::ops::harmonize::insert_rect(&mask, img.width, img.height).unwrap();
        let empty = vec![0.0; mask.len()];
        assert!(contact_shadow(&mut img, &empty, rect, &depth, 0.6).is_none());
        assert!(contact_shadow(&mut img, &mask, Rect::default(), &depth, 0.6).is_none());
        assert!(contact_shadow(&mut img, &mask, rect, &vec![1e10; depth.len()], 0.6).is_none());
        assert!(contact_shadow(&mut img, &mask, rect, &depth, 0.0).is_none());
        assert_eq!(img, orig);
    }
}
