//! The integration tests of harmonizer-core: one binary, one topic module per
//! file under `tests/core/` (add yours as `#[path = "core/<topic>.rs"] mod <topic>;`).

#[path = "core/classical.rs"]
mod classical;
#[path = "core/denoise.rs"]
mod denoise;
#[path = "core/denoise_session.rs"]
mod denoise_session;
#[path = "core/gamut.rs"]
mod gamut;
#[path = "core/hostile.rs"]
mod hostile;
#[path = "core/inserts.rs"]
mod inserts;
#[path = "core/io.rs"]
mod io;
#[path = "core/neural.rs"]
mod neural;
#[path = "core/session.rs"]
mod session;
#[path = "core/temporal.rs"]
mod temporal;
