//! libharmonizer: the C ABI of harmonizer.
//!
//! The contract (also in `ffi/README.md` and `ARCHITECTURE.md`):
//! - objects are opaque handles (`hz_device`, `hz_session`) created by a
//!   `_new` function and destroyed by the matching `_free`;
//! - every function returns an [`hz_status`]; on failure
//!   [`hz_last_error_message`] explains it (per thread), outputs are left
//!   untouched or set to NULL, and no state changes (no partial success);
//! - `const` pointers are read only; outputs come last;
//! - per-call structs (`hz_image`, `hz_frame`, `hz_report`,
//!   `hz_device_options`) start with `struct_size`, which the caller sets to
//!   `sizeof` of the struct; a struct grows only by appended fields, and
//!   the size an older header gave it stays accepted (`hz_frame`,
//!   `hz_report`): the fields it lacks read as zero and are not written;
//! - parameters are set by name, so adding one never changes the ABI;
//! - calls on different sessions may run concurrently; calls on one session
//!   are serialized by a lock inside the handle.
//!
//! All `unsafe` code of the project lives in this crate, each block with a
//! `// SAFETY:` comment. Every exported function runs inside [`ffi_guard!`],
//! so no panic crosses the boundary.
#![allow(non_camel_case_types)]
#![deny(missing_docs)]

pub mod callbacks;
pub mod device;
pub mod image;
pub mod run;
pub mod session;

use std::cell::RefCell;
use std::ffi::{c_char, CStr, CString};

use harmonizer_core::Error;

/// Result type of the bodies of exported functions.
pub(crate) type FfiResult = Result<(), Error>;

/// Status code returned by every function. Values are explicit and never reused.
#[repr(u32)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum hz_status {
    /// Success.
    HZ_OK = 0,
    /// A bad argument or bad input data (NULL pointer, size, stride, channel, value range).
    HZ_ERROR_INVALID_ARGUMENT = 1,
    /// The call is not allowed in the object's current state.
    HZ_ERROR_INVALID_OPERATION = 2,
    /// A buffer could not be allocated within the memory limit: a frame
    /// whose working set exceeds the device's `memory_limit` (or the
    /// machine's memory), or an allocation the system refused.
    HZ_ERROR_OUT_OF_MEMORY = 3,
    /// The model or its manifest is missing, malformed or incompatible.
    HZ_ERROR_MODEL = 4,
    /// The ONNX Runtime shared library could not be found or loaded.
    HZ_ERROR_RUNTIME_MISSING = 5,
    /// The progress callback returned false; the session's state is unchanged.
    HZ_ERROR_CANCELLED = 6,
    /// An internal error (a bug); the message says where.
    HZ_ERROR_UNKNOWN = 7,
    /// Reading or writing a file failed.
    HZ_ERROR_IO = 8,
    /// The input uses something this build does not support.
    HZ_ERROR_NOT_SUPPORTED = 9,
}

impl hz_status {
    /// The status for a core error (one to one).
    pub fn of(e: &Error) -> hz_status {
        match e {
            Error::Invalid(_) => hz_status::HZ_ERROR_INVALID_ARGUMENT,
            Error::InvalidOperation(_) => hz_status::HZ_ERROR_INVALID_OPERATION,
            Error::NotSupported(_) => hz_status::HZ_ERROR_NOT_SUPPORTED,
            Error::Io(_) => hz_status::HZ_ERROR_IO,
            Error::OutOfMemory(_) => hz_status::HZ_ERROR_OUT_OF_MEMORY,
            Error::Model(_) => hz_status::HZ_ERROR_MODEL,
            Error::RuntimeMissing(_) => hz_status::HZ_ERROR_RUNTIME_MISSING,
            Error::Cancelled(_) => hz_status::HZ_ERROR_CANCELLED,
        }
    }

    /// The status's name as in the header.
    pub fn name(self) -> &'static CStr {
        match self {
            hz_status::HZ_OK => c"HZ_OK",
            hz_status::HZ_ERROR_INVALID_ARGUMENT => c"HZ_ERROR_INVALID_ARGUMENT",
            hz_status::HZ_ERROR_INVALID_OPERATION => c"HZ_ERROR_INVALID_OPERATION",
            hz_status::HZ_ERROR_OUT_OF_MEMORY => c"HZ_ERROR_OUT_OF_MEMORY",
            hz_status::HZ_ERROR_MODEL => c"HZ_ERROR_MODEL",
            hz_status::HZ_ERROR_RUNTIME_MISSING => c"HZ_ERROR_RUNTIME_MISSING",
            hz_status::HZ_ERROR_CANCELLED => c"HZ_ERROR_CANCELLED",
            hz_status::HZ_ERROR_UNKNOWN => c"HZ_ERROR_UNKNOWN",
            hz_status::HZ_ERROR_IO => c"HZ_ERROR_IO",
            hz_status::HZ_ERROR_NOT_SUPPORTED => c"HZ_ERROR_NOT_SUPPORTED",
        }
    }

    fn from_u32(v: u32) -> Option<hz_status> {
        use hz_status::*;
        [
            HZ_OK,
            HZ_ERROR_INVALID_ARGUMENT,
            HZ_ERROR_INVALID_OPERATION,
            HZ_ERROR_OUT_OF_MEMORY,
            HZ_ERROR_MODEL,
            HZ_ERROR_RUNTIME_MISSING,
            HZ_ERROR_CANCELLED,
            HZ_ERROR_UNKNOWN,
            HZ_ERROR_IO,
            HZ_ERROR_NOT_SUPPORTED,
        ]
        .into_iter()
        .find(|s| *s as u32 == v)
    }
}

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

