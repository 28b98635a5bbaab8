//! The classical backend end to end through a `Session` (real history and
//! reprojection): holes filled (PSNR in the holes against ground truth), a
//! tone-shifted insert moved toward its true colors with smoothed
//! parameters, a contact shadow under the insert only, flicker lowered
//! without ghosting a moving object, and thread-count independence.
//!
//! The frames are made here: a static camera over a textured wall (far) and
//! floor (depth falling toward the bottom), optionally a box standing on the
//! floor (the insert), round holes with soft borders, per-pixel flicker.

use std::sync::Arc;

use harmonizer_core::backend::classical::{Classical, HISTORY_REFRESH, TONE_KEY};
use harmonizer_core::backend::{Backend, BackendInput, Carry, Progress, Stages};
use harmonizer_core::frame::{FrameInput, ImageView, PreparedFrame};
use harmonizer_core::ops::harmonize;
use harmonizer_core::temporal::{History, HistoryView};
use harmonizer_core::{DepthKind, Device, DeviceOptions, Image, ParamValue, Params, Session};

const W: usize = 160;
const H: usize = 96;
const HORIZON: usize = 40;

fn hash(i: u64) -> f32 {
    let mut z = i.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
}

/// The background's true color at a pixel.
fn background(x: usize, y: usize) -> [f32; 3] {
    let (xf, yf) = (x as f32, y as f32);
    let t = 0.5 + 0.3 * (xf * 0.13).sin() * (yf * 0.11).cos();
    if y < HORIZON {
        [0.55 * t, 0.5 * t, 0.45 * t]
    } else {
        let u = 0.5 + 0.2 * (xf * 0.07 + yf * 0.05).sin();
        [0.5 * u + 0.1 * t, 0.45 * u, 0.35 * u + 0.05 * t]
    }
}

fn floor_depth(y: usize) -> f32 {
    if y < HORIZON {
        50.0
    } else {
        2.0 + 200.0 / (y - HORIZON + 20) as f32
    }
}

/// The insert: a box standing on the floor, columns `x0..x0+36`, rows 45..80.
#[derive(Clone, Copy)]
struct Insert {
    x0: usize,
    /// Render mismatch: (gain, blue gain, contrast) applied to the true colors.
    shift: (f32, f32, f32),
}

const BOX_Y: (usize, usize) = (45, 80);

impl Insert {
    fn covers(&self, x: usize, y: usize) -> bool {
        (self.x0..self.x0 + 36).contains(&x) && (BOX_Y.0..BOX_Y.1).contains(&y)
    }
    /// True color: the same grade as the floor with its own pattern.
    fn truth(&self, x: usize, y: usize) -> [f32; 3] {
        let t = 0.45 + 0.25 * (((x - self.x0) as f32) * 0.4).sin() * ((y as f32) * 0.3).cos();
        [0.5 * t + 0.05, 0.45 * t, 0.35 * t + 0.02]
    }
    fn rendered(&self, x: usize, y: usize) -> [f32; 3] {
        let (gain, blue, contrast) = self.shift;
        let c = self.truth(x, y);
        let f = |v: f32| 0.3 * (v / 0.3).powf(contrast);
        [gain * f(c[0]), gain * f(c[1]), gain * blue * f(c[2])]
    }
}

/// One rendered frame and its ground truth (interleaved host buffers).
struct Frame {
    color: Vec<f32>,
    truth: Vec<f32>,
    coverage: Vec<f32>,
    depth: Vec<f32>,
    motion: Vec<f32>,
    mask: Vec<f32>,
    insert: Option<Insert>,
    /// Where the truth is the background and was in the previous frame too.
    steady: Vec<bool>,
}

#[derive(Clone, Copy, Default)]
struct Look {
    insert: Option<Insert>,
    /// Box x position in the previous frame (for motion vectors and steadiness).
    prev_x0: Option<usize>,
    /// Hole centres (radius 6, soft 2-pixel border).
    holes: &'static [(f32, f32)],
    /// Per-pixel multiplicative flicker amplitude and the frame's seed.
    flicker: f32,
    seed: u64,
}

