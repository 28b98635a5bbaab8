"""The light direction the hook passes for inserts' cast shadows (issue 19):
``harmonizer:lightDirection`` on the product or settings prim, else the
stage's brightest DistantLight at each frame (its +Z axis in world space),
else none; ``--light-direction`` / ``--no-light``; the value reaching the
session; and end to end on the rendered shot, the insert's shadow landing
where the stage's Sun and camera put it."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux
from usd_harmonizer import ProductRunner, SettingsError, resolve, run_stage
from usd_harmonizer.camera import exr_matrices, project
from usd_harmonizer.cli import main
from usd_harmonizer.exrio import read_exr
from usd_harmonizer.light import (
    ATTR_LIGHT_DIRECTION,
    dominant_distant_light,
    light_at,
    parse_direction,
)
from usd_harmonizer.process import Options, make_device

import handmade

FRAMES = [1, 2, 3]


def _stage(tmp_path: Path, up_axis: str = "Y") -> Usd.Stage:
    """A hand-made stage (one product, frames 1-3) opened for editing."""
    rgb = {f: np.full((handmade.H, handmade.W, 3), 0.25, np.float32) for f in FRAMES}
    path = handmade.author(
        tmp_path, [handmade.Product("/Render/Products/beauty", "img.####.exr", rgb)], FRAMES
    )
    stage = Usd.Stage.Open(str(path))
    UsdGeom.SetStageUpAxis(stage, up_axis)
    return stage


def _plus_z(prim: Usd.Prim, frame: float) -> np.ndarray:
    """The prim's local +Z axis in world space, normalized (computed here
    with numpy from the local-to-world matrix, row-vector)."""
    m = UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(Usd.TimeCode(frame))
    z = np.array([m[2][0], m[2][1], m[2][2]], dtype=np.float64)
    return z / np.linalg.norm(z)


def _distant(stage, path: str, intensity: float, rotate=(0.0, 0.0, 0.0), exposure=None):
    light = UsdLux.DistantLight.Define(stage, path)
    light.CreateIntensityAttr(intensity)
    if exposure is not None:
        light.CreateExposureAttr(exposure)
    UsdGeom.XformCommonAPI(light).SetRotate(Gf.Vec3f(*rotate))
    return light


def _rot_x_then_z(ax: float, az: float) -> np.ndarray:
    """+Z after rotating by ``ax`` degrees about X, then ``az`` about Z (XYZ order)."""
    a, c = math.radians(ax), math.radians(az)
    z = np.array([0.0, -math.sin(a), math.cos(a)])
    return np.array([z[0] * math.cos(c) - z[1] * math.sin(c), z[0] * math.sin(c) + z[1] * math.cos(c), z[2]])


def test_direction_is_the_brightest_distant_lights_plus_z(tmp_path: Path) -> None:
    stage = _stage(tmp_path, up_axis="Z")
    # Under a rotated, scaled parent: the world transform counts, not the local one.
    rig = UsdGeom.Xform.Define(stage, "/World/Rig")
    UsdGeom.XformCommonAPI(rig).SetRotate(Gf.Vec3f(0.0, 0.0, 90.0))
    UsdGeom.XformCommonAPI(rig).SetScale(Gf.Vec3f(2.0, 2.0, 2.0))
    sun = _distant(stage, "/World/Rig/Sun", 3.0, rotate=(40.0, 0.0, 30.0))
    # Brighter by intensity alone, dimmer by intensity * 2^exposure (2^-2 * 8 = 2 < 3).
    _distant(stage, "/World/Fill", 8.0, rotate=(-60.0, 0.0, 0.0), exposure=-2.0)
    # Not directional, and brighter: never used.
    UsdLux.SphereLight.Define(stage, "/World/Bulb").CreateIntensityAttr(1000.0)
    light = dominant_distant_light(stage, 1)
    assert light.source == "DistantLight /World/Rig/Sun"
    want = _plus_z(sun.GetPrim(), 1)
    np.testing.assert_allclose(light.direction, want, atol=1e-9)
    # The same by hand: the light's own +Z (rotate X 40 then Z 30), then the rig's 90 about Z.
    local = _rot_x_then_z(40.0, 30.0)
    np.testing.assert_allclose(light.direction, [-local[1], local[0], local[2]], atol=1e-6)
    assert abs(np.linalg.norm(light.direction) - 1.0) < 1e-12
    # No conversion for upAxis Z: the stage's world, as the camera matrices are.
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    # Exposure decides: the fill at exposure 0 (8 > 3) wins.
    UsdLux.DistantLight(stage.GetPrimAtPath("/World/Fill")).GetExposureAttr().Set(0.0)
    assert dominant_distant_light(stage, 1).source == "DistantLight /World/Fill"
    # An invisible or inactive light is not a light of the render.
    UsdGeom.Imageable(stage.GetPrimAtPath("/World/Fill")).MakeInvisible()
    assert dominant_distant_light(stage, 1).source == "DistantLight /World/Rig/Sun"
    stage.GetPrimAtPath("/World/Rig").SetActive(False)
    assert dominant_distant_light(stage, 1).direction is None


def test_animated_rotation_is_read_at_each_frame(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    sun = _distant(stage, "/World/Sun", 5.0)
    xf = UsdGeom.XformCommonAPI(sun)
    xf.SetRotate(Gf.Vec3f(-30.0, 10.0, 0.0), time=Usd.TimeCode(1))
    xf.SetRotate(Gf.Vec3f(-70.0, 50.0, 0.0), time=Usd.TimeCode(3))
    dirs = [dominant_distant_light(stage, f).direction for f in FRAMES]
    for f, d in zip(FRAMES, dirs, strict=True):
        np.testing.assert_allclose(d, _plus_z(sun.GetPrim(), f), atol=1e-9, err_msg=f"frame {f}")
    # It moves: a direction read once would be wrong by degrees on later frames.
    angle = math.degrees(math.acos(float(np.clip(np.dot(dirs[0], dirs[2]), -1, 1))))
    assert angle > 30.0, angle
    assert not np.allclose(dirs[1], dirs[0]) and not np.allclose(dirs[1], dirs[2])


def test_override_attribute_on_product_then_settings(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    _distant(stage, "/World/Sun", 5.0, rotate=(-45.0, 0.0, 0.0))
    product = stage.GetPrimAtPath("/Render/Products/beauty")
    settings = stage.GetPrimAtPath("/Render/Settings")
    prims = [product, settings]
    assert light_at(stage, prims, 1).source == "DistantLight /World/Sun"
    settings.CreateAttribute(ATTR_LIGHT_DIRECTION, Sdf.ValueTypeNames.Float3, custom=True).Set(
        Gf.Vec3f(0.0, 2.0, 0.0)
    )
    light = light_at(stage, prims, 1)
    assert light.source == "/Render/Settings.harmonizer:lightDirection"
    np.testing.assert_allclose(light.direction, [0.0, 1.0, 0.0])
    attr = product.CreateAttribute(ATTR_LIGHT_DIRECTION, Sdf.ValueTypeNames.Float3, custom=True)
    attr.Set(Gf.Vec3f(1.0, 1.0, 0.0), Usd.TimeCode(1))
    attr.Set(Gf.Vec3f(-1.0, 1.0, 0.0), Usd.TimeCode(3))
    first, last = light_at(stage, prims, 1), light_at(stage, prims, 3)
    assert first.source == "/Render/Products/beauty.harmonizer:lightDirection"
    s = 1.0 / math.sqrt(2.0)
    np.testing.assert_allclose(first.direction, [s, s, 0.0], atol=1e-7)
    np.testing.assert_allclose(last.direction, [-s, s, 0.0], atol=1e-7)
    # (0, 0, 0): no light, though the stage has a sun.
    attr.Clear()
    attr.Set(Gf.Vec3f(0.0, 0.0, 0.0))
    none = light_at(stage, prims, 2)
    assert none.direction is None and none.param == ""


def test_no_lights_no_direction(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    UsdLux.DomeLight.Define(stage, "/World/Sky").CreateIntensityAttr(2.0)
    _distant(stage, "/World/Off", 0.0)  # zero intensity: not a light
    light = light_at(stage, [stage.GetPrimAtPath("/Render/Products/beauty")], 1)
    assert light.direction is None and light.source == "none"


def test_parse_direction() -> None:
    assert parse_direction("0,0,2", "--light-direction") == (0.0, 0.0, 1.0)
    assert parse_direction(" 3 4 0 ", "--light-direction") == pytest.approx((0.6, 0.8, 0.0))
    for bad in ("1,2", "0,0,0", "a,b,c", "1,nan,0"):
        with pytest.raises(SettingsError, match="--light-direction"):
            parse_direction(bad, "--light-direction")


def _session_values(
    stage_path: Path, options: Options, param: str = "light_direction"
) -> list[tuple[object, object]]:
    """(the session's ``param``, FrameResult) for frames 1-3 of the product."""
    stage = Usd.Stage.Open(str(stage_path))
    info = resolve(stage)
    device = make_device(options)
    out = []
    try:
        runner = ProductRunner(info.products[0], info, device, options)
        try:
            assert runner.session.get("light_space") == "world"
            for f in FRAMES:
                r = runner.process_frame(f)
                out.append((runner.session.get(param), r))
        finally:
            runner.close()
    finally:
        device.close()
    return out


def _floats(text: str) -> list[float]:
    return [float(t) for t in text.split(",")]


def test_direction_reaches_the_session_every_frame(tmp_path: Path) -> None:
    stage = _stage(tmp_path)
    sun = _distant(stage, "/World/Sun", 5.0)
    xf = UsdGeom.XformCommonAPI(sun)
    xf.SetRotate(Gf.Vec3f(-20.0, 0.0, 0.0), time=Usd.TimeCode(1))
    xf.SetRotate(Gf.Vec3f(-80.0, 0.0, 40.0), time=Usd.TimeCode(3))
    stage.GetRootLayer().Save()
    path = tmp_path / "stage.usda"
    got = _session_values(path, Options(backend="bypass", out_dir=tmp_path / "a"))
    for f, (param, r) in zip(FRAMES, got, strict=True):
        want = _plus_z(sun.GetPrim(), f)
        np.testing.assert_allclose(_floats(param), want, atol=1e-6, err_msg=f"frame {f}")
        np.testing.assert_allclose(r.light_direction, want, atol=1e-9)
        assert r.light_source == "DistantLight /World/Sun"
        attrs = read_exr(r.output, "out").attributes()
        np.testing.assert_allclose(_floats(attrs["harmonizer:lightDirection"]), want, atol=1e-6)
    # "none" and a fixed direction win over the stage's sun.
    got = _session_values(path, Options(backend="bypass", light="none", out_dir=tmp_path / "b"))
    assert [p for p, _ in got] == ["", "", ""]
    assert all(r.light_direction is None and r.light_source == "none" for _, r in got)
    assert "harmonizer:lightDirection" not in read_exr(got[0][1].output, "out").attributes()
    got = _session_values(path, Options(backend="bypass", light=(0.0, 3.0, 4.0), out_dir=tmp_path / "c"))
    for param, r in got:
        np.testing.assert_allclose(_floats(param), [0.0, 0.6, 0.8], atol=1e-6)
        assert r.light_source == "--light-direction"


def test_cli_light_flags(tmp_path: Path, capsys) -> None:
    stage = _stage(tmp_path)
    _distant(stage, "/World/Sun", 5.0, rotate=(-45.0, 0.0, 0.0))
    stage.GetRootLayer().Save()
    path = str(tmp_path / "stage.usda")
    common = [path, "--backend", "bypass", "--no-layer", "--frames", "1-2"]

    def run(out: str, *flags: str) -> tuple[dict, str]:
        capsys.readouterr()
        assert main([*common, "--out-dir", str(tmp_path / out), *flags]) == 0
        printed = capsys.readouterr().out
        return read_exr(tmp_path / out / "beauty" / "img.0002.exr", "out").attributes(), printed

    attrs, printed = run("auto")
    np.testing.assert_allclose(
        _floats(attrs["harmonizer:lightDirection"]), [0.0, math.sqrt(0.5), math.sqrt(0.5)], atol=1e-6
    )
    assert "light: DistantLight /World/Sun, light ratio: measured by the library" in printed, printed
    # A negative first component needs the = form (argparse takes "-1,..." for an option).
    attrs, printed = run("flag", "--light-direction=-1,0,1")
    np.testing.assert_allclose(
        _floats(attrs["harmonizer:lightDirection"]), [-math.sqrt(0.5), 0.0, math.sqrt(0.5)], atol=1e-6
    )
    assert "light: --light-direction" in printed
    attrs, printed = run("off", "--no-light")
    assert "harmonizer:lightDirection" not in attrs
    assert "light: none" in printed
    assert main([*common, "--light-direction", "1,2"]) == 1
    assert "--light-direction '1,2': expected three numbers" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main([*common, "--light-direction", "0,0,1", "--no-light"])


def test_cast_shadow_lands_away_from_the_stage_sun(shot: Path) -> None:
    """End to end on the rendered shot (Z up): the light and the camera
    matrices the hook passes agree on the stage's world.

    The shot's Sun is turned (in the shot's own layer) to come from the left,
    low: the Cycles frames were lit from elsewhere, so the floor the insert
    sphere would shade from this Sun has no shadow in them, and the classical
    backend adds it. At the ground point G = C - (C.z / d.z) d under the
    sphere's centre C (d toward the Sun), and 0.3 further from the Sun, the
    output is darker than the same run with ``light="none"`` (0.40 of it,
    measured); at the mirror of G through the sphere's foot it is unchanged.
    """
    stage = Usd.Stage.Open(str(shot))
    d = np.array([-0.8, -0.3, 0.5])
    d /= np.linalg.norm(d)
    # rotateXYZ (a, 0, c) turns +Z into (sin a sin c, -sin a cos c, cos a).
    a, c = math.degrees(math.acos(d[2])), math.degrees(math.atan2(d[0], -d[1]))
    sun = stage.GetPrimAtPath("/World/Sun")
    UsdGeom.XformCommonAPI(sun).SetRotate(Gf.Vec3f(a, 0.0, c))
    stage.GetRootLayer().Save()
    np.testing.assert_allclose(_plus_z(sun, 1003), d, atol=1e-6)
    frames = [1001, 1002, 1003]
    out = {}
    for light in ("auto", "none"):
        summary = run_stage(
            shot,
            products=["beauty"],
            frames=frames,
            options=Options(backend="classical", light=light, out_dir=shot.parent / light),
            write_layer_file=False,
        )
        r = summary.results["/Render/Products/beauty"][1][-1]
        assert r.light_source == ("DistantLight /World/Sun" if light == "auto" else "none")
        out[light] = read_exr(r.output, "out")
    src = read_exr(r.source, "in")
    centre = np.array([0.9, -0.3, 0.55])  # author_scene's insert sphere (radius 0.55)
    g = centre - centre[2] / d[2] * d
    away = -np.array([d[0], d[1], 0.0]) / np.hypot(d[0], d[1])
    points = {"shadow": g, "shadow_far": g + 0.3 * away, "lit_side": np.array([*(2 * centre[:2] - g[:2]), 0.0])}
    _, w2n = exr_matrices(stage.GetPrimAtPath("/World/Cam"), 1003, (128, 72))
    ratios = {}
    for k, p in points.items():
        x, y = (int(v) for v in project(w2n, p[None], 128, 72)[0])
        win = (slice(y - 1, y + 2), slice(x - 1, x + 2))
        assert 1 <= x < 127 and 1 <= y < 71 and src.channel("mask.insert")[win].max() == 0, (k, x, y)

        def lum(img):
            return sum(w * img.channel(ch)[win] for w, ch in zip((0.2126, 0.7152, 0.0722), "RGB")).mean()

        ratios[k] = float(lum(out["auto"]) / lum(out["none"]))
    print(f"\nshot, frame 1003, output with the Sun / without: {ratios}")
    assert ratios["shadow"] < 0.8 and ratios["shadow_far"] < 0.8, ratios
    assert abs(ratios["lit_side"] - 1.0) < 0.02, ratios


def _ratio_values(stage_path: Path, options: Options) -> list[tuple[object, object]]:
    """(session light_ratio, FrameResult) for frames 1-3 of the product."""
    return _session_values(stage_path, options, "light_ratio")


def test_light_ratio_is_the_sun_over_the_dome(tmp_path: Path) -> None:
    """Issue 19: the session's ``light_ratio`` is the brightest
    DistantLight's irradiance over half the DomeLights' (pi times their
    radiance), read at each frame; ``harmonizer:lightRatio`` overrides it;
    a dome texture not found, no dome or no light leave it to the library (0)."""
    stage = _stage(tmp_path)
    _distant(stage, "/World/Sun", 2.0, exposure=1.0)  # 4, white
    _distant(stage, "/World/Fill", 1.5)
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateIntensityAttr(0.5)
    dome.CreateColorAttr(Gf.Vec3f(0.4, 0.6, 1.0))
    dome.GetIntensityAttr().Set(1.0, Usd.TimeCode(3))
    dome.GetIntensityAttr().Set(0.5, Usd.TimeCode(1))
    stage.GetRootLayer().Save()
    path = tmp_path / "stage.usda"
    luma = 0.2126 * 0.4 + 0.7152 * 0.6 + 0.0722 * 1.0
    # The ambient: half a whole sky's irradiance (pi times the radiance).
    want = {f: 4.0 / (0.5 * math.pi * i * luma) for f, i in ((1, 0.5), (2, 0.75), (3, 1.0))}
    got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "a"))
    for f, (param, r) in zip(FRAMES, got, strict=True):
        assert param == pytest.approx(want[f], rel=1e-5), f
        assert r.light_ratio == pytest.approx(want[f], rel=1e-6)
        assert r.light_ratio_source == "DistantLight /World/Sun over DomeLight /World/Sky"
        attrs = read_exr(r.output, "out").attributes()
        assert float(attrs["harmonizer:lightRatio"]) == pytest.approx(want[f], rel=1e-6)
    # The override on the product wins; 0 there hands it to the library.
    stage = Usd.Stage.Open(str(path))
    attr = stage.GetPrimAtPath("/Render/Products/beauty").CreateAttribute(
        "harmonizer:lightRatio", Sdf.ValueTypeNames.Float
    )
    attr.Set(2.5)
    stage.GetRootLayer().Save()
    got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "b"))
    assert all(p == pytest.approx(2.5) for p, _ in got)
    attr.Set(0.0)
    stage.GetRootLayer().Save()
    got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "c"))
    assert all(p == 0.0 and r.light_ratio is None for p, r in got)
    attr.Set(-1.0)
    stage.GetRootLayer().Save()
    with pytest.raises(Exception, match="lightRatio"):
        _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "d"))
    attr.Clear()
    # A dome's texture that cannot be read leaves the ratio to the library, saying why; no light, no ratio.
    UsdLux.DomeLight(stage.GetPrimAtPath("/World/Sky")).CreateTextureFileAttr(
        Sdf.AssetPath("sky.exr")
    )
    stage.GetRootLayer().Save()
    got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "e"))
    assert all(
        p == 0.0 and r.light_ratio_source == "DomeLight /World/Sky: texture 'sky.exr' not found"
        for p, r in got
    )
    got = _ratio_values(path, Options(backend="bypass", light="none", out_dir=tmp_path / "f"))
    assert all(p == 0.0 for p, _ in got)


