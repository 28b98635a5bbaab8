//! The neural backend on the real ONNX Runtime (from the project's `.venv`)
//! with the fixture models of `tests/fixtures/models` (made by
//! `make_fixtures.py`): encoding, channel layout, tiling, memory limit,
//! cancellation, runtime discovery and manifest errors.

use std::path::PathBuf;
use std::sync::{Arc, OnceLock};

use harmonizer_core::backend::neural::encoding::ColorCodec;
use harmonizer_core::backend::neural::{runtime, Neural, NeuralModel};
use harmonizer_core::backend::{Backend, BackendInput, Carry, Progress, Stages};
use harmonizer_core::frame::PreparedFrame;
use harmonizer_core::model::{Encoding, Exposure};
use harmonizer_core::temporal::{History, HistoryFrame, HistoryView};
use harmonizer_core::{
    Device, DeviceOptions, Error, FrameInput, Image, ImageView, ModelSource, ParamValue, Params,
    Session,
};

/// The ONNX Runtime library; a missing runtime fails the test (never skips).
fn ort_lib() -> PathBuf {
    static LIB: OnceLock<std::result::Result<PathBuf, String>> = OnceLock::new();
    LIB.get_or_init(|| runtime::locate(None).map_err(|e| e.to_string()))
        .clone()
        .unwrap_or_else(|e| {
            panic!("the neural tests need ONNX Runtime: run scripts/setup-venv.sh in the repository root ({e})")
        })
}

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/models")
        .join(format!("{name}.onnx"))
}

fn fixture_manifest(name: &str) -> serde_json::Value {
    let text = std::fs::read_to_string(fixture(name).with_extension("json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn options(model: ModelSource, memory_limit: usize) -> DeviceOptions {
    DeviceOptions {
        threads: 2,
        ort_library: Some(ort_lib()),
        memory_limit,
        model,
        oidn_library: None,
    }
}

pub(crate) fn device_file(name: &str) -> Arc<Device> {
    Device::new(options(ModelSource::File(fixture(name)), 0)).unwrap()
}

/// A device running fixture `name` with its manifest changed by `edit`.
fn device_edited(
    name: &str,
    memory_limit: usize,
    edit: impl FnOnce(&mut serde_json::Value),
) -> Arc<Device> {
    let mut m = fixture_manifest(name);
    edit(&mut m);
    let onnx = std::fs::read(fixture(name)).unwrap();
    Device::new(options(
        ModelSource::Bytes {
            onnx,
            manifest: m.to_string(),
        },
        memory_limit,
    ))
    .unwrap()
}

fn session(device: Arc<Device>, set: &[(&str, ParamValue)]) -> Session {
    let mut params = Params::default();
    params
        .set("backend", &ParamValue::Str("neural".into()))
        .unwrap();
    // The test images are per-pixel random HDR values, which `denoise
    // auto` rightly takes for a noisy render: these tests are about the
    // network's numbers, so the denoise stage stays off.
    params
        .set("denoise", &ParamValue::Str("off".into()))
        .unwrap();
    // Nor does a frame without holes or insert skip the network.
    params
        .set("neural_clean_frames", &ParamValue::Bool(true))
        .unwrap();
    // Nor do the insert operations change what the network made of an
    // insert mask (`inserts` tests them after the network).
    for k in ["harmonize", "contact_shadows"] {
        params.set(k, &ParamValue::Bool(false)).unwrap();
    }
    for (k, v) in set {
        params.set(k, v).unwrap();
    }
    let s = Session::new(device, params).unwrap();
    assert_eq!(s.backend_name(), "neural");
    s
}

/// Deterministic pseudo-random numbers in [0,1).
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / (1u64 << 24) as f32
    }
}

/// Interleaved HDR RGB (log-uniform over 2^-8..2^6 with some exact zeros).
fn hdr_rgb(w: usize, h: usize, seed: u64) -> Vec<f32> {
    let mut r = Rng(seed);
    (0..w * h * 3)
        .map(|_| {
            let u = r.next();
            if u < 0.03 {
                0.0
            } else {
                (2.0f32).powf(-8.0 + 14.0 * r.next())
            }
        })
        .collect()
}

fn plane_of(img: &Image, c: usize) -> Vec<f32> {
    img.plane(c).to_vec()
}

/// Interleaved RGB premultiplied by a per-pixel coverage.
fn premultiply(rgb: &[f32], cov: &[f32]) -> Vec<f32> {
    rgb.iter()
        .enumerate()
        .map(|(i, v)| v * cov[i / 3])
        .collect()
}

/// Planar channel `c` of interleaved data.
fn deinterleave(data: &[f32], channels: usize, c: usize) -> Vec<f32> {
    data.iter().skip(c).step_by(channels).copied().collect()
}

fn assert_close(got: &[f32], want: &[f32], rel: f32, what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: length");
    let mut worst = (0.0f32, 0usize);
    for (i, (g, w)) in got.iter().zip(want).enumerate() {
        let err = (g - w).abs() / w.abs().max(1e-3);
        if err.is_nan() || err > worst.0 {
            worst = (err, i);
        }
    }
    assert!(
        worst.0 <= rel,
        "{what}: worst relative error {} at {} (got {}, want {}), allowed {rel}",
        worst.0,
        worst.1,
        got[worst.1],
        want[worst.1]
    );
}

#[test]
fn encoding_round_trip_is_exact() {
    let (w, h) = (97, 61);
    let data = hdr_rgb(w, h, 7);
    let mut img = Image::zeros(w, h, 3);
    for c in 0..3 {
        img.plane_mut(c).copy_from_slice(&deinterleave(&data, 3, c));
    }
    for enc in [
        Encoding::Log {
            key: 0.18,
            exposure: Exposure::Frame,
            log_range: 8.0,
        },
        Encoding::Log {
            key: 0.5,
            exposure: Exposure::None,
            log_range: 16.0,
        },
        Encoding::Linear {
            key: 0.18,
            exposure: Exposure::Frame,
        },
    ] {
        let codec = ColorCodec::for_frame(&enc, &img, None);
        assert!(codec.scale.is_finite() && codec.scale > 0.0);
        for &x in img
            .data
            .iter()
            .chain([0.0, 1e-6, 1.0, 1000.0, 60000.0].iter())
        {
            let y = codec.encode(x);
            let back = codec.decode(y);
            assert!(
                (back - x).abs() <= 1e-5 * x,
                "{enc:?}: {x} -> {y} -> {back}"
            );
        }
    }
    // The exposure is a whole-frame statistic: key 0.18 maps the log-average to 0.18.
    let flat = Image::filled(8, 8, 3, 2.0);
    let codec = ColorCodec::for_frame(
        &Encoding::Linear {
            key: 0.18,
            exposure: Exposure::Frame,
        },
        &flat,
        None,
    );
    assert!(
        (codec.encode(2.0) - 0.18).abs() < 1e-4,
        "{}",
        codec.encode(2.0)
    );
}

