//! The device: a private thread pool, the ONNX Runtime location, a memory
//! limit, the model and Open Image Denoise. Shared (via `Arc`) by all
//! sessions on it.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use crate::error::{Error, Result};

/// Where the neural model comes from.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum ModelSource {
    /// The model embedded in the library (the default).
    #[default]
    Embedded,
    /// An `.onnx` file with its manifest (`<name>.json`) beside it.
    File(PathBuf),
    /// An ONNX model and its JSON manifest in memory.
    Bytes {
        /// The ONNX protobuf.
        onnx: Vec<u8>,
        /// The manifest JSON text.
        manifest: String,
    },
}

/// Device settings.
#[derive(Debug, Clone, Default)]
pub struct DeviceOptions {
    /// Worker threads; 0 = one per core.
    pub threads: usize,
    /// Path of `libonnxruntime.so`; `None` = `HARMONIZER_ORT_LIB`, `ORT_DYLIB_PATH`, the project's `.venv`.
    pub ort_library: Option<PathBuf>,
    /// Limit on the working memory of one frame in bytes; 0 = the memory
    /// of the machine (RAM plus swap, or the cgroup's limit when lower).
    /// A frame whose estimated working set (the session's frame-sized
    /// buffers and history, see [`crate::Session::memory_estimate`]) exceeds
    /// it is refused with [`Error::OutOfMemory`] before anything is
    /// allocated; the neural backend's tiles get what is left.
    pub memory_limit: usize,
    /// The neural model.
    pub model: ModelSource,
    /// Path of `libOpenImageDenoise.so` for the denoise stage; `None` =
    /// `HARMONIZER_OIDN_LIB`, the `pyoidn` wheel in a `.venv*`, the
    /// system's library ([`crate::denoise::locate`]). Loaded on first use.
    pub oidn_library: Option<PathBuf>,
}

/// A device. Create once, share between sessions.
pub struct Device {
    options: DeviceOptions,
    /// The memory limit in force and what it is.
    memory: (usize, &'static str),
    pool: rayon::ThreadPool,
    neural: Mutex<Option<Arc<crate::backend::neural::NeuralModel>>>,
    oidn: Mutex<Option<Arc<crate::denoise::Oidn>>>,
}

impl std::fmt::Debug for Device {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Device")
            .field("options", &self.options)
            .finish_non_exhaustive()
    }
}

impl Device {
    /// Creates a device with its own thread pool (threads are not pinned).
    ///
    /// A model given as a file or as bytes is checked here: the file and
    /// its manifest are read, the manifest validated and the ONNX bytes
    /// checked to be an ONNX model whose graph has the manifest's input and
    /// output, then loaded into ONNX Runtime when it can be found. A
    /// missing or bad model is an error naming it ([`Error::Io`],
    /// [`Error::Model`]); a missing runtime is not (it is reported when a
    /// session asks for the neural backend, and `auto` runs classical).
    pub fn new(options: DeviceOptions) -> Result<Arc<Device>> {
        let threads = if options.threads == 0 {
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        } else {
            options.threads
        };
        if threads > 1024 {
            return Err(Error::invalid(format!(
                "threads: {threads} is out of range 0..=1024"
            )));
        }
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("harmonizer-{i}"))
            .build()
            .map_err(|e| Error::Io(format!("cannot start {threads} worker threads: {e}")))?;
        let memory = match options.memory_limit {
            0 => (machine_memory(), "memory of this machine"),
            n => (n, "device memory_limit"),
        };
        let device = Device {
            options,
            memory,
            pool,
            neural: Mutex::new(None),
            oidn: Mutex::new(None),
        };
        if device.options.model != ModelSource::Embedded {
            // Loading reads and checks the files, the manifest and the
            // graph's names before it needs ONNX Runtime, so a bad model is
            // refused here with or without the runtime.
            match device.neural_model() {
                Ok(_) => {}
                Err(e @ (Error::Model(_) | Error::Io(_))) => return Err(e),
                // The runtime is missing or another one is loaded: said
                // when a session asks for the model.
                Err(_) => {}
            }
        }
        Ok(Arc::new(device))
    }

    /// The limit a frame's working set must fit, in bytes, and what it is
    /// (`"device memory_limit"` or `"memory of this machine"`).
    pub fn memory_budget(&self) -> (usize, &'static str) {
        self.memory
    }

    /// The settings this device was created with.
    pub fn options(&self) -> &DeviceOptions {
        &self.options
    }

    /// Worker threads in the device's pool.
    pub fn threads(&self) -> usize {
        self.pool.current_num_threads()
    }

    /// The device's private pool.
    pub fn pool(&self) -> &rayon::ThreadPool {
        &self.pool
    }

    /// The neural model, loaded on first use and shared by sessions.
    /// `Ok(None)` when the source is `Embedded` and this build embeds no model.
    pub fn neural_model(&self) -> Result<Option<Arc<crate::backend::neural::NeuralModel>>> {
        let mut slot = self.neural.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(m) = slot.as_ref() {
            return Ok(Some(m.clone()));
        }
        let loaded = crate::backend::neural::NeuralModel::load(&self.options)?;
        if let Some(m) = &loaded {
            *slot = Some(m.clone());
        }
        Ok(loaded)
    }
}

