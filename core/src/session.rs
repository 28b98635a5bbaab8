//! The session: one camera's temporal state, run frame by frame.

use std::sync::Arc;

use crate::backend::{self, Backend, BackendInput, Carry, KeptColor, Progress, Stages};
use crate::denoise::accumulate::{accumulate, Accumulation};
use crate::denoise::stage::{Decision, Stage};
use crate::denoise::{noise_level, NOISE_THRESHOLD};
use crate::device::Device;
use crate::error::{Error, Result};
use crate::frame::{
    FrameInput, FrameShape, Image, ImageViewMut, PrepareOptions, PreparedFrame, Recycler, RgbaImage,
};
use crate::params::{BackendKind, DenoiseMode, GapPolicy, ParamValue, Params};
use crate::temporal::scene_cut::{current_samples, geometric, history_samples, score_samples};
use crate::temporal::{History, HistoryFrame, HistoryView, Lattice, LatticeRows};

/// Why the temporal state was dropped before a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ResetReason {
    /// The first frame of the session (or after `reset`).
    FirstFrame,
    /// The host set the reset flag.
    Requested,
    /// The frame size changed.
    SizeChanged,
    /// The set of AOVs given changed.
    LayoutChanged,
    /// Parameters or the model changed (commit).
    ParamsChanged,
    /// The frame number is not the previous one plus one.
    FrameGap,
    /// The scene-cut detector fired.
    SceneCut,
}

impl ResetReason {
    /// Name for reports.
    pub fn name(self) -> &'static str {
        match self {
            ResetReason::FirstFrame => "first_frame",
            ResetReason::Requested => "requested",
            ResetReason::SizeChanged => "size_changed",
            ResetReason::LayoutChanged => "layout_changed",
            ResetReason::ParamsChanged => "params_changed",
            ResetReason::FrameGap => "frame_gap",
            ResetReason::SceneCut => "scene_cut",
        }
    }
}

/// What happened to one frame.
#[derive(Debug, Clone, Default)]
pub struct FrameReport {
    /// The host's frame number.
    pub frame_index: Option<i64>,
    /// Why the state was reset before this frame, if it was.
    pub reset: Option<ResetReason>,
    /// Backend that ran.
    pub backend: String,
    /// History frames used.
    pub history_used: usize,
    /// Color samples replaced by 0 because they were NaN or infinite.
    pub sanitized: usize,
    /// Pixels whose color has negative components (outside the Rec.709
    /// gamut, from a wide-gamut host): the enhancement works on the color
    /// clipped at 0 and the negative parts pass through to the result.
    pub out_of_gamut: usize,
    /// Warnings (non-consecutive frames, huge motion vectors, NaN inputs, ...).
    pub warnings: Vec<String>,
    /// Whether the denoise stage ran on this frame (`denoise`).
    pub denoised: bool,
    /// On the frame where `denoise` was decided for the sequence (the
    /// first after a reset other than a scene cut): what was decided and
    /// why, e.g. `denoise auto: on (noise level 0.93, threshold 0.20)`.
    pub denoise_decision: Option<String>,
    /// The noise estimate ([`crate::denoise::noise_level`], stops) when
    /// `denoise auto` measured it (on the deciding frame, `samples` 0).
    pub noise_level: Option<f32>,
    /// Per-stage times in ms.
    pub stages: Stages,
    /// Total time in ms.
    pub total_ms: f64,
}

impl FrameReport {
    /// The report's fields every JSON form shares (`harmonize run`'s
    /// per-frame entries, the C ABI's report): reset, backend, history,
    /// sanitizing, denoising, the stages' times; the caller adds its own.
    pub fn json_fields(&self) -> serde_json::Map<String, serde_json::Value> {
        use serde_json::json;
        let stages: serde_json::Map<String, serde_json::Value> = self
            .stages
            .0
            .iter()
            .map(|(k, v)| (k.clone(), json!(v)))
            .collect();
        let mut m = serde_json::Map::new();
        m.insert("backend".into(), json!(self.backend));
        m.insert("reset".into(), json!(self.reset.map(|x| x.name())));
        m.insert("history_used".into(), json!(self.history_used));
        m.insert("sanitized".into(), json!(self.sanitized));
        m.insert("out_of_gamut".into(), json!(self.out_of_gamut));
        m.insert("denoised".into(), json!(self.denoised));
        m.insert("denoise_decision".into(), json!(self.denoise_decision));
        m.insert("noise_level".into(), json!(self.noise_level));
        m.insert("stages".into(), serde_json::Value::Object(stages));
        m
    }
}

/// Which optional inputs a frame had; a change resets the state.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Signature {
    width: usize,
    height: usize,
    depth: bool,
    motion: bool,
    camera: bool,
}

/// State that only changes when a frame succeeds.
#[derive(Debug, Clone, Default)]
struct State {
    history: History,
    carry: Carry,
    last: Option<Signature>,
    last_index: Option<i64>,
    pending_reset: Option<ResetReason>,
    /// `denoise` for the current sequence (`None`: decided at the next
    /// frame).
    denoise: Option<Decision>,
    /// The denoise stage's temporal accumulation, when the sequence
    /// accumulates.
    accumulated: Option<Accumulation>,
}

