//! The session's denoise stage (`denoise`, `denoise_quality`, `samples`)
//! on the real Open Image Denoise (the `pyoidn` wheel in the project's
//! `.venv`; a missing library fails these tests, except the one that
//! names a missing library on purpose): the PSNR gain on a noisy
//! synthetic sequence, `auto` from the host's sample count and from the
//! noise estimate, the albedo from an EXR's generic layout to the
//! denoiser, a failed or cancelled frame, a missing library.
//!
//! The noisy sequence is the synthetic scene (`synth::Scene`) with
//! `synth::render_noise` at 4 samples per pixel on its color; PSNR is
//! `synth::psnr` (scene-linear, peak 1) against the ground truth on the
//! pixels where the input's only fault is the noise (no hole, no insert,
//! no missing shadow). Measured values are printed (`--nocapture`).

use std::path::Path;
use std::sync::Arc;

use harmonizer_core::denoise::{
    noise_level, DenoiseInput, DenoiseOptions, Denoiser, Quality, NOISE_THRESHOLD,
};
use harmonizer_core::frame::{ImageView, PreparedFrame};
use harmonizer_core::io::exr::{write_channels, LoadedFrame, OutChannel};
use harmonizer_core::io::layout::LayoutOptions;
use harmonizer_core::synth::{self, Scene, SynthConfig, SynthFrame};
use harmonizer_core::{
    DepthKind, Device, DeviceOptions, Error, FrameShape, Image, ParamValue, Session,
};

const W: usize = 192;
const H: usize = 108;

fn device(oidn_library: Option<&str>) -> Arc<Device> {
    Device::new(DeviceOptions {
        threads: 2,
        oidn_library: oidn_library.map(Into::into),
        ..DeviceOptions::default()
    })
    .unwrap()
}

fn session(dev: &Arc<Device>, params: &[(&str, ParamValue)]) -> Session {
    let mut s = Session::new(dev.clone(), Default::default()).unwrap();
    s.set("backend", ParamValue::Str("classical".into()))
        .unwrap();
    for (k, v) in params {
        s.set(k, v.clone()).unwrap();
    }
    s.commit().unwrap();
    s
}

fn s(v: &str) -> ParamValue {
    ParamValue::Str(v.into())
}

/// `frames` frames of the synthetic scene at `w` x `h`; with `samples`,
/// their color carries the noise of that many samples per pixel.
fn frames(w: usize, h: usize, frames: usize, samples: Option<u32>) -> Vec<SynthFrame> {
    let scene = Scene::new(SynthConfig {
        width: w,
        height: h,
        frames,
        seed: 3,
        first_frame: 1,
    })
    .unwrap();
    (0..frames as i64)
        .map(|t| {
            let mut f = scene.frame(1 + t);
            if let Some(n) = samples {
                synth::render_noise(&mut f.input.color, 4, n, 1000 + t as u64);
            }
            f
        })
        .collect()
}

/// Pixels where the input differs from the truth only by noise and flicker.
fn plain(f: &SynthFrame) -> Vec<bool> {
    (0..f.hole_mask.len())
        .map(|i| {
            !f.hole_mask[i] && !f.insert_mask[i] && !f.shadow_mask[i] && f.input.coverage[i] >= 1.0
        })
        .collect()
}

fn same(a: &Image, b: &Image) -> bool {
    a.data.len() == b.data.len()
        && a.data
            .iter()
            .zip(&b.data)
            .all(|(x, y)| x.to_bits() == y.to_bits())
}

/// Runs `seq` through `s` (with the albedo when `albedo`); the outputs and
/// reports.
fn run(
    s: &mut Session,
    seq: &[SynthFrame],
    albedo: bool,
) -> Vec<(Image, harmonizer_core::FrameReport)> {
    seq.iter()
        .map(|f| {
            let input = match albedo {
                true => f.input.frame_input_with_albedo(),
                false => f.input.frame_input(),
            };
            s.process(&input, None).unwrap()
        })
        .collect()
}

/// The prepared color of each frame of `seq` (what the session works on:
/// sanitized, premultiplied), interleaved RGB.
fn prepared(seq: &[SynthFrame]) -> Vec<Vec<f32>> {
    seq.iter()
        .map(|f| {
            let p = PreparedFrame::from_input(&f.input.frame_input(), DepthKind::Planar).unwrap();
            synth::interleave(&p.color, 3)
        })
        .collect()
}

