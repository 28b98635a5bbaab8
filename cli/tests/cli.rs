//! The `harmonize` binary, run as a user would (issue 2, part 5).

use std::path::Path;
use std::process::{Command, Output};

use harmonizer_core::io::exr::LoadedFrame;
use harmonizer_core::io::layout::LayoutOptions;
use harmonizer_core::io::pattern::FramePattern;
use harmonizer_core::synth::{Sequence, SynthConfig};

fn harmonize(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_harmonize"))
        .args(args)
        .output()
        .expect("harmonize runs")
}

fn text(o: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&o.stdout).into(),
        String::from_utf8_lossy(&o.stderr).into(),
    )
}

fn sequence(dir: &Path, config: SynthConfig) -> (Sequence, String) {
    let seq = Sequence::generate(config).unwrap();
    let (input, _truth) = seq.write_generic(dir, "shot.####.exr").unwrap();
    (seq, input)
}

/// [`sequence`] of the default scene at `width` x `height`, `frames` frames.
fn small_sequence(dir: &Path, width: usize, height: usize, frames: usize) -> (Sequence, String) {
    sequence(
        dir,
        SynthConfig {
            width,
            height,
            frames,
            ..Default::default()
        },
    )
}

mod run {
    use super::*;

    /// What one `harmonize run` over the acceptance sequence gave.
    struct Acceptance {
        hole_in: f64,
        hole_out: f64,
        warp_in: f64,
        warp_out: f64,
        stdout: String,
        report: serde_json::Value,
        output: FramePattern,
    }

    impl Acceptance {
        /// The output's PSNR in holes is at least `hole_gain` dB above the
        /// input's, and its warping error below `warp_ratio` times the input's.
        fn check(&self, hole_gain: f64, warp_ratio: f64) {
            assert!(
                self.hole_out > self.hole_in + hole_gain,
                "holes PSNR {:.2} -> {:.2}",
                self.hole_in,
                self.hole_out
            );
            assert!(
                self.warp_out < warp_ratio * self.warp_in,
                "warping error {:.5} -> {:.5}",
                self.warp_in,
                self.warp_out
            );
        }
    }

    /// Runs `harmonize run` (with `extra` arguments) over the acceptance
    /// sequence: 24 frames of 320x180 with holes, an inserted object and flicker.
    fn run_acceptance(dir: &Path, extra: &[&str]) -> Acceptance {
        let (seq, input) = sequence(dir, SynthConfig::default());
        let out = dir
            .join("out")
            .join("shot.####.exr")
            .to_string_lossy()
            .to_string();
        let report = dir.join("report.json");
        let mut args = vec!["run", &input, "-o", &out, "--threads", "2", "--report"];
        args.push(report.to_str().unwrap());
        args.extend_from_slice(extra);
        let o = harmonize(&args);
        let (stdout, stderr) = text(&o);
        assert!(o.status.success(), "stdout: {stdout}\nstderr: {stderr}");
        let op = FramePattern::parse(&out).unwrap();
        let outs: Vec<Vec<f32>> = (1..=24)
            .map(|n| {
                let f = LoadedFrame::read(&op.path(n), Some(n), &LayoutOptions::default()).unwrap();
                let cov = f.coverage.as_ref().expect("output keeps A");
                f.color
                    .chunks(3)
                    .zip(cov)
                    .flat_map(|(c, a)| [c[0], c[1], c[2], *a])
                    .collect()
            })
            .collect();
        let ins: Vec<Vec<f32>> = seq.frames.iter().map(|f| f.input.color.clone()).collect();
        let a = Acceptance {
            hole_in: seq.psnr(&ins, 4, "holes"),
            hole_out: seq.psnr(&outs, 4, "holes"),
            warp_in: seq.warping_error(&ins, 4),
            warp_out: seq.warping_error(&outs, 4),
            stdout,
            report: serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap(),
            output: op,
        };
        eprintln!(
            "{extra:?}: holes PSNR {:.2} -> {:.2} dB; warping error {:.5} -> {:.5}",
            a.hole_in, a.hole_out, a.warp_in, a.warp_out
        );
        a
    }

    /// The acceptance run, classical backend. Thresholds: the
    /// output's PSNR in holes is at least 6 dB above the input's, and its
    /// warping error is below 0.8x the input's.
    #[test]
    fn classical_fills_holes_and_reduces_flicker() {
        let dir = tempfile::tempdir().unwrap();
        let a = run_acceptance(dir.path(), &["--backend", "classical"]);
        assert!(a.stdout.contains("24 frame(s)"), "{}", a.stdout);
        assert!(a.stdout.contains("sanitized color samples"), "{}", a.stdout);
        a.check(6.0, 0.8);

        let r = &a.report;
        let frames = r["frames"].as_array().unwrap();
        assert_eq!(frames.len(), 24);
        assert_eq!(frames[0]["reset"], "first_frame");
        assert!(frames[1]["reset"].is_null());
        assert_eq!(frames[0]["backend"], "classical");
        assert!(frames[5]["process_ms"].as_f64().unwrap() > 0.0);
        assert!(frames[5]["stages"]
            .as_object()
            .is_some_and(|m| !m.is_empty()));
        assert_eq!(r["summary"]["frames"], 24);
        assert_eq!(r["summary"]["sanitized"], 0);
        // The header records the run.
        let f = harmonizer_core::io::exr::ExrFile::open(&a.output.path(3), Some(3)).unwrap();
        assert!(f.find("mask.insert").is_some(), "input channels kept");
    }

    /// The same run with no backend named: the embedded network when ONNX
    /// Runtime is found (the test scripts set `HARMONIZER_ORT_LIB`), which
    /// must also fill the holes and lower the warping error.
    #[test]
    fn default_backend_is_the_embedded_network() {
        if std::env::var_os("HARMONIZER_ORT_LIB").is_none() {
            eprintln!("skipped: HARMONIZER_ORT_LIB is not set (scripts/test.sh sets it)");
            return;
        }
        let dir = tempfile::tempdir().unwrap();
        let a = run_acceptance(dir.path(), &[]);
        let frames = a.report["frames"].as_array().unwrap();
        assert_eq!(frames.len(), 24);
        assert!(
            frames.iter().all(|f| f["backend"] == "neural"),
            "{frames:?}"
        );
        // harmonizer-small 1.2.0 measured 10.71 -> 22.37 dB and 0.02413 -> 0.00981
        // (1.1.1: 22.87 dB, 0.00766).
        a.check(10.0, 0.5);
    }

