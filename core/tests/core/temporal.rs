//! Temporal state: reprojection with motion vectors and with depth + cameras,
//! validity masks (out of frame, disocclusions), determinism across thread
//! counts, scene-cut detection.
//!
//! The frames are rendered here analytically: a textured plane (z = 0, bounded,
//! sky around it) with a textured square occluder in front (z = -3), seen by a
//! camera that moves sideways, forward and turns. Depth, motion vectors and
//! which pixels were visible in the previous frame are exact.

use glam::{DVec2, DVec3, Vec3};
use harmonizer_core::backend::classical::Classical;
use harmonizer_core::backend::{Backend, BackendInput, Carry, Progress, Stages};
use harmonizer_core::frame::Recycler;
use harmonizer_core::frame::{Camera, FrameInput, ImageView, PreparedFrame, RgbaImage};
use harmonizer_core::temporal::scene_cut::{
    current_samples, geometric, history_samples, score_samples,
};
use harmonizer_core::temporal::{
    is_scene_cut, scene_cut_score, History, HistoryFrame, HistoryView, Lattice, LatticeRows,
    ReprojectionMode,
};
use harmonizer_core::{DepthKind, Image, Params};

/// Which textures the scene has (1 is an unrelated scene: a cut).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Look {
    /// The main scene.
    Main,
    /// Unrelated content.
    Other,
}

/// One analytically rendered frame (interleaved buffers as a host gives them).
pub struct Rendered {
    pub w: usize,
    pub h: usize,
    /// RGB, interleaved.
    pub color: Vec<f32>,
    /// Planar depth (1e10 for sky).
    pub depth: Vec<f32>,
    /// Motion vectors to the previous camera (x right, y down), interleaved.
    pub motion: Vec<f32>,
    pub camera: Camera,
    /// World point seen by each pixel (`None`: sky), and its direction.
    pub hit: Vec<Option<DVec3>>,
    pub dir: Vec<DVec3>,
}

impl Rendered {
    /// The host view of this frame; `motion` and `depth` optional.
    pub fn input(&self, motion: bool, depth: bool, camera: bool, index: i64) -> FrameInput<'_> {
        let mut f =
            FrameInput::new(ImageView::from_f32("color", &self.color, self.w, self.h, 3).unwrap());
        if motion {
            f.motion =
                Some(ImageView::from_f32("motion", &self.motion, self.w, self.h, 2).unwrap());
        }
        if depth {
            f.depth = Some(ImageView::from_f32("depth", &self.depth, self.w, self.h, 1).unwrap());
        }
        if camera {
            f.camera = Some(self.camera);
        }
        f.frame_index = Some(index);
        f
    }

    /// Multiplies the color (exposure flicker).
    pub fn exposed(mut self, gain: f32) -> Rendered {
        self.color.iter_mut().for_each(|v| *v *= gain);
        self
    }
}

/// The camera of frame `t` (moves right, up, forward and turns a little).
pub fn camera_at(t: f32, w: usize, h: usize) -> Camera {
    let eye = Vec3::new(-1.5 + 0.8 * t, 0.3 + 0.1 * t, -9.0 + 0.25 * t);
    let target = Vec3::new(-0.5 + 0.3 * t, 0.0, 0.0);
    Camera::look_at(eye, target, 0.75, w as f32 / h as f32)
}

fn eye_of(cam: &Camera) -> DVec3 {
    (cam.world_to_camera.as_dmat4().inverse() * glam::DVec4::W).truncate()
}

fn texture(look: Look, occluder: bool, p: DVec3) -> [f32; 3] {
    let (x, y) = (p.x, p.y);
    let c = match (look, occluder) {
        (Look::Main, false) => [
            0.5 + 0.3 * (2.1 * x + 0.5).sin() * (1.7 * y).cos(),
            0.4 + 0.25 * (1.3 * x - 2.2 * y).sin(),
            0.3 + 0.2 * (2.7 * x + 0.9 * y).cos(),
        ],
        (Look::Main, true) => [
            0.9,
            0.2 + 0.1 * (5.0 * x).sin(),
            0.1 + 0.08 * (5.0 * y).cos(),
        ],
        (Look::Other, false) => [
            0.1 + 0.08 * (3.3 * y).sin(),
            0.6 + 0.35 * (4.1 * x + 1.0).cos() * (2.9 * y).sin(),
            0.9 + 0.5 * (3.7 * x - 1.1 * y).sin(),
        ],
        (Look::Other, true) => [0.05, 0.7, 0.2 + 0.1 * (4.0 * x).sin()],
    };
    c.map(|v| v as f32)
}

