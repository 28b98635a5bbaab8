//! `hz_session`: one camera's temporal state. Parameters by name, the
//! per-frame `hz_frame`, processing, queries and the last frame's report.

use std::cell::RefCell;
use std::ffi::{c_char, c_void};
use std::sync::{Mutex, MutexGuard};

use harmonizer_core::params::PARAM_NAMES;
use harmonizer_core::session::ResetReason;
use harmonizer_core::{
    Camera, Error, FrameInput, FrameReport, FrameShape, ParamValue, Params, Session,
};

use crate::callbacks::{self, hz_message_fn, hz_message_level, hz_progress_fn};
use crate::device::{device_ref, hz_device};
use crate::image::{hz_image, Described};
use crate::{
    check_null, check_struct_sizes, ffi_guard, hz_status, read_prefix, read_str, write_prefix,
    write_str,
};

/// Drop the temporal state before this frame (`hz_frame.flags`).
pub const HZ_FRAME_RESET: u32 = 1;
/// `hz_frame.frame_index` is set (`hz_frame.flags`); without it the frame has
/// no number and no gap detection happens.
pub const HZ_FRAME_HAS_INDEX: u32 = 2;
const KNOWN_FLAGS: u32 = HZ_FRAME_RESET | HZ_FRAME_HAS_INDEX;

/// One rendered frame. Zero-initialize, set `struct_size = sizeof(hz_frame)`
/// and `color`; every other pointer may be NULL (input absent).
///
/// The struct grows only at its end: a host built against an older header
/// passes that header's `sizeof(hz_frame)` (without `albedo` and
/// `denoise_normal`, or without `insert_id`), and the fields it lacks read
/// as NULL.
///
/// Conventions: color is scene-linear Linear Rec.709, premultiplied by
/// coverage. Depth is planar (distance along the view axis; set the session
/// parameter `depth_kind` to `"euclidean"` for ray length), empty pixels very
/// large. Motion vectors are in pixels, from the current pixel to where the
/// same surface point was in the PREVIOUS frame, x right, y DOWN, after
/// multiplying by `motion_vector_scale` (Blender's Vector pass: `{1, -1}`).
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct hz_frame {
    /// `sizeof(hz_frame)`.
    pub struct_size: usize,
    /// Color, at least 3 channels (RGB premultiplied; a 4th channel is ignored). Required.
    pub color: *const hz_image,
    /// Depth, 1 channel. Optional.
    pub depth: *const hz_image,
    /// Motion vectors, 2 channels (see the conventions above). Optional.
    pub motion: *const hz_image,
    /// Normals, 3 channels, any space. Optional. Validated like the other
    /// inputs (size, channel count); NaN and infinite samples are counted
    /// and reported as a warning (replaced by 0 where a backend reads them).
    /// Only a neural model whose manifest lists normal channels reads them;
    /// the classical and bypass backends give the same output without them.
    pub normal: *const hz_image,
    /// Coverage in [0, 1], 1 channel: 0 where the renderer had no data (a hole). Optional.
    pub coverage: *const hz_image,
    /// Insert mask in [0, 1], 1 channel: where an inserted object is. Optional.
    pub insert_mask: *const hz_image,
    /// 16 floats, row-major: the OpenEXR `worldToCamera` matrix, a ROW-vector
    /// matrix (`p_camera = [x y z 1] * M`), camera space +x right, +y up,
    /// +z forward. NULL = no camera; set together with `world_to_ndc`.
    pub world_to_camera: *const f32,
    /// 16 floats, row-major: the OpenEXR `worldToNDC` row-vector matrix; NDC
    /// (0,0) is the top-left and (1,1) the bottom-right corner after dividing by w.
    pub world_to_ndc: *const f32,
    /// The host's frame number (with `HZ_FRAME_HAS_INDEX`); a gap triggers the
    /// session's `gap_policy`.
    pub frame_index: i64,
    /// `HZ_FRAME_RESET`, `HZ_FRAME_HAS_INDEX`.
    pub flags: u32,
    /// Multiplies the motion image into the convention above; `{0, 0}` (a
    /// zero-initialized struct) means `{1, 1}`.
    pub motion_vector_scale: [f32; 2],
    /// Albedo, 3 channels (a 4th is ignored), linear RGB reflectance in
    /// [0, 1]: Cycles' Denoising Albedo pass or any renderer's albedo AOV
    /// (0 where nothing was hit). Optional; read by the denoise stage only
    /// (session parameter `denoise`), which denoises the color with it and
    /// the normals, both prefiltered. Validated like the other inputs
    /// (size, channel count); NaN and infinite samples become 0 (counted
    /// and reported as a warning), other values are clamped to [0, 1].
    /// Appended: NULL for a host that passes an older `struct_size`.
    pub albedo: *const hz_image,
    /// The denoiser's normals, 3 channels, any space (Cycles' Denoising
    /// Normal pass, in camera space). Optional; read by the denoise stage
    /// only, and only with `albedo`; when absent the denoiser uses
    /// `normal`. Validated like `normal`. Appended: NULL for a host that
    /// passes an older `struct_size`.
    pub denoise_normal: *const hz_image,
    /// Insert object ids, 1 channel, integer ids held as floats (0: not an
    /// inserted object): which inserted object each pixel belongs to, for
    /// example Blender's Object Index pass, an id per Cryptomatte match or
    /// a USD prim or instance id. Optional. Each distinct id above 0 among
    /// the insert's pixels is one object, harmonized with its own filter
    /// and followed over time by its id, whether or not its pixels touch
    /// another object's; insert pixels with id 0 are grouped by connected
    /// parts as without ids. With `insert_mask` NULL the mask is 1 where
    /// the id is above 0. Validated like the other inputs (size, channel
    /// count); NaN and infinite samples count as 0 (counted and reported
    /// as a warning), negative ones as 0. Appended: NULL for a host that
    /// passes an older `struct_size`.
    pub insert_id: *const hz_image,
}

