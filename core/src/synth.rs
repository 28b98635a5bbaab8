//! Deterministic synthetic sequences with ground truth (demo, bench, tests).
