//! Running a session over an EXR sequence: the loop behind `harmonize run`
//! (and `demo`). Frames are read, enhanced and written in increasing order;
//! the first failing frame stops the run with an error that names it, and
//! outputs already written stay.

use std::path::PathBuf;

use serde_json::{json, Value};

use super::exr::{refuse_input, LoadedFrame, OutputMeta};
use super::guard::ReadLimits;
use super::layout::LayoutOptions;
use super::pattern::{select_frames, FramePattern, FrameRange};
use crate::error::{Error, Result};
use crate::frame::Image;
use crate::session::{FrameReport, Session};

/// What to run.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Input frame pattern.
    pub input: String,
    /// Output frame pattern.
    pub output: String,
    /// How channels are found.
    pub layout: LayoutOptions,
    /// Only these frames (all must exist); `None` = every existing frame.
    pub frames: Option<FrameRange>,
    /// Frames before `frames` run first to warm the temporal state, not
    /// written (those of `start - preroll ..= start - 1` that exist): a
    /// chunk of a sequence then starts with the history a sequential run
    /// would have. Needs `frames`.
    pub preroll: usize,
}

/// One frame to process.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PlannedFrame {
    /// Frame number.
    pub frame: i64,
    /// Input file.
    pub input: PathBuf,
    /// Output file.
    pub output: PathBuf,
    /// A pre-roll frame ([`RunOptions::preroll`]): processed, not written.
    pub preroll: bool,
}

/// One processed frame.
#[derive(Debug, Clone)]
pub struct FrameResult {
    /// What was planned.
    pub planned: PlannedFrame,
    /// The session's report.
    pub report: FrameReport,
    /// Warnings from reading the file (camera dropped, ...).
    pub read_warnings: Vec<String>,
    /// Time to read the EXR, ms.
    pub read_ms: f64,
    /// Time to write the EXR, ms.
    pub write_ms: f64,
    /// The enhanced frame (RGB premultiplied, A coverage; 4 planes), kept
    /// only when [`run_sequence`] is asked to.
    pub output: Option<Image>,
}

/// Adds `context` in front of an error's message, keeping its kind.
pub fn with_context(e: Error, context: &str) -> Error {
    let f = |m: String| format!("{context}: {m}");
    match e {
        Error::Invalid(m) => Error::Invalid(f(m)),
        Error::InvalidOperation(m) => Error::InvalidOperation(f(m)),
        Error::NotSupported(m) => Error::NotSupported(f(m)),
        Error::Io(m) => Error::Io(f(m)),
        Error::OutOfMemory(m) => Error::OutOfMemory(f(m)),
        Error::Model(m) => Error::Model(f(m)),
        Error::RuntimeMissing(m) => Error::RuntimeMissing(f(m)),
        Error::Cancelled(m) => Error::Cancelled(f(m)),
    }
}

/// Lists the frames to process and their outputs, the pre-roll frames
/// first; refuses an output that would overwrite an input.
pub fn plan(options: &RunOptions) -> Result<Vec<PlannedFrame>> {
    if options.preroll > 0 && options.frames.is_none() {
        return Err(Error::invalid(
            "--preroll needs --frames A-B: the frames before A warm the temporal state",
        ));
    }
    let input = FramePattern::parse(&options.input)?;
    let output = FramePattern::parse(&options.output)?;
    let frames = select_frames(&input, options.frames)?;
    let mut planned: Vec<PlannedFrame> = Vec::new();
    if let Some(range) = options.frames.filter(|_| options.preroll > 0) {
        let n = i64::try_from(options.preroll).unwrap_or(i64::MAX);
        let first = range.start.saturating_sub(n);
        // The pre-roll frames that exist (a chunk at the start of a
        // sequence has fewer); a missing one in between is a gap, which
        // the session's `gap_policy` handles as in any run.
        for (frame, path) in input.list()? {
            if (first..range.start).contains(&frame) {
                planned.push(PlannedFrame {
                    frame,
                    output: output.path(frame),
                    input: path,
                    preroll: true,
                });
            }
        }
    }
    planned.extend(frames.into_iter().map(|(frame, path)| PlannedFrame {
        frame,
        output: output.path(frame),
        input: path,
        preroll: false,
    }));
    for p in planned.iter().filter(|p| !p.preroll) {
        refuse_input(&p.output, &p.input, Some(p.frame))?;
    }
    Ok(planned)
}

