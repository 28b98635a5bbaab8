//! Shading correction of an inserted object toward the scene's light.
//!
//! An insert rendered under another light (another sun, or only a sky)
//! lacks the directional shading the scene's light gives: the surfaces
//! facing the scene's light are no brighter than those facing away. With
//! the light's direction from the host and the camera, the insert's own
//! normals come from the depth (the surface between neighbouring pixels,
//! in world space, whatever space a host's normal AOV is in), and each of
//! its pixels gets its facing `c = max(0, n.l)` ([`Facing`]).
//!
//! Lambertian shading under a sun and an ambient light is
//! `albedo * ambient * (1 + k * c)`, `k` the direct light's share against
//! the ambient one. The scene's `k` comes from its own shadows: lit ground
//! against the same ground in shadow ([`super::cast_shadow::scene_light`]).
//! The insert's `k` is fitted: its luminance regressed on its facing
//! ([`fit`]). Where the insert shows clearly less of the scene's light
//! than the scene does, each pixel is multiplied by
//! `(1 + k_scene * c) / (1 + k_insert * c)` ([`apply`]): the sides facing
//! away from the light (the ambient) keep their colors, the sides facing
//! it get the light the scene gives them. An insert that already shows as
//! much (a correctly lit one; its albedo and highlights make the fit vary
//! by a few tenths of a stop) or more of the light is left alone: a fit
//! cannot tell more light from a brighter albedo on the lit side.
//!
//! The correction is the [`Shade`] of the object's filter track, smoothed
//! over time with the rest of the filter.

use glam::{DVec2, DVec3};
use rayon::prelude::*;

use super::{par_bands_mut, Rect, EMPTY_DEPTH, LUMA};
use crate::frame::{Camera, Image};

/// Neighbouring pixels whose depths differ by more than this share lie on
/// different surfaces: no normal between them.
const EDGE_DEPTH: f32 = 0.05;
/// Fewest insert pixels with a normal a fit is made from.
const MIN_SAMPLES: f64 = 64.0;
/// Smallest variance of the facing over the insert a fit is made from (a
/// flat face toward the camera shows no shading to fit).
const MIN_FACING_VARIANCE: f64 = 0.01;
/// The largest direct-to-ambient ratio either side takes.
pub const MAX_RATIO: f32 = 12.0;
/// Facing (`n.l`) at which the insert's shading is compared with the
/// scene's: a surface turned toward the light.
pub const GAP_FACING: f32 = 0.7;
/// An insert that shows another light ([`Fit::other_light`]) and less of
/// the scene's by less than this many stops at [`GAP_FACING`] is left
/// alone; the correction ramps in over [`SHADE_RAMP`] stops beyond.
pub const SHADE_DEAD_ZONE: f32 = 0.3;
/// The dead zone for an insert that shows no other light than the scene's,
/// only less of it: objects differ more in how much their albedo and
/// highlights follow the light (a fit of a correctly lit object in the
/// out-of-domain courtyard shows 0.5-0.8 stops less than the ground's
/// shadows measure).
pub const SHADE_DEAD_ZONE_ALONE: f32 = 1.0;
/// Width (stops) of the ramp beyond the dead zones.
pub const SHADE_RAMP: f32 = 0.35;

/// Each pixel's normal and facing toward the light over an insert's
/// bounding box.
#[derive(Debug, Clone, PartialEq)]
pub struct Facing {
    /// The box (the insert part's [`Rect`]).
    pub rect: Rect,
    /// Every `step`-th pixel of `rect` in both directions has a normal.
    pub step: usize,
    /// The light's direction (unit, world space).
    pub light: [f32; 3],
    /// The world-space unit normal per pixel of the lattice, row-major,
    /// facing the camera; NaN where none was found (an edge, empty depth,
    /// off the insert).
    pub normal: Vec<[f32; 3]>,
}

impl Facing {
    /// Columns of the lattice.
    pub fn columns(&self) -> usize {
        self.rect.width().div_ceil(self.step)
    }

    /// `max(0, n.l)` at index `k` of [`Facing::normal`]; NaN without a normal.
    pub fn cos(&self, k: usize) -> f32 {
        let (n, l) = (self.normal[k], self.light);
        (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]).max(0.0)
    }
}

