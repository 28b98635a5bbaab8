//! The `harmonize` command: enhance EXR sequences (`run`), the synthetic
//! demo (`demo`), benchmarks (`bench`) and file inspection (`info`).
//! The logic lives in `harmonizer-core`; this is argument handling and output.

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;

use clap::{Parser, Subcommand};
use harmonizer_core::denoise::{DenoiseInput, DenoiseOptions, Denoiser};
use harmonizer_core::io::layout::{ChannelMapping, LayoutOptions, LayoutPreset};
use harmonizer_core::io::pattern::{FramePattern, FrameRange};
use harmonizer_core::io::run::{
    plan, report_json, run_sequence, summary_json, FrameResult, RunOptions,
};
use harmonizer_core::params::{BackendKind, DenoiseMode};
use harmonizer_core::synth::{self, Scene, Sequence, SynthConfig};
use harmonizer_core::{
    Device, DeviceOptions, Error, ModelSource, ParamValue, Params, Result, Session,
};
use serde_json::{json, Map, Value};

mod files;
use files::Files;

#[derive(Parser)]
#[command(
    name = "harmonize",
    version,
    about = "Temporal post-render enhancer for rendered EXR sequences"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(clap::Args)]
struct SessionArgs {
    /// Backend: auto (neural when a model is available, else classical), neural, classical or bypass.
    #[arg(long, default_value = "auto")]
    backend: String,
    /// ONNX model file (its manifest `<name>.json` beside it); default: the embedded model.
    #[arg(long)]
    model: Option<PathBuf>,
    /// Previous enhanced frames used as context (0..=8).
    #[arg(long, default_value_t = 4)]
    context: usize,
    /// Worker threads (0 = one per core).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Any session parameter, `name=value` (repeatable), e.g. `--set strength=0.8`.
    #[arg(long = "set", value_name = "NAME=VALUE")]
    set: Vec<String>,
}