    #[test]
    fn frame_range_gap_and_set() {
        let dir = tempfile::tempdir().unwrap();
        let (_, input) = small_sequence(dir.path(), 48, 27, 6);
        std::fs::remove_file(FramePattern::parse(&input).unwrap().path(4)).unwrap();
        let out = dir.path().join("o.%04d.exr").to_string_lossy().to_string();
        let report = dir.path().join("r.json");
        let o = harmonize(&[
            "run",
            &input,
            "-o",
            &out,
            "--backend",
            "bypass",
            "--frames",
            "2-6",
            "--set",
            "strength=0.5",
        ]);
        let (_, stderr) = text(&o);
        assert!(!o.status.success());
        assert!(
            stderr.contains("missing frame(s) 4") && stderr.contains("shot.0004.exr"),
            "{stderr}"
        );
        // Without a range the gap resets the temporal state (the default policy).
        let o = harmonize(&[
            "run",
            &input,
            "-o",
            &out,
            "--backend",
            "bypass",
            "--report",
            report.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{:?}", text(&o));
        let r: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        let f5 = r["frames"]
            .as_array()
            .unwrap()
            .iter()
            .find(|f| f["frame"] == 5)
            .unwrap()
            .clone();
        assert_eq!(f5["reset"], "frame_gap");
        let o = harmonize(&["run", &input, "-o", &out, "--set", "strength=7"]);
        let (_, stderr) = text(&o);
        assert!(
            !o.status.success() && stderr.contains("strength") && stderr.contains('7'),
            "{stderr}"
        );
    }
}

mod errors {
    use super::*;

    #[test]
    fn bad_inputs_exit_non_zero_naming_file_and_frame() {
        let dir = tempfile::tempdir().unwrap();
        let (_, input) = small_sequence(dir.path(), 32, 18, 4);
        let out = dir.path().join("o.####.exr").to_string_lossy().to_string();

        // No frame token.
        let o = harmonize(&["run", "beauty.exr", "-o", &out]);
        assert!(
            !o.status.success()
                && text(&o).1.contains("beauty.exr")
                && text(&o).1.contains("frame token"),
            "{:?}",
            text(&o)
        );
        // Output over input.
        let o = harmonize(&["run", &input, "-o", &input]);
        assert!(
            !o.status.success() && text(&o).1.contains("input file"),
            "{:?}",
            text(&o)
        );
        // Bad range.
        let o = harmonize(&["run", &input, "-o", &out, "--frames", "5-1"]);
        assert!(
            !o.status.success() && text(&o).1.contains("5-1"),
            "{:?}",
            text(&o)
        );
        // Missing channel under an explicit mapping.
        let o = harmonize(&["run", &input, "-o", &out, "--channel", "depth=depth.Z"]);
        let (_, e) = text(&o);
        assert!(
            !o.status.success()
                && e.contains("frame 1")
                && e.contains("depth.Z")
                && e.contains("shot.0001.exr"),
            "{e}"
        );
        // A truncated frame stops the run at that frame; earlier outputs stay.
        let p3 = FramePattern::parse(&input).unwrap().path(3);
        let bytes = std::fs::read(&p3).unwrap();
        std::fs::write(&p3, &bytes[..bytes.len() / 3]).unwrap();
        let o = harmonize(&["run", &input, "-o", &out, "--backend", "classical"]);
        let (_, e) = text(&o);
        assert!(
            !o.status.success()
                && e.contains("frame 3")
                && e.contains("shot.0003.exr")
                && e.contains("truncated"),
            "{e}"
        );
        let op = FramePattern::parse(&out).unwrap();
        assert!(op.path(2).is_file() && !op.path(3).exists());
        // Unknown layout and backend.
        let o = harmonize(&["run", &input, "-o", &out, "--layout", "nuke"]);
        assert!(!o.status.success() && text(&o).1.contains("nuke"));
        let o = harmonize(&["run", &input, "-o", &out, "--backend", "gpu"]);
        assert!(!o.status.success() && text(&o).1.contains("gpu"));
    }
}

mod tools {
    use super::*;

    #[test]
    fn info_describes_a_file() {
        let dir = tempfile::tempdir().unwrap();
        let (_, input) = small_sequence(dir.path(), 32, 18, 1);
        let p = FramePattern::parse(&input).unwrap().path(1);
        let o = harmonize(&["info", p.to_str().unwrap()]);
        let (out, err) = text(&o);
        assert!(o.status.success(), "{err}");
        for want in [
            "32x18",
            "layout: generic",
            "motion.X (float)",
            "camera: present",
            "roles found: color, coverage, depth, motion, normal, insert",
        ] {
            assert!(out.contains(want), "{want:?} in {out}");
        }
        let o = harmonize(&["info", dir.path().join("missing.exr").to_str().unwrap()]);
        assert!(!o.status.success() && text(&o).1.contains("missing.exr"));
    }

    #[test]
    fn demo_writes_frames_sheet_and_metrics() {
        let dir = tempfile::tempdir().unwrap();
        let o = harmonize(&[
            "demo",
            "--out",
            dir.path().to_str().unwrap(),
            "--threads",
            "2",
        ]);
        let (out, err) = text(&o);
        assert!(o.status.success(), "{out}\n{err}");
        assert!(
            out.contains("contact_sheet.png") && out.contains("warping error"),
            "{out}"
        );
        let sheet = image::open(dir.path().join("contact_sheet.png")).unwrap();
        assert_eq!((sheet.width(), sheet.height()), (3 * 320 + 8, 4 * 180 + 12));
        for n in [1, 24] {
            for sub in ["input", "output", "truth"] {
                assert!(
                    dir.path()
                        .join(sub)
                        .join(format!("frame.{n:04}.exr"))
                        .is_file(),
                    "{sub} {n}"
                );
            }
        }
        let m: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(dir.path().join("metrics.json")).unwrap(),
        )
        .unwrap();
        assert!(m["psnr_holes_output"].as_f64().unwrap() > m["psnr_holes_input"].as_f64().unwrap());
    }

    #[test]
    fn bench_json_parses() {
        let o = harmonize(&[
            "bench",
            "--json",
            "--sizes",
            "160x90",
            "--frames",
            "2",
            "--threads",
            "2",
        ]);
        let (out, err) = text(&o);
        assert!(o.status.success(), "{err}");
        let v: serde_json::Value = serde_json::from_str(out.trim()).unwrap();
        let runs = v["runs"].as_array().unwrap();
        let c = runs
            .iter()
            .find(|r| r["backend"] == "classical")
            .expect("classical always runs");
        assert_eq!(
            (c["width"].as_u64(), c["height"].as_u64()),
            (Some(160), Some(90))
        );
        assert_eq!(c["context"], 4);
        assert_eq!(c["threads"], 2);
        assert!(c["ms_per_frame"].as_f64().unwrap() > 0.0);
        assert!(c["copy_floor_ms"].as_f64().unwrap() > 0.0);
        assert!(c["stages"].as_object().is_some_and(|m| !m.is_empty()));
        let o = harmonize(&["bench", "--sizes", "160by90"]);
        assert!(!o.status.success() && text(&o).1.contains("160by90"));
    }
}

/// The denoise stage from the command line (`--set denoise=...`,
/// `--set samples=...`), the albedo of the generic layout, and the bench's
/// denoise entry. Needs Open Image Denoise (the `pyoidn` wheel in `.venv`).
mod denoise {
    use super::*;
    use harmonizer_core::io::exr::{write_channels, OutChannel};