/// `sizeof(hz_frame)` in the headers before `albedo` and `denoise_normal`.
const FRAME_SIZE_V1: usize = crate::older_size::<hz_frame>(std::mem::offset_of!(hz_frame, albedo));
/// `sizeof(hz_frame)` in the headers before `insert_id`.
const FRAME_SIZE_V2: usize =
    crate::older_size::<hz_frame>(std::mem::offset_of!(hz_frame, insert_id));
/// The sizes of `hz_frame` a host may pass, oldest first.
const FRAME_SIZES: [usize; 3] = [
    FRAME_SIZE_V1,
    FRAME_SIZE_V2,
    std::mem::size_of::<hz_frame>(),
];

/// Type of a named parameter.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum hz_param_type {
    /// `hz_session_set_int` / `hz_session_get_int`.
    HZ_PARAM_INT = 1,
    /// `hz_session_set_float` / `hz_session_get_float`.
    HZ_PARAM_FLOAT = 2,
    /// `hz_session_set_bool` / `hz_session_get_bool`.
    HZ_PARAM_BOOL = 3,
    /// `hz_session_set_string` / `hz_session_get_string`.
    HZ_PARAM_STRING = 4,
}

/// Why the temporal state was dropped before the reported frame.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum hz_reset_reason {
    /// No reset: the history was used.
    HZ_RESET_NONE = 0,
    /// The first frame of the session or after `hz_session_reset`.
    HZ_RESET_FIRST_FRAME = 1,
    /// `HZ_FRAME_RESET` or `hz_session_reset`.
    HZ_RESET_REQUESTED = 2,
    /// The frame size changed.
    HZ_RESET_SIZE_CHANGED = 3,
    /// The set of inputs (depth, motion, camera) changed.
    HZ_RESET_LAYOUT_CHANGED = 4,
    /// A committed parameter change (backend, context, depth kind).
    HZ_RESET_PARAMS_CHANGED = 5,
    /// The frame index is not the previous one plus one (`gap_policy` reset).
    HZ_RESET_FRAME_GAP = 6,
    /// The scene-cut detector fired.
    HZ_RESET_SCENE_CUT = 7,
}

impl hz_reset_reason {
    fn of(r: Option<ResetReason>) -> hz_reset_reason {
        match r {
            None => hz_reset_reason::HZ_RESET_NONE,
            Some(ResetReason::FirstFrame) => hz_reset_reason::HZ_RESET_FIRST_FRAME,
            Some(ResetReason::Requested) => hz_reset_reason::HZ_RESET_REQUESTED,
            Some(ResetReason::SizeChanged) => hz_reset_reason::HZ_RESET_SIZE_CHANGED,
            Some(ResetReason::LayoutChanged) => hz_reset_reason::HZ_RESET_LAYOUT_CHANGED,
            Some(ResetReason::ParamsChanged) => hz_reset_reason::HZ_RESET_PARAMS_CHANGED,
            Some(ResetReason::FrameGap) => hz_reset_reason::HZ_RESET_FRAME_GAP,
            Some(ResetReason::SceneCut) => hz_reset_reason::HZ_RESET_SCENE_CUT,
        }
    }
}

/// What happened to the last successfully processed frame
/// (`hz_session_get_report`). Set `struct_size = sizeof(hz_report)`. The
/// struct grows only at its end: a host built against an older header
/// passes that header's `sizeof(hz_report)` and gets the fields it knows
/// (nothing is written past them).
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct hz_report {
    /// `sizeof(hz_report)`.
    pub struct_size: usize,
    /// The frame's number (valid when `has_frame_index`).
    pub frame_index: i64,
    /// Whether the frame had `HZ_FRAME_HAS_INDEX`.
    pub has_frame_index: bool,
    /// Why the temporal state was reset before the frame.
    pub reset_reason: hz_reset_reason,
    /// History frames used.
    pub history_used: usize,
    /// Color samples replaced by 0 because they were NaN or infinite
    /// (negative components of out-of-gamut colors are kept, not replaced).
    pub sanitized: usize,
    /// Warnings (`hz_session_get_report_warning`).
    pub warning_count: usize,
    /// Wall time of the call in milliseconds.
    pub total_ms: f64,
    /// Whether the denoise stage ran on this frame (session parameter
    /// `denoise`). Appended, like the fields after it: not written for a
    /// host that passes an older `struct_size`.
    pub denoised: bool,
    /// Whether `noise_level` is set: on the frame where `denoise auto`
    /// decided from the frame's noise estimate (`samples` 0).
    pub has_noise_level: bool,
    /// The noise estimate, in stops of white noise in log2 luminance
    /// (`denoise auto` turns the stage on above 0.2; clean renders measure
    /// about 0.04-0.09, renders of a few samples per pixel 0.4 and more);
    /// 0 without `has_noise_level`. What was decided and why:
    /// `hz_session_get_report_denoise_decision`.
    pub noise_level: f32,
}

