//! `hz_device`: thread pool, ONNX Runtime location, memory limit and model,
//! shared by the sessions created on it.

use std::ffi::{c_char, c_void};
use std::path::PathBuf;
use std::sync::Arc;

use harmonizer_core::{Device, DeviceOptions, Error, ModelSource};

use crate::{check_null, check_struct_size, ffi_guard, hz_status, read_str};

/// Opaque device handle. Sessions keep their device alive: freeing a device
/// while sessions use it is allowed; it is released with its last session.
pub struct hz_device {
    pub(crate) inner: Arc<Device>,
}

/// Device settings. Zero-initialize, set `struct_size = sizeof(hz_device_options)`,
/// then the fields you need: zero or NULL means the default.
#[repr(C)]
#[derive(Debug, Clone, Copy)]
pub struct hz_device_options {
    /// `sizeof(hz_device_options)`.
    pub struct_size: usize,
    /// Worker threads of the device's private pool; 0 = one per core. Threads are not pinned.
    pub threads: u32,
    /// Limit on the working memory of one frame, in bytes; 0 = the memory of
    /// the machine (RAM plus swap, or the cgroup's limit when lower). A frame
    /// whose estimated working set exceeds it is refused by
    /// `hz_session_process` with `HZ_ERROR_OUT_OF_MEMORY`; the neural
    /// backend's tiles shrink to fit what is left.
    pub memory_limit: u64,
    /// Path of `libonnxruntime`; NULL = `HARMONIZER_ORT_LIB`, `ORT_DYLIB_PATH`,
    /// then the project's `.venv`. Only the neural backend loads it.
    pub ort_library: *const c_char,
    /// An `.onnx` model file (its JSON manifest beside it); NULL = the embedded
    /// default. Read and checked by `hz_device_new`.
    pub model_path: *const c_char,
    /// An ONNX model in memory (copied); NULL = none. Needs `model_manifest`.
    pub model_data: *const c_void,
    /// Bytes at `model_data`.
    pub model_data_size: usize,
    /// The JSON manifest of the in-memory model (NUL-terminated, copied).
    pub model_manifest: *const c_char,
}

/// Reads the options a host passed (NULL = defaults).
///
/// # Safety
/// `o` is NULL or points to a readable `hz_device_options` whose pointers
/// follow the documented contract.
unsafe fn read_options(o: *const hz_device_options) -> Result<DeviceOptions, Error> {
    if o.is_null() {
        return Ok(DeviceOptions::default());
    }
    // SAFETY: non-NULL; only the first field is read before the size check.
    let size = unsafe { std::ptr::addr_of!((*o).struct_size).read_unaligned() };
    check_struct_size(
        "hz_device_options",
        size,
        std::mem::size_of::<hz_device_options>(),
    )?;
    // SAFETY: the struct has this library's size.
    let o = unsafe { o.read_unaligned() };
    let mut opts = DeviceOptions {
        threads: o.threads as usize,
        memory_limit: usize::try_from(o.memory_limit).unwrap_or(usize::MAX),
        ..DeviceOptions::default()
    };
    if !o.ort_library.is_null() {
        // SAFETY: non-NULL, NUL-terminated per the contract.
        opts.ort_library = Some(PathBuf::from(unsafe {
            read_str("options.ort_library", o.ort_library)
        }?));
    }
    let has_path = !o.model_path.is_null();
    let has_data = !o.model_data.is_null();
    opts.model = match (has_path, has_data) {
        (true, true) => {
            return Err(Error::invalid(
                "options: model_path and model_data are both set; give one model",
            ))
        }
        (true, false) => {
            // SAFETY: non-NULL, NUL-terminated per the contract.
            ModelSource::File(PathBuf::from(unsafe {
                read_str("options.model_path", o.model_path)
            }?))
        }
        (false, true) => {
            if o.model_data_size == 0 {
                return Err(Error::invalid(
                    "options: model_data is set but model_data_size is 0",
                ));
            }
            if o.model_data_size > isize::MAX as usize {
                return Err(Error::invalid(format!(
                    "options: model_data_size {} is too large",
                    o.model_data_size
                )));
            }
            if o.model_manifest.is_null() {
                return Err(Error::invalid(
                    "options: model_data needs model_manifest (the JSON manifest)",
                ));
            }
            // SAFETY: non-NULL, readable for `model_data_size` bytes per the contract.
            let onnx =
                unsafe { std::slice::from_raw_parts(o.model_data.cast::<u8>(), o.model_data_size) }
                    .to_vec();
            // SAFETY: non-NULL, NUL-terminated per the contract.
            let manifest =
                unsafe { read_str("options.model_manifest", o.model_manifest) }?.to_string();
            ModelSource::Bytes { onnx, manifest }
        }
        (false, false) => {
            if !o.model_manifest.is_null() {
                return Err(Error::invalid(
                    "options: model_manifest is set but model_data is NULL",
                ));
            }
            ModelSource::Embedded
        }
    };
    Ok(opts)
}