/// Interleaved images (`channels` per pixel) as the planar RGBA outputs
/// and (empty) reports [`mean_psnr`] takes.
fn as_outputs(imgs: &[Vec<f32>], channels: usize) -> Vec<(Image, harmonizer_core::FrameReport)> {
    imgs.iter()
        .map(|v| {
            let mut img = Image::zeros(W, H, 4);
            for p in 0..W * H {
                for c in 0..3 {
                    img.data[c * W * H + p] = v[channels * p + c];
                }
            }
            (img, harmonizer_core::FrameReport::default())
        })
        .collect()
}

/// Mean PSNR of the outputs against the truth on [`plain`] pixels, over
/// the frames after the first.
fn mean_psnr(seq: &[SynthFrame], outs: &[(Image, harmonizer_core::FrameReport)]) -> f64 {
    let v: Vec<f64> = seq
        .iter()
        .zip(outs)
        .skip(1)
        .map(|(f, (o, _))| synth::psnr(&synth::interleave(o, 4), 4, &f.truth, 3, Some(&plain(f))))
        .collect();
    v.iter().sum::<f64>() / v.len() as f64
}

#[test]
fn denoise_on_gains_over_off_on_a_noisy_sequence() {
    let seq = frames(W, H, 6, Some(4));
    let dev = device(None);
    let noisy = mean_psnr(&seq, &as_outputs(&prepared(&seq), 3));
    let mut results = Vec::new();
    for (mode, albedo) in [("off", false), ("on", false), ("on", true)] {
        let mut sess = session(&dev, &[("denoise", s(mode))]);
        let outs = run(&mut sess, &seq, albedo);
        for (t, (_, r)) in outs.iter().enumerate() {
            assert_eq!(r.denoised, mode == "on", "{mode} frame {t}");
            let accumulated = r.stages.0.iter().any(|(k, _)| k == "accumulate");
            assert_eq!(accumulated, mode == "on", "{mode} frame {t}");
            let timed = r.stages.0.iter().any(|(k, _)| k == "denoise");
            assert_eq!(timed, mode == "on", "{mode} frame {t}: {:?}", r.stages);
            assert_eq!(r.denoise_decision.is_some(), t == 0, "{mode} frame {t}");
            assert!(r.warnings.is_empty(), "{mode} frame {t}: {:?}", r.warnings);
        }
        let db = mean_psnr(&seq, &outs);
        println!("denoise {mode} (albedo {albedo}): PSNR {db:.2} dB (noisy input {noisy:.2} dB)");
        results.push(db);
    }
    // Measured: off 23.1, on 28.0, on with the albedo 33.9 dB (noisy
    // input 16.9; the classical stabilization alone averages some noise
    // away). The color alone loses the small frame's fine textures (the
    // checker and the bricks are a few pixels wide); the albedo keeps them.
    let (off, on, on_albedo) = (results[0], results[1], results[2]);
    assert!(
        on_albedo >= off + 8.0,
        "denoise on with albedo {on_albedo:.2} dB vs off {off:.2} dB (at least 8 dB more)"
    );
    assert!(
        on >= off + 3.0,
        "denoise on {on:.2} dB vs off {off:.2} dB (at least 3 dB more)"
    );
}

/// Mean warping error (mean absolute RGB difference to the previous
/// output warped by the exact motion, on pixels seen in both frames and
/// [`plain`]) of `images` (interleaved, `channels` per pixel).
fn flicker(seq: &[SynthFrame], images: &[Vec<f32>], channels: usize) -> f64 {
    let v: Vec<f64> = (1..seq.len())
        .map(|t| {
            let f = &seq[t];
            let mask: Vec<bool> = plain(f)
                .iter()
                .zip(&f.temporal_mask)
                .map(|(a, b)| *a && *b)
                .collect();
            synth::warping_error(
                &images[t],
                &images[t - 1],
                channels,
                W,
                H,
                &f.truth_motion,
                Some(&mask),
            )
        })
        .collect();
    v.iter().sum::<f64>() / v.len() as f64
}

