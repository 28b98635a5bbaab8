//! Criterion benches of harmonizer-core, one function per group.
//!
//! Run one group: `cargo bench -p harmonizer-core --bench core -- reprojection`.

use criterion::{criterion_group, criterion_main, Criterion};
use harmonizer_core::frame::{DepthKind, Image, PreparedFrame};
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
            color,
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

criterion_group!(benches, reprojection);
criterion_main!(benches);
