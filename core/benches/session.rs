//! The whole session (`Session::process`) on a synthetic sequence, frame
//! after frame, with per-stage medians: the figure issue 2's speed target is
//! about, without the synthesis in the measurement (frames are made first).
//!
//! `cargo bench -p harmonizer-core --bench session -- [WxH] [frames] [threads] [backend] [passes]`
//! (defaults: 1920x1080, 10 frames, 2 threads, classical, 1 pass). The first
//! `context_frames + 1` frames of each pass are warm-up (a cold start, then
//! the history filling up, its buffers fresh memory) and are not counted. Outputs are given back with
//! `Session::recycle`, as a host that reuses them does; with the environment
//! variable `HZ_BENCH_NO_RECYCLE` set they are dropped instead.
//!
//! With backend `parts`, times the shared parts alone instead, many times
//! each on the same data, and prints the minimum and the median (the
//! minimum is the figure least disturbed by other work on the machine):
//! preparing a frame, reprojecting history frame 0 and frame 3 (chained).

use harmonizer_core::frame::{DepthKind, Image, PreparedFrame, Recycler, RgbaImage};
use harmonizer_core::synth::{Scene, SynthConfig, SynthFrame};
use harmonizer_core::temporal::{History, HistoryFrame, HistoryView};
use harmonizer_core::{Device, DeviceOptions, ParamValue, Params, Session};

/// Runs `f` `n` times; prints the minimum and median time in ms.
fn time(name: &str, n: usize, mut f: impl FnMut()) {
    let mut t = Vec::with_capacity(n);
    for _ in 0..n {
        let t0 = std::time::Instant::now();
        f();
        t.push(t0.elapsed().as_secs_f64() * 1e3);
    }
    let min = t.iter().copied().fold(f64::INFINITY, f64::min);
    println!("{name:<28} min {min:8.2} ms  median {:8.2} ms", median(t));
}

/// The shared parts alone (see the module docs).
fn parts(made: &[SynthFrame], threads: usize, runs: usize) {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .expect("pool");
    let rec = Recycler::new();
    let prep = |f: &SynthFrame| {
        PreparedFrame::from_input_recycled(
            &f.input.frame_input(),
            DepthKind::Planar,
            &pool,
            &rec,
            false,
            false,
        )
        .expect("frame prepared")
    };
    let (last, older) = made.split_last().expect("frames");
    let mut history = History::default();
    for f in older {
        let p = prep(f);
        let (w, h) = (p.width(), p.height());
        let mut color = Image::zeros(w, h, 4);
        let n = w * h;
        color.data[..3 * n].copy_from_slice(&p.color.data);
        color.data[3 * n..].copy_from_slice(p.coverage.as_deref().expect("coverage"));
        history.push(
            HistoryFrame {
                color: RgbaImage::from_planes(&color, None),
                depth: p.depth,
                motion: p.motion,
                camera: p.camera,
                frame_index: p.frame_index,
            },
            4,
        );
    }
    time("prepare", runs, || prep(last).recycle(&rec));
    let current = prep(last);
    time("reproject k=0", runs, || {
        let view = HistoryView::new_recycled(&history, &current, 4, &pool, &rec);
        std::hint::black_box(view.reproject(0));
    });
    if history.len() >= 4 {
        time("reproject k=3 (chained)", runs, || {
            let view = HistoryView::new_recycled(&history, &current, 4, &pool, &rec);
            std::hint::black_box(view.reproject(3));
        });
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with("--"))
        .collect();
    let arg = |i: usize, d: &str| args.get(i).cloned().unwrap_or_else(|| d.to_string());
    let size = arg(0, "1920x1080");
    let (w, h) = size
        .split_once('x')
        .and_then(|(w, h)| Some((w.parse::<usize>().ok()?, h.parse::<usize>().ok()?)))
        .expect("size as WxH");
    let frames: usize = arg(1, "10").parse().expect("frames");
    let threads: usize = arg(2, "2").parse().expect("threads");
    let backend = arg(3, "classical");
    let passes: usize = arg(4, "1").parse().expect("passes");
    // Steady state: the history fills (and its buffers come from fresh
    // memory) over the first `context_frames` frames.
    let warmup = (Params::default().context_frames + 1).max(2);

    let scene = Scene::new(SynthConfig {
        width: w,
        height: h,
        frames,
        seed: 1,
        first_frame: 1,
    })
    .expect("synthetic scene");
    let made: Vec<_> = (0..frames).map(|t| scene.frame(1 + t as i64)).collect();
    if backend == "parts" {
        parts(&made, threads, 10 * passes);
        return;
    }
    let device = Device::new(DeviceOptions {
        threads,
        ..DeviceOptions::default()
    })
    .expect("device");
    let mut params = Params::default();
    params
        .set("backend", &ParamValue::Str(backend.clone()))
        .expect("backend parameter");
    let mut session = Session::new(device, params).expect("session");
    eprintln!("frames made; processing");

    let mut totals = Vec::new();
    let mut stages: Vec<(String, Vec<f64>)> = Vec::new();
    for _ in 0..passes {
        session.reset();
        for (t, f) in made.iter().enumerate() {
            let (out, report) = session
                .process(&f.input.frame_input(), None)
                .expect("frame processed");
            if std::env::var_os("HZ_BENCH_NO_RECYCLE").is_none() {
                session.recycle(out);
            }
            if t < warmup {
                continue;
            }
            totals.push(report.total_ms);
            for (k, v) in &report.stages.0 {
                match stages.iter_mut().find(|(n, _)| n == k) {
                    Some(e) => e.1.push(*v),
                    None => stages.push((k.clone(), vec![*v])),
                }
            }
        }
    }
    let stages: Vec<String> = stages
        .into_iter()
        .map(|(k, v)| format!("{k} {:.2}", median(v)))
        .collect();
    let min = totals.iter().copied().fold(f64::INFINITY, f64::min);
    println!(
        "{backend} {w}x{h} threads={threads}: {:.2} ms/frame (median of {}, min {min:.2}), stages: {}",
        median(totals.clone()),
        totals.len(),
        stages.join(", ")
    );
}
