//! Overhead of the C ABI against calling the core directly: the same frames,
//! the same session settings, the same RGBA output buffer.
//!
//! `cargo bench -p harmonizer-ffi --bench abi` runs the criterion groups and
//! then an interleaved comparison (direct and ABI calls alternate frame by
//! frame, so load from other processes hits both alike) that prints the
//! median ms/frame of each path and the overhead in percent (target <= 2 %).
//! `-- --summary-only` skips the criterion groups; `cargo test --benches`
//! runs each criterion benchmark once and skips the summary.

use std::ffi::CString;
use std::ptr::null;
use std::sync::Arc;
use std::time::Instant;

use criterion::Criterion;
use harmonizer::device::{hz_device, hz_device_free, hz_device_new, hz_device_options};
use harmonizer::hz_status::HZ_OK;
use harmonizer::image::{hz_format, hz_image};
use harmonizer::session::{
    hz_frame, hz_session, hz_session_commit, hz_session_free, hz_session_new, hz_session_process,
    hz_session_set_string, HZ_FRAME_HAS_INDEX,
};
use harmonizer_core::{
    Device, DeviceOptions, FrameInput, ImageView, ImageViewMut, Params, Session,
};

const THREADS: usize = 2;
const PERIOD: usize = 8;

/// A sequence periodic in `PERIOD` frames (no scene cut at the wrap): a
/// texture moving one pixel per frame with matching motion vectors, a hole.
struct Frames {
    w: usize,
    h: usize,
    color: Vec<Vec<f32>>, // RGBA
    coverage: Vec<f32>,
    motion: Vec<f32>,
    depth: Vec<f32>,
}

fn frames(w: usize, h: usize) -> Frames {
    let tau = std::f32::consts::TAU;
    let mut coverage = vec![1.0f32; w * h];
    for y in h / 3..h / 3 + h / 10 {
        for x in w / 3..w / 3 + w / 10 {
            coverage[y * w + x] = 0.0;
        }
    }
    let color = (0..PERIOD)
        .map(|t| {
            let mut c = vec![0.0f32; w * h * 4];
            for y in 0..h {
                for x in 0..w {
                    let i = y * w + x;
                    let u = (x + PERIOD - t % PERIOD) as f32 / PERIOD as f32;
                    let v = 0.5 + 0.4 * (tau * u).sin() * (y as f32 * 0.05).cos();
                    let a = coverage[i];
                    c[i * 4..i * 4 + 4].copy_from_slice(&[a * v, a * (1.0 - v), a * 0.5, a]);
                }
            }
            c
        })
        .collect();
    let mut motion = vec![0.0f32; w * h * 2];
    motion.chunks_mut(2).for_each(|m| m[0] = -1.0);
    Frames {
        w,
        h,
        color,
        coverage,
        motion,
        depth: vec![5.0; w * h],
    }
}

fn hz_img(data: *const f32, w: usize, h: usize, channels: u32) -> hz_image {
    hz_image {
        struct_size: std::mem::size_of::<hz_image>(),
        format: hz_format::HZ_FORMAT_F32 as u32,
        channels,
        width: w,
        height: h,
        offset: 0,
        pixel_stride: 0,
        row_stride: 0,
        data: data as *mut _,
    }
}

/// The direct path: a core session, as a Rust host would use it.
struct Direct {
    session: Session,
    index: i64,
}

impl Direct {
    fn new(device: &Arc<Device>, backend: &str) -> Direct {
        let mut params = Params::default();
        params
            .set("backend", &harmonizer_core::ParamValue::Str(backend.into()))
            .unwrap();
        Direct {
            session: Session::new(device.clone(), params).unwrap(),
            index: 0,
        }
    }
    fn step(&mut self, f: &Frames, out: &mut [f32]) {
        let t = self.index as usize % PERIOD;
        let (w, h) = (f.w, f.h);
        let mut input =
            FrameInput::new(ImageView::from_f32("color", &f.color[t], w, h, 4).unwrap());
        input.coverage = Some(ImageView::from_f32("coverage", &f.coverage, w, h, 1).unwrap());
        input.motion = Some(ImageView::from_f32("motion", &f.motion, w, h, 2).unwrap());
        input.depth = Some(ImageView::from_f32("depth", &f.depth, w, h, 1).unwrap());
        input.frame_index = Some(self.index);
        let mut o = ImageViewMut::from_f32("output", out, w, h, 4).unwrap();
        self.session.process_into(&input, &mut o, None).unwrap();
        self.index += 1;
    }
}

/// The C ABI path, through the exported functions.
struct Abi {
    session: *mut hz_session,
    index: i64,
}

impl Abi {
    fn new(device: &hz_device, backend: &str) -> Abi {
        let mut s = std::ptr::null_mut();
        let b = CString::new(backend).unwrap();
        // SAFETY: valid handles and NUL-terminated strings.
        unsafe {
            assert_eq!(hz_session_new(device, &mut s), HZ_OK);
            assert_eq!(
                hz_session_set_string(s, c"backend".as_ptr(), b.as_ptr()),
                HZ_OK
            );
            assert_eq!(hz_session_commit(s), HZ_OK);
        }
        Abi {
            session: s,
            index: 0,
        }
    }
    fn step(&mut self, f: &Frames, out: &mut [f32]) {
        let t = self.index as usize % PERIOD;
        let (w, h) = (f.w, f.h);
        let color = hz_img(f.color[t].as_ptr(), w, h, 4);
        let coverage = hz_img(f.coverage.as_ptr(), w, h, 1);
        let motion = hz_img(f.motion.as_ptr(), w, h, 2);
        let depth = hz_img(f.depth.as_ptr(), w, h, 1);
        let output = hz_img(out.as_mut_ptr(), w, h, 4);
        let frame = hz_frame {
            struct_size: std::mem::size_of::<hz_frame>(),
            color: &color,
            depth: &depth,
            motion: &motion,
            normal: null(),
            coverage: &coverage,
            insert_mask: null(),
            world_to_camera: null(),
            world_to_ndc: null(),
            frame_index: self.index,
            flags: HZ_FRAME_HAS_INDEX,
            motion_vector_scale: [1.0, 1.0],
            albedo: null(),
            denoise_normal: null(),
            insert_id: null(),
        };
        // SAFETY: every buffer outlives the call and matches its description.
        assert_eq!(
            unsafe { hz_session_process(self.session, &frame, &output) },
            HZ_OK
        );
        self.index += 1;
    }
}