/// `sizeof(hz_report)` in the headers before `denoised`, `has_noise_level`
/// and `noise_level`.
const REPORT_SIZE_V1: usize =
    crate::older_size::<hz_report>(std::mem::offset_of!(hz_report, denoised));
/// The sizes of `hz_report` a host may pass, oldest first.
const REPORT_SIZES: [usize; 2] = [REPORT_SIZE_V1, std::mem::size_of::<hz_report>()];

/// Opaque session handle.
pub struct hz_session {
    state: Mutex<State>,
}

pub(crate) struct State {
    pub(crate) session: Session,
    pub(crate) report: Option<FrameReport>,
    progress: Option<callbacks::Progress>,
    message: Option<callbacks::Message>,
}

thread_local! {
    /// Sessions locked by this thread (a callback calling back into its own
    /// session would deadlock; it gets an error instead).
    static LOCKED: RefCell<Vec<usize>> = const { RefCell::new(Vec::new()) };
}

/// A locked session.
pub(crate) struct Locked<'a> {
    guard: MutexGuard<'a, State>,
    key: usize,
}

impl Drop for Locked<'_> {
    fn drop(&mut self) {
        LOCKED.with(|l| {
            let mut l = l.borrow_mut();
            if let Some(i) = l.iter().rposition(|k| *k == self.key) {
                l.remove(i);
            }
        });
    }
}

impl std::ops::Deref for Locked<'_> {
    type Target = State;
    fn deref(&self) -> &State {
        &self.guard
    }
}

impl std::ops::DerefMut for Locked<'_> {
    fn deref_mut(&mut self) -> &mut State {
        &mut self.guard
    }
}

/// Locks a session handle, serializing calls on it.
///
/// # Safety
/// `s` is NULL or a live handle from `hz_session_new`.
pub(crate) unsafe fn lock<'a>(s: *const hz_session) -> Result<Locked<'a>, Error> {
    if s.is_null() {
        return Err(Error::invalid("session is NULL"));
    }
    let key = s as usize;
    if LOCKED.with(|l| l.borrow().contains(&key)) {
        return Err(Error::InvalidOperation(
            "called from a callback of the same session (calls on a session are serialized)".into(),
        ));
    }
    // SAFETY: non-NULL and live per the contract.
    let handle: &'a hz_session = unsafe { &*s };
    // A panic inside a call poisons the lock; the session's state only changes
    // when a frame succeeds, so it is still consistent.
    let guard = handle.state.lock().unwrap_or_else(|p| p.into_inner());
    LOCKED.with(|l| l.borrow_mut().push(key));
    Ok(Locked { guard, key })
}

/// Creates a session on `device` with default parameters (`backend` `auto`:
/// the neural model when the device has one, else `classical`). On failure
/// `*out_session` is set to NULL.
///
/// # Safety
/// `device` is a live handle; `out_session` is writable.
#[no_mangle]
pub unsafe extern "C" fn hz_session_new(
    device: *const hz_device,
    out_session: *mut *mut hz_session,
) -> hz_status {
    ffi_guard!("hz_session_new", {
        check_null!(out_session);
        // SAFETY: writable per the contract.
        unsafe { out_session.write(std::ptr::null_mut()) };
        // SAFETY: live handle per the contract.
        let device = unsafe { device_ref(device) }?;
        let session = Session::new(device.inner.clone(), Params::default())?;
        let handle = Box::new(hz_session {
            state: Mutex::new(State {
                session,
                report: None,
                progress: None,
                message: None,
            }),
        });
        // SAFETY: as above.
        unsafe { out_session.write(Box::into_raw(handle)) };
        Ok(())
    })
}

/// Destroys a session (NULL is a no-op). No call on it may be running.
///
/// # Safety
/// `session` is NULL or a handle from `hz_session_new` not freed before.
#[no_mangle]
pub unsafe extern "C" fn hz_session_free(session: *mut hz_session) -> hz_status {
    ffi_guard!("hz_session_free", {
        if !session.is_null() {
            if LOCKED.with(|l| l.borrow().contains(&(session as usize))) {
                return Err(Error::InvalidOperation(
                    "cannot free a session from its own callback".into(),
                ));
            }
            // SAFETY: a live handle from `Box::into_raw`, freed once.
            drop(unsafe { Box::from_raw(session) });
        }
        Ok(())
    })
}

/// Stages an integer parameter (for example `"context_frames"`, `"tile_size"`).
/// Unknown names and out-of-range values fail. Takes effect at `hz_session_commit`.
///
/// # Safety
/// `session` is a live handle; `name` a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn hz_session_set_int(
    session: *mut hz_session,
    name: *const c_char,
    value: i64,
) -> hz_status {
    ffi_guard!("hz_session_set_int", {
        // SAFETY: forwarded contract.
        unsafe { set(session, name, ParamValue::Int(value)) }
    })
}

/// Stages a number parameter (for example `"strength"`, `"temporal_blend"`).
///
/// # Safety
/// As `hz_session_set_int`.
#[no_mangle]
pub unsafe extern "C" fn hz_session_set_float(
    session: *mut hz_session,
    name: *const c_char,
    value: f64,
) -> hz_status {
    ffi_guard!("hz_session_set_float", {
        // SAFETY: forwarded contract.
        unsafe { set(session, name, ParamValue::Float(value)) }
    })
}