fn sky(look: Look, d: DVec3) -> [f32; 3] {
    match look {
        Look::Main => [(0.3 + 0.2 * d.x) as f32, (0.4 + 0.2 * d.y) as f32, 0.8],
        Look::Other => [0.05, (0.1 + 0.1 * d.x) as f32, (0.2 + 0.2 * d.y) as f32],
    }
}

/// Ray-casts `cam` (with the previous camera `prev` for motion vectors).
pub fn render(look: Look, cam: Camera, prev: Camera, w: usize, h: usize) -> Rendered {
    let un = cam.unprojector(w, h);
    let eye = eye_of(&cam);
    let prev_eye = eye_of(&prev);
    let n = w * h;
    let mut r = Rendered {
        w,
        h,
        color: vec![0.0; 3 * n],
        depth: vec![1e10; n],
        motion: vec![0.0; 2 * n],
        camera: cam,
        hit: vec![None; n],
        dir: vec![DVec3::ZERO; n],
    };
    for i in 0..h {
        for j in 0..w {
            let px = DVec2::new(j as f64 + 0.5, i as f64 + 0.5);
            let p = i * w + j;
            // Direction with planar depth 1: the ray parameter is the planar depth.
            let dir = un.world_point(px, 1.0) - eye;
            r.dir[p] = dir;
            let mut best: Option<(f64, bool)> = None;
            for (z, half_x, half_y, occ) in [(0.0, 7.0, 4.5, false), (-3.0, 0.8, 0.8, true)] {
                let t = (z - eye.z) / dir.z;
                if t <= 0.0 {
                    continue;
                }
                let q = eye + t * dir;
                if q.x.abs() < half_x && q.y.abs() < half_y && best.is_none_or(|b| t < b.0) {
                    best = Some((t, occ));
                }
            }
            let seen = match best {
                Some((t, occ)) => {
                    let q = eye + t * dir;
                    r.depth[p] = t as f32;
                    r.hit[p] = Some(q);
                    r.color[3 * p..3 * p + 3].copy_from_slice(&texture(look, occ, q));
                    q
                }
                None => {
                    r.color[3 * p..3 * p + 3].copy_from_slice(&sky(look, dir.normalize()));
                    prev_eye + dir.normalize() * 1e7
                }
            };
            let (pp, _) = prev
                .project(seen, w, h)
                .expect("in front of the previous camera");
            r.motion[2 * p] = (pp.x - px.x) as f32;
            r.motion[2 * p + 1] = (pp.y - px.y) as f32;
        }
    }
    r
}

/// Frames `t0..=t1` of the main scene at `w` x `h`.
pub fn sequence(t0: i64, t1: i64, w: usize, h: usize) -> Vec<Rendered> {
    (t0..=t1)
        .map(|t| {
            render(
                Look::Main,
                camera_at(t as f32, w, h),
                camera_at(t as f32 - 1.0, w, h),
                w,
                h,
            )
        })
        .collect()
}

/// The frame as a history entry (alpha 1), all AOVs kept.
pub fn history_frame(r: &Rendered, index: i64) -> HistoryFrame {
    let f =
        PreparedFrame::from_input(&r.input(true, true, true, index), DepthKind::Planar).unwrap();
    let n = r.w * r.h;
    let mut color = Image::filled(r.w, r.h, 4, 1.0);
    color.data[..3 * n].copy_from_slice(&f.color.data);
    HistoryFrame {
        color: RgbaImage::from_planes(&color, None),
        depth: f.depth,
        motion: f.motion,
        camera: f.camera,
        frame_index: Some(index),
    }
}

fn pool(threads: usize) -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap()
}