    /// Three noisy frames (4 samples per pixel) of 64x36 in the generic
    /// layout with the albedo channels; the input pattern.
    fn noisy_sequence(dir: &Path) -> String {
        let seq = Sequence::generate(SynthConfig {
            width: 64,
            height: 36,
            frames: 3,
            ..Default::default()
        })
        .unwrap();
        let pattern = FramePattern::parse(&dir.join("in.####.exr").to_string_lossy()).unwrap();
        for f in &seq.frames {
            let mut color = f.input.color.clone();
            harmonizer_core::synth::render_noise(&mut color, 4, 4, f.input.frame_index as u64);
            let plane = |d: &[f32], ch: usize, c: usize| -> Vec<f32> {
                d.iter().skip(c).step_by(ch).copied().collect()
            };
            let rgba: Vec<Vec<f32>> = (0..4).map(|c| plane(&color, 4, c)).collect();
            let n: Vec<Vec<f32>> = (0..3).map(|c| plane(&f.input.normal, 3, c)).collect();
            let a: Vec<Vec<f32>> = (0..3).map(|c| plane(&f.input.albedo, 3, c)).collect();
            let ch = |name, data| OutChannel {
                name,
                data,
                half: false,
            };
            write_channels(
                &pattern.path(f.input.frame_index),
                64,
                36,
                &[
                    ch("R", &rgba[0]),
                    ch("G", &rgba[1]),
                    ch("B", &rgba[2]),
                    ch("A", &rgba[3]),
                    ch("N.X", &n[0]),
                    ch("N.Y", &n[1]),
                    ch("N.Z", &n[2]),
                    ch("albedo.R", &a[0]),
                    ch("albedo.G", &a[1]),
                    ch("albedo.B", &a[2]),
                ],
                None,
            )
            .unwrap();
        }
        pattern.as_str().to_string()
    }

    fn run_report(dir: &Path, input: &str, set: &[&str]) -> (String, serde_json::Value) {
        let out = dir.join("out.####.exr").to_string_lossy().to_string();
        let report = dir.join("r.json");
        let mut args = vec![
            "run",
            input,
            "-o",
            &out,
            "--backend",
            "classical",
            "--threads",
            "2",
            "--report",
            report.to_str().unwrap(),
        ];
        for kv in set {
            args.extend(["--set", kv]);
        }
        let o = harmonize(&args);
        let (stdout, stderr) = text(&o);
        assert!(o.status.success(), "{set:?}: {stdout}\n{stderr}");
        let r = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        (stdout, r)
    }

    #[test]
    fn run_denoises_through_set_and_info_shows_the_albedo() {
        let dir = tempfile::tempdir().unwrap();
        let input = noisy_sequence(dir.path());
        let o = harmonize(&[
            "info",
            &FramePattern::parse(&input)
                .unwrap()
                .path(1)
                .to_string_lossy(),
        ]);
        let (out, err) = text(&o);
        assert!(o.status.success(), "{err}");
        assert!(
            out.contains("albedo.R (float)")
                && out.contains("roles found: color, coverage, normal, albedo"),
            "{out}"
        );
        for (set, decision) in [
            (&["denoise=on", "samples=4"][..], "denoise on"),
            (
                &["samples=4"][..],
                "denoise auto: on (the host renders 4 samples per pixel",
            ),
            (
                &["denoise_quality=fast"][..],
                "denoise auto: on (noise level",
            ),
            (&["denoise=off"][..], "denoise off"),
        ] {
            let (stdout, r) = run_report(dir.path(), &input, set);
            let on = decision != "denoise off";
            let frames = r["frames"].as_array().unwrap();
            assert_eq!(frames.len(), 3);
            let d = frames[0]["denoise_decision"].as_str().unwrap();
            assert!(d.starts_with(decision), "{set:?}: {d}");
            assert!(stdout.contains(&format!("frame 1: {d}")), "{stdout}");
            for f in frames {
                assert_eq!(f["denoised"], on, "{set:?}: {f}");
                assert_eq!(f["stages"]["denoise"].is_number(), on, "{set:?}: {f}");
            }
            assert!(frames[1]["denoise_decision"].is_null());
            assert_eq!(r["summary"]["denoised"], if on { 3 } else { 0 });
            assert!(
                stdout.contains(&format!("frames denoised: {}", if on { 3 } else { 0 })),
                "{stdout}"
            );
            if set == ["denoise_quality=fast"] {
                assert!(
                    frames[0]["noise_level"].as_f64().unwrap() > 0.2,
                    "{}",
                    frames[0]
                );
            }
        }
        let out = dir.path().join("x.####.exr").to_string_lossy().to_string();
        let o = harmonize(&["run", &input, "-o", &out, "--set", "denoise=maybe"]);
        let (_, stderr) = text(&o);
        assert!(
            !o.status.success() && stderr.contains("denoise") && stderr.contains("maybe"),
            "{stderr}"
        );
    }

