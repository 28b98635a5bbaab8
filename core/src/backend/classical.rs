//! The classical backend: hole filling, insert harmonization, contact
//! shadows and temporal stabilization (see `crate::ops`), in that order.
//!
//! 1. **inpaint** (`fill_holes`): pixels with coverage < 1 are completed
//!    from the reprojected history (frame 0, then older frames only where
//!    still missing, and only while more than [`OLDER_HISTORY_MIN_HOLES`] of
//!    the frame is missing), then by push-pull over a window around the rest,
//!    on the square root of the color ([`crate::ops::inpaint::push_pull_sqrt`];
//!    with depth and holes that are a large part of the window, from the
//!    background side of each silhouette:
//!    [`crate::ops::inpaint::push_pull_sqrt_or_far`]).
//!    The history fills a pixel only where few confidently covered pixels
//!    are near ([`history_weight`] of [`crate::ops::inpaint::KnownCounts`]
//!    within [`GATE_RADIUS`]): thin gaps take the spatial fill. Pixels below
//!    `coverage_floor` lose their own color first
//!    ([`crate::ops::inpaint::drop_faint`]).
//!    The history is reprojected at the hole pixels alone
//!    ([`crate::temporal::HistoryView::sample`]), except for frames reached
//!    by chained motion vectors (reprojected whole, stage `reproject`).
//! 2. **harmonize** (`harmonize`, needs the insert mask): each inserted
//!    object (the pixels of one of the host's object ids, else a
//!    connected part of the mask; [`harmonize::objects`]) gets the scene
//!    light's shading (`relight`, with a light direction, depth and a
//!    camera; [`relight`]) and, with `match_tone` (off by default), its
//!    color statistics matched part of the way to a ring of background
//!    around it (with ids, the other objects left out of it), and with the
//!    frame's albedo and normals (`albedo_tone`, on by default) a color
//!    matrix that shades its albedo as the background's light does
//!    ([`albedo_tone`]); each object's filter, shading and matrix are
//!    smoothed over time in the [`Carry`] (keys [`TONE_KEY`],
//!    [`SHADE_KEY`] and [`MATRIX_KEY`], the objects followed by their ids,
//!    [`ID_KEY`], else by their centroids) with the weight
//!    `temporal_blend` on the past.
//! 3. **shadow** (`contact_shadows`, needs mask and depth): a soft contact
//!    shadow of strength `shadow_strength` under the insert.
//! 4. **stabilize** (`stabilize`): blend with the reprojected previous result
//!    (`temporal_blend` times validity), history clamped to the local range;
//!    history frame 0 is reprojected row by row inside that pass
//!    ([`crate::temporal::HistoryView::reproject_row`]), so no frame-sized
//!    reprojection is written and read back.
//!
//! Everything runs on the device's pool, row-parallel in fixed bands, so the
//! output does not depend on the thread count.

use rayon::prelude::*;

use super::{Backend, BackendInput, Carry, KeptColor, Progress, Stages};
use crate::error::Result;
use crate::frame::{Image, PreparedFrame};
use crate::ops::{
    albedo_tone, cast_shadow, harmonize, inpaint, par_bands_mut, relight, shadow, stabilize, Rect,
};
use crate::temporal::ReprojectionMode;

/// Carry key of the smoothed harmonization filters, one per inserted object
/// ([`harmonize::tracks_to_vec`]).
pub const TONE_KEY: &str = "classical.harmonize.tone";

/// Carry key of the host's object id of each track of [`TONE_KEY`], in its
/// order (0 for an object without one); absent when no track has an id.
pub const ID_KEY: &str = "classical.harmonize.id";

/// Carry key of the smoothed shading corrections
/// ([`relight::Shade`]: target, current), one per track of [`TONE_KEY`] in
/// its order.
pub const SHADE_KEY: &str = "classical.harmonize.shade";

/// Carry key of the smoothed color matrices from the albedo
/// ([`albedo_tone::ColorMatrix::to_vec`], 9 values each), one per track of
/// [`TONE_KEY`] in its order.
pub const MATRIX_KEY: &str = "classical.harmonize.albedo_matrix";

/// Carry key of the smoothed shares of the contact and the cast shadow still
/// missing from the render ([`shadow::missing_share`]) and of the cast
/// shadow's strength.
pub const SHADOW_KEY: &str = "classical.shadow.missing";

/// Carry key of the scene's light as last measured
/// ([`cast_shadow::scene_light`]): its stops and facing (NaN for a frame
/// that showed no shadow of its own), the light direction it was measured
/// toward (world, 3 values) and the frames since it was.
pub const SCENE_LIGHT_KEY: &str = "classical.scene_light";

/// The scene's light is measured again on every this many frames; the
/// frames between take the last measure (the same light over a few frames
/// of one shot), unless the light's direction moved.
pub const SCENE_LIGHT_FRAMES: f32 = 4.0;

