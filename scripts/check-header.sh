#!/usr/bin/env bash
# Regenerates ffi/include/harmonizer.h from ffi/src with cbindgen (in memory)
# and fails when the committed header differs; checks the header's version
# macros against Cargo.toml. With --bless, rewrites the header instead.
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ "${1:-}" == "--bless" ]]; then
    export HZ_BLESS_HEADER=1
fi
cargo test -p harmonizer-ffi --test abi -- header
