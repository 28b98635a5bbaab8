"""USD cameras against Cycles' motion vectors, window conforming, and OCIO color."""

from __future__ import annotations

from pathlib import Path

import fixtures
import handmade
import numpy as np
import pytest
from pxr import Gf, Usd
from usd_harmonizer import ColorSpaceError
from usd_harmonizer.camera import conform_window, exr_matrices, project, unproject
from usd_harmonizer.color import (
    ColorConverter,
    converter_for,
    find_color_space,
    load_config,
)
from usd_harmonizer.cli import main
from usd_harmonizer.exrio import read_exr


def test_camera_matrices_match_cycles_vector_pass(rendered: Path) -> None:
    """Reprojecting frame t from its depth with the USD camera of t and t-1
    must reproduce the motion vectors Cycles rendered from the same stage
    (static scene, moving camera): median error < 0.02 px, 99th pct < 0.1 px."""
    stage = Usd.Stage.Open(str(rendered / "shot.usda"))
    cam = stage.GetPrimAtPath("/World/Cam")
    w, h = fixtures.W, fixtures.H
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    px = np.stack([jj.ravel() + 0.5, ii.ravel() + 0.5], axis=1)
    for f in fixtures.FRAMES[1:]:
        img = read_exr(rendered / f"render/beauty.{f:04d}.exr", "test")
        w2c, w2n = exr_matrices(cam, f, (w, h))
        _, pw2n = exr_matrices(cam, f - 1, (w, h))
        world = unproject(
            w2c, w2n, px, img.channel("Z").ravel().astype(np.float64), w, h
        )
        mv = project(pw2n, world, w, h) - px
        cycles = np.stack(
            [img.channel("Vector.X").ravel(), -img.channel("Vector.Y").ravel()], axis=1
        )
        err = np.linalg.norm(mv - cycles, axis=1)
        assert np.abs(cycles).max() > 1.0, "the camera must move"
        assert np.median(err) < 0.02, (f, np.median(err))
        assert np.percentile(err, 99) < 0.1, (f, np.percentile(err, 99))
        # Camera space +z forward: planar depth equals camera z.
        cam_z = (np.concatenate([world, np.ones((len(world), 1))], axis=1) @ w2c)[:, 2]
        assert np.allclose(cam_z, img.channel("Z").ravel(), rtol=1e-4)


def test_conform_window() -> None:
    win = Gf.Range2d(Gf.Vec2d(-1, -1), Gf.Vec2d(1, 1))  # aspect 1

    def size(r: Gf.Range2d) -> tuple[float, float]:
        return (round(r.GetSize()[0], 6), round(r.GetSize()[1], 6))

    assert size(conform_window(win, "expandAperture", 2.0)) == (4.0, 2.0)
    assert size(conform_window(win, "cropAperture", 2.0)) == (2.0, 1.0)
    assert size(conform_window(win, "adjustApertureWidth", 2.0)) == (4.0, 2.0)
    assert size(conform_window(win, "adjustApertureHeight", 2.0)) == (2.0, 1.0)
    assert size(conform_window(win, "adjustPixelAspectRatio", 2.0)) == (2.0, 2.0)
    assert size(conform_window(win, "expandAperture", 0.5)) == (2.0, 4.0)


def test_ndc_corners(rendered: Path) -> None:
    """The frustum's top-left corner lands on NDC (0, 0), bottom-right on (1, 1)."""
    stage = Usd.Stage.Open(str(rendered / "shot.usda"))
    prim = stage.GetPrimAtPath("/World/Cam")
    from pxr import UsdGeom

    fr = UsdGeom.Camera(prim).GetCamera(Usd.TimeCode(1003)).frustum
    corners = fr.ComputeCornersAtDistance(
        5.0
    )  # bottom-left, bottom-right, top-left, top-right
    _, w2n = exr_matrices(prim, 1003, (128, 72))
    pts = np.array([[c[0], c[1], c[2]] for c in corners])
    uv = project(w2n, pts, 1, 1)
    assert np.allclose(uv, [[0, 1], [1, 1], [0, 0], [1, 0]], atol=1e-6)


