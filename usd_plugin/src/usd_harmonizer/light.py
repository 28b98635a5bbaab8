"""The direction toward a stage's dominant light, per frame: what the
library's ``light_direction`` parameter needs for inserts' cast shadows.

Where it comes from, first found wins:

1. ``harmonizer:lightDirection`` (float3, world space, toward the light) on
   the render product, else on the RenderSettings prim; time samples are
   honoured. An authored ``(0, 0, 0)`` means "no light" (no cast shadows).
2. The stage's ``UsdLux.DistantLight`` with the largest
   ``intensity * 2^exposure`` at the frame's time code (active, not
   invisible, above 0; a tie goes to the first in namespace order; lights
   inside instances are not looked for). A DistantLight emits along its
   local -Z, so the direction toward it is its local-to-world transform's
   +Z axis, normalized.
3. The sun in a textured dome (an HDRI; :func:`dome_lighting`): the
   texels within :data:`SUN_RADIUS_DEG` of the texture's brightest, when
   that texel is at least :data:`SUN_CONTRAST` times the mean radiance of
   the rest of the sphere and those texels carry at least
   :data:`SUN_SHARE` of its power (a clear sky's sun, a studio HDRI's key
   light; not an overcast sky); the direction is their power-weighted mean,
   under the dome's transform at the frame, when above the horizon. The
   brightest such sun of the visible domes wins.
4. None: the library casts no directional shadow (the contact shadow
   under an insert stays).

The direction is in the stage's world space, whatever its ``upAxis``: the
camera matrices the hook passes (:mod:`usd_harmonizer.camera`) are in that
same space, and the library only needs the two to agree. Point, sphere,
rect and disk lights are not used: a point light's direction depends on
where the insert stands.

The scene's direct-to-ambient ratio (the library's ``light_ratio``,
:func:`light_ratio_at`), first found wins:

1. ``harmonizer:lightRatio`` (float, at least 0; 0: let the library measure
   it) on the render product, else on the RenderSettings prim.
2. The brightest DistantLight's irradiance (``intensity * 2^exposure``
   times its color's luminance) over the ambient: half the DomeLights'
   irradiance on a surface facing up (``pi`` times each one's
   ``intensity * 2^exposure`` times its color's luminance: a whole sky of
   that radiance), since a wall, an object's side or ground in a wall's
   shadow sees about half the sky. A dome with a texture file (an HDRI)
   gives the irradiance its texture sends onto a surface facing the
   stage's up axis (:func:`dome_lighting`): a latitude-longitude image
   in OpenEXR's convention, as UsdLux specifies (the top row toward the
   dome's +Y, or its ``poleAxis`` for ``DomeLight_1``; longitude 0 toward
   +Z, +pi/2 toward +X), its linear RGB times the dome's color, under the
   dome's world transform at the frame, times ``intensity * 2^exposure``.
   A texture's sun (above) is direct light, left out of the ambient;
   without a DistantLight the brightest dome sun is the direct light (its
   irradiance on a surface facing it). A texture that cannot be read that
   way (not found, not a float image, another layout than lat-long) gives
   none, and says why.
3. None: the library measures it from each frame's own shadows.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from pxr import Gf, Usd, UsdGeom, UsdLux

from .errors import SettingsError

#: Override attribute on a RenderProduct or the RenderSettings prim.
ATTR_LIGHT_DIRECTION = "harmonizer:lightDirection"
#: The direct-to-ambient ratio's override attribute (same prims).
ATTR_LIGHT_RATIO = "harmonizer:lightRatio"
#: The largest ratio the library takes (``light_ratio``).
MAX_RATIO = 12.0
#: Rec.709 luminance weights (the library's working space).
LUMA = (0.2126, 0.7152, 0.0722)


@dataclass(frozen=True)
class Light:
    """A light direction and where it came from."""

    #: Unit vector toward the light, world space; None: no light.
    direction: tuple[float, float, float] | None
    #: Where it came from, for reports: ``"/Render/Products/beauty.harmonizer:lightDirection"``,
    #: ``"DistantLight /World/Sun"``, ``"--light-direction"``, ``"none"``.
    source: str

    @property
    def param(self) -> str:
        """The ``light_direction`` session parameter ("x, y, z", empty for none)."""
        if self.direction is None:
            return ""
        return ", ".join(repr(float(c)) for c in self.direction)


NO_LIGHT = Light(None, "none")


def normalized(v, where: str) -> tuple[float, float, float] | None:
    """``v`` (three numbers) as a unit vector; None for the zero vector.
    Anything else than three finite numbers is a :class:`SettingsError`
    naming ``where``."""
    try:
        x, y, z = (float(c) for c in v)
    except (TypeError, ValueError):
        raise SettingsError(
            f"{where}: {v!r} is not a direction (three numbers x, y, z toward the light)"
        ) from None
    if not all(math.isfinite(c) for c in (x, y, z)):
        raise SettingsError(f"{where}: {v!r} is not a finite direction")
    n = math.sqrt(x * x + y * y + z * z)
    if n == 0.0:
        return None
    return (x / n, y / n, z / n)


def parse_direction(text: str, where: str) -> tuple[float, float, float]:
    """A direction from ``"x,y,z"`` (commas and/or spaces), normalized; the
    zero vector and anything but three finite numbers are errors."""
    parts = [p for p in text.replace(",", " ").split() if p]
    if len(parts) != 3:
        raise SettingsError(
            f"{where} {text!r}: expected three numbers x,y,z (the direction toward the light, world space)"
        )
    d = normalized(parts, f"{where} {text!r}")
    if d is None:
        raise SettingsError(
            f"{where} {text!r}: the zero vector has no direction (use --no-light for none)"
        )
    return d


def override(prims: list[Usd.Prim], frame: float) -> Light | None:
    """``harmonizer:lightDirection`` at ``frame`` on the first of ``prims``
    that authors it (a zero vector: no light), else None."""
    for prim in prims:
        attr = prim.GetAttribute(ATTR_LIGHT_DIRECTION)
        if not attr or not attr.HasAuthoredValue():
            continue
        where = f"{prim.GetPath()}.{ATTR_LIGHT_DIRECTION}"
        v = attr.Get(Usd.TimeCode(frame))
        if v is None:
            raise SettingsError(f"{where}: no value at frame {frame:g}")
        return Light(normalized(v, where), where)
    return None


def distant_lights(stage: Usd.Stage) -> list[Usd.Prim]:
    """The stage's DistantLight prims (active, loaded, defined; not inside
    instances), in namespace order: one traversal, which a run keeps."""
    return [p for p in stage.Traverse() if p.IsA(UsdLux.DistantLight)]


def _value(attr: Usd.Attribute, time: Usd.TimeCode, fallback: float) -> float:
    v = attr.Get(time) if attr else None
    return fallback if v is None else float(v)


def dominant_distant_light(
    stage: Usd.Stage, frame: float, lights: list[Usd.Prim] | None = None
) -> Light:
    """The direction toward the stage's brightest DistantLight at ``frame``
    (see the module's notes), or :data:`NO_LIGHT`. ``lights``: the
    candidates (default: :func:`distant_lights` of the stage)."""
    time = Usd.TimeCode(frame)
    best: tuple[float, Usd.Prim] | None = None
    for prim in distant_lights(stage) if lights is None else lights:
        if not prim.IsValid() or not prim.IsActive():  # edited since found
            continue
        light = UsdLux.DistantLight(prim)
        if UsdGeom.Imageable(prim).ComputeVisibility(time) == UsdGeom.Tokens.invisible:
            continue
        power = _value(light.GetIntensityAttr(), time, 1.0) * 2.0 ** _value(
            light.GetExposureAttr(), time, 0.0
        )
        if math.isfinite(power) and power > 0 and (best is None or power > best[0]):
            best = (power, prim)
    if best is None:
        return NO_LIGHT
    prim = best[1]
    m = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time)
    # Gf matrices are row-vector: the local +Z axis in world is (0, 0, 1) * M.
    z = m.TransformDir(Gf.Vec3d(0.0, 0.0, 1.0))
    d = normalized(z, f"DistantLight {prim.GetPath()} at frame {frame:g}")
    if d is None:  # a transform that scales the light to nothing
        return NO_LIGHT
    return Light(d, f"DistantLight {prim.GetPath()}")


def light_at(
    stage: Usd.Stage,
    prims: list[Usd.Prim],
    frame: float,
    lights: list[Usd.Prim] | None = None,
    domes: list[Usd.Prim] | None = None,
) -> Light:
    """The light of ``frame``: the override on ``prims`` (the product, then
    the settings prim), else the stage's brightest DistantLight (among
    ``lights`` when given), else the brightest sun in a dome's texture
    (among ``domes`` when given), else none."""
    found = override(prims, frame) or dominant_distant_light(stage, frame, lights)
    if found is NO_LIGHT:
        return dome_sun_light(stage, frame, domes)
    return found


def _power_rgb(light, time: Usd.TimeCode) -> tuple[float, float, float]:
    """``intensity * 2^exposure`` times the color."""
    color = light.GetColorAttr().Get(time) if light.GetColorAttr() else None
    tint = (1.0, 1.0, 1.0) if color is None else _rgb(color)
    scale = _value(light.GetIntensityAttr(), time, 1.0) * 2.0 ** _value(
        light.GetExposureAttr(), time, 0.0
    )
    return _rgb(scale * c for c in tint)


def _visible(prim: Usd.Prim, time: Usd.TimeCode) -> bool:
    return (
        prim.IsValid()
        and prim.IsActive()
        and UsdGeom.Imageable(prim).ComputeVisibility(time) != UsdGeom.Tokens.invisible
    )


def ratio_lights(stage: Usd.Stage) -> list[Usd.Prim]:
    """The stage's DistantLight and DomeLight (or DomeLight_1) prims, in
    namespace order (one traversal, which a run keeps)."""
    return [p for p in stage.Traverse() if p.IsA(UsdLux.DistantLight) or is_dome(p)]


def is_dome(prim: Usd.Prim) -> bool:
    """A DomeLight or DomeLight_1 prim."""
    return prim.IsA(UsdLux.DomeLight) or prim.IsA(UsdLux.DomeLight_1)


#: A dome texture is read at most this many texels wide (block means; half
#: as many rows): the irradiance is a smooth integral.
DOME_TEXELS = 256


class DomeTextureError(ValueError):
    """A dome's texture that cannot be read as a lat-long image."""


