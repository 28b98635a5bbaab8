"""Color conversion with PyOpenColorIO (never OpenImageIO's bundled OCIO).

The library works in scene-linear Linear Rec.709. A product's color space
comes from the var or product (``harmonizer:colorSpace``, ``colorSpace``,
``colorSpace:name``), else the file (``colorInteropID``, ``oiio:ColorSpace``),
else the settings' ``renderingColorSpace``, else the config's
``scene_linear`` role. The config is ``$OCIO`` when set, else
``ocio://default``. Names are resolved through aliases and color interop IDs
(``lin_ap1_scene`` finds ACEScg).

New products are declared on the stage with UsdColorSpaceAPI, whose
``colorSpace:name`` is one of USD's color space tokens (``GfColorSpaceNames``:
``lin_ap1_scene``, ``lin_rec709_scene``, ...): :func:`usd_color_space_name`
maps an OCIO color space to the token.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import PyOpenColorIO as ocio

from .errors import ColorSpaceError

#: Interop ID and common names of the library's working space.
LINEAR_REC709 = (
    "lin_rec709_scene",
    "lin_rec709_srgb",
    "Linear Rec.709 (sRGB)",
    "Linear Rec.709",
    "lin_rec709",
)

_configs: dict[str, ocio.Config] = {}


def _usd_tokens() -> frozenset[str]:
    try:
        from pxr import Gf

        names = Gf.ColorSpaceNames
    except (ImportError, AttributeError):  # usd-core before GfColorSpace
        return frozenset(
            (
                "lin_ap0_scene",
                "lin_ap1_scene",
                "lin_rec709_scene",
                "lin_rec2020_scene",
                "lin_p3d65_scene",
                "lin_adobergb_scene",
                "lin_ciexyzd65_scene",
                "srgb_rec709_scene",
                "srgb_p3d65_scene",
                "srgb_ap1_scene",
                "g18_rec709_scene",
                "g22_rec709_scene",
                "g24_rec709_scene",
                "g22_ap1_scene",
                "g22_adobergb_scene",
                "identity",
                "raw",
                "data",
            )
        )
    return frozenset(
        str(getattr(names, n))
        for n in dir(names)
        if not n.startswith("_") and n != "Unknown"
    )


#: USD's color space tokens (``GfColorSpaceNames``), the values
#: UsdColorSpaceAPI's ``colorSpace:name`` takes.
USD_COLOR_SPACE_NAMES = _usd_tokens()


def load_config(path: str | None = None) -> tuple[ocio.Config, str]:
    """The OCIO config: ``path``, else ``$OCIO``, else ``ocio://default``."""
    src = path or os.environ.get("OCIO") or "ocio://default"
    if src not in _configs:
        try:
            _configs[src] = ocio.Config.CreateFromFile(src)
        except Exception as e:  # OCIO raises its own Exception type
            raise ColorSpaceError(f"OCIO config {src}: cannot load: {e}") from e
    return _configs[src], src


def find_color_space(config: ocio.Config, name: str) -> ocio.ColorSpace | None:
    """A color space by name, alias (case-insensitive) or interop ID."""
    cs = config.getColorSpace(name)
    if cs is not None:
        return cs
    low = name.lower()
    for cs in config.getColorSpaces():
        iid = cs.getInteropID() if hasattr(cs, "getInteropID") else ""
        if iid and iid.lower() == low:
            return cs
    return None


def usd_color_space_name(cs: ocio.ColorSpace, declared: str = "") -> str | None:
    """The USD color space token (``GfColorSpaceNames``) of the OCIO color
    space ``cs``: ``declared`` itself when it is a USD token (the name the
    stage or file used to declare ``cs``), else the color space's interop ID,
    one of its aliases or its name when that is a USD token; None when the
    space has no USD token (a config's own space without an interop ID)."""
    if declared in USD_COLOR_SPACE_NAMES:
        return declared
    iid = cs.getInteropID() if hasattr(cs, "getInteropID") else ""
    for n in (iid, *cs.getAliases(), cs.getName()):
        if n in USD_COLOR_SPACE_NAMES:
            return str(n)
    return None


