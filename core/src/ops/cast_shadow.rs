//! Cast shadows of inserted objects toward a known light: a screen-space
//! ray march from the background to the light, against the insert.
//!
//! The light is a direction in world space (toward the light, as a sun's
//! `-Z` axis points away from it), given by the host (`light_direction`).
//! For every cell of a grid over the area the shadow can reach, the
//! background point under the cell's centre is unprojected with the depth
//! and the camera, and [`STEPS`] points are taken toward the light, up to
//! [`REACH`] times the insert's world size. A point that projects onto the
//! insert mask, behind the insert's surface there but by less than the
//! insert's size (the object's unseen back), is shadowed: the insert stands
//! between it and the light. The grid is blurred by [`SOFTNESS`] of the
//! insert's size (a soft penumbra, steady from frame to frame) and handed to
//! [`super::shadow::apply`] as a [`ShadowMap`] whose depth is the cells' own,
//! so the darkening stops at depth edges.
//!
//! Only the insert casts: the rest of the scene's shadows are the
//! renderer's. Several inserts in one mask cast together.

use glam::{DMat4, DVec2, DVec3, DVec4};
use rayon::prelude::*;

use super::shadow::ShadowMap;
use super::{Rect, EMPTY_DEPTH};
use crate::frame::Camera;

/// March steps per cell.
pub const STEPS: usize = 24;
/// March length, in multiples of the insert's world size (the diagonal of
/// its bounding box).
pub const REACH: f64 = 2.5;
/// A march point behind the insert's surface by more than this many
/// insert sizes is behind the object, not inside it.
pub const THICKNESS: f64 = 0.75;
/// Penumbra blur (sigma) as a share of the insert's size on screen.
pub const SOFTNESS: f32 = 0.02;
/// Largest grid edge in cells: the cell grows with the area.
pub const MAX_GRID: usize = 128;
/// Insert samples per edge of its bounding box (for its world size).
const SIZE_SAMPLES: usize = 48;

/// The insert's world-space bounding box from a lattice of its pixels.
fn insert_bounds(
    mask: &[f32],
    depth: &[f32],
    insert: Rect,
    width: usize,
    world_point: impl Fn(DVec2, f64) -> DVec3,
) -> Option<(DVec3, DVec3)> {
    let sx = insert.width().div_ceil(SIZE_SAMPLES).max(1);
    let sy = insert.height().div_ceil(SIZE_SAMPLES).max(1);
    let (mut lo, mut hi) = (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN));
    let mut n = 0;
    for y in (insert.y0..insert.y1).step_by(sy) {
        for x in (insert.x0..insert.x1).step_by(sx) {
            let i = y * width + x;
            let d = depth[i];
            if mask[i] > 0.5 && d.is_finite() && d > 0.0 && d < EMPTY_DEPTH {
                let p = world_point(DVec2::new(x as f64 + 0.5, y as f64 + 0.5), d as f64);
                lo = lo.min(p);
                hi = hi.max(p);
                n += 1;
            }
        }
    }
    (n >= 4).then_some((lo, hi))
}

/// Pixel position and planar depth of world point `p` (`None` behind the camera).
#[inline]
fn project(w2c: &DMat4, w2n: &DMat4, p: DVec3, width: f64, height: f64) -> Option<(f64, f64, f64)> {
    let h = p.extend(1.0);
    let z = w2c.row(2).dot(h);
    let n: DVec4 = *w2n * h;
    (z > 1e-6 && n.w.abs() > 1e-12).then(|| (n.x / n.w * width, n.y / n.w * height, z))
}

/// Marches from world point `p` toward `l` in `steps` equal steps up to
/// `reach`; true when `hit(pixel index, planar depth of the point)` holds at
/// a step that projects inside the `size` (width, height) frame. The
/// point's homogeneous position and depth are linear in the distance, so a
/// step costs a few multiply-adds and a division.
#[allow(clippy::too_many_arguments)]
#[inline]
fn march(
    w2c: &DMat4,
    w2n: &DMat4,
    p: DVec3,
    l: DVec3,
    reach: f64,
    steps: usize,
    (wf, hf): (f64, f64),
    hit: impl Fn(usize, f64) -> bool,
) -> bool {
    let (hp, hl) = (*w2n * p.extend(1.0), *w2n * l.extend(0.0));
    let (zp, zl) = (w2c.row(2).dot(p.extend(1.0)), w2c.row(2).dot(l.extend(0.0)));
    (1..=steps).any(|s| {
        let t = reach * s as f64 / steps as f64;
        let (h, qz) = (hp + t * hl, zp + t * zl);
        if qz <= 1e-6 || h.w.abs() <= 1e-12 {
            return false;
        }
        let (qx, qy) = (h.x / h.w * wf, h.y / h.w * hf);
        if !(qx >= 0.0 && qy >= 0.0 && qx < wf && qy < hf) {
            return false;
        }
        hit(qy as usize * wf as usize + qx as usize, qz)
    })
}

