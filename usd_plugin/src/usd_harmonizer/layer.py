"""Records enhanced outputs on the stage as new RenderProducts.

By default a new layer is written that sublayers the stage's root layer and
defines, next to each processed product ``P``, a product ``P_harmonized``
(same type, camera, resolution and orderedVars; ``productName`` time-sampled
per processed frame, with the pattern as its default; ``harmonizer:*``
attributes and a ``harmonizer:sourceProduct`` relationship), plus a
RenderSettings prim ``<settings>_harmonized`` listing them. The original
layer is not modified unless ``in_place`` is set.

Each new product's color space is declared with UsdColorSpaceAPI
(``colorSpace:name``): the USD token of the space its color was read in and
written back to (the source product's own token when the stage declares it;
an OCIO name is mapped to its token, see
:func:`usd_harmonizer.color.usd_color_space_name`), and as the OCIO name in
``harmonizer:colorSpace``.
"""

from __future__ import annotations

import os
from pathlib import Path

from pxr import Gf, Sdf, Usd, UsdRender, Vt

from .errors import UsdHarmonizerError
from .process import FrameResult
from .settings import ProductInfo, SettingsInfo

SUFFIX = "_harmonized"


def _rel_path(target: Path, base: Path) -> str:
    try:
        return os.path.relpath(target, base)
    except ValueError:  # different drives
        return os.fspath(target)


def default_layer_path(stage: Usd.Stage) -> Path:
    """``<stage dir>/<stage stem>.harmonized.usda``."""
    real = stage.GetRootLayer().realPath
    p = Path(real) if real else Path.cwd() / "stage.usda"
    return p.with_name(p.stem + ".harmonized.usda")


def write_layer(
    settings: SettingsInfo,
    results: dict[str, tuple[ProductInfo, list[FrameResult]]],
    layer_path: Path | None = None,
    in_place: bool = False,
    version: str = "",
) -> Path:
    """Writes the layer (or edits the root layer with ``in_place``); returns its path."""
    stage = settings.stage
    root = stage.GetRootLayer()
    if in_place:
        layer = root
        path = Path(root.realPath)
    else:
        path = Path(layer_path) if layer_path is not None else default_layer_path(stage)
        if root.realPath and path.resolve() == Path(root.realPath).resolve():
            raise UsdHarmonizerError(
                f"--layer {path} is the stage's root layer; use --in-place to edit it"
            )
        path.parent.mkdir(parents=True, exist_ok=True)
        # Authored under a temporary name in the final directory (so the
        # relative sublayer path resolves), then renamed into place.
        tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix or '.usda'}")
        layer = Sdf.Layer.CreateNew(os.fspath(tmp))
        if layer is None:
            raise UsdHarmonizerError(f"cannot create the layer {tmp}")
        layer.subLayerPaths.append(
            _rel_path(Path(root.realPath), path.parent)
            if root.realPath
            else root.identifier
        )
        for key in (
            "startTimeCode",
            "endTimeCode",
            "timeCodesPerSecond",
            "framesPerSecond",
        ):
            if root.pseudoRoot.HasInfo(key):
                layer.pseudoRoot.SetInfo(key, root.pseudoRoot.GetInfo(key))
    base = path.parent
    # Author through a stage whose edit target is the new layer.
    edit_stage = Usd.Stage.Open(layer) if not in_place else stage
    new_products: list[Sdf.Path] = []
    for prod_path, (prod, frames) in results.items():
        if not frames:
            continue
        src = Sdf.Path(prod_path)
        dst = src.GetParentPath().AppendChild(src.name + SUFFIX)
        np_ = UsdRender.Product.Define(edit_stage, dst)
        np_.CreateProductTypeAttr(prod.product_type)
        name_attr = np_.CreateProductNameAttr()
        first = frames[0]
        default = prod.product_name_attr.Get(Usd.TimeCode.Default())
        pattern_name = Path(
            str(default) if default else prod.product_name(first.frame)
        ).name
        name_attr.Set(_rel_path(first.output.parent / pattern_name, base))
        for r in frames:
            name_attr.Set(_rel_path(r.output, base), Usd.TimeCode(r.frame))
        if prod.camera_path:
            np_.CreateCameraRel().SetTargets([Sdf.Path(prod.camera_path)])
        np_.CreateResolutionAttr(Gf.Vec2i(*prod.resolution))
        np_.CreatePixelAspectRatioAttr(prod.pixel_aspect)
        np_.CreateAspectRatioConformPolicyAttr(prod.conform_policy)
        np_.CreateOrderedVarsRel().SetTargets([Sdf.Path(v.path) for v in prod.vars])
        prim = np_.GetPrim()
        prim.CreateRelationship("harmonizer:sourceProduct", custom=True).SetTargets(
            [src]
        )
        prim.CreateAttribute(
            "harmonizer:version", Sdf.ValueTypeNames.String, custom=True
        ).Set(version)
        prim.CreateAttribute(
            "harmonizer:backend", Sdf.ValueTypeNames.String, custom=True
        ).Set(frames[-1].backend)
        prim.CreateAttribute(
            "harmonizer:colorSpace", Sdf.ValueTypeNames.String, custom=True
        ).Set(frames[-1].color_space)
        token = frames[-1].usd_color_space
        if token and hasattr(Usd, "ColorSpaceAPI"):  # usd-core >= 24.11
            Usd.ColorSpaceAPI.Apply(prim).CreateColorSpaceNameAttr(token)
        prim.CreateAttribute(
            "harmonizer:frames", Sdf.ValueTypeNames.IntArray, custom=True
        ).Set(Vt.IntArray([r.frame for r in frames]))
        prim.CreateAttribute(
            "harmonizer:resetFrames", Sdf.ValueTypeNames.IntArray, custom=True
        ).Set(Vt.IntArray([r.frame for r in frames if r.reset]))
        new_products.append(dst)
    if not new_products:
        raise UsdHarmonizerError("no frame was processed; nothing to record")
    sp = Sdf.Path(settings.path)
    sdst = sp.GetParentPath().AppendChild(sp.name + SUFFIX)
    ns = UsdRender.Settings.Define(edit_stage, sdst)
    ns.CreateProductsRel().SetTargets(new_products)
    ns.GetPrim().CreateRelationship(
        "harmonizer:sourceSettings", custom=True
    ).SetTargets([sp])
    if in_place:
        root.Save()
    else:
        if not layer.Save():
            raise UsdHarmonizerError(f"cannot write the layer {tmp}")
        os.replace(tmp, path)
    return path