#[test]
fn identity_model_returns_its_input_through_tiles() {
    let (w, h) = (333, 187);
    let rgb = hdr_rgb(w, h, 1);
    let device = device_file("identity");
    let model = device.neural_model().unwrap().unwrap();
    assert_eq!(
        (model.name.as_str(), model.version.as_str()),
        ("identity", "1.0.0")
    );
    let mut s = session(device.clone(), &[]);
    let plan = model.tile_plan(w, h, s.params()).unwrap();
    assert!(
        plan.len() >= 12,
        "expected many 64 px tiles, got {}",
        plan.len()
    );
    let input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    let (out, report) = s.process(&input, None).unwrap();
    assert_eq!(report.backend, "neural");
    for c in 0..3 {
        assert_close(
            &plane_of(&out, c),
            &deinterleave(&rgb, 3, c),
            1e-5,
            &format!("identity channel {c}"),
        );
    }
    assert!(out.plane(3).iter().all(|&a| a == 1.0));

    // Straight-color model, holes kept: RGB = prediction * coverage, A = coverage.
    let cov: Vec<f32> = (0..w * h)
        .map(|i| [0.0, 0.25, 0.5, 1.0, 1.0][i % 5])
        .collect();
    let premult = premultiply(&rgb, &cov);
    let device = device_edited("identity", 0, |m| m["premultiplied"] = false.into());
    let mut s = session(device, &[("fill_holes", ParamValue::Bool(false))]);
    let mut input = FrameInput::new(ImageView::from_f32("color", &premult, w, h, 3).unwrap());
    input.coverage = Some(ImageView::from_f32("coverage", &cov, w, h, 1).unwrap());
    let (out, _) = s.process(&input, None).unwrap();
    for c in 0..3 {
        assert_close(
            &plane_of(&out, c),
            &deinterleave(&premult, 3, c),
            1e-5,
            &format!("straight channel {c}"),
        );
    }
    assert_eq!(out.plane(3), &cov[..]);
}

#[test]
fn residual_model_adds_to_the_encoded_input() {
    let (w, h) = (70, 45);
    let rgb = hdr_rgb(w, h, 2);
    let input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    // Tiles across x (70 > 64) and one window (tile_size 80).
    for tile in [0, 80] {
        let device = device_file("residual_zero");
        let mut s = session(device.clone(), &[("tile_size", ParamValue::Int(tile))]);
        let model = device.neural_model().unwrap().unwrap();
        let n = model.tile_plan(w, h, s.params()).unwrap().len();
        assert_eq!(n == 1, tile == 80, "tile_size {tile}: {n} tiles");
        let (out, _) = s.process(&input, None).unwrap();
        for c in 0..3 {
            assert_close(
                &plane_of(&out, c),
                &deinterleave(&rgb, 3, c),
                1e-5,
                &format!("residual channel {c}, {n} tiles"),
            );
        }
    }
}

/// Runs the backend directly with a hand-made history (`prev` frames, newest first).
fn run_backend(
    model: &Arc<NeuralModel>,
    device: &Device,
    frame: &PreparedFrame,
    prev: &[Image],
    params: &Params,
) -> Image {
    // These frames have no holes: the network runs on them only when asked.
    // The insert operations after it stay off (see `session`).
    let params = &Params {
        neural_clean_frames: true,
        harmonize: false,
        contact_shadows: false,
        ..params.clone()
    };
    let mut history = History::default();
    for img in prev.iter().rev() {
        history.push(
            HistoryFrame {
                color: harmonizer_core::frame::RgbaImage::from_planes(img, None),
                depth: None,
                motion: None,
                camera: None,
                frame_index: None,
            },
            8,
        );
    }
    let view = HistoryView::new(&history, frame, params.context_frames, device.pool());
    let input = BackendInput {
        frame,
        history: &view,
        params,
        pool: device.pool(),
        kept: None,
        scene_probe: None,
        memory_budget: usize::MAX,
    };
    let backend = Neural {
        model: model.clone(),
    };
    backend
        .process(
            &input,
            &mut Carry::default(),
            &mut Progress::new(None),
            &mut Stages::default(),
        )
        .unwrap()
}

#[test]
fn channel_probe_proves_the_tensor_layout() {
    let (w, h) = (53, 41);
    let rgb = hdr_rgb(w, h, 3);
    let mut r = Rng(9);
    let insert: Vec<f32> = (0..w * h).map(|_| r.next()).collect();
    let depth: Vec<f32> = (0..w * h).map(|_| 0.5 + 20.0 * r.next()).collect();
    let mut input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    input.insert_mask = Some(ImageView::from_f32("insert", &insert, w, h, 1).unwrap());
    input.depth = Some(ImageView::from_f32("depth", &depth, w, h, 1).unwrap());
    let frame = PreparedFrame::from_input(&input, Default::default()).unwrap();
    let hist = |seed: u64| {
        let mut r = Rng(seed);
        let mut img = Image::zeros(w, h, 4);
        img.data.iter_mut().for_each(|v| *v = r.next() * 4.0);
        img
    };
    let (h0, h1) = (hist(11), hist(12));

    // The probe outputs input channels 5, 8, 4: with its manifest hist0.r, valid0, insert.
    let device = device_file("channel_probe");
    let model = device.neural_model().unwrap().unwrap();
    assert_eq!(model.manifest.context_frames, 2);
    let out = run_backend(
        &model,
        &device,
        &frame,
        &[h0.clone(), h1.clone()],
        &Params::default(),
    );
    assert_close(&plane_of(&out, 0), h0.plane(0), 1e-6, "output.r = hist0.r");
    assert!(
        out.plane(1).iter().all(|&v| v == 1.0),
        "output.g = valid0 (identity reprojection)"
    );
    assert_close(&plane_of(&out, 2), &insert, 1e-6, "output.b = insert");

    // Cold start: no history -> zeros and validity 0.
    let out = run_backend(&model, &device, &frame, &[], &Params::default());
    assert!(out.plane(0).iter().chain(out.plane(1)).all(|&v| v == 0.0));

    // The same graph under another manifest reads other channels at those positions:
    // 5 = hist1.g, 8 = valid1, 4 = disparity; output channels reversed (b, g, r).
    let device = device_edited("channel_probe", 0, |m| {
        let ch = m["input"]["channels"].as_array_mut().unwrap();
        ch.swap(5, 10); // hist0.r <-> hist1.g
        ch.swap(8, 12); // valid0 <-> valid1
        ch.swap(4, 14); // insert <-> disparity
        m["output"]["channels"] = serde_json::json!(["color.b", "color.g", "color.r"]);
    });
    let model = device.neural_model().unwrap().unwrap();
    let out = run_backend(
        &model,
        &device,
        &frame,
        &[h0.clone(), h1.clone()],
        &Params::default(),
    );
    let disparity: Vec<f32> = depth.iter().map(|d| 1.0 / (1.0 + d)).collect();
    assert_close(&plane_of(&out, 2), h1.plane(1), 1e-6, "output.b = hist1.g");
    assert!(out.plane(1).iter().all(|&v| v == 1.0), "output.g = valid1");
    assert_close(&plane_of(&out, 0), &disparity, 1e-6, "output.r = disparity");

    // Session context 1 < K = 2: the second history frame is zeros with validity 0.
    let params = Params {
        context_frames: 1,
        ..Params::default()
    };
    let out = run_backend(&model, &device, &frame, &[h0.clone(), h1.clone()], &params);
    assert!(out.plane(2).iter().chain(out.plane(1)).all(|&v| v == 0.0));

    // The manifest's `history_read` 1: the same, whatever the session's
    // context; hist0 is still read.
    let device = device_edited("channel_probe", 0, |m| {
        let ch = m["input"]["channels"].as_array_mut().unwrap();
        ch.swap(8, 12); // valid0 <-> valid1
        m["history_read"] = 1.into();
    });
    let model = device.neural_model().unwrap().unwrap();
    assert_eq!(model.manifest.history_slots(), 1);
    let out = run_backend(
        &model,
        &device,
        &frame,
        &[h0.clone(), h1],
        &Params::default(),
    );
    assert_close(&plane_of(&out, 0), h0.plane(0), 1e-6, "output.r = hist0.r");
    assert!(
        out.plane(1).iter().all(|&v| v == 0.0),
        "output.g = valid1: none"
    );
    // Above `context_frames`: refused, naming the field.
    let text = fixture_manifest("channel_probe");
    let mut bad = text.clone();
    bad["history_read"] = 3.into();
    let err = harmonizer_core::model::Manifest::from_json(&bad.to_string(), "test")
        .unwrap_err()
        .to_string();
    assert!(err.contains("history_read"), "{err}");
}