def _latlong(path: Path, rgb: np.ndarray) -> None:
    """Writes a float lat-long image (rows from the top) with OpenImageIO."""
    import OpenImageIO as oiio

    h, w, c = rgb.shape
    out = oiio.ImageOutput.create(str(path))
    assert out is not None and out.open(
        str(path), oiio.ImageSpec(w, h, c, oiio.HALF if path.suffix == ".exr" else oiio.FLOAT)
    )
    assert out.write_image(np.ascontiguousarray(rgb, np.float32))
    out.close()


def test_light_ratio_reads_a_textured_dome(tmp_path: Path) -> None:
    """Issue 19: an HDRI dome gives the irradiance its texture sends onto a
    surface facing the stage's up axis. OpenEXR's lat-long, as UsdLux says:
    a texture bright in its upper half gives ``pi`` times its mean radiance
    on a Y-up stage (whatever varies along the longitude); on a Z-up stage
    half as much (that half then faces sideways) unless the dome is turned
    up or a ``DomeLight_1`` has its pole on the scene's axis; a patch at
    longitude +pi/2 lies toward the dome's +X; the dome's color, intensity
    and exposure scale it; an 8-bit image or another layout is not read,
    and says so."""
    h, w = 64, 128
    sky = np.zeros((h, w, 3), np.float32)
    sky[: h // 2] = (0.3, 0.5, 0.9)
    sky[: h // 2, 10:20] *= 4.0  # brighter over some longitudes
    _latlong(tmp_path / "sky.exr", sky)
    lum = float(np.dot([0.2126, 0.7152, 0.0722], sky[: h // 2].mean(axis=(0, 1))))

    stage = _stage(tmp_path, up_axis="Y")
    _distant(stage, "/World/Sun", 3.0)
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateTextureFileAttr(Sdf.AssetPath("sky.exr"))
    dome.CreateIntensityAttr(0.5)
    stage.GetRootLayer().Save()
    path = tmp_path / "stage.usda"
    want = 3.0 / (0.5 * math.pi * 0.5 * lum)
    got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "y"))
    for f, (param, r) in zip(FRAMES, got, strict=True):
        assert param == pytest.approx(want, rel=0.01), (f, param, want)
        assert r.light_ratio == pytest.approx(param, rel=1e-6)
        assert r.light_ratio_source == "DistantLight /World/Sun over DomeLight /World/Sky"
    # Color and exposure: (0.5, 1, 1) halves the red, 2^1 doubles it all.
    dome.CreateColorAttr(Gf.Vec3f(0.5, 1.0, 1.0))
    dome.CreateExposureAttr(1.0)
    stage.GetRootLayer().Save()
    tinted = float(np.dot([0.2126 * 0.5, 0.7152, 0.0722], sky[: h // 2].mean(axis=(0, 1))))
    got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "tint"))
    assert got[0][0] == pytest.approx(3.0 / (0.5 * math.pi * 0.5 * 2.0 * tinted), rel=0.01)
    dome.GetColorAttr().Clear()
    dome.GetExposureAttr().Clear()

    # Z up, an upper half of one radiance: its top faces the dome's +Y
    # (sideways), and a surface facing up gets half of pi times it.
    half = np.zeros((h, w, 3), np.float32)
    half[: h // 2] = 0.5
    _latlong(tmp_path / "half.exr", half)
    dome.GetTextureFileAttr().Set(Sdf.AssetPath("half.exr"))
    UsdLux.DistantLight(stage.GetPrimAtPath("/World/Sun")).GetIntensityAttr().Set(
        1.5
    )  # under the largest ratio
    stage.GetRootLayer().Save()
    want_half = 1.5 / (0.5 * math.pi * 0.5 * 0.5)
    assert _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "half_y"))[0][
        0
    ] == pytest.approx(want_half, rel=0.01)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    stage.GetRootLayer().Save()
    got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "half_z"))
    assert got[0][0] == pytest.approx(2.0 * want_half, rel=0.02)
    # Turned up by 90 degrees about X (+Y onto +Z), it lights the ground again.
    UsdGeom.XformCommonAPI(dome).SetRotate(Gf.Vec3f(90.0, 0.0, 0.0))
    stage.GetRootLayer().Save()
    got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "half_z_turned"))
    assert got[0][0] == pytest.approx(want_half, rel=0.01)

    # Longitude: a patch at latitude 0, longitude +pi/2 lies toward the
    # dome's +X. Turned -90 degrees about Y, +X faces up (+Z): the patch
    # lights the ground; turned +90, it faces down. Over a uniform 5 and
    # ten times brighter: not a sun.
    patch = np.full((h, w, 3), 5.0, np.float32)
    col = round((math.pi - math.pi / 2) / (2 * math.pi) * w)  # column of longitude +pi/2
    patch[h // 2 - 2 : h // 2 + 2, col - 2 : col + 2] = 50.0
    _latlong(tmp_path / "patch.exr", patch)
    dome.GetTextureFileAttr().Set(Sdf.AssetPath("patch.exr"))
    solid = 16 * (math.pi / h) * (2 * math.pi / w)  # 4x4 texels at the equator
    for turn, extra in ((-90.0, 45.0 * solid), (90.0, 0.0)):
        UsdGeom.XformCommonAPI(dome).SetRotate(Gf.Vec3f(0.0, turn, 0.0))
        stage.GetRootLayer().Save()
        got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / f"patch_{turn}"))
        want_patch = 1.5 / (0.5 * 0.5 * (5.0 * math.pi + extra))
        assert got[0][0] == pytest.approx(want_patch, rel=0.005), (turn, got[0][0], want_patch)
    UsdGeom.XformCommonAPI(dome).SetRotate(Gf.Vec3f(0.0, 0.0, 0.0))

    # DomeLight_1 with its pole on the scene's up axis: no turn needed.
    stage.RemovePrim("/World/Sky")
    dome1 = UsdLux.DomeLight_1.Define(stage, "/World/Sky")
    dome1.CreateTextureFileAttr(Sdf.AssetPath("half.exr"))
    dome1.CreateIntensityAttr(0.5)
    dome1.CreatePoleAxisAttr("scene")
    stage.GetRootLayer().Save()
    got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "pole"))
    assert got[0][0] == pytest.approx(want_half, rel=0.01)
    assert got[0][1].light_ratio_source == "DistantLight /World/Sun over DomeLight /World/Sky"

    # Not read: an 8-bit image, another layout, a texture not twice as wide as high.
    import OpenImageIO as oiio

    out = oiio.ImageOutput.create(str(tmp_path / "sky.png"))
    assert out.open(str(tmp_path / "sky.png"), oiio.ImageSpec(w, h, 3, oiio.UINT8))
    assert out.write_image(np.zeros((h, w, 3), np.uint8))
    out.close()
    _latlong(tmp_path / "square.exr", np.ones((h, h, 3), np.float32))
    for tex, fmt, why in (
        ("sky.png", "automatic", "is not a float (linear) image"),
        ("sky.exr", "mirroredBall", "texture format 'mirroredBall': only lat-long images are read"),
        ("square.exr", "automatic", "is 64x64: a lat-long image is twice as wide as high"),
    ):
        dome1.GetTextureFileAttr().Set(Sdf.AssetPath(tex))
        dome1.CreateTextureFormatAttr(fmt)
        stage.GetRootLayer().Save()
        got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / f"bad_{fmt}_{tex}"))
        assert all(p == 0.0 and why in r.light_ratio_source for p, r in got), (
            tex,
            [r.light_ratio_source for _, r in got],
        )