/// Records `msg` as this thread's last error.
pub(crate) fn set_last_error(msg: String) {
    let c = CString::new(msg.replace('\0', "\\0")).unwrap_or_default();
    LAST_ERROR.with(|e| *e.borrow_mut() = c);
}

/// Records a failure of `func` and returns its status.
#[doc(hidden)]
pub fn fail(func: &str, e: Error) -> hz_status {
    set_last_error(format!("{func}: {e}"));
    hz_status::of(&e)
}

/// Records a panic caught in `func` and returns `HZ_ERROR_UNKNOWN`.
#[doc(hidden)]
pub fn fail_panic(func: &str, payload: Box<dyn std::any::Any + Send>) -> hz_status {
    let what = payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into());
    set_last_error(format!("{func}: internal error (please report): {what}"));
    hz_status::HZ_ERROR_UNKNOWN
}

/// The panic boundary every exported function runs in: the body returns
/// `Result<(), Error>`; errors become a status plus this thread's last error
/// message (prefixed with the function's name), panics become
/// `HZ_ERROR_UNKNOWN`.
#[macro_export]
#[doc(hidden)]
macro_rules! ffi_guard {
    ($func:literal, $body:block) => {{
        let r =
            ::std::panic::catch_unwind(::std::panic::AssertUnwindSafe(|| -> $crate::FfiResult {
                $body
            }));
        match r {
            Ok(Ok(())) => $crate::hz_status::HZ_OK,
            Ok(Err(e)) => $crate::fail($func, e),
            Err(p) => $crate::fail_panic($func, p),
        }
    }};
}

/// Returns `HZ_ERROR_INVALID_ARGUMENT` naming the argument when a pointer is NULL.
#[macro_export]
#[doc(hidden)]
macro_rules! check_null {
    ($($ptr:ident),+ $(,)?) => {
        $(
            if $ptr.is_null() {
                return Err(::harmonizer_core::Error::invalid(concat!(stringify!($ptr), " is NULL")));
            }
        )+
    };
}

/// Checks a caller's `struct_size` against this library's `sizeof`.
pub(crate) fn check_struct_size(what: &str, got: usize, want: usize) -> FfiResult {
    check_struct_sizes(what, got, &[want])
}