/// The box filter in the encoded domain with reflected borders; on an axis
/// whose `zero_near` is set, zeros before the first pixel instead (a window
/// that starts at the frame edge sees the graph's own zero padding there) and
/// reflection after the last.
fn box3_reference(
    rgb: &[f32],
    w: usize,
    h: usize,
    codec: &ColorCodec,
    zero_near: (bool, bool),
) -> Vec<Vec<f32>> {
    let refl = |i: isize, n: usize| harmonizer_core::backend::neural::tiling::reflect(i, n);
    (0..3)
        .map(|c| {
            let enc: Vec<f32> = deinterleave(rgb, 3, c)
                .iter()
                .map(|&v| codec.encode(v))
                .collect();
            let mut out = vec![0.0; w * h];
            for y in 0..h {
                for x in 0..w {
                    let mut s = 0.0f32;
                    for dy in -1..=1isize {
                        for dx in -1..=1isize {
                            let (yy, xx) = (y as isize + dy, x as isize + dx);
                            if (zero_near.0 && xx < 0) || (zero_near.1 && yy < 0) {
                                continue;
                            }
                            s += enc[refl(yy, h) * w + refl(xx, w)];
                        }
                    }
                    out[y * w + x] = codec.decode(s / 9.0);
                }
            }
            out
        })
        .collect()
}

#[test]
fn tiled_box3_equals_untiled_and_the_reference() {
    let (w, h) = (333, 187);
    let rgb = hdr_rgb(w, h, 4);
    let input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    let device = device_file("box3");
    let model = device.neural_model().unwrap().unwrap();
    let run = |tile: i64, overlap: i64| {
        let mut s = session(
            device.clone(),
            &[
                ("tile_size", ParamValue::Int(tile)),
                ("tile_overlap", ParamValue::Int(overlap)),
            ],
        );
        let plan = model.tile_plan(w, h, s.params()).unwrap();
        (s.process(&input, None).unwrap().0, plan)
    };
    let frame = PreparedFrame::from_input(&input, Default::default()).unwrap();
    let codec = ColorCodec::for_frame(&model.manifest.encoding, &frame.color, None);

    // One window over the whole frame, starting at its edge: the frame as the
    // network sees a whole frame (zero padding before, reflection up to the
    // multiple of 16 after, 333x187 -> 336x192).
    let (single, plan) = run(1024, 2);
    assert_eq!(plan.len(), 1);
    assert_eq!((plan.x.window, plan.y.window), (336, 192));
    let whole = box3_reference(&rgb, w, h, &codec, (true, true));
    for (c, want) in whole.iter().enumerate() {
        assert_close(
            single.plane(c),
            want,
            1e-5,
            &format!("one window vs reference, channel {c}"),
        );
    }
    assert!(single.plane(3).iter().all(|&a| a == 1.0));
    // A frame exactly one tile_size wide is one window too.
    assert_eq!(
        model
            .tile_plan(
                333,
                187,
                &Params {
                    tile_size: 336,
                    ..Params::default()
                }
            )
            .unwrap()
            .len(),
        1
    );

    // Several tiles equal one window over the frame widened by reflection on
    // the sides of each axis cut into tiles (the overlap context of the border
    // tiles); an axis that fits one window starts at the frame edge.
    for (tile, overlap) in [(34, 8), (48, 2), (64, 4), (100, 6), (128, 8), (200, 3)] {
        let (tiled, plan) = run(tile, overlap);
        assert!(plan.len() > 1, "tile {tile}: one tile");
        let single = (plan.x.cores.len() == 1, plan.y.cores.len() == 1);
        assert_eq!(single, (false, tile == 200), "tile {tile}");
        let untiled = box3_reference(&rgb, w, h, &codec, single);
        for (c, want) in untiled.iter().enumerate() {
            assert_close(
                tiled.plane(c),
                want,
                1e-5,
                &format!("tile {tile} overlap {overlap} channel {c}"),
            );
        }
        assert!(tiled.plane(3).iter().all(|&a| (a - 1.0).abs() < 1e-6));
    }
    // Deterministic: the same frame twice gives the same bits.
    assert_eq!(run(64, 4).0, run(64, 4).0);
}

#[test]
fn memory_limit_forces_smaller_tiles() {
    let (w, h) = (333, 187);
    let rgb = hdr_rgb(w, h, 5);
    let input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    let free = device_file("box3");
    let model = free.neural_model().unwrap().unwrap();
    let params = Params::default();
    let unlimited = model.tile_plan(w, h, &params).unwrap();
    // The session's frame buffers come first; the tiles get what is left.
    let frame = session(free.clone(), &[])
        .memory_estimate(&harmonizer_core::FrameShape::of(&input))
        .unwrap();
    let limit = frame + model.working_bytes(&unlimited) - 1;
    let tight = device_edited("box3", limit, |_| {});
    let tight_model = tight.neural_model().unwrap().unwrap();
    let plan = tight_model
        .tile_plan_within(w, h, &params, limit - frame)
        .unwrap();
    assert!(
        plan.x.window < unlimited.x.window,
        "{plan:?} vs {unlimited:?}"
    );
    assert!(tight_model.working_bytes(&plan) <= limit - frame);
    assert!(plan.len() > unlimited.len());
    let a = session(free, &[]).process(&input, None).unwrap().0;
    let b = session(tight.clone(), &[]).process(&input, None).unwrap().0;
    for c in 0..4 {
        assert_close(
            b.plane(c),
            a.plane(c),
            1e-5,
            &format!("memory-limited channel {c}"),
        );
    }
    // Below the smallest tile: a clear error naming memory_limit.
    let tiny = device_edited("box3", 1000, |_| {});
    let e = tiny
        .neural_model()
        .unwrap()
        .unwrap()
        .tile_plan(w, h, &params)
        .unwrap_err();
    assert!(
        matches!(e, Error::OutOfMemory(_)) && e.to_string().contains("memory_limit 1000"),
        "{e}"
    );
}

#[test]
fn cancel_between_tiles_leaves_the_session_unchanged() {
    let (w, h) = (333, 187);
    let frames: Vec<Vec<f32>> = (0..3).map(|i| hdr_rgb(w, h, 20 + i)).collect();
    let device = device_file("box3");
    let run_all = |cancel_at: Option<usize>| {
        let mut s = session(
            device.clone(),
            &[
                ("tile_size", ParamValue::Int(64)),
                ("tile_overlap", ParamValue::Int(4)),
            ],
        );
        let mut outs = Vec::new();
        for (i, rgb) in frames.iter().enumerate() {
            let mut input = FrameInput::new(ImageView::from_f32("color", rgb, w, h, 3).unwrap());
            input.frame_index = Some(i as i64);
            if cancel_at == Some(i) {
                let mut calls = 0;
                let mut cb = |_: f64| {
                    calls += 1;
                    calls < 4
                };
                let e = s.process(&input, Some(&mut cb)).unwrap_err();
                assert!(matches!(e, Error::Cancelled(_)), "{e}");
                assert_eq!(s.history_len(), i.min(4));
            }
            let mut reports = 0;
            let mut cb = |_: f64| {
                reports += 1;
                true
            };
            outs.push(s.process(&input, Some(&mut cb)).unwrap().0);
            assert!(reports >= 20, "progress per tile: {reports} reports");
        }
        outs
    };
    assert_eq!(run_all(Some(1)), run_all(None));
}