/// The shadow the insert (mask above 0.5, bounding box `insert`) casts
/// toward `light` (world space, toward the light; need not be unit
/// length), as occlusion on a grid; `None` without a usable insert, light
/// or camera, or when the light is behind the insert as seen from every
/// background point of the frame (nothing to darken).
pub fn cast_shadow_map(
    mask: &[f32],
    depth: &[f32],
    insert: Rect,
    camera: &Camera,
    light: DVec3,
    width: usize,
    height: usize,
) -> Option<ShadowMap> {
    let l = light.try_normalize()?;
    if insert.is_empty() || width * height == 0 {
        return None;
    }
    let unproject = camera.unprojector(width, height);
    let (lo, hi) = insert_bounds(mask, depth, insert, width, |px, d| {
        unproject.world_point(px, d)
    })?;
    let size = (hi - lo).length().max(1e-6);
    let reach = REACH * size;
    let (w2c, w2n) = (
        camera.world_to_camera.as_dmat4(),
        camera.world_to_ndc.as_dmat4(),
    );
    let (wf, hf) = (width as f64, height as f64);
    // Where the shadow can fall: the insert's box and the box moved away
    // from the light by the reach, on screen (the whole frame when a corner
    // is behind the camera).
    let mut area = insert;
    let mut whole = false;
    for k in 0..16 {
        let c = DVec3::new(
            if k & 1 == 0 { lo.x } else { hi.x },
            if k & 2 == 0 { lo.y } else { hi.y },
            if k & 4 == 0 { lo.z } else { hi.z },
        ) - if k & 8 == 0 { DVec3::ZERO } else { l * reach };
        match project(&w2c, &w2n, c, wf, hf) {
            Some((x, y, _)) => {
                let (x, y) = (x.clamp(0.0, wf), y.clamp(0.0, hf));
                area = area.union(&Rect {
                    x0: x as usize,
                    y0: y as usize,
                    x1: (x.ceil() as usize + 1).min(width),
                    y1: (y.ceil() as usize + 1).min(height),
                });
            }
            None => whole = true,
        }
    }
    let area = if whole {
        Rect::full(width, height)
    } else {
        area.expand(2, width, height)
    };
    let cell = area.width().max(area.height()).div_ceil(MAX_GRID).max(1);
    let (gw, gh) = (area.width().div_ceil(cell), area.height().div_ceil(cell));
    let thickness = THICKNESS * size;
    // Row-parallel on the current pool (each cell on its own: the result
    // does not depend on the thread count).
    let rows: Vec<(Vec<f32>, Vec<f32>)> = (0..gh)
        .into_par_iter()
        .map(|j| {
            let (mut occ, mut dep) = (vec![0.0f32; gw], vec![0.0f32; gw]);
            let y = (area.y0 + j * cell + cell / 2).min(area.y1 - 1);
            for i in 0..gw {
                let x = (area.x0 + i * cell + cell / 2).min(area.x1 - 1);
                let at = y * width + x;
                let d = depth[at];
                if !(d.is_finite() && d > 0.0 && d < EMPTY_DEPTH) {
                    continue;
                }
                dep[i] = d;
                if mask[at] > 0.5 {
                    continue;
                }
                let p = unproject.world_point(DVec2::new(x as f64 + 0.5, y as f64 + 0.5), d as f64);
                let hit = march(&w2c, &w2n, p, l, reach, STEPS, (wf, hf), |k, qz| {
                    let di = depth[k] as f64;
                    mask[k] > 0.5 && di < qz && qz - di < thickness
                });
                if hit {
                    occ[i] = 1.0;
                }
            }
            (occ, dep)
        })
        .collect();
    let (mut occ, mut dep) = (Vec::with_capacity(gw * gh), Vec::with_capacity(gw * gh));
    for (o, d) in rows {
        occ.extend(o);
        dep.extend(d);
    }
    if occ.iter().all(|&o| o == 0.0) {
        return None;
    }
    // Penumbra: a separable Gaussian over the grid.
    let sigma = (SOFTNESS * insert.width().max(insert.height()) as f32 / cell as f32).max(0.6);
    blur(&mut occ, gw, gh, sigma);
    Some(ShadowMap {
        area,
        cell,
        grid_width: gw,
        grid_height: gh,
        occlusion: occ,
        depth: dep,
    })
}