    /// `harmonize bench --json --sizes 64x36 --threads 2` with `extra`; its JSON.
    fn bench_json(extra: &[&str]) -> serde_json::Value {
        let mut args = vec!["bench", "--json", "--sizes", "64x36", "--threads", "2"];
        args.extend_from_slice(extra);
        let o = harmonize(&args);
        let (out, err) = text(&o);
        assert!(o.status.success(), "{err}");
        serde_json::from_str(out.trim()).unwrap()
    }

    #[test]
    fn bench_times_the_stage_beside_oidn_alone() {
        let v = bench_json(&[
            "--frames",
            "2",
            "--backend",
            "classical",
            "--set",
            "denoise=on",
        ]);
        let run = &v["runs"][0];
        assert_eq!(run["set"][0], "denoise=on");
        assert!(run["stages"]["denoise"].as_f64().unwrap() > 0.0, "{run}");
        assert!(run["oidn_alone_ms"].as_f64().unwrap() > 0.0, "{run}");
        // Without the stage, no OIDN timing.
        let v = bench_json(&["--frames", "1", "--backend", "classical"]);
        assert!(
            v["runs"][0]["oidn_alone_ms"].is_null() && v["runs"][0]["stages"]["denoise"].is_null()
        );
        // The `denoise` entry: the classical backend with the stage on, its
        // accumulation timed too, beside OIDN alone.
        let v = bench_json(&["--frames", "2", "--backend", "denoise"]);
        let run = &v["runs"][0];
        assert_eq!(run["backend"], "denoise");
        assert!(run["stages"]["denoise"].as_f64().unwrap() > 0.0, "{run}");
        assert!(run["stages"]["accumulate"].as_f64().unwrap() > 0.0, "{run}");
        assert!(run["oidn_alone_ms"].as_f64().unwrap() > 0.0, "{run}");
    }
}

/// What a run writes is checked before any frame is read: no output may be
/// an input or another output, and every directory written to must be
/// writable (issue 3, defects 3 and 4).
#[cfg(unix)]
mod safety {
    use super::*;

    /// A 4-frame 32x18 sequence in `dir/input`; its pattern.
    fn small(dir: &Path) -> String {
        sequence(
            dir,
            SynthConfig {
                width: 32,
                height: 18,
                frames: 4,
                ..Default::default()
            },
        )
        .1
    }

    fn s(p: &Path) -> &str {
        p.to_str().unwrap()
    }

