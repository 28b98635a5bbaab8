"""Reads the multi-part multilayer EXR that Blender 5.0 writes (pip ``OpenEXR``).

Channels are found by name, never by position. The Vector pass is converted
to the library's motion-vector convention (``motion.x = Vector.X``,
``motion.y = -Vector.Y``: pixels, current -> previous, y down).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


class ExrError(RuntimeError):
    """A required channel is missing or malformed."""


def _channels(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    # Imported here: the modules that import this one (the renderers, the
    # benchmark's scene builders) are also used where only bpy is installed.
    import OpenEXR

    chans: dict[str, np.ndarray] = {}
    header: dict = {}
    with OpenEXR.File(str(path), separate_channels=True) as f:
        for part in f.parts:
            header.update({k: v for k, v in part.header.items() if isinstance(k, str)})
            for name, ch in part.channels.items():
                chans[name] = np.asarray(ch.pixels)
    return chans, header


def read_blender_exr(path: Path, layer: str = "ViewLayer") -> dict:
    """Returns ``rgba [H,W,4]``, ``depth [H,W]`` (planar), ``motion [H,W,2]``
    (library convention), ``normal [H,W,3]`` (world), ``albedo [H,W,3]``
    (the Denoising Albedo pass, when stored), ``crypto`` (list of
    (id, coverage) rank pairs) and ``crypto_manifest`` (object name -> hex id);
    entries whose passes are absent are missing from the dict, except Combined."""
    path = Path(path)
    chans, header = _channels(path)

    def get(name: str) -> np.ndarray:
        key = f"{layer}.{name}"
        if key not in chans:
            raise ExrError(f"{path}: channel '{key}' missing (have {sorted(chans)[:20]})")
        return chans[key].astype(np.float32)

    out: dict = {"rgba": np.stack([get(f"Combined.{c}") for c in "RGBA"], -1)}
    if f"{layer}.Depth.Z" in chans:
        out["depth"] = get("Depth.Z")
    if f"{layer}.Vector.X" in chans:
        out["motion"] = np.stack([get("Vector.X"), -get("Vector.Y")], -1)
    if f"{layer}.Normal.X" in chans:
        out["normal"] = np.stack([get(f"Normal.{c}") for c in "XYZ"], -1)
    if f"{layer}.Denoising Albedo.R" in chans:
        out["albedo"] = np.stack([get(f"Denoising Albedo.{c}") for c in "RGB"], -1)
    ranks = []
    k = 0
    while f"{layer}.CryptoObject{k:02d}.r" in chans:
        base = f"CryptoObject{k:02d}"
        ranks.append((get(f"{base}.r"), get(f"{base}.g")))
        ranks.append((get(f"{base}.b"), get(f"{base}.a")))
        k += 1
    if ranks:
        out["crypto"] = ranks
        manifest = {}
        for key, val in header.items():
            if key.startswith("cryptomatte/") and key.endswith("/manifest"):
                manifest.update(json.loads(val))
        out["crypto_manifest"] = manifest
    return out
