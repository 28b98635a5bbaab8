#!/usr/bin/env bash
# Creates (or completes) the two Python environments of training/, idempotently:
#   .venv-bpy    Blender as a module for data synthesis (training/requirements-synth.txt)
#   .venv-train  PyTorch, ONNX, ONNX Runtime for training and export (training/requirements.txt)
# `setup_env.sh bpy` creates only .venv-bpy. Only what is missing is installed. Environment: PYTHON311 (interpreter),
# HZ_BPY_VENV, HZ_TRAIN_VENV (venv paths).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(dirname "$here")"
py="${PYTHON311:-python3.11}"
bpy_venv="${HZ_BPY_VENV:-$repo/.venv-bpy}"
train_venv="${HZ_TRAIN_VENV:-$repo/.venv-train}"

ensure() {
    local venv=$1 check=$2 req=$3
    if [ -x "$venv/bin/python" ] && "$venv/bin/python" -c "$check" >/dev/null 2>&1; then
        return 0
    fi
    if ! command -v "$py" >/dev/null 2>&1; then
        echo "setup_env: $py not found (bpy 5.0.1 needs Python 3.11; set PYTHON311)" >&2
        exit 2
    fi
    [ -x "$venv/bin/python" ] || "$py" -m venv "$venv"
    echo "setup_env: installing $req into $venv"
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check -r "$req"
    "$venv/bin/python" -c "$check"
}

ensure "$bpy_venv" "import bpy, numpy, OpenEXR" "$here/requirements-synth.txt"
[ "${1:-}" = bpy ] && exit 0  # `setup_env.sh bpy`: the Blender environment only
ensure "$train_venv" "import torch, numpy, onnx, onnxruntime, OpenEXR, pytest, ruff" "$here/requirements.txt"