fn render(look: Look) -> Frame {
    let n = W * H;
    let mut f = Frame {
        color: vec![0.0; 3 * n],
        truth: vec![0.0; 3 * n],
        coverage: vec![1.0; n],
        depth: vec![0.0; n],
        motion: vec![0.0; 2 * n],
        mask: vec![0.0; n],
        insert: look.insert,
        steady: vec![true; n],
    };
    let box_depth = floor_depth(BOX_Y.1 - 1);
    for y in 0..H {
        for x in 0..W {
            let p = y * W + x;
            let mut truth = background(x, y);
            let mut shown = truth;
            f.depth[p] = floor_depth(y);
            if let Some(ins) = look.insert {
                if ins.covers(x, y) {
                    truth = ins.truth(x, y);
                    shown = ins.rendered(x, y);
                    f.mask[p] = 1.0;
                    f.depth[p] = box_depth;
                    f.steady[p] = false;
                    if let Some(px) = look.prev_x0 {
                        f.motion[2 * p] = px as f32 - ins.x0 as f32;
                    }
                }
                if let Some(px) = look.prev_x0 {
                    if (Insert { x0: px, ..ins }).covers(x, y) {
                        f.steady[p] = false;
                    }
                }
            }
            let mut cov: f32 = 1.0;
            for &(cx, cy) in look.holes {
                let d = ((x as f32 + 0.5 - cx).powi(2) + (y as f32 + 0.5 - cy).powi(2)).sqrt();
                cov = cov.min(((d - 6.0) / 2.0).clamp(0.0, 1.0));
            }
            f.coverage[p] = cov;
            let noise = 1.0 + look.flicker * (2.0 * hash(look.seed * 1_000_003 + p as u64) - 1.0);
            for c in 0..3 {
                f.truth[3 * p + c] = truth[c];
                f.color[3 * p + c] = cov * shown[c] * noise;
            }
        }
    }
    f
}

impl Frame {
    fn input(&self, index: i64) -> FrameInput<'_> {
        let mut i = FrameInput::new(ImageView::from_f32("color", &self.color, W, H, 3).unwrap());
        i.coverage = Some(ImageView::from_f32("coverage", &self.coverage, W, H, 1).unwrap());
        i.depth = Some(ImageView::from_f32("depth", &self.depth, W, H, 1).unwrap());
        i.motion = Some(ImageView::from_f32("motion", &self.motion, W, H, 2).unwrap());
        if self.insert.is_some() {
            i.insert_mask = Some(ImageView::from_f32("insert_mask", &self.mask, W, H, 1).unwrap());
        }
        i.frame_index = Some(index);
        i
    }
}

fn device(threads: usize) -> Arc<Device> {
    Device::new(DeviceOptions {
        threads,
        ..DeviceOptions::default()
    })
    .unwrap()
}

fn session(dev: &Arc<Device>, extra: &[(&str, ParamValue)]) -> Session {
    let mut s = Session::new(dev.clone(), Params::default()).unwrap();
    s.set("backend", ParamValue::Str("classical".into()))
        .unwrap();
    for (k, v) in extra {
        s.set(k, v.clone()).unwrap();
    }
    s.commit().unwrap();
    s
}

fn off(names: &[&str]) -> Vec<(&'static str, ParamValue)> {
    ["fill_holes", "harmonize", "contact_shadows", "stabilize"]
        .into_iter()
        .filter(|n| names.contains(n))
        .map(|n| (n, ParamValue::Bool(false)))
        .collect()
}

/// The output's RGB at a pixel (premultiplied; A = 1 in these scenes).
fn rgb(img: &Image, x: usize, y: usize) -> [f32; 3] {
    [img.at(x, y, 0), img.at(x, y, 1), img.at(x, y, 2)]
}

fn psnr_where(
    out: impl Fn(usize, usize, usize) -> f32,
    truth: &[f32],
    sel: impl Fn(usize) -> bool,
) -> f64 {
    let (mut se, mut n) = (0.0f64, 0usize);
    for p in 0..W * H {
        if sel(p) {
            for c in 0..3 {
                let d = (out(p % W, p / W, c) - truth[3 * p + c]) as f64;
                se += d * d;
                n += 1;
            }
        }
    }
    assert!(n > 0, "empty region");
    10.0 * (1.0 / (se / n as f64)).log10()
}

