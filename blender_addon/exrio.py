"""Multi-part OpenEXR reading and writing for the Blender extension.

Blender 5.0 writes a multilayer EXR as one part per pass (``ViewLayer.Combined``,
``ViewLayer.Depth``, ``ViewLayer.Vector``, ...). This module reads every part
(spec, header attributes and pixels, each channel in its stored precision),
finds channels by name, and writes a file back with every part and channel
kept, atomically (a temporary file beside the target, then a rename).

It uses the OpenImageIO Python module that Blender ships; it imports no ``bpy``
so the same code serves the render handler and the batch operator.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field

import numpy as np


class ExrError(Exception):
    """A file could not be read or written, or lacks a channel; names the file."""


@dataclass
class Part:
    """One part (OIIO subimage) of a multi-part EXR: its spec and pixels."""

    spec: object  # OpenImageIO.ImageSpec
    pixels: np.ndarray  # (H, W, C) float32 (converted from half on read)

    @property
    def name(self) -> str:
        """The part name (``ViewLayer.Combined``), or '' for a single-part file."""
        return self.spec.get_string_attribute("name", "") or self.spec.get_string_attribute("oiio:subimagename", "")

    @property
    def channels(self) -> list[str]:
        """Full channel names of this part."""
        return list(self.spec.channelnames)


@dataclass
class MultiPartExr:
    """Every part of an EXR file, in file order."""

    path: str
    parts: list[Part] = field(default_factory=list)

    @property
    def width(self) -> int:
        """Width of the first part's data window."""
        return self.parts[0].spec.width

    @property
    def height(self) -> int:
        """Height of the first part's data window."""
        return self.parts[0].spec.height

    def attribute(self, name: str, default=None):
        """A header attribute of the first part that has it."""
        for part in self.parts:
            if part.spec.getattribute(name) is not None:
                return part.spec.getattribute(name)
        return default

    def channel_names(self) -> list[str]:
        """Every channel name in the file, in file order."""
        return [c for part in self.parts for c in part.channels]

    def find(self, name: str) -> tuple[int, int] | None:
        """(part index, channel index) of a channel found by its full name."""
        for pi, part in enumerate(self.parts):
            chans = part.channels
            if name in chans:
                return pi, chans.index(name)
        return None

    def has(self, name: str) -> bool:
        """Whether the file holds the channel ``name``."""
        return self.find(name) is not None

    def channel(self, name: str) -> np.ndarray:
        """The (H, W) float32 view of one channel, found by name."""
        loc = self.find(name)
        if loc is None:
            raise ExrError(f"{self.path}: channel {name!r} not found (channels: {', '.join(self.channel_names())})")
        pi, ci = loc
        return self.parts[pi].pixels[:, :, ci]

    def channels(self, names: list[str]) -> np.ndarray:
        """(H, W, len(names)) float32 of several channels found by name.

        A view into the part's pixels when the channels are adjacent in one
        part (no copy), else a stacked copy.
        """
        locs = [self.find(n) for n in names]
        for n, loc in zip(names, locs, strict=True):
            if loc is None:
                raise ExrError(f"{self.path}: channel {n!r} not found (channels: {', '.join(self.channel_names())})")
        pis = {pi for pi, _ in locs}
        idx = [ci for _, ci in locs]
        if len(pis) == 1 and idx == list(range(idx[0], idx[0] + len(idx))):
            pi = locs[0][0]
            return self.parts[pi].pixels[:, :, idx[0] : idx[0] + len(idx)]
        return np.stack([self.channel(n) for n in names], axis=-1)

    def set_channels(self, names: list[str], values: np.ndarray) -> None:
        """Replace channels (found by name) with ``values`` (H, W, len(names))."""
        for k, n in enumerate(names):
            loc = self.find(n)
            if loc is None:
                raise ExrError(f"{self.path}: channel {n!r} not found")
            pi, ci = loc
            self.parts[pi].pixels[:, :, ci] = values[:, :, k]


def _oiio_error(oiio, obj=None) -> str:
    msg = ""
    if obj is not None:
        try:
            msg = obj.geterror()
        except Exception:  # pragma: no cover - depends on the OIIO build
            msg = ""
    return msg or oiio.geterror() or "unknown OpenImageIO error"


def read(oiio, path: str) -> MultiPartExr:
    """Read every part of the EXR at ``path`` (pixels as float32)."""
    if not os.path.isfile(path):
        raise ExrError(f"{path}: file not found")
    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise ExrError(f"{path}: cannot open: {_oiio_error(oiio)}")
    try:
        if inp.format_name() != "openexr":
            raise ExrError(f"{path}: not an OpenEXR file (format {inp.format_name()!r})")
        exr = MultiPartExr(path)
        index = 0
        while inp.seek_subimage(index, 0):
            spec = inp.spec(index, 0)
            if spec.deep:
                raise ExrError(f"{path}: part {index} is a deep image, which is not supported")
            # Name the part explicitly: the (chbegin, chend) form reads the first part.
            pixels = inp.read_image(index, 0, 0, spec.nchannels, oiio.FLOAT)
            if pixels is None or not isinstance(pixels, np.ndarray):
                part_name = spec.get_string_attribute("name", "")
                raise ExrError(f"{path}: part {index} ({part_name}): cannot read pixels: {_oiio_error(oiio, inp)}")
            pixels = np.ascontiguousarray(pixels.reshape(spec.height, spec.width, spec.nchannels), dtype=np.float32)
            exr.parts.append(Part(oiio.ImageSpec(spec), pixels))
            index += 1
        if not exr.parts:
            raise ExrError(f"{path}: no image parts")
        return exr
    finally:
        inp.close()


def write(oiio, exr: MultiPartExr, path: str, *, extra_attributes: dict | None = None) -> None:
    """Write every part of ``exr`` to ``path`` atomically.

    Each part keeps its spec: channel names, per-channel precision (half or
    float), compression and header attributes. ``extra_attributes`` (name ->
    str/int/float) are added to the first part's header.
    """
    directory = os.path.dirname(os.path.abspath(path)) or "."
    os.makedirs(directory, exist_ok=True)
    specs = []
    for k, part in enumerate(exr.parts):
        spec = oiio.ImageSpec(part.spec)
        if k == 0 and extra_attributes:
            for key, value in extra_attributes.items():
                spec.attribute(key, value)
        specs.append(spec)
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".tmp.exr", dir=directory)
    os.close(fd)
    try:
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise ExrError(f"{path}: cannot create an EXR writer: {_oiio_error(oiio)}")
        if len(specs) > 1 and not out.supports("multiimage"):
            raise ExrError(f"{path}: this OpenImageIO build cannot write multi-part EXR")
        ok = out.open(tmp, specs) if len(specs) > 1 else out.open(tmp, specs[0], "Create")
        if not ok:
            raise ExrError(f"{path}: cannot open for writing: {_oiio_error(oiio, out)}")
        try:
            for k, (spec, part) in enumerate(zip(specs, exr.parts, strict=True)):
                if k > 0 and not out.open(tmp, spec, "AppendSubimage"):
                    raise ExrError(f"{path}: cannot append part {k} ({part.name}): {_oiio_error(oiio, out)}")
                if not out.write_image(np.ascontiguousarray(part.pixels, dtype=np.float32)):
                    raise ExrError(f"{path}: cannot write part {k} ({part.name}): {_oiio_error(oiio, out)}")
        finally:
            out.close()
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