#[test]
fn the_accumulation_steadies_what_the_denoiser_leaves() {
    // Open Image Denoise per frame (the stage's filter run directly, on
    // the same color, albedo and normal) against the session with `denoise
    // on`, which accumulates its output over time.
    let seq = frames(W, H, 8, Some(4));
    let dev = device(None);
    let mut d = Denoiser::new(&dev.oidn().unwrap()).unwrap();
    let per_frame: Vec<Vec<f32>> = seq
        .iter()
        .map(|f| {
            let rgb = prepared(std::slice::from_ref(f)).remove(0);
            let mut out = vec![0.0f32; rgb.len()];
            d.denoise(
                &DenoiseInput {
                    width: W,
                    height: H,
                    color: &rgb,
                    albedo: Some(&f.input.albedo),
                    normal: Some(&f.input.normal),
                },
                DenoiseOptions {
                    hdr: true,
                    quality: Quality::High,
                    clean_aux: false,
                    prefilter: false,
                    max_memory_mb: None,
                },
                &mut out,
            )
            .unwrap();
            out
        })
        .collect();
    let mut sess = session(&dev, &[("denoise", s("on"))]);
    let outs = run(&mut sess, &seq, true);
    for (t, (_, r)) in outs.iter().enumerate() {
        let timed: Vec<&str> = r.stages.0.iter().map(|(k, _)| k.as_str()).collect();
        assert!(
            timed.contains(&"denoise") && timed.contains(&"accumulate"),
            "frame {t}: {timed:?}"
        );
        // The backend does not stabilize again over the accumulation.
        assert!(!timed.contains(&"stabilize"), "frame {t}: {timed:?}");
    }
    let ours: Vec<Vec<f32>> = outs.iter().map(|(o, _)| synth::interleave(o, 3)).collect();
    let (f_oidn, f_ours) = (flicker(&seq, &per_frame, 3), flicker(&seq, &ours, 3));
    let (p_oidn, p_ours) = (
        mean_psnr(&seq, &as_outputs(&per_frame, 3)),
        mean_psnr(&seq, &outs),
    );
    println!(
        "OIDN per frame: {p_oidn:.2} dB, flicker {f_oidn:.5}; accumulated: {p_ours:.2} dB, flicker {f_ours:.5}"
    );
    // Measured: OIDN per frame 35.47 dB, flicker 0.0212; accumulated
    // 35.32 dB, 0.0135 (0.64x). On the out-of-domain 4-spp Cycles
    // sequence the accumulation gains 0.7 dB (docs/model_card.md).
    assert!(
        f_ours <= 0.7 * f_oidn,
        "flicker {f_ours:.5} against OIDN per frame {f_oidn:.5} (at most 0.7x)"
    );
    assert!(
        p_ours >= p_oidn - 0.2,
        "PSNR {p_ours:.2} dB against OIDN per frame {p_oidn:.2} dB"
    );
}

#[test]
fn denoise_temporal_accumulates_without_a_second_spatial_pass() {
    // Frames a renderer denoised per frame: the truth with a little
    // frame-to-frame flicker. `temporal` needs no Open Image Denoise (the
    // library here is missing) and removes flicker without losing detail.
    let mut seq = frames(W, H, 8, None);
    for (t, f) in seq.iter_mut().enumerate() {
        for (p, px) in f.input.color.chunks_exact_mut(4).enumerate() {
            if f.input.coverage[p] >= 1.0 {
                let mut h = (p as u64 ^ (t as u64) << 32).wrapping_mul(0x9E37_79B9_7F4A_7C15);
                h ^= h >> 31;
                let g = 1.0 + 0.06 * ((h % 1000) as f32 / 1000.0 - 0.5);
                for v in &mut px[..3] {
                    *v *= g;
                }
            }
        }
    }
    let dev = device(Some("/nonexistent/libOpenImageDenoise.so.2"));
    let mut sess = session(&dev, &[("denoise", s("temporal"))]);
    let outs = run(&mut sess, &seq, false);
    for (t, (_, r)) in outs.iter().enumerate() {
        let timed: Vec<&str> = r.stages.0.iter().map(|(k, _)| k.as_str()).collect();
        assert!(
            r.denoised && r.warnings.is_empty(),
            "frame {t}: {:?}",
            r.warnings
        );
        assert!(
            timed.contains(&"accumulate") && !timed.contains(&"denoise"),
            "frame {t}: {timed:?}"
        );
        if t == 0 {
            let why = r.denoise_decision.as_deref().unwrap_or("");
            assert!(why.contains("denoise temporal"), "{why}");
        }
    }
    let inputs: Vec<Vec<f32>> = seq.iter().map(|f| f.input.color.clone()).collect();
    let ours: Vec<Vec<f32>> = outs.iter().map(|(o, _)| synth::interleave(o, 3)).collect();
    let (f_in, f_ours) = (flicker(&seq, &inputs, 4), flicker(&seq, &ours, 3));
    let (p_in, p_ours) = (
        mean_psnr(&seq, &as_outputs(&prepared(&seq), 3)),
        mean_psnr(&seq, &outs),
    );
    println!(
        "input: {p_in:.2} dB, flicker {f_in:.5}; temporal: {p_ours:.2} dB, flicker {f_ours:.5}"
    );
    // Measured: input 35.23 dB, flicker 0.0240; temporal 36.30 dB, 0.0146
    // (0.61x: per-pixel flicker, which the 3x3 clipping box partly keeps;
    // the out-of-domain Cycles sequence, blotches from frame to frame,
    // gives 0.51x, see docs/model_card.md).
    assert!(
        f_ours <= 0.7 * f_in,
        "flicker {f_ours:.5} against the input's {f_in:.5}"
    );
    assert!(
        p_ours >= p_in,
        "PSNR {p_ours:.2} dB against the input's {p_in:.2} dB"
    );
}

