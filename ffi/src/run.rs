//! `hz_run_sequence`: a session over an EXR sequence on disk, read and
//! written by the library itself (the loop of `harmonize run`, with its
//! frame range and pre-roll), so a host that runs chunks of a sequence in
//! process (the Python farm driver) writes the bytes the CLI writes.

use std::ffi::{c_char, c_void, CString};
use std::path::PathBuf;

use harmonizer_core::io::layout::{
    check_insert_indices, ChannelMapping, LayoutOptions, LayoutPreset,
};
use harmonizer_core::io::pattern::FrameRange;
use harmonizer_core::io::run::{plan, report_json, run_sequence, FrameResult, RunOptions};
use harmonizer_core::{Error, ParamValue, Params};

use crate::session::{hz_session, lock, uncommitted};
use crate::{check_null, check_struct_sizes, ffi_guard, hz_status, read_prefix, read_str};

/// Only the frames `frame_first..=frame_last` (`hz_run_options.flags`);
/// without it every existing frame of the input pattern.
pub const HZ_RUN_HAS_FRAMES: u32 = 1;
/// `hz_run_options.insert_index` is set (`hz_run_options.flags`).
pub const HZ_RUN_HAS_INSERT_INDEX: u32 = 2;
/// When the session's committed `denoise` and `samples` are their defaults,
/// set what the first file's headers say about its noise before the run
/// (Blender's `cycles.<layer>.samples` gives `samples`, Cycles' Noisy Image
/// pass `denoise temporal`), as `harmonize run` does when the user set
/// neither (`hz_run_options.flags`).
pub const HZ_RUN_RENDER_HINTS: u32 = 4;
/// The most Object Indices `hz_run_options.insert_indices` may hold (a
/// count past it is a wrong count, not a scene).
const MAX_INSERT_INDICES: usize = 65536;
const KNOWN_RUN_FLAGS: u32 = HZ_RUN_HAS_FRAMES | HZ_RUN_HAS_INSERT_INDEX | HZ_RUN_RENDER_HINTS;

/// What `hz_run_sequence` runs. Zero-initialize, set `struct_size =
/// sizeof(hz_run_options)`, `input` and `output`; NULL or zero fields are
/// the defaults.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct hz_run_options {
    /// `sizeof(hz_run_options)`.
    pub struct_size: usize,
    /// Input frame pattern (`####`, `%04d`, `$F4`, `${F4}` or `<F4>`). Required.
    pub input: *const c_char,
    /// Output frame pattern. Required. An output that would overwrite an
    /// input is refused before any frame is read.
    pub output: *const c_char,
    /// Channel layout: `"auto"` (NULL), `"generic"` or `"blender"`.
    pub layout: *const c_char,
    /// Channel mapping as `harmonize run --channel` takes it, entries
    /// separated by `;`: `"color=R,G,B;coverage=A"`. NULL = none.
    pub channels: *const c_char,
    /// `HZ_RUN_HAS_FRAMES`, `HZ_RUN_HAS_INSERT_INDEX`, `HZ_RUN_RENDER_HINTS`.
    pub flags: u32,
    /// First frame written (with `HZ_RUN_HAS_FRAMES`).
    pub frame_first: i64,
    /// Last frame written (with `HZ_RUN_HAS_FRAMES`); every frame of the
    /// range must exist.
    pub frame_last: i64,
    /// Frames before `frame_first` processed first and not written, so the
    /// chunk starts with the temporal state a sequential run would have
    /// (those of `frame_first - preroll ..= frame_first - 1` that exist).
    /// Needs `HZ_RUN_HAS_FRAMES`.
    pub preroll: usize,
    /// Blender layout: the Object Index of the inserted object (with
    /// `HZ_RUN_HAS_INSERT_INDEX`).
    pub insert_index: i64,
    /// Where to write the run's JSON report (what `harmonize run --report`
    /// writes; also after a failed run, with its `error`). NULL = none.
    pub report: *const c_char,
    /// Blender layout: the Object Indices of several inserted objects,
    /// `insert_index_count` of them (`harmonize run --insert-index 3,5`):
    /// each is harmonized as an object of its own, by its index. Replaces
    /// `insert_index` when the count is not zero. NULL with a count of 0 =
    /// none. (Appended after `report`; an older header's size is accepted.)
    pub insert_indices: *const i64,
    /// How many values `insert_indices` holds.
    pub insert_index_count: usize,
}