    /// The bytes of every file directly in `dir`, by name.
    fn snapshot(dir: &Path) -> Vec<(String, Vec<u8>)> {
        let mut v: Vec<_> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file())
            .map(|p| {
                (
                    p.file_name().unwrap().to_string_lossy().to_string(),
                    std::fs::read(&p).unwrap(),
                )
            })
            .collect();
        v.sort();
        v
    }

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .map(|r| {
                r.map(|e| e.unwrap().file_name().to_string_lossy().to_string())
                    .collect()
            })
            .unwrap_or_default();
        v.sort();
        v
    }

    /// `run INPUT -o OUT --backend bypass EXTRA...` fails, naming every
    /// string of `want` on stderr.
    fn run_refused(input: &str, out: &Path, extra: &[&str], want: &[&str]) -> String {
        let mut args = vec!["run", input, "-o", s(out), "--backend", "bypass"];
        args.extend_from_slice(extra);
        refused(&args, want)
    }

    /// Fails, naming every string of `want` on stderr.
    fn refused(args: &[&str], want: &[&str]) -> String {
        let o = harmonize(args);
        let (out, err) = text(&o);
        assert!(!o.status.success(), "{args:?} ran: {out}\n{err}");
        for w in want {
            assert!(err.contains(w), "{args:?}: {w:?} not in {err}");
        }
        err
    }

    #[test]
    fn report_or_output_onto_an_input_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let input = small(d);
        let ip = FramePattern::parse(&input).unwrap();
        let before = snapshot(&d.join("input"));
        let out_dir = d.join("out");
        let out = out_dir.join("o.####.exr");
        let run = |report: &Path, want: &[&str]| {
            run_refused(&input, &out, &["--report", s(report)], want)
        };
        // The report is an input frame, by its own path.
        let p1 = ip.path(1);
        let e = run(&p1, &["--report", "input frame 1", "shot.0001.exr"]);
        assert!(e.contains("input file"), "{e}");
        // ... through a symbolic link to it, a hard link to it, and a linked directory.
        std::os::unix::fs::symlink(ip.path(2), d.join("link.json")).unwrap();
        run(&d.join("link.json"), &["link.json", "shot.0002.exr"]);
        std::fs::hard_link(ip.path(3), d.join("hard.json")).unwrap();
        run(&d.join("hard.json"), &["hard.json", "shot.0003.exr"]);
        std::os::unix::fs::symlink(d.join("input"), d.join("linked")).unwrap();
        run(
            &d.join("linked").join("shot.0004.exr"),
            &["linked/shot.0004.exr", "shot.0004.exr"],
        );
        // An output frame that is a hard link to another frame's input.
        std::fs::create_dir(&out_dir).unwrap();
        std::fs::hard_link(ip.path(2), out_dir.join("o.0001.exr")).unwrap();
        refused(
            &["run", &input, "-o", s(&out), "--backend", "bypass"],
            &[
                "output frame 1",
                "o.0001.exr",
                "input frame 2",
                "shot.0002.exr",
            ],
        );
        std::fs::remove_file(out_dir.join("o.0001.exr")).unwrap();
        // The model's manifest is an input too.
        std::fs::write(d.join("m.onnx"), b"not a model").unwrap();
        std::fs::write(d.join("m.json"), b"{}").unwrap();
        run_refused(
            &input,
            &out,
            &[
                "--model",
                s(&d.join("m.onnx")),
                "--report",
                s(&d.join("m.json")),
            ],
            &["m.json", "model manifest"],
        );
        assert_eq!(std::fs::read(d.join("m.json")).unwrap(), b"{}");
        // Nothing was written: inputs unchanged, no output frame.
        assert!(snapshot(&d.join("input")) == before, "an input changed");
        assert_eq!(names(&out_dir), Vec::<String>::new());
    }

    /// Inputs x.0001.exr and x.1001.exr with `-o x.1###.exr`: frame 1's
    /// output would replace frame 1001's input before it is read.
    #[test]
    fn output_pattern_onto_a_later_input_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let input = small(d);
        let ip = FramePattern::parse(&input).unwrap();
        std::fs::rename(ip.path(2), ip.path(1001)).unwrap();
        std::fs::remove_file(ip.path(3)).unwrap();
        std::fs::remove_file(ip.path(4)).unwrap();
        let before = snapshot(&d.join("input"));
        let out = d.join("input").join("shot.1###.exr");
        refused(
            &["run", &input, "-o", s(&out), "--backend", "bypass"],
            &["output frame 1", "input frame 1001", "shot.1001.exr"],
        );
        assert!(snapshot(&d.join("input")) == before, "an input changed");
    }

    #[test]
    fn two_outputs_onto_one_path_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let input = small(d);
        let out_dir = d.join("out");
        let out = out_dir.join("o.####.exr");
        run_refused(
            &input,
            &out,
            &["--report", s(&out_dir.join("o.0002.exr"))],
            &["--report", "output frame 2", "o.0002.exr", "same file"],
        );
        assert_eq!(names(&out_dir), Vec::<String>::new());

        // demo: its output directory a link to its input directory.
        let demo = d.join("demo");
        std::fs::create_dir_all(demo.join("input")).unwrap();
        std::os::unix::fs::symlink(demo.join("input"), demo.join("output")).unwrap();
        refused(
            &["demo", "--out", s(&demo), "--backend", "bypass"],
            &[
                "output frame 1",
                "input frame 1",
                "frame.0001.exr",
                "same file",
            ],
        );
        assert_eq!(names(&demo.join("input")), Vec::<String>::new());
        assert_eq!(names(&demo), ["input", "output"]);
        // demo: its metrics over the model's manifest (an input).
        let demo = d.join("demo2");
        std::fs::create_dir(&demo).unwrap();
        std::fs::write(demo.join("metrics.onnx"), b"not a model").unwrap();
        std::fs::write(demo.join("metrics.json"), b"{}").unwrap();
        refused(
            &[
                "demo",
                "--out",
                s(&demo),
                "--model",
                s(&demo.join("metrics.onnx")),
            ],
            &["metrics", "model manifest", "metrics.json"],
        );
        assert_eq!(std::fs::read(demo.join("metrics.json")).unwrap(), b"{}");
        assert_eq!(names(&demo), ["metrics.json", "metrics.onnx"]);
    }

    /// Frame 1 is truncated, so an error found only after reading it says
    /// "truncated": the directory errors must come first.
    #[test]
    fn unwritable_output_directories_are_found_before_reading() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        let input = small(d);
        let p1 = FramePattern::parse(&input).unwrap().path(1);
        let bytes = std::fs::read(&p1).unwrap();
        std::fs::write(&p1, &bytes[..bytes.len() / 3]).unwrap();
        std::fs::write(d.join("afile"), b"a file").unwrap();
        let good = d.join("out").join("o.####.exr");
        let bypass = ["--backend", "bypass"];

        // The output directory's parent is a file.
        let out = d.join("afile").join("sub").join("o.####.exr");
        let e = refused(
            &[&["run", &input, "-o", s(&out)][..], &bypass].concat(),
            &[
                "cannot write output",
                "afile/sub/o.0001.exr",
                "Not a directory",
            ],
        );
        assert!(!e.contains("truncated"), "{e}");
        // The report's directory is a file.
        let report = d.join("afile").join("r.json");
        let e = refused(
            &[
                &["run", &input, "-o", s(&good), "--report", s(&report)][..],
                &bypass,
            ]
            .concat(),
            &["cannot write --report file", "afile/r.json", "File exists"],
        );
        assert!(!e.contains("truncated"), "{e}");
        // The report's path is a directory.
        let e = refused(
            &[
                &["run", &input, "-o", s(&good), "--report", s(d)][..],
                &bypass,
            ]
            .concat(),
            &["cannot write --report file", "a directory is there"],
        );
        assert!(!e.contains("truncated"), "{e}");
        // The output directories are made up front, as the run would.
        let deep = d.join("new").join("deeper");
        let e = refused(
            &[
                &["run", &input, "-o", s(&deep.join("o.####.exr"))][..],
                &bypass,
            ]
            .concat(),
            &["truncated"],
        );
        assert!(deep.is_dir(), "{e}");

        // A directory without write permission (root writes anyway).
        let ro = d.join("ro");
        std::fs::create_dir(&ro).unwrap();
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o555)).unwrap();
        if std::fs::write(ro.join("probe"), b"").is_ok() {
            eprintln!(
                "NOT CHECKED: a read-only directory is writable for this user (root?); \
                 the unwritable-directory case is covered by the file-parent cases only"
            );
        } else {
            let e = refused(
                &[
                    &["run", &input, "-o", s(&ro.join("o.####.exr"))][..],
                    &bypass,
                ]
                .concat(),
                &["cannot write output", "ro/o.0001.exr", "Permission denied"],
            );
            assert!(!e.contains("truncated"), "{e}");
            let e = refused(
                &[
                    &[
                        "run",
                        &input,
                        "-o",
                        s(&good),
                        "--report",
                        s(&ro.join("r.json")),
                    ][..],
                    &bypass,
                ]
                .concat(),
                &[
                    "cannot write --report file",
                    "ro/r.json",
                    "Permission denied",
                ],
            );
            assert!(!e.contains("truncated"), "{e}");
            assert_eq!(names(&ro), Vec::<String>::new());
        }
        std::fs::set_permissions(&ro, std::fs::Permissions::from_mode(0o755)).unwrap();
    }
}

/// `--preroll`: a chunk of a longer sequence warmed by the frames before it.
mod preroll {
    use super::*;

    /// RGB of frames `range` written under `pattern`, interleaved.
    fn read(pattern: &str, range: std::ops::RangeInclusive<i64>) -> Vec<Vec<f32>> {
        let p = FramePattern::parse(pattern).unwrap();
        range
            .map(|n| {
                LoadedFrame::read(&p.path(n), Some(n), &LayoutOptions::default())
                    .unwrap()
                    .color
            })
            .collect()
    }