/// Largest grid edge (cells) of [`scene_shadow_darkening`].
pub const SCENE_GRID: usize = 96;
/// March steps of [`scene_shadow_darkening`].
pub const SCENE_STEPS: usize = 16;
/// A march point behind the visible surface by less than this share of its
/// depth is inside the occluder (more: behind it).
pub const SCENE_THICKNESS: f64 = 0.05;
/// Fewest lit and fewest shadowed cells [`scene_shadow_darkening`] decides on.
pub const SCENE_MIN_CELLS: usize = 24;

/// How dark the scene's own shadows are, in stops: the renderer's ground in
/// the shadow of its own geometry against the same kind of ground in the
/// light. On a grid over the frame, each background cell facing the light
/// (its normal from the depth, `n.l` above 0.3) is marched toward the light
/// against the depth buffer (a point behind the visible surface by less
/// than [`SCENE_THICKNESS`] of its depth is occluded); the median log luminance of
/// the lit cells minus that of the shadowed ones, per band of `n.l` (so a
/// wall and the floor are not compared), weighted by the smaller count.
/// `None` when too few cells of either kind are seen (no shadow in view):
/// the caller keeps its own strength. The insert (mask above 0.5) is left
/// out, so it neither casts nor receives here.
pub fn scene_shadow_darkening(
    img: &crate::frame::Image,
    mask: Option<&[f32]>,
    depth: &[f32],
    camera: &Camera,
    light: DVec3,
) -> Option<f32> {
    scene_light(img, mask, depth, camera, light).map(|s| s.stops)
}

/// What the scene's own shadows say of its light: how dark they are and
/// at which facing that was measured ([`scene_light`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SceneLight {
    /// Lit against shadowed ground, stops ([`scene_shadow_darkening`]).
    pub stops: f32,
    /// Mean `n.l` of the lit cells compared, weighted as the stops are.
    pub facing: f32,
}

impl SceneLight {
    /// The direct light's share against the ambient one for a surface
    /// facing the light: `k` in `ambient * (1 + k * n.l)`, from the lit
    /// ground being `2^stops` times the shadowed one at `facing`.
    pub fn direct_to_ambient(&self) -> f32 {
        (self.stops.exp2() - 1.0) / self.facing.max(0.1)
    }
}