/// The normal and facing of every `step`-th insert pixel (mask above 0) of
/// `rect` in both directions, normals from the depth and the camera:
/// [`Facing::rect`] is `rect` and [`Facing::step`] `step`. `None` without a
/// usable light direction.
#[allow(clippy::too_many_arguments)]
pub fn facing(
    depth: &[f32],
    mask: &[f32],
    rect: Rect,
    step: usize,
    camera: &Camera,
    light: DVec3,
    width: usize,
    height: usize,
) -> Option<Facing> {
    let step = step.max(1);
    let l = light.try_normalize()?;
    let un = camera.unprojector(width, height);
    let eye = camera
        .world_to_camera
        .as_dmat4()
        .inverse()
        .w_axis
        .truncate();
    let valid = |i: usize| {
        let d = depth[i];
        d.is_finite() && d > 0.0 && d < EMPTY_DEPTH
    };
    let point = |x: usize, y: usize| {
        un.world_point(
            DVec2::new(x as f64 + 0.5, y as f64 + 0.5),
            depth[y * width + x] as f64,
        )
    };
    // The neighbour on the same surface along one axis: the nearer in depth
    // of the two sides, signed so the difference points along +axis.
    let side = |i: usize, a: Option<usize>, b: Option<usize>| -> Option<(usize, f64)> {
        let d0 = depth[i];
        let near = |j: Option<usize>| {
            j.filter(|&j| valid(j) && (depth[j] - d0).abs() <= EDGE_DEPTH * d0)
                .map(|j| (j, (depth[j] - d0).abs()))
        };
        match (near(a), near(b)) {
            (Some((j, da)), Some((k, db))) => Some(if db < da { (k, 1.0) } else { (j, -1.0) }),
            (Some((j, _)), None) => Some((j, -1.0)),
            (None, Some((k, _))) => Some((k, 1.0)),
            (None, None) => None,
        }
    };
    const NONE: [f32; 3] = [f32::NAN; 3];
    let ys: Vec<usize> = (rect.y0..rect.y1).step_by(step).collect();
    let rows: Vec<Vec<[f32; 3]>> = ys
        .into_par_iter()
        .map(|y| {
            (rect.x0..rect.x1)
                .step_by(step)
                .map(|x| {
                    let i = y * width + x;
                    if mask[i] <= 0.0 || !valid(i) {
                        return NONE;
                    }
                    let left = (x > 0).then(|| i - 1);
                    let right = (x + 1 < width).then_some(i + 1);
                    let up = (y > 0).then(|| i - width);
                    let down = (y + 1 < height).then_some(i + width);
                    let (Some((jx, sx)), Some((jy, sy))) =
                        (side(i, left, right), side(i, up, down))
                    else {
                        return NONE;
                    };
                    let p = point(x, y);
                    let dx = (point(jx % width, jx / width) - p) * sx;
                    let dy = (point(jy % width, jy / width) - p) * sy;
                    match dx.cross(dy).try_normalize() {
                        Some(n) => {
                            let n = if n.dot(eye - p) < 0.0 { -n } else { n };
                            [n.x as f32, n.y as f32, n.z as f32]
                        }
                        None => NONE,
                    }
                })
                .collect()
        })
        .collect();
    let mut normal = Vec::with_capacity(rows.iter().map(Vec::len).sum());
    rows.into_iter().for_each(|r| normal.extend(r));
    Some(Facing {
        rect,
        step,
        light: [l.x as f32, l.y as f32, l.z as f32],
        normal,
    })
}

/// What an insert's shading says of its light ([`fit`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Fit {
    /// `k` in `a * (1 + k * c)`: its luminance regressed on its facing to
    /// the scene's light.
    pub ratio: f32,
    /// Its mean facing to the scene's light.
    pub mean_facing: f32,
    /// Whether it shows another light: with the facing to some direction
    /// more than 60 degrees from the scene's light as a second regressor,
    /// at least [`OTHER_LIGHT_GAIN`] of the one-light fit's residual is
    /// explained, by a light at least [`OTHER_LIGHT_RATIO`] of its ambient.
    pub other_light: bool,
}

/// Share of the one-light fit's residual a second light must explain.
pub const OTHER_LIGHT_GAIN: f64 = 0.35;
/// Smallest direct-to-ambient ratio of that second light.
pub const OTHER_LIGHT_RATIO: f64 = 0.3;
/// Most samples a fit reads: the lattice step over an insert's box
/// ([`fit_step`]).
const FIT_SAMPLES: f64 = 2048.0;

/// The lattice step of [`facing`] for [`fit`] over `rect`: about
/// 2048 samples.
pub fn fit_step(rect: Rect) -> usize {
    ((rect.width() * rect.height()) as f64 / FIT_SAMPLES)
        .sqrt()
        .ceil()
        .max(1.0) as usize
}