#[test]
fn auto_follows_the_hosts_sample_count() {
    let seq = frames(W, H, 3, Some(4));
    let dev = device(None);
    let on = run(&mut session(&dev, &[("denoise", s("on"))]), &seq, true);
    let off = run(&mut session(&dev, &[("denoise", s("off"))]), &seq, true);
    for (samples, want_on) in [(4, true), (64, true), (1, true), (65, false), (1024, false)] {
        let mut sess = session(&dev, &[("samples", ParamValue::Int(samples))]);
        assert_eq!(sess.params().samples, samples as u32);
        let outs = run(&mut sess, &seq, true);
        let decision = outs[0].1.denoise_decision.clone().unwrap();
        println!("samples {samples}: {decision}");
        assert!(
            decision.starts_with(if want_on {
                "denoise auto: on"
            } else {
                "denoise auto: off"
            }) && decision.contains(&format!("{samples} samples per pixel")),
            "{decision}"
        );
        // The host's word: no noise estimate.
        assert_eq!(outs[0].1.noise_level, None);
        let want = if want_on { &on } else { &off };
        for (t, ((a, r), (b, _))) in outs.iter().zip(want).enumerate() {
            assert_eq!(r.denoised, want_on, "samples {samples} frame {t}");
            assert!(
                same(a, b),
                "samples {samples} frame {t}: differs from denoise {want_on}"
            );
            assert_eq!(r.denoise_decision.is_some(), t == 0);
        }
    }
    // A change of `samples` is decided again (and resets the state).
    let mut sess = session(&dev, &[("samples", ParamValue::Int(1024))]);
    run(&mut sess, &seq[..1], true);
    sess.set("samples", ParamValue::Int(4)).unwrap();
    sess.commit().unwrap();
    let (_, r) = sess
        .process(&seq[1].input.frame_input_with_albedo(), None)
        .unwrap();
    assert!(r.denoised, "{:?}", r.denoise_decision);
    assert_eq!(
        r.reset,
        Some(harmonizer_core::session::ResetReason::ParamsChanged)
    );
    // Bypass passes the input through: `auto` does not denoise for it,
    // `on` does.
    let mut bypass = session(
        &dev,
        &[("backend", s("bypass")), ("samples", ParamValue::Int(4))],
    );
    let outs = run(&mut bypass, &seq[..1], false);
    assert!(!outs[0].1.denoised);
    assert!(outs[0]
        .1
        .denoise_decision
        .as_deref()
        .unwrap()
        .contains("bypass"));
    let mut bypass = session(&dev, &[("backend", s("bypass")), ("denoise", s("on"))]);
    assert!(run(&mut bypass, &seq[..1], false)[0].1.denoised);
}