/// The insert's shadows: the contact shadow under it and, with a light
/// direction and a camera, the shadow it casts away from the light
/// ([`cast_shadow::cast_shadow_map`]). Each is darkened by the share of it
/// the render does not already show ([`shadow::existing_darkening`],
/// measured on `img` before either is applied). The cast shadow is as dark
/// as the scene's own shadows ([`cast_shadow::scene_shadow_darkening`]) when
/// some are in view, else `shadow_strength`; the contact shadow (ambient
/// occlusion, not the light's shadow) takes [`CONTACT_SHARE`] of that. The
/// shares and the strength are smoothed over time in the carry. Returns
/// the area touched.
#[allow(clippy::too_many_arguments)]
fn shadows(
    img: &mut Image,
    rendered: Option<&Image>,
    mask: &[f32],
    rect: Rect,
    depth: &[f32],
    input: &BackendInput<'_>,
    scene: &mut SceneLightOnce,
    carry: &mut Carry,
) -> Option<Rect> {
    let (params, frame) = (input.params, input.frame);
    let (w, h) = (img.width, img.height);
    let contact = shadow::shadow_map(mask, depth, rect, w, h, frame.camera.as_ref());
    let light = params
        .light_direction_world(frame.camera.as_ref())
        .zip(frame.camera.as_ref());
    let cast = light
        .and_then(|(l, camera)| cast_shadow::cast_shadow_map(mask, depth, rect, camera, l, w, h));
    // What the render shows is read off its own pixels (`rendered`, else
    // `img`; for the insert's shadows only those covered at least
    // [`shadow::COVERED`]): a repair's fill is not the render's.
    let (probe, coverage) = (rendered.unwrap_or(img), frame.coverage.as_deref());
    // How dark a shadow is here, from the scene's own shadows.
    let measured_strength = match (&cast, light) {
        (Some(_), Some((l, camera))) => scene.get(probe, mask, depth, input, camera, l).map(|s| {
            (1.0 - (-s.stops).exp2()).clamp(MIN_STRENGTH, params.shadow_strength.max(MIN_STRENGTH))
        }),
        _ => None,
    };
    // Whether the render already has the insert's shadows: told by the cast
    // shadow when there is one (the contact shadow lies inside it, where
    // the ground around is as dark), else by the contact shadow.
    let missing = |m: &Option<shadow::ShadowMap>| {
        m.as_ref().map(|m| {
            shadow::missing_share(shadow::existing_darkening(probe, mask, depth, m, coverage))
        })
    };
    let measured = match missing(&cast) {
        Some(c) => [contact.as_ref().map(|_| c), Some(c), measured_strength],
        None => [missing(&contact), None, measured_strength],
    };
    let previous = carry
        .values
        .get(SHADOW_KEY)
        .filter(|v| v.len() == 3 && v.iter().all(|x| x.is_finite()));
    let keep = params.temporal_blend;
    let fallback = [1.0, 1.0, params.shadow_strength];
    let smoothed: Vec<f32> = (0..3)
        .map(|k| match (previous.map(|p| p[k]), measured[k]) {
            (Some(p), Some(m)) => p + (1.0 - keep) * (m - p),
            (p, m) => m.or(p).unwrap_or(fallback[k]),
        })
        .collect();
    let strength = if cast.is_some() {
        smoothed[2]
    } else {
        params.shadow_strength
    };
    let mut area: Option<Rect> = None;
    let plan = [
        (&contact, smoothed[0], CONTACT_SHARE * strength),
        (&cast, smoothed[1], strength),
    ];
    for (map, share, s) in plan {
        if let Some(map) = map {
            if share > 0.0 && s > 0.0 {
                let a = shadow::apply(img, mask, depth, map, s * share);
                area = Some(area.map_or(a, |b| b.union(&a)));
            }
        }
    }
    carry.values.insert(SHADOW_KEY.to_string(), smoothed);
    area
}

/// The scene's light, found at most once per frame: by the first of the
/// shading correction and the cast shadow that needs it (the insert, mask
/// above 0.5, is left out of the measure, so harmonizing the insert in
/// between does not change it).
///
/// Measured from the frame's own shadows ([`cast_shadow::scene_light`]),
/// except where the host gives the ratio (`light_ratio`, or its
/// `light_color` and `ambient_color`) and the frame has
/// holes (a reconstruction's depth is too rough to trace its shadows:
/// out of domain the measure read a third of a render's ratio there) or
/// shows no shadow of its own: then the host's ratio, at
/// [`relight::GAP_FACING`] (on frames with holes the measure is not made).
///
/// A measure is carried ([`SCENE_LIGHT_KEY`]) and taken again by the
/// [`SCENE_LIGHT_FRAMES`]th frame after it, or when the light's direction
/// moved by more than half a degree.
#[derive(Debug, Default)]
struct SceneLightOnce {
    /// This frame's light, once found.
    now: Option<Option<cast_shadow::SceneLight>>,
    /// The carried measure: the light, the direction, the frames since.
    carried: Option<(Option<cast_shadow::SceneLight>, glam::DVec3, f32)>,
    /// What to carry on ([`SceneLightOnce::store`]).
    record: Option<Vec<f32>>,
}

impl SceneLightOnce {
    /// With the last measure from `carry`.
    fn carried(carry: &Carry) -> SceneLightOnce {
        let carried = carry
            .values
            .get(SCENE_LIGHT_KEY)
            .filter(|v| v.len() == 6 && v[2..].iter().all(|x| x.is_finite()))
            .map(|v| {
                let light =
                    (v[0].is_finite() && v[1].is_finite()).then_some(cast_shadow::SceneLight {
                        stops: v[0],
                        facing: v[1],
                    });
                let dir = glam::DVec3::new(v[2] as f64, v[3] as f64, v[4] as f64);
                (light, dir, v[5])
            });
        SceneLightOnce {
            carried,
            ..SceneLightOnce::default()
        }
    }