#[derive(Subcommand)]
enum Command {
    /// Enhance an EXR sequence: `harmonize run in/####.exr -o out/####.exr`.
    Run {
        /// Input frame pattern (`####`, `%04d`, `$F4`, `${F4}` or `<F4>`).
        input: String,
        /// Output frame pattern.
        #[arg(short, long)]
        output: String,
        /// Channel layout: auto, generic or blender.
        #[arg(long, default_value = "auto")]
        layout: String,
        /// Map a role to channels: color=R,G,B; coverage=A; depth=Z; motion=X,Y
        /// (prefix `-` negates); normal=X,Y,Z; insert=M; insert_id=ID. Repeatable.
        #[arg(long = "channel", value_name = "ROLE=CH[,CH...]")]
        channel: Vec<String>,
        /// Blender layout: the object index (Object Index pass) of the
        /// inserted object; several (`3,5`): each index is one object.
        #[arg(long, value_name = "N[,N...]")]
        insert_index: Option<String>,
        /// Only frames A-B (all must exist).
        #[arg(long)]
        frames: Option<String>,
        /// Process the N frames before A first, without writing them, so a
        /// chunk A-B of a longer sequence starts with the temporal state a
        /// sequential run would have (needs --frames; fewer at the start of
        /// the sequence).
        #[arg(long, default_value_t = 0)]
        preroll: usize,
        /// What a gap in frame numbers does: reset the temporal state or keep it (with a warning).
        #[arg(long, default_value = "reset")]
        gap: String,
        /// Write per-frame timings, resets and warnings as JSON.
        #[arg(long)]
        report: Option<PathBuf>,
        #[command(flatten)]
        session: SessionArgs,
    },
    /// Generate the synthetic demo sequence, enhance it, write a contact sheet and print metrics.
    Demo {
        /// Output directory.
        #[arg(long, default_value = "harmonize-demo")]
        out: PathBuf,
        #[command(flatten)]
        session: SessionArgs,
    },
    /// Time the backends on synthetic frames against a plain copy of the same bytes.
    Bench {
        /// Print one JSON object.
        #[arg(long)]
        json: bool,
        /// Worker threads (0 = one per core).
        #[arg(long, default_value_t = 0)]
        threads: usize,
        /// Frame sizes, WxH, comma separated.
        #[arg(long, default_value = "1024x576,1920x1080")]
        sizes: String,
        /// Measured frames per run, after the warm-up frames (context + 1, at
        /// least 2: the history fills and buffers are reused from then on,
        /// as over a long sequence); the median is reported.
        #[arg(long, default_value_t = 10)]
        frames: usize,
        /// Backends to time (default: classical, plus neural when a model is
        /// available, plus denoise when Open Image Denoise is found);
        /// `denoise` is the classical backend with `denoise=on` (the denoise
        /// stage with its accumulation), timed beside OIDN alone.
        #[arg(long)]
        backend: Vec<String>,
        /// ONNX model file for the neural backend.
        #[arg(long)]
        model: Option<PathBuf>,
        /// Previous frames used as context.
        #[arg(long, default_value_t = 4)]
        context: usize,
        /// Any session parameter, `name=value` (repeatable), e.g. `--set
        /// denoise=on`: with the denoise stage on, the frames carry an
        /// albedo and Open Image Denoise alone is timed on them too.
        #[arg(long = "set", value_name = "NAME=VALUE")]
        set: Vec<String>,
        /// The frames carry their albedo (what a host that renders its
        /// inserts gives): the insert color matrix (`albedo_tone`) is timed.
        #[arg(long)]
        albedo: bool,
    },
    /// Write a synthetic sequence with ground truth as `generic` EXRs
    /// (DIR/input/shot.####.exr, DIR/truth/shot.####.exr): inputs for tests,
    /// benchmarks and farm trials.
    Synth {
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
        /// Number of frames.
        #[arg(long, default_value_t = 24)]
        frames: usize,
        /// Frame size, WxH.
        #[arg(long, default_value = "320x180")]
        size: String,
        /// Number of the first frame.
        #[arg(long, default_value_t = 1)]
        first: i64,
        /// Seed of the holes, flicker and noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Camera path: default (leaves the scene after about 50 frames) or
        /// sway (stays in it for any length).
        #[arg(long, default_value = "default")]
        camera: String,
        /// Also write the ground truth (DIR/truth/).
        #[arg(long)]
        truth: bool,
    },
    /// Describe an EXR file: parts, channels, detected layout, camera.
    Info {
        /// The file.
        file: PathBuf,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let r = match cli.command {
        Command::Run {
            input,
            output,
            layout,
            channel,
            insert_index,
            frames,
            preroll,
            gap,
            report,
            session,
        } => cmd_run(
            input,
            output,
            layout,
            channel,
            insert_index,
            frames,
            preroll,
            gap,
            report,
            session,
        ),
        Command::Demo { out, session } => cmd_demo(&out, session),
        Command::Bench {
            json,
            threads,
            sizes,
            frames,
            backend,
            model,
            context,
            set,
            albedo,
        } => cmd_bench(
            json, threads, &sizes, frames, backend, model, context, &set, albedo,
        ),
        Command::Synth {
            out,
            frames,
            size,
            first,
            seed,
            camera,
            truth,
        } => cmd_synth(&out, frames, &size, first, seed, &camera, truth),
        Command::Info { file } => cmd_info(&file),
    };
    match r {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("harmonize: error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Parses `--set` values: true/false, integers, numbers, else strings.
fn parse_value(v: &str) -> ParamValue {
    match v {
        "true" => ParamValue::Bool(true),
        "false" => ParamValue::Bool(false),
        _ => v
            .parse::<i64>()
            .map(ParamValue::Int)
            .or_else(|_| v.parse::<f64>().map(ParamValue::Float))
            .unwrap_or_else(|_| ParamValue::Str(v.to_string())),
    }
}

/// Applies `--set NAME=VALUE` entries to `params`.
fn apply_sets(params: &mut Params, sets: &[String]) -> Result<()> {
    for s in sets {
        let (k, v) = s.split_once('=').ok_or_else(|| {
            Error::invalid(format!(
                "--set {s:?}: expected NAME=VALUE, e.g. strength=0.8"
            ))
        })?;
        params.set(k.trim(), &parse_value(v.trim()))?;
    }
    Ok(())
}

fn make_session(args: &SessionArgs, gap: Option<&str>) -> Result<Session> {
    let mut params = Params::default();
    params.set("backend", &ParamValue::Str(args.backend.clone()))?;
    params.set("context_frames", &ParamValue::Int(args.context as i64))?;
    if let Some(g) = gap {
        params.set("gap_policy", &ParamValue::Str(g.to_string()))?;
    }
    apply_sets(&mut params, &args.set)?;
    let device = Device::new(DeviceOptions {
        threads: args.threads,
        model: args
            .model
            .clone()
            .map(ModelSource::File)
            .unwrap_or_default(),
        ..DeviceOptions::default()
    })?;
    Session::new(device, params)
}

/// The model file and its manifest, inputs of any command given `--model`.
fn model_inputs(files: &mut Files, model: Option<&Path>) {
    if let Some(m) = model {
        files.input("--model", m);
        files.input(
            "model manifest",
            harmonizer_core::backend::neural::manifest_path(m),
        );
    }
}

fn write_json(path: &Path, v: &Value) -> Result<()> {
    let text = serde_json::to_string_pretty(v).map_err(|e| Error::io(path, e))?;
    harmonizer_core::io::exr::write_atomic(path, |tmp| std::fs::write(tmp, text.as_bytes()))
}

/// `--insert-index N[,N...]`: the Object Index value of the inserted
/// object(s), or of several objects (each then one object, its index its
/// id: above 0 and named once).
fn insert_indices(arg: &str) -> Result<Vec<i64>> {
    let bad = |why: String| {
        harmonizer_core::Error::invalid(format!(
            "--insert-index {arg:?}: {why} (expected N, or N,N,... with Object Index values above 0)"
        ))
    };
    let mut out: Vec<i64> = Vec::new();
    for part in arg.split(',').map(str::trim) {
        let n: i64 = part
            .parse()
            .map_err(|_| bad(format!("{part:?} is not an integer")))?;
        out.push(n);
    }
    harmonizer_core::io::layout::check_insert_indices(&format!("--insert-index {arg:?}"), &out)?;
    Ok(out)
}

fn layout_options(
    layout: &str,
    channel: &[String],
    insert_index: Option<&str>,
) -> Result<LayoutOptions> {
    let mut mapping = ChannelMapping::default();
    for c in channel {
        mapping.add(c)?;
    }
    let indices = insert_index.map(insert_indices).transpose()?;
    let (insert_index, insert_indices) = match indices.as_deref() {
        Some([one]) => (Some(*one), Vec::new()),
        Some(many) => (None, many.to_vec()),
        None => (None, Vec::new()),
    };
    Ok(LayoutOptions {
        preset: LayoutPreset::parse(layout)?,
        mapping,
        insert_index,
        insert_indices,
    })
}

fn print_summary(results: &[FrameResult], output: &str) {
    let s = summary_json(results);
    let resets: Vec<String> = results
        .iter()
        .filter_map(|r| {
            r.report
                .reset
                .map(|x| format!("{} ({})", r.planned.frame, x.name()))
        })
        .collect();
    let backend = results.first().map_or("-", |r| r.report.backend.as_str());
    println!(
        "harmonize: {} frame(s) written to {output}; backend {backend}; {:.1} ms/frame processing ({:.1} read, {:.1} write)",
        results.len(),
        s["mean_process_ms"].as_f64().unwrap_or(0.0),
        s["mean_read_ms"].as_f64().unwrap_or(0.0),
        s["mean_write_ms"].as_f64().unwrap_or(0.0),
    );
    println!(
        "  resets: {}",
        if resets.is_empty() {
            "none".into()
        } else {
            resets.join(", ")
        }
    );
    println!(
        "  sanitized color samples (NaN, Inf): {}; out-of-gamut pixels passed through: {}; warnings: {}",
        s["sanitized"], s["out_of_gamut"], s["warnings"]
    );
    for r in results {
        if let Some(d) = &r.report.denoise_decision {
            println!("  frame {}: {d}", r.planned.frame);
        }
    }
    println!("  frames denoised: {}", s["denoised"]);
    for r in results {
        for w in r.read_warnings.iter().chain(&r.report.warnings) {
            println!("  warning: {w}");
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn cmd_run(
    input: String,
    output: String,
    layout: String,
    channel: Vec<String>,
    insert_index: Option<String>,
    frames: Option<String>,
    preroll: usize,
    gap: String,
    report: Option<PathBuf>,
    session_args: SessionArgs,
) -> Result<()> {
    let options = RunOptions {
        input,
        output: output.clone(),
        layout: layout_options(&layout, &channel, insert_index.as_deref())?,
        frames: frames.as_deref().map(FrameRange::parse).transpose()?,
        preroll,
    };
    let planned = plan(&options)?;
    let mut files = Files::default();
    for p in &planned {
        files.input(format!("input frame {}", p.frame), &p.input);
    }
    model_inputs(&mut files, session_args.model.as_deref());
    for p in planned.iter().filter(|p| !p.preroll) {
        files.output(format!("output frame {}", p.frame), &p.output);
    }
    if let Some(path) = &report {
        files.output("--report file", path);
    }
    files.check()?;
    let mut session_args = session_args;
    if let Some((set, why)) = render_hints(&options, &planned, &session_args.set) {
        println!("harmonize: {why}");
        session_args.set.push(set);
    }
    let mut session = make_session(&session_args, Some(&gap))?;
    let bar = progress_bar(planned.len() as u64);
    let mut done: Vec<FrameResult> = Vec::new();
    let r = run_sequence(&mut session, &options, &planned, false, &mut |res| {
        bar.set_message(format!("frame {}", res.planned.frame));
        bar.inc(1);
        done.push(res.clone());
        Ok(())
    });
    bar.finish_and_clear();
    // The summary counts the frames written; the pre-roll frames are in
    // the report's frame list, marked.
    let prerolled = done.iter().filter(|r| r.planned.preroll).count();
    let written: Vec<FrameResult> = done
        .iter()
        .filter(|r| !r.planned.preroll)
        .cloned()
        .collect();
    if let Some(path) = &report {
        write_json(
            path,
            &report_json(&options, &layout, &done, r.as_ref().err()),
        )?;
    }
    r?;
    print_summary(&written, &output);
    if prerolled > 0 {
        println!("  pre-roll: {prerolled} frame(s) before the first, processed and not written");
    }
    if let Some(path) = &report {
        println!("  report: {}", path.display());
    }
    Ok(())
}

/// What the first input file says about its noise (Blender's
/// `cycles.<layer>.samples`, Cycles' `Noisy Image` pass), as the `--set`
/// a host would pass and why, when the user set neither `denoise` nor
/// `samples` (`RenderHints::params`; its headers only); `None` when the
/// file says nothing or cannot be read (the run then reports that itself).
fn render_hints(
    options: &RunOptions,
    planned: &[harmonizer_core::io::run::PlannedFrame],
    sets: &[String],
) -> Option<(String, String)> {
    if sets
        .iter()
        .any(|s| s.starts_with("denoise=") || s.starts_with("samples="))
    {
        return None;
    }
    let first = planned.first()?;
    let hints = harmonizer_core::io::exr::read_render_hints(&first.input, &options.layout);
    let (name, value, why) = hints.params()?;
    let value = match value {
        ParamValue::Str(s) => s,
        ParamValue::Int(i) => i.to_string(),
        _ => return None,
    };
    Some((
        format!("{name}={value}"),
        format!("{why} (from {})", first.input.display()),
    ))
}

fn progress_bar(len: u64) -> indicatif::ProgressBar {
    if !std::io::stderr().is_terminal() {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(len);
    if let Ok(style) =
        indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} {msg} [{elapsed} < {eta}]")
    {
        bar.set_style(style);
    }
    bar
}

fn srgb_oetf(v: f32) -> u8 {
    let v = v.clamp(0.0, 1.0);
    let s = if v <= 0.003_130_8 {
        12.92 * v
    } else {
        1.055 * v.powf(1.0 / 2.4) - 0.055
    };
    (s * 255.0 + 0.5) as u8
}

/// A contact sheet: one row per frame, columns input | enhanced | truth.
fn contact_sheet(path: &Path, rows: &[[(&[f32], usize); 3]], w: usize, h: usize) -> Result<()> {
    let gap = 4;
    let (sw, sh) = (
        3 * w + 2 * gap,
        rows.len() * h + (rows.len().saturating_sub(1)) * gap,
    );
    let mut img = image::RgbImage::from_pixel(sw as u32, sh as u32, image::Rgb([24, 24, 24]));
    for (r, row) in rows.iter().enumerate() {
        for (c, (data, ch)) in row.iter().enumerate() {
            for y in 0..h {
                for x in 0..w {
                    let k = (y * w + x) * ch;
                    let px = image::Rgb([
                        srgb_oetf(data[k]),
                        srgb_oetf(data[k + 1]),
                        srgb_oetf(data[k + 2]),
                    ]);
                    img.put_pixel((c * (w + gap) + x) as u32, (r * (h + gap) + y) as u32, px);
                }
            }
        }
    }
    let enc = |tmp: &Path| img.save_with_format(tmp, image::ImageFormat::Png);
    harmonizer_core::io::exr::write_atomic(path, enc)
}

fn cmd_synth(
    out: &Path,
    frames: usize,
    size: &str,
    first: i64,
    seed: u64,
    camera: &str,
    truth: bool,
) -> Result<()> {
    let [(width, height)] = parse_sizes(size)?[..] else {
        return Err(Error::invalid(format!("--size {size:?}: expected one WxH")));
    };
    let config = SynthConfig {
        width,
        height,
        frames,
        seed,
        first_frame: first,
    };
    let scene = Scene::with_path(config, synth::CameraPath::parse(camera)?)?;
    let pattern = "shot.####.exr";
    let input = FramePattern::parse(&out.join("input").join(pattern).to_string_lossy())?;
    let truths = FramePattern::parse(&out.join("truth").join(pattern).to_string_lossy())?;
    let mut files = Files::default();
    for n in first..first + frames as i64 {
        files.output(format!("input frame {n}"), input.path(n));
        if truth {
            files.output(format!("truth frame {n}"), truths.path(n));
        }
    }
    files.check()?;
    let bar = progress_bar(frames as u64);
    for n in first..first + frames as i64 {
        let f = scene.frame(n);
        harmonizer_core::io::exr::write_generic(&input.path(n), &f.input)?;
        if truth {
            harmonizer_core::io::exr::write_truth(&truths.path(n), &f)?;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    println!(
        "harmonize synth: {frames} frame(s) {width}x{height}, camera {camera}: {}",
        input.as_str()
    );
    if truth {
        println!("  truth: {}", truths.as_str());
    }
    Ok(())
}

fn cmd_demo(out: &Path, args: SessionArgs) -> Result<()> {
    let config = SynthConfig::default();
    println!(
        "harmonize demo: {} frames {}x{} (holes, an inserted sphere with a tone mismatch and no contact shadow, flicker)",
        config.frames, config.width, config.height
    );
    let pattern = "frame.####.exr";
    let sheet = out.join("contact_sheet.png");
    let metrics = out.join("metrics.json");
    let mut files = Files::default();
    model_inputs(&mut files, args.model.as_deref());
    for (sub, what) in [
        ("input", "input frame"),
        ("truth", "truth frame"),
        ("output", "output frame"),
    ] {
        let p = FramePattern::parse(&out.join(sub).join(pattern).to_string_lossy())?;
        for t in 0..config.frames as i64 {
            let n = config.first_frame + t;
            files.output(format!("{what} {n}"), p.path(n));
        }
    }
    files.output("contact sheet", &sheet);
    files.output("metrics", &metrics);
    files.check()?;
    let seq = Sequence::generate(config)?;
    let (input, truth) = seq.write_generic(out, pattern)?;
    let output = out
        .join("output")
        .join(pattern)
        .to_string_lossy()
        .to_string();
    let options = RunOptions {
        input: input.clone(),
        output: output.clone(),
        layout: LayoutOptions::default(),
        frames: None,
        preroll: 0,
    };
    let planned = plan(&options)?;
    let mut session = make_session(&args, None)?;
    let bar = progress_bar(planned.len() as u64);
    let results = run_sequence(&mut session, &options, &planned, true, &mut |_| {
        bar.inc(1);
        Ok(())
    })?;
    bar.finish_and_clear();
    let outs: Vec<Vec<f32>> = results
        .iter()
        .map(|r| synth::interleave(r.output.as_ref().expect("outputs kept"), 4))
        .collect();
    let ins: Vec<Vec<f32>> = seq.frames.iter().map(|f| f.input.color.clone()).collect();
    let m = json!({
        "backend": results.first().map(|r| r.report.backend.clone()),
        "psnr_input": seq.psnr(&ins, 4, "all"),
        "psnr_output": seq.psnr(&outs, 4, "all"),
        "psnr_holes_input": seq.psnr(&ins, 4, "holes"),
        "psnr_holes_output": seq.psnr(&outs, 4, "holes"),
        "psnr_insert_input": seq.psnr(&ins, 4, "insert"),
        "psnr_insert_output": seq.psnr(&outs, 4, "insert"),
        "psnr_shadow_input": seq.psnr(&ins, 4, "shadow"),
        "psnr_shadow_output": seq.psnr(&outs, 4, "shadow"),
        "warping_error_input": seq.warping_error(&ins, 4),
        "warping_error_output": seq.warping_error(&outs, 4),
        "mean_process_ms": results.iter().map(|r| r.report.total_ms).sum::<f64>() / results.len().max(1) as f64,
    });
    let picks: Vec<usize> = [0, 7, 15, 23]
        .into_iter()
        .filter(|&i| i < seq.frames.len())
        .collect();
    let rows: Vec<[(&[f32], usize); 3]> = picks
        .iter()
        .map(|&i| {
            [
                (&ins[i][..], 4),
                (&outs[i][..], 4),
                (&seq.frames[i].truth[..], 3),
            ]
        })
        .collect();
    contact_sheet(&sheet, &rows, config.width, config.height)?;
    write_json(&metrics, &m)?;
    let f = |k: &str| m[k].as_f64().unwrap_or(f64::NAN);
    println!("  input:   {input}");
    println!("  output:  {output}");
    println!("  truth:   {truth}");
    println!(
        "  contact sheet (input | enhanced | truth): {}",
        sheet.display()
    );
    println!("  metrics: {}", metrics.display());
    println!("  backend: {}", m["backend"].as_str().unwrap_or("-"));
    println!(
        "  PSNR vs truth, all pixels:  input {:6.2} dB -> output {:6.2} dB",
        f("psnr_input"),
        f("psnr_output")
    );
    println!(
        "  PSNR vs truth, holes:       input {:6.2} dB -> output {:6.2} dB",
        f("psnr_holes_input"),
        f("psnr_holes_output")
    );
    println!(
        "  PSNR vs truth, insert:      input {:6.2} dB -> output {:6.2} dB",
        f("psnr_insert_input"),
        f("psnr_insert_output")
    );
    println!(
        "  PSNR vs truth, shadow:      input {:6.2} dB -> output {:6.2} dB",
        f("psnr_shadow_input"),
        f("psnr_shadow_output")
    );
    println!(
        "  warping error:              input {:.5} -> output {:.5}",
        f("warping_error_input"),
        f("warping_error_output")
    );
    Ok(())
}

fn parse_sizes(s: &str) -> Result<Vec<(usize, usize)>> {
    s.split(',')
        .map(|t| {
            let t = t.trim();
            let (w, h) = t
                .split_once('x')
                .ok_or_else(|| Error::invalid(format!("--sizes: {t:?} is not WxH")))?;
            let w: usize = w
                .parse()
                .map_err(|_| Error::invalid(format!("--sizes: bad width in {t:?}")))?;
            let h: usize = h
                .parse()
                .map_err(|_| Error::invalid(format!("--sizes: bad height in {t:?}")))?;
            if w < 8 || h < 8 {
                return Err(Error::invalid(format!(
                    "--sizes: {t:?} is too small (at least 8x8)"
                )));
            }
            Ok((w, h))
        })
        .collect()
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(|a, b| a.total_cmp(b));
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Whether a session with `params` denoises (on, or auto told a sample
/// count of 1 to 64): its bench frames then carry an albedo.
fn denoising(params: &Params) -> bool {
    match params.denoise {
        DenoiseMode::On => true,
        DenoiseMode::Auto => (1..=64).contains(&params.samples),
        DenoiseMode::Off | DenoiseMode::Temporal => false,
    }
}

/// Open Image Denoise alone on one synthetic frame: the time of the
/// `Denoiser::denoise` call, in ms, on the frame's interleaved RGB with its
/// albedo and normal (what the session's stage hands it).
fn oidn_alone(
    d: &mut Denoiser,
    f: &harmonizer_core::synth::SynthInput,
    params: &Params,
) -> Result<f64> {
    let rgb: Vec<f32> = f
        .color
        .chunks_exact(4)
        .flat_map(|p| [p[0], p[1], p[2]])
        .collect();
    let mut out = vec![0.0f32; rgb.len()];
    let input = DenoiseInput {
        width: f.width,
        height: f.height,
        color: &rgb,
        albedo: Some(&f.albedo),
        normal: Some(&f.normal),
    };
    let options = DenoiseOptions {
        hdr: true,
        quality: params.denoise_quality,
        clean_aux: false,
        prefilter: params.denoise_prefilter,
        max_memory_mb: None,
    };
    let t = std::time::Instant::now();
    d.denoise(&input, options, &mut out)?;
    let ms = t.elapsed().as_secs_f64() * 1e3;
    std::hint::black_box(&out);
    Ok(ms)
}

fn bench_one(
    device: &Arc<Device>,
    backend: &str,
    size: (usize, usize),
    frames: usize,
    context: usize,
    sets: &[String],
    albedo: bool,
) -> Result<Value> {
    // Steady state: the first `context` frames fill the history, and until
    // it is full every frame's kept buffers are fresh memory (page faults).
    let warmup = (context + 1).max(2);
    let mut params = Params::default();
    params.set("backend", &ParamValue::Str(backend.to_string()))?;
    params.set("context_frames", &ParamValue::Int(context as i64))?;
    apply_sets(&mut params, sets)?;
    let denoise = denoising(&params);
    // Open Image Denoise alone, on the device's library and threads.
    let mut alone = match denoise {
        true => Some(Denoiser::new(&device.oidn()?)?),
        false => None,
    };
    let mut session = Session::new(device.clone(), params.clone())?;
    let scene = Scene::new(SynthConfig {
        width: size.0,
        height: size.1,
        frames: warmup + frames,
        seed: 1,
        first_frame: 1,
    })?;
    let mut totals = Vec::new();
    let mut copies = Vec::new();
    let mut alone_ms = Vec::new();
    let mut dst: Vec<Vec<f32>> = Vec::new();
    let mut stages: Vec<(String, Vec<f64>)> = Vec::new();
    for t in 0..(warmup + frames) {
        // Each frame is made between timed frames (so its buffers are not
        // in cache when timed), on the device's own threads: made on other
        // threads (rayon's global pool), every stage of the next frame ran
        // 35-60 % slower on a 2-core machine, an effect of the bench's own
        // extra threads on scheduling, not of the library.
        let f = device.pool().install(|| scene.frame(1 + t as i64));
        let input = match denoise || albedo {
            true => f.input.frame_input_with_albedo(),
            false => f.input.frame_input(),
        };
        let (out, report) = session.process(&input, None)?;
        // The memory-bandwidth floor: copy the same bytes (input buffers and output).
        let bufs: [&[f32]; 7] = [
            &f.input.color,
            &f.input.depth,
            &f.input.motion,
            &f.input.normal,
            &f.input.coverage,
            &f.input.insert_mask,
            &out.data,
        ];
        // Destination buffers are allocated and touched once, so the copy
        // measures memory bandwidth, not first-touch page faults.
        if dst.is_empty() {
            dst = bufs.iter().map(|b| vec![1.0f32; b.len()]).collect();
        }
        let tc = std::time::Instant::now();
        for (d, s) in dst.iter_mut().zip(bufs) {
            d.copy_from_slice(s);
        }
        std::hint::black_box(&dst);
        let copy_ms = tc.elapsed().as_secs_f64() * 1e3;
        // A host copies the result out and hands the buffer back.
        session.recycle(out);
        // The same frame through Open Image Denoise alone (its first call
        // sets the filters up, as the session's first frame does).
        let alone = match alone.as_mut() {
            Some(d) => Some(oidn_alone(d, &f.input, &params)?),
            None => None,
        };
        if t < warmup {
            continue;
        }
        totals.push(report.total_ms);
        copies.push(copy_ms);
        alone_ms.extend(alone);
        for (k, v) in &report.stages.0 {
            match stages.iter_mut().find(|(n, _)| n == k) {
                Some(e) => e.1.push(*v),
                None => stages.push((k.clone(), vec![*v])),
            }
        }
    }
    let mut sm = Map::new();
    for (k, v) in stages {
        sm.insert(k, json!(median(v)));
    }
    let mut run = json!({
        "backend": session.backend_name(),
        "width": size.0,
        "height": size.1,
        "context": context,
        "threads": device.threads(),
        "frames": frames,
        "warmup_frames": warmup,
        "ms_per_frame": median(totals),
        "copy_floor_ms": median(copies),
        "stages": Value::Object(sm),
    });
    if !sets.is_empty() {
        run["set"] = json!(sets);
    }
    if albedo {
        run["albedo"] = json!(true);
    }
    if !alone_ms.is_empty() {
        run["oidn_alone_ms"] = json!(median(alone_ms));
    }
    Ok(run)
}

#[allow(clippy::too_many_arguments)]
fn cmd_bench(
    as_json: bool,
    threads: usize,
    sizes: &str,
    frames: usize,
    backends: Vec<String>,
    model: Option<PathBuf>,
    context: usize,
    sets: &[String],
    albedo: bool,
) -> Result<()> {
    let sizes = parse_sizes(sizes)?;
    if frames == 0 {
        return Err(Error::invalid("--frames: must be at least 1"));
    }
    let device = Device::new(DeviceOptions {
        threads,
        model: model.map(ModelSource::File).unwrap_or_default(),
        ..DeviceOptions::default()
    })?;
    let backends = if backends.is_empty() {
        let mut b = vec!["classical".to_string()];
        match device.neural_model() {
            Ok(Some(_)) => b.push("neural".to_string()),
            Ok(None) => {}
            Err(e) => eprintln!("harmonize bench: neural backend skipped: {e}"),
        }
        match device.oidn() {
            Ok(_) => b.push("denoise".to_string()),
            Err(e) => eprintln!("harmonize bench: denoise skipped: {e}"),
        }
        b
    } else {
        for b in backends.iter().filter(|b| *b != "denoise") {
            BackendKind::parse(b)?;
        }
        backends
    };
    let mut runs = Vec::new();
    for b in &backends {
        for &size in &sizes {
            let run = match b.as_str() {
                // The denoise stage on the classical backend's frames.
                "denoise" => {
                    let mut with = sets.to_vec();
                    with.push("denoise=on".to_string());
                    let mut run =
                        bench_one(&device, "classical", size, frames, context, &with, albedo)?;
                    run["backend"] = json!("denoise");
                    run
                }
                _ => bench_one(&device, b, size, frames, context, sets, albedo)?,
            };
            if !as_json {
                let stages: Vec<String> = run["stages"]
                    .as_object()
                    .map(|m| {
                        m.iter()
                            .map(|(k, v)| format!("{k} {:.2}", v.as_f64().unwrap_or(0.0)))
                            .collect()
                    })
                    .unwrap_or_default();
                let total = run["ms_per_frame"].as_f64().unwrap_or(f64::NAN);
                let alone = run["oidn_alone_ms"]
                    .as_f64()
                    .map(|ms| format!("  OIDN alone {ms:.1} ms ({:.2}x)", total / ms))
                    .unwrap_or_default();
                println!(
                    "{:<10} {:>5}x{:<5} K={} threads={}  {:8.2} ms/frame  copy floor {:6.2} ms  ({:.1}x){alone}  stages: {}",
                    run["backend"].as_str().unwrap_or("?"),
                    size.0,
                    size.1,
                    context,
                    device.threads(),
                    run["ms_per_frame"].as_f64().unwrap_or(f64::NAN),
                    run["copy_floor_ms"].as_f64().unwrap_or(f64::NAN),
                    run["ms_per_frame"].as_f64().unwrap_or(f64::NAN) / run["copy_floor_ms"].as_f64().unwrap_or(f64::NAN),
                    stages.join(", ")
                );
            }
            runs.push(run);
        }
    }
    if as_json {
        println!("{}", json!({ "runs": runs }));
    }
    Ok(())
}

fn cmd_info(path: &Path) -> Result<()> {
    let i = harmonizer_core::io::exr::info(path)?;
    println!("{}", path.display());
    println!("  size: {}x{} (display window)", i.display.0, i.display.1);
    println!("  parts: {}", i.parts.len());
    for (k, (name, w, h)) in i.parts.iter().enumerate() {
        println!("    [{k}] {:?} {w}x{h}", name);
    }
    println!("  channels: {}", i.channels.len());
    for (name, kind) in &i.channels {
        println!("    {name} ({})", kind.name());
    }
    match &i.view_layer {
        Some(l) => println!("  layout: {} (view layer {l:?})", i.layout.name()),
        None => println!("  layout: {}", i.layout.name()),
    }
    println!("  roles found: {}", i.roles.join(", "));
    println!(
        "  camera: {}",
        if i.camera {
            "present (worldToCamera, worldToNDC)"
        } else {
            "absent"
        }
    );
    Ok(())
}