/// One camera's temporal enhancer. Calls on one session are serialized by `&mut`.
pub struct Session {
    device: Arc<Device>,
    params: Params,
    staged: Params,
    backend: Box<dyn Backend>,
    state: State,
    /// Frame-sized buffers reused from frame to frame (no page faults on the hot path).
    recycler: Recycler,
    /// Why `auto` did not pick the neural backend, reported with the frames
    /// until one succeeds.
    fallback: Option<String>,
    /// The denoise stage (its Open Image Denoise filters, made on the first
    /// denoised frame, and buffers). Not temporal state: a frame gives the
    /// same result through it whatever ran before.
    denoiser: Stage,
}

impl std::fmt::Debug for Session {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Session")
            .field("params", &self.params)
            .field("backend", &self.backend.name())
            .field("history", &self.state.history.len())
            .finish_non_exhaustive()
    }
}

/// The backend for `params`, and a warning when `auto` fell back to classical.
fn make_backend(device: &Device, params: &Params) -> Result<(Box<dyn Backend>, Option<String>)> {
    let backend: Box<dyn Backend> = match params.backend {
        BackendKind::Bypass => Box::new(backend::Bypass),
        BackendKind::Classical => Box::new(backend::classical::Classical),
        BackendKind::Neural => match device.neural_model()? {
            Some(model) => Box::new(backend::neural::Neural { model }),
            None => {
                return Err(Error::Model(
                    "backend neural: this build embeds no model; pass a model file or use backend classical"
                        .into(),
                ))
            }
        },
        // The embedded model needs ONNX Runtime; without it `auto` still works
        // (classical) and says why. Any other model error is an error.
        BackendKind::Auto => match device.neural_model() {
            Ok(Some(model)) => Box::new(backend::neural::Neural { model }),
            Ok(None) => Box::new(backend::classical::Classical),
            Err(Error::RuntimeMissing(why)) => {
                return Ok((
                    Box::new(backend::classical::Classical),
                    Some(format!(
                        "backend auto: running classical because the neural model cannot run: {why}"
                    )),
                ))
            }
            Err(e) => return Err(e),
        },
    };
    backend.check_params(params)?;
    Ok((backend, None))
}

impl Session {
    /// A session on `device` with `params`.
    pub fn new(device: Arc<Device>, params: Params) -> Result<Session> {
        let (backend, fallback) = make_backend(&device, &params)?;
        Ok(Session {
            device,
            staged: params.clone(),
            params,
            backend,
            state: State::default(),
            recycler: Recycler::new(),
            fallback,
            denoiser: Stage::new(),
        })
    }

    /// The committed parameters.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// The device.
    pub fn device(&self) -> &Arc<Device> {
        &self.device
    }

    /// Stages a parameter change; it takes effect at [`Session::commit`].
    pub fn set(&mut self, name: &str, value: ParamValue) -> Result<()> {
        self.staged.set(name, &value)
    }

    /// Reads a staged parameter.
    pub fn get(&self, name: &str) -> Result<ParamValue> {
        self.staged.get(name)
    }

    /// Applies staged parameters. A change of backend, context,
    /// `depth_kind`, `denoise` or `samples` resets the state (the history
    /// would mix frames denoised and not; `denoise` is decided again). Settings the backend cannot run with (tile settings that
    /// cannot tile a frame with the neural model, see
    /// [`Backend::check_params`]) are refused here, naming the parameters;
    /// on error nothing changes.
    pub fn commit(&mut self) -> Result<()> {
        if self.staged == self.params {
            return Ok(());
        }
        if self.staged.backend == self.params.backend {
            // The same backend: only the new settings need checking (a
            // rebuilt one would say again why `auto` fell back, every time
            // a host moves its light).
            self.backend.check_params(&self.staged)?;
        } else {
            let (backend, fallback) = make_backend(&self.device, &self.staged)?;
            self.backend = backend;
            self.fallback = fallback;
        }
        let reset = self.staged.backend != self.params.backend
            || self.staged.context_frames != self.params.context_frames
            || self.staged.depth_kind != self.params.depth_kind
            || self.staged.denoise != self.params.denoise
            || self.staged.samples != self.params.samples;
        self.params = self.staged.clone();
        if reset {
            self.drop_state(ResetReason::ParamsChanged);
        }
        Ok(())
    }

    /// Drops the temporal state; the next frame is a cold start.
    pub fn reset(&mut self) {
        self.drop_state(ResetReason::Requested);
    }

    fn drop_state(&mut self, why: ResetReason) {
        self.recycler = Recycler::new();
        let had = !self.state.history.is_empty() || self.state.last.is_some();
        self.state = State {
            pending_reset: had.then_some(why),
            ..State::default()
        };
    }

    /// History frames held.
    pub fn history_len(&self) -> usize {
        self.state.history.len()
    }

    /// Bytes of temporal state held.
    pub fn memory_bytes(&self) -> usize {
        self.state.history.bytes()
            + self
                .state
                .accumulated
                .as_ref()
                .map_or(0, Accumulation::bytes)
    }

    /// Name of the backend that runs.
    pub fn backend_name(&self) -> &str {
        self.backend.name()
    }

    /// Gives an image returned by [`Session::process`] back once the host is
    /// done with it, so the next frame reuses its buffer instead of
    /// allocating (and page-faulting) a new frame-sized one. Optional: an
    /// image simply dropped costs only that allocation.
    pub fn recycle(&self, image: Image) {
        self.recycler.give(image.data);
    }

