//! Backends behind one trait: `neural` (the ONNX model), `classical` (hole
//! filling, harmonization, contact shadows, stabilization) and `bypass`.

pub mod classical;
pub mod neural;

use std::collections::BTreeMap;
use std::sync::Mutex;

use crate::error::{Error, Result};
use crate::frame::{Image, PreparedFrame, RgbaImage};
use crate::params::Params;
use crate::temporal::{HistoryView, LatticeRows};

/// Small per-session state a backend carries from frame to frame (for
/// example smoothed harmonization parameters). The session hands the backend a
/// copy and keeps it only when the frame succeeds, so a failed or cancelled
/// frame leaves the state as it was.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Carry {
    /// Named values.
    pub values: BTreeMap<String, Vec<f32>>,
}

/// Progress reporting with cancellation: monotonic values in `[0,1]`.
pub struct Progress<'a> {
    callback: Option<&'a mut dyn FnMut(f64) -> bool>,
    last: f64,
    /// Range of the overall progress this stage maps `[0,1]` into.
    span: (f64, f64),
}

impl<'a> Progress<'a> {
    /// Wraps an optional host callback.
    pub fn new(callback: Option<&'a mut dyn FnMut(f64) -> bool>) -> Self {
        Progress {
            callback,
            last: 0.0,
            span: (0.0, 1.0),
        }
    }

    /// Maps later `report` values in `[0,1]` into `[lo,hi]` of the overall progress.
    pub fn set_span(&mut self, lo: f64, hi: f64) {
        self.span = (lo, hi);
    }

    /// The current span (see [`Progress::set_span`]).
    pub fn span(&self) -> (f64, f64) {
        self.span
    }

    /// Reports progress (in the current span); `Err(Cancelled)` when the host asks to stop.
    pub fn report(&mut self, p: f64) -> Result<()> {
        let v = (self.span.0 + (self.span.1 - self.span.0) * p.clamp(0.0, 1.0)).max(self.last);
        self.last = v;
        if let Some(cb) = self.callback.as_mut() {
            if !cb(v) {
                return Err(Error::Cancelled(format!(
                    "the progress callback returned false at {v:.3}"
                )));
            }
        }
        Ok(())
    }
}

/// Per-stage wall times of one frame, in milliseconds, in call order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Stages(pub Vec<(String, f64)>);

impl Stages {
    /// Runs `f` and records its time under `name` (added to an existing entry).
    pub fn time<T>(&mut self, name: &str, f: impl FnOnce() -> T) -> T {
        let t = std::time::Instant::now();
        let r = f();
        let ms = t.elapsed().as_secs_f64() * 1e3;
        if let Some(e) = self.0.iter_mut().find(|(n, _)| n == name) {
            e.1 += ms;
        } else {
            self.0.push((name.to_string(), ms));
        }
        r
    }
}

/// The buffer of the history's interleaved copy of the result, handed to
/// the backend so that its last pass over the image can write it while the
/// rows are in cache (the session copies the result itself otherwise).
#[derive(Debug)]
pub struct KeptColor {
    slot: Mutex<(Option<RgbaImage>, bool)>,
}

impl KeptColor {
    /// Wraps `buffer` (contents arbitrary), not filled yet.
    pub fn new(buffer: RgbaImage) -> KeptColor {
        KeptColor {
            slot: Mutex::new((Some(buffer), false)),
        }
    }

    /// Takes the buffer to write it (`None` when already taken); give it
    /// back with [`KeptColor::give`].
    pub fn take(&self) -> Option<RgbaImage> {
        let mut s = self.slot.lock().unwrap_or_else(|e| e.into_inner());
        s.1 = false;
        s.0.take()
    }

    /// Gives the buffer back; `filled` when it holds the result exactly,
    /// interleaved (what [`RgbaImage::set_planes`] of the backend's output
    /// would write): the backend must not change its output after that.
    pub fn give(&self, buffer: RgbaImage, filled: bool) {
        let mut s = self.slot.lock().unwrap_or_else(|e| e.into_inner());
        *s = (Some(buffer), filled);
    }

    /// Changes the buffer by `f` where it holds the result (a backend that
    /// changes its output after the buffer was filled makes the same change
    /// here, so it still holds the result); nothing otherwise.
    pub fn patch(&self, f: impl FnOnce(&mut RgbaImage)) {
        let mut s = self.slot.lock().unwrap_or_else(|e| e.into_inner());
        if let (Some(buffer), true) = &mut *s {
            f(buffer);
        }
    }

    /// The buffer and whether it holds the result.
    pub fn into_inner(self) -> (Option<RgbaImage>, bool) {
        self.slot.into_inner().unwrap_or_else(|e| e.into_inner())
    }
}

