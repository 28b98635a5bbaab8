#!/usr/bin/env bash
# Smoke test of the data generator and the trainer on a tiny configuration:
# checks training/'s lint and format (ruff),
# renders one tiny scene (one sample of each stream) and one of the
# reconstruction stream alone with Blender,
# checks the samples and their conventions, trains 2 steps, exports to ONNX
# and checks the export against PyTorch in ONNX Runtime.
#
#   bash training/smoke_test.sh            (uses .venv-bpy and .venv-train)
#   HZ_BPY_PYTHON=... HZ_TRAIN_PYTHON=... bash training/smoke_test.sh
#
# Needs: bpy 5.0.1 + OpenEXR (training/requirements-synth.txt), torch + onnx +
# onnxruntime (training/requirements.txt), the sweethome3d-furniture package
# (installed by the script with apt-get when run as root). training/setup_env.sh
# creates the two venvs when they are missing.
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
repo="$(dirname "$here")"
bpy_py="${HZ_BPY_PYTHON:-$repo/.venv-bpy/bin/python}"
train_py="${HZ_TRAIN_PYTHON:-$repo/.venv-train/bin/python}"
if [ -z "${HZ_BPY_PYTHON:-}${HZ_TRAIN_PYTHON:-}" ]; then
  "$here/setup_env.sh"
fi
for p in "$bpy_py" "$train_py"; do
  if [ ! -x "$p" ]; then
    echo "smoke_test: interpreter $p not found; see training/README.md (Setup)" >&2
    exit 2
  fi
done
work="$(mktemp -d "${TMPDIR:-/tmp}/hz-smoke.XXXXXX")"
trap 'rm -rf "$work"' EXIT
cd "$repo"

echo "== lint and format (ruff, training/ruff.toml)"
"$train_py" -m ruff check --quiet --config training/ruff.toml training
"$train_py" -m ruff format --quiet --check --config training/ruff.toml training

echo "== unit tests (numpy, torch, ONNX Runtime)"
# test_quality.py needs the benchmark's peers (OpenCV, pyoidn): scripts/quality.sh --smoke runs it in .venv-quality.
"$train_py" -m pytest -q -p no:cacheprovider -W ignore::DeprecationWarning training/tests \
    --ignore=training/tests/test_quality.py

echo "== assets"
"$bpy_py" -m training.synth.assets --no-attribution

echo "== render 1 tiny scene (6 streams)"
start=$(date +%s)
nice -n 10 "$bpy_py" -m training.synth.render_scene --scene-id 0 --out "$work/data/train/scene_000000" \
  --width 64 --height 48 --frames 3 --samples 4 --threads 2 > "$work/render.log" 2>&1 || {
  tail -40 "$work/render.log" >&2
  echo "smoke_test: render failed" >&2
  exit 1
}
echo "rendered in $(( $(date +%s) - start )) s"

echo "== check samples"
"$train_py" - "$work/data/train/scene_000000" <<'PY'
import sys
import numpy as np
from training.synth.dataset import STREAMS, load_sample, scene_streams

d = sys.argv[1]
fail = []
if scene_streams(d) != list(STREAMS):
    fail.append(f"streams {scene_streams(d)} != {list(STREAMS)}")
for st in STREAMS:
    s = load_sample(d, st)
    T, H, W, C = s["input"].shape
    if (T, H, W, C) != (3, 48, 64, 4):
        fail.append(f"{st}: input shape {s['input'].shape}")
    for k in ("input", "target", "motion", "normal", "mask_insert", "mask_shadow"):
        if not np.isfinite(s[k]).all():
            fail.append(f"{st}: {k} has NaN/Inf")
    cov = s["input"][..., 3]
    if cov.min() < 0 or cov.max() > 1:
        fail.append(f"{st}: coverage outside [0,1]: {cov.min()}..{cov.max()}")
    if (s["depth"] <= 0).any():
        fail.append(f"{st}: non-positive depth")
    if s["world_to_camera"].shape != (3, 4, 4):
        fail.append(f"{st}: camera shape {s['world_to_camera'].shape}")
    diff = np.abs(s["input"][..., :3] - s["target"]).mean()
    if diff <= 1e-5:
        fail.append(f"{st}: input equals target (mean |diff| {diff})")
    print(f"{st}: mean |input-target| {diff:.4f}, coverage mean {cov.mean():.3f}, "
          f"insert {s['mask_insert'].mean():.3f}, shadow {s['mask_shadow'].mean():.3f}")