/// Creates a device. Pass `HZ_VERSION_MAJOR` as `version_major`: a library
/// of another major version refuses (`HZ_ERROR_NOT_SUPPORTED`). `options` may
/// be NULL for defaults. On failure `*out_device` is set to NULL.
///
/// A model given by `model_path` or `model_data` is checked here: the file
/// and its manifest are read (`HZ_ERROR_IO` naming the file when it cannot
/// be), the manifest validated and the bytes checked to be an ONNX model
/// with the manifest's input and output (`HZ_ERROR_MODEL` naming the file
/// or "in-memory model"), and the model loaded when ONNX Runtime is found.
/// A missing runtime is not an error here: `hz_session_new` with the
/// neural backend reports it, and `auto` runs the classical backend.
///
/// # Safety
/// `options` is NULL or a valid `hz_device_options`; `out_device` is writable.
#[no_mangle]
pub unsafe extern "C" fn hz_device_new(
    version_major: u32,
    options: *const hz_device_options,
    out_device: *mut *mut hz_device,
) -> hz_status {
    ffi_guard!("hz_device_new", {
        check_null!(out_device);
        // SAFETY: non-NULL and writable per the contract.
        unsafe { out_device.write(std::ptr::null_mut()) };
        crate::check_version(version_major, None)?;
        // SAFETY: forwarded contract.
        let opts = unsafe { read_options(options) }?;
        let device = Device::new(opts)?;
        let handle = Box::into_raw(Box::new(hz_device { inner: device }));
        // SAFETY: as above.
        unsafe { out_device.write(handle) };
        Ok(())
    })
}

/// Releases the caller's reference to a device (NULL is a no-op).
///
/// # Safety
/// `device` is NULL or a handle from `hz_device_new` not freed before.
#[no_mangle]
pub unsafe extern "C" fn hz_device_free(device: *mut hz_device) -> hz_status {
    ffi_guard!("hz_device_free", {
        if !device.is_null() {
            // SAFETY: a live handle from `Box::into_raw`, freed once.
            drop(unsafe { Box::from_raw(device) });
        }
        Ok(())
    })
}

/// Worker threads of the device's pool.
///
/// # Safety
/// `device` is a live handle; `out_threads` is writable.
#[no_mangle]
pub unsafe extern "C" fn hz_device_get_threads(
    device: *const hz_device,
    out_threads: *mut u32,
) -> hz_status {
    ffi_guard!("hz_device_get_threads", {
        check_null!(device, out_threads);
        // SAFETY: live handle per the contract.
        let d = unsafe { &*device };
        let n = u32::try_from(d.inner.threads()).unwrap_or(u32::MAX);
        // SAFETY: writable per the contract.
        unsafe { out_threads.write(n) };
        Ok(())
    })
}

/// Borrows a device handle.
///
/// # Safety
/// `device` is NULL or a live handle.
pub(crate) unsafe fn device_ref<'a>(device: *const hz_device) -> Result<&'a hz_device, Error> {
    if device.is_null() {
        return Err(Error::invalid("device is NULL"));
    }
    // SAFETY: non-NULL; live per the caller's contract.
    Ok(unsafe { &*device })
}