const HOLES: [&[(f32, f32)]; 4] = [
    &[(30.0, 20.0), (100.0, 60.0), (140.0, 85.0)],
    &[(45.0, 25.0), (80.0, 70.0), (20.0, 80.0)],
    &[(60.0, 30.0), (120.0, 20.0), (35.0, 65.0)],
    &[(75.0, 15.0), (10.0, 50.0), (130.0, 55.0)],
];

#[test]
fn holes_are_filled_from_history_then_push_pull() {
    let dev = device(2);
    let mut s = session(&dev, &off(&["harmonize", "contact_shadows", "stabilize"]));
    for (t, holes) in HOLES.iter().enumerate() {
        let f = render(Look {
            holes,
            ..Look::default()
        });
        let (out, report) = s.process(&f.input(t as i64), None).unwrap();
        let in_hole = |p: usize| f.coverage[p] < 1.0;
        let before = psnr_where(|x, y, c| f.color[3 * (y * W + x) + c], &f.truth, in_hole);
        let after = psnr_where(|x, y, c| out.at(x, y, c), &f.truth, in_hole);
        // Thresholds: push-pull alone (frame 0) must reach 20 dB in the holes
        // (soft borders included), history filling of a static view 40 dB, and
        // both at least 10 dB above the input.
        let want = if t == 0 { 20.0 } else { 40.0 };
        assert!(
            after > want && after > before + 10.0,
            "frame {t}: hole PSNR {before:.1} -> {after:.1} dB (want > {want})"
        );
        assert!(
            out.plane(3).iter().all(|&a| a == 1.0),
            "frame {t}: filled pixels have A = 1"
        );
        // Covered pixels are untouched.
        let p = 5 * W + 150;
        assert_eq!(f.coverage[p], 1.0);
        assert_eq!(out.at(150, 5, 0), f.color[3 * p]);
        assert!(
            report.stages.0.iter().any(|(n, _)| n == "inpaint"),
            "{:?}",
            report.stages
        );
        eprintln!("holes frame {t}: PSNR {before:.1} -> {after:.1} dB");
    }
}

/// A reconstruction's frame: a crack one pixel wide (rows 10..60 of
/// column 100) and a wide hole (columns 30..60, rows 20..50), color
/// `gain` times the background.
fn cracked(gain: f32, holes: bool) -> Frame {
    let mut f = render(Look::default());
    for y in 0..H {
        for x in 0..W {
            let p = y * W + x;
            let crack = x == 100 && (10..60).contains(&y);
            let wide = (30..60).contains(&x) && (20..50).contains(&y);
            let cov = if holes && (crack || wide) { 0.0 } else { 1.0 };
            f.coverage[p] = cov;
            for c in 0..3 {
                f.color[3 * p + c] = cov * gain * f.truth[3 * p + c];
            }
        }
    }
    f
}

#[test]
fn thin_cracks_take_their_neighbours_and_wide_holes_the_history() {
    let dev = device(2);
    let mut extra = off(&["harmonize", "contact_shadows", "stabilize"]);
    extra.push(("scene_cut_detection", ParamValue::Bool(false)));
    let mut s = session(&dev, &extra);
    // The history (a previous output) is 20 % darker than the frame now.
    let before = cracked(0.8, false);
    s.process(&before.input(0), None).unwrap();
    let f = cracked(1.0, true);
    let (out, _) = s.process(&f.input(1), None).unwrap();
    // The frame's own fill, without history.
    let (own, _) = session(&dev, &extra).process(&f.input(1), None).unwrap();
    let ratio_of = |img: &Image, x: usize, y: usize| {
        let p = y * W + x;
        (0..3)
            .map(|c| img.at(x, y, c) / f.truth[3 * p + c])
            .sum::<f32>()
            / 3.0
    };
    let ratio = |x: usize, y: usize| ratio_of(&out, x, y);
    // Interpolating the textured background across the crack is off by a
    // few percent; the history would be 20 % off everywhere. (Once the
    // history has filled the wide hole, the crack is a few pixels of the
    // fill's window: the plain fill's sparse evaluation, not the far side.)
    let crack: Vec<f32> = (12..58).map(|y| ratio(100, y)).collect();
    let mean = crack.iter().map(|r| (r - 1.0).abs()).sum::<f32>() / crack.len() as f32;
    assert!(
        mean < 0.04 && crack.iter().all(|&r| r > 0.9),
        "crack: {crack:.3?} of the truth, want the neighbours' (1), not the history's 0.8"
    );
    // The wide hole takes the history, pulled toward the frame's own fill
    // by at most `HISTORY_REFRESH` (issue 22).
    for (x, y) in [(45, 35), (40, 30), (52, 42)] {
        let (r, r0) = (ratio(x, y), ratio_of(&own, x, y));
        assert!(
            (r - 0.8).abs() < 0.02 + HISTORY_REFRESH * (r0 - 0.8).abs(),
            "wide hole ({x}, {y}): {r:.3} of the truth, want the history's 0.8 \
             (the frame's own fill: {r0:.3})"
        );
    }
}

