//! Contact shadows: a soft darkening of the background just under and
//! around an inserted object's footprint.
//!
//! The footprint is the lowest insert pixel of every column (mask > 0.5) with
//! the insert's depth there. On a grid downsampled by up to 4, the footprint
//! is blurred horizontally (Gaussian, normalized) and vertically with an
//! asymmetric kernel of peak 1 that reaches further below the footprint than
//! above it, giving an occlusion `O` in [0,1] that is 1 on a long footprint
//! line; the footprint depth is blurred the same way. A background pixel is
//! darkened by `strength * O * exp(-((d - D) / (0.1 D))^2) * (1 - mask)`:
//! only where its depth `d` is close to the footprint depth `D` (the ground
//! the object stands on, not a wall far behind it, not the sky) and never on
//! the insert itself. Sizes scale with the footprint width.

use rayon::prelude::*;

use super::{bbox_above, par_bands_mut, Rect, EMPTY_DEPTH};
use crate::frame::Image;

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
    /// Occlusion per cell in [0,1].
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

fn gaussian(sigma: f32) -> Vec<f32> {
    let r = (3.0 * sigma).ceil().max(1.0) as usize;
    (0..=2 * r)
        .map(|i| {
            let d = i as f32 - r as f32;
            (-0.5 * d * d / (sigma * sigma)).exp()
        })
        .collect()
}

/// Builds the shadow map of the insert in `mask` standing at `depth`.
/// `None` when the mask is empty or no footprint pixel has a depth.
pub fn shadow_map(mask: &[f32], depth: &[f32], width: usize, height: usize) -> Option<ShadowMap> {
    let (rect, _) = bbox_above(mask, width, height, 0.5)?;
    // Footprint: lowest insert pixel per column and the insert's depth there
    // (one pixel inside the edge when possible: edge depth may be background).
    let mut foot: Vec<(usize, usize, f32)> = Vec::new();
    for x in rect.x0..rect.x1 {
        let Some(yb) = (rect.y0..rect.y1)
            .rev()
            .find(|&y| mask[y * width + x] > 0.5)
        else {
            continue;
        };
        let yi = if yb > rect.y0 && mask[(yb - 1) * width + x] > 0.5 {
            yb - 1
        } else {
            yb
        };
        let d = depth[yi * width + x];
        if d.is_finite() && d > 0.0 && d < EMPTY_DEPTH {
            foot.push((x, yb, d));
        }
    }
    if foot.is_empty() {
        return None;
    }
    let size = (rect.width() as f32)
        .max(0.25 * rect.height() as f32)
        .max(8.0);
    let (sx, sb, sa) = (SIGMA_SIDE * size, SIGMA_BELOW * size, SIGMA_ABOVE * size);
    let cell = ((size / 48.0) as usize).clamp(1, 4);
    let ymin = foot.iter().map(|f| f.1).min().expect("footprint");
    let ymax = foot.iter().map(|f| f.1).max().expect("footprint");
    let area = Rect {
        x0: rect.x0.saturating_sub((3.0 * sx).ceil() as usize),
        x1: (rect.x1 + (3.0 * sx).ceil() as usize).min(width),
        y0: ymin.saturating_sub((3.0 * sa).ceil() as usize + 1),
        y1: (ymax + (3.0 * sb).ceil() as usize + 2).min(height),
    };
    let gw = area.width().div_ceil(cell);
    let gh = area.height().div_ceil(cell);
    let mut occ = vec![0.0f32; gw * gh];
    let mut dep = vec![0.0f32; gw * gh];
    let share = 1.0 / cell as f32;
    for &(x, y, d) in &foot {
        let g = ((y - area.y0) / cell) * gw + (x - area.x0) / cell;
        occ[g] += share;
        dep[g] += share * d;
    }
    // Horizontal: normalized Gaussian.
    let kx = gaussian(sx / cell as f32);
    let kx_sum: f32 = kx.iter().sum();
    let rx = kx.len() / 2;
    let mut tmp_o = vec![0.0f32; gw * gh];
    let mut tmp_d = vec![0.0f32; gw * gh];
    for y in 0..gh {
        for x in 0..gw {
            let (mut so, mut sd) = (0.0, 0.0);
            for (t, k) in kx.iter().enumerate() {
                let xs = x as isize + t as isize - rx as isize;
                if xs < 0 || xs >= gw as isize {
                    continue;
                }
                so += k * occ[y * gw + xs as usize];
                sd += k * dep[y * gw + xs as usize];
            }
            tmp_o[y * gw + x] = so / kx_sum;
            tmp_d[y * gw + x] = sd / kx_sum;
        }
    }
    // Vertical: peak-1 asymmetric kernel; source `dy` rows above the target
    // (target below the footprint) uses the long reach.
    let (sbc, sac) = (sb / cell as f32, (sa / cell as f32).max(0.5));
    let rb = (3.0 * sbc).ceil() as isize;
    let ra = (3.0 * sac).ceil() as isize;
    for x in 0..gw {
        for y in 0..gh {
            let (mut so, mut sd) = (0.0, 0.0);
            for dy in -ra..=rb {
                let ys = y as isize - dy;
                if ys < 0 || ys >= gh as isize {
                    continue;
                }
                let s = if dy >= 0 { sbc } else { sac };
                let k = (-0.5 * (dy * dy) as f32 / (s * s)).exp();
                so += k * tmp_o[ys as usize * gw + x];
                sd += k * tmp_d[ys as usize * gw + x];
            }
            occ[y * gw + x] = so;
            dep[y * gw + x] = sd;
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

/// Darkens the background of a 4-plane image under the insert by
/// `strength` at most. Returns the area touched, `None` when nothing was.
pub fn contact_shadow(img: &mut Image, mask: &[f32], depth: &[f32], strength: f32) -> Option<Rect> {
    if strength <= 0.0 {
        return None;
    }
    let (w, h) = (img.width, img.height);
    let map = shadow_map(mask, depth, w, h)?;
    let area = map.area;
    par_bands_mut(img, area.y0, area.y1).for_each(|(y0, [r, g, b, a])| {
        let rows = a.len() / w;
        for dy in 0..rows {
            let y = y0 + dy;
            for x in area.x0..area.x1 {
                let p = y * w + x;
                let m = mask[p];
                if m >= 1.0 {
                    continue;
                }
                let (o, fd) = map.sample(x, y);
                if o <= 1e-4 {
                    continue;
                }
                let d = depth[p];
                if !(d.is_finite() && d < EMPTY_DEPTH) || fd <= 0.0 {
                    continue;
                }
                let z = (d - fd) / (DEPTH_TOLERANCE * fd);
                let s = strength * o * (-z * z).exp() * (1.0 - m);
                let k = 1.0 - s;
                let i = dy * w + x;
                r[i] *= k;
                g[i] *= k;
                b[i] *= k;
            }
        }
    });
    Some(area)
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
        contact_shadow(&mut img, &mask, &depth, 0.6).unwrap();
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
    fn no_shadow_without_insert_or_depth_or_strength() {
        let (mut img, mask, depth) = scene();
        let orig = img.clone();
        assert!(contact_shadow(&mut img, &vec![0.0; mask.len()], &depth, 0.6).is_none());
        assert!(contact_shadow(&mut img, &mask, &vec![1e10; depth.len()], 0.6).is_none());
        assert!(contact_shadow(&mut img, &mask, &depth, 0.0).is_none());
        assert_eq!(img, orig);
    }
}