#[test]
fn noise_is_detected_on_noisy_frames_and_not_on_clean_ones() {
    let clean = frames(W, H, 4, None);
    let noisy = frames(W, H, 3, Some(4));
    let sixty_four = frames(W, H, 1, Some(64));
    let level = |f: &SynthFrame| {
        let p = PreparedFrame::from_input(&f.input.frame_input(), DepthKind::Planar).unwrap();
        noise_level(&p.color, p.coverage.as_deref(), None).unwrap()
    };
    let (c, n, n64) = (level(&clean[0]), level(&noisy[0]), level(&sixty_four[0]));
    println!(
        "noise level: clean {c:.4}, 64 samples {n64:.4}, 4 samples {n:.4} (threshold {NOISE_THRESHOLD})"
    );
    // The synthetic scene's own noise (up to 0.006 absolute plus 2.5 %,
    // much of it in its dark parts) gives it a level of its own, below the
    // threshold: the default `auto` leaves the demo sequence alone.
    assert!(c < 0.75 * NOISE_THRESHOLD, "clean {c}");
    assert!(n > 2.0 * NOISE_THRESHOLD, "4 samples {n}");
    assert!(n64 > c && n64 < n, "64 samples {n64}");

    // `auto` with `samples` unknown measures the first frame and keeps the
    // decision for the sequence.
    let dev = device(None);
    let mut sess = session(&dev, &[]);
    let outs = run(&mut sess, &noisy, false);
    let r0 = &outs[0].1;
    println!("{:?}", r0.denoise_decision);
    assert!(r0.denoised && r0.noise_level.is_some_and(|l| (l - n).abs() < 1e-6));
    assert!(r0
        .denoise_decision
        .as_deref()
        .unwrap()
        .starts_with("denoise auto: on (noise level"));
    assert!(r0.stages.0.iter().any(|(k, _)| k == "noise_estimate"));
    for (_, r) in &outs[1..] {
        assert!(r.denoised && r.noise_level.is_none() && r.denoise_decision.is_none());
    }
    // A clean frame in the same sequence (frame 4 after 1-3) is still
    // denoised (decided once); after a reset it is measured again, found
    // clean.
    let (_, r) = sess.process(&clean[3].input.frame_input(), None).unwrap();
    assert_eq!(r.reset, None);
    assert!(r.denoised && r.denoise_decision.is_none());
    let mut reset = clean[0].input.frame_input();
    reset.reset = true;
    let (_, r) = sess.process(&reset, None).unwrap();
    assert!(!r.denoised, "{:?}", r.denoise_decision);
    assert!(r
        .denoise_decision
        .as_deref()
        .unwrap()
        .starts_with("denoise auto: off (noise level"));
    // A clean sequence from the start: off, and the output is what
    // `denoise off` gives.
    let outs = run(&mut session(&dev, &[]), &clean[..3], false);
    let off = run(
        &mut session(&dev, &[("denoise", s("off"))]),
        &clean[..3],
        false,
    );
    assert!(outs.iter().all(|(_, r)| !r.denoised));
    for ((a, _), (b, _)) in outs.iter().zip(&off) {
        assert!(same(a, b));
    }
}

/// Writes `f` in the generic layout, with the albedo channels when
/// `albedo`, and full coverage except a hole in the top-left corner.
fn write_frame(path: &Path, f: &SynthFrame, albedo: bool) -> Vec<f32> {
    let (w, h) = (f.input.width, f.input.height);
    let plane = |d: &[f32], ch: usize, c: usize| -> Vec<f32> {
        d.iter().skip(c).step_by(ch).copied().collect()
    };
    let mut cov = vec![1.0f32; w * h];
    let mut color = f.input.color.clone();
    for y in 0..h / 4 {
        for x in 0..w / 4 {
            let p = y * w + x;
            cov[p] = if x + 1 == w / 4 || y + 1 == h / 4 {
                0.5
            } else {
                0.0
            };
            for c in 0..3 {
                color[4 * p + c] *= cov[p];
            }
        }
    }
    let rgb: Vec<Vec<f32>> = (0..3).map(|c| plane(&color, 4, c)).collect();
    let n: Vec<Vec<f32>> = (0..3).map(|c| plane(&f.input.normal, 3, c)).collect();
    let a: Vec<Vec<f32>> = (0..3).map(|c| plane(&f.input.albedo, 3, c)).collect();
    let ch = |name, data| OutChannel {
        name,
        data,
        half: false,
    };
    let mut list = vec![
        ch("R", &rgb[0]),
        ch("G", &rgb[1]),
        ch("B", &rgb[2]),
        ch("A", &cov),
        ch("N.X", &n[0]),
        ch("N.Y", &n[1]),
        ch("N.Z", &n[2]),
    ];
    if albedo {
        list.extend([
            ch("albedo.R", &a[0]),
            ch("albedo.G", &a[1]),
            ch("albedo.B", &a[2]),
        ]);
    }
    write_channels(path, w, h, &list, None).unwrap();
    cov
}

