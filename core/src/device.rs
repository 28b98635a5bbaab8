//! The device: a private thread pool, the ONNX Runtime location, a memory
//! limit and the model. Shared (via `Arc`) by all sessions on it.

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
    /// Soft limit on working memory in bytes for tiled inference; 0 = no limit.
    pub memory_limit: usize,
    /// The neural model.
    pub model: ModelSource,
}

/// A device. Create once, share between sessions.
pub struct Device {
    options: DeviceOptions,
    pool: rayon::ThreadPool,
    neural: Mutex<Option<Arc<crate::backend::neural::NeuralModel>>>,
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
        Ok(Arc::new(Device {
            options,
            pool,
            neural: Mutex::new(None),
        }))
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
