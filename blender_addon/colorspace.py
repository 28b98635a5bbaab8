"""Color conversion between a file's scene-linear space and Linear Rec.709.

harmonizer works in scene-linear Linear Rec.709. Blender renders in its working
space (``bpy.data.colorspace.working_space``: 'Linear Rec.709', 'Linear
Rec.2020' or 'ACEScg') and Blender 5.0 tags the EXR with that space in the
``colorInteropID`` header attribute. The conversion runs through PyOpenColorIO
with Blender's own OCIO config (or ``$OCIO`` when set, as Blender itself does).

No ``bpy`` here: callers pass the config path and the space names.
"""

from __future__ import annotations

import os

import numpy as np

#: The space the library works in (a name in Blender's OCIO config).
LIBRARY_SPACE = "Linear Rec.709"


class ColorError(Exception):
    """A color space is unknown or a conversion failed."""


class Converter:
    """Converts premultiplied RGB between ``space`` and Linear Rec.709, both ways.

    The conversions between Blender's working spaces are 3x3 matrices, so they
    commute with premultiplication by coverage and round-trip exactly (to float
    precision). Arrays are converted in place.
    """

    def __init__(self, ocio, config_path: str, space: str):
        if not config_path or not os.path.isfile(config_path):
            raise ColorError(f"OpenColorIO config not found: {config_path!r}")
        try:
            self.config = ocio.Config.CreateFromFile(config_path)
        except Exception as exc:
            raise ColorError(f"{config_path}: cannot load OpenColorIO config: {exc}") from exc
        cs = self.config.getColorSpace(space)
        if cs is None:
            raise ColorError(
                f"color space {space!r} is not in the OpenColorIO config {config_path} "
                f"(expected a scene-linear space such as 'Linear Rec.709', 'Linear Rec.2020' or 'ACEScg')"
            )
        target = self.config.getColorSpace(LIBRARY_SPACE)
        if target is None:
            raise ColorError(f"color space {LIBRARY_SPACE!r} is not in the OpenColorIO config {config_path}")
        self.ocio = ocio
        self.space = cs.getName()
        self.identity = cs.getName() == target.getName()
        if self.identity:
            self._to_lib = self._from_lib = None
        else:
            self._to_lib = self.config.getProcessor(cs.getName(), target.getName()).getDefaultCPUProcessor()
            self._from_lib = self.config.getProcessor(target.getName(), cs.getName()).getDefaultCPUProcessor()

    def _apply(self, proc, rgb: np.ndarray) -> None:
        if proc is None:
            return
        if rgb.dtype != np.float32 or rgb.ndim != 3 or rgb.shape[2] < 3:
            raise ColorError(f"expected a float32 (H, W, >=3) array, got {rgb.dtype} {rgb.shape}")
        h, w, c = rgb.shape
        if c == 3 and rgb.flags.c_contiguous:
            proc.applyRGB(rgb)
            return
        # Not packed RGB: convert a packed copy and write it back.
        tmp = np.ascontiguousarray(rgb[:, :, :3])
        proc.applyRGB(tmp)
        rgb[:, :, :3] = tmp

    def to_library(self, rgb: np.ndarray) -> None:
        """Convert (H, W, >=3) float32 RGB from the file's space to Linear Rec.709, in place."""
        self._apply(self._to_lib, rgb)

    def from_library(self, rgb: np.ndarray) -> None:
        """Convert (H, W, >=3) float32 RGB from Linear Rec.709 back to the file's space, in place."""
        self._apply(self._from_lib, rgb)


def file_space(header_interop_id: str | None, ocio_config, fallback: str) -> str:
    """The color space of a file: its ``colorInteropID`` when the config knows it, else ``fallback``."""
    if header_interop_id:
        cs = ocio_config.getColorSpace(str(header_interop_id))
        if cs is not None:
            return cs.getName()
    return fallback