/// True when the surface seen by `cur` pixel `p` is visible in frame `past`
/// (in frame, not hidden), measured exactly, and not within `margin` pixels of
/// a place where that changes.
fn truly_visible(cur: &Rendered, p: usize, past: &Rendered) -> Option<(bool, bool)> {
    let (w, h) = (cur.w, cur.h);
    let target = match cur.hit[p] {
        Some(q) => q,
        None => eye_of(&past.camera) + cur.dir[p].normalize() * 1e7,
    };
    let (pp, d) = past.camera.project(target, w, h)?;
    let margin = 2.0;
    if pp.x < margin || pp.y < margin || pp.x > w as f64 - margin || pp.y > h as f64 - margin {
        return if pp.x < -margin
            || pp.y < -margin
            || pp.x > w as f64 + margin
            || pp.y > h as f64 + margin
        {
            Some((false, false))
        } else {
            None
        };
    }
    // Visible when the nearby pixels of `past` all see this depth (or all sky).
    let (cx, cy) = (pp.x.floor() as i64, pp.y.floor() as i64);
    let mut same = 0;
    let mut other = 0;
    for y in cy - 1..=cy + 1 {
        for x in cx - 1..=cx + 1 {
            let q = y as usize * w + x as usize;
            let pd = past.depth[q] as f64;
            let ok = match cur.hit[p] {
                Some(_) => (pd - d).abs() < 0.02 * d,
                None => pd >= 1e9,
            };
            if ok {
                same += 1
            } else {
                other += 1
            }
        }
    }
    match (same, other) {
        (_, 0) => Some((true, true)),
        (0, _) => Some((false, true)),
        _ => None,
    }
}

struct Check {
    visible: usize,
    visible_valid: usize,
    hidden: usize,
    hidden_valid: usize,
    /// Hidden although in frame (behind the occluder in the past frame).
    occluded: usize,
    mean_err: f64,
    max_err: f32,
}

/// Compares history frame `k` reprojected into `cur` with `cur`'s color.
fn check(view: &HistoryView<'_>, k: usize, cur: &Rendered, past: &Rendered) -> Check {
    let rep = view.reproject(k);
    let n = cur.w * cur.h;
    let mut c = Check {
        visible: 0,
        visible_valid: 0,
        hidden: 0,
        hidden_valid: 0,
        occluded: 0,
        mean_err: 0.0,
        max_err: 0.0,
    };
    for p in 0..n {
        match truly_visible(cur, p, past) {
            Some((true, _)) => {
                c.visible += 1;
                if rep.valid[p] >= 0.999 {
                    c.visible_valid += 1;
                    for ch in 0..3 {
                        let e = (rep.color.data[ch * n + p] - cur.color[3 * p + ch]).abs();
                        c.mean_err += e as f64;
                        c.max_err = c.max_err.max(e);
                    }
                }
            }
            Some((false, in_frame)) => {
                c.hidden += 1;
                c.occluded += usize::from(in_frame);
                if rep.valid[p] > 0.5 {
                    c.hidden_valid += 1;
                }
            }
            None => {}
        }
    }
    c.mean_err /= (3 * c.visible_valid.max(1)) as f64;
    c
}

const W: usize = 192;
const H: usize = 108;

/// Stated tolerances (color values around 0.1..0.9): mean abs error of valid
/// pixels <= 0.001, max <= 0.005; >= 97 % of truly visible pixels valid;
/// <= 2 % of truly hidden ones (out of frame or disoccluded) valid.
fn assert_check(c: &Check, what: &str) {
    eprintln!(
        "{what}: visible {} (valid {}), hidden {} (valid {}, disoccluded in frame {}), mean err {:.5}, max err {:.4}",
        c.visible, c.visible_valid, c.hidden, c.hidden_valid, c.occluded, c.mean_err, c.max_err
    );
    assert!(
        c.occluded >= 50,
        "{what}: the scene must disocclude something ({} px)",
        c.occluded
    );
    assert!(
        c.visible_valid as f64 >= 0.97 * c.visible as f64,
        "{what}: visible pixels marked invalid"
    );
    assert!(
        c.hidden_valid as f64 <= 0.02 * c.hidden as f64,
        "{what}: disoccluded pixels marked valid"
    );
    assert!(c.mean_err <= 0.001, "{what}: mean error {}", c.mean_err);
    assert!(c.max_err <= 0.005, "{what}: max error {}", c.max_err);
}

fn history_of(frames: &[Rendered], first_index: i64) -> History {
    let mut hist = History::default();
    for (i, f) in frames.iter().enumerate() {
        hist.push(history_frame(f, first_index + i as i64), 8);
    }
    hist
}