#[test]
fn without_fill_holes_the_holes_stay() {
    let dev = device(2);
    let mut s = session(
        &dev,
        &off(&["fill_holes", "harmonize", "contact_shadows", "stabilize"]),
    );
    let f = render(Look {
        holes: HOLES[0],
        ..Look::default()
    });
    let (out, _) = s.process(&f.input(0), None).unwrap();
    assert_eq!(out.plane(3), &f.coverage[..]);
}

fn log_error(out: &Image, f: &Frame) -> f64 {
    let mut e = 0.0;
    let mut n = 0;
    for p in 0..W * H {
        if f.mask[p] > 0.0 {
            let (x, y) = (p % W, p / W);
            let o = rgb(out, x, y);
            for (c, oc) in o.iter().enumerate() {
                e += ((oc + 1e-3).log2() - (f.truth[3 * p + c] + 1e-3).log2()).abs() as f64;
                n += 1;
            }
        }
    }
    e / n as f64
}

#[test]
fn a_tone_shifted_insert_gets_closer_to_its_true_colors() {
    let dev = device(2);
    let mut params = off(&["contact_shadows", "stabilize"]);
    params.push(("match_tone", ParamValue::Bool(true)));
    let mut s = session(&dev, &params);
    let ins = Insert {
        x0: 60,
        // 3 stops too bright, 2 stops too blue, flatter: a clear mismatch,
        // beyond what the object's own albedo could explain.
        shift: (8.0, 4.0, 0.5),
    };
    let mut errors = Vec::new();
    for t in 0..6 {
        let f = render(Look {
            insert: Some(ins),
            ..Look::default()
        });
        let (out, _) = s.process(&f.input(t), None).unwrap();
        let before = log_error(&f.color_image(), &f);
        let after = log_error(&out, &f);
        errors.push((before, after));
        // Background is not touched by harmonization.
        assert_eq!(out.at(5, 5, 1), f.color[3 * (5 * W + 5) + 1]);
    }
    eprintln!("insert mean |log2 error| per frame (before, after): {errors:?}");
    // Stated threshold: at least 15% less log error on the insert (the
    // correction is conservative: only the excess beyond the albedo dead
    // zones is taken).
    for (t, (b, a)) in errors.iter().enumerate() {
        assert!(a < &(0.85 * b), "frame {t}: {b:.3} -> {a:.3}");
    }
}