def test_the_sun_in_a_dome_s_texture_is_the_light(tmp_path: Path) -> None:
    """Issue 19: an HDRI with a sun and no DistantLight: the direction is
    toward the sun in the texture (its texels' power-weighted mean), the
    ratio its irradiance over half the rest of the sky's; a sun below the
    horizon is none; a DistantLight wins the direction and the ratio, the
    texture's sun still left out of the ambient."""
    h, w = 64, 128
    tex = np.zeros((h, w, 3), np.float32)
    tex[: h // 2] = 0.5  # sky
    tex[h // 2 :] = 0.1  # ground
    r0, c0 = 21, 31  # a 2x2 sun centred at latitude 90 - 180 * 22 / 64, longitude +pi/2
    tex[r0 : r0 + 2, c0 : c0 + 2] = 500.0
    _latlong(tmp_path / "sunny.exr", tex)
    lat = math.pi / 2 - math.pi * (r0 + 1) / h
    toward = np.array([math.cos(lat), math.sin(lat), 0.0])  # +X at longitude +pi/2, Y up
    stage = _stage(tmp_path, up_axis="Y")
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateTextureFileAttr(Sdf.AssetPath("sunny.exr"))
    stage.GetRootLayer().Save()
    path = tmp_path / "stage.usda"
    opts = Options(backend="bypass", out_dir=tmp_path / "dir")
    for direction, r in _session_values(path, opts):
        assert r.light_source == "DomeLight /World/Sky (the sun in its texture)"
        d = _floats(direction)
        angle = math.degrees(math.acos(min(1.0, float(np.dot(d, toward)))))
        assert angle < 0.5, (d, toward)
    # The sun's irradiance (texels at about one latitude) over half the sky's
    # on a surface facing up (pi * 0.5, less the sky texels around the sun).
    texel = [math.cos(math.pi / 2 - math.pi * (r + 0.5) / h) * (math.pi / h) * (2 * math.pi / w) for r in (r0, r0 + 1)]
    direct = 500.0 * 2 * sum(texel)
    want = direct / (0.5 * math.pi * 0.5)
    got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "ratio"))
    for param, r in got:
        assert param == pytest.approx(want, rel=0.03), (param, want)
        assert r.light_ratio_source == "the sun of DomeLight /World/Sky over DomeLight /World/Sky"
    # Turned upside down (180 degrees about X): the sun is below the horizon.
    UsdGeom.XformCommonAPI(dome).SetRotate(Gf.Vec3f(180.0, 0.0, 0.0))
    stage.GetRootLayer().Save()
    assert all(
        r.light_direction is None and r.light_source == "none"
        for _, r in _session_values(path, Options(backend="bypass", out_dir=tmp_path / "below"))
    )
    assert all(p == 0.0 for p, _ in _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "below_r")))
    UsdGeom.XformCommonAPI(dome).SetRotate(Gf.Vec3f(0.0, 0.0, 0.0))
    # A DistantLight wins; the texture's sun is still not ambient.
    _distant(stage, "/World/Sun", 1.0, rotate=(-50.0, 0.0, 0.0))
    stage.GetRootLayer().Save()
    for _, r in _session_values(path, Options(backend="bypass", out_dir=tmp_path / "distant")):
        assert r.light_source == "DistantLight /World/Sun"
    got = _ratio_values(path, Options(backend="bypass", out_dir=tmp_path / "distant_r"))
    assert got[0][0] == pytest.approx(1.0 / (0.5 * math.pi * 0.5), rel=0.03)
    assert got[0][1].light_ratio_source == "DistantLight /World/Sun over DomeLight /World/Sky"