@lru_cache(maxsize=8)
def _latlong(path: str, mtime: float) -> np.ndarray:
    """A lat-long image's linear RGB, block-averaged to at most
    :data:`DOME_TEXELS` x half as many texels (float64, rows from the top).
    ``mtime`` keys the cache to the file's version."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise DomeTextureError(f"cannot open {path}: {oiio.geterror()}")
    try:
        spec = inp.spec()
        if spec.format.basetype not in (oiio.FLOAT, oiio.HALF):
            raise DomeTextureError(f"{path} is not a float (linear) image ({spec.format})")
        names = list(spec.channelnames)
        idx = [names.index(c) for c in "RGB"] if all(c in names for c in "RGB") else [0, 1, 2]
        if spec.nchannels < 3:
            raise DomeTextureError(f"{path} has {spec.nchannels} channels, not RGB")
        h, w = spec.height, spec.width
        if w != 2 * h:
            raise DomeTextureError(f"{path} is {w}x{h}: a lat-long image is twice as wide as high")
        px = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
    finally:
        inp.close()
    if px is None:
        raise DomeTextureError(f"cannot read {path}: {oiio.geterror()}")
    # In place (an 8k image is hundreds of megabytes as it is): no NaN,
    # infinity or negative light; then block means, summed in float64.
    px = np.asarray(px, np.float32).reshape(h, w, spec.nchannels)
    np.nan_to_num(px, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    np.maximum(px, 0.0, out=px)
    f = max(1, math.ceil(w / DOME_TEXELS))
    hh, ww = h // f, w // f
    blocks = px[: hh * f, : ww * f].reshape(hh, f, ww, f, spec.nchannels)
    return blocks.mean(axis=(1, 3), dtype=np.float64)[..., idx]


#: A texture's sun: the texels within this angle (degrees) of its brightest
#: one (the disc, block-averaged, and its aureole) ...
SUN_RADIUS_DEG = 6.0
#: ... when the brightest texel is at least this many times the mean
#: radiance of the rest of the sphere ...
SUN_CONTRAST = 20.0
#: ... and those texels carry at least this share of the texture's power.
SUN_SHARE = 0.05


@dataclass(frozen=True)
class DomeLighting:
    """What a textured dome gives at a frame (world space)."""

    #: Irradiance on a surface facing the stage's up axis, the sun's
    #: texels left out (RGB).
    ambient_up_rgb: tuple[float, float, float]
    #: The direction toward the texture's sun (unit), or None: no compact
    #: bright source, or one below the horizon.
    sun: tuple[float, float, float] | None
    #: The sun's irradiance on a surface facing it (RGB; 0 without).
    sun_rgb: tuple[float, float, float]

    @property
    def sun_irradiance(self) -> float:
        """``sun_rgb``'s luminance."""
        return _luma(self.sun_rgb)