    /// Estimated bytes of working memory of a frame of `shape` with the
    /// committed parameters: the prepared frame's planes, the backend's
    /// output (unless it works in place), the history's copy of the result,
    /// the history at its capacity (`context_frames` frames of RGBA, depth
    /// and motion, as kept) and the backend's own frame-sized planes
    /// ([`Backend::working_planes`]); f32 planes of `width * height`.
    /// [`Error::OutOfMemory`] when the size arithmetic overflows.
    pub fn memory_estimate(&self, shape: &FrameShape) -> Result<usize> {
        let p = &self.params;
        let b = usize::from;
        let in_place = self.backend.works_in_place() && p.strength >= 1.0;
        let color = if in_place { 4 } else { 3 + 4 };
        // The denoise stage: the albedo and its normals prepared, and its
        // own buffers (`Stage::working_planes`).
        let denoise = self.may_denoise();
        let aux = denoise && shape.albedo;
        let denoise_normal = aux && (shape.denoise_normal || shape.normal);
        // The insert color matrix: the albedo and the normals in the
        // inserts' box, at most the whole frame (and a lattice).
        let insert_albedo = p.insert_albedo(shape);
        let normals =
            shape.normal && (self.backend.uses_normals() || (aux && !shape.denoise_normal));
        let aovs = b(shape.coverage)
            + b(shape.insert_mask || shape.insert_id)
            + b(shape.insert_id)
            + b(shape.depth)
            + 2 * b(shape.motion)
            + 3 * b(normals)
            + 3 * b(aux)
            + 6 * b(insert_albedo)
            + 3 * b(aux && shape.denoise_normal)
            + if denoise {
                Stage::working_planes(aux, denoise_normal)
            } else {
                0
            }
            // The temporal accumulation (kept and working planes) and, with
            // `strength` below 1, the input's color kept for the blend.
            + if denoise || p.denoise == DenoiseMode::Temporal {
                Accumulation::planes(shape.depth, shape.coverage) + 3 * b(p.strength < 1.0)
            } else {
                0
            };
        let k = p.context_frames;
        let history = match k {
            0 => 0,
            k => 4 + k * (4 + b(shape.depth) + 2 * b(shape.motion)),
        };
        let planes = color + aovs + history + self.backend.working_planes(p);
        let (w, h) = (shape.width, shape.height);
        w.checked_mul(h)
            .and_then(|n| n.checked_mul(planes))
            .and_then(|n| n.checked_mul(std::mem::size_of::<f32>()))
            .ok_or_else(|| {
                Error::OutOfMemory(format!(
                    "frame {w}x{h}: its working set ({planes} planes of {w}x{h} f32 samples) \
                     is larger than the address space"
                ))
            })
    }

    /// Whether the denoise stage may run on the next frame: `denoise on`,
    /// or `auto` unless the parameters or the sequence's decision say off.
    fn may_denoise(&self) -> bool {
        match self.params.denoise {
            DenoiseMode::Off | DenoiseMode::Temporal => false,
            DenoiseMode::On => true,
            DenoiseMode::Auto => match self.decide_from_params() {
                Some((d, _)) => d.on,
                None => self.state.denoise.is_none_or(|d| d.on),
            },
        }
    }

    /// The `denoise` decision the parameters make alone, and why; `None`
    /// when `auto` has to look at the frame (`samples` 0).
    fn decide_from_params(&self) -> Option<(Decision, String)> {
        let p = &self.params;
        let (d, why) = match p.denoise {
            DenoiseMode::Off => (Decision::OFF, "denoise off".to_string()),
            DenoiseMode::On => (Decision::ON, "denoise on".to_string()),
            DenoiseMode::Temporal => (
                Decision::TEMPORAL,
                "denoise temporal: the frames are accumulated over time, not denoised again"
                    .to_string(),
            ),
            DenoiseMode::Auto if p.backend == BackendKind::Bypass => (
                Decision::OFF,
                "denoise auto: off (backend bypass passes the input through; set denoise on to denoise)"
                    .to_string(),
            ),
            DenoiseMode::Auto => match p.samples {
                0 => return None,
                n @ 1..=64 => (Decision::ON, format!("denoise auto: on (the host renders {n} samples per pixel, 1 to 64)")),
                n => (Decision::OFF, format!("denoise auto: off (the host renders {n} samples per pixel, over 64)")),
            },
        };
        Some((d, why))
    }

    /// Checks a frame of `shape` against the device's memory limit
    /// ([`Device::memory_budget`]: `memory_limit`, else the machine's
    /// memory) before anything is allocated or read: the frame's
    /// [`Session::memory_estimate`] must fit it, else
    /// [`Error::OutOfMemory`] naming the size, the estimate and the limit.
    /// Returns the bytes left to the backend (`usize::MAX`: no limit known).
    /// [`Session::process`] calls it first; a host may call it before it
    /// builds the frame's views (the C ABI does).
    pub fn check_memory(&self, shape: &FrameShape) -> Result<usize> {
        let need = self.memory_estimate(shape)?;
        let (limit, what) = self.device.memory_budget();
        if need > limit {
            let gib = |n: usize| n as f64 / (1u64 << 30) as f64;
            return Err(Error::OutOfMemory(format!(
                "frame {}x{}: its working set needs about {need} bytes ({:.2} GiB), \
                 more than the {what} of {limit} bytes ({:.2} GiB)",
                shape.width,
                shape.height,
                gib(need),
                gib(limit)
            )));
        }
        Ok(match limit {
            usize::MAX => usize::MAX,
            _ => limit - need,
        })
    }