/// Four RGB frames of one image with a little per-frame flicker (no scene
/// cut, so the history is kept).
fn flickering(w: usize, h: usize, seed: u64) -> Vec<Vec<f32>> {
    let base = hdr_rgb(w, h, seed);
    (0..4)
        .map(|i| {
            base.iter()
                .enumerate()
                .map(|(j, v)| v * (1.0 + 0.1 * (((j * 7 + i * 13) % 11) as f32 / 11.0 - 0.5)))
                .collect()
        })
        .collect()
}

#[test]
fn classical_post_runs_the_classical_operations_on_the_network_output() {
    // The identity model returns its input, so with `classical_post` the
    // sequence must come out as the classical backend makes it (full coverage:
    // the identity leaves no hole of its own), stabilization and harmonization
    // of the insert included; without it, as the input.
    let (w, h) = (96, 64);
    let frames = flickering(w, h, 40);
    let mask: Vec<f32> = (0..w * h)
        .map(|i| {
            let (x, y) = (i % w, i / w);
            if (30..60).contains(&x) && (20..50).contains(&y) {
                1.0
            } else {
                0.0
            }
        })
        .collect();
    let run = |backend: &str, post: bool| {
        let mut params = Params::default();
        params
            .set("backend", &ParamValue::Str(backend.into()))
            .unwrap();
        params
            .set("classical_post", &ParamValue::Bool(post))
            .unwrap();
        // Random frames: `denoise auto` would denoise them (see `session`).
        params
            .set("denoise", &ParamValue::Str("off".into()))
            .unwrap();
        // Nor would the network run on frames without holes, and the
        // classical operations would stabilize only an insert they
        // recolored (this one matches its surroundings).
        params
            .set("neural_clean_frames", &ParamValue::Bool(true))
            .unwrap();
        params
            .set("stabilize_all", &ParamValue::Bool(true))
            .unwrap();
        let mut s = Session::new(device_file("identity"), params).unwrap();
        let mut outs = Vec::new();
        for (i, rgb) in frames.iter().enumerate() {
            let mut input = FrameInput::new(ImageView::from_f32("color", rgb, w, h, 3).unwrap());
            input.insert_mask = Some(ImageView::from_f32("insert", &mask, w, h, 1).unwrap());
            input.frame_index = Some(i as i64);
            let mut reports = Vec::new();
            let mut cb = |p: f64| {
                reports.push(p);
                true
            };
            let (out, report) = s.process(&input, Some(&mut cb)).unwrap();
            assert!(reports.windows(2).all(|p| p[0] <= p[1]), "{reports:?}");
            outs.push((out, report));
        }
        outs
    };
    let classical = run("classical", false);
    let post = run("neural", true);
    let plain = run("neural", false);
    for (i, ((c, _), ((p, report), (n, _)))) in classical
        .iter()
        .zip(post.iter().zip(plain.iter()))
        .enumerate()
    {
        // Zeros come back as about 1e-6 through the log codec.
        assert_close(
            &p.data,
            &c.data,
            2e-3,
            &format!("frame {i}: neural + classical_post"),
        );
        let stages: Vec<&str> = report.stages.0.iter().map(|(s, _)| s.as_str()).collect();
        assert!(
            stages.contains(&"inference") && stages.contains(&"harmonize"),
            "{stages:?}"
        );
        assert_eq!(stages.contains(&"stabilize"), i > 0, "{stages:?}");
        let rgb = plane_of(n, 0);
        let want = deinterleave(&frames[i], 3, 0);
        assert_close(&rgb, &want, 1e-4, &format!("frame {i}: neural alone"));
    }
    // The classical operations changed something (else the test proves nothing).
    let moved = post[3]
        .0
        .data
        .iter()
        .zip(&plain[3].0.data)
        .filter(|(a, b)| (*a - *b).abs() > 1e-3)
        .count();
    assert!(moved > 100, "classical_post changed {moved} values");
}

#[test]
fn manifest_stabilize_blends_the_network_output_with_its_history() {
    // The identity model with `stabilize: true` in its manifest must give what
    // the identity model followed by the classical operations gives when only
    // stabilization is on (the identity leaves no hole, so the fill does
    // nothing); with the session's `stabilize` off, the plain identity output.
    let (w, h) = (96, 64);
    let frames = flickering(w, h, 41);
    let run = |device: Arc<Device>, set: &[(&str, ParamValue)]| {
        let mut s = session(device, set);
        frames
            .iter()
            .enumerate()
            .map(|(i, rgb)| {
                let mut input =
                    FrameInput::new(ImageView::from_f32("color", rgb, w, h, 3).unwrap());
                input.frame_index = Some(i as i64);
                s.process(&input, None).unwrap()
            })
            .collect::<Vec<_>>()
    };
    let asks = || device_edited("identity", 0, |m| m["stabilize"] = true.into());
    let stabilized = run(asks(), &[]);
    let reference = run(
        device_file("identity"),
        &[
            ("classical_post", ParamValue::Bool(true)),
            ("harmonize", ParamValue::Bool(false)),
            ("contact_shadows", ParamValue::Bool(false)),
            // The classical operations stabilize a frame without holes
            // only where they changed it; the manifest's stabilization
            // is of the network's whole output.
            ("stabilize_all", ParamValue::Bool(true)),
        ],
    );
    let off = run(asks(), &[("stabilize", ParamValue::Bool(false))]);
    let plain = run(device_file("identity"), &[]);
    for (i, ((s, report), (r, _))) in stabilized.iter().zip(&reference).enumerate() {
        assert_eq!(s.data, r.data, "frame {i}: stabilized output");
        let stages: Vec<&str> = report.stages.0.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(
            stages.contains(&"stabilize"),
            i > 0,
            "frame {i}: {stages:?}"
        );
    }
    for (i, ((o, _), (p, _))) in off.iter().zip(&plain).enumerate() {
        assert_eq!(o.data, p.data, "frame {i}: stabilize off");
    }
    // Stabilization changed something (else the test proves nothing).
    let moved = stabilized[3]
        .0
        .data
        .iter()
        .zip(&plain[3].0.data)
        .filter(|(a, b)| (*a - *b).abs() > 1e-3)
        .count();
    assert!(moved > 100, "stabilization changed {moved} values");
}