def _luma(c) -> float:
    return sum(w * float(v) for w, v in zip(LUMA, c, strict=True))


def _rgb(c) -> tuple[float, float, float]:
    r, g, b = (float(v) for v in c)
    return (r, g, b)


@lru_cache(maxsize=4)
def _latlong_directions(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Each texel's direction (OpenEXR's lat-long: +Y up, longitude 0 toward
    +Z, +pi/2 toward +X; rows from the top) and solid angle, read-only
    (computed once per size: every frame asks)."""
    lat = math.pi / 2 - math.pi * (np.arange(h) + 0.5) / h
    lon = math.pi - 2 * math.pi * (np.arange(w) + 0.5) / w
    clat, slat = np.cos(lat)[:, None], np.sin(lat)[:, None]
    d = np.stack(np.broadcast_arrays(clat * np.sin(lon)[None], slat, clat * np.cos(lon)[None]), -1)
    solid = np.broadcast_to(clat * (math.pi / h) * (2 * math.pi / w), (h, w))
    d.setflags(write=False)
    return d, solid


@lru_cache(maxsize=8)
def _latlong_sun(path: str, mtime: float) -> np.ndarray | None:
    """The texels of a lat-long image's sun (a bool mask; see
    :data:`SUN_RADIUS_DEG`), or None where it has none."""
    rgb = _latlong(path, mtime)
    h, w = rgb.shape[:2]
    d, solid = _latlong_directions(h, w)
    lum = rgb @ np.asarray(LUMA)
    k = np.unravel_index(int(np.argmax(lum)), lum.shape)
    near = d @ d[k] >= math.cos(math.radians(SUN_RADIUS_DEG))
    power = lum * solid
    total, sun = float(power.sum()), float(power[near].sum())
    rest = (total - sun) / max(float(solid[~near].sum()), 1e-12)
    if total <= 0 or sun < SUN_SHARE * total or lum[k] < SUN_CONTRAST * rest:
        return None
    return near


def _dome(prim: Usd.Prim):
    return UsdLux.DomeLight_1(prim) if prim.IsA(UsdLux.DomeLight_1) else UsdLux.DomeLight(prim)


def dome_lighting(stage: Usd.Stage, prim: Usd.Prim, time: Usd.TimeCode) -> DomeLighting:
    """What a textured dome's texture gives at ``time`` (see the module's
    notes). Raises :class:`DomeTextureError` where the texture cannot be
    read as lat-long."""
    dome = _dome(prim)
    asset = dome.GetTextureFileAttr().Get(time)
    fmt = dome.GetTextureFormatAttr().Get(time) if dome.GetTextureFormatAttr() else None
    if fmt not in (None, "automatic", "latlong"):
        raise DomeTextureError(f"texture format {fmt!r}: only lat-long images are read")
    path = asset.resolvedPath
    if not path or not os.path.isfile(path):
        raise DomeTextureError(f"texture {asset.path!r} not found")
    mtime = os.path.getmtime(path)
    rgb = _latlong(path, mtime)
    sun_mask = _latlong_sun(path, mtime)
    h, w = rgb.shape[:2]
    d, solid = _latlong_directions(h, w)
    up_axis = UsdGeom.GetStageUpAxis(stage)
    pole = dome.GetPoleAxisAttr().Get(time) if prim.IsA(UsdLux.DomeLight_1) else "Y"
    if pole == "Z" or (pole == "scene" and up_axis == UsdGeom.Tokens.z):
        d = np.stack([d[..., 0], -d[..., 2], d[..., 1]], -1)  # +Y onto +Z (90 degrees about X)
    m = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(time)
    rot = np.array([[m[i][j] for j in range(3)] for i in range(3)])  # row vectors: d @ rot
    world = d @ rot
    world /= np.maximum(np.linalg.norm(world, axis=-1, keepdims=True), 1e-12)
    up = np.array([0.0, 0.0, 1.0]) if up_axis == UsdGeom.Tokens.z else np.array([0.0, 1.0, 0.0])
    color = dome.GetColorAttr().Get(time) if dome.GetColorAttr() else None
    tint = np.ones(3) if color is None else np.array([float(c) for c in color])
    scale = _value(dome.GetIntensityAttr(), time, 1.0) * 2.0 ** _value(
        dome.GetExposureAttr(), time, 0.0
    )
    lit = rgb * (tint * scale)
    lum = lit @ np.asarray(LUMA)
    facing_up = np.maximum(world @ up, 0.0) * solid
    rest = np.ones((h, w), bool) if sun_mask is None else ~sun_mask
    ambient = _rgb((lit * facing_up[..., None])[rest].sum(axis=0))
    none = (0.0, 0.0, 0.0)
    if sun_mask is None:
        return DomeLighting(ambient, None, none)
    power = (lum * solid)[sun_mask]
    toward = (world[sun_mask] * power[:, None]).sum(axis=0)
    n = float(np.linalg.norm(toward))
    if not math.isfinite(n) or n <= 0:
        return DomeLighting(ambient, None, none)
    toward /= n
    if float(toward @ up) <= 0:  # below the horizon: no direct light on the ground
        return DomeLighting(ambient, None, none)
    facing = solid[sun_mask] * np.maximum(world[sun_mask] @ toward, 0.0)
    direct = _rgb((lit[sun_mask] * facing[:, None]).sum(axis=0))
    return DomeLighting(ambient, (float(toward[0]), float(toward[1]), float(toward[2])), direct)


def dome_sun_light(stage: Usd.Stage, frame: float, domes: list[Usd.Prim] | None = None) -> Light:
    """The direction toward the brightest sun in the stage's textured domes
    (among ``domes`` when given) at ``frame``, or :data:`NO_LIGHT`. A
    texture that cannot be read gives none here (the ratio says why)."""
    time = Usd.TimeCode(frame)
    best: tuple[float, tuple[float, float, float], Usd.Prim] | None = None
    for prim in [p for p in stage.Traverse() if is_dome(p)] if domes is None else domes:
        if not is_dome(prim) or not _visible(prim, time):
            continue
        attr = _dome(prim).GetTextureFileAttr()
        tex = attr.Get(time) if attr else None
        if tex is None or not tex.path:
            continue
        try:
            got = dome_lighting(stage, prim, time)
        except DomeTextureError:
            continue
        if got.sun is not None and (best is None or got.sun_irradiance > best[0]):
            best = (got.sun_irradiance, got.sun, prim)
    if best is None:
        return NO_LIGHT
    return Light(best[1], f"DomeLight {best[2].GetPath()} (the sun in its texture)")


def color_text(c) -> str:
    """A color parameter's text: "r, g, b" (negative values as 0)."""
    return ", ".join(f"{max(float(v), 0.0):.6g}" for v in c)