/// Weighted least squares of `y` on `[1, x1, ..]` (2 or 3 regressors with
/// the constant): the coefficients and the weighted mean squared residual.
/// `rows` is read twice (the normal equations, then the residual), never
/// collected.
fn least_squares<const N: usize>(
    rows: impl Iterator<Item = ([f64; N], f64, f64)> + Clone,
) -> Option<([f64; N], f64)> {
    let mut a = [[0.0f64; N]; N];
    let mut b = [0.0f64; N];
    for (x, y, w) in rows.clone() {
        for i in 0..N {
            b[i] += w * x[i] * y;
            for j in 0..N {
                a[i][j] += w * x[i] * x[j];
            }
        }
    }
    let x = super::solve(a, b, 1e-9 * (1.0 + a[0][0]))?;
    let (mut e, mut wsum) = (0.0, 0.0);
    for (xi, y, w) in rows {
        let p: f64 = (0..N).map(|k| x[k] * xi[k]).sum();
        e += w * (p - y) * (p - y);
        wsum += w;
    }
    Some((x, e / wsum.max(1e-12)))
}

/// The insert's own shading, fitted on the lattice of `f` (pixels whose mask
/// is above 0.5 (weighted by `2 * mask - 1`), unpremultiplied luminance
/// against facing ([`Fit`]). `None` when too few pixels have a normal or
/// they all face the light alike.
pub fn fit(img: &Image, mask: &[f32], f: &Facing) -> Option<Fit> {
    let w = img.width;
    let (r, g, b, a) = (img.plane(0), img.plane(1), img.plane(2), img.plane(3));
    let (rect, step, cols) = (f.rect, f.step, f.columns());
    // (normal, luminance, weight), in row order.
    let samples: Vec<([f32; 3], f64, f64)> = (rect.y0..rect.y1)
        .step_by(step)
        .enumerate()
        .flat_map(|(j, y)| {
            (rect.x0..rect.x1)
                .step_by(step)
                .enumerate()
                .filter_map(move |(i, x)| {
                    let p = y * w + x;
                    let n = f.normal[j * cols + i];
                    let wt = (2.0 * mask[p] - 1.0).clamp(0.0, 1.0);
                    if !n[0].is_finite() || wt <= 0.0 || a[p] <= 1e-3 {
                        return None;
                    }
                    let lum = (LUMA[0] * r[p] + LUMA[1] * g[p] + LUMA[2] * b[p]) / a[p];
                    Some((n, lum.max(0.0) as f64, wt as f64))
                })
        })
        .collect();
    let wsum: f64 = samples.iter().map(|s| s.2).sum();
    if wsum < MIN_SAMPLES {
        return None;
    }
    let l = f.light;
    let facing =
        |n: [f32; 3], d: [f32; 3]| (n[0] * d[0] + n[1] * d[1] + n[2] * d[2]).max(0.0) as f64;
    // Each sample's facing to the scene's light, once.
    let lit: Vec<f64> = samples.iter().map(|&(n, ..)| facing(n, l)).collect();
    let one = || {
        samples
            .iter()
            .zip(&lit)
            .map(|(&(_, y, wt), &c)| ([1.0, c], y, wt))
    };
    let mc = one().map(|s| s.2 * s.0[1]).sum::<f64>() / wsum;
    let var = one().map(|s| s.2 * (s.0[1] - mc).powi(2)).sum::<f64>() / wsum;
    let my = one().map(|s| s.2 * s.1).sum::<f64>() / wsum;
    if var < MIN_FACING_VARIANCE || my <= 0.0 {
        return None;
    }
    let ([intercept, slope], residual) = least_squares(one())?;
    let ratio = if intercept <= 0.0 {
        MAX_RATIO
    } else {
        (slope / intercept).clamp(0.0, MAX_RATIO as f64) as f32
    };
    // A second light: directions every 15 degrees of elevation (-30 to 90)
    // and 20 of azimuth, more than 60 degrees from the scene's light.
    let mut other_light = false;
    if residual > 0.0 {
        'search: for e in 0..9 {
            let el = ((-30 + 15 * e) as f32).to_radians();
            for k in 0..18 {
                let az = ((20 * k) as f32).to_radians();
                let d = [el.cos() * az.sin(), el.cos() * az.cos(), el.sin()];
                if d[0] * l[0] + d[1] * l[1] + d[2] * l[2] >= 0.5 {
                    continue;
                }
                let two = samples
                    .iter()
                    .zip(&lit)
                    .map(|(&(n, y, wt), &c)| ([1.0, c, facing(n, d)], y, wt));
                if let Some(([a0, _, a2], res)) = least_squares(two) {
                    if a0 > 0.0
                        && a2 / a0 >= OTHER_LIGHT_RATIO
                        && 1.0 - res / residual >= OTHER_LIGHT_GAIN
                    {
                        other_light = true;
                        break 'search;
                    }
                }
            }
        }
    }
    Some(Fit {
        ratio,
        mean_facing: mc as f32,
        other_light,
    })
}

