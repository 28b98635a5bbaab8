//! The Open Image Denoise C API, resolved by name from the shared library
//! with `libloading`: the library, one CPU device ([`Oidn`]) and RT filters
//! ([`Filter`]).
//!
//! This file holds the only `unsafe` code of `harmonizer-core` (the crate
//! denies `unsafe_code` and allows it for this module alone). Every block
//! says why it is sound; the safe wrappers check what the C API cannot
//! (slice lengths, sizes, which images a filter still points at) before
//! calling into C.
//!
//! The declarations follow OIDN 2.x's `oidn.h` (checked against the cffi
//! declarations of the `pyoidn` wheel): enums are C `int`, `bool` is C99
//! `_Bool`, sizes are `size_t`.

use std::ffi::{c_char, c_int, c_void, CStr};
use std::path::{Path, PathBuf};
use std::ptr::NonNull;
use std::sync::{Arc, Mutex};

use crate::error::{Error, Result};

type RawDevice = *mut c_void;
type RawFilter = *mut c_void;

/// `OIDN_DEVICE_TYPE_CPU`.
const DEVICE_TYPE_CPU: c_int = 1;
/// `OIDN_FORMAT_FLOAT3`.
const FORMAT_FLOAT3: c_int = 3;
/// `OIDN_ERROR_UNSUPPORTED_HARDWARE`.
const ERROR_UNSUPPORTED_HARDWARE: c_int = 5;
/// Bytes of one interleaved RGB f32 pixel.
const PIXEL_BYTES: usize = 3 * std::mem::size_of::<f32>();

/// The OIDN functions this module calls, resolved once per library.
struct Api {
    new_device: unsafe extern "C" fn(c_int) -> RawDevice,
    set_device_int: unsafe extern "C" fn(RawDevice, *const c_char, c_int),
    set_device_bool: unsafe extern "C" fn(RawDevice, *const c_char, bool),
    get_device_int: unsafe extern "C" fn(RawDevice, *const c_char) -> c_int,
    commit_device: unsafe extern "C" fn(RawDevice),
    get_device_error: unsafe extern "C" fn(RawDevice, *mut *const c_char) -> c_int,
    release_device: unsafe extern "C" fn(RawDevice),
    new_filter: unsafe extern "C" fn(RawDevice, *const c_char) -> RawFilter,
    set_shared_filter_image: unsafe extern "C" fn(
        RawFilter,
        *const c_char,
        *mut c_void,
        c_int,
        usize,
        usize,
        usize,
        usize,
        usize,
    ),
    unset_filter_image: unsafe extern "C" fn(RawFilter, *const c_char),
    set_filter_bool: unsafe extern "C" fn(RawFilter, *const c_char, bool),
    set_filter_int: unsafe extern "C" fn(RawFilter, *const c_char, c_int),
    commit_filter: unsafe extern "C" fn(RawFilter),
    execute_filter: unsafe extern "C" fn(RawFilter),
    release_filter: unsafe extern "C" fn(RawFilter),
}

/// Resolves `name` in `lib` as a `T`.
///
/// # Safety
/// `T` must be the function pointer type of the C declaration of `name`.
unsafe fn symbol<T: Copy>(
    lib: &libloading::Library,
    name: &CStr,
) -> std::result::Result<T, String> {
    // SAFETY: the caller guarantees that `T` is the symbol's type.
    let sym = unsafe { lib.get::<T>(name) };
    sym.map(|s| *s).map_err(|e| {
        format!(
            "it has no {} ({}): Open Image Denoise 2.x is required",
            name.to_string_lossy(),
            with_sources(&e)
        )
    })
}

impl Api {
    fn resolve(lib: &libloading::Library) -> std::result::Result<Api, String> {
        // SAFETY: each type below is the declaration of that function in
        // OIDN 2.x's `oidn.h`.
        unsafe {
            Ok(Api {
                new_device: symbol(lib, c"oidnNewDevice")?,
                set_device_int: symbol(lib, c"oidnSetDeviceInt")?,
                set_device_bool: symbol(lib, c"oidnSetDeviceBool")?,
                get_device_int: symbol(lib, c"oidnGetDeviceInt")?,
                commit_device: symbol(lib, c"oidnCommitDevice")?,
                get_device_error: symbol(lib, c"oidnGetDeviceError")?,
                release_device: symbol(lib, c"oidnReleaseDevice")?,
                new_filter: symbol(lib, c"oidnNewFilter")?,
                set_shared_filter_image: symbol(lib, c"oidnSetSharedFilterImage")?,
                unset_filter_image: symbol(lib, c"oidnUnsetFilterImage")?,
                set_filter_bool: symbol(lib, c"oidnSetFilterBool")?,
                set_filter_int: symbol(lib, c"oidnSetFilterInt")?,
                commit_filter: symbol(lib, c"oidnCommitFilter")?,
                execute_filter: symbol(lib, c"oidnExecuteFilter")?,
                release_filter: symbol(lib, c"oidnReleaseFilter")?,
            })
        }
    }
}