#[test]
fn motion_vectors_reproject_previous_frame_within_tolerance() {
    let seq = sequence(0, 4, W, H);
    let cur = &seq[4];
    let hist = history_of(&seq[..4], 0);
    let frame =
        PreparedFrame::from_input(&cur.input(true, true, true, 4), DepthKind::Planar).unwrap();
    let pool = pool(2);
    let view = HistoryView::new(&hist, &frame, 4, &pool);
    assert_eq!(view.len(), 4);
    for k in 0..4 {
        assert_eq!(view.mode(k), ReprojectionMode::MotionVectors);
        // History frame k is seq[3 - k].
        let c = check(&view, k, cur, &seq[3 - k]);
        assert_check(&c, &format!("motion k={k}"));
    }
}

#[test]
fn depth_and_cameras_reproject_a_static_scene_within_tolerance() {
    let seq = sequence(0, 4, W, H);
    let cur = &seq[4];
    let hist = history_of(&seq[..4], 0);
    let frame =
        PreparedFrame::from_input(&cur.input(false, true, true, 4), DepthKind::Planar).unwrap();
    let pool = pool(2);
    let view = HistoryView::new(&hist, &frame, 4, &pool);
    for k in [0, 3] {
        assert_eq!(view.mode(k), ReprojectionMode::DepthCamera);
        let c = check(&view, k, cur, &seq[3 - k]);
        assert_check(&c, &format!("depth+camera k={k}"));
    }
}

#[test]
fn disocclusions_need_the_depth_test() {
    let seq = sequence(0, 1, W, H);
    let mut hist = History::default();
    let mut hf = history_frame(&seq[0], 0);
    hf.depth = None;
    hist.push(hf, 4);
    let frame =
        PreparedFrame::from_input(&seq[1].input(true, true, true, 1), DepthKind::Planar).unwrap();
    let pool = pool(1);
    let view = HistoryView::new(&hist, &frame, 4, &pool);
    let c = check(&view, 0, &seq[1], &seq[0]);
    assert!(
        c.occluded >= 50 && c.hidden_valid >= c.occluded / 2,
        "without depth the occluded pixels look valid"
    );
}

#[test]
fn without_depth_validity_is_the_frame_test_only() {
    let seq = sequence(0, 1, W, H);
    let mut hist = History::default();
    let mut hf = history_frame(&seq[0], 0);
    hf.depth = None;
    hist.push(hf, 4);
    let frame =
        PreparedFrame::from_input(&seq[1].input(true, false, true, 1), DepthKind::Planar).unwrap();
    let pool = pool(1);
    let view = HistoryView::new(&hist, &frame, 4, &pool);
    let rep = view.reproject(0);
    let n = W * H;
    let mut in_frame = 0;
    for p in 0..n {
        let (i, j) = (p / W, p % W);
        let x = j as f32 + 0.5 + seq[1].motion[2 * p];
        let y = i as f32 + 0.5 + seq[1].motion[2 * p + 1];
        let inside = x >= 0.5 && y >= 0.5 && x <= W as f32 - 0.5 && y <= H as f32 - 0.5;
        let outside = x < -0.5 || y < -0.5 || x > W as f32 + 0.5 || y > H as f32 + 0.5;
        if inside {
            in_frame += 1;
            assert!(
                rep.valid[p] > 0.999,
                "pixel {p} maps inside ({x}, {y}): valid {}",
                rep.valid[p]
            );
        }
        if outside {
            assert_eq!(rep.valid[p], 0.0, "pixel {p} maps outside ({x}, {y})");
            assert_eq!(rep.color.data[p], 0.0);
        }
    }
    assert!(in_frame > n / 2);
}

#[test]
fn reprojection_is_bit_identical_for_1_and_2_threads() {
    let seq = sequence(0, 3, W, H);
    let hist = history_of(&seq[..3], 0);
    for motion in [true, false] {
        let frame =
            PreparedFrame::from_input(&seq[3].input(motion, true, true, 3), DepthKind::Planar)
                .unwrap();
        let (p1, p2) = (pool(1), pool(2));
        let v1 = HistoryView::new(&hist, &frame, 3, &p1);
        let v2 = HistoryView::new(&hist, &frame, 3, &p2);
        for k in [2, 0, 1] {
            let (a, b) = (v1.reproject(k), v2.reproject(k));
            assert!(a
                .color
                .data
                .iter()
                .zip(&b.color.data)
                .all(|(x, y)| x.to_bits() == y.to_bits()));
            assert!(a
                .valid
                .iter()
                .zip(&b.valid)
                .all(|(x, y)| x.to_bits() == y.to_bits()));
        }
    }
}