    /// Enhances one frame. On error (including cancellation and a frame
    /// too large for the memory limit, see [`Session::check_memory`]) the
    /// temporal state is exactly as before the call. Returns the enhanced
    /// frame as 4 planes (RGB premultiplied by A, A coverage after hole
    /// filling).
    pub fn process(
        &mut self,
        input: &FrameInput<'_>,
        progress: Option<&mut dyn FnMut(f64) -> bool>,
    ) -> Result<(Image, FrameReport)> {
        let t0 = std::time::Instant::now();
        let budget = self.check_memory(&FrameShape::of(input))?;
        let mut progress = Progress::new(progress);
        let (out, mut report) = match self.process_once(input, budget, &mut progress, false)? {
            Attempt::Done(out, report) => (out, *report),
            Attempt::Cut => {
                // The backend ran with the history before the detector,
                // which found a cut: the frame again, from a reset. Its
                // first run counts as the detector's time.
                let ms = t0.elapsed().as_secs_f64() * 1e3;
                match self.process_once(input, budget, &mut progress, true)? {
                    Attempt::Done(out, report) => {
                        let mut report = *report;
                        report.stages.0.insert(0, ("scene_cut".to_string(), ms));
                        (out, report)
                    }
                    Attempt::Cut => {
                        unreachable!("a frame run from a reset has no history to cut from")
                    }
                }
            }
        };
        report.total_ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok((out, report))
    }