/// Libraries loaded in this process, by the name they were loaded as
/// (canonical path, or the bare system name). They are never unloaded: the
/// CPU device's TBB worker threads may outlive every device, and unloading
/// code under running threads would crash. So the function pointers stay
/// valid for the life of the process.
static LOADED: Mutex<Vec<(PathBuf, &'static Api)>> = Mutex::new(Vec::new());

/// The file to load for `path`: a path with a directory is resolved
/// through symbolic links, because the loader expands the library's RPATH
/// `$ORIGIN` and OIDN looks for its device modules from the directory it
/// was opened in, not the one the file lies in; a symlink elsewhere to the
/// wheel's library would find neither its `_core` library nor its CPU
/// device. A bare file name is left to the system's loader.
fn real_path(path: &Path) -> PathBuf {
    if path.components().count() > 1 {
        path.canonicalize().unwrap_or_else(|_| path.to_path_buf())
    } else {
        path.to_path_buf()
    }
}

/// Loads the library at `path` (from [`real_path`]) once per process and
/// resolves the API. The error is the loader's or the missing symbol's
/// message, without the path.
fn load(path: &Path) -> std::result::Result<&'static Api, String> {
    let mut loaded = LOADED.lock().unwrap_or_else(|p| p.into_inner());
    if let Some((_, api)) = loaded.iter().find(|(k, _)| k == path) {
        return Ok(api);
    }
    // SAFETY: loading runs the library's initializers; Open Image Denoise's
    // (and those of its `_core` library and TBB, found through its RPATH
    // `$ORIGIN/../lib`) only set up static data. A file that is not a
    // shared library is refused by the loader with an error.
    let lib = unsafe { libloading::Library::new(path) }.map_err(|e| with_sources(&e))?;
    let api = Api::resolve(&lib)?;
    // Kept loaded for the life of the process (see `LOADED`).
    std::mem::forget(lib);
    let api: &'static Api = Box::leak(Box::new(api));
    loaded.push((path.to_path_buf(), api));
    Ok(api)
}

/// Whether OIDN's CPU device module lies beside the library at `path`
/// (`None` for a bare name: the system's loader knows where it is).
fn cpu_module_beside(path: &Path) -> Option<bool> {
    let dir = path.parent().filter(|d| !d.as_os_str().is_empty())?;
    let entries = std::fs::read_dir(dir).ok()?;
    Some(entries.flatten().any(|e| {
        e.file_name()
            .to_string_lossy()
            .starts_with("libOpenImageDenoise_device_cpu.so")
    }))
}

/// An error's message followed by those of its sources (libloading's
/// `dlopen failed` carries the loader's message as its source).
fn with_sources(e: &dyn std::error::Error) -> String {
    let mut text = e.to_string();
    let mut next = e.source();
    while let Some(s) = next {
        text.push_str(": ");
        text.push_str(&s.to_string());
        next = s.source();
    }
    text
}

/// The name of an `OIDNError` code.
fn error_name(code: c_int) -> &'static str {
    match code {
        1 => "OIDN_ERROR_UNKNOWN",
        2 => "OIDN_ERROR_INVALID_ARGUMENT",
        3 => "OIDN_ERROR_INVALID_OPERATION",
        4 => "OIDN_ERROR_OUT_OF_MEMORY",
        5 => "OIDN_ERROR_UNSUPPORTED_HARDWARE",
        6 => "OIDN_ERROR_CANCELLED",
        _ => "an unknown OIDN error code",
    }
}

/// The crate error for an OIDN error code, with `message` as its text.
fn error_of(code: c_int, message: String) -> Error {
    match code {
        2 => Error::Invalid(message),
        4 => Error::OutOfMemory(message),
        5 => Error::NotSupported(message),
        6 => Error::Cancelled(message),
        // 1 (unknown) and 3 (invalid operation): the library refused the
        // call in its current state.
        _ => Error::InvalidOperation(message),
    }
}