    /// Carries this frame's measure on (or none, when it made none).
    fn store(self, carry: &mut Carry) {
        match self.record {
            Some(v) => carry.values.insert(SCENE_LIGHT_KEY.to_string(), v),
            None => carry.values.remove(SCENE_LIGHT_KEY),
        };
    }

    fn get(
        &mut self,
        img: &Image,
        mask: &[f32],
        depth: &[f32],
        input: &BackendInput<'_>,
        camera: &crate::frame::Camera,
        light: glam::DVec3,
    ) -> Option<cast_shadow::SceneLight> {
        let (carried, record) = (&self.carried, &mut self.record);
        *self.now.get_or_insert_with(|| {
            let host = input.params.host_light_ratio();
            // The host's ratio, at the facing the shading correction
            // compares at.
            let given = (host > 0.0).then(|| cast_shadow::SceneLight {
                stops: (1.0 + host * relight::GAP_FACING).log2(),
                facing: relight::GAP_FACING,
            });
            if given.is_some() && input.frame.has_holes() {
                // Not measured: the reconstruction's depth would mislead it.
                return given;
            }
            let dir = light.normalize_or_zero();
            let (measured, age) = match carried {
                Some((m, d, age))
                    if age + 1.0 < SCENE_LIGHT_FRAMES && d.dot(dir) > SAME_LIGHT_COS =>
                {
                    (*m, age + 1.0)
                }
                _ => (
                    cast_shadow::scene_light(img, Some(mask), depth, camera, light),
                    0.0,
                ),
            };
            let (stops, facing) = measured.map_or((f32::NAN, f32::NAN), |m| (m.stops, m.facing));
            *record = Some(vec![
                stops,
                facing,
                dir.x as f32,
                dir.y as f32,
                dir.z as f32,
                age,
            ]);
            measured.or(given)
        })
    }
}

/// Cosine of the half degree the light may move by before the scene's light
/// is measured again ([`SceneLightOnce`]).
const SAME_LIGHT_COS: f64 = 0.999_962;

/// The scene's direct-to-ambient ratio for the shading correction: from its
/// light ([`SceneLightOnce`]) when known, else from `shadow_strength` (a
/// shadow taking that share of the light, on ground facing the light).
fn scene_ratio(measured: Option<cast_shadow::SceneLight>, shadow_strength: f32) -> f32 {
    match measured {
        Some(s) => s.direct_to_ambient(),
        None => {
            let s = shadow_strength.clamp(0.0, 0.9);
            s / (1.0 - s)
        }
    }
}

/// Share of the shadow strength the contact shadow under an insert takes.
pub const CONTACT_SHARE: f32 = 0.5;

/// Weakest cast shadow the scene's own shadows can set.
pub const MIN_STRENGTH: f32 = 0.05;

/// An object's filter continues the nearest one of the previous frame within
/// this share of the frame's larger edge.
pub const TRACK_REACH: f32 = 0.15;

/// A harmonization filter within this of the identity (stops, or ratio)
/// leaves the insert as it came: it is not stabilized either.
pub const RECOLOR_TOLERANCE: f32 = 0.02;

/// Margin (pixels) around the insert's bounding box that harmonization may
/// change and a frame without holes stabilizes.
pub const INSERT_MARGIN: usize = 8;

/// Share of the frame that must still be missing after history frame `k`
/// for frame `k + 1` to be reprojected and used for hole filling.
pub const OLDER_HISTORY_MIN_HOLES: f64 = 0.01;

/// Radius of the square around a hole pixel whose confidently covered
/// share decides how much history it takes ([`history_weight`]).
pub const GATE_RADIUS: usize = 3;

/// How much of the reprojected history a hole pixel takes, from the share
/// of confidently covered pixels (coverage at least `coverage_floor`, and
/// at least 0.5) within [`GATE_RADIUS`]: all up to 0.225, none from 0.3.
/// Measured on the out-of-domain reconstructions (`scripts/quality.sh`):
/// in the gaps between splats last frame's fill, reprojected, was further
/// from the truth than the fill from the neighbours (outdoors, pixels of
/// coverage 0.25-0.5: MSE 0.0148 against 0.0110 without history).
pub fn history_weight(known_share: f32) -> f32 {
    ((0.3 - known_share) / 0.075).clamp(0.0, 1.0)
}

/// Share of the frame's own fill of its holes ([`inpaint::SpatialFill`];
/// less far from data) that a reprojected history sample takes before it
/// fills a hole, in both backends. Without it the fill carried in a hole
/// that stays in view remembers the frame it was first made in, however
/// long ago, and a chunk of a sequence started with a pre-roll never meets
/// the sequential run there (issue 22: the lowest frame of 24-frame chunks
/// with a pre-roll of 8 was 45.4 dB from the sequential run's, classical,
/// 42.1 neural; with 0.2, 58.8 and 57.1; docs/farm.md). Out of domain it
/// also gains on recon_hall (classical 19.98 -> 20.11 dB, neural 19.89 ->
/// 20.04) and leaves recon_courtyard as it was (`scripts/quality.sh`).
pub const HISTORY_REFRESH: f32 = 0.2;

/// The classical pipeline.
#[derive(Debug, Default)]
pub struct Classical;

