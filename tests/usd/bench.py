"""Per-frame cost of the USD hook, by stage (read, color, library, write).

    .venv-usd/bin/python tests/usd/bench.py [--scale 15] [--backend classical]

Copies the rendered fixture shot, scales its product files up by ``--scale``
(nearest; 15 gives 1920x1080; motion vectors scaled too), then runs
``PostFrameHook`` over frames 1001-1006 of each product and prints the median
of each stage. Numbers depend on the machine and its load; the library's own
time is its ``total_ms``.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
from pxr import Gf, Usd, UsdRender

sys.path.insert(0, str(Path(__file__).resolve().parent))

import fixtures
from usd_harmonizer import PostFrameHook


def scale_shot(src: Path, dst: Path, k: int) -> None:
    shutil.copytree(
        src, dst, ignore=shutil.ignore_patterns("blender", "reference", "harmonized")
    )
    stage = Usd.Stage.Open(str(dst / "shot.usda"))
    settings = UsdRender.Settings(stage.GetPrimAtPath("/Render/Settings"))
    settings.GetResolutionAttr().Set(Gf.Vec2i(fixtures.W * k, fixtures.H * k))
    stage.Save()
    for p in (dst / "render").rglob("*.exr"):
        inp = oiio.ImageInput.open(str(p))
        spec = oiio.ImageSpec(inp.spec())
        a = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, "float"))
        inp.close()
        a = np.repeat(np.repeat(a, k, 0), k, 1)
        for c in ("Vector.X", "Vector.Y"):
            if c in spec.channelnames:
                a[..., list(spec.channelnames).index(c)] *= k
        spec.width, spec.height = a.shape[1], a.shape[0]
        spec.full_width, spec.full_height = spec.width, spec.height
        out = oiio.ImageOutput.create(str(p))
        out.open(str(p), spec)
        out.write_image(a)
        out.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scale", type=int, default=15)
    ap.add_argument("--backend", default="classical")
    args = ap.parse_args()
    root = fixtures.build()
    with tempfile.TemporaryDirectory() as tmp:
        shot = Path(tmp) / "shot"
        scale_shot(root, shot, args.scale)
        w, h = fixtures.W * args.scale, fixtures.H * args.scale
        for product in ("beauty", "nomv"):
            with PostFrameHook(
                str(shot / "shot.usda"), products=[product], backend=args.backend
            ) as hook:
                res = [hook(f)[0] for f in fixtures.FRAMES]
            keys = ("read", "color", "library", "write", "total")
            med = {k: statistics.median(r.timings[k] for r in res[1:]) for k in keys}
            lib = statistics.median(r.total_ms for r in res[1:])
            print(
                f"{product} {w}x{h} {args.backend}: "
                + ", ".join(f"{k} {v:.0f} ms" for k, v in med.items())
                + f" (library total_ms {lib:.0f})"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