/// Takes the calling thread's first unqueried error of `device` (NULL: of
/// device creation). OIDN keeps errors per thread, so this must run on the
/// thread that made the failing call, before any other call on it.
fn take_error(api: &Api, device: RawDevice) -> Option<(c_int, String)> {
    let mut msg: *const c_char = std::ptr::null();
    // SAFETY: `device` is NULL or a live device handle; `msg` is a valid
    // place for the message pointer.
    let code = unsafe { (api.get_device_error)(device, &mut msg) };
    if code == 0 {
        return None;
    }
    let text = if msg.is_null() {
        String::from("(no message)")
    } else {
        // SAFETY: OIDN returns a NUL-terminated string that stays valid
        // until the next API call on this thread; it is copied at once.
        unsafe { CStr::from_ptr(msg) }
            .to_string_lossy()
            .into_owned()
    };
    Some((code, text))
}

/// The Open Image Denoise library and one committed CPU device, shared
/// (through `Arc`) by the [`Denoiser`](super::Denoiser)s on it. `Send` and
/// `Sync`: OIDN's API is thread-safe; calls on one device are serialized by
/// the library.
pub struct Oidn {
    api: &'static Api,
    device: NonNull<c_void>,
    library: PathBuf,
    threads: usize,
    version: c_int,
}

// SAFETY (both): OIDN's API is thread-safe ("All API calls are
// thread-safe, but operations that use the same device will be
// serialized", OIDN's API documentation) and a device is not tied to the
// thread that made it. OIDN keeps errors per thread; `Oidn::check` reads
// them on the thread that made the call, right after it. The only call
// into C through `&self` is `oidnNewFilter` (`Filter::new`); the rest
// goes through `&mut Filter` or `Drop`.
unsafe impl Send for Oidn {}
// SAFETY: see `Send` above.
unsafe impl Sync for Oidn {}

impl std::fmt::Debug for Oidn {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Oidn")
            .field("library", &self.library)
            .field("version", &self.version())
            .field("threads", &self.threads)
            .finish_non_exhaustive()
    }
}

impl Oidn {
    /// Loads the library at `path` (from `from`, for messages) and makes a
    /// CPU device with `threads` worker threads (not pinned to cores).
    pub(super) fn open(path: &Path, from: &str, threads: usize, hint: &str) -> Result<Oidn> {
        let real = real_path(path);
        let api = load(&real).map_err(|e| {
            Error::RuntimeMissing(format!(
                "Open Image Denoise: cannot load {} (from {from}): {e}; {hint}",
                path.display()
            ))
        })?;
        // SAFETY: a plain call; NULL is returned on failure.
        let raw = unsafe { (api.new_device)(DEVICE_TYPE_CPU) };
        let Some(device) = NonNull::new(raw) else {
            let (code, msg) =
                take_error(api, std::ptr::null_mut()).unwrap_or((1, "no message".into()));
            let text = format!(
                "Open Image Denoise ({}): cannot create the CPU device: {msg} ({})",
                real.display(),
                error_name(code)
            );
            // OIDN says "unsupported device type: CPU" both when its CPU
            // device module is missing and when the CPU lacks what it needs.
            return Err(match cpu_module_beside(&real) {
                Some(false) => Error::RuntimeMissing(format!(
                    "{text}: its CPU device module (libOpenImageDenoise_device_cpu.so.*) is not beside it; \
                     OIDN loads it from the library's own directory; {hint}"
                )),
                Some(true) if code == ERROR_UNSUPPORTED_HARDWARE => Error::NotSupported(format!(
                    "{text}: the CPU device module is present, so this CPU is not supported by Open Image \
                     Denoise (x86-64 needs SSE4.1)"
                )),
                None if code == ERROR_UNSUPPORTED_HARDWARE => Error::NotSupported(format!(
                    "{text}: this CPU is not supported or the system's OIDN has no CPU device module; {hint}"
                )),
                _ => Error::RuntimeMissing(format!("{text}; {hint}")),
            });
        };
        // From here on `Drop` releases the device.
        let mut oidn = Oidn {
            api,
            device,
            library: real,
            threads,
            version: 0,
        };
        let count = c_int::try_from(threads)
            .map_err(|_| Error::invalid(format!("threads: {threads} is out of range")))?;
        // SAFETY: a live device; the names are NUL-terminated.
        unsafe {
            (api.set_device_int)(oidn.raw(), c"numThreads".as_ptr(), count);
            // Leave the host's threads alone, as the device's rayon pool does.
            (api.set_device_bool)(oidn.raw(), c"setAffinity".as_ptr(), false);
            (api.commit_device)(oidn.raw());
        }
        oidn.check("committing the CPU device")?;
        // SAFETY: a live, committed device; the name is NUL-terminated.
        oidn.version = unsafe { (api.get_device_int)(oidn.raw(), c"version".as_ptr()) };
        oidn.check("reading the version")?;
        if oidn.version / 10000 != 2 {
            return Err(Error::NotSupported(format!(
                "Open Image Denoise {} ({}): version 2.x is required; {hint}",
                oidn.version(),
                oidn.library.display()
            )));
        }
        Ok(oidn)
    }