    /// One run of [`Session::process`]: the frame with the history, or
    /// reset as at a scene cut when `cut` (the run after one that found
    /// the cut: [`Attempt::Cut`], the state untouched); `budget` is the
    /// backend's memory ([`BackendInput::memory_budget`]).
    fn process_once(
        &mut self,
        input: &FrameInput<'_>,
        budget: usize,
        progress: &mut Progress<'_>,
        cut: bool,
    ) -> Result<Attempt> {
        let mut stages = Stages::default();
        let mut report = FrameReport {
            frame_index: input.frame_index,
            ..FrameReport::default()
        };
        progress.report(0.0)?;

        let pool = self.device.pool();
        // The reset decision, from what the frame has (before its samples
        // are read: the denoise stage needs it to know whether `denoise` is
        // decided again).
        let sig = Signature {
            width: input.width(),
            height: input.height(),
            depth: input.depth.is_some(),
            motion: input.motion.is_some(),
            camera: input.camera.is_some(),
        };
        let (mut reset, gap_warning) = self.reset_reason(input, &sig, cut);
        // `denoise` for this frame: the sequence's decision, else what the
        // parameters say, else `auto` looks at the frame once it is
        // prepared. A scene cut keeps the decision (same render settings;
        // the frame was denoised before the detector compared it).
        let kept_decision = match reset {
            Some(r) if r != ResetReason::SceneCut => None,
            _ => self.state.denoise,
        };
        let from_params = match kept_decision {
            Some(_) => None,
            None => self.decide_from_params(),
        };
        let may_denoise = kept_decision
            .or(from_params.as_ref().map(|d| d.0))
            .is_none_or(|d| d.on);

        // The backend may work on the frame's color itself when nothing
        // after it reads that color (`apply_strength` does).
        let in_place = self.backend.works_in_place() && self.params.strength >= 1.0;
        let aux = may_denoise && input.albedo.is_some();
        // The insert color matrix reads the albedo and the normals where
        // it fits.
        let insert_albedo = self.params.insert_albedo(&FrameShape::of(input));
        let options = PrepareOptions {
            normals: self.backend.uses_normals() || (aux && input.denoise_normal.is_none()),
            rgba: in_place,
            denoise_aux: aux,
            albedo: insert_albedo,
        };
        let mut frame = stages.time("prepare", || {
            PreparedFrame::from_input_with(
                input,
                self.params.depth_kind,
                pool,
                &self.recycler,
                options,
            )
        })?;
        if frame.sanitized > 0 {
            report.sanitized = frame.sanitized;
            report.warnings.push(format!(
                "frame {}: {} color samples were NaN or infinite and were replaced by 0",
                fmt_index(input.frame_index),
                frame.sanitized
            ));
        }
        for (count, what) in [
            (
                frame.sanitized_aovs,
                "AOV samples were NaN and were replaced",
            ),
            (
                frame.sanitized_normals,
                "normal samples were NaN or infinite and were replaced by 0",
            ),
            (
                frame.sanitized_albedo,
                "albedo samples were NaN or infinite and were replaced by 0",
            ),
        ] {
            if count > 0 {
                report.warnings.push(format!(
                    "frame {}: {count} {what}",
                    fmt_index(input.frame_index)
                ));
            }
        }
        if frame.huge_motion > 0 {
            report.warnings.push(format!(
                "frame {}: {} motion vectors are longer than the image ({}x{}); check motion_vector_scale and the motion AOV",
                fmt_index(input.frame_index),
                frame.huge_motion,
                frame.width(),
                frame.height()
            ));
        }

        // The denoise stage, before the scene-cut detector and the backend,
        // so both (and the history) see the denoised color.
        let decision = match self.denoise_decision(
            kept_decision,
            from_params,
            &frame,
            &mut report,
            &mut stages,
        ) {
            Ok(d) => d,
            Err(e) => {
                frame.recycle(&self.recycler);
                return Err(e);
            }
        };
        // `strength` blends with the host's input, not the denoised frame
        // (so `strength 0` returns the input exactly, denoising or not):
        // keep its color when the stage changes it.
        let mut original = None;
        if (decision.on || decision.temporal) && self.params.strength < 1.0 {
            let n = frame.width() * frame.height();
            match self.recycler.try_take(3 * n) {
                Ok(mut data) => {
                    data.copy_from_slice(&frame.color.data[..3 * n]);
                    original = Some(data);
                }
                Err(e) => {
                    frame.recycle(&self.recycler);
                    return Err(e);
                }
            }
        }
        // With a device `memory_limit`, Open Image Denoise gets half of what
        // the frame's counted planes leave (its filters keep their working
        // memory while the backend runs), the backend the other half.
        let limited = self.device.options().memory_limit > 0;
        let oidn_memory = (decision.on && limited).then_some(budget / 2);
        let budget = budget - oidn_memory.unwrap_or(0);
        if decision.on {
            let quality = self.params.denoise_quality;
            let prefilter = self.params.denoise_prefilter;
            let ran = self.device.oidn().and_then(|oidn| {
                stages.time("denoise", || {
                    self.denoiser
                        .run(&oidn, &mut frame, quality, prefilter, oidn_memory, pool)
                })
            });
            // The stage takes long (OIDN has no cancellation point of
            // ours inside): the host may stop right after it.
            if let Err(e) = ran.and_then(|_| progress.report(0.05)) {
                frame.recycle(&self.recycler);
                return Err(e);
            }
            report.denoised = true;
        }
        let denoise_state = Some(decision);

        // The history's copy of the result, written by the backend's last
        // pass when it can (nothing after the backend changes the result
        // unless `strength` is below 1, see `apply_strength`).
        let capacity = self.params.context_frames;
        let kept = match (capacity > 0)
            .then(|| self.recycler.try_take(4 * frame.width() * frame.height()))
            .transpose()
        {
            Ok(data) => data.map(|data| {
                KeptColor::new(RgbaImage {
                    width: frame.width(),
                    height: frame.height(),
                    data,
                })
            }),
            Err(e) => {
                frame.recycle(&self.recycler);
                return Err(e);
            }
        };
        if let Some(w) = gap_warning {
            report.warnings.push(w);
        }
        // The backend's parameters: with the denoise stage accumulating,
        // the backend does not stabilize again (the accumulation is these
        // frames' stabilization; a second blend over it only lags and
        // smears: 32.7 dB against 34.3 on the out-of-domain 4-spp
        // sequence, `scripts/quality.sh`).
        let stabilized_params;
        let params = if decision.temporal && self.params.stabilize {
            stabilized_params = Params {
                stabilize: false,
                ..self.params.clone()
            };
            &stabilized_params
        } else {
            &self.params
        };
        let st = &self.state;
        let empty = History::default();
        let context = self.params.context_frames;
        // The scene-cut detector compares the frame with history frame 0
        // at a sparse lattice. When the backend reprojects that frame row by
        // row anyway, it records the lattice's rows and the cut is scored
        // after it (`deferred`); else the detector reprojects them first.
        let lattice = Lattice::new(frame.width(), frame.height());
        let probe = LatticeRows::new(&lattice);
        let mut deferred = false;
        if reset.is_none() && self.params.scene_cut_detection {
            let view =
                HistoryView::new_recycled(&st.history, &frame, context, pool, &self.recycler);
            // Not after a denoised frame: a cut found late runs the frame
            // again, and with it the denoiser, which costs far more than
            // reprojecting the lattice's rows up front.
            deferred = !view.is_empty()
                && !decision.on
                && self.backend.records_scene_probe(params)
                && frame.scene_samples.is_some();
            let cut = !view.is_empty()
                && !deferred
                && stages.time("scene_cut", || {
                    crate::temporal::is_scene_cut(&view, &frame, self.params.scene_cut_threshold)
                });
            if cut {
                reset = Some(ResetReason::SceneCut);
            }
        }
        // The denoise stage's temporal accumulation, now that the frame is
        // known to continue the sequence (or not).
        let mut accumulation = None;
        if decision.temporal {
            let prev = match reset {
                None => self.state.accumulated.as_ref(),
                Some(_) => None,
            };
            let rec = &self.recycler;
            match stages.time("accumulate", || accumulate(prev, &mut frame, pool, rec)) {
                Ok(a) => accumulation = Some(a),
                Err(e) => {
                    frame.recycle(&self.recycler);
                    return Err(e);
                }
            }
            report.denoised = true;
        }
        let rgba = in_place.then(|| frame.take_color());
        let history = if reset.is_some() { &empty } else { &st.history };
        let view = HistoryView::new_recycled(history, &frame, context, pool, &self.recycler);
        report.reset = reset;
        report.history_used = view.len();
        if reset == Some(ResetReason::SizeChanged) {
            self.recycler
                .keep_frame_size(frame.width() * frame.height());
        }

        let mut carry = if reset.is_some() {
            Carry::default()
        } else {
            st.carry.clone()
        };
        let backend_input = BackendInput {
            frame: &frame,
            history: &view,
            params,
            pool,
            kept: kept.as_ref().filter(|_| self.params.strength >= 1.0),
            scene_probe: deferred.then_some(&probe),
            memory_budget: budget,
        };
        progress.set_span(0.05, 0.95);
        let out = match rgba {
            Some(rgba) => self.backend.process_in_place(
                rgba,
                &backend_input,
                &mut carry,
                progress,
                &mut stages,
            ),
            None => self
                .backend
                .process(&backend_input, &mut carry, progress, &mut stages),
        };
        let (kept, kept_filled) = kept.map_or((None, false), KeptColor::into_inner);
        // Scored from the rows the backend recorded (or, had it recorded
        // none, reprojected now) and the samples kept while preparing.
        let found_cut = |stages: &mut Stages| -> bool {
            deferred
                && stages.time("scene_cut", || {
                    let hist = probe
                        .finish()
                        .unwrap_or_else(|| history_samples(&lattice, &view));
                    let cur = current_samples(&lattice, &frame);
                    score_samples(&lattice, &cur, &hist, geometric(&view))
                        .is_cut(self.params.scene_cut_threshold)
                })
        };
        let mut out = match out {
            Ok(out) if found_cut(&mut stages) => {
                drop(view);
                self.give_back(frame, kept, Some(out));
                return Ok(Attempt::Cut);
            }
            Ok(out) => out,
            Err(e) => {
                drop(view);
                self.give_back(frame, kept, None);
                return Err(e);
            }
        };
        progress.set_span(0.0, 1.0);
        if self.params.strength < 1.0 {
            let input = original.as_deref().unwrap_or(&frame.color.data);
            stages.time("strength", || {
                apply_strength(&mut out, input, &frame, self.params.strength)
            });
        }
        if let Some(data) = original {
            self.recycler.give(data);
        }
        let done = progress.report(1.0);
        drop(view);
        if let Err(e) = done {
            self.give_back(frame, kept, Some(out));
            return Err(e);
        }

        // Commit: only now does the temporal state change.
        let t_commit = std::time::Instant::now();
        let mut history = if reset.is_some() {
            History::default()
        } else {
            std::mem::take(&mut self.state.history)
        };
        let PreparedFrame {
            color,
            coverage,
            depth,
            motion,
            normal,
            insert_mask,
            insert_id,
            camera,
            frame_index,
            scan,
            out_of_gamut,
            ..
        } = frame;
        let width = color.width;
        let rec = &self.recycler;
        rec.give(color.data);
        if let Some(mask) = insert_mask {
            crate::frame::recycle_mask(rec, mask, width, scan);
        }
        for b in [coverage, insert_id].into_iter().flatten() {
            rec.give(b);
        }
        if let Some(n) = normal {
            rec.give(n.data);
        }
        if capacity > 0 {
            // Kept interleaved (see `HistoryFrame::color`), written by the
            // backend's last pass or copied here.
            let kept = match kept {
                Some(k) if kept_filled => k,
                k => {
                    let mut k = k.unwrap_or_else(|| RgbaImage {
                        width: out.width,
                        height: out.height,
                        data: rec.take(4 * out.len()),
                    });
                    k.set_planes(&out, Some(pool));
                    k
                }
            };
            let evicted = history.push(
                HistoryFrame {
                    color: kept,
                    depth,
                    motion,
                    camera,
                    frame_index,
                },
                capacity,
            );
            for f in evicted {
                f.recycle(rec);
            }
        } else {
            for b in [depth, motion.map(|m| m.data)].into_iter().flatten() {
                rec.give(b);
            }
        }
        if let Some(old) = std::mem::replace(&mut self.state.accumulated, accumulation) {
            old.recycle(rec);
        }
        self.state = State {
            history,
            carry,
            last: Some(sig),
            last_index: input.frame_index,
            pending_reset: None,
            denoise: denoise_state,
            accumulated: self.state.accumulated.take(),
        };
        // The history copy of the result and the buffers handed back.
        let commit_ms = t_commit.elapsed().as_secs_f64() * 1e3;
        stages.0.push(("commit".to_string(), commit_ms));
        report.backend = self.backend.name().to_string();
        if let Some(why) = self.fallback.take() {
            report.warnings.push(why);
        }
        report.stages = stages;
        // The negative parts of out-of-gamut colors, added back after the
        // history took its copy (the history stays what the backends
        // produce, never negative).
        report.out_of_gamut = out_of_gamut.len();
        add_out_of_gamut(&mut out, &out_of_gamut);
        Ok(Attempt::Done(out, Box::new(report)))
    }

