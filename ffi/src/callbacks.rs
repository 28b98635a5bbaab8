//! Host callbacks: progress (with cancellation) and messages (warnings).
//!
//! Callbacks run on the thread that called `hz_session_process`, while the
//! session's lock is held: they must not call functions on the same session
//! (such a call fails with `HZ_ERROR_INVALID_OPERATION`) and must not unwind
//! (C++ exceptions, longjmp) through the library.

use std::ffi::{c_char, c_void, CString};

/// Progress callback: `progress` is monotonic in [0, 1]; return false to
/// cancel (the call then returns `HZ_ERROR_CANCELLED` and the session's state
/// is exactly as before the call).
pub type hz_progress_fn = Option<unsafe extern "C" fn(user: *mut c_void, progress: f64) -> bool>;

/// Message callback: `level` is one of `hz_message_level`; `text` is valid
/// during the call only.
pub type hz_message_fn =
    Option<unsafe extern "C" fn(user: *mut c_void, level: u32, text: *const c_char)>;

/// Severity of a message.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum hz_message_level {
    /// Information (for example why the temporal state was reset).
    HZ_MESSAGE_INFO = 1,
    /// A suspicious input (NaN color, a non-consecutive frame index, ...).
    HZ_MESSAGE_WARNING = 2,
}

/// A callback with its user pointer, stored in a session.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Callback<F> {
    pub func: F,
    pub user: *mut c_void,
}

// SAFETY: the host registers the callback for a session it may use from any
// thread; the library calls it only on the thread of a call on that session,
// one call at a time (the session lock), which is what the contract states.
unsafe impl<F: Send> Send for Callback<F> {}

impl Callback<unsafe extern "C" fn(*mut c_void, f64) -> bool> {
    /// Calls the progress callback.
    pub fn call(&self, p: f64) -> bool {
        // SAFETY: a function pointer the host registered, called with its own
        // user pointer, as documented.
        unsafe { (self.func)(self.user, p) }
    }
}

impl Callback<unsafe extern "C" fn(*mut c_void, u32, *const c_char)> {
    /// Calls the message callback.
    pub fn call(&self, level: hz_message_level, text: &str) {
        let c = CString::new(text.replace('\0', "\\0")).unwrap_or_default();
        // SAFETY: as above; `c` outlives the call.
        unsafe { (self.func)(self.user, level as u32, c.as_ptr()) }
    }
}

/// The progress callback as stored.
pub(crate) type Progress = Callback<unsafe extern "C" fn(*mut c_void, f64) -> bool>;
/// The message callback as stored.
pub(crate) type Message = Callback<unsafe extern "C" fn(*mut c_void, u32, *const c_char)>;
