#!/usr/bin/env bash
# Issue 21: install like a pipeline TD. Builds the wheels (scripts/wheels.sh,
# into a temporary directory), installs them into a clean python3.11 venv
# (not the checkout: harmonizer[neural,denoise] and usd_harmonizer), then with
# every HARMONIZER_* variable unset and the working directory outside the
# checkout: runs frames through harmonizer.Session (classical, neural with the
# onnxruntime wheel, denoise with the pyoidn wheel) and a small hand-made
# stage through usd-harmonize; builds the Blender zip from the same binding
# wheel (offline). Fails when `git status --porcelain --ignored`
# of the checkout differs afterwards (nothing written into the source tree).
#
#   tests/wheels/run.sh          # CARGO_TARGET_DIR: reused when set (CI: target/)
set -euo pipefail
cd "$(dirname "$0")/../.."
ROOT=$PWD
PY=${PYTHON311:-python3.11}
WORK=$(mktemp -d "${TMPDIR:-/tmp}/harmonizer-wheels.XXXXXX")
trap 'rm -rf "$WORK"' EXIT

before=$(git status --porcelain --ignored)

echo "== wheels"
nice -n 10 "$ROOT/scripts/wheels.sh" "$WORK/dist"

echo "== clean venv, install the wheels"
"$PY" -m venv "$WORK/venv"
V=$WORK/venv/bin
hz_whl=$(ls "$WORK"/dist/harmonizer-*.whl)
usd_whl=$(ls "$WORK"/dist/usd_harmonizer-*.whl)
case "$(basename "$hz_whl")" in
    *-none-any.whl) echo "FAIL: $hz_whl is not platform-tagged"; exit 1 ;;
esac
"$V/python" -m pip install --quiet --disable-pip-version-check "${hz_whl}[neural,denoise]" "$usd_whl"

# No HARMONIZER_* variable, no ORT_DYLIB_PATH, not in the checkout (the
# library's own search walks up from the working directory to a .venv).
unset_env=()
for v in $(env | sed -n 's/^\(HARMONIZER_[A-Za-z0-9_]*\)=.*/\1/p') ORT_DYLIB_PATH PYTHONPATH; do
    unset_env+=(-u "$v")
done
run() { (cd "$WORK" && env "${unset_env[@]}" PYTHONDONTWRITEBYTECODE=1 "$@"); }

echo "== harmonizer.Session from the wheel"
run "$V/python" - "$WORK" <<'PY'
import sys
from pathlib import Path

import numpy as np

import harmonizer as hz
from harmonizer import _native

venv = Path(sys.prefix).resolve()
lib = Path(_native.lib()._name).resolve()
assert lib.is_relative_to(venv) and lib.parent.name == "lib", f"not the wheel's library: {lib}"
ort, oidn = _native.ort_library(), _native.oidn_library()
assert ort and Path(ort).resolve().is_relative_to(venv), f"onnxruntime wheel not found: {ort}"
assert oidn and Path(oidn).resolve().is_relative_to(venv), f"pyoidn wheel not found: {oidn}"
rng = np.random.default_rng(21)
color = np.concatenate([rng.uniform(0, 1, (24, 32, 3)), np.ones((24, 32, 1))], -1).astype(np.float32)
with hz.Device() as dev:
    for backend in ("classical", "neural"):
        with hz.Session(dev, backend=backend) as s:
            for f in range(2):
                out = s.process(color, frame_index=f)
            assert out.shape == (24, 32, 4) and np.isfinite(out).all()
            assert s.backend_name == backend, (backend, s.backend_name)
            print(f"ok: {backend} backend, {s.last_report['total_ms']:.1f} ms")
    with hz.Session(dev, backend="bypass", denoise="on") as s:
        s.process(color, frame_index=1)
        assert s.last_report["denoised"], s.last_report
        print("ok: denoise on (pyoidn wheel)")
print("ok: harmonizer", hz.__version__, "library", hz.version(), "from", lib)
PY

echo "== usd-harmonize on a hand-made stage"
# The stage is authored with the venv's usd-core and OpenImageIO (the
# fixture helper is read from the checkout without writing bytecode there).
run "$V/python" - "$ROOT/tests/usd" "$WORK/shot" <<'PY'
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, sys.argv[1])
import handmade

rng = np.random.default_rng(5)
frames = [1, 2, 3]
rgb = {f: rng.uniform(0, 1, (handmade.H, handmade.W, 3)).astype(np.float32) for f in frames}
stage = handmade.author(Path(sys.argv[2]), [handmade.Product("/Render/Beauty", "beauty.$F4.exr", rgb)], frames)
print("authored", stage)
PY
run "$V/usd-harmonize" "$WORK/shot/stage.usda" --frames 1-3 --backend classical --out-dir "$WORK/shot/out"
ls "$WORK"/shot/out/*/* 2>/dev/null || ls -R "$WORK/shot/out"
n=$(find "$WORK/shot/out" -name '*.exr' | wc -l)
[[ "$n" -eq 3 ]] || { echo "FAIL: usd-harmonize wrote $n EXR files, expected 3"; exit 1; }

echo "== the Blender zip reuses the binding wheel (offline, writes only into --out)"
run "$PY" -B "$ROOT/blender_addon/build.py" --binding-wheel "$hz_whl" --no-onnxruntime --no-oidn \
    --no-validate --out "$WORK/blender"
[[ "$(ls -A "$WORK/blender")" == "harmonizer-"*"-linux-x64.zip" ]] || { echo "FAIL: --out holds $(ls -A "$WORK/blender")"; exit 1; }
"$PY" - "$WORK"/blender/*.zip "$hz_whl" <<'PY'
import hashlib, os, sys, zipfile

zf = zipfile.ZipFile(sys.argv[1])
inner = zf.read("wheels/" + os.path.basename(sys.argv[2]))
assert hashlib.sha256(inner).digest() == hashlib.sha256(open(sys.argv[2], "rb").read()).digest(), "not the same wheel"
print("ok: the zip carries", os.path.basename(sys.argv[2]))
PY

after=$(git status --porcelain --ignored)
if [[ "$before" != "$after" ]]; then
    echo "FAIL: the checkout changed:"; diff <(echo "$before") <(echo "$after") || true; exit 1
fi
echo "wheels test passed (checkout unchanged)"