/// [`scene_shadow_darkening`] with the facing it was measured at.
pub fn scene_light(
    img: &crate::frame::Image,
    mask: Option<&[f32]>,
    depth: &[f32],
    camera: &Camera,
    light: DVec3,
) -> Option<SceneLight> {
    let l = light.try_normalize()?;
    let (width, height) = (img.width, img.height);
    if width < 4 || height < 4 {
        return None;
    }
    let unproject = camera.unprojector(width, height);
    let (w2c, w2n) = (
        camera.world_to_camera.as_dmat4(),
        camera.world_to_ndc.as_dmat4(),
    );
    let (wf, hf) = (width as f64, height as f64);
    let eye = w2c.inverse().w_axis.truncate();
    let cell = width.max(height).div_ceil(SCENE_GRID).max(2);
    let (gw, gh) = (width / cell, height / cell);
    let ok = |x: usize, y: usize| {
        let i = y * width + x;
        let d = depth[i];
        d.is_finite() && d > 0.0 && d < EMPTY_DEPTH && mask.is_none_or(|m| m[i] <= 0.5)
    };
    let world = |x: usize, y: usize| {
        unproject.world_point(
            DVec2::new(x as f64 + 0.5, y as f64 + 0.5),
            depth[y * width + x] as f64,
        )
    };
    let lum = |x: usize, y: usize| {
        let i = y * width + x;
        let (r, g, b) = (img.plane(0)[i], img.plane(1)[i], img.plane(2)[i]);
        super::LUMA[0] * r + super::LUMA[1] * g + super::LUMA[2] * b
    };
    // Per cell: (band of n.l, shadowed, log2 luminance, n.l).
    let cells: Vec<(usize, bool, f32, f32)> = (0..gh)
        .into_par_iter()
        .flat_map_iter(|j| {
            let y = j * cell + cell / 2;
            (0..gw).filter_map(move |i| {
                let x = i * cell + cell / 2;
                let (x1, y1) = ((x + 1).min(width - 1), (y + 1).min(height - 1));
                if !(ok(x, y) && ok(x1, y) && ok(x, y1)) {
                    return None;
                }
                // One surface under the three pixels (not an edge), so the
                // normal is the surface's.
                let d0 = depth[y * width + x];
                let smooth = |d: f32| (d - d0).abs() <= 0.02 * d0;
                if !(smooth(depth[y * width + x1]) && smooth(depth[y1 * width + x])) {
                    return None;
                }
                let p = world(x, y);
                let n = (world(x1, y) - p).cross(world(x, y1) - p).try_normalize()?;
                // The normal facing the camera.
                let n = if n.dot(eye - p) < 0.0 { -n } else { n };
                let facing = n.dot(l);
                if facing < 0.3 {
                    return None;
                }
                let band = if facing < 0.6 {
                    0
                } else if facing < 0.8 {
                    1
                } else {
                    2
                };
                let d = depth[y * width + x] as f64;
                let reach = 0.35 * (p - eye).length();
                let start = p + n * (0.01 * d);
                let shadowed = march(
                    &w2c,
                    &w2n,
                    start,
                    l,
                    reach,
                    SCENE_STEPS,
                    (wf, hf),
                    |k, qz| {
                        let di = depth[k] as f64;
                        mask.is_none_or(|m| m[k] <= 0.5)
                            && di < qz * 0.99
                            && qz - di < SCENE_THICKNESS * qz
                    },
                );
                let v = lum(x, y);
                (v > 0.0).then(|| (band, shadowed, v.log2(), facing as f32))
            })
        })
        .collect();
    let median = |mut v: Vec<f32>| {
        v.sort_by(f32::total_cmp);
        v[v.len() / 2]
    };
    let (mut sum, mut facing, mut weight) = (0.0f64, 0.0f64, 0.0f64);
    for band in 0..3 {
        let pick = |s: bool| -> Vec<f32> {
            cells
                .iter()
                .filter(|c| c.0 == band && c.1 == s)
                .map(|c| c.2)
                .collect()
        };
        let (lit, dark) = (pick(false), pick(true));
        let n = lit.len().min(dark.len());
        if n >= SCENE_MIN_CELLS {
            let lit_facing = cells
                .iter()
                .filter(|c| c.0 == band && !c.1)
                .map(|c| c.3 as f64)
                .sum::<f64>()
                / lit.len() as f64;
            sum += n as f64 * (median(lit) - median(dark)) as f64;
            facing += n as f64 * lit_facing;
            weight += n as f64;
        }
    }
    (weight > 0.0).then(|| SceneLight {
        stops: ((sum / weight) as f32).max(0.0),
        facing: (facing / weight) as f32,
    })
}

/// Separable normalized Gaussian blur of a `gw x gh` grid, edges clamped.
fn blur(v: &mut [f32], gw: usize, gh: usize, sigma: f32) {
    let k = super::shadow::gaussian(sigma);
    let mut tmp = vec![0.0f32; v.len()];
    // Along the rows (gh lines of gw cells, neighbours 1 apart), then along
    // the columns (gw lines of gh cells, neighbours gw apart).
    blur_lines(
        v,
        &mut tmp,
        &k,
        Lines {
            len: gw,
            count: gh,
            step: 1,
            line_step: gw,
        },
    );
    blur_lines(
        &tmp,
        v,
        &k,
        Lines {
            len: gh,
            count: gw,
            step: gw,
            line_step: 1,
        },
    );
}

/// `count` lines of `len` cells in a flat grid: cell `i` of line `l` at
/// `l * line_step + i * step`.
struct Lines {
    len: usize,
    count: usize,
    step: usize,
    line_step: usize,
}

/// A normalized 1-D blur with taps `k` along each line, edges clamped.
fn blur_lines(src: &[f32], dst: &mut [f32], k: &[f32], lines: Lines) {
    let r = (k.len() / 2) as isize;
    let ks: f32 = k.iter().sum();
    let at = |l: usize, i: usize| l * lines.line_step + i * lines.step;
    for l in 0..lines.count {
        for i in 0..lines.len {
            let mut s = 0.0;
            for (t, &kv) in k.iter().enumerate() {
                let j = (i as isize + t as isize - r).clamp(0, lines.len as isize - 1) as usize;
                s += kv * src[at(l, j)];
            }
            dst[at(l, i)] = s / ks;
        }
    }
}