/// Stages a boolean parameter (for example `"fill_holes"`, `"stabilize"`).
///
/// # Safety
/// As `hz_session_set_int`.
#[no_mangle]
pub unsafe extern "C" fn hz_session_set_bool(
    session: *mut hz_session,
    name: *const c_char,
    value: bool,
) -> hz_status {
    ffi_guard!("hz_session_set_bool", {
        // SAFETY: forwarded contract.
        unsafe { set(session, name, ParamValue::Bool(value)) }
    })
}

/// Stages a string parameter (for example `"backend"`: `auto`, `neural`,
/// `classical`, `bypass`; `"gap_policy"`: `reset`, `keep`; `"depth_kind"`:
/// `planar`, `euclidean`).
///
/// # Safety
/// As `hz_session_set_int`; `value` a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn hz_session_set_string(
    session: *mut hz_session,
    name: *const c_char,
    value: *const c_char,
) -> hz_status {
    ffi_guard!("hz_session_set_string", {
        // SAFETY: NUL-terminated per the contract.
        let value = unsafe { read_str("value", value) }?;
        // SAFETY: forwarded contract.
        unsafe { set(session, name, ParamValue::Str(value.to_string())) }
    })
}

unsafe fn set(
    session: *mut hz_session,
    name: *const c_char,
    value: ParamValue,
) -> crate::FfiResult {
    // SAFETY: NUL-terminated per the contract.
    let name = unsafe { read_str("name", name) }?;
    // SAFETY: forwarded contract.
    let mut s = unsafe { lock(session) }?;
    s.session.set(name, value)
}

/// The type of a named parameter (an `hz_param_type` value).
///
/// # Safety
/// `session` is a live handle; `name` a NUL-terminated string; `out_type` writable.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_type(
    session: *const hz_session,
    name: *const c_char,
    out_type: *mut hz_param_type,
) -> hz_status {
    ffi_guard!("hz_session_get_type", {
        check_null!(out_type);
        // SAFETY: forwarded contract.
        let v = unsafe { get(session, name) }?;
        let t = match v {
            ParamValue::Int(_) => hz_param_type::HZ_PARAM_INT,
            ParamValue::Float(_) => hz_param_type::HZ_PARAM_FLOAT,
            ParamValue::Bool(_) => hz_param_type::HZ_PARAM_BOOL,
            ParamValue::Str(_) => hz_param_type::HZ_PARAM_STRING,
        };
        // SAFETY: writable per the contract.
        unsafe { out_type.write(t) };
        Ok(())
    })
}

unsafe fn get(session: *const hz_session, name: *const c_char) -> Result<ParamValue, Error> {
    // SAFETY: NUL-terminated per the contract.
    let name = unsafe { read_str("name", name) }?;
    // SAFETY: forwarded contract.
    let s = unsafe { lock(session) }?;
    s.session.get(name)
}

fn wrong_type(name: &str, want: &str, got: &ParamValue) -> Error {
    Error::invalid(format!(
        "parameter {name:?} is not {want}: its value is {got:?}"
    ))
}

/// Reads a staged integer parameter.
///
/// # Safety
/// `session` is a live handle; `name` a NUL-terminated string; `out_value` writable.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_int(
    session: *const hz_session,
    name: *const c_char,
    out_value: *mut i64,
) -> hz_status {
    ffi_guard!("hz_session_get_int", {
        check_null!(out_value);
        // SAFETY: forwarded contract.
        match unsafe { get(session, name) }? {
            // SAFETY: writable per the contract.
            ParamValue::Int(i) => unsafe { out_value.write(i) },
            // SAFETY: `name` was read above.
            v => {
                return Err(wrong_type(
                    unsafe { read_str("name", name) }?,
                    "an integer",
                    &v,
                ))
            }
        }
        Ok(())
    })
}

/// Reads a staged number parameter (integers are converted).
///
/// # Safety
/// As `hz_session_get_int`.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_float(
    session: *const hz_session,
    name: *const c_char,
    out_value: *mut f64,
) -> hz_status {
    ffi_guard!("hz_session_get_float", {
        check_null!(out_value);
        // SAFETY: forwarded contract.
        let f = match unsafe { get(session, name) }? {
            ParamValue::Float(f) => f,
            ParamValue::Int(i) => i as f64,
            // SAFETY: `name` was read above.
            v => {
                return Err(wrong_type(
                    unsafe { read_str("name", name) }?,
                    "a number",
                    &v,
                ))
            }
        };
        // SAFETY: writable per the contract.
        unsafe { out_value.write(f) };
        Ok(())
    })
}

/// Reads a staged boolean parameter.
///
/// # Safety
/// As `hz_session_get_int`.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_bool(
    session: *const hz_session,
    name: *const c_char,
    out_value: *mut bool,
) -> hz_status {
    ffi_guard!("hz_session_get_bool", {
        check_null!(out_value);
        // SAFETY: forwarded contract.
        match unsafe { get(session, name) }? {
            // SAFETY: writable per the contract.
            ParamValue::Bool(b) => unsafe { out_value.write(b) },
            // SAFETY: `name` was read above.
            v => {
                return Err(wrong_type(
                    unsafe { read_str("name", name) }?,
                    "a boolean",
                    &v,
                ))
            }
        }
        Ok(())
    })
}