@dataclass(frozen=True)
class SceneLight:
    """The scene's light at a frame as the stage's lights say it."""

    #: The direct-to-ambient ratio (the library's ``light_ratio``), None:
    #: the library measures it.
    ratio: float | None
    #: Where it came from.
    source: str
    #: The direct light's irradiance on a surface facing it, and the
    #: ambient's on a surface in its shadow (half the domes' on a surface
    #: facing up), per channel: the library's ``light_color`` and
    #: ``ambient_color``; None where the ratio is not the lights' (an
    #: override, or none).
    light_color: tuple[float, float, float] | None = None
    ambient_color: tuple[float, float, float] | None = None

    def params(self) -> dict[str, str]:
        """The library's ``light_color`` and ``ambient_color`` ("r, g, b"),
        empty without them."""
        if self.light_color is None or self.ambient_color is None:
            return {}
        return {
            "light_color": color_text(self.light_color),
            "ambient_color": color_text(self.ambient_color),
        }


def light_ratio_at(
    stage: Usd.Stage,
    prims: list[Usd.Prim],
    frame: float,
    lights: list[Usd.Prim] | None = None,
) -> tuple[float | None, str]:
    """The scene's direct-to-ambient ratio at ``frame`` (see the module's
    notes) and where it came from; None: the library measures it.
    ``prims``: where the override is looked for (the product, then the
    settings prim); ``lights``: the candidates (default:
    :func:`ratio_lights` of the stage)."""
    got = scene_light_at(stage, prims, frame, lights)
    return got.ratio, got.source


