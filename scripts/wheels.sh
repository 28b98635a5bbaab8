#!/usr/bin/env bash
# Builds the wheels of the Python binding (harmonizer, carrying libharmonizer)
# and of the USD hook (usd_harmonizer) into dist/ (or DIR). Builds happen out
# of tree: nothing is written into ffi/python or usd_plugin. cargo builds the
# library into $CARGO_TARGET_DIR when set (CI reuses the workspace's target/),
# else into a temporary directory.
#
#   scripts/wheels.sh [DIR]
#   pip install dist/harmonizer-*.whl dist/usd_harmonizer-*.whl   # [neural], [denoise] extras
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
OUT=${1:-$ROOT/dist}
mkdir -p "$OUT"
OUT=$(cd "$OUT" && pwd)
PY=${PYTHON:-python3.11}
# hatchling imports ffi/python/hatch_build.py: no __pycache__ beside it.
export PYTHONDONTWRITEBYTECODE=1
# pip wheel keeps its build in a temporary directory; hatchling writes only the wheel.
rm -f "$OUT"/harmonizer-*.whl "$OUT"/usd_harmonizer-*.whl
"$PY" -m pip wheel --quiet --disable-pip-version-check --no-deps -w "$OUT" "$ROOT/ffi/python" "$ROOT/usd_plugin"
ls "$OUT"/harmonizer-*.whl "$OUT"/usd_harmonizer-*.whl
