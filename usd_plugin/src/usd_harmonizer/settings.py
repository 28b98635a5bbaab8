"""Resolution of a stage's RenderSettings, RenderProducts and RenderVars.

usd-core has no Python wrapper for ``UsdRender.ComputeSpec``; this module
walks the schema itself: the settings prim (the stage's
``renderSettingsPrimPath`` or a named prim), its ``products``, each product's
``orderedVars`` and ``camera`` (falling back to the settings' camera and
resolution, as UsdRender specifies), the frame range (stage start/end time
codes unless given) and the file of each frame (``productName`` evaluated per
time code, frame tokens expanded), and the denoise stage's settings
(``harmonizer:denoise``, ``harmonizer:denoiseQuality``, ``harmonizer:samples``
on the product, else on the settings prim).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from pxr import Sdf, Usd, UsdGeom, UsdRender

from .errors import CameraError, SettingsError, VarError
from .frames import expand_frame_tokens, has_frame_token

#: Custom attribute names read on vars and products (none of them is standard UsdRender).
ATTR_ROLE = "harmonizer:role"
ATTR_CHANNELS = "harmonizer:channels"
ATTR_COLOR_SPACE = "harmonizer:colorSpace"
ATTR_MOTION_SCALE = "harmonizer:motionVectorScale"
ATTR_DEPTH_KIND = "harmonizer:depthKind"
#: RenderMan / Karma style name of the AOV in the file.
ATTR_AOV_NAME = "driver:parameters:aov:name"
#: The denoise stage's settings on a product or the RenderSettings prim
#: (attribute -> session parameter). Renderers name their sample counts
#: differently (and some count anti-aliasing samples per axis), so the
#: count the frames were rendered with is read only from ``harmonizer:samples``.
ATTR_DENOISE = "harmonizer:denoise"
ATTR_DENOISE_QUALITY = "harmonizer:denoiseQuality"
ATTR_SAMPLES = "harmonizer:samples"
DENOISE_ATTRS: dict[str, str] = {
    ATTR_DENOISE: "denoise",
    ATTR_DENOISE_QUALITY: "denoise_quality",
    ATTR_SAMPLES: "samples",
}
#: Values each denoise parameter accepts (``samples``: an integer >= 0).
DENOISE_VALUES: dict[str, tuple[str, ...]] = {
    # ``temporal``: the renderer denoised each frame; the library only
    # accumulates them over time (no second spatial pass).
    "denoise": ("auto", "on", "off", "temporal"),
    "denoise_quality": ("high", "balanced", "fast"),
}


def _authored(attr: Usd.Attribute | None):
    """The authored default value, or None."""
    if attr is None or not attr.IsValid() or not attr.HasAuthoredValue():
        return None
    return attr.Get(Usd.TimeCode.Default())


def _schema_value(attr: Usd.Attribute):
    """The default value including the schema fallback."""
    return attr.Get(Usd.TimeCode.Default()) if attr and attr.IsValid() else None


def _color_space_of(prim: Usd.Prim) -> tuple[str, str] | None:
    """A color space declared on ``prim``: ``harmonizer:colorSpace``, then
    ``colorSpace`` (custom), then ``colorSpace:name`` (UsdColorSpaceAPI) on the
    prim. Returns (value, attribute path) or None."""
    for name in (ATTR_COLOR_SPACE, "colorSpace", "colorSpace:name"):
        v = _authored(prim.GetAttribute(name))
        if v:
            return str(v), f"{prim.GetPath()}.{name}"
    return None


def check_denoise_param(name: str, value: object, where: str) -> object:
    """A denoise parameter's value, checked: ``denoise`` auto/on/off/temporal,
    ``denoise_quality`` high/balanced/fast (case-insensitive), ``samples`` an
    integer >= 0 (0: unknown, the first frame's noise decides). ``where``
    names the attribute or option for the error."""
    if name == "samples":
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float))
            or value != int(value)
            or value < 0
        ):
            raise SettingsError(
                f"{where}: {value!r} is not a sample count (an integer >= 0; 0: unknown)"
            )
        return int(value)
    text = str(value).strip().lower()
    if text not in DENOISE_VALUES[name]:
        raise SettingsError(
            f"{where}: {value!r} is not one of {', '.join(DENOISE_VALUES[name])}"
        )
    return text


def _denoise_params(*prims: Usd.Prim) -> dict[str, object]:
    """The denoise parameters authored on the first of ``prims`` that has each."""
    out: dict[str, object] = {}
    for attr, param in DENOISE_ATTRS.items():
        for prim in prims:
            v = _authored(prim.GetAttribute(attr))
            if v is not None:
                out[param] = check_denoise_param(param, v, f"{prim.GetPath()}.{attr}")
                break
    return out


def _inherited_color_space(prim: Usd.Prim) -> tuple[str, str] | None:
    """``colorSpace:name`` (UsdColorSpaceAPI) on the nearest ancestor of
    ``prim`` that authors it: the API's color space is inherited down the
    namespace."""
    p = prim.GetParent()
    while p and not p.IsPseudoRoot():
        v = _authored(p.GetAttribute("colorSpace:name"))
        if v:
            return str(v), f"{p.GetPath()}.colorSpace:name"
        p = p.GetParent()
    return None


@dataclass
class VarInfo:
    """One RenderVar as the product declares it."""

    path: str
    name: str
    source_name: str
    source_type: str
    data_type: str
    aov_name: str | None
    role: str | None
    channels: list[str] | None
    #: Declared on the var itself (value, attribute path).
    color_space: tuple[str, str] | None
    #: ``colorSpace:name`` inherited from an ancestor.
    inherited_color_space: tuple[str, str] | None
    motion_scale: tuple[float, float] | None
    depth_kind: str | None

    @staticmethod
    def from_prim(prim: Usd.Prim) -> VarInfo:
        """Reads a RenderVar prim."""
        var = UsdRender.Var(prim)
        ms = _authored(prim.GetAttribute(ATTR_MOTION_SCALE))
        ch = _authored(prim.GetAttribute(ATTR_CHANNELS))
        role = _authored(prim.GetAttribute(ATTR_ROLE))
        dk = _authored(prim.GetAttribute(ATTR_DEPTH_KIND))
        aov = _authored(prim.GetAttribute(ATTR_AOV_NAME))
        return VarInfo(
            path=str(prim.GetPath()),
            name=prim.GetName(),
            source_name=str(_schema_value(var.GetSourceNameAttr()) or ""),
            source_type=str(_schema_value(var.GetSourceTypeAttr()) or "raw"),
            data_type=str(_schema_value(var.GetDataTypeAttr()) or "color3f"),
            aov_name=str(aov) if aov else None,
            role=str(role) if role else None,
            channels=[str(c) for c in ch] if ch else None,
            color_space=_color_space_of(prim),
            inherited_color_space=_inherited_color_space(prim),
            motion_scale=(float(ms[0]), float(ms[1])) if ms is not None else None,
            depth_kind=str(dk) if dk else None,
        )

    @property
    def components(self) -> int:
        """Number of components its ``dataType`` has."""
        t = self.data_type.lower()
        t = t.removesuffix("[]")
        for n in (4, 3, 2):
            if t.endswith((f"{n}f", f"{n}h", f"{n}d", f"{n}i")):
                return n
        if t in ("color", "point", "vector", "normal"):
            return 3
        return 1


@dataclass
class ProductInfo:
    """One RenderProduct, resolved."""

    path: str
    name: str
    product_type: str
    product_name_attr: Usd.Attribute
    vars: list[VarInfo]
    camera_path: str | None
    resolution: tuple[int, int]
    pixel_aspect: float
    conform_policy: str
    #: Declared on the product itself (value, attribute path).
    color_space: tuple[str, str] | None
    #: Inherited from an ancestor's ``colorSpace:name``, else the settings'.
    inherited_color_space: tuple[str, str] | None
    base_dir: Path
    stage: Usd.Stage = field(repr=False)
    #: Denoise session parameters from the product or the settings prim
    #: (``denoise``, ``denoise_quality``, ``samples``); options given to the
    #: hook or the CLI win.
    params: dict[str, object] = field(default_factory=dict)

    def product_name(self, frame: int) -> str:
        """``productName`` at ``frame`` (time samples honoured), unexpanded."""
        v = self.product_name_attr.Get(Usd.TimeCode(frame))
        if not v:
            raise SettingsError(
                f"render product {self.path}: productName is empty at frame {frame}"
            )
        return str(v)

    def file_for(self, frame: int) -> Path:
        """The product's file at ``frame``: ``productName`` evaluated at the
        time code, frame tokens expanded, relative names resolved against the
        base directory (the root layer's directory unless given)."""
        p = Path(expand_frame_tokens(self.product_name(frame), frame))
        return p if p.is_absolute() else self.base_dir / p

    @property
    def time_sampled(self) -> bool:
        """True when ``productName`` has time samples."""
        return self.product_name_attr.GetNumTimeSamples() > 0

    def check_frames_distinct(self, frames: list[int]) -> None:
        """Raises when several frames would map to the same file."""
        if len(frames) < 2:
            return
        seen: dict[Path, int] = {}
        for f in frames:
            p = self.file_for(f)
            if p in seen:
                raise SettingsError(
                    f"render product {self.path}: frames {seen[p]} and {f} both resolve to {p} "
                    f"(productName {self.product_name(f)!r} has no frame token "
                    "($F4, ${F4}, <F4>, #### or %04d) and no time sample per frame)"
                )
            seen[p] = f

    def camera_prim(self) -> Usd.Prim | None:
        """The camera prim, or None when neither product nor settings name one."""
        if self.camera_path is None:
            return None
        prim = self.stage.GetPrimAtPath(self.camera_path)
        if not prim or not prim.IsValid():
            raise CameraError(
                f"render product {self.path}: camera {self.camera_path} does not exist on the stage"
            )
        if not prim.IsA(UsdGeom.Camera):
            raise CameraError(
                f"render product {self.path}: camera {self.camera_path} is a {prim.GetTypeName() or 'typeless prim'}, "
                "not a UsdGeom.Camera"
            )
        return prim


@dataclass
class SettingsInfo:
    """The resolved render settings of a stage."""

    path: str
    products: list[ProductInfo]
    frames: list[int]
    rendering_color_space: str | None
    stage: Usd.Stage = field(repr=False)


def open_stage(path: str | os.PathLike[str]) -> Usd.Stage:
    """Opens a stage file, with an error naming it when that fails."""
    p = Path(path)
    if not p.is_file():
        raise SettingsError(f"stage {p}: no such file")
    try:
        stage = Usd.Stage.Open(str(p))
    except Exception as e:  # pxr raises Tf.ErrorException
        raise SettingsError(f"stage {p}: cannot open: {e}") from e
    if stage is None:
        raise SettingsError(f"stage {p}: cannot open")
    return stage


def find_settings_prim(stage: Usd.Stage, settings: str | None = None) -> Usd.Prim:
    """The RenderSettings prim: ``settings`` (a path) if given, else the
    stage's ``renderSettingsPrimPath``, else the only RenderSettings prim."""
    where = stage.GetRootLayer().identifier
    if settings:
        prim = (
            stage.GetPrimAtPath(settings)
            if Sdf.Path.IsValidPathString(settings)
            else None
        )
        if not prim or not prim.IsValid():
            raise SettingsError(f"stage {where}: no prim at --settings {settings!r}")
        if not prim.IsA(UsdRender.Settings):
            raise SettingsError(
                f"stage {where}: {settings} is a {prim.GetTypeName()!r}, not a RenderSettings prim"
            )
        return prim
    s = UsdRender.Settings.GetStageRenderSettings(stage)
    if s:
        return s.GetPrim()
    meta = stage.GetMetadata("renderSettingsPrimPath")
    if meta:
        raise SettingsError(
            f"stage {where}: renderSettingsPrimPath {meta!r} is not a RenderSettings prim"
        )
    found = [p for p in stage.Traverse() if p.IsA(UsdRender.Settings)]
    if len(found) == 1:
        return found[0]
    if not found:
        raise SettingsError(
            f"stage {where}: no RenderSettings prim (and no renderSettingsPrimPath metadata)"
        )
    raise SettingsError(
        f"stage {where}: {len(found)} RenderSettings prims and no renderSettingsPrimPath; "
        f"pick one with --settings ({', '.join(str(p.GetPath()) for p in found)})"
    )


def _rel_targets(rel: Usd.Relationship) -> list[Sdf.Path]:
    return list(rel.GetForwardedTargets()) if rel and rel.IsValid() else []


def resolve(
    stage: Usd.Stage,
    settings: str | None = None,
    products: list[str] | None = None,
    frames: list[int] | None = None,
    base_dir: str | os.PathLike[str] | None = None,
) -> SettingsInfo:
    """Resolves the render settings, the products (all, or those whose name or
    path is in ``products``), their vars and cameras, and the frame range."""
    sprim = find_settings_prim(stage, settings)
    rs = UsdRender.Settings(sprim)
    root = stage.GetRootLayer()
    if base_dir is None:
        real = root.realPath
        base = Path(real).parent if real else Path.cwd()
    else:
        base = Path(base_dir)
    s_camera = _rel_targets(rs.GetCameraRel())
    s_res = _schema_value(rs.GetResolutionAttr())
    s_par = _schema_value(rs.GetPixelAspectRatioAttr())
    s_conform = _schema_value(rs.GetAspectRatioConformPolicyAttr())
    s_cs = _color_space_of(sprim)
    result: list[ProductInfo] = []
    targets = _rel_targets(rs.GetProductsRel())
    if not targets:
        raise SettingsError(
            f"render settings {sprim.GetPath()}: the products relationship is empty"
        )
    for t in targets:
        pprim = stage.GetPrimAtPath(t)
        if not pprim or not pprim.IsValid():
            raise SettingsError(
                f"render settings {sprim.GetPath()}: product {t} does not exist on the stage"
            )
        if not pprim.IsA(UsdRender.Product):
            raise SettingsError(
                f"render settings {sprim.GetPath()}: {t} is a {pprim.GetTypeName()!r}, not a RenderProduct"
            )
        if products and pprim.GetName() not in products and str(t) not in products:
            continue
        prod = UsdRender.Product(pprim)
        vars_: list[VarInfo] = []
        for vt in _rel_targets(prod.GetOrderedVarsRel()):
            vprim = stage.GetPrimAtPath(vt)
            if not vprim or not vprim.IsValid():
                raise VarError(
                    f"render product {t}: RenderVar {vt} (orderedVars) does not exist on the stage"
                )
            if not vprim.IsA(UsdRender.Var):
                raise VarError(
                    f"render product {t}: {vt} (orderedVars) is a {vprim.GetTypeName()!r}, not a RenderVar"
                )
            vars_.append(VarInfo.from_prim(vprim))
        if not vars_:
            raise VarError(f"render product {t}: orderedVars is empty")
        cam = _rel_targets(prod.GetCameraRel()) or s_camera
        res_attr = prod.GetResolutionAttr()
        res = _authored(res_attr) if res_attr.HasAuthoredValue() else s_res
        par = (
            _authored(prod.GetPixelAspectRatioAttr())
            if prod.GetPixelAspectRatioAttr().HasAuthoredValue()
            else s_par
        )
        conform = (
            _authored(prod.GetAspectRatioConformPolicyAttr())
            if prod.GetAspectRatioConformPolicyAttr().HasAuthoredValue()
            else s_conform
        )
        result.append(
            ProductInfo(
                path=str(t),
                name=pprim.GetName(),
                product_type=str(_schema_value(prod.GetProductTypeAttr()) or "raster"),
                product_name_attr=prod.GetProductNameAttr(),
                vars=vars_,
                camera_path=str(cam[0]) if cam else None,
                resolution=(int(res[0]), int(res[1]))
                if res is not None
                else (2048, 1080),
                pixel_aspect=float(par) if par else 1.0,
                conform_policy=str(conform or "expandAperture"),
                color_space=_color_space_of(pprim),
                inherited_color_space=_inherited_color_space(pprim) or s_cs,
                base_dir=base,
                stage=stage,
                params=_denoise_params(pprim, sprim),
            )
        )
    if products:
        names = {p.name for p in result} | {p.path for p in result}
        missing = [p for p in products if p not in names]
        if missing:
            avail = ", ".join(str(t) for t in targets)
            raise SettingsError(
                f"render settings {sprim.GetPath()}: no product named {missing[0]!r} (products: {avail})"
            )
    if frames is None:
        if stage.HasAuthoredTimeCodeRange():
            first, last = stage.GetStartTimeCode(), stage.GetEndTimeCode()
            frames = list(range(round(first), round(last) + 1))
        else:
            tc = Usd.TimeCode.Default()
            samples = sorted(
                {int(s) for p in result for s in p.product_name_attr.GetTimeSamples()}
            )
            if samples:
                frames = samples
            elif all(
                not has_frame_token(str(p.product_name_attr.Get(tc) or ""))
                for p in result
            ):
                frames = [0]
            else:
                raise SettingsError(
                    f"stage {root.identifier}: no startTimeCode/endTimeCode and productName has a frame token; "
                    "give the frames with --frames"
                )
    rcs = _authored(rs.GetRenderingColorSpaceAttr())
    return SettingsInfo(
        path=str(sprim.GetPath()),
        products=result,
        frames=list(frames),
        rendering_color_space=str(rcs) if rcs else None,
        stage=stage,
    )