#[test]
fn history_of_another_size_is_not_used() {
    let small = sequence(0, 0, 96, 54);
    let big = sequence(1, 1, W, H);
    let hist = history_of(&small, 0);
    let frame =
        PreparedFrame::from_input(&big[0].input(true, true, true, 1), DepthKind::Planar).unwrap();
    let pool = pool(1);
    assert!(HistoryView::new(&hist, &frame, 4, &pool).is_empty());
}

#[test]
fn identity_and_unavailable_modes() {
    let seq = sequence(0, 1, W, H);
    let pool = pool(1);
    // Color only: the camera is taken as static.
    let mut hist = History::default();
    let mut hf = history_frame(&seq[0], 0);
    (hf.depth, hf.motion, hf.camera) = (None, None, None);
    hist.push(hf.clone(), 4);
    let frame = PreparedFrame::from_input(&seq[1].input(false, false, false, 1), DepthKind::Planar)
        .unwrap();
    let view = HistoryView::new(&hist, &frame, 4, &pool);
    assert_eq!(view.mode(0), ReprojectionMode::Identity);
    assert_eq!(view.reproject(0).color, hf.color.to_planes());
    // Different cameras and no depth nor motion: nothing can be aligned.
    let mut hist = History::default();
    hf.camera = Some(seq[0].camera);
    hist.push(hf, 4);
    let frame =
        PreparedFrame::from_input(&seq[1].input(false, false, true, 1), DepthKind::Planar).unwrap();
    let view = HistoryView::new(&hist, &frame, 4, &pool);
    assert_eq!(view.mode(0), ReprojectionMode::Unavailable);
    assert!(view.reproject(0).valid.iter().all(|&v| v == 0.0));
}

/// Which AOVs the scene-cut tests give (motion, depth, camera): every
/// reprojection mode.
const AOV_SETS: [(bool, bool, bool); 4] = [
    (true, true, true),
    (false, true, true),
    (true, false, false),
    (false, false, false),
];

/// A history of `prev` alone, with only the AOVs asked for.
fn history_with(prev: &Rendered, motion: bool, depth: bool, camera: bool) -> History {
    let mut hist = History::default();
    let mut hf = history_frame(prev, 0);
    hf.depth = hf.depth.filter(|_| depth);
    hf.motion = hf.motion.filter(|_| motion);
    hf.camera = hf.camera.filter(|_| camera);
    hist.push(hf, 4);
    hist
}

fn cut_check(
    cur: Rendered,
    prev: &Rendered,
    motion: bool,
    depth: bool,
    camera: bool,
) -> (bool, String) {
    let hist = history_with(prev, motion, depth, camera);
    let frame =
        PreparedFrame::from_input(&cur.input(motion, depth, camera, 1), DepthKind::Planar).unwrap();
    let pool = pool(2);
    let view = HistoryView::new(&hist, &frame, 4, &pool);
    let score = scene_cut_score(&view, &frame).unwrap();
    (is_scene_cut(&view, &frame, 0.6), format!("{score:?}"))
}

#[test]
fn scene_cut_fires_on_a_cut_and_not_on_exposure_flicker_or_camera_motion() {
    let prev = sequence(0, 0, W, H).remove(0);
    let cam = camera_at(1.0, W, H);
    let prev_cam = camera_at(0.0, W, H);
    for (motion, depth, camera) in AOV_SETS {
        let what = format!("motion {motion}, depth {depth}, camera {camera}");
        for gain in [1.0, 1.25, 0.75] {
            let cur = render(Look::Main, cam, prev_cam, W, H).exposed(gain);
            let (cut, score) = cut_check(cur, &prev, motion, depth, camera);
            assert!(!cut, "{what}: gain {gain} is not a cut: {score}");
        }
        // Unrelated content from another viewpoint.
        let other_cam = Camera::look_at(
            Vec3::new(3.0, 1.0, -6.0),
            Vec3::new(1.0, 0.5, 0.0),
            0.9,
            W as f32 / H as f32,
        );
        let cur = render(Look::Other, other_cam, other_cam, W, H);
        let (cut, score) = cut_check(cur, &prev, motion, depth, camera);
        assert!(cut, "{what}: a cut must fire: {score}");
        // Same viewpoint and geometry, unrelated textures.
        let cur = render(Look::Other, cam, prev_cam, W, H);
        let (cut, score) = cut_check(cur, &prev, motion, depth, camera);
        assert!(cut, "{what}: a cut (same geometry) must fire: {score}");
    }
}