#[test]
fn the_stabilization_copies_the_history_the_tiles_reprojected_bit_for_bit() {
    // The manifest's stabilization copies history frame 0 as the tiles
    // reprojected it (by motion vectors here, into one window or several
    // tiles); it must equal the classical stabilization after the network
    // (`classical_post` with the other operations off), which reprojects
    // the history itself.
    let (w, h) = (96, 64);
    let frames = flickering(w, h, 43);
    let mut r = Rng(44);
    let motion: Vec<f32> = (0..w * h)
        .flat_map(|_| [1.5 + r.next() - 0.5, -0.75 + r.next() * 0.5])
        .collect();
    let depth: Vec<f32> = (0..w * h).map(|i| 2.0 + (i % w) as f32 * 0.01).collect();
    let run = |device: Arc<Device>, set: &[(&str, ParamValue)]| {
        // Random pixels moved by the motion look like a scene cut.
        let mut set = set.to_vec();
        set.push(("scene_cut_detection", ParamValue::Bool(false)));
        let mut s = session(device, &set);
        frames
            .iter()
            .enumerate()
            .map(|(i, rgb)| {
                let mut input =
                    FrameInput::new(ImageView::from_f32("color", rgb, w, h, 3).unwrap());
                input.motion = Some(ImageView::from_f32("motion", &motion, w, h, 2).unwrap());
                input.depth = Some(ImageView::from_f32("depth", &depth, w, h, 1).unwrap());
                input.frame_index = Some(i as i64);
                s.process(&input, None).unwrap().0
            })
            .collect::<Vec<_>>()
    };
    // The probe returns input channels 5, 8 and 4: made the current color
    // here, so the stabilization has something to change.
    let probe = |stabilize: bool| {
        device_edited("channel_probe", 0, |m| {
            let ch = m["input"]["channels"].as_array_mut().unwrap();
            ch.swap(0, 5);
            ch.swap(1, 8);
            ch.swap(2, 4);
            m["stabilize"] = stabilize.into();
        })
    };
    for tiles in [
        vec![("tile_size", ParamValue::Int(160))],
        vec![
            ("tile_size", ParamValue::Int(40)),
            ("tile_overlap", ParamValue::Int(3)),
        ],
    ] {
        let stabilized = run(probe(true), &tiles);
        let mut post = tiles.clone();
        post.extend([
            ("classical_post", ParamValue::Bool(true)),
            ("harmonize", ParamValue::Bool(false)),
            ("contact_shadows", ParamValue::Bool(false)),
            ("stabilize_all", ParamValue::Bool(true)),
        ]);
        let reference = run(probe(false), &post);
        for (i, (s, r)) in stabilized.iter().zip(&reference).enumerate() {
            assert!(s.data == r.data, "{tiles:?}, frame {i}: stabilized output");
        }
        let plain = run(probe(false), &tiles);
        let moved = (1..frames.len())
            .map(|i| {
                let pairs = stabilized[i].data.iter().zip(&plain[i].data);
                pairs.filter(|(a, b)| (*a - *b).abs() > 1e-3).count()
            })
            .sum::<usize>();
        assert!(
            moved > 100,
            "{tiles:?}: stabilization changed {moved} values"
        );
    }
}

#[test]
fn missing_runtime_says_what_to_install() {
    let opts = DeviceOptions {
        ort_library: Some("/nonexistent/libonnxruntime.so.1.31.1".into()),
        model: ModelSource::File(fixture("identity")),
        ..DeviceOptions::default()
    };
    let e = Device::new(opts).unwrap().neural_model().unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, Error::RuntimeMissing(_)), "{msg}");
    for needle in [
        "/nonexistent/libonnxruntime.so.1.31.1",
        "pip install onnxruntime==1.31.*",
        "HARMONIZER_ORT_LIB",
    ] {
        assert!(msg.contains(needle), "{needle:?} missing from: {msg}");
    }
    // A second, different runtime in the same process is refused clearly.
    device_file("identity").neural_model().unwrap();
    let other = ort_lib().with_file_name("libonnxruntime_providers_shared.so");
    assert!(other.is_file(), "{}", other.display());
    let opts = DeviceOptions {
        ort_library: Some(other.clone()),
        model: ModelSource::File(fixture("identity")),
        ..DeviceOptions::default()
    };
    let e = Device::new(opts).unwrap().neural_model().unwrap_err();
    assert!(
        matches!(e, Error::InvalidOperation(_)) && e.to_string().contains("already loaded"),
        "{e}"
    );
}

#[test]
fn auto_without_the_runtime_runs_classical_and_says_why() {
    let device = Device::new(DeviceOptions {
        ort_library: Some("/nonexistent/libonnxruntime.so.1.31.1".into()),
        model: ModelSource::File(fixture("identity")),
        ..DeviceOptions::default()
    })
    .unwrap();
    // Asked for by name, the neural backend is an error that names the runtime.
    let mut params = Params::default();
    params
        .set("backend", &ParamValue::Str("neural".into()))
        .unwrap();
    let e = Session::new(device.clone(), params).unwrap_err();
    assert!(matches!(e, Error::RuntimeMissing(_)), "{e}");
    // `auto` falls back to classical; the first frame's report says why, once.
    let mut s = Session::new(device, Params::default()).unwrap();
    assert_eq!(s.backend_name(), "classical");
    let (w, h) = (64, 48);
    let rgb = hdr_rgb(w, h, 7);
    let input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    let (_, first) = s.process(&input, None).unwrap();
    assert_eq!(first.backend, "classical");
    assert!(
        first.warnings.iter().any(|m| m.contains("backend auto")
            && m.contains("/nonexistent/libonnxruntime.so.1.31.1")
            && m.contains("pip install onnxruntime")),
        "{:?}",
        first.warnings
    );
    let (_, second) = s.process(&input, None).unwrap();
    assert!(
        !second.warnings.iter().any(|m| m.contains("backend auto")),
        "{:?}",
        second.warnings
    );
}

/// The error of a device made with fixture `name` and its manifest changed
/// by `edit`: the model is checked when the device is made.
fn model_error(name: &str, edit: impl FnOnce(&mut serde_json::Value)) -> String {
    let mut m = fixture_manifest(name);
    edit(&mut m);
    let onnx = std::fs::read(fixture(name)).unwrap();
    let e = Device::new(options(
        ModelSource::Bytes {
            onnx,
            manifest: m.to_string(),
        },
        0,
    ))
    .unwrap_err();
    assert!(matches!(e, Error::Model(_)), "{e}");
    e.to_string()
}

#[test]
fn bad_manifests_and_models_name_the_field() {
    let e = model_error("identity", |m| m["input"]["channels"][1] = "color.q".into());
    assert!(
        e.contains("input.channels[1]") && e.contains("color.q"),
        "{e}"
    );
    let e = model_error("identity", |m| m["context_frames"] = 9.into());
    assert!(e.contains("context_frames") && e.contains('9'), "{e}");
    let e = model_error("identity", |m| m["tile_overlap"] = 40.into());
    assert!(e.contains("tile_size") && e.contains("40"), "{e}");
    let e = model_error("identity", |m| m["encoding"]["log_range"] = (-2.0).into());
    assert!(e.contains("encoding.log_range") && e.contains("-2"), "{e}");
    let e = model_error("identity", |m| m["format_version"] = 7.into());
    assert!(e.contains("format_version") && e.contains('7'), "{e}");
    let e = model_error("identity", |m| {
        m["input"]["channels"]
            .as_array_mut()
            .unwrap()
            .push("coverage".into());
    });
    assert!(
        e.contains("4") && e.contains("3 channels") && e.contains("input.channels"),
        "{e}"
    );
    // The fixture whose graph input is "x" while its manifest says "input".
    let e = Device::new(options(ModelSource::File(fixture("wrong_name")), 0))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("\"input\"") && e.contains("\"x\"") && e.contains("wrong_name.onnx"),
        "{e}"
    );
    // A file without its manifest.
    let dir = tempfile::tempdir().unwrap();
    let lone = dir.path().join("lone.onnx");
    std::fs::copy(fixture("identity"), &lone).unwrap();
    let e = Device::new(options(ModelSource::File(lone), 0))
        .unwrap_err()
        .to_string();
    assert!(e.contains("lone.json"), "{e}");
}

