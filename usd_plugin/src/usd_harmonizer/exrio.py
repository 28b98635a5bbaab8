"""EXR files through OpenImageIO (files only; color goes through PyOpenColorIO).

Every part (subimage) of a file is read with its spec; channels are looked up
by name, never by position (OpenImageIO reorders EXR channels). Writing keeps
every part, channel, pixel type and attribute, replaces the channels given,
adds attributes, and is atomic (a temporary file in the same directory, then
``os.replace``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio

from .errors import FrameError, ProductFileError


@dataclass
class Part:
    """One part (subimage) of an EXR: its spec and float32 pixels (H, W, C)."""

    spec: oiio.ImageSpec
    pixels: np.ndarray
    names: list[str] = field(default_factory=list)


@dataclass
class ExrImage:
    """All parts of an EXR, with a channel-name index."""

    path: Path
    parts: list[Part]

    @property
    def channel_names(self) -> list[str]:
        """Every channel name of every part."""
        return [n for p in self.parts for n in p.names]

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) of the first part's data window."""
        s = self.parts[0].spec
        return s.width, s.height

    def _locate(self, name: str) -> tuple[Part, int]:
        for p in self.parts:
            if name in p.names:
                return p, p.names.index(name)
        raise KeyError(name)

    def channel(self, name: str) -> np.ndarray:
        """One channel (H, W) float32 view."""
        p, i = self._locate(name)
        return p.pixels[..., i]

    def stack(self, names: list[str]) -> np.ndarray:
        """Channels stacked to (H, W, len(names)) float32 (a new array)."""
        return np.stack([self.channel(n) for n in names], axis=-1).astype(
            np.float32, copy=False
        )

    def set_channel(self, name: str, values: np.ndarray) -> None:
        """Replaces one channel's pixels."""
        p, i = self._locate(name)
        p.pixels[..., i] = values

    def attributes(self) -> dict[str, Any]:
        """Header attributes of the first part."""
        return {a.name: a.value for a in self.parts[0].spec.extra_attribs}


def read_exr(path: Path, where: str) -> ExrImage:
    """Reads every part of ``path``; ``where`` names the product and frame for errors."""
    if not path.is_file():
        raise ProductFileError(f"{where}: file {path} does not exist")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ProductFileError(f"{where}: cannot open {path}: {oiio.geterror()}")
    parts: list[Part] = []
    try:
        i = 0
        while inp.seek_subimage(i, 0):
            spec = inp.spec()
            data = inp.read_image(i, 0, 0, spec.nchannels, "float")
            if data is None:
                raise ProductFileError(
                    f"{where}: cannot read part {i} of {path}: {inp.geterror()}"
                )
            data = np.asarray(data, dtype=np.float32).reshape(
                spec.height, spec.width, spec.nchannels
            )
            if not data.flags.writeable:
                data = data.copy()
            parts.append(Part(oiio.ImageSpec(spec), data, list(spec.channelnames)))
            i += 1
    finally:
        inp.close()
    if not parts:
        raise ProductFileError(f"{where}: {path} has no image")
    dims = {(p.spec.width, p.spec.height, p.spec.x, p.spec.y) for p in parts}
    if len(dims) > 1:
        raise ProductFileError(
            f"{where}: the parts of {path} have different data windows {sorted(dims)}"
        )
    return ExrImage(path, parts)


def _set_attr(spec: oiio.ImageSpec, name: str, value: Any) -> None:
    if isinstance(value, bool):
        spec.attribute(name, "int", int(value))
    elif isinstance(value, int):
        spec.attribute(name, "int", value)
    elif isinstance(value, float):
        spec.attribute(name, "float", value)
    else:
        spec.attribute(name, str(value))


def write_exr_atomic(
    image: ExrImage, path: Path, attributes: dict[str, Any], where: str
) -> None:
    """Writes every part of ``image`` to ``path`` with ``attributes`` added to
    each part's header, through a temporary file renamed into place."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix or '.exr'}")
    specs = []
    for p in image.parts:
        spec = oiio.ImageSpec(p.spec)
        for k, v in attributes.items():
            _set_attr(spec, k, v)
        specs.append(spec)
    out = oiio.ImageOutput.create(str(tmp))
    if out is None:
        raise FrameError(f"{where}: cannot create {tmp}: {oiio.geterror()}")
    try:
        ok = (
            out.open(str(tmp), specs)
            if len(specs) > 1
            else out.open(str(tmp), specs[0])
        )
        if not ok:
            raise FrameError(
                f"{where}: cannot open {tmp} for writing: {out.geterror()}"
            )
        for i, p in enumerate(image.parts):
            if i > 0 and not out.open(str(tmp), specs[i], "AppendSubimage"):
                raise FrameError(
                    f"{where}: cannot append part {i} to {tmp}: {out.geterror()}"
                )
            if not out.write_image(np.ascontiguousarray(p.pixels)):
                raise FrameError(f"{where}: cannot write {tmp}: {out.geterror()}")
        if not out.close():
            raise FrameError(f"{where}: cannot finish {tmp}: {out.geterror()}")
    except BaseException:
        out.close()
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, path)