#[test]
fn the_albedo_of_the_generic_layout_reaches_the_denoiser() {
    let seq = frames(W, H, 1, Some(4));
    let f = &seq[0];
    let dir = tempfile::tempdir().unwrap();
    let (with, without) = (dir.path().join("with.exr"), dir.path().join("without.exr"));
    let cov = write_frame(&with, f, true);
    write_frame(&without, f, false);
    let dev = device(None);
    let process = |path: &Path| {
        let loaded = LoadedFrame::read(path, Some(1), &LayoutOptions::default()).unwrap();
        let input = loaded.frame_input().unwrap();
        let mut sess = session(&dev, &[("backend", s("bypass")), ("denoise", s("on"))]);
        let (out, r) = sess.process(&input, None).unwrap();
        assert!(r.denoised);
        (loaded, out)
    };
    let (loaded, out) = process(&with);
    assert!(loaded.albedo.is_some() && loaded.normal.is_some());
    let info = harmonizer_core::io::exr::info(&with).unwrap();
    assert!(info.roles.contains(&"albedo"), "{:?}", info.roles);
    let (plain_loaded, plain) = process(&without);
    assert!(plain_loaded.albedo.is_none());
    // The same frame through the denoiser directly: color (as read),
    // albedo and normal (not prefiltered: `denoise_prefilter` is off by
    // default), HDR, quality high.
    let mut d = Denoiser::new(&dev.oidn().unwrap()).unwrap();
    let mut direct = vec![0.0f32; 3 * W * H];
    d.denoise(
        &DenoiseInput {
            width: W,
            height: H,
            color: &loaded.color,
            albedo: loaded.albedo.as_deref(),
            normal: loaded.normal.as_deref(),
        },
        DenoiseOptions {
            hdr: true,
            quality: Quality::High,
            clean_aux: false,
            prefilter: false,
            max_memory_mb: None,
        },
        &mut direct,
    )
    .unwrap();
    let n = W * H;
    let (mut equal, mut differ) = (0, 0);
    for p in 0..n {
        for c in 0..3 {
            let got = out.data[c * n + p];
            // Covered pixels are the denoiser's output; holes keep the input.
            let want = if cov[p] > 0.0 {
                direct[3 * p + c]
            } else {
                loaded.color[3 * p + c]
            };
            assert_eq!(got.to_bits(), want.to_bits(), "pixel {p} channel {c}");
            equal += 1;
            differ += usize::from(got != plain.data[c * n + p]);
        }
    }
    // Without the albedo the result is another one.
    println!("{differ} of {equal} samples differ without the albedo");
    assert!(differ > equal / 2, "{differ} of {equal}");
    // The alpha is the coverage.
    assert_eq!(&out.data[3 * n..], &cov[..]);
}

#[test]
fn a_failed_or_cancelled_frame_leaves_the_state_unchanged() {
    let seq = frames(W, H, 4, Some(4));
    let dev = device(None);
    let expected = run(&mut session(&dev, &[]), &seq, true);
    let mut sess = session(&dev, &[]);
    // The deciding frame cancelled after the denoise stage ran (at the
    // progress report that follows it, the second), then one cancelled in
    // the backend (the third): nothing kept, the decision made again.
    for stop in [2, 3] {
        let mut calls = 0;
        let mut cancel = |_: f64| {
            calls += 1;
            calls < stop
        };
        let e = sess
            .process(&seq[0].input.frame_input_with_albedo(), Some(&mut cancel))
            .unwrap_err();
        assert!(matches!(e, Error::Cancelled(_)), "{e}");
        assert_eq!(sess.history_len(), 0);
    }
    let mut calls = 0;
    let mut cancel = |_: f64| {
        calls += 1;
        calls < 2
    };
    let e = sess
        .process(&seq[0].input.frame_input_with_albedo(), Some(&mut cancel))
        .unwrap_err();
    assert!(matches!(e, Error::Cancelled(_)), "{e}");
    assert_eq!(sess.history_len(), 0);
    let (out, r) = sess
        .process(&seq[0].input.frame_input_with_albedo(), None)
        .unwrap();
    assert!(r.denoise_decision.is_some() && r.denoised);
    assert!(same(&out, &expected[0].0));
    sess.process(&seq[1].input.frame_input_with_albedo(), None)
        .unwrap();
    // An albedo of the wrong size: an error naming it, the state as it was.
    let small = vec![0.5f32; 3 * (W - 1) * H];
    let mut bad = seq[2].input.frame_input();
    bad.albedo = Some(ImageView::from_f32("albedo", &small, W - 1, H, 3).unwrap());
    let e = sess.process(&bad, None).unwrap_err();
    assert!(
        matches!(e, Error::Invalid(_))
            && e.to_string().contains("albedo")
            && e.to_string().contains("differs"),
        "{e}"
    );
    for (t, f) in seq.iter().enumerate().skip(2) {
        let (out, r) = sess
            .process(&f.input.frame_input_with_albedo(), None)
            .unwrap();
        assert!(
            same(&out, &expected[t].0),
            "frame {t} after the failed frame differs"
        );
        assert!(r.denoised && r.reset.is_none());
    }
    // NaN in the albedo: replaced and warned, not an error.
    let mut nan = seq[0].input.albedo.clone();
    nan[5] = f32::NAN;
    nan[7] = f32::INFINITY;
    let mut f = seq[0].input.frame_input();
    f.albedo = Some(ImageView::from_f32("albedo", &nan, W, H, 3).unwrap());
    f.reset = true;
    let (_, r) = sess.process(&f, None).unwrap();
    assert!(
        r.warnings
            .iter()
            .any(|w| w.contains("2 albedo samples were NaN or infinite")),
        "{:?}",
        r.warnings
    );
}

