//! The whole session (`Session::process`) on a synthetic sequence, frame
//! after frame, with per-stage medians: the figure issue 2's speed target is
//! about, without the synthesis in the measurement (frames are made first).
//!
//! `cargo bench -p harmonizer-core --bench session -- [WxH] [frames] [threads] [backend] [passes]`
//! (defaults: 1920x1080, 6 frames, 2 threads, classical, 1 pass). The first
//! two frames of each pass are warm-up (a cold start, then the first frame
//! with history) and are not counted.

use harmonizer_core::synth::{Scene, SynthConfig};
use harmonizer_core::{Device, DeviceOptions, ParamValue, Params, Session};

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
    let frames: usize = arg(1, "6").parse().expect("frames");
    let threads: usize = arg(2, "2").parse().expect("threads");
    let backend = arg(3, "classical");
    let passes: usize = arg(4, "1").parse().expect("passes");
    let warmup = 2;

    let scene = Scene::new(SynthConfig {
        width: w,
        height: h,
        frames,
        seed: 1,
        first_frame: 1,
    })
    .expect("synthetic scene");
    let made: Vec<_> = (0..frames).map(|t| scene.frame(1 + t as i64)).collect();
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
            session.recycle(out);
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
    println!(
        "{backend} {w}x{h} threads={threads}: {:.2} ms/frame (median of {}), stages: {}",
        median(totals.clone()),
        totals.len(),
        stages.join(", ")
    );
}
