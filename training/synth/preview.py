"""Contact sheet of one rendered scene: per stream, input over target, plus masks.

    python -m training.synth.preview training/data/train/scene_000000 -o sheet.png

Needs only numpy (writes PNG itself). Color is shown through the sRGB
transfer function, clipped; masks as grey.
"""

from __future__ import annotations

import argparse
import struct
import sys
import zlib
from pathlib import Path

import numpy as np

from training.synth.dataset import load_sample, scene_streams


def to_srgb8(rgb: np.ndarray) -> np.ndarray:
    c = np.clip(np.nan_to_num(rgb.astype(np.float32)), 0.0, 1.0)
    c = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)
    return (c * 255 + 0.5).astype(np.uint8)


def write_png(path: Path, img: np.ndarray) -> None:
    """Writes an 8-bit RGB ``[H, W, 3]`` image as PNG."""
    h, w, _ = img.shape
    raw = b"".join(b"\x00" + img[i].tobytes() for i in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    tmp = Path(str(path) + ".tmp")
    tmp.write_bytes(png)
    tmp.replace(path)


def sheet(scene_dir: Path, frames: list[int] | None = None) -> np.ndarray:
    rows = []
    for stream in scene_streams(scene_dir):
        s = load_sample(scene_dir, stream)
        T = s["input"].shape[0]
        fr = frames or [0, T // 2, T - 1]
        row_in = np.concatenate([to_srgb8(s["input"][t, ..., :3]) for t in fr], 1)
        row_gt = np.concatenate([to_srgb8(s["target"][t]) for t in fr], 1)
        cov = s["input"][fr[0], ..., 3]
        masks = np.stack([cov, s["mask_insert"][fr[0]], s["mask_shadow"][fr[0]]], -1)
        rows.append(np.concatenate([row_in, to_srgb8(masks)], 1))
        rows.append(np.concatenate([row_gt, np.zeros_like(to_srgb8(masks))], 1))
    return np.concatenate(rows, 0)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene_dir", type=Path)
    ap.add_argument("-o", "--output", type=Path, required=True)
    args = ap.parse_args(argv)
    write_png(args.output, sheet(args.scene_dir))
    print(f"preview: wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