/// Reads a staged string parameter into `buffer` (see "Strings" in the
/// header's introduction: `buffer` may be NULL to ask for `*out_length`).
///
/// # Safety
/// As `hz_session_get_int`; `buffer` is NULL or writable for `buffer_size`
/// bytes; `out_length` is NULL or writable.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_string(
    session: *const hz_session,
    name: *const c_char,
    buffer: *mut c_char,
    buffer_size: usize,
    out_length: *mut usize,
) -> hz_status {
    ffi_guard!("hz_session_get_string", {
        // SAFETY: forwarded contract.
        match unsafe { get(session, name) }? {
            // SAFETY: forwarded contract.
            ParamValue::Str(s) => unsafe { write_str(&s, buffer, buffer_size, out_length) },
            // SAFETY: `name` was read above.
            v => Err(wrong_type(
                unsafe { read_str("name", name) }?,
                "a string",
                &v,
            )),
        }
    })
}

/// Applies the staged parameters. A change of backend, `context_frames` or
/// `depth_kind` resets the temporal state. Settings the backend cannot run
/// with are refused here (`HZ_ERROR_INVALID_ARGUMENT`, naming the
/// parameters): with the neural backend, `tile_size` and `tile_overlap`
/// (0 = the model's) that cannot tile every frame size with the model
/// (a tile's core, `tile_size - 2 * tile_overlap`, must leave room for the
/// feathered blend; the message says the smallest `tile_size` that works).
/// On failure nothing changes.
///
/// # Safety
/// `session` is a live handle.
#[no_mangle]
pub unsafe extern "C" fn hz_session_commit(session: *mut hz_session) -> hz_status {
    ffi_guard!("hz_session_commit", {
        // SAFETY: forwarded contract.
        let mut s = unsafe { lock(session) }?;
        s.session.commit()
    })
}

/// Drops the temporal state; the next frame is a cold start.
///
/// # Safety
/// `session` is a live handle.
#[no_mangle]
pub unsafe extern "C" fn hz_session_reset(session: *mut hz_session) -> hz_status {
    ffi_guard!("hz_session_reset", {
        // SAFETY: forwarded contract.
        let mut s = unsafe { lock(session) }?;
        s.session.reset();
        Ok(())
    })
}

/// Sets (or with NULL `callback` clears) the progress callback used by
/// `hz_session_process`. See `hz_progress_fn`.
///
/// # Safety
/// `session` is a live handle; `callback` stays callable with `user` until
/// replaced or the session is freed.
#[no_mangle]
pub unsafe extern "C" fn hz_session_set_progress_callback(
    session: *mut hz_session,
    callback: hz_progress_fn,
    user: *mut c_void,
) -> hz_status {
    ffi_guard!("hz_session_set_progress_callback", {
        // SAFETY: forwarded contract.
        let mut s = unsafe { lock(session) }?;
        s.progress = callback.map(|func| callbacks::Callback { func, user });
        Ok(())
    })
}

/// Sets (or with NULL `callback` clears) the message callback: after each
/// successful frame it receives the frame's warnings (NaN or infinite color,
/// NaN AOVs, a non-consecutive frame index, ...) and resets other than the
/// first frame.
///
/// # Safety
/// As `hz_session_set_progress_callback`.
#[no_mangle]
pub unsafe extern "C" fn hz_session_set_message_callback(
    session: *mut hz_session,
    callback: hz_message_fn,
    user: *mut c_void,
) -> hz_status {
    ffi_guard!("hz_session_set_message_callback", {
        // SAFETY: forwarded contract.
        let mut s = unsafe { lock(session) }?;
        s.message = callback.map(|func| callbacks::Callback { func, user });
        Ok(())
    })
}

/// Reads a camera matrix (16 row-major floats).
///
/// # Safety
/// `p` is readable for 16 floats.
unsafe fn read_matrix(what: &str, p: *const f32) -> Result<[[f32; 4]; 4], Error> {
    // SAFETY: readable per the contract; unaligned reads are fine.
    let m = unsafe { p.cast::<[f32; 16]>().read_unaligned() };
    if let Some(i) = m.iter().position(|v| !v.is_finite()) {
        return Err(Error::invalid(format!(
            "{what}[{i}] is {}, not finite",
            m[i]
        )));
    }
    let mut rows = [[0.0; 4]; 4];
    for (r, row) in rows.iter_mut().enumerate() {
        row.copy_from_slice(&m[r * 4..r * 4 + 4]);
    }
    Ok(rows)
}

/// A validated `hz_frame`: images described, camera read.
struct FrameDesc {
    color: Described,
    depth: Option<Described>,
    motion: Option<Described>,
    normal: Option<Described>,
    albedo: Option<Described>,
    denoise_normal: Option<Described>,
    coverage: Option<Described>,
    insert_mask: Option<Described>,
    insert_id: Option<Described>,
    camera: Option<Camera>,
    frame_index: Option<i64>,
    reset: bool,
    motion_vector_scale: [f32; 2],
}