/// The frame as a 4-plane RGBA image: RGB premultiplied, A = coverage (1 when absent).
pub fn rgba_from_frame(frame: &PreparedFrame) -> Image {
    let mut out = Image::zeros(frame.width(), frame.height(), 4);
    rgba_into(frame, &mut out);
    out
}

/// [`rgba_from_frame`] into `out` (4 planes of the frame's size; every
/// sample is overwritten).
fn rgba_into(frame: &PreparedFrame, out: &mut Image) {
    let (w, h) = (frame.width(), frame.height());
    debug_assert_eq!((out.width, out.height, out.channels), (w, h, 4));
    let color = &frame.color;
    let coverage = frame.coverage.as_deref();
    par_bands_mut(out, 0, h).for_each(|(y0, [r, g, b, a])| {
        let s = y0 * w..y0 * w + a.len();
        r.copy_from_slice(&color.plane(0)[s.clone()]);
        g.copy_from_slice(&color.plane(1)[s.clone()]);
        b.copy_from_slice(&color.plane(2)[s.clone()]);
        match coverage {
            Some(c) => a.copy_from_slice(&c[s]),
            None => a.fill(1.0),
        }
    });
}

/// Runs the four operations on `img` (the frame as [`rgba_from_frame`] makes
/// it, the frame's color handed over by the session, or another backend's output when the classical pipeline runs as a
/// post-stage, `classical_post`) with the parameters in `input`.
pub fn run_ops(
    img: &mut Image,
    input: &BackendInput<'_>,
    carry: &mut Carry,
    progress: &mut Progress<'_>,
    stages: &mut Stages,
) -> Result<()> {
    run_ops_on(img, input, carry, progress, stages, false)
}

/// [`run_ops`]; `alpha_is_coverage`: `img`'s alpha is the frame's coverage
/// (1 where absent), so the holes found while preparing the frame
/// ([`crate::frame::Scan`]) are the image's and need no new search.
fn run_ops_on(
    img: &mut Image,
    input: &BackendInput<'_>,
    carry: &mut Carry,
    progress: &mut Progress<'_>,
    stages: &mut Stages,
    alpha_is_coverage: bool,
) -> Result<()> {
    let frame = input.frame;
    let params = input.params;
    let pool = input.pool;
    let history = input.history;
    let (w, h) = (img.width, img.height);

    // A frame with holes is stabilized whole, and its fill drops what is
    // covered less than the floor: an insert there gets its render back
    // (`KeptInsert`), its soft edge over a hole the share it covers.
    let keeps_inserts = frame.has_holes() && !params.stabilize_all;
    // That edge as rendered, before the fill (`img` is the frame's color
    // here, not another backend's output).
    let edge = match (&frame.insert_mask, frame.scan, frame.coverage.as_deref()) {
        (Some(mask), Some(scan), Some(cov)) if keeps_inserts && alpha_is_coverage => scan
            .insert
            .map(|rect| InsertEdge::capture(img, mask, cov, rect, params.coverage_floor)),
        _ => None,
    };

    if params.fill_holes {
        let scanned = frame
            .scan
            .filter(|_| alpha_is_coverage)
            .map(|s| s.holes.map(|(rect, count)| inpaint::Holes { rect, count }));
        let mut holes = match scanned {
            Some(holes) => holes,
            None => stages.time("inpaint", || pool.install(|| inpaint::find_holes(img))),
        };
        if let Some(hh) = holes {
            stages.time("inpaint", || {
                pool.install(|| inpaint::drop_faint(img, hh.rect, params.coverage_floor))
            });
        }
        // With depth, the spatial fill takes the background side; it tells
        // the frame's own data from what the history fills by this copy of
        // the coverage in the holes' box.
        let own = match (&holes, frame.depth.as_deref()) {
            (Some(hh), Some(depth)) => Some((inpaint::OwnCoverage::capture(img, hh.rect), depth)),
            _ => None,
        };
        // History only where few confidently covered pixels are near: in
        // the thin gaps between a reconstruction's splats the spatial fill
        // from the neighbours is closer than last frame's fill reprojected.
        let known = params.coverage_floor.max(0.5);
        let gate = holes.filter(|_| !history.is_empty()).map(|hh| {
            let counts = stages.time("inpaint", || {
                pool.install(|| inpaint::KnownCounts::new(img, hh.rect, GATE_RADIUS, known))
            });
            (hh.rect, counts)
        });
        let allow = |i: usize, j: usize| match &gate {
            Some((r, counts)) if r.contains(j, i) => history_weight(counts.share(j, i)),
            _ => 1.0,
        };
        // The frame's own fill of its holes, which the history is pulled
        // toward where it fills one (a chunk's seam, `HISTORY_REFRESH`).
        let refresh = HISTORY_REFRESH;
        let fresh = gate
            .as_ref()
            .filter(|_| refresh > 0.0)
            .and_then(|(rect, _)| {
                stages.time("inpaint", || {
                    pool.install(|| {
                        inpaint::SpatialFill::new(
                            [img.plane(0), img.plane(1), img.plane(2), img.plane(3)],
                            w,
                            *rect,
                            params.coverage_floor,
                            frame.depth.as_deref(),
                        )
                    })
                })
            });
        let pull = |i: usize, j: usize, c: [f32; 4]| match &fresh {
            Some(f) => f.pull(i, j, c, refresh),
            None => c,
        };
        // The pixels still missing, once a history frame has filled some.
        let mut missing: Option<Vec<(u32, u32)>> = None;
        let mut k = 0;
        while let Some(hh) = holes {
            // Older frames only while much is missing that may take history:
            // reprojecting one costs more than the rest of the pipeline, and
            // push-pull fills small residues well.
            let wanting = match &missing {
                Some(list) => list
                    .iter()
                    .filter(|&&(x, y)| allow(y as usize, x as usize) > 0.0)
                    .count(),
                None => hh.count,
            };
            let enough = k == 0 || wanting as f64 > OLDER_HISTORY_MIN_HOLES * (w * h) as f64;
            if k >= history.len() || !enough {
                break;
            }
            if k > 0 && history.mode(k) == ReprojectionMode::MotionVectors {
                // Chained motion vectors: the whole frame once (the chain
                // is a frame-wide pass anyway), then read pixel by pixel.
                stages.time("reproject", || {
                    pool.install(|| {
                        history.reproject(k);
                    })
                });
            }
            // Only the hole pixels of history frame `k` are reprojected.
            let left = stages.time("inpaint", || {
                let at = history.sampler(k);
                pool.install(|| {
                    inpaint::fill_from_history_listing(
                        img,
                        hh.rect,
                        |i, j| {
                            let (c, v) = at.at(i, j);
                            (pull(i, j, c), v * allow(i, j))
                        },
                        |i, j, out| {
                            let [o0, o1, o2, o3, ov] = out;
                            at.span(i, j, [&mut *o0, &mut *o1, &mut *o2, &mut *o3, &mut *ov]);
                            for (t, v) in ov.iter_mut().enumerate() {
                                *v *= allow(i, j + t);
                                if fresh.is_some() {
                                    let c = pull(i, j + t, [o0[t], o1[t], o2[t], o3[t]]);
                                    (o0[t], o1[t], o2[t], o3[t]) = (c[0], c[1], c[2], c[3]);
                                }
                            }
                        },
                    )
                })
            });
            (holes, missing) = left.unzip();
            k += 1;
        }
        if let Some(hh) = holes {
            let window = inpaint::fill_window(hh.rect, w, h);
            stages.time("inpaint", || {
                pool.install(|| {
                    let far = own.as_ref().map(|(own, depth)| (own, *depth));
                    inpaint::push_pull_sqrt_or_far(img, window, missing.as_deref(), far)
                })
            });
        }
    }
    progress.report(0.4)?;
    let changed = insert_ops(img, None, input, carry, progress, stages)?;

    // Frames with holes (reconstructions) are stabilized whole: their
    // covered pixels flicker too. Otherwise only the insert is: the rest is
    // the renderer's own, already as steady as it rendered it, and blending
    // it with a resampled history would only soften it.
    let area = if params.stabilize_all || frame.has_holes() {
        None
    } else {
        Some(changed.unwrap_or_default())
    };
    // In a frame with holes an insert the operations left as it came keeps
    // its render, as in a frame without holes: it is the host's object,
    // which a resampled history only softens.
    let kept = match (&frame.insert_mask, frame.scan) {
        (Some(mask), Some(scan)) if keeps_inserts && changed.is_none() => scan
            .insert
            .map(|rect| KeptInsert::save(img, mask, rect, edge.as_ref())),
        _ => None,
    };
    stabilize_with_history(img, input, stages, area);
    if let Some(k) = kept {
        k.restore(img, input.kept);
    }
    progress.report(1.0)?;
    Ok(())
}