    fn out(dir: &Path, name: &str) -> String {
        dir.join(name)
            .join("shot.####.exr")
            .to_string_lossy()
            .to_string()
    }

    /// Runs `harmonize run` over `input` (the frames `frames`, pre-roll
    /// `n`; all frames when `frames` is empty) with `backend`, into `out`.
    fn run(input: &str, out: &str, backend: &str, frames: &str, n: usize) -> Output {
        let n = n.to_string();
        let mut args = vec![
            "run",
            input,
            "-o",
            out,
            "--threads",
            "2",
            "--backend",
            backend,
        ];
        if !frames.is_empty() {
            args.extend_from_slice(&["--frames", frames, "--preroll", &n]);
        }
        let o = harmonize(&args);
        assert!(o.status.success(), "{:?}", text(&o));
        o
    }

    /// Mean PSNR of frames `a` against `b` (interleaved RGB).
    fn psnr(a: &[Vec<f32>], b: &[Vec<f32>]) -> f64 {
        let v: Vec<f64> = a
            .iter()
            .zip(b)
            .map(|(x, y)| harmonizer_core::synth::psnr(x, 3, y, 3, None).min(99.0))
            .collect();
        v.iter().sum::<f64>() / v.len() as f64
    }

    #[test]
    fn a_chunk_with_a_preroll_matches_the_sequential_run_and_writes_only_its_frames() {
        let dir = tempfile::tempdir().unwrap();
        let (_, input) = small_sequence(dir.path(), 96, 54, 32);
        let seq_out = out(dir.path(), "sequential");
        run(&input, &seq_out, "classical", "", 0);
        let want = read(&seq_out, 17..=32);
        let chunk = out(dir.path(), "chunk");
        let report = dir.path().join("report.json");
        let o = harmonize(&[
            "run",
            &input,
            "-o",
            &chunk,
            "--threads",
            "2",
            "--backend",
            "classical",
            "--frames",
            "17-32",
            "--preroll",
            "8",
            "--report",
            report.to_str().unwrap(),
        ]);
        let (stdout, stderr) = text(&o);
        assert!(o.status.success(), "{stdout}\n{stderr}");
        assert!(stdout.contains("16 frame(s) written"), "{stdout}");
        assert!(stdout.contains("pre-roll: 8 frame(s)"), "{stdout}");
        let cp = FramePattern::parse(&chunk).unwrap();
        assert!(
            (9..=16).all(|n| !cp.path(n).exists()),
            "pre-roll frames written"
        );
        let r: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        assert_eq!(r["summary"]["frames"], 16);
        assert_eq!(r["summary"]["preroll_frames"], 8);
        let frames = r["frames"].as_array().unwrap();
        assert_eq!(frames.len(), 24);
        assert!(frames[..8].iter().all(|f| f["preroll"] == true));
        assert!(frames[8..].iter().all(|f| f["preroll"] == false));
        let got = read(&chunk, 17..=32);
        let warm = psnr(&got, &want);
        // Without a pre-roll the chunk starts cold: its first frames differ.
        let cold_out = out(dir.path(), "cold");
        run(&input, &cold_out, "classical", "17-32", 0);
        let cold = psnr(&read(&cold_out, 17..=32), &want);
        println!(
            "chunk 17-32 against the sequential run: pre-roll 8 {warm:.1} dB, none {cold:.1} dB"
        );
        assert!(
            warm > 40.0 && warm > cold,
            "pre-roll 8 {warm:.1} dB, none {cold:.1} dB"
        );
        // The same chunk again: the same bytes.
        let again = out(dir.path(), "again");
        run(&input, &again, "classical", "17-32", 8);
        let ap = FramePattern::parse(&again).unwrap();
        for n in 17..=32 {
            assert_eq!(
                std::fs::read(cp.path(n)).unwrap(),
                std::fs::read(ap.path(n)).unwrap(),
                "frame {n}"
            );
        }
        // At the start of the sequence the pre-roll has fewer frames.
        let head = out(dir.path(), "head");
        let o = run(&input, &head, "classical", "3-8", 8);
        assert!(
            text(&o).0.contains("pre-roll: 2 frame(s)"),
            "{:?}",
            text(&o)
        );
    }

