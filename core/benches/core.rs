//! Criterion benches of harmonizer-core, one function per group.
//!
//! Run one group: `cargo bench -p harmonizer-core --bench core -- reprojection`.

use criterion::{criterion_group, criterion_main, Criterion};
use harmonizer_core::frame::{DepthKind, Image, PreparedFrame, RgbaImage};
use harmonizer_core::synth::{Scene, SynthConfig};
use harmonizer_core::temporal::{History, HistoryFrame, HistoryView};

/// Threads of the benches' pool (the 25 ms/frame budget is for 2 cores).
const THREADS: usize = 2;

fn pool() -> rayon::ThreadPool {
    rayon::ThreadPoolBuilder::new()
        .num_threads(THREADS)
        .build()
        .expect("bench pool")
}

/// Reprojection of history frames into the current view at 1920x1080:
/// motion vectors (k = 0, and k = 3 through the chain), depth + cameras
/// (k = 0), and the preparation of the frame it starts from.
fn reprojection(c: &mut Criterion) {
    let (w, h) = (1920, 1080);
    let scene = Scene::new(SynthConfig {
        width: w,
        height: h,
        frames: 5,
        seed: 1,
        first_frame: 0,
    })
    .expect("synthetic scene");
    let frames: Vec<_> = (0..5).map(|t| scene.frame(t)).collect();
    let pool = pool();
    let mut history = History::default();
    for f in &frames[..4] {
        let p = PreparedFrame::from_input(&f.input.frame_input(), DepthKind::Planar).unwrap();
        let n = w * h;
        let mut color = Image::zeros(w, h, 4);
        color.data[..3 * n].copy_from_slice(&p.color.data);
        color.data[3 * n..].copy_from_slice(p.coverage.as_deref().unwrap());
        let frame = HistoryFrame {
            color: RgbaImage::from_planes(&color, None),
            depth: p.depth,
            motion: p.motion,
            camera: p.camera,
            frame_index: p.frame_index,
        };
        history.push(frame, 4);
    }
    let input = frames[4].input.frame_input();
    let current = PreparedFrame::from_input(&input, DepthKind::Planar).unwrap();
    let mut static_input = input;
    static_input.motion = None;
    let current_static = PreparedFrame::from_input(&static_input, DepthKind::Planar).unwrap();

    let mut g = c.benchmark_group("reprojection");
    g.sample_size(20);
    g.bench_function("prepare_1080p", |b| {
        b.iter(|| PreparedFrame::from_input_on(&input, DepthKind::Planar, &pool).unwrap())
    });
    g.bench_function("motion_k0_1080p", |b| {
        b.iter(|| {
            HistoryView::new(&history, &current, 4, &pool)
                .reproject(0)
                .valid[0]
        })
    });
    g.bench_function("motion_k3_chained_1080p", |b| {
        b.iter(|| {
            HistoryView::new(&history, &current, 4, &pool)
                .reproject(3)
                .valid[0]
        })
    });
    g.bench_function("depth_camera_k0_1080p", |b| {
        b.iter(|| {
            HistoryView::new(&history, &current_static, 4, &pool)
                .reproject(0)
                .valid[0]
        })
    });
    g.finish();
}

/// The neural backend with the `box3` fixture model (a 3x3 box filter, so the
/// time is the tiling machinery: encoding, tile assembly, ONNX Runtime calls,
/// feathered blending) at 1024x576: untiled, and in 256 px and 128 px tiles.
/// Needs ONNX Runtime (`scripts/setup-venv.sh`).
fn tiling(c: &mut Criterion) {
    use harmonizer_core::backend::neural::{runtime, Neural};
    use harmonizer_core::backend::{Backend, BackendInput, Carry, Progress, Stages};
    use harmonizer_core::{Device, DeviceOptions, FrameInput, ImageView, ModelSource, Params};

    let lib = runtime::locate(None).unwrap_or_else(|e| {
        panic!("the tiling bench needs ONNX Runtime: run scripts/setup-venv.sh ({e})")
    });
    let model_path =
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/models/box3.onnx");
    let device = Device::new(DeviceOptions {
        threads: THREADS,
        ort_library: Some(lib),
        memory_limit: 0,
        model: ModelSource::File(model_path),
        oidn_library: None,
    })
    .expect("device");
    let model = device.neural_model().expect("box3 model").expect("a model");
    let backend = Neural {
        model: model.clone(),
    };
    let (w, h) = (1024, 576);
    let rgb: Vec<f32> = (0..w * h * 3)
        .map(|i| ((i * 7919) % 1000) as f32 / 250.0)
        .collect();
    let input = FrameInput::new(ImageView::from_f32("color", &rgb, w, h, 3).unwrap());
    let frame = PreparedFrame::from_input(&input, DepthKind::Planar).unwrap();
    let history = History::default();

    let mut g = c.benchmark_group("tiling");
    g.sample_size(10);
    for (name, tile, overlap) in [
        ("untiled", 2048, 16),
        ("tiles_256", 256, 16),
        ("tiles_128", 128, 16),
    ] {
        let params = Params {
            tile_size: tile,
            tile_overlap: overlap,
            ..Params::default()
        };
        let tiles = model.tile_plan(w, h, &params).expect("tile plan").len();
        g.bench_function(format!("box3_1024x576_{name}_{tiles}"), |b| {
            b.iter(|| {
                let view = HistoryView::new(&history, &frame, 4, device.pool());
                let input = BackendInput {
                    frame: &frame,
                    history: &view,
                    params: &params,
                    pool: device.pool(),
                    kept: None,
                    scene_probe: None,
                    memory_budget: usize::MAX,
                };
                backend
                    .process(
                        &input,
                        &mut Carry::default(),
                        &mut Progress::new(None),
                        &mut Stages::default(),
                    )
                    .unwrap()
            })
        });
    }
    g.finish();
}