/// An insert's pixels covered more than 0 and less than the floor, as
/// rendered (premultiplied color and coverage), in pixel order.
struct InsertEdge {
    pixels: Vec<(usize, [f32; 3], f32)>,
}

impl InsertEdge {
    fn capture(img: &Image, mask: &[f32], coverage: &[f32], rect: Rect, floor: f32) -> InsertEdge {
        let (w, n) = (img.width, img.width * img.height);
        let mut pixels = Vec::new();
        for y in rect.y0..rect.y1 {
            for x in rect.x0..rect.x1 {
                let p = y * w + x;
                let v = coverage[p];
                if mask[p] > 0.0 && v > 0.0 && v < floor {
                    pixels.push((p, [0, 1, 2].map(|k| img.data[k * n + p]), v));
                }
            }
        }
        InsertEdge { pixels }
    }
}

/// An insert's pixels before stabilization, weighted as the neural
/// backend keeps an object (twice the mask, at most 1).
struct KeptInsert {
    /// Per pixel of the insert's box with a mask above 0: its index,
    /// weight and RGBA.
    pixels: Vec<(usize, f32, [f32; 4])>,
}

impl KeptInsert {
    /// `edge`: the insert's pixels covered less than the floor as
    /// rendered; such a pixel (its soft edge over a hole, whose color the
    /// fill dropped) is saved as the share it covers plus the fill for the
    /// rest.
    fn save(img: &Image, mask: &[f32], rect: Rect, edge: Option<&InsertEdge>) -> KeptInsert {
        let w = img.width;
        let n = w * img.height;
        let mut pixels = Vec::new();
        for y in rect.y0..rect.y1 {
            for x in rect.x0..rect.x1 {
                let p = y * w + x;
                if mask[p] > 0.0 {
                    let c = [0, 1, 2, 3].map(|k| img.data[k * n + p]);
                    pixels.push((p, (2.0 * mask[p]).min(1.0), c));
                }
            }
        }
        // Both lists are in pixel order.
        let mut i = 0;
        for &(p, rendered, cov) in edge.map_or(&[][..], |e| &e.pixels[..]) {
            while i < pixels.len() && pixels[i].0 < p {
                i += 1;
            }
            if let Some((_, _, c)) = pixels.get_mut(i).filter(|e| e.0 == p) {
                let a = c[3];
                for k in 0..3 {
                    c[k] = inpaint::over_fill(rendered[k], cov, c[k], a);
                }
            }
        }
        KeptInsert { pixels }
    }

