"""Writes one sample as `generic`-layout EXR frames, the library's input format.

    .venv-bpy/bin/python -m training.synth.to_exr training/data/test/scene_000009 s1_recon -o /tmp/s1

writes ``/tmp/s1/input.####.exr`` (R,G,B premultiplied, A coverage, Z planar
depth, motion.X/Y, N.X/Y/Z, mask.insert; header ``worldToCamera`` and
``worldToNDC``) and ``/tmp/s1/target.####.exr`` (R,G,B,A=1), frames numbered
from 1, so ``harmonize run`` can process the input and be compared with the target.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import OpenEXR

from training.synth.dataset import load_sample


def write_exr(path: Path, channels: dict[str, np.ndarray], header: dict | None = None) -> None:
    hdr = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    hdr.update(header or {})
    chans = {k: np.ascontiguousarray(v, np.float32) for k, v in channels.items()}
    tmp = path.with_name(path.name + ".tmp.exr")
    with OpenEXR.File(hdr, chans) as f:
        f.write(str(tmp))
    tmp.replace(path)


def frame_channels(s: dict, t: int) -> tuple[dict[str, np.ndarray], dict]:
    """The generic-layout channels and the camera header of frame ``t`` of a sample."""
    inp = s["input"][t]
    chans = {
        "R": inp[..., 0],
        "G": inp[..., 1],
        "B": inp[..., 2],
        "A": inp[..., 3],
        "Z": s["depth"][t],
        "motion.X": s["motion"][t, ..., 0],
        "motion.Y": s["motion"][t, ..., 1],
        "N.X": s["normal"][t, ..., 0],
        "N.Y": s["normal"][t, ..., 1],
        "N.Z": s["normal"][t, ..., 2],
        "mask.insert": s["mask_insert"][t],
    }
    # The render's denoising passes when the sample has them (Cycles' Denoising Albedo / Normal).
    if "albedo" in s:
        chans.update({f"albedo.{c}": s["albedo"][t, ..., i] for i, c in enumerate("RGB")})
    if "aux_normal" in s:
        chans.update({f"denoise_normal.{c}": s["aux_normal"][t, ..., i] for i, c in enumerate("XYZ")})
    header = {}
    if "world_to_camera" in s:
        header = {
            "worldToCamera": np.ascontiguousarray(s["world_to_camera"][t], np.float32),
            "worldToNDC": np.ascontiguousarray(s["world_to_ndc"][t], np.float32),
        }
    return chans, header


def sample_to_exr(scene_dir: Path, stream: str, out: Path) -> int:
    s = load_sample(scene_dir, stream)
    out.mkdir(parents=True, exist_ok=True)
    T = s["input"].shape[0]
    for t in range(T):
        chans, header = frame_channels(s, t)
        write_exr(out / f"input.{t + 1:04d}.exr", chans, header)
        tg = s["target"][t]
        write_exr(
            out / f"target.{t + 1:04d}.exr",
            {"R": tg[..., 0], "G": tg[..., 1], "B": tg[..., 2], "A": np.ones(tg.shape[:2], np.float32)},
            header,
        )
    return T


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene_dir", type=Path)
    ap.add_argument("stream")
    ap.add_argument("-o", "--out", type=Path, required=True)
    args = ap.parse_args(argv)
    n = sample_to_exr(args.scene_dir, args.stream, args.out)
    print(f"to_exr: wrote {n} input and target frames to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