def test_color_space_lookup() -> None:
    cfg, _ = load_config("ocio://default")
    for name in ("ACEScg", "acescg", "lin_ap1_scene", "lin_ap1"):
        assert find_color_space(cfg, name).getName() == "ACEScg"
    assert (
        find_color_space(cfg, "lin_rec709_scene").getName() == "Linear Rec.709 (sRGB)"
    )
    assert find_color_space(cfg, "no such space") is None


@pytest.mark.parametrize(
    "space",
    ["ACEScg", "Linear Rec.709 (sRGB)", "lin_rec2020_scene", "srgb_rec709_scene"],
)
def test_round_trip(space: str) -> None:
    rng = np.random.default_rng(1)
    rgb = rng.uniform(0, 4, (16, 16, 3)).astype(np.float32)
    alpha = rng.uniform(0.2, 1, (16, 16)).astype(np.float32)
    rgb *= alpha[..., None]
    conv = ColorConverter(*load_config("ocio://default"), space, "test")
    back = conv.from_linear(conv.to_linear(rgb, alpha), alpha)
    assert np.abs(back - rgb).max() < 1e-4


def test_acescg_to_linear_rec709_is_the_real_conversion() -> None:
    conv = ColorConverter(*load_config("ocio://default"), "ACEScg", "test")
    # Pure AP1 red is outside Rec.709: negative green/blue, red > 1.
    out = conv.to_linear(np.array([[[1.0, 0.0, 0.0]]], np.float32))[0, 0]
    assert out[0] == pytest.approx(1.7051, abs=1e-3)
    assert out[1] == pytest.approx(-0.1302, abs=1e-3)


@pytest.mark.parametrize(
    "name, token",
    [
        ("ACEScg", "lin_ap1_scene"),
        ("lin_ap1", "lin_ap1_scene"),
        ("lin_ap1_scene", "lin_ap1_scene"),
        ("Linear Rec.709 (sRGB)", "lin_rec709_scene"),
        ("Linear Rec.2020", "lin_rec2020_scene"),
        ("sRGB - Texture", "srgb_rec709_scene"),
        ("Raw", "data"),
        ("ACEScct", None),  # no USD token: the new product gets no UsdColorSpaceAPI
    ],
)
def test_usd_color_space_name(name: str, token: str | None) -> None:
    """The USD token (GfColorSpaceNames) a new product declares for the OCIO
    space its color is in (issue 9)."""
    conv = ColorConverter(*load_config("ocio://default"), name, "test")
    assert conv.usd_name == token


def test_color_space_precedence_and_errors() -> None:
    c = converter_for(
        ("ACEScg", "/Render/Vars/color.colorSpace"),
        {"colorInteropID": "lin_rec709_scene"},
        "f.exr",
        None,
    )
    assert c.source_name == "ACEScg"
    c = converter_for(
        None, {"colorInteropID": "lin_ap1_scene"}, "f.exr", "lin_rec709_scene"
    )
    assert c.source_name == "ACEScg"
    c = converter_for(None, {"oiio:ColorSpace": "lin_rec2020_scene"}, "f.exr", None)
    assert c.source_name == "Linear Rec.2020"
    c = converter_for(None, {}, "f.exr", "lin_ap1_scene")
    assert c.source_name == "ACEScg"
    c = converter_for(None, {}, "f.exr", None, "ocio://default")
    assert c.source_name == "ACEScg"  # the default config's scene_linear role
    with pytest.raises(
        ColorSpaceError,
        match=r"color space 'ProPhoto Film' \(declared by /P.colorSpace\) is unknown to the OCIO config ocio://default \(known: ",
    ):
        converter_for(
            ("ProPhoto Film", "/P.colorSpace"), {}, "f.exr", None, "ocio://default"
        )
    with pytest.raises(
        ColorSpaceError,
        match=r"'weird' \(attribute colorInteropID of f.exr\) is unknown",
    ):
        converter_for(
            None, {"colorInteropID": "weird"}, "f.exr", None, "ocio://default"
        )
    with pytest.raises(
        ColorSpaceError, match=r"OCIO config /nonexistent.ocio: cannot load"
    ):
        load_config("/nonexistent.ocio")