/// The shading correction of one insert: each pixel times
/// `(1 + target * c) / (1 + current * c)`. Equal ratios change nothing.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Shade {
    /// Direct-to-ambient ratio the insert is given.
    pub target: f32,
    /// Direct-to-ambient ratio it shows.
    pub current: f32,
}

impl Shade {
    /// The correction that changes nothing.
    pub const IDENTITY: Shade = Shade {
        target: 0.0,
        current: 0.0,
    };

    /// Whether it changes nothing.
    pub fn is_identity(&self) -> bool {
        self.target == self.current
    }

    /// Moves a share `t` of the way to `other`.
    pub fn toward(&self, other: &Shade, t: f32) -> Shade {
        Shade {
            target: self.target + t * (other.target - self.target),
            current: self.current + t * (other.current - self.current),
        }
    }

    /// The largest change it makes to a pixel, stops (at `c = 1`).
    pub fn stops(&self) -> f32 {
        ((1.0 + self.target) / (1.0 + self.current)).log2()
    }
}

/// The correction for an insert whose shading is `fit`, in a scene whose
/// direct-to-ambient ratio is `scene`: none when the insert shows as much
/// of the scene's light or more; else, by how many stops less it shows on
/// a surface facing the light at [`GAP_FACING`], none within a dead zone ([`SHADE_DEAD_ZONE`] when it
/// shows another light, [`SHADE_DEAD_ZONE_ALONE`] when it only lacks the
/// scene's), the full difference [`SHADE_RAMP`] stops beyond.
pub fn shade(fit: &Fit, scene: f32) -> Shade {
    let scene = scene.clamp(0.0, MAX_RATIO);
    let current = fit.ratio;
    let c = GAP_FACING;
    let gap = ((1.0 + scene * c) / (1.0 + current * c)).log2();
    let dead = if fit.other_light {
        SHADE_DEAD_ZONE
    } else {
        SHADE_DEAD_ZONE_ALONE
    };
    let t = ((gap - dead) / SHADE_RAMP).clamp(0.0, 1.0);
    let t = t * t * (3.0 - 2.0 * t);
    Shade {
        target: current + t * (scene - current).max(0.0),
        current,
    }
}