def _working(config: ocio.Config, where: str) -> ocio.ColorSpace:
    for n in LINEAR_REC709:
        cs = find_color_space(config, n)
        if cs is not None:
            return cs
    raise ColorSpaceError(
        f"OCIO config {where}: has no Linear Rec.709 color space (interop ID lin_rec709_scene)"
    )


@dataclass
class ColorConverter:
    """Converts RGB between a product's color space and Linear Rec.709."""

    config: ocio.Config
    config_name: str
    source: str
    declared_by: str

    def __post_init__(self) -> None:
        src = find_color_space(self.config, self.source)
        if src is None:
            names = [cs.getName() for cs in self.config.getColorSpaces()]
            raise ColorSpaceError(
                f"color space {self.source!r} ({self.declared_by}) is unknown to the OCIO config {self.config_name} "
                f"(known: {', '.join(names[:24])}{' ...' if len(names) > 24 else ''})"
            )
        dst = _working(self.config, self.config_name)
        self.source_name = src.getName()
        #: USD color space token of the source space (None: it has none).
        self.usd_name = usd_color_space_name(src, self.source)
        self.identity = src.getName() == dst.getName()
        self.linear = self.identity or bool(
            self.config.isColorSpaceLinear(src.getName(), ocio.REFERENCE_SPACE_SCENE)
        )
        self._to = self.config.getProcessor(src, dst).getDefaultCPUProcessor()
        self._from = self.config.getProcessor(dst, src).getDefaultCPUProcessor()

    def _apply(
        self, cpu: ocio.CPUProcessor, rgb: np.ndarray, alpha: np.ndarray | None
    ) -> np.ndarray:
        out = np.ascontiguousarray(rgb, dtype=np.float32).copy()
        if self.identity:
            return out
        # Matrix (linear) transforms commute with premultiplication; others
        # are applied to straight color.
        straight = not self.linear and alpha is not None
        if straight:
            a = np.asarray(alpha, np.float32)[..., None]
            safe = np.where(a > 1e-8, a, 1.0)
            out = np.where(a > 1e-8, out / safe, 0.0).astype(np.float32)
        cpu.applyRGB(out)
        if straight:
            out *= a
        return out

    def to_linear(self, rgb: np.ndarray, alpha: np.ndarray | None = None) -> np.ndarray:
        """Product color space -> Linear Rec.709 (a new float32 array)."""
        return self._apply(self._to, rgb, alpha)

    def from_linear(
        self, rgb: np.ndarray, alpha: np.ndarray | None = None
    ) -> np.ndarray:
        """Linear Rec.709 -> product color space (a new float32 array)."""
        return self._apply(self._from, rgb, alpha)


def converter_for(
    declared: tuple[str, str] | None,
    file_attrs: dict[str, object],
    file_name: str,
    rendering_color_space: str | None,
    config_path: str | None = None,
) -> ColorConverter:
    """Picks the product's color space (see the module docs) and returns its converter."""
    config, cname = load_config(config_path)
    if declared is not None:
        return ColorConverter(config, cname, declared[0], f"declared by {declared[1]}")
    for key in ("colorInteropID", "oiio:ColorSpace"):
        v = file_attrs.get(key)
        if isinstance(v, str) and v:
            return ColorConverter(config, cname, v, f"attribute {key} of {file_name}")
    if rendering_color_space:
        return ColorConverter(
            config, cname, rendering_color_space, "RenderSettings renderingColorSpace"
        )
    role = config.getRoleColorSpace("scene_linear")
    if not role:
        raise ColorSpaceError(
            f"OCIO config {cname}: no color space declared for {file_name} and no scene_linear role"
        )
    return ColorConverter(config, cname, role, f"scene_linear role of {cname}")