meta = load_sample(d, "s2_tone")["meta"]
chk = meta["checks"]
print("checks:", chk)
if chk["median_px_err_camera_vs_motion"] > 0.1:
    fail.append(f"camera matrices disagree with motion vectors by {chk['median_px_err_camera_vs_motion']} px")
if chk["mean_abs_err_warped_prev"] > chk["mean_abs_err_unwarped_prev"] * 1.05 + 1e-3:
    fail.append("motion vectors do not align the previous frame: " + str(chk))
if load_sample(d, "s2_tone")["mask_insert"].max() < 0.5:
    fail.append("insert mask is empty")
if fail:
    print("smoke_test: FAILED:\n  " + "\n  ".join(fail), file=sys.stderr)
    sys.exit(1)
PY

echo "== render 1 tiny scene of the reconstruction stream only (--streams recon, 4 frames)"
nice -n 10 "$bpy_py" -m training.synth.render_scene --scene-id 1 --out "$work/data/train/scene_000001" \
  --width 64 --height 48 --frames 4 --samples 4 --threads 2 --streams recon > "$work/render_recon.log" 2>&1 || {
  tail -40 "$work/render_recon.log" >&2
  echo "smoke_test: render --streams recon failed" >&2
  exit 1
}
"$train_py" - "$work/data/train/scene_000001" <<'PY'
import json
import sys
from pathlib import Path

import numpy as np
from training.synth.dataset import load_sample, redegrade, scene_streams

d = Path(sys.argv[1])
fail = []
if scene_streams(d) != ["s1_recon"]:
    fail.append(f"streams {scene_streams(d)} != ['s1_recon']")
if sorted(p.name for p in d.iterdir()) != ["ctx.npz", "meta.json", "s1_recon.npz", "scene.npz"]:
    fail.append(f"files {sorted(p.name for p in d.iterdir())}")
s = load_sample(d, "s1_recon")
# The context views kept in ctx.npz give the stream back with the scene's own seed.
again = redegrade(d, np.random.default_rng([1, 1, 1]))
if not np.array_equal(again["input"][..., 3], s["input"][..., 3]) or not np.array_equal(again["depth"], s["depth"]):
    fail.append("re-degrading ctx.npz with the scene's seed changes the coverage or the depth")
if np.abs(again["input"][..., :3] - s["input"][..., :3]).max() > 2e-3 * max(1.0, float(s["input"][..., :3].max())):
    fail.append("re-degrading ctx.npz with the scene's seed changes the colors")
if s["input"].shape != (4, 48, 64, 4):
    fail.append(f"input shape {s['input'].shape}")
if s["mask_shadow"].any():
    fail.append("mask_shadow is not all zeros without a noinsert pass")
if not (s["input"][..., 3] < 0.95).any():
    fail.append("the reconstruction has no holes")
if json.loads((d / "meta.json").read_text()).get("rendered_streams") != "recon":
    fail.append("meta.json does not say rendered_streams: recon")
if fail:
    print("smoke_test: FAILED (--streams recon):\n  " + "\n  ".join(fail), file=sys.stderr)
    sys.exit(1)
print(f"s1_recon only: input {s['input'].shape}, coverage mean {s['input'][..., 3].mean():.3f}")
PY