/// Regression (issue 12): a missing or garbage model was accepted by
/// `Device::new` and refused only when a session asked for it. The device
/// reads and checks it (manifest, ONNX bytes) and refuses naming the path,
/// with ONNX Runtime or without it.
#[test]
fn a_missing_or_garbage_model_is_refused_by_the_device() {
    let dir = tempfile::tempdir().unwrap();
    let garbage = dir.path().join("garbage.onnx");
    std::fs::write(&garbage, b"this is not an onnx model at all").unwrap();
    std::fs::copy(
        fixture("identity").with_extension("json"),
        garbage.with_extension("json"),
    )
    .unwrap();
    let missing = dir.path().join("no_such_model.onnx");
    let no_runtime = Some(PathBuf::from("/nonexistent/libonnxruntime.so.1.31.1"));
    for ort_library in [Some(ort_lib()), no_runtime.clone()] {
        let with = |model: ModelSource| DeviceOptions {
            ort_library: ort_library.clone(),
            ..options(model, 0)
        };
        let e = Device::new(with(ModelSource::File(missing.clone()))).unwrap_err();
        assert!(matches!(e, Error::Io(_)), "{e}");
        assert!(e.to_string().contains("no_such_model.onnx"), "{e}");
        let e = Device::new(with(ModelSource::File(garbage.clone()))).unwrap_err();
        assert!(matches!(e, Error::Model(_)), "{e}");
        assert!(
            e.to_string().contains("garbage.onnx") && e.to_string().contains("not an ONNX model"),
            "{e}"
        );
        let e = Device::new(with(ModelSource::Bytes {
            onnx: b"\x08\x07garbage".to_vec(),
            manifest: std::fs::read_to_string(fixture("identity").with_extension("json")).unwrap(),
        }))
        .unwrap_err();
        assert!(
            matches!(e, Error::Model(_)) && e.to_string().contains("in-memory model"),
            "{e}"
        );
        let e = Device::new(with(ModelSource::Bytes {
            onnx: std::fs::read(fixture("identity")).unwrap(),
            manifest: "{ not json".into(),
        }))
        .unwrap_err();
        assert!(matches!(e, Error::Model(_)), "{e}");
        // The graph's names are checked without the runtime too.
        let e = Device::new(with(ModelSource::File(fixture("wrong_name")))).unwrap_err();
        assert!(e.to_string().contains("\"x\""), "{e}");
        // A good model is accepted either way (without the runtime, the
        // session says so when it asks for the neural backend).
        let d = Device::new(with(ModelSource::File(fixture("identity")))).unwrap();
        assert_eq!(d.neural_model().is_ok(), ort_library != no_runtime);
    }
}

/// Regression (issue 12): tile settings that pass `set` and `commit` but
/// make every frame wider than a tile fail. They are refused at commit
/// (and by `Session::new`), naming the parameters, and nothing changes.
#[test]
fn tile_settings_that_cannot_tile_are_refused_at_commit() {
    let (w, h) = (333, 187);
    let rgb = hdr_rgb(w, h, 50);
    let input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    let device = device_file("box3");
    let mut s = session(device.clone(), &[]);
    let before = s.process(&input, None).unwrap().0;
    // box3: tile_size 128, tile_overlap 8, spatial_multiple 16.
    for (tile, overlap, names) in [
        (32, 16, "tile_size 32 and tile_overlap 16"),
        (1, 0, "tile_size 1 and tile_overlap 0 (the model's 8)"),
        (64, 64, "tile_size 64 and tile_overlap 64"),
        (0, 40, "tile_size 0 (the model's 128) and tile_overlap 40"),
    ] {
        s.set("tile_size", ParamValue::Int(tile)).unwrap();
        s.set("tile_overlap", ParamValue::Int(overlap)).unwrap();
        let e = s.commit().unwrap_err();
        let msg = e.to_string();
        assert!(matches!(e, Error::Invalid(_)), "{msg}");
        assert!(msg.contains(names) && msg.contains("box3"), "{msg}");
        assert!(msg.contains("use tile_size >="), "{msg}");
        // Frames of some widths fail with these settings; the committed
        // settings stay the old ones.
        assert_eq!(s.params().tile_size, 0);
        let params = Params {
            tile_size: tile as usize,
            tile_overlap: overlap as usize,
            ..Params::default()
        };
        let model = device.neural_model().unwrap().unwrap();
        assert!(
            (1..1000).any(|n| model.tile_plan(n, 16, &params).is_err()),
            "{tile} {overlap}: some frame widths fail"
        );
        let mut p = params.clone();
        p.backend = harmonizer_core::params::BackendKind::Neural;
        assert!(Session::new(device.clone(), p).is_err());
    }
    s.set("tile_size", ParamValue::Int(0)).unwrap();
    s.set("tile_overlap", ParamValue::Int(0)).unwrap();
    s.commit().unwrap();
    assert!(s.process(&input, None).unwrap().0 == before);
    // The smallest tile the message names works, one less does not.
    s.set("tile_size", ParamValue::Int(32)).unwrap();
    s.set("tile_overlap", ParamValue::Int(16)).unwrap();
    let msg = s.commit().unwrap_err().to_string();
    let smallest: i64 = msg
        .split("use tile_size >= ")
        .nth(1)
        .and_then(|t| t.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{msg}"));
    s.set("tile_size", ParamValue::Int(smallest - 1)).unwrap();
    assert!(s.commit().is_err());
    s.set("tile_size", ParamValue::Int(smallest)).unwrap();
    s.commit().unwrap();
    s.process(&input, None).unwrap();
}

#[test]
fn embedded_slot_is_empty_without_a_default_model() {
    let opts = options(ModelSource::Embedded, 0);
    match harmonizer_core::model::embedded() {
        None => assert!(NeuralModel::load(&opts).unwrap().is_none()),
        Some(_) => assert!(NeuralModel::load(&opts).unwrap().is_some()),
    }
}

#[test]
fn outputs_do_not_depend_on_threads_or_tiling_of_pointwise_models() {
    let (w, h) = (157, 93);
    let rgb = hdr_rgb(w, h, 30);
    let input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    // The same bits on 1, 2 and 3 threads, with one window and with many tiles.
    let run = |threads: usize, tile: i64| {
        let device = Device::new(DeviceOptions {
            threads,
            ..options(ModelSource::File(fixture("box3")), 0)
        })
        .unwrap();
        let mut s = session(
            device,
            &[
                ("tile_size", ParamValue::Int(tile)),
                ("tile_overlap", ParamValue::Int(4)),
            ],
        );
        s.process(&input, None).unwrap().0
    };
    for tile in [1024, 48] {
        let one = run(1, tile);
        for threads in [2, 3] {
            assert!(
                run(threads, tile) == one,
                "tile {tile}: {threads} threads differ from 1"
            );
        }
    }

    // A pointwise model gives the same result whatever the tiling: every input
    // channel kind (encoded history, validity, disparity, insert) lands in the
    // right place through the per-frame planes and the per-tile copies.
    let mut r = Rng(31);
    let insert: Vec<f32> = (0..w * h).map(|_| r.next()).collect();
    let depth: Vec<f32> = (0..w * h).map(|_| 0.5 + 20.0 * r.next()).collect();
    let mut input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    input.insert_mask = Some(ImageView::from_f32("insert", &insert, w, h, 1).unwrap());
    input.depth = Some(ImageView::from_f32("depth", &depth, w, h, 1).unwrap());
    let frame = PreparedFrame::from_input(&input, Default::default()).unwrap();
    let mut hist = Image::zeros(w, h, 4);
    hist.data.iter_mut().for_each(|v| *v = r.next() * 4.0);
    for (edit, picks) in [
        (false, "hist0.r, valid0, insert"),
        (true, "disparity, valid1, hist1.g"),
    ] {
        let device = device_edited("channel_probe", 0, |m| {
            if edit {
                let ch = m["input"]["channels"].as_array_mut().unwrap();
                ch.swap(5, 14); // hist0.r <-> disparity
                ch.swap(8, 12); // valid0 <-> valid1
                ch.swap(4, 10); // insert <-> hist1.g
            }
        });
        let model = device.neural_model().unwrap().unwrap();
        let prev = [hist.clone(), hist.clone()];
        let whole = Params {
            tile_size: 160,
            ..Params::default()
        };
        assert_eq!(model.tile_plan(w, h, &whole).unwrap().len(), 1);
        let tiled = Params {
            tile_size: 40,
            tile_overlap: 3,
            ..Params::default()
        };
        assert!(model.tile_plan(w, h, &tiled).unwrap().len() > 12);
        let a = run_backend(&model, &device, &frame, &prev, &whole);
        let b = run_backend(&model, &device, &frame, &prev, &tiled);
        for c in 0..3 {
            assert_close(
                b.plane(c),
                a.plane(c),
                1e-6,
                &format!("{picks}: channel {c}"),
            );
        }
        let want: Vec<f32> = if edit {
            depth.iter().map(|d| 1.0 / (1.0 + d)).collect()
        } else {
            hist.plane(0).to_vec()
        };
        assert_close(a.plane(0), &want, 1e-6, &format!("{picks}: channel 0"));
    }
}

#[test]
fn a_model_that_reads_normals_gets_them_through_the_session() {
    let (w, h) = (40, 30);
    let rgb = hdr_rgb(w, h, 40);
    let normal: Vec<f32> = (0..w * h).flat_map(|_| [0.0f32, 0.6, 0.8]).collect();
    // The probe's output b is input channel 4: here normal.y.
    let device = device_edited("channel_probe", 0, |m| {
        m["input"]["channels"][4] = "normal.y".into();
    });
    let mut s = session(device, &[]);
    let mut input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    input.normal = Some(ImageView::from_f32("normal", &normal, w, h, 3).unwrap());
    let (out, _) = s.process(&input, None).unwrap();
    assert!(
        out.plane(2).iter().all(|&v| (v - 0.6).abs() < 1e-6),
        "output.b = normal.y: {:?}",
        &out.plane(2)[..4]
    );
}

#[test]
fn a_frame_with_nothing_to_repair_skips_the_network() {
    // No hole, no insert: the network (a 3x3 box blur here) does not run
    // unless `neural_clean_frames`; the frame gets the classical operations,
    // bit for bit. With a hole it runs.
    let (w, h) = (64, 48);
    let rgb = hdr_rgb(w, h, 9);
    let input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    let device = device_file("box3");
    let run = |backend: &str, clean: bool, input: &FrameInput<'_>| {
        let mut params = Params::default();
        for (k, v) in [
            ("backend", ParamValue::Str(backend.into())),
            ("denoise", ParamValue::Str("off".into())),
            ("neural_clean_frames", ParamValue::Bool(clean)),
        ] {
            params.set(k, &v).unwrap();
        }
        let mut s = Session::new(device.clone(), params).unwrap();
        s.process(input, None).unwrap().0
    };
    let classical = run("classical", false, &input);
    assert!(run("neural", false, &input) == classical);
    assert!(run("neural", true, &input) != classical);
    let mut coverage = vec![1.0f32; w * h];
    coverage[w * 10 + 10] = 0.0;
    let mut holed = input;
    holed.coverage = Some(ImageView::from_f32("coverage", &coverage, w, h, 1).unwrap());
    assert!(run("neural", false, &holed) != run("classical", false, &holed));
}