    #[test]
    fn a_preroll_without_frames_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (_, input) = small_sequence(dir.path(), 32, 18, 3);
        let o = harmonize(&["run", &input, "-o", &out(dir.path(), "o"), "--preroll", "4"]);
        let (_, stderr) = text(&o);
        assert!(!o.status.success());
        assert!(stderr.contains("--preroll needs --frames"), "{stderr}");
    }

    /// Issue 22's seam measurement: the 96-frame synthetic sequence with
    /// the sway camera (it stays in the scene; the default camera leaves
    /// it after about 50 frames) in chunks of 24 (1-24, 25-48, 49-72,
    /// 73-96) against one sequential run, for pre-rolls 0, 4, 8 and 16,
    /// classical and neural (set `HARMONIZER_ORT_LIB`). Prints per
    /// pre-roll: the mean PSNR of the chunked frames 25-96 against the
    /// sequential ones and the lowest (a seam's first frame), and the
    /// warping error (exact motion, the truth's temporal mask) of the frame
    /// pairs across the seams (24|25, 48|49, 72|73) against the other
    /// pairs, beside the sequential run's. A measurement: run it alone,
    /// `cargo test -p harmonizer-cli --release --test cli preroll::seams --
    /// --ignored --nocapture` (HZ_SEAMS_BACKENDS=classical to skip neural).
    #[test]
    #[ignore = "a measurement: run it alone, see the doc comment"]
    fn seams() {
        use harmonizer_core::synth::CameraPath;
        let dir = tempfile::tempdir().unwrap();
        let seq = Sequence::generate_with(
            SynthConfig {
                width: 320,
                height: 180,
                frames: 96,
                ..Default::default()
            },
            CameraPath::Sway,
        )
        .unwrap();
        let (input, _) = seq.write_generic(dir.path(), "shot.####.exr").unwrap();
        let backends = std::env::var("HZ_SEAMS_BACKENDS").unwrap_or("classical,neural".into());
        let seams = [25usize, 49, 73];
        // Warping error of the pair (t-1, t), frames numbered from 1.
        let warp = |imgs: &[Vec<f32>], t: usize| {
            let f = &seq.frames[t - 1];
            harmonizer_core::synth::warping_error(
                &imgs[t - 1],
                &imgs[t - 2],
                3,
                320,
                180,
                &f.truth_motion,
                Some(&f.temporal_mask),
            )
        };
        let pairs = |imgs: &[Vec<f32>]| {
            let at: Vec<f64> = seams.iter().map(|&t| warp(imgs, t)).collect();
            let rest: Vec<f64> = (2..=96)
                .filter(|t| !seams.contains(t))
                .map(|t| warp(imgs, t))
                .collect();
            (at, rest.iter().sum::<f64>() / rest.len() as f64)
        };
        for backend in backends.split(',') {
            let seq_out = out(dir.path(), &format!("{backend}-all"));
            run(&input, &seq_out, backend, "", 0);
            let want = read(&seq_out, 1..=96);
            let (s_at, s_rest) = pairs(&want);
            println!(
                "{backend} sequential: warping error at the seams' frames {:.5} {:.5} {:.5}, elsewhere {s_rest:.5}",
                s_at[0], s_at[1], s_at[2]
            );
            for n in [0usize, 4, 8, 16] {
                let o = out(dir.path(), &format!("{backend}-{n}"));
                for start in [1i64, 25, 49, 73] {
                    run(&input, &o, backend, &format!("{start}-{}", start + 23), n);
                }
                let got = read(&o, 1..=96);
                let p: Vec<f64> = (24..96)
                    .map(|i| harmonizer_core::synth::psnr(&got[i], 3, &want[i], 3, None).min(99.0))
                    .collect();
                let mean = p.iter().sum::<f64>() / p.len() as f64;
                let low = p.iter().cloned().fold(f64::INFINITY, f64::min);
                let (at, rest) = pairs(&got);
                let ratio = at.iter().sum::<f64>() / at.len() as f64 / rest;
                println!(
                    "{backend} pre-roll {n:2}: PSNR vs sequential, frames 25-96 mean {mean:.2} dB, lowest {low:.2} dB; \
                     warping error across the seams {:.5} {:.5} {:.5}, elsewhere {rest:.5}, ratio {ratio:.3}",
                    at[0], at[1], at[2]
                );
            }
        }
    }

    /// Issue 18's drift bar: over 96 frames of the synthetic sequence with
    /// the sway camera (it stays in the scene), the mean PSNR against the
    /// truth of the last 24 frames is within 0.3 dB of that of frames 5-28
    /// (after the warm-up), for the classical backend and, when ONNX Runtime
    /// is found, the default (the embedded network). Measured (scene-linear
    /// PSNR): classical 31.16 -> 31.13 dB, 1.2.0 29.79 -> 30.36 dB; 1.1.1
    /// went 30.06 -> 25.52 dB (its output, fed back through its history,
    /// crept in color).
    #[test]
    fn long_sequences_do_not_drift() {
        use harmonizer_core::synth::CameraPath;
        let dir = tempfile::tempdir().unwrap();
        let (w, h, t) = (320, 180, 96);
        let seq = Sequence::generate_with(
            SynthConfig {
                width: w,
                height: h,
                frames: t,
                ..Default::default()
            },
            CameraPath::Sway,
        )
        .unwrap();
        let (input, _) = seq.write_generic(dir.path(), "shot.####.exr").unwrap();
        let mut backends = vec!["classical"];
        if std::env::var_os("HARMONIZER_ORT_LIB").is_some() {
            backends.push("auto");
        }
        for backend in backends {
            let o = out(dir.path(), backend);
            let r = run(&input, &o, backend, "", 0);
            assert!(r.status.success(), "{}", text(&r).1);
            let got = read(&o, 1..=t as i64);
            let p: Vec<f64> = (0..t)
                .map(|i| harmonizer_core::synth::psnr(&got[i], 3, &seq.frames[i].truth, 3, None))
                .collect();
            let mean =
                |r: std::ops::Range<usize>| p[r.clone()].iter().sum::<f64>() / r.len() as f64;
            let (first, last) = (mean(4..28), mean(t - 24..t));
            println!(
                "{backend}: frames 5-28 {first:.2} dB, {}-{t} {last:.2} dB",
                t - 23
            );
            assert!(
                last > first - 0.3,
                "{backend} drifts: frames 5-28 {first:.2} dB, last 24 {last:.2} dB"
            );
        }
    }

    /// PSNR of 12-frame chunks (13-24, 25-36, 37-48) of the 48-frame
    /// synthetic sequence (its camera leaves the scene after about 50
    /// frames) against one sequential run, for pre-rolls 0, 4, 8 and 12,
    /// classical and neural. A measurement: run it alone, `cargo test -p
    /// harmonizer-cli --release --test cli preroll::measure -- --ignored
    /// --nocapture`.
    #[test]
    #[ignore = "a measurement: run it alone, see the doc comment"]
    fn measure() {
        let dir = tempfile::tempdir().unwrap();
        let (_, input) = small_sequence(dir.path(), 320, 180, 48);
        for backend in ["classical", "neural"] {
            let seq_out = out(dir.path(), &format!("{backend}-all"));
            run(&input, &seq_out, backend, "", 0);
            for n in [0usize, 4, 8, 12] {
                let mut line = format!("{backend} pre-roll {n:2}:");
                let mut firsts = Vec::new();
                for start in [13i64, 25, 37] {
                    let frames = format!("{start}-{}", start + 11);
                    let o = out(dir.path(), &format!("{backend}-{n}-{start}"));
                    run(&input, &o, backend, &frames, n);
                    let got = read(&o, start..=start + 11);
                    let want = read(&seq_out, start..=start + 11);
                    line += &format!(" {frames} {:.2} dB", psnr(&got, &want));
                    firsts.push(psnr(&got[..1], &want[..1]));
                }
                let first = firsts.iter().cloned().fold(f64::INFINITY, f64::min);
                println!("{line}; the chunks' first frames at least {first:.2} dB");
            }
        }
    }
}

/// Several inserted objects told apart by the host's object ids: the
/// generic layout's `mask.id` channel and the Blender layout's
/// `--insert-index 3,5`.
mod object_ids {
    use super::*;
    use harmonizer_core::io::exr::{write_channels, OutChannel};

