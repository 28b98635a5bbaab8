"""Repacks a scene written unpacked (float arrays) into the committed format of ``sequences.pack``.

python3 -m training.ood.repack training/ood/data/courtyard
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from training.ood.sequences import pack, unpack


def repack(scene_dir: Path) -> None:
    f = Path(scene_dir) / "scene.npz"
    with np.load(f) as z:
        arrays = unpack(z) if any("@" in k for k in z.files) else {k: z[k] for k in z.files}
    tmp = f.with_name("scene.tmp.npz")
    np.savez_compressed(tmp, **pack(arrays))
    tmp.replace(f)


if __name__ == "__main__":
    for d in sys.argv[1:]:
        repack(Path(d))
        print(f"repack: {d}: {(Path(d) / 'scene.npz').stat().st_size / 1e6:.1f} MB")