/// Regression: a correct insert is left alone. The insert is correctly lit
/// (same light as the floor) and only its albedo differs, saturated yellow
/// or red on a grey-brown floor; harmonization used to pull it toward the
/// floor's colors (a yellow sphere turned nearly grey). Insert PSNR against
/// the truth may drop by at most 0.5 dB with `match_tone`; by default
/// (no tone matching, no light direction to relight by) the insert comes
/// out exactly as it went in.
#[test]
fn correct_insert_is_left_alone() {
    let dev = device(2);
    let ins = Insert {
        x0: 60,
        shift: (1.0, 1.0, 1.0),
    };
    for (albedo, match_tone) in [
        ([1.6, 1.2, 0.1], true),
        ([1.5, 0.15, 0.12], true),
        ([1.6, 1.2, 0.1], false),
        ([1.5, 0.15, 0.12], false),
    ] {
        let mut params = off(&["contact_shadows", "stabilize"]);
        params.push(("match_tone", ParamValue::Bool(match_tone)));
        let mut s = session(&dev, &params);
        let mut f = render(Look {
            insert: Some(ins),
            ..Look::default()
        });
        for p in 0..W * H {
            if f.mask[p] > 0.0 {
                // The floor's light on the object's own albedo, 1% render noise.
                let (x, y) = (p % W, p / W);
                let shade =
                    0.45 + 0.25 * (((x - ins.x0) as f32) * 0.4).sin() * ((y as f32) * 0.3).cos();
                let noise = 1.0 + 0.02 * (hash(p as u64 + 77) - 0.5);
                for (c, a) in albedo.iter().enumerate() {
                    f.truth[3 * p + c] = a * shade;
                    f.color[3 * p + c] = a * shade * noise;
                }
            }
        }
        let in_insert = |p: usize| f.mask[p] > 0.0;
        let before = psnr_where(|x, y, c| f.color[3 * (y * W + x) + c], &f.truth, in_insert);
        let (out, _) = s.process(&f.input(0), None).unwrap();
        let after = psnr_where(|x, y, c| out.at(x, y, c), &f.truth, in_insert);
        eprintln!(
            "albedo {albedo:?}, match_tone {match_tone}: insert PSNR {before:.2} -> {after:.2} dB"
        );
        if match_tone {
            assert!(
                after >= before - 0.5,
                "albedo {albedo:?}: insert PSNR {before:.2} -> {after:.2} dB"
            );
        } else {
            let changed = (0..W * H)
                .filter(|&p| in_insert(p))
                .filter(|&p| (0..3).any(|c| out.at(p % W, p / W, c) != f.color[3 * p + c]))
                .count();
            assert_eq!(
                changed, 0,
                "albedo {albedo:?}: {changed} insert pixels changed"
            );
        }
    }
}

impl Frame {
    fn color_image(&self) -> Image {
        let n = W * H;
        let mut img = Image::filled(W, H, 4, 1.0);
        for p in 0..n {
            for c in 0..3 {
                img.data[c * n + p] = self.color[3 * p + c];
            }
        }
        img
    }
}

/// The holes and the insert box found while preparing a frame are exactly
/// what the pipeline's own searches find (`find_holes` on the RGBA image,
/// `insert_rect` on the prepared mask), with soft borders, NaN coverage and
/// mask samples, and any thread count.
#[test]
fn holes_and_insert_found_while_preparing_equal_the_searches() {
    use harmonizer_core::backend::classical::rgba_from_frame;
    use harmonizer_core::ops::{harmonize::insert_rect, inpaint::find_holes};
    let insert = Insert {
        x0: 70,
        shift: (1.0, 1.0, 1.0),
    };
    for (t, holes) in HOLES.iter().enumerate() {
        let mut f = render(Look {
            holes,
            insert: Some(insert),
            ..Look::default()
        });
        // NaN samples (sanitized to 0) and a stray mask pixel.
        f.coverage[7 * W + 3 + t] = f32::NAN;
        f.mask[2 * W + 150 - t] = f32::NAN;
        f.mask[H * W - 1 - 9 * t] = 0.25;
        for threads in [1, 2] {
            let dev = device(threads);
            let p = PreparedFrame::from_input_on(&f.input(t as i64), DepthKind::Planar, dev.pool())
                .unwrap();
            let scan = p.scan.expect("scanned while prepared");
            let want = find_holes(&rgba_from_frame(&p)).map(|h| (h.rect, h.count));
            assert!(want.is_some(), "frame {t} has holes");
            assert_eq!(scan.holes, want, "frame {t}, {threads} threads: holes");
            let mask = p.insert_mask.as_deref().unwrap();
            assert_eq!(
                scan.insert,
                insert_rect(mask, W, H),
                "frame {t}, {threads} threads: insert box"
            );
        }
    }
    // No coverage and no mask: nothing found.
    let f = render(Look::default());
    let mut input = f.input(0);
    input.coverage = None;
    let p = PreparedFrame::from_input(&input, DepthKind::Planar).unwrap();
    assert_eq!(p.scan.map(|s| (s.holes, s.insert)), Some((None, None)));
}