    fn raw(&self) -> RawDevice {
        self.device.as_ptr()
    }

    /// Turns the calling thread's pending device error into an error naming
    /// the library and what was being done.
    fn check(&self, during: &str) -> Result<()> {
        match take_error(self.api, self.raw()) {
            None => Ok(()),
            Some((code, msg)) => Err(error_of(
                code,
                format!(
                    "Open Image Denoise ({}) failed {during}: {msg} ({})",
                    self.library.display(),
                    error_name(code)
                ),
            )),
        }
    }

    /// The path the library was loaded from, symbolic links resolved (a
    /// bare file name when the system's loader searched for it).
    pub fn library(&self) -> &Path {
        &self.library
    }

    /// The device's worker threads.
    pub fn threads(&self) -> usize {
        self.threads
    }

    /// The library's version, `major.minor.patch`.
    pub fn version(&self) -> String {
        let v = self.version;
        format!("{}.{}.{}", v / 10000, v / 100 % 100, v % 100)
    }
}

impl Drop for Oidn {
    fn drop(&mut self) {
        // SAFETY: the device is live and released once; every `Filter`
        // holds an `Arc<Oidn>`, so none outlives it.
        unsafe { (self.api.release_device)(self.raw()) };
    }
}

/// The images of an RT filter.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Slot {
    /// `color`: the noisy beauty.
    Color,
    /// `albedo`.
    Albedo,
    /// `normal`.
    Normal,
}

impl Slot {
    const ALL: [Slot; 3] = [Slot::Color, Slot::Albedo, Slot::Normal];

    fn name(self) -> &'static CStr {
        match self {
            Slot::Color => c"color",
            Slot::Albedo => c"albedo",
            Slot::Normal => c"normal",
        }
    }

    fn index(self) -> usize {
        self as usize
    }
}

/// One OIDN `RT` filter on an [`Oidn`] device.
///
/// A filter keeps the image pointers it was last given. [`Filter::run`]
/// sets every image it reads (and unsets the ones it does not) before it
/// commits and executes, inside one call that borrows the slices, so the
/// filter never reads memory it was not lent for that call.
///
/// `Send`: OIDN objects are not tied to a thread (see `Oidn`'s `Send`).
/// `Sync`: every method that calls into C takes `&mut self`.
pub(super) struct Filter {
    oidn: Arc<Oidn>,
    raw: NonNull<c_void>,
    /// Which of [`Slot::ALL`] the filter has an image for.
    bound: [bool; 3],
}

// SAFETY: see the type's documentation.
unsafe impl Send for Filter {}
// SAFETY: see the type's documentation.
unsafe impl Sync for Filter {}

impl Filter {
    /// A new `RT` filter.
    pub(super) fn new(oidn: &Arc<Oidn>) -> Result<Filter> {
        // SAFETY: a live device; the type name is NUL-terminated.
        let raw = unsafe { (oidn.api.new_filter)(oidn.raw(), c"RT".as_ptr()) };
        let Some(raw) = NonNull::new(raw) else {
            oidn.check("creating an RT filter")?;
            return Err(Error::InvalidOperation(format!(
                "Open Image Denoise ({}): oidnNewFilter(\"RT\") returned NULL without an error",
                oidn.library.display()
            )));
        };
        Ok(Filter {
            oidn: oidn.clone(),
            raw,
            bound: [false; 3],
        })
    }

