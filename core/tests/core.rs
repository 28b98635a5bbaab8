//! The integration tests of harmonizer-core, one binary with topic modules
//! (files under `tests/core/`).

mod session;
mod temporal;