#[test]
fn a_missing_library_is_an_error_with_on_and_a_warning_with_auto() {
    let seq = frames(W, H, 3, Some(4));
    let missing = "/nonexistent/oidn/libOpenImageDenoise.so.2";
    let dev = device(Some(missing));
    let mut on = session(&dev, &[("denoise", s("on"))]);
    let e = on.process(&seq[0].input.frame_input(), None).unwrap_err();
    let msg = e.to_string();
    assert!(matches!(e, Error::RuntimeMissing(_)), "{msg}");
    for needle in [
        "denoise on",
        missing,
        "pip install pyoidn",
        "HARMONIZER_OIDN_LIB",
    ] {
        assert!(msg.contains(needle), "{needle:?} missing from: {msg}");
    }
    assert_eq!(on.history_len(), 0);
    // `auto` (noisy frames, or the host's 4 samples): processed without
    // denoising, one warning for the sequence, the output of `denoise off`.
    let off = run(
        &mut session(&device(None), &[("denoise", s("off"))]),
        &seq,
        false,
    );
    for params in [vec![], vec![("samples", ParamValue::Int(4))]] {
        let outs = run(&mut session(&dev, &params), &seq, false);
        let w = &outs[0].1.warnings;
        assert!(
            w.len() == 1
                && w[0].contains("Open Image Denoise cannot be used")
                && w[0].contains(missing),
            "{w:?}"
        );
        for (t, ((a, r), (b, _))) in outs.iter().zip(&off).enumerate() {
            assert!(!r.denoised && same(a, b), "frame {t}");
            if t > 0 {
                assert!(r.warnings.is_empty(), "frame {t}: {:?}", r.warnings);
            }
        }
    }
}

#[test]
fn strength_zero_returns_the_input_even_when_denoising() {
    // `strength` blends with the host's input, not the denoised frame; the
    // bypass backend with `denoise on` is the denoised frame alone.
    let seq = frames(W, H, 2, Some(4));
    let dev = device(None);
    let mut zero = session(
        &dev,
        &[("denoise", s("on")), ("strength", ParamValue::Float(0.0))],
    );
    let mut half = session(
        &dev,
        &[("denoise", s("on")), ("strength", ParamValue::Float(0.5))],
    );
    let mut only = session(&dev, &[("denoise", s("on")), ("backend", s("bypass"))]);
    let n = W * H;
    for f in &seq {
        let input = f.input.frame_input_with_albedo();
        let (out, r) = zero.process(&input, None).unwrap();
        assert!(r.denoised);
        for p in 0..n {
            for c in 0..4 {
                assert_eq!(
                    out.data[c * n + p].to_bits(),
                    f.input.color[4 * p + c].to_bits()
                );
            }
        }
        let (out, _) = half.process(&input, None).unwrap();
        let (denoised, _) = only.process(&input, None).unwrap();
        // Half way between the input and the (denoised, enhanced) result:
        // closer to the denoised frame than the input is.
        let dist = |a: &[f32], b: &dyn Fn(usize) -> f32| -> f64 {
            (0..n)
                .map(|p| (a[p] as f64 - b(p) as f64).abs())
                .sum::<f64>()
        };
        let d_out = dist(&out.data[..n], &|p| denoised.data[p]);
        let d_in = dist(
            &f.input.color.iter().step_by(4).copied().collect::<Vec<_>>(),
            &|p| denoised.data[p],
        );
        assert!(d_out < 0.75 * d_in, "{d_out} vs {d_in}");
    }
}