/// Applies `shade` to the insert in place, weighted by the mask: RGB times
/// `1 + m * (ratio - 1)`. Pixels without a normal take the ratio at the
/// insert's mean facing `mean_facing`.
/// `f` must have every pixel ([`Facing::step`] 1).
pub fn apply(img: &mut Image, mask: &[f32], f: &Facing, mean_facing: f32, shade: &Shade) {
    if shade.is_identity() || f.rect.is_empty() {
        return;
    }
    debug_assert_eq!(f.step, 1);
    let w = img.width;
    let rect = f.rect;
    let rw = rect.width();
    let s = *shade;
    let ratio = |c: f32| (1.0 + s.target * c) / (1.0 + s.current * c);
    let fallback = ratio(mean_facing);
    par_bands_mut(img, rect.y0, rect.y1).for_each(|(y0, [r, g, b, _])| {
        let rows = r.len() / w;
        for dy in 0..rows {
            let y = y0 + dy;
            for x in rect.x0..rect.x1 {
                let m = mask[y * w + x];
                if m <= 0.0 {
                    continue;
                }
                let c = f.cos((y - rect.y0) * rw + (x - rect.x0));
                let q = if c.is_finite() { ratio(c) } else { fallback };
                let k = 1.0 + m * (q - 1.0);
                let p = dy * w + x;
                r[p] *= k;
                g[p] *= k;
                b[p] *= k;
            }
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    /// A sphere of radius 1 at the origin seen from +z at distance 4 over
    /// a far background, with the camera's planar depth; its albedo 0.5,
    /// lit by `ambient * (1 + k * max(0, n.l))`.
    fn sphere(w: usize, h: usize, light: DVec3, k: f32) -> (Image, Vec<f32>, Vec<f32>, Camera) {
        let camera = Camera::look_at(
            Vec3::new(0.0, 0.0, 4.0),
            Vec3::ZERO,
            40f32.to_radians(),
            w as f32 / h as f32,
        );
        let un = camera.unprojector(w, h);
        let eye = DVec3::new(0.0, 0.0, 4.0);
        let l = light.normalize();
        let n = w * h;
        let mut img = Image::filled(w, h, 4, 1.0);
        let (mut depth, mut mask) = (vec![50.0f32; n], vec![0.0f32; n]);
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let dir = (un.world_point(DVec2::new(x as f64 + 0.5, y as f64 + 0.5), 1.0) - eye)
                    .normalize();
                // Ray-sphere: |eye + t dir| = 1.
                let bq = eye.dot(dir);
                let disc = bq * bq - (eye.length_squared() - 1.0);
                let v = if disc > 0.0 {
                    let t = -bq - disc.sqrt();
                    let p = eye + dir * t;
                    depth[i] = (4.0 - p.z) as f32;
                    mask[i] = 1.0;
                    0.5 * 0.2 * (1.0 + k * p.normalize().dot(l).max(0.0) as f32)
                } else {
                    0.1
                };
                for c in 0..3 {
                    img.data[c * n + i] = v;
                }
            }
        }
        (img, depth, mask, camera)
    }

    #[test]
    fn the_fit_recovers_the_shading_of_a_lit_sphere() {
        let light = DVec3::new(0.5, 0.6, 0.7);
        for k in [0.0f32, 1.0, 3.0] {
            let (img, depth, mask, cam) = sphere(160, 120, light, k);
            let rect = super::super::harmonize::insert_rect(&mask, 160, 120).unwrap();
            let f = facing(&depth, &mask, rect, 1, &cam, light, 160, 120).unwrap();
            let got = fit(&img, &mask, &f).unwrap();
            assert!(
                (got.ratio - k).abs() < 0.1 * k.max(1.0),
                "k {k}: fitted {got:?}"
            );
            assert!(got.mean_facing > 0.2 && got.mean_facing < 0.8, "{got:?}");
            assert!(!got.other_light, "{got:?}");
        }
    }

    #[test]
    fn a_sphere_lit_only_by_the_sky_gets_the_suns_shading() {
        let light = DVec3::new(0.5, 0.6, 0.7);
        let (mut img, depth, mask, cam) = sphere(160, 120, light, 0.0);
        let (want, ..) = sphere(160, 120, light, 3.0);
        let rect = super::super::harmonize::insert_rect(&mask, 160, 120).unwrap();
        let f = facing(&depth, &mask, rect, 1, &cam, light, 160, 120).unwrap();
        let got = fit(&img, &mask, &f).unwrap();
        let s = shade(&got, 3.0);
        assert!((s.target - 3.0).abs() < 1e-3, "{s:?}");
        let err = |img: &Image| {
            let n = 160 * 120;
            let mut e = 0.0f64;
            for (i, _) in mask.iter().enumerate().take(n).filter(|(_, &m)| m > 0.0) {
                e += ((img.data[i] - want.data[i]) as f64).powi(2);
            }
            e
        };
        let before = err(&img);
        apply(&mut img, &mask, &f, got.mean_facing, &s);
        let after = err(&img);
        assert!(after < 0.05 * before, "error {before} -> {after}");
        // The background is untouched.
        assert_eq!(img.data[0], 0.1);
    }

    #[test]
    fn a_sphere_lit_by_another_sun_shows_it() {
        let scene_light = DVec3::new(0.5, 0.6, 0.7);
        // Another sun, from the other side (more than 60 degrees away).
        let (img, depth, mask, cam) = sphere(160, 120, DVec3::new(-0.8, 0.2, 0.4), 2.0);
        let rect = super::super::harmonize::insert_rect(&mask, 160, 120).unwrap();
        let f = facing(
            &depth,
            &mask,
            rect,
            fit_step(rect),
            &cam,
            scene_light,
            160,
            120,
        )
        .unwrap();
        let got = fit(&img, &mask, &f).unwrap();
        assert!(got.other_light, "{got:?}");
        assert!(!shade(&got, 3.0).is_identity());
    }

    #[test]
    fn a_correctly_lit_or_brighter_lit_insert_is_left_alone() {
        let fit = |ratio, mean_facing, other_light| Fit {
            ratio,
            mean_facing,
            other_light,
        };
        assert!(shade(&fit(3.0, 0.6, true), 3.0).is_identity());
        assert!(shade(&fit(6.0, 0.6, true), 3.0).is_identity());
        // Less of the light, by 0.8 stops, and no other light: albedo.
        assert!(shade(&fit(2.3, 0.7, false), 5.0).is_identity());
        // The same with another light: corrected.
        assert_eq!(shade(&fit(2.3, 0.7, true), 5.0).target, 5.0);
        // None of the scene's light: the full correction.
        assert_eq!(shade(&fit(0.0, 0.5, false), 4.0).target, 4.0);
    }
}