impl Device {
    /// Open Image Denoise and its CPU device with this device's thread
    /// count, loaded on first use ([`crate::denoise::Oidn::new`] with
    /// `oidn_library`) and shared by the sessions on this device. A
    /// failure is not kept: the next call tries again.
    ///
    /// Errors: [`Error::RuntimeMissing`] naming the library looked for and
    /// what to install; see [`crate::denoise::Oidn::new`].
    pub fn oidn(&self) -> Result<Arc<crate::denoise::Oidn>> {
        let mut slot = self.oidn.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(o) = slot.as_ref() {
            return Ok(o.clone());
        }
        let o = crate::denoise::Oidn::new(self.options.oidn_library.as_deref(), self.threads())?;
        *slot = Some(o.clone());
        Ok(o)
    }
}

/// The memory this process can use, in bytes: RAM plus swap
/// (`/proc/meminfo`), or the cgroup's limit when lower; `usize::MAX` where
/// neither can be read.
pub fn machine_memory() -> usize {
    let kib = |text: &str, key: &str| -> Option<usize> {
        let line = text.lines().find(|l| l.starts_with(key))?;
        let n: usize = line[key.len()..]
            .trim()
            .trim_end_matches("kB")
            .trim()
            .parse()
            .ok()?;
        n.checked_mul(1024)
    };
    let total = std::fs::read_to_string("/proc/meminfo").ok().and_then(|t| {
        let ram = kib(&t, "MemTotal:")?;
        Some(ram.saturating_add(kib(&t, "SwapTotal:").unwrap_or(0)))
    });
    let cgroup = [
        "/sys/fs/cgroup/memory.max",
        "/sys/fs/cgroup/memory/memory.limit_in_bytes",
    ]
    .iter()
    .find_map(|p| {
        std::fs::read_to_string(p)
            .ok()?
            .trim()
            .parse::<usize>()
            .ok()
    });
    match (total, cgroup) {
        (Some(t), Some(c)) => t.min(c),
        (Some(t), None) => t,
        (None, Some(c)) => c,
        (None, None) => usize::MAX,
    }
}

/// A non-empty path from the environment variable `var`.
pub(crate) fn env_path(var: &str) -> Option<std::path::PathBuf> {
    std::env::var_os(var)
        .filter(|v| !v.is_empty())
        .map(std::path::PathBuf::from)
}

/// The file named `prefix*` in `<venv>/lib/python3*/site-packages/<package_dir>`
/// (a library a Python wheel ships), the most specific name when there are
/// several (`libx.so.1.2.3` over `libx.so`).
pub(crate) fn wheel_library(
    venv: &std::path::Path,
    package_dir: &str,
    prefix: &str,
) -> Option<std::path::PathBuf> {
    let pythons = std::fs::read_dir(venv.join("lib")).ok()?;
    let mut found = Vec::new();
    for py in pythons.flatten() {
        if !py.file_name().to_string_lossy().starts_with("python3") {
            continue;
        }
        let Ok(files) = std::fs::read_dir(py.path().join("site-packages").join(package_dir)) else {
            continue;
        };
        for f in files.flatten() {
            if f.file_name().to_string_lossy().starts_with(prefix) && f.path().is_file() {
                found.push(f.path());
            }
        }
    }
    found.sort();
    found.pop()
}

/// Where a runtime library's `.venv` is looked for: the working directory and
/// the executable's directory (and, by the callers, their ancestors).
pub(crate) fn search_starts() -> Vec<std::path::PathBuf> {
    let mut starts = Vec::new();
    if let Ok(cwd) = std::env::current_dir() {
        starts.push(cwd);
    }
    if let Some(dir) = std::env::current_exe()
        .ok()
        .and_then(|e| e.parent().map(std::path::Path::to_path_buf))
    {
        starts.push(dir);
    }
    starts
}
