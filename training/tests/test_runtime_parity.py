"""The trained network's contract against the real runtime: the Python side
(encoding, input assembly, residual, decoding) must give what `harmonize run
--backend neural` gives for the same exported model.

Needs the `harmonize` binary (HZ_HARMONIZE, else target/release or target/debug)
and ONNX Runtime's library (HARMONIZER_ORT_LIB or ORT_DYLIB_PATH, else .venv's).
"""

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
OpenEXR = pytest.importorskip("OpenEXR")

from training import export as hz_export  # noqa: E402
from training.model import Enhancer, ModelConfig, assemble_input, decode, frame_scale  # noqa: E402
from training.synth.to_exr import write_exr  # noqa: E402

REPO = Path(__file__).resolve().parents[2]


def harmonize_binary():
    env = os.environ.get("HZ_HARMONIZE")
    cands = [Path(env)] if env else [REPO / "target/release/harmonize", REPO / "target/debug/harmonize"]
    return next((p for p in cands if p.exists()), None)


def ort_library():
    for v in ("HARMONIZER_ORT_LIB", "ORT_DYLIB_PATH"):
        if os.environ.get(v):
            return os.environ[v]
    libs = sorted((REPO / ".venv/lib").glob("python3*/site-packages/onnxruntime/capi/libonnxruntime.so.*"))
    return str(libs[-1]) if libs else None


@pytest.mark.parametrize("depth_tol,prior_input", [(0.0, False), (0.05, False), (0.0, True), (0.05, True)])
def test_harmonize_neural_matches_the_python_contract(tmp_path, depth_tol, prior_input):
    exe, lib = harmonize_binary(), ort_library()
    if exe is None or lib is None:
        pytest.skip(
            f"SKIPPED LOUDLY: needs the harmonize binary (found {exe}) and libonnxruntime (found {lib}); "
            "build with `cargo build --release -p harmonizer-cli` and run scripts/setup-venv.sh"
        )
    torch.manual_seed(0)
    # With a depth-aware prior the runtime also gives the disparity channel.
    # With `prior_input` the runtime computes the prior the graph reads
    # (manifest `prior`); the reference computes it in PyTorch.
    model = Enhancer(ModelConfig(widths=(8, 8, 12, 16), prior_depth_tol=depth_tol, prior_input=prior_input))
    torch.nn.init.normal_(model.head.weight, std=0.05)
    hz_export.export(model, tmp_path / "model")
    man = json.loads((tmp_path / "model.json").read_text())
    assert ("prior" in man) == prior_input and (man["input"]["channels"][-1] == "prior.b") == prior_input

    rng = np.random.default_rng(0)
    h, w = 75, 109  # not multiples of spatial_multiple: the far-side reflection counts
    base = rng.random((3, 5, 7)).astype(np.float32) * 2.0
    rgb = torch.nn.functional.interpolate(torch.from_numpy(base)[None], size=(h, w), mode="bilinear")[0].numpy()
    cov = np.ones((h, w), np.float32)
    cov[30:45, 40:70] = 0.0
    cov[29, 40:70] = 0.5
    rgb = rgb * cov
    insert = np.zeros((h, w), np.float32)
    insert[50:70, 10:30] = 1.0
    # Planar depth: a near object in front of a far wall, empty in the hole.
    depth = np.full((h, w), 8.0, np.float32)
    depth[:, :50] = 2.0
    depth[cov < 1] = 1e10
    channels = {"R": rgb[0], "G": rgb[1], "B": rgb[2], "A": cov, "mask.insert": insert}
    if depth_tol > 0:
        channels["Z"] = depth
    write_exr(tmp_path / "in.0001.exr", channels)
    env = dict(os.environ, ORT_DYLIB_PATH=lib, HARMONIZER_ORT_LIB=lib)
    cmd = [
        str(exe),
        "run",
        str(tmp_path / "in.####.exr"),
        "-o",
        str(tmp_path / "out.####.exr"),
        "--layout",
        "generic",
        "--backend",
        "neural",
        "--model",
        str(tmp_path / "model.onnx"),
        "--threads",
        "1",
        # The network's contract alone: the insert operations that follow it
        # on a frame with holes (the contact shadow under the mask) stay off,
        # and so does giving the insert's covered pixels their rendered color
        # back (`keep_covered`; these models have no repair margin).
        "--set",
        "harmonize=false",
        "--set",
        "contact_shadows=false",
        "--set",
        "keep_covered=false",
    ]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    assert p.returncode == 0, p.stderr
    with OpenEXR.File(str(tmp_path / "out.0001.exr"), separate_channels=True) as f:
        ch = f.channels()
        got = np.stack([np.asarray(ch[c].pixels, np.float32) for c in "RGB"])

    rgba = torch.from_numpy(np.concatenate([rgb, cov[None]])[None])
    scale = frame_scale(rgba, man["encoding"]["key"])
    x = assemble_input(
        model.cfg, rgba, torch.from_numpy(insert[None, None]), [], scale, torch.from_numpy(depth[None, None])
    )
    # The frame fits one tile: the runtime's window starts at the frame edge and is
    # the frame reflected on the far side up to a multiple of spatial_multiple
    # (core/src/backend/neural/tiling.rs).
    mult = man["spatial_multiple"]
    assert h <= man["tile_size"] and w <= man["tile_size"]
    wh = -(-h // mult) * mult
    ww = -(-w // mult) * mult
    xp = np.pad(x.numpy(), ((0, 0), (0, 0), (0, wh - h), (0, ww - w)), mode="reflect")
    with torch.no_grad():
        out = model(torch.from_numpy(xp))[:, :, :h, :w]
        want = decode(out, scale, man["encoding"]["log_range"])[0].numpy()
    rel = np.abs(got - want) / (np.abs(want) + 1e-2)
    worst = np.unravel_index(int(rel.argmax()), rel.shape)
    # 1e-3: float32 differences through a random network (straight color amplifies
    # them at soft edges); a layout or encoding mistake is off by far more. Below
    # 0.01 (the frame's colors reach 2) the bound is absolute, 1e-5: ONNX Runtime's
    # AVX2 kernels (no AVX-512) put one pixel of 3.1e-5 off by 1.2e-6 (3.7 %).
    assert rel.max() < 1e-3, f"max relative difference {rel.max()} at {worst}: got {got[worst]}, want {want[worst]}"
    # The correction is not trivial (the test would not notice a missing residual otherwise).
    assert np.abs(want - rgb).mean() > 1e-3