/// The scene-cut detector's samples as the session takes them when the
/// classical backend runs before the detector (the current frame while it
/// is prepared, history frame 0 from the stabilization pass) are the
/// detector's own bit for bit, in every reprojection mode, so a cut is
/// decided the same wherever they were taken (issue 2).
#[test]
fn lattice_samples_from_prepare_and_stabilization_are_the_detectors() {
    let seq = sequence(0, 1, W, H);
    let pool = pool(2);
    let n = W * H;
    // Holes and partly covered pixels, so the coverage weights count.
    let cov: Vec<f32> = (0..n)
        .map(|p| match p % 7 {
            0 => 0.0,
            1 => 0.5,
            _ => 1.0,
        })
        .collect();
    let bits = |v: &[[f32; 4]]| v.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
    let lattice = Lattice::new(W, H);
    assert!(lattice.len() > 1000, "{} samples", lattice.len());
    for (motion, depth, camera) in AOV_SETS {
        let what = format!("motion {motion}, depth {depth}, camera {camera}");
        let hist = history_with(&seq[0], motion, depth, camera);
        let mut input = seq[1].input(motion, depth, camera, 1);
        input.coverage = Some(ImageView::from_f32("coverage", &cov, W, H, 1).unwrap());
        let rec = Recycler::new();
        let mut frame =
            PreparedFrame::from_input_recycled(&input, DepthKind::Planar, &pool, &rec, false, true)
                .unwrap();
        // The current frame: kept while prepared = read from the planes.
        let kept = frame.scene_samples.take().expect("samples kept");
        assert_eq!(
            bits(&kept),
            bits(&current_samples(&lattice, &frame)),
            "{what}"
        );
        frame.scene_samples = Some(kept);
        let (want, want_score) = {
            let view = HistoryView::new(&hist, &frame, 4, &pool);
            let score = scene_cut_score(&view, &frame).unwrap();
            (history_samples(&lattice, &view), format!("{score:?}"))
        };
        assert!(
            want.iter().any(|s| s[3] > 0.0),
            "{what}: some history valid"
        );
        // History frame 0 as the stabilization pass records it.
        let color = frame.take_color();
        let view = HistoryView::new(&hist, &frame, 4, &pool);
        let probe = LatticeRows::new(&lattice);
        let params = Params::default();
        let input = BackendInput {
            frame: &frame,
            history: &view,
            params: &params,
            pool: &pool,
            kept: None,
            scene_probe: Some(&probe),
            memory_budget: usize::MAX,
        };
        assert!(Classical.records_scene_probe(&params));
        Classical
            .process_in_place(
                color,
                &input,
                &mut Carry::default(),
                &mut Progress::new(None),
                &mut Stages::default(),
            )
            .unwrap();
        let got = probe.finish().expect("every lattice row recorded");
        assert_eq!(bits(&got), bits(&want), "{what}");
        let cur = frame.scene_samples.as_deref().unwrap();
        let score = score_samples(&lattice, cur, &got, geometric(&view));
        assert_eq!(format!("{score:?}"), want_score, "{what}");
    }
}

#[test]
fn motion_vectors_are_not_chained_across_a_frame_gap() {
    let seq = sequence(0, 3, W, H);
    let mut hist = History::default();
    hist.push(history_frame(&seq[0], 0), 4);
    // Frame 3's motion vectors reach frame 2, not frame 0: depth + cameras align instead.
    let frame =
        PreparedFrame::from_input(&seq[3].input(true, true, true, 3), DepthKind::Planar).unwrap();
    let pool = pool(2);
    let view = HistoryView::new(&hist, &frame, 4, &pool);
    assert_eq!(view.mode(0), ReprojectionMode::DepthCamera);
    let c = check(&view, 0, &seq[3], &seq[0]);
    assert_check(&c, "gap, depth+camera");
}