/// Runs `session` over the planned frames. `on_frame` sees each result as it
/// is written (for progress bars and reports), pre-roll frames too (not
/// written; `planned.preroll`); an error it returns stops the run after
/// that frame (a host's cancel). With `keep_outputs` the enhanced images
/// are kept in the results.
pub fn run_sequence(
    session: &mut Session,
    options: &RunOptions,
    planned: &[PlannedFrame],
    keep_outputs: bool,
    on_frame: &mut dyn FnMut(&FrameResult) -> Result<()>,
) -> Result<Vec<FrameResult>> {
    let mut first: Option<(usize, usize, PathBuf)> = None;
    let mut results = Vec::with_capacity(planned.len());
    for p in planned {
        let here = format!("frame {} ({})", p.frame, p.input.display());
        let t = std::time::Instant::now();
        // The file's claims are checked against the device's memory limit
        // (or the machine's memory) before it is decoded.
        let limits = ReadLimits::with_memory_limit(session.device().options().memory_limit);
        let mut loaded = LoadedFrame::read_with(&p.input, Some(p.frame), &options.layout, &limits)?;
        let read_ms = t.elapsed().as_secs_f64() * 1e3;
        match &first {
            None => first = Some((loaded.width, loaded.height, p.input.clone())),
            Some((w, h, path)) if (*w, *h) != (loaded.width, loaded.height) => {
                return Err(Error::invalid(format!(
                    "{here}: size {}x{} differs from the first frame's {w}x{h} ({})",
                    loaded.width,
                    loaded.height,
                    path.display()
                )));
            }
            Some(_) => {}
        }
        let input = loaded.frame_input().map_err(|e| with_context(e, &here))?;
        let (out, report) = session
            .process(&input, None)
            .map_err(|e| with_context(e, &here))?;
        let t = std::time::Instant::now();
        let meta = OutputMeta {
            backend: report.backend.clone(),
            reset: report
                .reset
                .map(|r| r.name().to_string())
                .unwrap_or_default(),
            single_threaded: session.device().threads() <= 1,
        };
        if !p.preroll {
            loaded.write_enhanced(&out, &p.output, &meta)?;
        }
        let write_ms = t.elapsed().as_secs_f64() * 1e3;
        let result = FrameResult {
            planned: p.clone(),
            report,
            read_warnings: std::mem::take(&mut loaded.warnings),
            read_ms,
            write_ms,
            output: keep_outputs.then_some(out),
        };
        on_frame(&result)?;
        results.push(result);
    }
    Ok(results)
}

impl FrameResult {
    /// The frame's entry in a run report (`harmonize run --report`,
    /// `hz_run_sequence`): frame, pre-roll, files, backend, reset, counts,
    /// warnings (the file's, then the session's), times and stages.
    pub fn json(&self) -> Value {
        let mut warnings: Vec<String> = self.read_warnings.clone();
        warnings.extend(self.report.warnings.iter().cloned());
        let mut m = self.report.json_fields();
        let own = json!({
            "frame": self.planned.frame,
            "preroll": self.planned.preroll,
            "input": self.planned.input.display().to_string(),
            "output": self.planned.output.display().to_string(),
            "warnings": warnings,
            "read_ms": self.read_ms,
            "process_ms": self.report.total_ms,
            "write_ms": self.write_ms,
        });
        if let Value::Object(own) = own {
            m.extend(own);
        }
        Value::Object(m)
    }
}

/// The summary of a run's written frames: counts, resets, mean times.
pub fn summary_json(results: &[FrameResult]) -> Value {
    let n = results.len().max(1) as f64;
    let resets: Vec<Value> = results
        .iter()
        .filter_map(|r| {
            r.report
                .reset
                .map(|x| json!({"frame": r.planned.frame, "reason": x.name()}))
        })
        .collect();
    json!({
        "frames": results.len(),
        "resets": resets,
        "sanitized": results.iter().map(|r| r.report.sanitized).sum::<usize>(),
        "out_of_gamut": results.iter().map(|r| r.report.out_of_gamut).sum::<usize>(),
        "denoised": results.iter().filter(|r| r.report.denoised).count(),
        "warnings": results.iter().map(|r| r.report.warnings.len() + r.read_warnings.len()).sum::<usize>(),
        "mean_process_ms": results.iter().map(|r| r.report.total_ms).sum::<f64>() / n,
        "mean_read_ms": results.iter().map(|r| r.read_ms).sum::<f64>() / n,
        "mean_write_ms": results.iter().map(|r| r.write_ms).sum::<f64>() / n,
    })
}

/// The report of a run (`harmonize run --report`, `hz_run_options.report`):
/// every processed frame, pre-roll frames marked, and the summary of the
/// written ones with `preroll_frames`; `error` when the run stopped on one.
pub fn report_json(
    options: &RunOptions,
    layout: &str,
    done: &[FrameResult],
    error: Option<&Error>,
) -> Value {
    let written: Vec<FrameResult> = done
        .iter()
        .filter(|r| !r.planned.preroll)
        .cloned()
        .collect();
    let mut summary = summary_json(&written);
    summary["preroll_frames"] = json!(done.len() - written.len());
    let mut v = json!({
        "input": options.input,
        "output": options.output,
        "layout": layout,
        "version": crate::VERSION,
        "frames": done.iter().map(FrameResult::json).collect::<Vec<_>>(),
        "summary": summary,
    });
    if let Some(e) = error {
        v["error"] = json!(e.to_string());
    }
    v
}