impl Drop for Abi {
    fn drop(&mut self) {
        // SAFETY: a live handle, freed once.
        unsafe { hz_session_free(self.session) };
    }
}

/// A core device and an ABI device with the same settings (each its own pool
/// of `THREADS` threads; an idle pool sleeps).
fn device() -> (Arc<Device>, Dev) {
    let opts = DeviceOptions {
        threads: THREADS,
        ..DeviceOptions::default()
    };
    let core = Device::new(opts).unwrap();
    let o = hz_device_options {
        struct_size: std::mem::size_of::<hz_device_options>(),
        threads: THREADS as u32,
        memory_limit: 0,
        ort_library: null(),
        model_path: null(),
        model_data: null(),
        model_data_size: 0,
        model_manifest: null(),
    };
    let mut d = std::ptr::null_mut();
    // SAFETY: valid options and out pointer.
    assert_eq!(unsafe { hz_device_new(0, &o, &mut d) }, HZ_OK);
    (core, Dev(d))
}

/// An owned ABI device handle.
struct Dev(*mut hz_device);

impl std::ops::Deref for Dev {
    type Target = hz_device;
    fn deref(&self) -> &hz_device {
        // SAFETY: a live handle until drop.
        unsafe { &*self.0 }
    }
}

impl Drop for Dev {
    fn drop(&mut self) {
        // SAFETY: a live handle, freed once.
        unsafe { hz_device_free(self.0) };
    }
}

const SIZES: [(usize, usize); 2] = [(1024, 576), (1920, 1080)];
const BACKENDS: [&str; 2] = ["bypass", "classical"];

fn criterion_groups(c: &mut Criterion) {
    let (core_dev, abi_dev) = device();
    for (w, h) in SIZES {
        let f = frames(w, h);
        let mut out = vec![0.0f32; w * h * 4];
        for backend in BACKENDS {
            let mut g = c.benchmark_group(format!("abi/{backend}/{w}x{h}"));
            g.sample_size(10);
            let mut direct = Direct::new(&core_dev, backend);
            g.bench_function("direct", |b| b.iter(|| direct.step(&f, &mut out)));
            let mut abi = Abi::new(&abi_dev, backend);
            g.bench_function("c_abi", |b| b.iter(|| abi.step(&f, &mut out)));
            g.finish();
        }
    }
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// Direct and ABI calls alternate frame by frame; returns the JSON lines.
fn interleaved() -> Vec<String> {
    let (core_dev, abi_dev) = device();
    let mut lines = Vec::new();
    for (w, h) in SIZES {
        let f = frames(w, h);
        let mut out_d = vec![0.0f32; w * h * 4];
        let mut out_a = vec![0.0f32; w * h * 4];
        for backend in BACKENDS {
            let n = if backend == "bypass" { 120 } else { 40 };
            let mut direct = Direct::new(&core_dev, backend);
            let mut abi = Abi::new(&abi_dev, backend);
            for _ in 0..PERIOD {
                direct.step(&f, &mut out_d);
                abi.step(&f, &mut out_a);
            }
            let (mut td, mut ta) = (Vec::with_capacity(n), Vec::with_capacity(n));
            for i in 0..n {
                // Alternate which path goes first, so neither always runs on a warm cache.
                let order = if i % 2 == 0 { [0, 1] } else { [1, 0] };
                for which in order {
                    let t0 = Instant::now();
                    if which == 0 {
                        direct.step(&f, &mut out_d);
                    } else {
                        abi.step(&f, &mut out_a);
                    }
                    let ms = t0.elapsed().as_secs_f64() * 1e3;
                    if which == 0 {
                        td.push(ms)
                    } else {
                        ta.push(ms)
                    }
                }
                assert!(out_d == out_a, "{backend} {w}x{h}: the two paths disagree");
            }
            let (md, ma) = (median(&mut td), median(&mut ta));
            lines.push(format!(
                "{{\"backend\": \"{backend}\", \"width\": {w}, \"height\": {h}, \"threads\": {THREADS}, \
                 \"frames\": {n}, \"direct_ms\": {md:.3}, \"abi_ms\": {ma:.3}, \"overhead_percent\": {:.2}}}",
                (ma / md - 1.0) * 100.0
            ));
        }
    }
    lines
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    // `cargo bench` passes `--bench`; without it (`cargo test --benches`)
    // criterion runs each benchmark once as a test and the summary is skipped.
    let benching = args.iter().any(|a| a == "--bench");
    let summary_only = args.iter().any(|a| a == "--summary-only");
    if !summary_only {
        let mut c = Criterion::default().configure_from_args();
        criterion_groups(&mut c);
        c.final_summary();
    }
    if benching || summary_only {
        println!("ABI overhead (median ms/frame, direct and ABI interleaved):");
        for line in interleaved() {
            println!("{line}");
        }
    }
}