echo "== the context views of an existing scene rendered again (--context-only)"
mv "$work/data/train/scene_000001/ctx.npz" "$work/ctx_first.npz"
nice -n 10 "$bpy_py" -m training.synth.render_scene --scene-id 1 --out "$work/data/train/scene_000001" \
  --threads 2 --context-only > "$work/render_ctx.log" 2>&1 || {
  tail -40 "$work/render_ctx.log" >&2
  echo "smoke_test: render --context-only failed or the scene did not rebuild the same" >&2
  exit 1
}
tail -1 "$work/render_ctx.log"
"$train_py" - "$work/ctx_first.npz" "$work/data/train/scene_000001/ctx.npz" <<'PY'
import sys

import numpy as np

with np.load(sys.argv[1]) as a, np.load(sys.argv[2]) as b:
    same = all(np.array_equal(a[k], b[k]) for k in ("depth", "world_to_camera", "world_to_ndc"))
    err = float(np.abs(a["color"].astype(np.float32) - b["color"]).max())
if not same or err > 0.05:
    print(f"smoke_test: FAILED: the context views rendered again differ (geometry same: {same}, color {err})",
          file=sys.stderr)
    sys.exit(1)
print(f"context views rendered again: geometry identical, color within {err:.4f}")
PY

echo "== train 2 steps (both scenes)"
"$train_py" -m training.train --data "$work/data" --run "$work/run" --steps 2 --batch 1 --crop 48 64 \
  --unroll 2 --widths 8 8 12 16 --log-every 1 --ckpt-every 1 --p-no-history 0 --redegrade 3

echo "== reconstruction variants from the kept context views (--redegrade)"
"$train_py" - "$work/data" <<'PY'
import sys
from pathlib import Path

import numpy as np
from training.synth.dataset import list_scenes, redegrade
from training.train import SampleCache, batch_rng, make_batch

scenes = list_scenes(Path(sys.argv[1]), "train")
cfg = {"batch": 4, "crop": [48, 64], "unroll": 2, "context_frames": 4, "p_no_history": 0.0,
       "p_drop_insert": 0.0, "p_flicker": 0.0, "streams": "s1_recon"}
a, b = (SampleCache(scenes, 8, ("s1_recon",), redegrade=3, seed=1) for _ in range(2))
fail = []
if set(a.variants.values()) != {3}:
    fail.append(f"variants {a.variants}")
s1 = scenes[1]
v0, v2 = a.get(s1, "s1_recon", 0), a.get(s1, "s1_recon", 2)
want = redegrade(s1, np.random.default_rng([1, 1, 1, 2]))
if not np.array_equal(v2["input"], want["input"]) or np.array_equal(v2["input"][..., 3], v0["input"][..., 3]):
    fail.append("variant 2 is not the scene made again with the seed [1, 1, 1, 2]")
# A batch depends on (seed, step) alone, whatever the cache holds.
for step in range(3):
    x, y = make_batch(a, batch_rng(1, step), cfg), make_batch(b, batch_rng(1, step), cfg)
    if not all(np.array_equal(np.asarray(x[k]), np.asarray(y[k])) for k in x if hasattr(x[k], "shape")):
        fail.append(f"batch {step} differs between two caches")
if fail:
    print("smoke_test: FAILED (--redegrade):\n  " + "\n  ".join(fail), file=sys.stderr)
    sys.exit(1)
print("redegrade: 3 variants a scene, batches repeatable")
PY

echo "== resume to step 3 (batches made ahead by a worker process)"
"$train_py" -m training.train --data "$work/data" --run "$work/run" --steps 3 --batch 1 --crop 48 64 \
  --unroll 2 --log-every 1 --ckpt-every 1 --workers 1 | tee "$work/resume.log"
grep -q "resumed .* at step 2" "$work/resume.log"

echo "== export"
"$train_py" -m training.export --ckpt "$work/run/ckpt_last.pt" --out "$work/model"
echo "smoke_test: 1 passed, 0 failed"