def scene_light_at(
    stage: Usd.Stage,
    prims: list[Usd.Prim],
    frame: float,
    lights: list[Usd.Prim] | None = None,
) -> SceneLight:
    """:func:`light_ratio_at` with the lights' colors (:class:`SceneLight`)."""
    time = Usd.TimeCode(frame)
    for prim in prims:
        attr = prim.GetAttribute(ATTR_LIGHT_RATIO)
        if not attr or not attr.HasAuthoredValue():
            continue
        where = f"{prim.GetPath()}.{ATTR_LIGHT_RATIO}"
        v = attr.Get(time)
        try:
            r = float(v)
        except (TypeError, ValueError):
            raise SettingsError(f"{where}: {v!r} is not a ratio (a number, at least 0)") from None
        if not math.isfinite(r) or r < 0:
            raise SettingsError(f"{where}: {r!r} is not a ratio (a number, at least 0)")
        return SceneLight((min(r, MAX_RATIO) if r > 0 else None), where)
    sun: tuple[float, Usd.Prim, tuple[float, float, float]] | None = None
    dome_sun: tuple[float, Usd.Prim, tuple[float, float, float]] | None = None
    ambient, domes = np.zeros(3), []
    for prim in ratio_lights(stage) if lights is None else lights:
        if prim.IsA(UsdLux.DistantLight) and _visible(prim, time):
            c = _power_rgb(UsdLux.DistantLight(prim), time)
            p = _luma(c)
            if math.isfinite(p) and p > 0 and (sun is None or p > sun[0]):
                sun = (p, prim, c)
        elif is_dome(prim) and _visible(prim, time):
            dome = _dome(prim)
            tex = dome.GetTextureFileAttr().Get(time) if dome.GetTextureFileAttr() else None
            if tex is not None and tex.path:
                try:
                    got = dome_lighting(stage, prim, time)
                except DomeTextureError as exc:
                    return SceneLight(None, f"DomeLight {prim.GetPath()}: {exc}")
                ambient += 0.5 * np.asarray(got.ambient_up_rgb)
                if got.sun is not None and (dome_sun is None or got.sun_irradiance > dome_sun[0]):
                    dome_sun = (got.sun_irradiance, prim, got.sun_rgb)
            else:
                ambient += 0.5 * math.pi * np.asarray(_power_rgb(dome, time))
            domes.append(str(prim.GetPath()))
    amb = _luma(ambient)
    if not domes or not math.isfinite(amb) or amb <= 0:
        return SceneLight(None, "none")
    if sun is not None:
        source = f"DistantLight {sun[1].GetPath()}"
    elif dome_sun is not None:
        sun, source = dome_sun, f"the sun of DomeLight {dome_sun[1].GetPath()}"
    else:
        return SceneLight(None, "none")
    return SceneLight(
        min(sun[0] / amb, MAX_RATIO),
        f"{source} over DomeLight {', '.join(domes)}",
        _rgb(sun[2]),
        _rgb(np.maximum(ambient, 0.0)),
    )
