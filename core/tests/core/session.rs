//! The session: resets, determinism, commit-on-success, gap policy, warnings.