/// Checks a caller's `struct_size` for a struct that grew by appending
/// fields: `sizes` are the `sizeof` each header version gave it, oldest
/// first, this library's last.
pub(crate) fn check_struct_sizes(what: &str, got: usize, sizes: &[usize]) -> FfiResult {
    if sizes.contains(&got) {
        return Ok(());
    }
    let (want, older) = sizes.split_last().expect("at least this library's size");
    let older = match older {
        [] => String::new(),
        _ => format!(
            "; an older header's {} is also accepted",
            older
                .iter()
                .map(|s| s.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    Err(Error::invalid(format!(
        "{what}.struct_size is {got}, expected {want} (set it to sizeof({what}){older}; \
         another value means the header and the library differ)"
    )))
}

/// The `sizeof` an older header gave `T` when its fields ended where the
/// field at offset `first_new` (`offset_of!`) now starts: that offset
/// rounded up to `T`'s alignment. Holds because the appended fields are
/// no more aligned than the older ones.
pub(crate) const fn older_size<T>(first_new: usize) -> usize {
    let align = std::mem::align_of::<T>();
    first_new.div_ceil(align) * align
}

/// Reads the first `size` bytes of a struct a host passed (a size
/// [`check_struct_sizes`] accepted); the fields after them, which the
/// host's header did not have, are zero (NULL, 0, false: absent or default).
///
/// # Safety
/// `p` is readable for `size` bytes, `size <= size_of::<T>()`, and the
/// all-zero bit pattern is a valid `T`.
pub(crate) unsafe fn read_prefix<T: Copy>(p: *const T, size: usize) -> T {
    debug_assert!(size <= std::mem::size_of::<T>());
    let mut v = std::mem::MaybeUninit::<T>::zeroed();
    // SAFETY: `p` is readable for `size` bytes and `v` is writable for
    // `size_of::<T>() >= size`; bytes need no alignment; the bytes not
    // copied are zero, valid per the contract.
    unsafe {
        std::ptr::copy_nonoverlapping(p.cast::<u8>(), v.as_mut_ptr().cast::<u8>(), size);
        v.assume_init()
    }
}

/// Writes the first `size` bytes of `value` to a struct the host passed
/// (a size [`check_struct_sizes`] accepted): an older host gets the fields
/// its header has and nothing is written past them.
///
/// # Safety
/// `out` is writable for `size` bytes and `size <= size_of::<T>()`.
pub(crate) unsafe fn write_prefix<T: Copy>(out: *mut T, value: &T, size: usize) {
    debug_assert!(size <= std::mem::size_of::<T>());
    // SAFETY: readable (`value`) and writable (`out`) for `size` bytes, no
    // overlap (`value` is the library's own); bytes need no alignment.
    unsafe {
        std::ptr::copy_nonoverlapping((value as *const T).cast::<u8>(), out.cast::<u8>(), size)
    };
}

/// Reads a NUL-terminated UTF-8 string argument.
///
/// # Safety
/// `p` is NULL or points to a NUL-terminated string valid for the call.
pub(crate) unsafe fn read_str<'a>(what: &str, p: *const c_char) -> Result<&'a str, Error> {
    if p.is_null() {
        return Err(Error::invalid(format!("{what} is NULL")));
    }
    // SAFETY: non-NULL and NUL-terminated per the caller's contract.
    let c = unsafe { CStr::from_ptr(p) };
    c.to_str().map_err(|_| {
        Error::invalid(format!(
            "{what}: {:?} is not valid UTF-8",
            c.to_string_lossy()
        ))
    })
}

/// Copies `s` into a caller's buffer: `length` (optional) receives the length
/// without the terminating NUL; `buffer` may be NULL to ask for the length only.
///
/// # Safety
/// `buffer` is NULL or valid for `size` bytes; `length` is NULL or valid.
pub(crate) unsafe fn write_str(
    s: &str,
    buffer: *mut c_char,
    size: usize,
    length: *mut usize,
) -> FfiResult {
    if !length.is_null() {
        // SAFETY: non-NULL, valid per the caller's contract.
        unsafe { length.write(s.len()) };
    }
    if buffer.is_null() {
        return Ok(());
    }
    if size <= s.len() {
        return Err(Error::invalid(format!(
            "buffer of {size} bytes is too small for {} bytes plus the terminating NUL",
            s.len()
        )));
    }
    // SAFETY: `buffer` holds `size > s.len()` bytes; the regions cannot overlap
    // because `s` is owned by the library.
    unsafe {
        std::ptr::copy_nonoverlapping(s.as_ptr(), buffer.cast::<u8>(), s.len());
        buffer.add(s.len()).write(0);
    }
    Ok(())
}

/// The message of the last call on this thread that failed (empty if none).
/// The pointer stays valid until the next failing call on this thread.
#[no_mangle]
pub extern "C" fn hz_last_error_message() -> *const c_char {
    LAST_ERROR.with(|e| e.borrow().as_ptr())
}

/// The name of a status code (`"HZ_ERROR_IO"`), or `"unknown status"`.
#[no_mangle]
pub extern "C" fn hz_status_name(status: u32) -> *const c_char {
    hz_status::from_u32(status).map_or(c"unknown status".as_ptr(), |s| s.name().as_ptr())
}

static VERSION: &CStr =
    match CStr::from_bytes_with_nul(concat!(env!("CARGO_PKG_VERSION"), "\0").as_bytes()) {
        Ok(v) => v,
        Err(_) => panic!("version contains NUL"),
    };

/// The library version (`"MAJOR.MINOR.PATCH"`), static.
#[no_mangle]
pub extern "C" fn hz_version() -> *const c_char {
    VERSION.as_ptr()
}

/// The library's (major, minor, patch) version from `Cargo.toml`.
pub fn version_numbers() -> (u32, u32, u32) {
    let p = |s: &str| s.parse::<u32>().unwrap_or(0);
    (
        p(env!("CARGO_PKG_VERSION_MAJOR")),
        p(env!("CARGO_PKG_VERSION_MINOR")),
        p(env!("CARGO_PKG_VERSION_PATCH")),
    )
}

/// Checks that a host compiled against a header of version `major.minor`
/// (pass `HZ_VERSION_MAJOR, HZ_VERSION_MINOR`) can use this library: the
/// major versions must match and the library must be at least as new as the
/// header. `HZ_ERROR_NOT_SUPPORTED` otherwise.
#[no_mangle]
pub extern "C" fn hz_check_version(major: u32, minor: u32) -> hz_status {
    ffi_guard!("hz_check_version", { check_version(major, Some(minor)) })
}

pub(crate) fn check_version(major: u32, minor: Option<u32>) -> FfiResult {
    let (lib_major, lib_minor, _) = version_numbers();
    if major != lib_major {
        return Err(Error::NotSupported(format!(
            "the host was built against harmonizer.h major version {major}, \
             this library is {} (major {lib_major}); rebuild the host against this library's header",
            env!("CARGO_PKG_VERSION")
        )));
    }
    if let Some(minor) = minor {
        if minor > lib_minor {
            return Err(Error::NotSupported(format!(
                "the host was built against harmonizer.h {major}.{minor}, \
                 this library is older ({}); install a newer library",
                env!("CARGO_PKG_VERSION")
            )));
        }
    }
    Ok(())
}