    /// Why the state is dropped before `input` (whose optional inputs
    /// are `sig`), before any scene-cut test (`cut`: the run after a cut
    /// found late), and the warning a frame-number gap gives.
    fn reset_reason(
        &self,
        input: &FrameInput<'_>,
        sig: &Signature,
        cut: bool,
    ) -> (Option<ResetReason>, Option<String>) {
        let st = &self.state;
        let mut reset = st.pending_reset;
        let mut warning = None;
        if input.reset {
            reset = Some(ResetReason::Requested);
        } else if let Some(last) = st.last {
            if last.width != sig.width || last.height != sig.height {
                reset = Some(ResetReason::SizeChanged);
            } else if last != *sig {
                reset = Some(ResetReason::LayoutChanged);
            } else if let (Some(prev), Some(cur)) = (st.last_index, input.frame_index) {
                // Checked: i64::MAX then i64::MIN is a gap, not a wrap.
                if prev.checked_add(1) != Some(cur) {
                    warning = Some(match self.params.gap_policy {
                        GapPolicy::Reset => {
                            reset = Some(ResetReason::FrameGap);
                            format!(
                                "frame {cur}: not consecutive to frame {prev}; temporal state reset (gap_policy reset)"
                            )
                        }
                        GapPolicy::Keep => format!(
                            "frame {cur}: not consecutive to frame {prev}; temporal state kept (gap_policy keep)"
                        ),
                    });
                }
            }
        } else if reset.is_none() {
            reset = Some(ResetReason::FirstFrame);
        }
        if cut && reset.is_none() {
            reset = Some(ResetReason::SceneCut);
        }
        (reset, warning)
    }