    /// Blends the saved pixels back into `img` and into the history's copy
    /// of the result, where that holds it.
    fn restore(&self, img: &mut Image, kept: Option<&KeptColor>) {
        if self.pixels.is_empty() {
            return;
        }
        let n = img.width * img.height;
        for &(p, t, c) in &self.pixels {
            for (k, v) in c.iter().enumerate() {
                let o = &mut img.data[k * n + p];
                *o += t * (v - *o);
            }
        }
        if let Some(slot) = kept {
            slot.patch(|buf| {
                for &(p, _, _) in &self.pixels {
                    for k in 0..4 {
                        buf.data[4 * p + k] = img.data[k * n + p];
                    }
                }
            });
        }
    }
}

/// The insert operations of [`run_ops`] alone: each inserted object's
/// harmonization (shading toward the host's light, `match_tone`, the color
/// matrix from the albedo) and the contact shadows, with their carried
/// state. Returns the area stabilization should blend in a frame without
/// holes: a recolored insert and a margin around it. The neural backend
/// runs them on its output for frames with holes and an insert.
///
/// `rendered`: the frame's color as the host rendered it, when `img` is
/// another backend's output (the network repaints covered pixels near
/// holes). What the render already shows of the scene's light (its own
/// shadows, and whether the insert's are there) is measured on it; `None`:
/// on `img` (the classical backend's, the render with its holes filled).
pub fn insert_ops(
    img: &mut Image,
    rendered: Option<&Image>,
    input: &BackendInput<'_>,
    carry: &mut Carry,
    progress: &mut Progress<'_>,
    stages: &mut Stages,
) -> Result<Option<Rect>> {
    let frame = input.frame;
    let params = input.params;
    let pool = input.pool;
    let (w, h) = (img.width, img.height);

    // The insert's bounding box, shared by harmonization and the shadow.
    let insert = match &frame.insert_mask {
        Some(mask) if params.harmonize || params.contact_shadows => match frame.scan {
            // Found while the mask was prepared.
            Some(scan) => scan.insert,
            None => stages.time("harmonize", || {
                pool.install(|| harmonize::insert_rect(mask, w, h))
            }),
        }
        .map(|rect| (mask, rect)),
        _ => None,
    };
    // Whether harmonization changed the insert's colors noticeably.
    let mut recolored = false;
    let mut scene = SceneLightOnce::carried(carry);
    let light = params
        .light_direction_world(frame.camera.as_ref())
        .filter(|_| params.relight)
        .zip(frame.camera.as_ref())
        .zip(frame.depth.as_deref());
    match insert {
        Some((mask, rect)) if params.harmonize => {
            // Each inserted object (the pixels of one of the host's ids,
            // else a connected part of the mask) gets its own filter,
            // carried from frame to frame by its id, else by where it is.
            // With ids, objects may touch: each one's ring leaves the
            // others out (without ids, objects are apart and their rings
            // are as they always were).
            let ids = frame.insert_id.as_deref();
            let parts = stages.time("harmonize", || {
                pool.install(|| harmonize::objects(mask, ids, rect, w, h))
            });
            let previous = carry
                .values
                .get(TONE_KEY)
                .and_then(|v| harmonize::tracks_from_slice(v))
                .unwrap_or_default();
            // The shading corrections, one per track of `previous`.
            let previous_shades: Vec<relight::Shade> = carry
                .values
                .get(SHADE_KEY)
                .filter(|v| v.len() == 2 * previous.len() && v.iter().all(|x| x.is_finite()))
                .map(|v| {
                    v.chunks(2)
                        .map(|c| relight::Shade {
                            target: c[0],
                            current: c[1],
                        })
                        .collect()
                })
                .unwrap_or_default();
            // The id of each track of `previous` (0 without one).
            let previous_ids: Vec<f32> = carry
                .values
                .get(ID_KEY)
                .filter(|v| v.len() == previous.len() && v.iter().all(|x| x.is_finite()))
                .cloned()
                .unwrap_or_else(|| vec![0.0; previous.len()]);
            // The color matrices from the albedo, one per track of `previous`.
            let previous_matrices: Vec<albedo_tone::ColorMatrix> = carry
                .values
                .get(MATRIX_KEY)
                .filter(|v| v.len() == albedo_tone::ColorMatrix::LEN * previous.len())
                .and_then(|v| {
                    v.chunks(albedo_tone::ColorMatrix::LEN)
                        .map(albedo_tone::ColorMatrix::from_slice)
                        .collect()
                })
                .unwrap_or_default();
            // The albedo and normals the matrices are fitted with, and the
            // scene's light from the background (once for every object).
            let albedo_aovs = match &frame.insert_aovs {
                Some(samples) if params.albedo_tone => Some(albedo_tone::Aovs {
                    samples,
                    coverage: frame.coverage.as_deref(),
                    depth: frame.depth.as_deref(),
                }),
                _ => None,
            };
            // Where the background shows no albedo (a reconstruction, the
            // albedo only on the object), the host's lights, when it gives
            // them: the normals are the host's world-space ones.
            let host_light = || {
                let toward = params.light_direction_world(frame.camera.as_ref())?;
                albedo_tone::Light::given(
                    params.ambient_color?,
                    params.light_color?,
                    toward.as_vec3().to_array(),
                )
            };
            let albedo_light = albedo_aovs.as_ref().and_then(|aovs| {
                stages.time("harmonize", || {
                    pool.install(|| albedo_tone::light(img, aovs, mask))
                        .or_else(host_light)
                        .map(|light| (aovs, light))
                })
            });
            let mut matrices = Vec::with_capacity(albedo_tone::ColorMatrix::LEN * parts.len());
            let current: Vec<(f32, [f32; 2])> = parts.iter().map(|p| (p.id, p.centroid)).collect();
            let seen: Vec<(f32, [f32; 2])> = previous_ids
                .iter()
                .zip(&previous)
                .map(|(&id, (c, _))| (id, *c))
                .collect();
            let reach = TRACK_REACH * w.max(h) as f32;
            let matched = harmonize::match_objects(&current, &seen, reach);
            let mut tracks = Vec::with_capacity(parts.len());
            let mut track_ids = Vec::with_capacity(parts.len());
            let mut shades = Vec::with_capacity(2 * parts.len());
            for (part, m) in parts.iter().zip(matched) {
                let pmask: &[f32] = if part.mask.is_empty() {
                    mask
                } else {
                    &part.mask
                };
                // The shading toward the host's light first: the color
                // filter then matches the object as the scene lights it.
                let shade = match light {
                    Some(((l, camera), depth)) => stages.time("harmonize", || {
                        // Fitted on a lattice; the normals of every pixel
                        // only for an insert that is corrected.
                        let step = relight::fit_step(part.rect);
                        let lattice = pool.install(|| {
                            relight::facing(depth, pmask, part.rect, step, camera, l, w, h)
                        })?;
                        let fit = pool.install(|| relight::fit(img, pmask, &lattice))?;
                        let ratio = scene_ratio(
                            scene.get(rendered.unwrap_or(img), mask, depth, input, camera, l),
                            params.shadow_strength,
                        );
                        let measured = relight::shade(&fit, ratio);
                        let shade = match m.and_then(|j| previous_shades.get(j)) {
                            Some(p) => p.toward(&measured, 1.0 - params.temporal_blend),
                            None => measured,
                        };
                        if !shade.is_identity() {
                            let full = match step {
                                1 => lattice,
                                _ => pool.install(|| {
                                    relight::facing(depth, pmask, part.rect, 1, camera, l, w, h)
                                })?,
                            };
                            pool.install(|| {
                                relight::apply(img, pmask, &full, fit.mean_facing, &shade)
                            });
                        }
                        Some(shade)
                    }),
                    None => None,
                };
                // Without `match_tone` the object keeps its colors (the
                // identity filter), and its track carries the shading.
                let estimate = if params.match_tone {
                    stages.time("harmonize", || {
                        pool.install(|| {
                            harmonize::estimate_among(
                                img,
                                pmask,
                                ids.map(|_| &mask[..]),
                                part.rect,
                                frame.coverage.as_deref(),
                                frame.depth.as_deref(),
                            )
                        })
                    })
                } else {
                    Some(harmonize::Tone::IDENTITY)
                };
                let tone = match (m.map(|j| previous[j].1), estimate) {
                    (Some(p), Some(e)) => Some(p.toward(&e, 1.0 - params.temporal_blend)),
                    (p, e) => e.or(p),
                };
                if let Some(tone) = tone {
                    stages.time("harmonize", || {
                        pool.install(|| harmonize::apply(img, pmask, part.rect, &tone))
                    });
                    // Last, on the shaded and filtered colors: the matrix
                    // from the albedo (the identity without one).
                    let previous_matrix = m.and_then(|j| previous_matrices.get(j)).copied();
                    let matrix = albedo_light.as_ref().and_then(|(aovs, light)| {
                        stages.time("harmonize", || {
                            albedo_tone::estimate(img, aovs, light, pmask, part.rect)
                        })
                    });
                    let matrix = match (previous_matrix, matrix) {
                        (Some(p), Some(e)) => p.toward(&e.matrix, 1.0 - params.temporal_blend),
                        (p, e) => e
                            .map(|e| e.matrix)
                            .or(p)
                            .unwrap_or(albedo_tone::ColorMatrix::IDENTITY),
                    };
                    stages.time("harmonize", || {
                        pool.install(|| albedo_tone::apply(img, pmask, part.rect, &matrix))
                    });
                    matrices.extend(matrix.to_vec());
                    tracks.push((part.centroid, tone));
                    track_ids.push(part.id);
                    let shade = shade.unwrap_or(relight::Shade::IDENTITY);
                    shades.extend([shade.target, shade.current]);
                    recolored |= !tone.is_near_identity(RECOLOR_TOLERANCE)
                        || shade.stops().abs() > RECOLOR_TOLERANCE
                        || !matrix.is_near_identity(RECOLOR_TOLERANCE);
                }
            }
            carry
                .values
                .insert(TONE_KEY.to_string(), harmonize::tracks_to_vec(&tracks));
            carry.values.insert(SHADE_KEY.to_string(), shades);
            carry.values.insert(MATRIX_KEY.to_string(), matrices);
            if track_ids.iter().any(|&id| id > 0.0) {
                carry.values.insert(ID_KEY.to_string(), track_ids);
            } else {
                carry.values.remove(ID_KEY);
            }
        }
        _ => {
            carry.values.remove(TONE_KEY);
            carry.values.remove(SHADE_KEY);
            carry.values.remove(MATRIX_KEY);
            carry.values.remove(ID_KEY);
        }
    }
    progress.report(0.6)?;

    // What is stabilized in a frame without holes: a recolored insert and a
    // margin around it (its harmonized edge). Not an insert left as it came
    // (a correctly lit one keeps its detail), nor the shadows: the ground
    // they darken is the render's own texture, which a resampled history
    // only softens (0.9 dB overall on the out-of-domain shadow sequence).
    let changed = insert
        .filter(|_| recolored)
        .map(|(_, rect)| rect.expand(INSERT_MARGIN, w, h));
    if params.contact_shadows && params.shadow_strength > 0.0 {
        if let (Some((mask, rect)), Some(depth)) = (insert, &frame.depth) {
            stages.time("shadow", || {
                pool.install(|| shadows(img, rendered, mask, rect, depth, input, &mut scene, carry))
            });
        } else {
            carry.values.remove(SHADOW_KEY);
        }
    } else {
        carry.values.remove(SHADOW_KEY);
    }
    scene.store(carry);
    progress.report(0.7)?;
    Ok(changed)
}