/// Everything a backend sees for one frame.
pub struct BackendInput<'a> {
    /// The current frame in planar form.
    pub frame: &'a PreparedFrame,
    /// The enhanced history, reprojected into the current view on demand.
    pub history: &'a HistoryView<'a>,
    /// The session's committed parameters.
    pub params: &'a Params,
    /// The device's thread pool; run parallel work inside `pool.install`.
    pub pool: &'a rayon::ThreadPool,
    /// Where the history's copy of the result may be written by the last
    /// pass over the image (`None`: the session copies it).
    pub kept: Option<&'a KeptColor>,
    /// Where a pass that reprojects history frame 0 row by row over the
    /// whole frame records the rows at the scene-cut detector's lattice
    /// (the session then scores the cut from them after the backend, see
    /// [`Backend::records_scene_probe`]); `None`: nothing to record.
    pub scene_probe: Option<&'a LatticeRows<'a>>,
    /// Bytes of working memory left to the backend beyond the frame-sized
    /// buffers the session counted (`Session::memory_estimate`) under the
    /// device's limit; `usize::MAX`: no limit. The neural backend shrinks
    /// its tiles to fit it.
    pub memory_budget: usize,
}

/// A backend turns one prepared frame plus history into the enhanced frame.
pub trait Backend: Send + Sync {
    /// Name for reports ("neural", "classical", "bypass").
    fn name(&self) -> &str;

    /// Whether the backend reads the normal AOV; when not, the session does
    /// not prepare it (a frame-sized read and conversion saved).
    fn uses_normals(&self) -> bool {
        true
    }

    /// Checks at commit that `params` can run on this backend (for the
    /// neural backend: that the tile settings can tile any frame with its
    /// model); an error names the parameters.
    fn check_params(&self, params: &Params) -> Result<()> {
        let _ = params;
        Ok(())
    }

    /// Frame-sized f32 planes of working memory the backend allocates
    /// besides its output, for the session's memory estimate.
    fn working_planes(&self, params: &Params) -> usize {
        let _ = params;
        0
    }

    /// Whether, with `params` and some history, the backend reprojects
    /// history frame 0 over the whole frame and records the scene-cut
    /// detector's rows in [`BackendInput::scene_probe`] as it goes. The
    /// session then runs the backend before it knows whether the frame is
    /// a scene cut, and runs the frame again from a reset when it is (cuts
    /// are rare; the detector's own reprojection is saved on every other
    /// frame). A backend that says so but records nothing costs only the
    /// detector's reprojection after it.
    fn records_scene_probe(&self, _params: &Params) -> bool {
        false
    }

    /// Produces the enhanced frame: 4 planes, RGB premultiplied by A, A the
    /// output coverage (1 where holes were filled).
    fn process(
        &self,
        input: &BackendInput<'_>,
        carry: &mut Carry,
        progress: &mut Progress<'_>,
        stages: &mut Stages,
    ) -> Result<Image>;

    /// Whether the backend works on the frame's color in place
    /// ([`Backend::process_in_place`]). The session then prepares the color
    /// as 4 planes (RGBA) and hands it over when nothing after the backend
    /// needs the frame's color (`strength` 1), so the backend makes no
    /// frame-sized copy of it.
    fn works_in_place(&self) -> bool {
        false
    }

    /// [`Backend::process`] with the frame's color handed over as `rgba`
    /// (4 planes: RGB premultiplied, A the coverage, 1 where absent;
    /// `input.frame.color` has no planes then). Called only when
    /// [`Backend::works_in_place`] is true; the default is an error.
    fn process_in_place(
        &self,
        rgba: Image,
        input: &BackendInput<'_>,
        carry: &mut Carry,
        progress: &mut Progress<'_>,
        stages: &mut Stages,
    ) -> Result<Image> {
        let _ = (rgba, input, carry, progress, stages);
        Err(Error::invalid(format!(
            "backend {}: does not work in place",
            self.name()
        )))
    }
}

/// Output equals input: RGB copied, A = coverage (1 when absent).
#[derive(Debug, Default)]
pub struct Bypass;

impl Backend for Bypass {
    fn name(&self) -> &str {
        "bypass"
    }

    fn process(
        &self,
        input: &BackendInput<'_>,
        _carry: &mut Carry,
        progress: &mut Progress<'_>,
        stages: &mut Stages,
    ) -> Result<Image> {
        let out = stages.time("bypass", || {
            let f = input.frame;
            let mut out = Image::try_zeros(f.width(), f.height(), 4)?;
            let n = f.color.len();
            out.data[..3 * n].copy_from_slice(&f.color.data[..3 * n]);
            match &f.coverage {
                Some(c) => out.data[3 * n..].copy_from_slice(c),
                None => out.data[3 * n..].fill(1.0),
            }
            Ok::<_, Error>(out)
        })?;
        progress.report(1.0)?;
        Ok(out)
    }

    fn works_in_place(&self) -> bool {
        true
    }

    /// The handed-over color is the output as it is.
    fn process_in_place(
        &self,
        rgba: Image,
        _input: &BackendInput<'_>,
        _carry: &mut Carry,
        progress: &mut Progress<'_>,
        _stages: &mut Stages,
    ) -> Result<Image> {
        progress.report(1.0)?;
        Ok(rgba)
    }
}