impl FrameDesc {
    /// # Safety
    /// `frame` is NULL or a readable `hz_frame` whose pointers follow the contract.
    unsafe fn read(frame: *const hz_frame) -> Result<FrameDesc, Error> {
        check_null!(frame);
        // SAFETY: non-NULL; only the first field is read before the size check.
        let size = unsafe { std::ptr::addr_of!((*frame).struct_size).read_unaligned() };
        check_struct_sizes("hz_frame", size, &FRAME_SIZES)?;
        // SAFETY: readable for the `size` the host set, one of this
        // library's sizes; the fields past it are pointers (NULL when zero).
        let f = unsafe { read_prefix(frame, size) };
        if f.flags & !KNOWN_FLAGS != 0 {
            return Err(Error::invalid(format!(
                "frame.flags {:#x} has unknown bits {:#x}",
                f.flags,
                f.flags & !KNOWN_FLAGS
            )));
        }
        let opt = |what: &str, p: *const hz_image| -> Result<Option<Described>, Error> {
            if p.is_null() {
                Ok(None)
            } else {
                // SAFETY: non-NULL, readable per the contract.
                unsafe { Described::read(what, p) }.map(Some)
            }
        };
        // SAFETY: readable per the contract (NULL is refused inside).
        let color = unsafe { Described::read("color", f.color) }?;
        let camera = match (f.world_to_camera.is_null(), f.world_to_ndc.is_null()) {
            (true, true) => None,
            (false, false) => {
                // SAFETY: non-NULL, 16 floats each per the contract.
                let (w2c, w2n) = unsafe {
                    (
                        read_matrix("world_to_camera", f.world_to_camera)?,
                        read_matrix("world_to_ndc", f.world_to_ndc)?,
                    )
                };
                Some(Camera::from_exr_rows(w2c, w2n))
            }
            _ => {
                return Err(Error::invalid(
                    "frame: world_to_camera and world_to_ndc must both be set or both be NULL",
                ))
            }
        };
        let scale = if f.motion_vector_scale == [0.0, 0.0] {
            [1.0, 1.0]
        } else {
            f.motion_vector_scale
        };
        Ok(FrameDesc {
            color,
            depth: opt("depth", f.depth)?,
            motion: opt("motion", f.motion)?,
            normal: opt("normal", f.normal)?,
            albedo: opt("albedo", f.albedo)?,
            denoise_normal: opt("denoise_normal", f.denoise_normal)?,
            coverage: opt("coverage", f.coverage)?,
            insert_mask: opt("insert_mask", f.insert_mask)?,
            insert_id: opt("insert_id", f.insert_id)?,
            camera,
            frame_index: (f.flags & HZ_FRAME_HAS_INDEX != 0).then_some(f.frame_index),
            reset: f.flags & HZ_FRAME_RESET != 0,
            motion_vector_scale: scale,
        })
    }

    /// The frame's size and the inputs it has, for the memory check made
    /// before any view of the host's buffers exists.
    fn shape(&self) -> FrameShape {
        FrameShape {
            width: self.color.width,
            height: self.color.height,
            depth: self.depth.is_some(),
            motion: self.motion.is_some(),
            normal: self.normal.is_some(),
            albedo: self.albedo.is_some(),
            denoise_normal: self.denoise_normal.is_some(),
            coverage: self.coverage.is_some(),
            insert_mask: self.insert_mask.is_some(),
            insert_id: self.insert_id.is_some(),
        }
    }

    /// Borrows the host's buffers as core views.
    ///
    /// # Safety
    /// Every described buffer is readable and not written while the views live.
    unsafe fn input<'a>(&self) -> Result<FrameInput<'a>, Error> {
        let opt = |what: &str, d: &Option<Described>| -> Result<_, Error> {
            // SAFETY: forwarded contract.
            d.as_ref().map(|d| unsafe { d.view(what) }).transpose()
        };
        // SAFETY: forwarded contract.
        let mut input = FrameInput::new(unsafe { self.color.view("color") }?);
        input.depth = opt("depth", &self.depth)?;
        input.motion = opt("motion", &self.motion)?;
        input.normal = opt("normal", &self.normal)?;
        input.albedo = opt("albedo", &self.albedo)?;
        input.denoise_normal = opt("denoise_normal", &self.denoise_normal)?;
        input.coverage = opt("coverage", &self.coverage)?;
        input.insert_mask = opt("insert_mask", &self.insert_mask)?;
        input.insert_id = opt("insert_id", &self.insert_id)?;
        input.camera = self.camera;
        input.frame_index = self.frame_index;
        input.reset = self.reset;
        input.motion_vector_scale = self.motion_vector_scale;
        Ok(input)
    }
}

/// True when parameters were staged but not committed.
pub(crate) fn uncommitted(s: &Session) -> Option<&'static str> {
    PARAM_NAMES
        .iter()
        .copied()
        .find(|name| s.get(name).ok() != s.params().get(name).ok())
}