/// The stabilization step of [`run_ops`] alone (when the session's
/// `stabilize` is on, `temporal_blend` above 0 and there is history): `img`
/// blended with history frame 0, clamped to the local color range. The
/// neural backend runs it on its output for models that ask for it
/// (manifest `stabilize`). It is the last change to `img`: the same pass
/// writes the history's copy of the result when the session hands over its
/// buffer (`input.kept`).
///
/// `area`: only its pixels are blended (`None`: the whole frame; an empty
/// rectangle: none, the pass still records the scene probe and the kept copy).
pub fn stabilize_with_history(
    img: &mut Image,
    input: &BackendInput<'_>,
    stages: &mut Stages,
    area: Option<Rect>,
) {
    let (params, history) = (input.params, input.history);
    if params.stabilize && params.temporal_blend > 0.0 && !history.is_empty() {
        // History frame 0 is reprojected row by row inside the blend pass
        // (the time is the stabilize stage's), never as a whole frame.
        stages.time("stabilize", || {
            let mut kept = input.kept.and_then(KeptColor::take);
            let fits = kept
                .as_ref()
                .is_some_and(|k| (k.width, k.height) == (img.width, img.height));
            input.pool.install(|| {
                stabilize::stabilize_rows_in(
                    img,
                    params.temporal_blend,
                    kept.as_mut().filter(|_| fits).map(|k| &mut k.data[..]),
                    &stabilize::ViewRows {
                        view: history,
                        k: 0,
                        probe: input.scene_probe,
                    },
                    area.unwrap_or(Rect::full(img.width, img.height)),
                )
            });
            if let (Some(slot), Some(k)) = (input.kept, kept) {
                slot.give(k, fits);
            }
        });
    }
}

