#!/usr/bin/env bash
# Issue 21: install like a pipeline TD. Builds the wheels (scripts/wheels.sh,
# into a temporary directory), installs them into a clean python3.11 venv
# (not the checkout: harmonizer[neural,denoise] and usd_harmonizer), then with
# every HARMONIZER_* variable unset and the working directory outside the
# checkout: runs frames through harmonizer.Session (classical, neural with the
# onnxruntime wheel, denoise with the pyoidn wheel) and a small hand-made
# stage through usd-harmonize; checks the binding wheel's manylinux tag
# (auditwheel show agrees, nothing grafted: the runtimes stay dlopen()ed) and
# that usd_harmonizer's wheel pins harmonizer==0.2.*. Then the one command from
# a checkout: `pip install ROOT/usd_plugin` into another clean venv (no wheels,
# no variables) and the same stage through its usd-harmonize. Builds the
# Blender zip from the same binding wheel (offline). Fails when
# `git status --porcelain --ignored` of the checkout differs afterwards
# (nothing written into the source tree).
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

echo "== the binding wheel's manylinux tag, the library's dependencies"
case "$(basename "$hz_whl")" in
    harmonizer-*-py3-none-manylinux_*_x86_64.whl) ;;
    *) echo "FAIL: $(basename "$hz_whl") is not tagged py3-none-manylinux_*_x86_64"; exit 1 ;;
esac
AUDITWHEEL=$(command -v auditwheel || true)
[[ -z "$AUDITWHEEL" && -x "$ROOT/.venv/bin/auditwheel" ]] && AUDITWHEEL=$ROOT/.venv/bin/auditwheel
[[ -n "$AUDITWHEEL" ]] || { echo "FAIL: auditwheel not found (scripts/setup-venv.sh installs it into .venv)"; exit 1; }
tag=$(basename "$hz_whl" .whl); tag=${tag##*-}
shown=$("$AUDITWHEEL" show "$hz_whl" 2>/dev/null | tr '\n' ' ' | sed -n 's/.*consistent with the following platform tag: *"\([^"]*\)".*/\1/p')
[[ "$shown" == "$tag" ]] || { echo "FAIL: the wheel says $tag, auditwheel show says '$shown'"; exit 1; }
"$PY" - "$hz_whl" "$WORK/lib" <<'PY'
import subprocess, sys, zipfile

zf = zipfile.ZipFile(sys.argv[1])
libs = [n for n in zf.namelist() if ".so" in n]
assert libs == ["harmonizer/lib/libharmonizer.so"], f"the wheel holds {libs}: something was grafted"
lib = zf.extract(libs[0], sys.argv[2])
dyn = subprocess.run(["readelf", "-d", lib], check=True, capture_output=True, text=True).stdout
needed = sorted(l.split("[")[1].rstrip("]") for l in dyn.splitlines() if "(NEEDED)" in l)
system = {"libc.so.6", "libm.so.6", "libgcc_s.so.1", "ld-linux-x86-64.so.2", "libpthread.so.0", "libdl.so.2"}
assert set(needed) <= system, f"libharmonizer needs {needed}: ONNX Runtime and OIDN must stay dlopen()ed"
print("ok: one library, needs only", ", ".join(needed))
PY
echo "ok: $(basename "$hz_whl"), auditwheel show agrees ($shown)"
# The metadata taken whole before it is searched (`unzip | grep -q` fails
# under pipefail when grep stops reading early and unzip gets SIGPIPE).
usd_meta=$(unzip -p "$usd_whl" '*.dist-info/METADATA')
grep -q '^Requires-Dist: harmonizer==0\.2\.\*$' <<<"$usd_meta" ||
    { echo "FAIL: $(basename "$usd_whl") does not require harmonizer==0.2.*:"; grep Requires-Dist <<<"$usd_meta"; exit 1; }
if grep -q 'file:' <<<"$usd_meta"; then
    echo "FAIL: $(basename "$usd_whl") names a local path"; exit 1
fi
echo "ok: $(basename "$usd_whl") requires harmonizer==0.2.*"
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

echo "== pip install ROOT/usd_plugin in a clean venv: the one command from a checkout"
# As a user would: the checkout's path, the working directory outside it, no
# HARMONIZER_* variable and bytecode not suppressed (the build hooks must take
# back their own). pip builds in place; usd_plugin/hatch_build.py names the
# checkout's ../ffi/python as the binding, which pip builds too (cargo reuses
# CARGO_TARGET_DIR when set).
"$PY" -m venv "$WORK/venv-src"
(cd "$WORK" && env "${unset_env[@]}" -u PYTHONDONTWRITEBYTECODE -u USD_HARMONIZER_BINDING \
    "$WORK/venv-src/bin/python" -m pip install --quiet --disable-pip-version-check "$ROOT/usd_plugin")
run "$WORK/venv-src/bin/python" - "$ROOT" <<'PY'
import json, sys
from importlib.metadata import distribution
from pathlib import Path

root = Path(sys.argv[1])
# The binding came from the checkout's ffi/python (so usd_plugin was built in
# place: a copy elsewhere has no ../ffi/python and would have asked PyPI).
url = json.loads(distribution("harmonizer").read_text("direct_url.json"))["url"]
assert url == (root / "ffi" / "python").as_uri(), url
req = sorted(r for r in distribution("usd_harmonizer").requires if r.startswith("harmonizer"))
assert req == [f"harmonizer @ {url}"] + [f"harmonizer[{e}] @ {url} ; extra == '{e}'" for e in ("denoise", "neural")], req
import harmonizer
from harmonizer import _native

lib = Path(_native.lib()._name).resolve()
assert lib.is_relative_to(Path(sys.prefix).resolve()), f"not the installed wheel's library: {lib}"
print("ok: harmonizer", harmonizer.__version__, "from", url, "library", lib.name)
PY
run "$WORK/venv-src/bin/usd-harmonize" "$WORK/shot/stage.usda" --frames 1-3 --backend classical --out-dir "$WORK/shot/out-src"
n=$(find "$WORK/shot/out-src" -name '*.exr' | wc -l)
[[ "$n" -eq 3 ]] || { echo "FAIL: usd-harmonize (installed from the checkout) wrote $n EXR files, expected 3"; exit 1; }
echo "ok: usd-harmonize installed by pip install $ROOT/usd_plugin"

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