/// Enhances one frame into `output` (3 channels RGB or 4 RGBA, F32 or F16,
/// the size of the color image). The output may be the color buffer itself
/// (in place) or overlap any input. On failure (including
/// `HZ_ERROR_CANCELLED`) the output is not written and the temporal state,
/// the report and the parameters are exactly as before the call.
///
/// A frame whose estimated working set (the session's frame-sized buffers
/// and its history at `context_frames`) exceeds the device's
/// `memory_limit`, or without one the machine's memory, is refused with
/// `HZ_ERROR_OUT_OF_MEMORY` (the message names the size, the estimate and
/// the limit) before any buffer is allocated or any input sample read; a
/// buffer the system cannot allocate is the same error, never an abort.
///
/// # Safety
/// `session` is a live handle; `frame` and `output` point to valid structs
/// whose buffers are readable (inputs) and writable (output) for the extent
/// they describe, and are not used by the host during the call.
#[no_mangle]
pub unsafe extern "C" fn hz_session_process(
    session: *mut hz_session,
    frame: *const hz_frame,
    output: *const hz_image,
) -> hz_status {
    ffi_guard!("hz_session_process", {
        // SAFETY: forwarded contract.
        let desc = unsafe { FrameDesc::read(frame) }?;
        // SAFETY: forwarded contract.
        let out = unsafe { Described::read("output", output) }?;
        out.check_output(desc.color.width, desc.color.height)?;
        // SAFETY: forwarded contract.
        let mut s = unsafe { lock(session) }?;
        if let Some(name) = uncommitted(&s.session) {
            return Err(Error::InvalidOperation(format!(
                "parameter {name:?} was set but not committed; call hz_session_commit first"
            )));
        }
        // Before the views exist: a frame too large is refused without
        // touching the host's buffers.
        s.session.check_memory(&desc.shape())?;
        let progress = s.progress;
        let mut on_progress = progress.map(|p| move |v: f64| p.call(v));
        let (image, report) = {
            // The input views live only inside this block: they are gone before
            // the output is written, so the output may alias them.
            // SAFETY: forwarded contract.
            let input = unsafe { desc.input() }?;
            s.session.process(
                &input,
                on_progress
                    .as_mut()
                    .map(|f| f as &mut dyn FnMut(f64) -> bool),
            )?
        };
        // SAFETY: writable for its validated extent per the contract; no
        // reference to the host's buffers is alive.
        unsafe { out.write(&image) };
        s.session.recycle(image);
        if let Some(m) = s.message {
            // Frame gaps already come with a warning from the core.
            let reset = report
                .reset
                .filter(|r| !matches!(r, ResetReason::FirstFrame | ResetReason::FrameGap));
            if let Some(r) = reset {
                let idx = report
                    .frame_index
                    .map_or("?".to_string(), |i| i.to_string());
                m.call(
                    hz_message_level::HZ_MESSAGE_INFO,
                    &format!("frame {idx}: temporal state reset ({})", r.name()),
                );
            }
            for w in &report.warnings {
                m.call(hz_message_level::HZ_MESSAGE_WARNING, w);
            }
        }
        s.report = Some(report);
        Ok(())
    })
}

/// Reads a `usize` query under the session lock.
unsafe fn query(
    session: *const hz_session,
    out: *mut usize,
    f: impl FnOnce(&State) -> Result<usize, Error>,
) -> crate::FfiResult {
    check_null!(out);
    // SAFETY: forwarded contract.
    let s = unsafe { lock(session) }?;
    let v = f(&s)?;
    // SAFETY: writable per the contract.
    unsafe { out.write(v) };
    Ok(())
}

/// History frames held (0 after a reset, up to `context_frames`).
///
/// # Safety
/// `session` is a live handle; `out_length` writable.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_history_length(
    session: *const hz_session,
    out_length: *mut usize,
) -> hz_status {
    ffi_guard!("hz_session_get_history_length", {
        // SAFETY: forwarded contract.
        unsafe { query(session, out_length, |s| Ok(s.session.history_len())) }
    })
}

/// Bytes of temporal state the session holds.
///
/// # Safety
/// `session` is a live handle; `out_bytes` writable.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_memory_bytes(
    session: *const hz_session,
    out_bytes: *mut usize,
) -> hz_status {
    ffi_guard!("hz_session_get_memory_bytes", {
        // SAFETY: forwarded contract.
        unsafe { query(session, out_bytes, |s| Ok(s.session.memory_bytes())) }
    })
}

/// Overlap of neural tiles in pixels (the committed `tile_overlap`; 0 = the
/// model manifest's).
///
/// # Safety
/// `session` is a live handle; `out_pixels` writable.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_tile_overlap(
    session: *const hz_session,
    out_pixels: *mut usize,
) -> hz_status {
    ffi_guard!("hz_session_get_tile_overlap", {
        // SAFETY: forwarded contract.
        unsafe { query(session, out_pixels, |s| Ok(s.session.params().tile_overlap)) }
    })
}

/// Reads a string query under the session lock into a caller's buffer.
unsafe fn query_str(
    session: *const hz_session,
    buffer: *mut c_char,
    size: usize,
    length: *mut usize,
    f: impl FnOnce(&State) -> Result<String, Error>,
) -> crate::FfiResult {
    let text = {
        // SAFETY: forwarded contract.
        let s = unsafe { lock(session) }?;
        f(&s)?
    };
    // SAFETY: forwarded contract.
    unsafe { write_str(&text, buffer, size, length) }
}

/// The model in use: (name, version), empty when the backend is not neural.
fn model_info(s: &Session) -> Result<(String, String), Error> {
    if s.backend_name() == "neural" {
        if let Some(m) = s.device().neural_model()? {
            return Ok((m.name.clone(), m.version.clone()));
        }
    }
    Ok((String::new(), String::new()))
}

/// The backend that runs (`"neural"`, `"classical"`, `"bypass"`).
///
/// # Safety
/// `session` is a live handle; `buffer` NULL or writable for `buffer_size`
/// bytes; `out_length` NULL or writable.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_backend_name(
    session: *const hz_session,
    buffer: *mut c_char,
    buffer_size: usize,
    out_length: *mut usize,
) -> hz_status {
    ffi_guard!("hz_session_get_backend_name", {
        // SAFETY: forwarded contract.
        unsafe {
            query_str(session, buffer, buffer_size, out_length, |s| {
                Ok(s.session.backend_name().to_string())
            })
        }
    })
}