#[test]
fn a_repair_margin_gives_covered_pixels_far_from_holes_their_rendered_color() {
    // The network (a 3x3 box blur) repaints everything; with the manifest's
    // `repair_margin` 2, covered pixels more than 2 px from a hole get
    // their rendered color back, at 2 px 0.4 of the network's output stays,
    // nearer and in the holes all of it. `keep_covered = false` turns it off.
    let (w, h) = (64, 48);
    let mut rgb = hdr_rgb(w, h, 11);
    let mut coverage = vec![1.0f32; w * h];
    for y in 20..24 {
        for x in 20..24 {
            coverage[y * w + x] = 0.0;
        }
    }
    // Covered above the floor (0.95): premultiplied by it.
    coverage[40 * w + 50] = 0.97;
    for (i, &c) in coverage.iter().enumerate() {
        for v in &mut rgb[3 * i..3 * i + 3] {
            *v *= c;
        }
    }
    let mut input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    input.coverage = Some(ImageView::from_f32("coverage", &coverage, w, h, 1).unwrap());
    let run_tiled = |margin: Option<u64>, keep: bool, tile: i64| {
        let device = device_edited("box3", 0, |m| {
            if let Some(k) = margin {
                m["repair_margin"] = k.into();
            }
        });
        let mut s = session(
            device,
            &[
                ("keep_covered", ParamValue::Bool(keep)),
                ("tile_size", ParamValue::Int(tile)),
                ("tile_overlap", ParamValue::Int(8)),
            ],
        );
        s.process(&input, None).unwrap().0
    };
    let run = |margin: Option<u64>, keep: bool| run_tiled(margin, keep, 128);
    let net = run(None, true);
    let kept = run(Some(2), true);
    assert!(run(Some(2), false) == net, "keep_covered off");
    // Several tiles (the margin applied after they are blended): the same
    // kept pixels, bit for bit, and the network's elsewhere within rounding.
    let tiled = run_tiled(Some(2), true, 32);
    let net_tiled = run_tiled(None, true, 32);
    for y in 0..h {
        for x in 0..w {
            for c in 0..3 {
                let (t, k) = (tiled.at(x, y, c), kept.at(x, y, c));
                if k == net.at(x, y, c) {
                    assert_eq!(t, net_tiled.at(x, y, c), "({x}, {y})");
                } else if (kept.at(x, y, c) - rgb[3 * (y * w + x) + c] / coverage[y * w + x]).abs()
                    == 0.0
                {
                    assert_eq!(t, k, "kept ({x}, {y})");
                }
            }
        }
    }
    let rendered = |x: usize, y: usize, c: usize| {
        let i = y * w + x;
        rgb[3 * i + c] / coverage[i]
    };
    for c in 0..3 {
        // Far from the hole: the rendered color, bit for bit.
        assert_eq!(kept.at(30, 22, c), rendered(30, 22, c));
        assert_eq!(kept.at(5, 5, c), rendered(5, 5, c));
        assert!((kept.at(50, 40, c) - rendered(50, 40, c)).abs() <= 1e-6 * rendered(50, 40, c));
        // The hole, and 1 px from it: the network's output.
        assert_eq!(kept.at(21, 21, c), net.at(21, 21, c));
        assert_eq!(kept.at(24, 22, c), net.at(24, 22, c));
        assert_eq!(kept.at(19, 19, c), net.at(19, 19, c));
        // 2 px from it: 0.4 of the network's output.
        let want = rendered(25, 22, c) + 0.4 * (net.at(25, 22, c) - rendered(25, 22, c));
        assert!((kept.at(25, 22, c) - want).abs() <= 1e-5 * want.abs().max(1.0));
    }
    // The network does change the far pixels (else the test proves nothing).
    assert!((0..3).any(|c| net.at(30, 22, c) != rendered(30, 22, c)));
    // A margin out of range names the field.
    let bad = Device::new(options(
        ModelSource::Bytes {
            onnx: std::fs::read(fixture("box3")).unwrap(),
            manifest: {
                let mut m = fixture_manifest("box3");
                m["repair_margin"] = 0.into();
                m.to_string()
            },
        },
        0,
    ))
    .unwrap_err()
    .to_string();
    assert!(bad.contains("repair_margin"), "{bad}");
}