/// The insert mask is prepared by writing only its box into a recycled
/// buffer of zeros: frame after frame, with the insert moving, the box
/// growing and shrinking, no insert at all and odd samples (NaN, negative,
/// -0, above 1, a strided host layout), every prepared sample is the host's
/// sanitized, and the box is the search's.
#[test]
fn insert_masks_prepared_in_recycled_buffers_are_the_sanitized_masks() {
    use harmonizer_core::frame::Recycler;
    use harmonizer_core::ops::harmonize::insert_rect;
    let dev = device(2);
    let rec = Recycler::new();
    let boxes: [Option<(usize, usize, usize, usize)>; 6] = [
        Some((10, 5, 60, 40)),
        Some((100, 50, 130, 70)),
        Some((0, 0, W, H)),
        None,
        Some((150, 80, 151, 81)),
        Some((20, 30, 90, 31)),
    ];
    let f = render(Look::default());
    for (t, b) in boxes.iter().enumerate() {
        let mut mask = vec![0.0f32; W * H];
        // Outside the box: zeros of both signs, negatives and NaN.
        for (p, m) in mask.iter_mut().enumerate() {
            *m = match p % 7 {
                0 => -0.0,
                1 => -0.5,
                2 if p % 3 == 0 => f32::NAN,
                _ => 0.0,
            };
        }
        if let Some((x0, y0, x1, y1)) = *b {
            for y in y0..y1 {
                for x in x0..x1 {
                    mask[y * W + x] = match (x + 3 * y) % 6 {
                        0 => -0.0,
                        1 => f32::NAN,
                        k => (k - 2) as f32 * 0.5, // 0 to 1.5
                    };
                }
            }
        }
        // Every other sample of an interleaved buffer (strided rows).
        let strided: Vec<f32> = mask.iter().flat_map(|&m| [m, 9.0]).collect();
        for layout in [0, 1] {
            let mut input = f.input(t as i64);
            input.insert_mask = Some(match layout {
                0 => ImageView::from_f32("insert_mask", &mask, W, H, 1).unwrap(),
                _ => ImageView::from_f32("insert_mask", &strided, W, H, 2).unwrap(),
            });
            let p = PreparedFrame::from_input_recycled(
                &input,
                DepthKind::Planar,
                dev.pool(),
                &rec,
                false,
                layout == 0,
            )
            .unwrap();
            let got = p.insert_mask.as_deref().unwrap();
            for (i, (&g, &m)) in got.iter().zip(&mask).enumerate() {
                let want = if m.is_nan() {
                    0.0
                } else {
                    m.clamp(0.0, 1.0) + 0.0
                };
                assert_eq!(
                    g.to_bits(),
                    want.to_bits(),
                    "frame {t}, layout {layout}: sample {i}"
                );
            }
            assert_eq!(p.scan.unwrap().insert, insert_rect(got, W, H), "frame {t}");
            p.recycle(&rec);
        }
    }
}

/// Runs the classical backend directly with a carry the test can read.
fn run_backend(f: &Frame, params: &Params, carry: &mut Carry, dev: &Device) -> Image {
    let prepared = PreparedFrame::from_input(&f.input(0), DepthKind::Planar).unwrap();
    let history = History::default();
    let view = HistoryView::empty(&history, &prepared);
    let input = BackendInput {
        frame: &prepared,
        history: &view,
        params,
        pool: dev.pool(),
        kept: None,
        scene_probe: None,
        memory_budget: usize::MAX,
    };
    let mut progress = Progress::new(None);
    let mut stages = Stages::default();
    Classical
        .process(&input, carry, &mut progress, &mut stages)
        .unwrap()
}