/// `sizeof(hz_run_options)` in headers before `insert_indices`.
const RUN_OPTIONS_SIZE_V1: usize =
    crate::older_size::<hz_run_options>(std::mem::offset_of!(hz_run_options, insert_indices));

/// Called after each frame of `hz_run_sequence` (pre-roll frames too) with
/// the frame's report as JSON (`{"frame", "preroll", "input", "output",
/// "backend", "reset", "history_used", "warnings": [..], "read_ms",
/// "process_ms", "write_ms", ...}`; valid during the call only). Return
/// false to stop the run after this frame (`HZ_ERROR_CANCELLED`). Runs with
/// the session's lock held, like the session's callbacks.
pub type hz_run_frame_fn =
    Option<unsafe extern "C" fn(user: *mut c_void, frame_json: *const c_char) -> bool>;

/// The options a host passed, read.
struct Read {
    options: RunOptions,
    layout: String,
    hints: bool,
    report: Option<PathBuf>,
}

/// # Safety
/// `o` is NULL or a readable `hz_run_options` whose strings are
/// NUL-terminated or NULL.
unsafe fn read_options(o: *const hz_run_options) -> Result<Read, Error> {
    check_null!(o);
    // SAFETY: non-NULL; only the first field is read before the size check.
    let size = unsafe { std::ptr::addr_of!((*o).struct_size).read_unaligned() };
    check_struct_sizes(
        "hz_run_options",
        size,
        &[RUN_OPTIONS_SIZE_V1, std::mem::size_of::<hz_run_options>()],
    )?;
    // SAFETY: readable for `size` bytes (an accepted size); the fields an
    // older header lacks read as zero (no `insert_indices`).
    let o = unsafe { read_prefix(o, size) };
    if o.flags & !KNOWN_RUN_FLAGS != 0 {
        return Err(Error::invalid(format!(
            "hz_run_options.flags has unknown bits {:#x}",
            o.flags & !KNOWN_RUN_FLAGS
        )));
    }
    // SAFETY (all reads below): NULL or NUL-terminated per the contract.
    let input = unsafe { read_str("options.input", o.input) }?.to_string();
    let output = unsafe { read_str("options.output", o.output) }?.to_string();
    let layout = match o.layout.is_null() {
        true => "auto".to_string(),
        false => unsafe { read_str("options.layout", o.layout) }?.to_string(),
    };
    let mut mapping = ChannelMapping::default();
    if !o.channels.is_null() {
        let text = unsafe { read_str("options.channels", o.channels) }?;
        for entry in text.split(';').map(str::trim).filter(|e| !e.is_empty()) {
            mapping.add(entry)?;
        }
    }
    let report = match o.report.is_null() {
        true => None,
        false => Some(PathBuf::from(unsafe {
            read_str("options.report", o.report)
        }?)),
    };
    let frames = if o.flags & HZ_RUN_HAS_FRAMES != 0 {
        if o.frame_last < o.frame_first {
            return Err(Error::invalid(format!(
                "options.frame_last {} is before frame_first {}",
                o.frame_last, o.frame_first
            )));
        }
        Some(FrameRange::parse(&format!(
            "{}-{}",
            o.frame_first, o.frame_last
        ))?)
    } else {
        None
    };
    let insert_indices = match (o.insert_indices.is_null(), o.insert_index_count) {
        (_, 0) => Vec::new(),
        (true, n) => {
            return Err(Error::invalid(format!(
                "options.insert_indices is NULL with insert_index_count {n}"
            )))
        }
        (false, n) if n > MAX_INSERT_INDICES => {
            return Err(Error::invalid(format!(
                "options.insert_index_count {n} is over {MAX_INSERT_INDICES}"
            )))
        }
        // SAFETY: non-NULL and readable for `n` values per the contract.
        (false, n) => unsafe { std::slice::from_raw_parts(o.insert_indices, n) }.to_vec(),
    };
    check_insert_indices("options.insert_indices", &insert_indices)?;
    let options = RunOptions {
        input,
        output,
        layout: LayoutOptions {
            preset: LayoutPreset::parse(&layout)?,
            mapping,
            insert_index: (o.flags & HZ_RUN_HAS_INSERT_INDEX != 0).then_some(o.insert_index),
            insert_indices,
        },
        frames,
        preroll: o.preroll,
    };
    Ok(Read {
        options,
        layout,
        hints: o.flags & HZ_RUN_RENDER_HINTS != 0,
        report,
    })
}