/// The classical backend at 1920x1080 with K = 4 on the synthetic scene
/// (holes, an inserted sphere, flicker), the plain copy of the same bytes
/// (the bypass backend: the memory-bandwidth floor), and each operation alone.
fn classical(c: &mut Criterion) {
    use harmonizer_core::backend::classical::{rgba_from_frame, Classical};
    use harmonizer_core::backend::{Backend, BackendInput, Bypass, Carry, Progress, Stages};
    use harmonizer_core::ops::{harmonize, inpaint, shadow, stabilize};
    use harmonizer_core::Params;

    let (w, h) = (1920, 1080);
    let scene = Scene::new(SynthConfig {
        width: w,
        height: h,
        frames: 5,
        seed: 1,
        first_frame: 0,
    })
    .expect("synthetic scene");
    let frames: Vec<_> = (0..5).map(|t| scene.frame(t)).collect();
    let pool = pool();
    // History: enhanced frames stand-in (the ground truth, A = 1).
    let mut history = History::default();
    for f in &frames[..4] {
        let p = PreparedFrame::from_input(&f.input.frame_input(), DepthKind::Planar).unwrap();
        let n = w * h;
        let mut color = Image::filled(w, h, 4, 1.0);
        for i in 0..n {
            for ch in 0..3 {
                color.data[ch * n + i] = f.truth[3 * i + ch];
            }
        }
        let frame = HistoryFrame {
            color: RgbaImage::from_planes(&color, None),
            depth: p.depth,
            motion: p.motion,
            camera: p.camera,
            frame_index: p.frame_index,
        };
        history.push(frame, 4);
    }
    let current =
        PreparedFrame::from_input(&frames[4].input.frame_input(), DepthKind::Planar).unwrap();
    let params = Params::default();
    let run = |backend: &dyn Backend, view: &HistoryView<'_>| {
        let input = BackendInput {
            frame: &current,
            history: view,
            params: &params,
            pool: &pool,
            kept: None,
            scene_probe: None,
            memory_budget: usize::MAX,
        };
        let mut carry = Carry::default();
        let mut progress = Progress::new(None);
        let mut stages = Stages::default();
        backend
            .process(&input, &mut carry, &mut progress, &mut stages)
            .unwrap()
    };

    let mut g = c.benchmark_group("classical");
    g.sample_size(20);
    g.bench_function("copy_floor_1080p", |b| {
        b.iter(|| run(&Bypass, &HistoryView::new(&history, &current, 4, &pool)))
    });
    g.bench_function("backend_1080p_k4", |b| {
        b.iter(|| run(&Classical, &HistoryView::new(&history, &current, 4, &pool)))
    });
    let warm = HistoryView::new(&history, &current, 4, &pool);
    for k in 0..4 {
        warm.reproject(k);
    }
    g.bench_function("backend_1080p_k4_reprojected", |b| {
        b.iter(|| run(&Classical, &warm))
    });

    let rgba = pool.install(|| rgba_from_frame(&current));
    let holes = inpaint::find_holes(&rgba).expect("the synthetic frame has holes");
    g.bench_function("push_pull_1080p", |b| {
        b.iter_batched_ref(
            || rgba.clone(),
            |img| pool.install(|| inpaint::push_pull(img, inpaint::fill_window(holes.rect, w, h))),
            criterion::BatchSize::LargeInput,
        )
    });
    g.bench_function("history_fill_1080p", |b| {
        b.iter_batched_ref(
            || rgba.clone(),
            |img| pool.install(|| inpaint::fill_from_history(img, warm.reproject(0), holes.rect)),
            criterion::BatchSize::LargeInput,
        )
    });
    let mask = current.insert_mask.as_deref().expect("insert mask");
    let depth = current.depth.as_deref().expect("depth");
    let rect = harmonize::insert_rect(mask, w, h).expect("an insert");
    g.bench_function("harmonize_1080p", |b| {
        b.iter_batched_ref(
            || rgba.clone(),
            |img| {
                pool.install(|| {
                    let tone = harmonize::estimate(
                        img,
                        mask,
                        rect,
                        current.coverage.as_deref(),
                        Some(depth),
                    );
                    harmonize::apply(img, mask, rect, &tone.unwrap_or(harmonize::Tone::IDENTITY));
                })
            },
            criterion::BatchSize::LargeInput,
        )
    });
    g.bench_function("shadow_1080p", |b| {
        b.iter_batched_ref(
            || rgba.clone(),
            |img| pool.install(|| shadow::contact_shadow(img, mask, rect, depth, 0.6)),
            criterion::BatchSize::LargeInput,
        )
    });
    g.bench_function("stabilize_1080p", |b| {
        b.iter_batched_ref(
            || rgba.clone(),
            |img| pool.install(|| stabilize::stabilize(img, warm.reproject(0), 0.6)),
            criterion::BatchSize::LargeInput,
        )
    });
    g.finish();
}

criterion_group!(benches, reprojection, tiling, classical);
criterion_main!(benches);