/// Parses `light_direction`: three numbers separated by commas or spaces,
/// not all zero; `Ok(None)` for an empty string.
pub fn parse_direction(s: &str) -> std::result::Result<Option<[f32; 3]>, String> {
    match crate::params::parse_three(s)? {
        Some(d) if d.iter().all(|c| c.is_finite()) && d.iter().any(|c| *c != 0.0) => Ok(Some(d)),
        None => Ok(None),
        Some(_) => Err(format!(
            "expected three finite numbers, not all zero (\"x, y, z\"), got {:?}",
            s.trim()
        )),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// A camera over a ground plane y = 0 (+y up) looking at a box (1 x 1 x 1
    /// standing at the origin): mask and depth of the box and the ground, by
    /// ray casting.
    fn scene(w: usize, h: usize) -> (Camera, Vec<f32>, Vec<f32>) {
        let cam = Camera::look_at(
            Vec3::new(0.0, 3.0, -6.0),
            Vec3::new(0.0, 0.5, 0.0),
            0.8,
            w as f32 / h as f32,
        );
        let un = cam.unprojector(w, h);
        let c2w = cam.world_to_camera.as_dmat4().inverse();
        let eye = (c2w * DVec4::new(0.0, 0.0, 0.0, 1.0)).truncate();
        let (mut mask, mut depth) = (vec![0.0; w * h], vec![1e10; w * h]);
        for y in 0..h {
            for x in 0..w {
                let px = DVec2::new(x as f64 + 0.5, y as f64 + 0.5);
                let dir = (un.world_point(px, 1.0) - eye).normalize();
                // Box [-0.5, 0.5] x [0, 1] x [-0.5, 0.5] (slab test), then the ground.
                let (mut t0, mut t1) = (0.0f64, f64::MAX);
                let slabs = [
                    (eye.x, dir.x, -0.5, 0.5),
                    (eye.y, dir.y, 0.0, 1.0),
                    (eye.z, dir.z, -0.5, 0.5),
                ];
                for (o, d, lo, hi) in slabs {
                    let (a, b) = ((lo - o) / d, (hi - o) / d);
                    t0 = t0.max(a.min(b));
                    t1 = t1.min(a.max(b));
                }
                let t = if t0 <= t1 {
                    mask[y * w + x] = 1.0;
                    t0
                } else if dir.y < 0.0 {
                    -eye.y / dir.y
                } else {
                    continue;
                };
                let p = eye + dir * t;
                depth[y * w + x] = cam.project(p, w, h).unwrap().1 as f32;
            }
        }
        (cam, mask, depth)
    }

    #[test]
    fn the_shadow_falls_away_from_the_light_on_the_ground() {
        let (w, h) = (160, 120);
        let (cam, mask, depth) = scene(w, h);
        let rect = super::super::harmonize::insert_rect(&mask, w, h).unwrap();
        // Light from +x, high: the shadow lies toward -x on the ground.
        let light = DVec3::new(1.0, 1.0, 0.0);
        let map = cast_shadow_map(&mask, &depth, rect, &cam, light, w, h).unwrap();
        let occ_at = |p: DVec3| {
            let (px, _) = cam.project(p, w, h).unwrap();
            let (x, y) = (px.x as usize, px.y as usize);
            if x < map.area.x0 || x >= map.area.x1 || y < map.area.y0 || y >= map.area.y1 {
                return 0.0;
            }
            map.sample(x, y).0
        };
        assert!(
            occ_at(DVec3::new(-1.0, 0.0, 0.0)) > 0.5,
            "no shadow where the box blocks the light"
        );
        assert!(
            occ_at(DVec3::new(1.2, 0.0, 0.0)) < 0.05,
            "shadow on the lit side"
        );
        assert!(
            occ_at(DVec3::new(-1.0, 0.0, -2.0)) < 0.05,
            "shadow beside the box's"
        );
        // From the other side, the other way.
        let light = DVec3::new(-1.0, 1.0, 0.0);
        let map2 = cast_shadow_map(&mask, &depth, rect, &cam, light, w, h).unwrap();
        let (px, _) = cam.project(DVec3::new(1.0, 0.0, 0.0), w, h).unwrap();
        assert!(map2.sample(px.x as usize, px.y as usize).0 > 0.5);
        // No light direction, no shadow.
        assert!(cast_shadow_map(&mask, &depth, rect, &cam, DVec3::ZERO, w, h).is_none());
    }

    #[test]
    fn directions_parse() {
        assert_eq!(parse_direction(""), Ok(None));
        assert_eq!(parse_direction("0.3, -0.5 0.8"), Ok(Some([0.3, -0.5, 0.8])));
        assert!(parse_direction("0,0,0").is_err());
        assert!(parse_direction("1,2").is_err());
        assert!(parse_direction("1,x,2").unwrap_err().contains("\"x\""));
    }
}
