#!/usr/bin/env bash
# Every test of libharmonizer (issue 3): header drift and version macros, the
# libloading driver, the C/C++ hosts (gcc + g++, shared + static, ASan +
# UBSan), the install (pkg-config, CMake, exported symbols) and the Python
# binding. Needs .venv (numpy, pytest, onnxruntime) for the Python tests.
set -euo pipefail
cd "$(dirname "$0")/.."
echo "== header drift and version macros"
scripts/check-header.sh
echo "== Rust driver over the cdylib (libloading)"
cargo test -p harmonizer-ffi
echo "== C99 / C++17 hosts, shared and static, sanitizers"
make -C tests/c PROFILE=release
echo "== install: pkg-config, CMake, Python next to the library"
tests/c/test_install.sh
echo "== Python binding (release library)"
(cd ffi/python && HARMONIZER_LIB="${CARGO_TARGET_DIR:-$PWD/../../target}/release/libharmonizer.so" \
    ../../.venv/bin/python -m pytest -q tests)
