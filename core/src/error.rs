//! Errors grouped by cause; each maps one to one onto a C status code and a
//! Python exception class.

/// What went wrong. Every message names the thing: file, frame, channel,
/// parameter, and the value seen.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum Error {
    /// A bad argument or bad input data (size, channel, stride, value range).
    #[error("invalid argument: {0}")]
    Invalid(String),
    /// The call is not allowed in the object's current state.
    #[error("invalid operation: {0}")]
    InvalidOperation(String),
    /// The input uses something this build does not support.
    #[error("not supported: {0}")]
    NotSupported(String),
    /// Reading or writing a file failed.
    #[error("i/o error: {0}")]
    Io(String),
    /// A buffer could not be allocated within the memory limit.
    #[error("out of memory: {0}")]
    OutOfMemory(String),
    /// The model or its manifest is missing, malformed or incompatible.
    #[error("model error: {0}")]
    Model(String),
    /// A shared library loaded at run time (ONNX Runtime, Open Image
    /// Denoise) could not be found or loaded.
    #[error("runtime library missing: {0}")]
    RuntimeMissing(String),
    /// The caller's progress callback asked to stop; state is unchanged.
    #[error("cancelled: {0}")]
    Cancelled(String),
}

/// Result alias used across the crate.
pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    /// Shorthand for [`Error::Invalid`].
    pub fn invalid(msg: impl Into<String>) -> Self {
        Error::Invalid(msg.into())
    }
    /// Shorthand for [`Error::Io`] that names the path.
    pub fn io(path: &std::path::Path, err: impl std::fmt::Display) -> Self {
        Error::Io(format!("{}: {}", path.display(), err))
    }
}
