"""Tiny stages authored by hand for the tests that need a product layout or
colors the rendered shot does not have (stereo products, wide-gamut color).

Each product has one color var (``R G B A``, float) and no camera; its files
are written with OpenImageIO from arrays the test chooses.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
from pxr import Gf, Usd, UsdRender
from usd_harmonizer.frames import expand_frame_tokens

#: Size of every hand-made image.
W, H = 16, 8


@dataclass
class Product:
    """A product to author: prim path, ``productName`` and its pixels."""

    path: str
    product_name: str
    #: frame -> (H, W, 3) premultiplied color (alpha is 1).
    rgb: dict[int, np.ndarray]
    #: UsdColorSpaceAPI ``colorSpace:name`` on the product, or None.
    color_space: str | None = None


def write_rgba(path: Path, rgb: np.ndarray, alpha: np.ndarray | None = None) -> None:
    """A single-part float EXR with channels R, G, B, A."""
    path.parent.mkdir(parents=True, exist_ok=True)
    h, w = rgb.shape[:2]
    a = np.ones((h, w), np.float32) if alpha is None else alpha
    spec = oiio.ImageSpec(w, h, 4, "float")
    spec.channelnames = ("R", "G", "B", "A")
    spec.attribute("compression", "zip")
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec), out.geterror()
    assert out.write_image(
        np.concatenate([rgb, a[..., None]], axis=-1).astype(np.float32)
    )
    assert out.close()


def author(root: Path, products: list[Product], frames: list[int]) -> Path:
    """Writes ``root/stage.usda`` (settings ``/Render/Settings`` listing the
    products, one color var) and every product's files; returns the stage."""
    root.mkdir(parents=True, exist_ok=True)
    stage = Usd.Stage.CreateNew(str(root / "stage.usda"))
    stage.SetStartTimeCode(frames[0])
    stage.SetEndTimeCode(frames[-1])
    var = UsdRender.Var.Define(stage, "/Render/Vars/color")
    var.CreateSourceNameAttr("color")
    var.CreateDataTypeAttr("color4f")
    paths = []
    for p in products:
        prod = UsdRender.Product.Define(stage, p.path)
        prod.CreateProductNameAttr(p.product_name)
        prod.CreateOrderedVarsRel().SetTargets([var.GetPath()])
        if p.color_space:
            Usd.ColorSpaceAPI.Apply(prod.GetPrim()).CreateColorSpaceNameAttr(
                p.color_space
            )
        paths.append(prod.GetPath())
        for f in frames:
            write_rgba(root / expand_frame_tokens(p.product_name, f), p.rgb[f])
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateProductsRel().SetTargets(paths)
    settings.CreateResolutionAttr(Gf.Vec2i(W, H))
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.GetRootLayer().Save()
    return root / "stage.usda"


def read_rgb(path: Path) -> np.ndarray:
    """R, G, B of a file, found by name, (H, W, 3) float32."""
    inp = oiio.ImageInput.open(str(path))
    assert inp is not None, oiio.geterror()
    spec = inp.spec()
    px = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, "float"), np.float32)
    inp.close()
    px = px.reshape(spec.height, spec.width, spec.nchannels)
    names = list(spec.channelnames)
    return np.stack([px[..., names.index(c)] for c in "RGB"], axis=-1)
