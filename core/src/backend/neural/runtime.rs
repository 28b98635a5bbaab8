//! Finding and loading the ONNX Runtime shared library (`ort` with
//! `load-dynamic`), once per process.
//!
//! Search order: the device option `ort_library`, `HARMONIZER_ORT_LIB`,
//! `ORT_DYLIB_PATH`, then a project `.venv` found by walking up from the
//! current directory and from the executable's directory
//! (`.venv/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so*`).

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use crate::error::{Error, Result};

/// The ONNX Runtime release this build is made for.
pub const ORT_REQUIREMENT: &str = "onnxruntime==1.31.*";

/// The install hint every `RuntimeMissing` error carries.
pub fn install_hint() -> String {
    format!(
        "install it with `python3 -m pip install {ORT_REQUIREMENT}` (or run scripts/setup-venv.sh in the \
         harmonizer checkout) and set HARMONIZER_ORT_LIB=<site-packages>/onnxruntime/capi/libonnxruntime.so.1.31.1 \
         (or pass the device option ort_library)"
    )
}

struct Loaded {
    path: PathBuf,
    env: ort::environment::Environment,
}

static RUNTIME: Mutex<Option<Loaded>> = Mutex::new(None);

/// Where a candidate library path came from (for messages).
fn missing(path: &Path, from: &str) -> Error {
    Error::RuntimeMissing(format!(
        "{} (from {from}) does not exist; {}",
        path.display(),
        install_hint()
    ))
}

/// Finds `libonnxruntime.so*` in a `.venv` in `start` or any of its ancestors.
pub fn find_in_venv(start: &Path) -> Option<PathBuf> {
    start.ancestors().find_map(|dir| {
        crate::device::wheel_library(&dir.join(".venv"), "onnxruntime/capi", "libonnxruntime.so")
    })
}

/// Resolves the library path without loading it.
pub fn locate(explicit: Option<&Path>) -> Result<PathBuf> {
    let candidates = [
        (
            explicit.map(Path::to_path_buf),
            "the device option ort_library",
        ),
        (
            crate::device::env_path("HARMONIZER_ORT_LIB"),
            "HARMONIZER_ORT_LIB",
        ),
        (crate::device::env_path("ORT_DYLIB_PATH"), "ORT_DYLIB_PATH"),
    ];
    for (path, from) in candidates {
        if let Some(p) = path {
            return if p.is_file() {
                Ok(p)
            } else {
                Err(missing(&p, from))
            };
        }
    }
    let starts = crate::device::search_starts();
    for s in &starts {
        if let Some(p) = find_in_venv(s) {
            return Ok(p);
        }
    }
    Err(Error::RuntimeMissing(format!(
        "libonnxruntime.so was not found (no ort_library option, HARMONIZER_ORT_LIB, ORT_DYLIB_PATH, nor a \
         .venv with onnxruntime above {}); {}",
        starts.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(" or "),
        install_hint()
    )))
}

fn same_file(a: &Path, b: &Path) -> bool {
    match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    }
}

/// Loads ONNX Runtime once per process and returns its environment and path.
/// A later call with an explicit `ort_library` naming another file is an error
/// (one runtime per process); without one it reuses the loaded runtime.
pub fn environment(explicit: Option<&Path>) -> Result<(ort::environment::Environment, PathBuf)> {
    let mut slot = RUNTIME.lock().unwrap_or_else(|p| p.into_inner());
    if let Some(l) = slot.as_ref() {
        if let Some(p) = explicit {
            if !p.is_file() {
                return Err(missing(p, "the device option ort_library"));
            }
            if !same_file(p, &l.path) {
                return Err(Error::InvalidOperation(format!(
                    "ONNX Runtime is already loaded from {} in this process; cannot also load {} (one runtime \
                     per process: give every device the same ort_library)",
                    l.path.display(),
                    p.display()
                )));
            }
        }
        return Ok((l.env.clone(), l.path.clone()));
    }
    let path = locate(explicit)?;
    let builder = ort::init_from(&path).map_err(|e| {
        Error::RuntimeMissing(format!(
            "cannot load {}: {e}; {}",
            path.display(),
            install_hint()
        ))
    })?;
    let env = builder
        .with_name("harmonizer")
        .with_telemetry(false)
        .build()
        .map_err(|e| {
            Error::RuntimeMissing(format!(
                "{}: cannot start ONNX Runtime: {e}",
                path.display()
            ))
        })?;
    *slot = Some(Loaded {
        path: path.clone(),
        env: env.clone(),
    });
    Ok((env, path))
}

/// The path ONNX Runtime was loaded from in this process, if it was.
pub fn loaded_path() -> Option<PathBuf> {
    RUNTIME
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .as_ref()
        .map(|l| l.path.clone())
}
