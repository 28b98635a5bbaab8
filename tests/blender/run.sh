#!/usr/bin/env bash
# Real-Blender tests of the harmonizer extension (issue 4): bpy 5.0.1 headless.
#
#   tests/blender/run.sh [--docs-image] [pytest args...]
#
# Creates the test venv (.venv-bpy: bpy==5.0.1, numpy, opencolorio, pytest) when
# it is missing, builds libharmonizer (release) when it is missing, packages the
# extension zip with blender_addon/build.py, and runs the tests, which install
# that zip with Blender's own "Install from Disk" operator.
#   --docs-image   also write docs/images/blender_before_after.png
# Environment: HARMONIZER_LIB (library to bundle), HZ_BPY_VENV (venv path),
# HZ_KEEP_TMP=1 (keep the rendered files).
set -euo pipefail
cd "$(dirname "$0")/../.."
REPO=$PWD

VENV=${HZ_BPY_VENV:-$REPO/.venv-bpy}
if ! "$VENV/bin/python" -c "import bpy, numpy, PyOpenColorIO, pytest" >/dev/null 2>&1; then
    PY=${PYTHON311:-python3.11}
    if ! command -v "$PY" >/dev/null; then
        echo "error: bpy 5.0.1 needs Python 3.11 ($PY not found; set PYTHON311)" >&2
        exit 2
    fi
    echo "creating $VENV (bpy==5.0.1, numpy, opencolorio, pytest)"
    "$PY" -m venv "$VENV"
    "$VENV/bin/python" -m pip install --quiet "bpy==5.0.1" numpy opencolorio pytest
fi

if [[ "${1:-}" == "--docs-image" ]]; then
    export HZ_DOCS_IMAGE="$REPO/docs/images/blender_before_after.png"
    shift
fi

LIB=${HARMONIZER_LIB:-$REPO/target/release/libharmonizer.so}
if [[ ! -f "$LIB" ]]; then
    echo "building libharmonizer: cargo build --release -p harmonizer-ffi"
    cargo build --release -p harmonizer-ffi
fi

OUT="$REPO/build/blender_addon/dist"
ZIP=$("$VENV/bin/python" blender_addon/build.py --lib "$LIB" --out "$OUT" \
    --cache "$REPO/build/blender_addon/wheel-cache" | tail -n 1)
echo "extension: $ZIP"
export HARMONIZER_BLENDER_ZIP="$ZIP"
exec nice -n 10 "$VENV/bin/python" -m pytest tests/blender -q -p no:cacheprovider -W ignore::DeprecationWarning "$@"