def test_data_window_matrix(rendered: Path) -> None:
    """With a data window inside (or around) the display window, pixel
    positions shift by the window offset: the library sees data-window pixels."""
    import OpenImageIO as oiio
    from usd_harmonizer.process import data_window_matrix

    stage = Usd.Stage.Open(str(rendered / "shot.usda"))
    _, w2n = exr_matrices(stage.GetPrimAtPath("/World/Cam"), 1003, (128, 72))
    pts = np.array([[0.5, 1.0, 0.0], [-1.2, 2.0, 0.3], [1.0, 0.0, 0.5]])
    full = project(w2n, pts, 128, 72)
    for x, y, w, h in ((10, 6, 100, 50), (-8, -4, 144, 80)):
        spec = oiio.ImageSpec(w, h, 3, "float")
        spec.x, spec.y = x, y
        spec.full_x, spec.full_y, spec.full_width, spec.full_height = 0, 0, 128, 72
        got = project(w2n @ data_window_matrix(spec), pts, w, h)
        assert np.allclose(got, full - [x, y], atol=1e-9)
    spec = oiio.ImageSpec(128, 72, 3, "float")
    assert np.array_equal(data_window_matrix(spec), np.eye(4))


def test_empty_depth_becomes_far() -> None:
    from usd_harmonizer.process import FAR_DEPTH, empty_depth_to_far

    d = np.array([[1.5, 0.0, -1.0], [np.inf, np.nan, 1e10]], np.float32)
    out = empty_depth_to_far(d)
    assert out.dtype == np.float32 and out.flags.c_contiguous
    assert out.tolist() == [[1.5, FAR_DEPTH, FAR_DEPTH], [FAR_DEPTH, FAR_DEPTH, 1e10]]
    assert d[0, 1] == 0.0  # the file's pixels are not touched


def wide_gamut_colors(rng: np.random.Generator) -> np.ndarray:
    """(H, W, 3) colors on the boundary of the product's own gamut (one
    component 0, one 1, one random, then scaled 0.01..8): every one outside
    Rec.709 when the space is ACEScg or Rec.2020; a grey ramp in the last row."""
    h, w = handmade.H, handmade.W
    rgb = np.zeros((h, w, 3))
    for px in rgb.reshape(-1, 3):
        i, j = rng.choice(3, 2, replace=False)
        px[i], px[j] = 1.0, rng.uniform(0, 1)
    rgb *= np.exp(rng.uniform(np.log(0.01), np.log(8.0), (h, w, 1)))
    rgb[-1] = np.linspace(0, 4, w)[:, None]
    return rgb.astype(np.float32)


@pytest.mark.parametrize(
    "mode",
    [("--backend", "bypass"), ("--backend", "classical", "--strength", "0")],
    ids=["bypass", "strength0"],
)
def test_wide_gamut_round_trip(tmp_path: Path, mode: tuple[str, ...]) -> None:
    """ACEScg and Rec.2020 products with saturated colors outside Rec.709
    (negative Linear Rec.709 components through the hook's OCIO config) come
    back within 1e-4 with backend=bypass and with strength 0: the library
    passes out-of-gamut color through instead of clipping it to 0."""
    rng = np.random.default_rng(2020)
    frames = [1, 2]
    spaces = {"acescg": "lin_ap1_scene", "rec2020": "lin_rec2020_scene"}
    rgb = {n: {f: wide_gamut_colors(rng) for f in frames} for n in spaces}
    stage = handmade.author(
        tmp_path / "wg",
        [
            handmade.Product(
                f"/Render/Products/{n}", f"render/{n}.####.exr", rgb[n], cs
            )
            for n, cs in spaces.items()
        ],
        frames,
    )
    config, name = load_config()  # what the hook uses: $OCIO, else ocio://default
    for n, cs in spaces.items():
        lin = ColorConverter(config, name, cs, "test").to_linear(rgb[n][1])
        # Every color but the grey row is outside Rec.709.
        assert (lin[:-1].min(axis=-1) < 0).all(), n
        assert lin.min() < -0.5, n
    out_dir = tmp_path / "out"
    assert main([str(stage), *mode, "--out-dir", str(out_dir), "--quiet"]) == 0
    for n in spaces:
        for f in frames:
            src = rgb[n][f]
            out = handmade.read_rgb(out_dir / n / f"{n}.{f:04d}.exr")
            finite = np.isfinite(src).all(axis=-1)
            assert finite.all()
            err = np.abs(out - src)[finite].max()
            assert err < 1e-4, (n, f, err, out[finite].min())