    /// `denoise` for the prepared `frame`: the sequence's decision
    /// (`kept`), else the one the parameters make (`from_params`), else
    /// (`auto`, `samples` 0) on when the frame's noise level is above
    /// [`NOISE_THRESHOLD`]. A new decision goes into the report. Turned on,
    /// Open Image Denoise is loaded here: when it cannot be, `denoise on`
    /// is an error naming the library and what to install, and `auto`
    /// decides off for the sequence with a warning saying why.
    fn denoise_decision(
        &self,
        kept: Option<Decision>,
        from_params: Option<(Decision, String)>,
        frame: &PreparedFrame,
        report: &mut FrameReport,
        stages: &mut Stages,
    ) -> Result<Decision> {
        if let Some(d) = kept {
            return Ok(d);
        }
        let (decision, why) = match from_params {
            Some(d) => d,
            None => {
                let level = stages.time("noise_estimate", || {
                    noise_level(
                        &frame.color,
                        frame.coverage.as_deref(),
                        Some(self.device.pool()),
                    )
                });
                report.noise_level = level;
                let on = level.is_some_and(|l| l > NOISE_THRESHOLD);
                let why = match level {
                    Some(l) => format!(
                        "denoise auto: {} (noise level {l:.3} on frame {}, threshold {NOISE_THRESHOLD:.2})",
                        if on { "on" } else { "off" },
                        fmt_index(frame.frame_index)
                    ),
                    None => format!(
                        "denoise auto: off (frame {} has too few covered pixels to measure its noise)",
                        fmt_index(frame.frame_index)
                    ),
                };
                (if on { Decision::ON } else { Decision::OFF }, why)
            }
        };
        if decision.on {
            if let Err(e) = self.device.oidn() {
                if self.params.denoise == DenoiseMode::On {
                    return Err(match e {
                        Error::RuntimeMissing(m) => Error::RuntimeMissing(format!(
                            "denoise on needs Open Image Denoise: {m}"
                        )),
                        e => e,
                    });
                }
                let why = format!(
                    "{why}, but Open Image Denoise cannot be used, so the frames of this sequence are not \
                     denoised: {e}"
                );
                report.warnings.push(why.clone());
                report.denoise_decision = Some(why);
                return Ok(Decision::OFF);
            }
        }
        report.denoise_decision = Some(why);
        Ok(decision)
    }

    /// Gives the buffers of a run that commits nothing (an error, a cancel,
    /// a cut found late) back to the recycler.
    fn give_back(&self, frame: PreparedFrame, kept: Option<RgbaImage>, out: Option<Image>) {
        frame.recycle(&self.recycler);
        for b in [kept.map(|k| k.data), out.map(|o| o.data)]
            .into_iter()
            .flatten()
        {
            self.recycler.give(b);
        }
    }

    /// Like [`Session::process`], then writes the result into `output`
    /// (3 channels: RGB; 4: RGBA).
    pub fn process_into(
        &mut self,
        input: &FrameInput<'_>,
        output: &mut ImageViewMut<'_>,
        progress: Option<&mut dyn FnMut(f64) -> bool>,
    ) -> Result<FrameReport> {
        check_output(input, output)?;
        let (img, report) = self.process(input, progress)?;
        write_output(&img, output);
        Ok(report)
    }
}

/// How one run of [`Session::process`] ended.
enum Attempt {
    /// The enhanced frame and its report; the state committed.
    Done(Image, Box<FrameReport>),
    /// A scene cut found after the backend ran with the history; nothing
    /// committed, the frame's buffers given back.
    Cut,
}

fn fmt_index(i: Option<i64>) -> String {
    i.map_or_else(|| "?".to_string(), |i| i.to_string())
}

/// Checks that `output` can take the result of `input`.
pub fn check_output(input: &FrameInput<'_>, output: &ImageViewMut<'_>) -> Result<()> {
    if output.width() != input.width() || output.height() != input.height() {
        return Err(Error::invalid(format!(
            "output: size {}x{} differs from color {}x{}",
            output.width(),
            output.height(),
            input.width(),
            input.height()
        )));
    }
    if output.channels() < 3 {
        return Err(Error::invalid(format!(
            "output: needs 3 (RGB) or 4 (RGBA) channels, got {}",
            output.channels()
        )));
    }
    Ok(())
}

/// Writes a 4-plane result into a host image (RGB, plus A if it has 4 channels).
pub fn write_output(img: &Image, output: &mut ImageViewMut<'_>) {
    let ch = output.channels().min(4);
    let w = img.width;
    for c in 0..ch {
        let plane = img.plane(c);
        for y in 0..img.height {
            output.write_row(y, c, &plane[y * w..(y + 1) * w]);
        }
    }
}

/// Adds the negative color parts split off while preparing (see
/// `PreparedFrame::out_of_gamut`) to the result.
fn add_out_of_gamut(out: &mut Image, parts: &[(usize, [f32; 3])]) {
    let n = out.len();
    for &(i, neg) in parts {
        for (c, v) in neg.into_iter().enumerate() {
            out.data[c * n + i] += v;
        }
    }
}