def test_the_lights_colors_reach_the_session(tmp_path: Path) -> None:
    """Issue 19: with the ratio, the session gets the lights themselves: the
    brightest DistantLight's irradiance per channel (``intensity *
    2^exposure`` times its color: ``light_color``) and half the domes' on a
    surface facing up (``ambient_color``; a textured dome's from its texture,
    the sun's texels as the direct light without a DistantLight), read at
    each frame; an override of the ratio, the params' own colors, or no
    dome leave them unset (or the params')."""
    stage = _stage(tmp_path)
    sun = _distant(stage, "/World/Sun", 2.0, exposure=1.0)
    sun.CreateColorAttr(Gf.Vec3f(1.0, 0.8, 0.5))
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateColorAttr(Gf.Vec3f(0.4, 0.6, 1.0))
    dome.CreateIntensityAttr(0.5)
    dome.GetIntensityAttr().Set(0.5, Usd.TimeCode(1))
    dome.GetIntensityAttr().Set(1.0, Usd.TimeCode(3))
    stage.GetRootLayer().Save()
    path = tmp_path / "stage.usda"

    def colors(out: str, **kw) -> list[tuple[str, str]]:
        got = _session_values(path, Options(backend="bypass", out_dir=tmp_path / out, **kw), "light_color")
        amb = _session_values(path, Options(backend="bypass", out_dir=tmp_path / (out + "_a"), **kw), "ambient_color")
        return [(c, a) for (c, _), (a, _) in zip(got, amb, strict=True)]

    for f, (light, ambient) in zip(FRAMES, colors("plain"), strict=True):
        i = {1: 0.5, 2: 0.75, 3: 1.0}[f]
        assert _floats(light) == pytest.approx([4.0, 3.2, 2.0], rel=1e-5), f
        assert _floats(ambient) == pytest.approx([0.5 * math.pi * i * c for c in (0.4, 0.6, 1.0)], rel=1e-5), f
    # The params' own colors win, and the other one still comes from the stage.
    got = colors("params", params={"light_color": "1, 1, 1"})
    assert all(_floats(c) == [1.0, 1.0, 1.0] and a != "" for c, a in got)
    # An override of the ratio says nothing of the colors.
    attr = stage.GetPrimAtPath("/Render/Products/beauty").CreateAttribute(
        "harmonizer:lightRatio", Sdf.ValueTypeNames.Float
    )
    attr.Set(2.5)
    stage.GetRootLayer().Save()
    assert all(c == "" and a == "" for c, a in colors("override"))
    attr.Clear()
    # A textured dome: its texture's light, per channel.
    h, w = 64, 128
    tex = np.zeros((h, w, 3), np.float32)
    tex[: h // 2] = (0.2, 0.4, 0.8)
    _latlong(tmp_path / "blue.exr", tex)
    dome.CreateTextureFileAttr(Sdf.AssetPath("blue.exr"))
    dome.GetIntensityAttr().Clear()
    dome.GetColorAttr().Set(Gf.Vec3f(1.0, 1.0, 1.0))
    stage.GetRootLayer().Save()
    for _, ambient in colors("textured"):
        # Half of pi times the upper half's radiance (a Y-up stage).
        assert _floats(ambient) == pytest.approx([0.5 * math.pi * c for c in (0.2, 0.4, 0.8)], rel=0.02)
    stage.RemovePrim("/World/Sky")
    stage.GetRootLayer().Save()
    assert all(c == "" and a == "" for c, a in colors("no_dome"))


def test_the_summary_line_says_the_light_ratio(tmp_path: Path, capsys) -> None:
    """``usd-harmonize`` says the ratio it passed and where it came from, or
    why the library measures it."""
    h, w = 32, 64
    tex = np.zeros((h, w, 3), np.float32)
    tex[: h // 2] = 0.5
    tex[10:12, 15:17] = 500.0
    _latlong(tmp_path / "sunny.exr", tex)
    stage = _stage(tmp_path, up_axis="Y")
    dome = UsdLux.DomeLight.Define(stage, "/World/Sky")
    dome.CreateTextureFileAttr(Sdf.AssetPath("sunny.exr"))
    stage.GetRootLayer().Save()
    common = [str(tmp_path / "stage.usda"), "--backend", "bypass", "--no-layer", "--frames", "1-2"]
    capsys.readouterr()
    assert main([*common, "--out-dir", str(tmp_path / "a")]) == 0
    printed = capsys.readouterr().out
    assert "light: DomeLight /World/Sky (the sun in its texture), light ratio: " in printed, printed
    assert "(the sun of DomeLight /World/Sky over DomeLight /World/Sky)" in printed, printed
    # A texture that cannot be read: the sun's light passes, the ratio says why not.
    dome.GetTextureFileAttr().Set(Sdf.AssetPath("missing.exr"))
    _distant(stage, "/World/Sun", 2.0)
    stage.GetRootLayer().Save()
    assert main([*common, "--out-dir", str(tmp_path / "b")]) == 0
    printed = capsys.readouterr().out
    want = "light ratio: measured by the library; DomeLight /World/Sky: texture 'missing.exr' not found"
    assert f"light: DistantLight /World/Sun, {want}" in printed, printed