#[test]
fn the_memory_estimate_counts_the_denoise_stage() {
    let dev = device(None);
    let mut shape = FrameShape::new(1920, 1080);
    shape.normal = true;
    let off = session(&dev, &[("denoise", s("off"))]);
    let on = session(&dev, &[("denoise", s("on"))]);
    let base = off.memory_estimate(&shape).unwrap();
    let plane = 1920 * 1080 * 4;
    // The interleaved color and output; the accumulation's RGB (kept) and
    // its 3 working planes.
    assert_eq!(on.memory_estimate(&shape).unwrap(), base + (6 + 6) * plane);
    // `temporal`: the accumulation alone.
    let temporal = session(&dev, &[("denoise", s("temporal"))]);
    assert_eq!(temporal.memory_estimate(&shape).unwrap(), base + 6 * plane);
    shape.albedo = true;
    // The albedo (prepared, interleaved, prefiltered) and the normals
    // (prepared for the denoiser, interleaved, prefiltered).
    assert_eq!(off.memory_estimate(&shape).unwrap(), base);
    assert_eq!(
        on.memory_estimate(&shape).unwrap(),
        base + (6 + 9 + 9 + 6) * plane
    );
    // With `strength` below 1 the input's color is kept for the blend.
    let half = session(
        &dev,
        &[("denoise", s("on")), ("strength", ParamValue::Float(0.5))],
    );
    let half_off = session(
        &dev,
        &[("denoise", s("off")), ("strength", ParamValue::Float(0.5))],
    );
    assert_eq!(
        half.memory_estimate(&shape).unwrap(),
        half_off.memory_estimate(&shape).unwrap() + (6 + 9 + 9 + 6 + 3) * plane
    );
    // `auto` with many samples says off up front.
    let many = session(&dev, &[("samples", ParamValue::Int(1024))]);
    assert_eq!(many.memory_estimate(&shape).unwrap(), base);
}

/// The time of `noise_level` on a noisy 1920x1080 frame on 2 threads
/// (median of 5). Prints, asserts nothing about time. Run alone: `cargo
/// test -p harmonizer-core --test core denoise_session::noise_level_timing
/// -- --ignored --nocapture`.
#[test]
#[ignore = "a measurement: run it alone, see the doc comment"]
fn noise_level_timing_1920x1080() {
    let f = &frames(1920, 1080, 1, Some(4))[0];
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(2)
        .build()
        .unwrap();
    let p = PreparedFrame::from_input_on(&f.input.frame_input(), DepthKind::Planar, &pool).unwrap();
    let mut ms: Vec<f64> = (0..5)
        .map(|_| {
            let t = std::time::Instant::now();
            std::hint::black_box(noise_level(&p.color, p.coverage.as_deref(), Some(&pool)));
            t.elapsed().as_secs_f64() * 1e3
        })
        .collect();
    ms.sort_by(f64::total_cmp);
    let level = noise_level(&p.color, p.coverage.as_deref(), Some(&pool)).unwrap();
    println!("noise_level 1920x1080: {:.2} ms (level {level:.3})", ms[2]);
}

#[test]
fn a_device_memory_limit_bounds_open_image_denoise_too() {
    // With a `memory_limit` just above the frame's counted planes, OIDN is
    // given half of what is left (`maxMemoryMB`, 2 MiB here) and works in
    // smaller tiles: the frame still comes out denoised, as the unlimited
    // one (measured identical: OIDN's tiles overlap by the network's
    // receptive field). What OIDN then allocates is not measured here.
    let (w, h) = (W, H);
    let seq = frames(w, h, 1, Some(4));
    let input = seq[0].input.frame_input_with_albedo();
    let free = device(None);
    let params = [("denoise", s("on"))];
    let (want, _) = session(&free, &params).process(&input, None).unwrap();
    let need = session(&free, &params)
        .memory_estimate(&FrameShape::of(&input))
        .unwrap();
    let limited = Device::new(DeviceOptions {
        threads: 2,
        memory_limit: need + (4 << 20),
        ..DeviceOptions::default()
    })
    .unwrap();
    let (got, r) = session(&limited, &params).process(&input, None).unwrap();
    assert!(r.denoised && r.warnings.is_empty(), "{:?}", r.warnings);
    let (a, b) = (synth::interleave(&got, 3), synth::interleave(&want, 3));
    let db = synth::psnr(&a, 3, &b, 3, None);
    println!("limited against unlimited: {db:.1} dB");
    assert!(db > 40.0, "{db:.1} dB");
    let noisy = synth::psnr(&prepared(&seq)[0], 3, &b, 3, None);
    assert!(db > noisy + 10.0, "{db:.1} dB, the input {noisy:.1} dB");
}