/// Blends the backend's result `out` with the input: `input` holds the
/// input's RGB planes (the frame's own color, or its copy from before the
/// denoise stage), `frame` its coverage.
fn apply_strength(out: &mut Image, input: &[f32], frame: &PreparedFrame, s: f32) {
    let n = out.len();
    for c in 0..3 {
        let src = &input[c * n..(c + 1) * n];
        for (o, i) in out.data[c * n..(c + 1) * n].iter_mut().zip(src) {
            *o = i + s * (*o - i);
        }
    }
    let a = &mut out.data[3 * n..];
    match &frame.coverage {
        Some(cov) => a
            .iter_mut()
            .zip(cov)
            .for_each(|(o, i)| *o = i + s * (*o - i)),
        None => a.iter_mut().for_each(|o| *o = 1.0 + s * (*o - 1.0)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::device::DeviceOptions;
    use crate::synth::{Scene, SynthConfig};

    /// A synthetic sequence of `frames` frames and a device of 2 threads.
    fn scene_and_device(width: usize, height: usize, frames: usize) -> (Scene, Arc<Device>) {
        let scene = Scene::new(SynthConfig {
            width,
            height,
            frames,
            ..SynthConfig::default()
        })
        .unwrap();
        let device = Device::new(DeviceOptions {
            threads: 2,
            ..DeviceOptions::default()
        })
        .unwrap();
        (scene, device)
    }

    /// The samples of `a` and `b`, pairwise, have the same bits.
    fn same_bits(a: &[f32], b: &[f32]) -> bool {
        a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits())
    }

    /// The classical backend without its in-place path: the frame's color
    /// is copied into a working image (`Backend::process`).
    struct Copying(crate::backend::classical::Classical);

    impl Backend for Copying {
        fn name(&self) -> &str {
            "classical"
        }

        fn process(
            &self,
            input: &BackendInput<'_>,
            carry: &mut Carry,
            progress: &mut Progress<'_>,
            stages: &mut Stages,
        ) -> Result<Image> {
            self.0.process(input, carry, progress, stages)
        }
    }

    /// Working in place on the prepared color (its coverage kept only as
    /// the alpha, holes and insert found while preparing) gives the bits of
    /// working on a copy, frame after frame: holes (some punched, partly
    /// covered, into the background around the insert, where the
    /// harmonization measures), an insert, motion.
    #[test]
    fn in_place_and_copying_paths_give_the_same_bits() {
        let (scene, device) = scene_and_device(160, 96, 6);
        let mut params = Params::default();
        params
            .set("backend", &ParamValue::Str("classical".into()))
            .unwrap();
        let mut in_place = Session::new(device.clone(), params.clone()).unwrap();
        let mut copying = Session::new(device, params).unwrap();
        copying.backend = Box::new(Copying(crate::backend::classical::Classical));
        assert!(in_place.backend.works_in_place() && !copying.backend.works_in_place());
        for t in 0..6 {
            let mut f = scene.frame(1 + t).input;
            let w = f.width;
            let insert = crate::ops::bbox_above(&f.insert_mask, w, f.height, 0.0)
                .expect("an insert")
                .0;
            // Partly covered pixels beside the insert and in every third
            // row of it (the harmonization weighs both by coverage).
            let beside =
                (insert.x0.saturating_sub(12)..insert.x0).chain(insert.x1..(insert.x1 + 12).min(w));
            for y in insert.y0..insert.y1 {
                let across = if y % 3 == 0 {
                    insert.x0..insert.x1
                } else {
                    0..0
                };
                for x in beside.clone().chain(across) {
                    let p = y * w + x;
                    f.coverage[p] = 0.25;
                    for c in 0..4 {
                        f.color[4 * p + c] *= 0.25;
                    }
                }
            }
            let (a, ra) = in_place.process(&f.frame_input(), None).unwrap();
            let (b, rb) = copying.process(&f.frame_input(), None).unwrap();
            assert_eq!((ra.reset, ra.history_used), (rb.reset, rb.history_used));
            assert!(same_bits(&a.data, &b.data), "frame {t}");
            assert_eq!(
                in_place.state.carry.values, copying.state.carry.values,
                "frame {t}: the smoothed harmonization"
            );
        }
    }

    /// The history keeps exactly the result handed to the host, whether the
    /// backend's last pass wrote the history's copy (classical, stabilize
    /// on) or the session copied it (stabilize off, strength below 1,
    /// bypass).
    #[test]
    fn the_history_holds_the_result_however_it_is_copied() {
        let (scene, device) = scene_and_device(67, 45, 4);
        let cases: [(&str, &[(&str, ParamValue)]); 4] = [
            ("classical", &[]),
            ("classical", &[("stabilize", ParamValue::Bool(false))]),
            ("classical", &[("strength", ParamValue::Float(0.5))]),
            ("bypass", &[]),
        ];
        for (backend, extra) in cases {
            let mut params = Params::default();
            params
                .set("backend", &ParamValue::Str(backend.into()))
                .unwrap();
            for (k, v) in extra {
                params.set(k, v).unwrap();
            }
            let mut session = Session::new(device.clone(), params).unwrap();
            for t in 0..4 {
                let f = scene.frame(1 + t);
                let (out, _) = session.process(&f.input.frame_input(), None).unwrap();
                let kept = &session.state.history.get(0).unwrap().color;
                let want = RgbaImage::from_planes(&out, None);
                assert!(
                    same_bits(&kept.data, &want.data),
                    "{backend} {extra:?}: frame {t}"
                );
                session.recycle(out);
            }
        }
    }
}
