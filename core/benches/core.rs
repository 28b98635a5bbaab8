//! Criterion benches of harmonizer-core, one function per group.

use criterion::{criterion_group, criterion_main, Criterion};

/// Reprojection of history frames into the current view at 1920x1080.
fn reprojection(_c: &mut Criterion) {}

criterion_group!(benches, reprojection);
criterion_main!(benches);