    /// Sets a bool parameter (`hdr`, `cleanAux`); takes effect at the next
    /// [`Filter::run`], which reports errors.
    pub(super) fn set_bool(&mut self, name: &CStr, value: bool) {
        // SAFETY: a live filter; the name is NUL-terminated.
        unsafe { (self.oidn.api.set_filter_bool)(self.raw.as_ptr(), name.as_ptr(), value) };
    }

    /// Sets an int parameter (`quality`); as [`Filter::set_bool`].
    pub(super) fn set_int(&mut self, name: &CStr, value: i32) {
        // SAFETY: a live filter; the name is NUL-terminated.
        unsafe { (self.oidn.api.set_filter_int)(self.raw.as_ptr(), name.as_ptr(), value) };
    }

    /// Filters `width` x `height` interleaved RGB f32 images: `inputs`
    /// (each slot at most once) into `output`. Every slice must hold
    /// exactly `width * height * 3` values. Images not in `inputs` are
    /// unset. `during` names the step for error messages.
    pub(super) fn run(
        &mut self,
        width: usize,
        height: usize,
        inputs: &[(Slot, &[f32])],
        output: &mut [f32],
        during: &str,
    ) -> Result<()> {
        // The checks that make the calls below sound, whatever the caller.
        let values = width
            .checked_mul(height)
            .and_then(|p| p.checked_mul(3))
            .filter(|_| width > 0 && height > 0)
            .ok_or_else(|| Error::invalid(format!("{during}: bad image size {width}x{height}")))?;
        let lengths_ok = output.len() == values && inputs.iter().all(|(_, d)| d.len() == values);
        let mut wanted = [false; 3];
        for (slot, _) in inputs {
            if std::mem::replace(&mut wanted[slot.index()], true) {
                return Err(Error::invalid(format!(
                    "{during}: image {slot:?} given twice"
                )));
            }
        }
        if !lengths_ok {
            return Err(Error::invalid(format!(
                "{during}: every image must hold {width}x{height}x3 = {values} values"
            )));
        }
        // The slices exist, so `values * 4` bytes fit in `isize`.
        let row_bytes = width * PIXEL_BYTES;
        let api = self.oidn.api;
        let filter = self.raw.as_ptr();
        for slot in Slot::ALL {
            if self.bound[slot.index()] && !wanted[slot.index()] {
                // SAFETY: a live filter; the name is NUL-terminated.
                unsafe { (api.unset_filter_image)(filter, slot.name().as_ptr()) };
                self.bound[slot.index()] = false;
            }
        }
        // SAFETY: a live filter; the names are NUL-terminated. Each image
        // is `width` x `height` FLOAT3 pixels, 12 bytes apart, rows
        // `row_bytes` apart, from offset 0: exactly the slice's length, so
        // every access is in bounds. OIDN only reads `color`, `albedo` and
        // `normal` (an input is written only when it is also the output,
        // and `output` is a `&mut` borrow that overlaps none of them), so
        // the `*mut` cast of a shared slice is never written through. The
        // memory is touched only inside `oidnExecuteFilter`, which returns
        // when the work is done (the synchronous call), while this function
        // still borrows every slice; the pointers the filter keeps
        // afterwards are replaced or unset at the next `run` before it
        // executes again, and nothing else executes the filter.
        unsafe {
            for (slot, data) in inputs {
                (api.set_shared_filter_image)(
                    filter,
                    slot.name().as_ptr(),
                    data.as_ptr().cast_mut().cast(),
                    FORMAT_FLOAT3,
                    width,
                    height,
                    0,
                    PIXEL_BYTES,
                    row_bytes,
                );
                self.bound[slot.index()] = true;
            }
            (api.set_shared_filter_image)(
                filter,
                c"output".as_ptr(),
                output.as_mut_ptr().cast(),
                FORMAT_FLOAT3,
                width,
                height,
                0,
                PIXEL_BYTES,
                row_bytes,
            );
            (api.commit_filter)(filter);
        }
        self.oidn.check(&format!(
            "committing the filter for {during} ({width}x{height})"
        ))?;
        // SAFETY: as above: the filter is committed with images that are
        // all borrowed for this call.
        unsafe { (api.execute_filter)(filter) };
        self.oidn.check(&format!(
            "executing the filter for {during} ({width}x{height})"
        ))
    }
}

impl Drop for Filter {
    fn drop(&mut self) {
        // SAFETY: the filter is live and released once; its device is kept
        // alive by `self.oidn` until after this call.
        unsafe { (self.oidn.api.release_filter)(self.raw.as_ptr()) };
    }
}