/// The neural model's name from its manifest; empty when the backend is not neural.
///
/// # Safety
/// As `hz_session_get_backend_name`.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_model_name(
    session: *const hz_session,
    buffer: *mut c_char,
    buffer_size: usize,
    out_length: *mut usize,
) -> hz_status {
    ffi_guard!("hz_session_get_model_name", {
        // SAFETY: forwarded contract.
        unsafe {
            query_str(session, buffer, buffer_size, out_length, |s| {
                Ok(model_info(&s.session)?.0)
            })
        }
    })
}

/// The neural model's version from its manifest; empty when the backend is not neural.
///
/// # Safety
/// As `hz_session_get_backend_name`.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_model_version(
    session: *const hz_session,
    buffer: *mut c_char,
    buffer_size: usize,
    out_length: *mut usize,
) -> hz_status {
    ffi_guard!("hz_session_get_model_version", {
        // SAFETY: forwarded contract.
        unsafe {
            query_str(session, buffer, buffer_size, out_length, |s| {
                Ok(model_info(&s.session)?.1)
            })
        }
    })
}

fn last_report(s: &State) -> Result<&FrameReport, Error> {
    s.report.as_ref().ok_or_else(|| {
        Error::InvalidOperation("no frame has been processed by this session yet".into())
    })
}

/// The report of the last successfully processed frame.
/// `HZ_ERROR_INVALID_OPERATION` before the first frame.
///
/// # Safety
/// `session` is a live handle; `out_report` points to an `hz_report` whose
/// `struct_size` the caller has set.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_report(
    session: *const hz_session,
    out_report: *mut hz_report,
) -> hz_status {
    ffi_guard!("hz_session_get_report", {
        check_null!(out_report);
        // SAFETY: non-NULL; the caller set `struct_size`.
        let size = unsafe { std::ptr::addr_of!((*out_report).struct_size).read_unaligned() };
        check_struct_sizes("hz_report", size, &REPORT_SIZES)?;
        // SAFETY: forwarded contract.
        let s = unsafe { lock(session) }?;
        let r = last_report(&s)?;
        let out = hz_report {
            struct_size: size,
            frame_index: r.frame_index.unwrap_or(0),
            has_frame_index: r.frame_index.is_some(),
            reset_reason: hz_reset_reason::of(r.reset),
            history_used: r.history_used,
            sanitized: r.sanitized,
            warning_count: r.warnings.len(),
            total_ms: r.total_ms,
            denoised: r.denoised,
            has_noise_level: r.noise_level.is_some(),
            noise_level: r.noise_level.unwrap_or(0.0),
        };
        // SAFETY: writable for the `size` the host set (checked above: one
        // of this library's sizes of `hz_report`, at most its `sizeof`).
        unsafe { write_prefix(out_report, &out, size) };
        Ok(())
    })
}

/// One warning of the last frame's report (`index < warning_count`).
///
/// # Safety
/// As `hz_session_get_backend_name`.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_report_warning(
    session: *const hz_session,
    index: usize,
    buffer: *mut c_char,
    buffer_size: usize,
    out_length: *mut usize,
) -> hz_status {
    ffi_guard!("hz_session_get_report_warning", {
        // SAFETY: forwarded contract.
        unsafe {
            query_str(session, buffer, buffer_size, out_length, |s| {
                let r = last_report(s)?;
                r.warnings.get(index).cloned().ok_or_else(|| {
                    Error::invalid(format!(
                        "warning index {index} is out of range (the report has {})",
                        r.warnings.len()
                    ))
                })
            })
        }
    })
}

/// What the denoise stage decided for the sequence and why, on the frame
/// where it decided (the first after a reset other than a scene cut), for
/// example `denoise on` or `denoise auto: on (noise level 0.930 on frame 1,
/// threshold 0.20)`; empty on the other frames.
///
/// # Safety
/// As `hz_session_get_backend_name`.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_report_denoise_decision(
    session: *const hz_session,
    buffer: *mut c_char,
    buffer_size: usize,
    out_length: *mut usize,
) -> hz_status {
    ffi_guard!("hz_session_get_report_denoise_decision", {
        // SAFETY: forwarded contract.
        unsafe {
            query_str(session, buffer, buffer_size, out_length, |s| {
                Ok(last_report(s)?.denoise_decision.clone().unwrap_or_default())
            })
        }
    })
}

/// The last frame's report as JSON: `{"frame_index", "reset", "backend",
/// "history_used", "sanitized", "out_of_gamut", "denoised",
/// "denoise_decision", "noise_level", "warnings": [..], "stages": {name: ms},
/// "total_ms"}` (`reset` is null or a name such as `"frame_gap"`;
/// `denoise_decision` and `noise_level` are null except on the frame where
/// the denoise stage decided, see `hz_report`).
///
/// # Safety
/// As `hz_session_get_backend_name`.
#[no_mangle]
pub unsafe extern "C" fn hz_session_get_report_json(
    session: *const hz_session,
    buffer: *mut c_char,
    buffer_size: usize,
    out_length: *mut usize,
) -> hz_status {
    ffi_guard!("hz_session_get_report_json", {
        // SAFETY: forwarded contract.
        unsafe {
            query_str(session, buffer, buffer_size, out_length, |s| {
                Ok(report_json(last_report(s)?))
            })
        }
    })
}

/// The JSON form of a report.
pub fn report_json(r: &FrameReport) -> String {
    let mut m = r.json_fields();
    m.insert("frame_index".into(), serde_json::json!(r.frame_index));
    m.insert("warnings".into(), serde_json::json!(r.warnings));
    m.insert("total_ms".into(), serde_json::json!(r.total_ms));
    serde_json::Value::Object(m).to_string()
}
