#!/usr/bin/env bash
# USD hook tests (issue 5): real usd-core, OpenImageIO, OpenColorIO, Blender's
# Cycles (fixture render from a USD stage) and libharmonizer.
#
#   tests/usd/run.sh [pytest args...]
#
# Idempotent on a fresh machine: creates .venv-usd (python3.11: usd-core,
# OpenImageIO, opencolorio, numpy, pytest) and installs usd_plugin editable;
# creates .venv-bpy (bpy==5.0.1, numpy) for the fixture render when missing
# (bpy and usd-core both ship `pxr`: never in one venv); builds libharmonizer
# (release) when missing. Fixtures are rendered once into build/usd_fixtures/.
# Environment: HARMONIZER_LIB (library to use), HARMONIZER_ORT_LIB (ONNX
# Runtime; default: the project's .venv, else installed into .venv-usd),
# HARMONIZER_OIDN_LIB (Open Image Denoise for the denoise stage; default: the
# pyoidn wheel in the project's .venv, else installed into .venv-usd), HZ_USD_VENV, HZ_BPY_VENV,
# HZ_USD_CACHE (fixture cache), PYTHON311.
set -euo pipefail
cd "$(dirname "$0")/../.."
REPO=$PWD
PY=${PYTHON311:-python3.11}

VENV=${HZ_USD_VENV:-$REPO/.venv-usd}
if ! "$VENV/bin/python" -c "import pxr.UsdRender, OpenImageIO, PyOpenColorIO, numpy, pytest" >/dev/null 2>&1; then
    command -v "$PY" >/dev/null || { echo "error: $PY not found (set PYTHON311)" >&2; exit 2; }
    echo "creating $VENV (usd-core, OpenImageIO, opencolorio, numpy, pytest)"
    "$PY" -m venv "$VENV"
    "$VENV/bin/python" -m pip install --quiet usd-core OpenImageIO opencolorio numpy pytest
fi
# harmonize-farm over a stage (issue 22).
if ! "$VENV/bin/python" -c "import distributed" >/dev/null 2>&1; then
    "$VENV/bin/python" -m pip install --quiet "dask[distributed]==2026.*"
fi
if ! "$VENV/bin/python" -c "import usd_harmonizer" >/dev/null 2>&1 || [[ ! -x "$VENV/bin/usd-harmonize" ]]; then
    echo "installing usd_plugin (editable) into $VENV"
    "$VENV/bin/python" -m pip install --quiet --no-deps -e usd_plugin
fi

BPY=${HZ_BPY_VENV:-$REPO/.venv-bpy}
if ! "$BPY/bin/python" -c "import bpy, numpy" >/dev/null 2>&1; then
    command -v "$PY" >/dev/null || { echo "error: bpy 5.0.1 needs $PY (set PYTHON311)" >&2; exit 2; }
    echo "creating $BPY (bpy==5.0.1, numpy) for the fixture render"
    "$PY" -m venv "$BPY"
    "$BPY/bin/python" -m pip install --quiet "bpy==5.0.1" numpy
fi
export HZ_BPY_VENV=$BPY

LIB=${HARMONIZER_LIB:-$REPO/target/release/libharmonizer.so}
if [[ ! -f "$LIB" ]]; then
    echo "building libharmonizer: cargo build --release -p harmonizer-ffi"
    cargo build --release -p harmonizer-ffi
fi
export HARMONIZER_LIB=$LIB

# ONNX Runtime for the neural-backend test: the project's .venv, else .venv-usd.
if [[ -z "${HARMONIZER_ORT_LIB:-}" ]]; then
    ort=$(ls "$REPO"/.venv/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so.* \
        "$VENV"/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so.* 2>/dev/null | sort | tail -n 1 || true)
    if [[ -z "$ort" ]]; then
        echo "installing onnxruntime into $VENV (neural-backend test)"
        "$VENV/bin/python" -m pip install --quiet "onnxruntime==1.31.*"
        ort=$(ls "$VENV"/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so.* | sort | tail -n 1)
    fi
    export HARMONIZER_ORT_LIB=$ort
fi

# Open Image Denoise (denoise stage, on by default for noisy frames): every
# test runs with the real library, whichever venvs this machine has.
if [[ -z "${HARMONIZER_OIDN_LIB:-}" ]]; then
    oidn=$(ls "$REPO"/.venv/lib/python3*/site-packages/pyoidn/oidn/lib/libOpenImageDenoise.so.2* \
        "$VENV"/lib/python3*/site-packages/pyoidn/oidn/lib/libOpenImageDenoise.so.2* 2>/dev/null | sort | tail -n 1 || true)
    if [[ -z "$oidn" ]]; then
        echo "installing pyoidn into $VENV (Open Image Denoise for the denoise stage)"
        "$VENV/bin/python" -m pip install --quiet "pyoidn==2.*"
        oidn=$(ls "$VENV"/lib/python3*/site-packages/pyoidn/oidn/lib/libOpenImageDenoise.so.2* | sort | tail -n 1)
    fi
    export HARMONIZER_OIDN_LIB=$oidn
fi

exec nice -n 10 "$VENV/bin/python" -m pytest tests/usd -q -p no:cacheprovider "$@"