    const W: usize = 96;
    const H: usize = 64;

    /// The touching boxes of `synth::touching_boxes` (Object Indices 3, 5).
    fn two_boxes() -> (Vec<Vec<f32>>, Vec<f32>, Vec<f32>) {
        let (rgb, mask, index) = harmonizer_core::synth::touching_boxes(W, H);
        (rgb.to_vec(), mask, index)
    }

    fn write(path: &Path, channels: &[(&str, &[f32])]) {
        write_channels(path, W, H, &OutChannel::floats(channels), None).unwrap();
    }

    fn run(input: &str, out: &str, extra: &[&str]) -> Output {
        let mut args = vec![
            "run",
            input,
            "-o",
            out,
            "--backend",
            "classical",
            "--threads",
            "2",
            // The boxes' filters are what these tests follow.
            "--set",
            "match_tone=true",
        ];
        args.extend(extra);
        harmonize(&args)
    }

    /// The output's mean absolute log2 change against the input over the
    /// pixels whose index is `which`, and the mean (signed) change.
    fn change(out: &Path, rgb: &[Vec<f32>], index: &[f32], which: f32) -> (f64, f64) {
        let f = LoadedFrame::read(out, Some(1), &LayoutOptions::default()).unwrap();
        let (mut abs, mut signed, mut n) = (0.0, 0.0, 0);
        for i in (0..W * H).filter(|&i| index[i] == which) {
            for (k, plane) in rgb.iter().enumerate() {
                let d = ((f.color[3 * i + k] + 1e-3) / (plane[i] + 1e-3)).log2() as f64;
                abs += d.abs();
                signed += d;
                n += 1;
            }
        }
        (abs / n as f64, signed / n as f64)
    }

    #[test]
    fn ids_harmonize_touching_objects_apart() {
        let dir = tempfile::tempdir().unwrap();
        let (rgb, mask, index) = two_boxes();
        let d = |name: &str| dir.path().join(name).to_string_lossy().to_string();
        let base = [("R", &rgb[0][..]), ("G", &rgb[1][..]), ("B", &rgb[2][..])];
        // Generic: the mask alone (one connected object), then with `mask.id`.
        let mut merged = base.to_vec();
        merged.push(("mask.insert", &mask));
        write(Path::new(&d("merged.0001.exr")), &merged);
        let mut ids = merged.clone();
        ids.push(("mask.id", &index));
        write(Path::new(&d("ids.0001.exr")), &ids);
        // Blender: the view layer's Combined and Object Index passes.
        let ones = vec![1.0; W * H];
        write(
            Path::new(&d("layer.0001.exr")),
            &[
                ("ViewLayer.Combined.R", &rgb[0]),
                ("ViewLayer.Combined.G", &rgb[1]),
                ("ViewLayer.Combined.B", &rgb[2]),
                ("ViewLayer.Combined.A", &ones),
                ("ViewLayer.Object Index.X", &index),
            ],
        );
        for (input, out, extra) in [
            ("merged.####.exr", "o_merged.####.exr", &[][..]),
            ("ids.####.exr", "o_ids.####.exr", &[][..]),
            (
                "layer.####.exr",
                "o_layer.####.exr",
                &["--insert-index", "3,5"][..],
            ),
            (
                "layer.####.exr",
                "o_one.####.exr",
                &["--insert-index", "3"][..],
            ),
        ] {
            let o = run(&d(input), &d(out), extra);
            assert!(o.status.success(), "{input} {extra:?}: {:?}", text(&o));
        }
        let at = |name: &str| dir.path().join(name);
        let merged_right = change(&at("o_merged.0001.exr"), &rgb, &index, 5.0).0;
        let (ids_right, _) = change(&at("o_ids.0001.exr"), &rgb, &index, 5.0);
        let (_, ids_wrong) = change(&at("o_ids.0001.exr"), &rgb, &index, 3.0);
        let (layer_right, _) = change(&at("o_layer.0001.exr"), &rgb, &index, 5.0);
        let (_, layer_wrong) = change(&at("o_layer.0001.exr"), &rgb, &index, 3.0);
        let (one_right, _) = change(&at("o_one.0001.exr"), &rgb, &index, 5.0);
        eprintln!(
            "right box changed: merged {merged_right:.3}, mask.id {ids_right:.3}, \
             --insert-index 3,5 {layer_right:.3}, 3 {one_right:.3} stops; wrong box: \
             mask.id {ids_wrong:.3}, --insert-index 3,5 {layer_wrong:.3}"
        );
        assert!(merged_right > 0.1, "{merged_right}");
        assert!(ids_right < 0.02 && layer_right < 0.02 && one_right < 0.02);
        assert!(ids_wrong < -0.5 && layer_wrong < -0.5);
        assert!((ids_wrong - layer_wrong).abs() < 1e-3);
    }

    #[test]
    fn bad_indices_and_missing_id_channels_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let (rgb, mask, _) = two_boxes();
        let input = dir.path().join("in.0001.exr");
        write(
            &input,
            &[
                ("R", &rgb[0]),
                ("G", &rgb[1]),
                ("B", &rgb[2]),
                ("mask.insert", &mask),
            ],
        );
        let pattern = dir.path().join("in.####.exr").to_string_lossy().to_string();
        let out = dir.path().join("o.####.exr").to_string_lossy().to_string();
        for (extra, want) in [
            (
                &["--insert-index", "3,x"][..],
                &["--insert-index", "\"x\""][..],
            ),
            (
                &["--insert-index", "3,0"],
                &["--insert-index", "0 is not above 0"],
            ),
            (&["--insert-index", "3,3"], &["3 is named twice"]),
            (
                &["--layout", "blender", "--insert-index", "3,5"],
                &[
                    "in.0001.exr",
                    "frame 1",
                    "--insert-index 3,5",
                    "Object Index",
                ],
            ),
            (
                &["--channel", "insert_id=objid.X"],
                &["in.0001.exr", "frame 1", "objid.X"],
            ),
        ] {
            let o = run(&pattern, &out, extra);
            let (_, e) = text(&o);
            assert!(!o.status.success(), "{extra:?} succeeded");
            for w in want {
                assert!(e.contains(w), "{extra:?}: {w:?} not in {e}");
            }
        }
    }
}