#[test]
fn harmonization_parameters_are_smoothed_over_time_and_dropped_with_the_insert() {
    let dev = device(2);
    let params = Params {
        contact_shadows: false,
        stabilize: false,
        match_tone: true,
        temporal_blend: 0.8,
        ..Params::default()
    };
    let mut carry = Carry::default();
    // The render mismatch jumps between two gains every frame.
    let mut raw = Vec::new();
    let mut smoothed = Vec::new();
    for t in 0..10 {
        // 3 or 4 stops too bright: beyond the exposure dead zone.
        let gain = if t % 2 == 0 { 8.0 } else { 16.0 };
        let f = render(Look {
            insert: Some(Insert {
                x0: 60,
                shift: (gain, 1.0, 1.0),
            }),
            ..Look::default()
        });
        let mut alone = Carry::default();
        run_backend(&f, &params, &mut alone, &dev);
        raw.push(
            harmonize::tracks_from_slice(&alone.values[TONE_KEY]).unwrap()[0]
                .1
                .exposure,
        );
        run_backend(&f, &params, &mut carry, &dev);
        smoothed.push(
            harmonize::tracks_from_slice(&carry.values[TONE_KEY]).unwrap()[0]
                .1
                .exposure,
        );
    }
    let swing = |v: &[f32]| {
        v.windows(2)
            .skip(4)
            .map(|w| (w[1] - w[0]).abs())
            .fold(0.0f32, f32::max)
    };
    eprintln!("exposure raw {raw:?}\nexposure smoothed {smoothed:?}");
    assert!(
        swing(&smoothed) < 0.35 * swing(&raw),
        "raw {raw:?} smoothed {smoothed:?}"
    );
    // No insert: the smoothed parameters are dropped.
    let f = render(Look::default());
    run_backend(&f, &params, &mut carry, &dev);
    assert!(!carry.values.contains_key(TONE_KEY));
}

#[test]
fn contact_shadow_darkens_below_the_insert_only() {
    let dev = device(2);
    let ins = Insert {
        x0: 60,
        shift: (1.0, 1.0, 1.0),
    };
    let f = render(Look {
        insert: Some(ins),
        ..Look::default()
    });
    let mut with = session(&dev, &off(&["harmonize", "stabilize"]));
    let mut without = session(&dev, &off(&["harmonize", "stabilize", "contact_shadows"]));
    let (a, _) = with.process(&f.input(0), None).unwrap();
    let (b, _) = without.process(&f.input(0), None).unwrap();
    let ratio = |x0: usize, x1: usize, y0: usize, y1: usize| {
        let (mut sa, mut sb) = (0.0, 0.0);
        for y in y0..y1 {
            for x in x0..x1 {
                sa += a.at(x, y, 1);
                sb += b.at(x, y, 1);
            }
        }
        sa / sb
    };
    let below = ratio(65, 91, BOX_Y.1, BOX_Y.1 + 3);
    let inside = ratio(60, 96, BOX_Y.0, BOX_Y.1);
    let above = ratio(60, 96, 0, BOX_Y.0);
    let far = ratio(0, 30, 60, H);
    eprintln!("shadow ratios: below {below:.3} inside {inside:.3} above {above:.3} far {far:.3}");
    // Thresholds: >= 12% darker right under the box (the contact shadow
    // takes half the default strength 0.6), exactly unchanged on the box,
    // above it and far to the side.
    assert!(below < 0.88, "below {below}");
    assert_eq!(inside, 1.0);
    assert_eq!(above, 1.0);
    assert_eq!(far, 1.0);
}

/// Mean absolute difference between consecutive frames over steady background.
fn flicker(frames: &[Vec<f32>], looks: &[Frame]) -> f64 {
    let mut e = 0.0;
    let mut n = 0;
    for t in 1..frames.len() {
        for p in 0..W * H {
            if looks[t].steady[p] {
                for c in 0..3 {
                    e += (frames[t][3 * p + c] - frames[t - 1][3 * p + c]).abs() as f64;
                    n += 1;
                }
            }
        }
    }
    e / n as f64
}

fn interleaved(img: &Image) -> Vec<f32> {
    let n = img.len();
    (0..n)
        .flat_map(|p| (0..3).map(move |c| (c, p)))
        .map(|(c, p)| img.data[c * n + p])
        .collect()
}