/// The runtime's prior (`prior.r|g|b`, manifest `prior`) against the
/// trainer's, exported as graphs (`make_prior_fixtures.py`): on the same
/// frame and history, through the same tiles, the probe (which returns
/// the prior the runtime computed) and the graph (which computes it in
/// ONNX Runtime) give the same output. The frame has a large hole across
/// a depth edge, a one-pixel crack (where the gate keeps the history
/// out), soft and faint edges, and is tiled (64 px tiles) at a size that
/// is no multiple of 16.
#[test]
fn the_runtime_prior_is_the_trainers() {
    let (w, h) = (109, 75);
    let rgb = hdr_rgb(w, h, 21);
    let mut cov = vec![1.0f32; w * h];
    // A far wall and a near object, each rough by up to 8 % (more than the
    // 5 % tolerance: some of a surface's own pixels are left out too).
    let mut rough = Rng(22);
    let mut depth: Vec<f32> = (0..w * h)
        .map(|_| 8.0 * (1.0 + 0.08 * rough.next()))
        .collect();
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            if x < 50 {
                depth[i] = 2.0 * (1.0 + 0.08 * rough.next());
            }
            if (20..45).contains(&y) && (30..80).contains(&x) {
                cov[i] = 0.0;
                depth[i] = 1e10;
            } else if y == 19 && (30..80).contains(&x) {
                cov[i] = 0.5;
            } else if x == 15 && (5..60).contains(&y) {
                cov[i] = 0.0;
            } else if (x * 7 + y * 3) % 23 == 0 {
                // Faint (dropped below the 0.95 floor) and nearly full pixels.
                cov[i] = if x % 2 == 0 { 0.9 } else { 0.97 };
            }
        }
    }
    let premult = premultiply(&rgb, &cov);
    let mut input = FrameInput::new(ImageView::from_f32("color", &premult, w, h, 3).unwrap());
    input.coverage = Some(ImageView::from_f32("coverage", &cov, w, h, 1).unwrap());
    input.depth = Some(ImageView::from_f32("depth", &depth, w, h, 1).unwrap());
    let frame = PreparedFrame::from_input(&input, Default::default()).unwrap();
    let hist = |seed: u64| {
        let mut r = Rng(seed);
        let mut img = Image::zeros(w, h, 4);
        let n = w * h;
        img.data[..3 * n]
            .iter_mut()
            .for_each(|v| *v = r.next() * 4.0);
        img.data[3 * n..].fill(1.0);
        img
    };
    let prev = [hist(31), hist(32)];
    for (graph, tol) in [("prior_graph_far", 0.05), ("prior_graph_plain", 0.0)] {
        let want_dev = device_file(graph);
        let want_model = want_dev.neural_model().unwrap().unwrap();
        let got_dev = device_edited("prior_probe", 0, |m| {
            m["prior"]["depth_tol"] = tol.into();
        });
        let got_model = got_dev.neural_model().unwrap().unwrap();
        for context in [2, 1, 0] {
            let params = Params {
                context_frames: context,
                ..Params::default()
            };
            let want = run_backend(&want_model, &want_dev, &frame, &prev, &params);
            let got = run_backend(&got_model, &got_dev, &frame, &prev, &params);
            for c in 0..3 {
                assert_close(
                    &plane_of(&got, c),
                    &plane_of(&want, c),
                    1e-4,
                    &format!("{graph}, {context} history frames, channel {c}"),
                );
            }
            // Not trivial: the holes were filled, and differently with history.
            let at = 30 * w + 60;
            assert!(want.plane(0)[at] > 0.0, "{graph}: the hole is filled");
        }
    }
}

/// The manifest's `prior.edge_fill` (the runtime's edge-continuing fill in
/// what the history left missing): through the probe (which returns the
/// prior), a hole across a horizontal edge is filled with the edge going on
/// through it, much nearer the frame's own colors than the push-pull's
/// blend of both sides, every covered pixel is the same with it as
/// without, and one thread gives the same bits as two.
#[test]
fn the_edge_fill_carries_an_edge_through_a_hole() {
    let (w, h) = (96, 64);
    let dark = [0.05f32, 0.04, 0.03];
    let light = [0.8f32, 0.7, 0.6];
    let truth: Vec<f32> = (0..w * h)
        .flat_map(|i| if i / w < 32 { dark } else { light })
        .collect();
    let hole = |i: usize| (30..66).contains(&(i % w)) && (20..44).contains(&(i / w));
    let cov: Vec<f32> = (0..w * h)
        .map(|i| if hole(i) { 0.0 } else { 1.0 })
        .collect();
    let premult = premultiply(&truth, &cov);
    let depth = vec![5.0f32; w * h];
    let mut input = FrameInput::new(ImageView::from_f32("color", &premult, w, h, 3).unwrap());
    input.coverage = Some(ImageView::from_f32("coverage", &cov, w, h, 1).unwrap());
    input.depth = Some(ImageView::from_f32("depth", &depth, w, h, 1).unwrap());
    let frame = PreparedFrame::from_input(&input, Default::default()).unwrap();
    let params = Params {
        context_frames: 0,
        ..Params::default()
    };
    let run = |share: f32, threads: usize| {
        let mut m = fixture_manifest("prior_probe");
        m["prior"]["edge_fill"] = share.into();
        let dev = Device::new(DeviceOptions {
            threads,
            ..options(
                ModelSource::Bytes {
                    onnx: std::fs::read(fixture("prior_probe")).unwrap(),
                    manifest: m.to_string(),
                },
                0,
            )
        })
        .unwrap();
        let model = dev.neural_model().unwrap().unwrap();
        run_backend(&model, &dev, &frame, &[], &params)
    };
    let (plain, edge) = (run(0.0, 2), run(1.0, 2));
    // The same bits on one thread (the planes are filled in parallel along
    // one order).
    assert_eq!(run(1.0, 1).data, edge.data, "one thread against two");
    // The error in the hole, relative to the step across the edge.
    let err = |img: &Image| {
        let mut sum = 0.0f32;
        let mut n = 0usize;
        for c in 0..3 {
            for (i, v) in img.plane(c).iter().enumerate() {
                if hole(i) {
                    sum += (v - truth[3 * i + c]).abs() / (light[c] - dark[c]);
                    n += 1;
                }
            }
        }
        sum / n as f32
    };
    let (e_plain, e_edge) = (err(&plain), err(&edge));
    assert!(
        e_edge < 0.6 * e_plain && e_edge < 0.15,
        "edge fill {e_edge}, push-pull {e_plain}"
    );
    for c in 0..3 {
        for (i, (a, b)) in plain.plane(c).iter().zip(edge.plane(c)).enumerate() {
            if !hole(i) {
                assert_eq!(a, b, "covered pixel ({}, {}), channel {c}", i % w, i / w);
            }
        }
    }
}