/// Runs `session` over an EXR sequence, reading and writing the files
/// itself, as `harmonize run INPUT -o OUTPUT [--frames A-B --preroll N]`
/// does with the session's committed parameters: the same plan, the same
/// outputs byte for byte (written atomically: a temporary file renamed, so
/// an output is complete or absent, and a chunk run again writes the same
/// bytes), the same report (`options.report`). `on_frame` (may be NULL)
/// sees each frame's report as JSON.
///
/// Unlike the other calls, a failing run has done part of its work: the
/// frames before the failing one are written and the session's temporal
/// state and report are those of the last frame that succeeded. The error
/// names the frame and file. The session keeps its state after a run
/// (call `hz_session_reset` before an unrelated sequence).
///
/// # Safety
/// `session` is a live handle; `options` points to an `hz_run_options`
/// whose strings are NUL-terminated or NULL; `on_frame` stays callable with
/// `user` during the call.
#[no_mangle]
pub unsafe extern "C" fn hz_run_sequence(
    session: *mut hz_session,
    options: *const hz_run_options,
    on_frame: hz_run_frame_fn,
    user: *mut c_void,
) -> hz_status {
    ffi_guard!("hz_run_sequence", {
        // SAFETY: forwarded contract.
        let read = unsafe { read_options(options) }?;
        let planned = plan(&read.options)?;
        // SAFETY: forwarded contract.
        let mut s = unsafe { lock(session) }?;
        if let Some(name) = uncommitted(&s.session) {
            return Err(Error::InvalidOperation(format!(
                "parameter {name:?} was set but not committed; call hz_session_commit first"
            )));
        }
        if read.hints {
            apply_render_hints(&mut s.session, &read.options, &planned)?;
        }
        let mut done: Vec<FrameResult> = Vec::new();
        let r = run_sequence(&mut s.session, &read.options, &planned, false, &mut |res| {
            done.push(res.clone());
            let Some(f) = on_frame else { return Ok(()) };
            let text = CString::new(res.json().to_string()).unwrap_or_default();
            // SAFETY: a function pointer the host passed, called with its
            // own user pointer; `text` outlives the call.
            if unsafe { f(user, text.as_ptr()) } {
                Ok(())
            } else {
                Err(Error::Cancelled(format!(
                    "the frame callback stopped the run after frame {}",
                    res.planned.frame
                )))
            }
        });
        if let Some(last) = done.last() {
            s.report = Some(last.report.clone());
        }
        drop(s);
        if let Some(path) = &read.report {
            let v = report_json(&read.options, &read.layout, &done, r.as_ref().err());
            let text = serde_json::to_string_pretty(&v).map_err(|e| Error::io(path, e))?;
            harmonizer_core::io::exr::write_atomic(path, |tmp| {
                std::fs::write(tmp, text.as_bytes())
            })?;
        }
        r.map(|_| ())
    })
}

/// What the first planned file's headers say about its noise, set on the
/// session when its `denoise` and `samples` are the defaults (as
/// `harmonize run` does when the user set neither).
fn apply_render_hints(
    session: &mut harmonizer_core::Session,
    options: &RunOptions,
    planned: &[harmonizer_core::io::run::PlannedFrame],
) -> crate::FfiResult {
    let defaults = Params::default();
    let p = session.params();
    if p.get("denoise")? != defaults.get("denoise")? || p.get("samples")? != ParamValue::Int(0) {
        return Ok(());
    }
    let Some(first) = planned.first() else {
        return Ok(());
    };
    let hints = harmonizer_core::io::exr::read_render_hints(&first.input, &options.layout);
    if let Some((name, value, _why)) = hints.params() {
        session.set(name, value)?;
        session.commit()?;
    }
    Ok(())
}
