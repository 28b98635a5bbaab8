"""Writes docs/images/usd_before_after.png: frame 1003 of the fixture shot's
beauty product before and after ``usd-harmonize --backend classical``.

    .venv-usd/bin/python tests/usd/docs_image.py SHOT_DIR OUT.png

SHOT_DIR holds ``render/beauty.1003.exr`` and ``render/harmonized/beauty.1003.exr``.
Display: Linear Rec.709 -> sRGB through ocio://default, 3x nearest upscale.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import PyOpenColorIO as ocio
from usd_harmonizer.exrio import read_exr


def to_srgb(rgb: np.ndarray) -> np.ndarray:
    cfg = ocio.Config.CreateFromFile("ocio://default")
    cpu = cfg.getProcessor(
        "lin_rec709_srgb", "srgb_rec709_scene"
    ).getDefaultCPUProcessor()
    out = np.ascontiguousarray(np.clip(rgb, 0, 1), np.float32).copy()
    cpu.applyRGB(out)
    return out


def main(shot_dir: str, out: str) -> int:
    d = Path(shot_dir)
    a = read_exr(d / "render/beauty.1003.exr", "before").stack(["R", "G", "B"])
    b = read_exr(d / "render/harmonized/beauty.1003.exr", "after").stack(
        ["R", "G", "B"]
    )
    gap = np.ones((a.shape[0], 4, 3), np.float32)
    img = np.concatenate([to_srgb(a), gap, to_srgb(b)], axis=1)
    img = np.repeat(np.repeat(img, 3, 0), 3, 1)
    spec = oiio.ImageSpec(img.shape[1], img.shape[0], 3, "uint8")
    o = oiio.ImageOutput.create(out)
    o.open(out, spec)
    o.write_image((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
    o.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