impl Backend for Classical {
    fn name(&self) -> &str {
        "classical"
    }

    fn uses_normals(&self) -> bool {
        false
    }

    /// The push-pull pyramid of the hole fill (4 planes and a weight over
    /// at most the frame, a third of it per level below) and the
    /// harmonization's and shadow's grids.
    fn working_planes(&self, _params: &crate::params::Params) -> usize {
        3
    }

    /// The stabilization pass reprojects history frame 0 over every row.
    fn records_scene_probe(&self, params: &crate::params::Params) -> bool {
        params.stabilize && params.temporal_blend > 0.0
    }

    fn process(
        &self,
        input: &BackendInput<'_>,
        carry: &mut Carry,
        progress: &mut Progress<'_>,
        stages: &mut Stages,
    ) -> Result<Image> {
        let img = stages.time("prepare", || -> Result<Image> {
            let f = input.frame;
            let mut img = match input.history.recycler() {
                Some(r) => r.try_image(f.width(), f.height(), 4)?,
                None => Image::try_zeros(f.width(), f.height(), 4)?,
            };
            input.pool.install(|| rgba_into(f, &mut img));
            Ok(img)
        })?;
        self.process_in_place(img, input, carry, progress, stages)
    }

    fn works_in_place(&self) -> bool {
        true
    }

    /// The operations run on the handed-over color itself.
    fn process_in_place(
        &self,
        mut img: Image,
        input: &BackendInput<'_>,
        carry: &mut Carry,
        progress: &mut Progress<'_>,
        stages: &mut Stages,
    ) -> Result<Image> {
        progress.report(0.05)?;
        // The image is the frame's color with its coverage as alpha
        // (handed over, or made by `rgba_into`).
        run_ops_on(&mut img, input, carry, progress, stages, true)?;
        Ok(img)
    }
}