#[test]
fn stabilization_lowers_flicker_without_ghosting_a_moving_object() {
    let dev = device(2);
    // A frame without holes is stabilized only where the operations
    // changed it unless `stabilize_all`: these flickering frames have none.
    let mut params = off(&["harmonize", "contact_shadows", "fill_holes"]);
    params.push(("stabilize_all", ParamValue::Bool(true)));
    let mut s = session(&dev, &params);
    let mut looks = Vec::new();
    let mut outs = Vec::new();
    for t in 0..10usize {
        let x0 = 20 + 6 * t;
        // A bright object (3x its true color, so a ghost would show).
        let insert = Insert {
            x0,
            shift: (3.0, 1.0, 1.0),
        };
        let prev_x0 = (t > 0).then(|| x0 - 6);
        let f = render(Look {
            insert: Some(insert),
            prev_x0,
            flicker: 0.1,
            seed: t as u64 + 1,
            ..Look::default()
        });
        let (out, _) = s.process(&f.input(t as i64), None).unwrap();
        outs.push(interleaved(&out));
        looks.push(f);
    }
    let inputs: Vec<Vec<f32>> = looks.iter().map(|f| f.color.clone()).collect();
    let fin = flicker(&inputs, &looks);
    let fout = flicker(&outs, &looks);
    // Ghosting: where the box was one frame ago but is not now, the output
    // must show the background (error within the flicker level), never the box.
    let mut ghost = 0.0;
    let mut noisy = 0.0;
    let mut full = 0.0;
    let mut n = 0;
    for t in 1..looks.len() {
        let (cur, prev) = (20 + 6 * t, 20 + 6 * (t - 1));
        for y in BOX_Y.0..BOX_Y.1 {
            for x in prev..cur {
                let p = y * W + x;
                for c in 0..3 {
                    let truth = looks[t].truth[3 * p + c];
                    ghost += (outs[t][3 * p + c] - truth).abs() as f64;
                    noisy += (looks[t].color[3 * p + c] - truth).abs() as f64;
                    full += (outs[t - 1][3 * p + c] - truth).abs() as f64;
                    n += 1;
                }
            }
        }
    }
    let (ghost, noisy, full) = (ghost / n as f64, noisy / n as f64, full / n as f64);
    eprintln!(
        "flicker in {fin:.4} out {fout:.4}; trail error: output {ghost:.4}, input noise {noisy:.4}, a full ghost {full:.4}"
    );
    // Thresholds: flicker down by at least 40%; the trail within 1.5x the
    // input noise and below 15% of what a full ghost would be.
    assert!(fout < 0.6 * fin, "flicker {fin} -> {fout}");
    assert!(
        ghost <= 1.5 * noisy,
        "trail error {ghost} vs input noise {noisy}"
    );
    assert!(
        ghost <= 0.15 * full,
        "trail error {ghost} vs a full ghost {full}"
    );
}

#[test]
fn output_is_independent_of_the_thread_count() {
    let run = |threads: usize| {
        let dev = device(threads);
        let mut s = session(&dev, &[]);
        (0..4usize)
            .map(|t| {
                let insert = Insert {
                    x0: 30 + 5 * t,
                    shift: (1.8, 1.3, 0.8),
                };
                let f = render(Look {
                    insert: Some(insert),
                    prev_x0: (t > 0).then(|| 25 + 5 * t),
                    holes: HOLES[t],
                    flicker: 0.05,
                    seed: t as u64,
                });
                s.process(&f.input(t as i64), None).unwrap().0
            })
            .collect::<Vec<_>>()
    };
    let one = run(1);
    let two = run(2);
    for (t, (a, b)) in one.iter().zip(&two).enumerate() {
        assert!(
            a.data
                .iter()
                .zip(&b.data)
                .all(|(x, y)| x.to_bits() == y.to_bits()),
            "frame {t} differs between 1 and 2 threads"
        );
    }
}

#[test]
fn all_operations_off_is_a_copy() {
    let dev = device(2);
    let mut s = session(
        &dev,
        &off(&["fill_holes", "harmonize", "contact_shadows", "stabilize"]),
    );
    let ins = Insert {
        x0: 60,
        shift: (2.0, 1.0, 1.0),
    };
    for t in 0..2 {
        let f = render(Look {
            insert: Some(ins),
            holes: HOLES[0],
            flicker: 0.1,
            seed: t,
            ..Look::default()
        });
        let (out, _) = s.process(&f.input(t as i64), None).unwrap();
        assert_eq!(interleaved(&out), f.color);
        assert_eq!(out.plane(3), &f.coverage[..]);
    }
}
