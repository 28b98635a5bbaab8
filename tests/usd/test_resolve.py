"""Settings, products, vars and frame resolution on stages authored with usd-core."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest
from pxr import Gf, Sdf, Usd, UsdGeom, UsdRender
from usd_harmonizer import (
    CameraError,
    SettingsError,
    VarError,
    expand_frame_tokens,
    parse_frame_range,
    resolve,
)
from usd_harmonizer.frames import has_frame_token, to_hash_pattern
from usd_harmonizer.settings import VarInfo, find_settings_prim
from usd_harmonizer.varmap import find_channels, map_vars, role_of


def make_stage(
    tmp_path: Path, name: str = "s.usda", product_name: str = "out/beauty.####.exr"
) -> Usd.Stage:
    stage = Usd.Stage.CreateNew(str(tmp_path / name))
    stage.SetStartTimeCode(1)
    stage.SetEndTimeCode(3)
    UsdGeom.Camera.Define(stage, "/Cam")
    for n, src, dt in (
        ("Ci", "Ci", "color3f"),
        ("a", "a", "float"),
        ("z", "z", "float"),
        ("mv", "motion", "float2"),
    ):
        v = UsdRender.Var.Define(stage, f"/Render/Vars/{n}")
        v.CreateSourceNameAttr(src)
        v.CreateDataTypeAttr(dt)
    p = UsdRender.Product.Define(stage, "/Render/Beauty")
    p.CreateProductNameAttr(product_name)
    p.CreateOrderedVarsRel().SetTargets(
        [Sdf.Path(f"/Render/Vars/{n}") for n in ("Ci", "a", "z", "mv")]
    )
    s = UsdRender.Settings.Define(stage, "/Render/Settings")
    s.CreateProductsRel().SetTargets([p.GetPath()])
    s.CreateCameraRel().SetTargets([Sdf.Path("/Cam")])
    s.CreateResolutionAttr(Gf.Vec2i(64, 32))
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    return stage


@pytest.mark.parametrize(
    "pattern, frame, expected",
    [
        ("a.####.exr", 7, "a.0007.exr"),
        ("a.#.exr", 1001, "a.1001.exr"),
        ("a.%04d.exr", 12, "a.0012.exr"),
        ("a.%d.exr", 12, "a.12.exr"),
        ("a.$F4.exr", 3, "a.0003.exr"),
        ("a.$F.exr", 3, "a.3.exr"),
        ("a.${F4}.exr", 1001, "a.1001.exr"),
        ("a.<F4>.exr", 42, "a.0042.exr"),
        ("a.<F>.exr", 42, "a.42.exr"),
        ("v###/a_$F5.exr", 9, "v009/a_00009.exr"),
        ("a.####.exr", -3, "a.-003.exr"),
    ],
)
def test_frame_tokens(pattern: str, frame: int, expected: str) -> None:
    assert has_frame_token(pattern)
    assert expand_frame_tokens(pattern, frame) == expected


def test_frame_token_helpers() -> None:
    assert not has_frame_token("beauty.exr")
    assert to_hash_pattern("a.$F4.b.<F2>.%03d.exr") == "a.####.b.##.###.exr"
    assert parse_frame_range("1001-1004") == [1001, 1002, 1003, 1004]
    assert parse_frame_range("1-9x4, 20") == [1, 5, 9, 20]
    with pytest.raises(SettingsError, match="cannot parse 'abc'"):
        parse_frame_range("abc")
    with pytest.raises(SettingsError, match="empty range"):
        parse_frame_range("5-1")


@pytest.mark.parametrize("token", ["####", "%04d", "$F4", "${F4}", "<F4>"])
def test_product_files_every_token(tmp_path: Path, token: str) -> None:
    stage = make_stage(tmp_path, product_name=f"out/beauty.{token}.exr")
    info = resolve(stage)
    assert info.path == "/Render/Settings"
    assert info.frames == [1, 2, 3]
    (prod,) = info.products
    assert prod.file_for(2) == tmp_path / "out/beauty.0002.exr"
    assert prod.resolution == (64, 32)  # from the settings
    assert prod.camera_path == "/Cam"  # from the settings
    assert [v.name for v in prod.vars] == ["Ci", "a", "z", "mv"]


def test_time_sampled_product_name(tmp_path: Path) -> None:
    stage = make_stage(tmp_path, product_name="fallback.exr")
    attr = UsdRender.Product(stage.GetPrimAtPath("/Render/Beauty")).GetProductNameAttr()
    attr.Set("shots/a_first.exr", 1)
    attr.Set("shots/b_$F4.exr", 2)
    prod = resolve(stage).products[0]
    assert prod.time_sampled
    assert prod.file_for(1) == tmp_path / "shots/a_first.exr"
    assert prod.file_for(2) == tmp_path / "shots/b_0002.exr"
    # Held value after the last sample, token expanded per frame.
    assert prod.file_for(3) == tmp_path / "shots/b_0003.exr"
    prod.check_frames_distinct([1, 2, 3])


def test_product_name_without_token_is_an_error_for_a_range(tmp_path: Path) -> None:
    stage = make_stage(tmp_path, product_name="out/beauty.exr")
    prod = resolve(stage).products[0]
    with pytest.raises(
        SettingsError,
        match=r"frames 1 and 2 both resolve to .*beauty.exr.*no frame token",
    ):
        prod.check_frames_distinct([1, 2, 3])


def test_settings_selection(tmp_path: Path) -> None:
    stage = make_stage(tmp_path)
    other = UsdRender.Settings.Define(stage, "/Render/Other")
    other.CreateProductsRel().SetTargets([Sdf.Path("/Render/Beauty")])
    assert find_settings_prim(stage).GetPath() == "/Render/Settings"
    assert resolve(stage, settings="/Render/Other").path == "/Render/Other"
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Gone")
    with pytest.raises(
        SettingsError,
        match=r"renderSettingsPrimPath '/Render/Gone' is not a RenderSettings prim",
    ):
        resolve(stage)
    stage.SetMetadata("renderSettingsPrimPath", "")
    with pytest.raises(
        SettingsError, match=r"2 RenderSettings prims.*/Render/Settings, /Render/Other"
    ):
        resolve(stage)
    with pytest.raises(SettingsError, match=r"no prim at --settings '/Nope'"):
        resolve(stage, settings="/Nope")
    with pytest.raises(
        SettingsError, match=r"/Cam is a 'Camera', not a RenderSettings"
    ):
        resolve(stage, settings="/Cam")


def test_product_selection_and_overrides(tmp_path: Path) -> None:
    stage = make_stage(tmp_path)
    p2 = UsdRender.Product.Define(stage, "/Render/Extra")
    p2.CreateProductNameAttr("extra.####.exr")
    p2.CreateOrderedVarsRel().SetTargets([Sdf.Path("/Render/Vars/Ci")])
    p2.CreateResolutionAttr(Gf.Vec2i(32, 16))
    UsdGeom.Camera.Define(stage, "/Cam2")
    p2.CreateCameraRel().SetTargets([Sdf.Path("/Cam2")])
    UsdRender.Settings(
        stage.GetPrimAtPath("/Render/Settings")
    ).GetProductsRel().AddTarget("/Render/Extra")
    info = resolve(stage, products=["Extra"], frames=[5, 6])
    (prod,) = info.products
    assert prod.path == "/Render/Extra"
    assert prod.resolution == (32, 16)
    assert prod.camera_path == "/Cam2"
    assert info.frames == [5, 6]
    with pytest.raises(
        SettingsError,
        match=r"no product named 'Nope' \(products: /Render/Beauty, /Render/Extra\)",
    ):
        resolve(stage, products=["Nope"])


def test_missing_var_and_product_targets(tmp_path: Path) -> None:
    stage = make_stage(tmp_path)
    UsdRender.Product(
        stage.GetPrimAtPath("/Render/Beauty")
    ).GetOrderedVarsRel().AddTarget("/Render/Vars/gone")
    with pytest.raises(
        VarError,
        match=r"/Render/Beauty: RenderVar /Render/Vars/gone \(orderedVars\) does not exist",
    ):
        resolve(stage)
    stage = make_stage(tmp_path, name="t.usda")
    UsdRender.Settings(
        stage.GetPrimAtPath("/Render/Settings")
    ).GetProductsRel().AddTarget("/Render/Missing")
    with pytest.raises(SettingsError, match=r"product /Render/Missing does not exist"):
        resolve(stage)


def test_camera_errors(tmp_path: Path) -> None:
    stage = make_stage(tmp_path)
    UsdRender.Settings(
        stage.GetPrimAtPath("/Render/Settings")
    ).GetCameraRel().SetTargets(["/NoCam"])
    with pytest.raises(
        CameraError, match=r"/Render/Beauty: camera /NoCam does not exist"
    ):
        resolve(stage).products[0].camera_prim()
    UsdRender.Settings(
        stage.GetPrimAtPath("/Render/Settings")
    ).GetCameraRel().SetTargets(["/Render/Vars"])
    with pytest.raises(
        CameraError,
        match=r"camera /Render/Vars is a typeless prim, not a UsdGeom.Camera",
    ):
        resolve(stage).products[0].camera_prim()


def test_var_roles(tmp_path: Path) -> None:
    stage = make_stage(tmp_path)
    prod = resolve(stage).products[0]
    roles = map_vars(prod)
    assert {r: v.name for r, v in roles.items()} == {
        "color": "Ci",
        "coverage": "a",
        "depth": "z",
        "motion": "mv",
    }
    # User mapping wins over names; "ignore" drops a var.
    roles = map_vars(prod, {"z": "ignore", "a": "insert_mask"})
    assert {r: v.name for r, v in roles.items()} == {
        "color": "Ci",
        "insert_mask": "a",
        "motion": "mv",
    }
    # harmonizer:role on the var.
    stage.GetPrimAtPath("/Render/Vars/a").CreateAttribute(
        "harmonizer:role", Sdf.ValueTypeNames.String
    ).Set("mask")
    assert (
        role_of(VarInfo.from_prim(stage.GetPrimAtPath("/Render/Vars/a")))
        == "insert_mask"
    )
    # The inserted objects' ids: by role name or by the names pipelines give them.
    assert map_vars(prod, {"a": "insertId"})["insert_id"].name == "a"
    plain = VarInfo.from_prim(stage.GetPrimAtPath("/Render/Vars/z"))
    for name in ("primId", "instanceId", "objectId", "insert_id", "mask.id"):
        var = dataclasses.replace(plain, source_name=name, name=name)
        assert role_of(var) == "insert_id", name
    with pytest.raises(VarError, match=r"both map to depth"):
        map_vars(prod, {"a": "depth"})
    with pytest.raises(VarError, match=r"--map a: unknown role 'specular'"):
        map_vars(prod, {"a": "specular"})
    with pytest.raises(
        VarError, match=r"no color RenderVar among orderedVars \[Ci \(sourceName 'Ci'\)"
    ):
        map_vars(prod, {"Ci": "ignore"})


def test_find_channels(tmp_path: Path) -> None:
    stage = make_stage(tmp_path)
    prod = resolve(stage).products[0]
    v = {x.name: x for x in prod.vars}
    names = [
        "A",
        "B",
        "G",
        "R",
        "z",
        "mv.x",
        "mv.y",
        "N.X",
        "N.Y",
        "N.Z",
    ]  # OIIO order is not USD order
    b = find_channels("color", v["Ci"], names, "here")
    assert b.channels == ["R", "G", "B"] and b.alpha == "A"
    assert find_channels("depth", v["z"], names, "here").channels == ["z"]
    assert find_channels("motion", v["mv"], names, "here").channels == ["mv.x", "mv.y"]
    assert find_channels("coverage", v["a"], names, "here").channels == ["A"]
    # color3f var whose file also has the alpha beside it.
    b = find_channels("color", v["Ci"], ["Ci.b", "Ci.a", "Ci.g", "Ci.r"], "here")
    assert b.channels == ["Ci.r", "Ci.g", "Ci.b"] and b.alpha == "Ci.a"
    b = find_channels("color", v["Ci"], ["Ci.R", "Ci.G", "Ci.B"], "here")
    assert b.alpha is None
    with pytest.raises(
        VarError,
        match=r"here: RenderVar /Render/Vars/mv \(motion, dataType float2\): no matching channels.*channels present: \['A', 'B'",
    ):
        find_channels("motion", v["mv"], ["R", "G", "B", "A"], "here")
    stage.GetPrimAtPath("/Render/Vars/mv").CreateAttribute(
        "harmonizer:channels", Sdf.ValueTypeNames.StringArray
    ).Set(["vel.u", "vel.v"])
    mv = VarInfo.from_prim(stage.GetPrimAtPath("/Render/Vars/mv"))
    assert find_channels("motion", mv, ["vel.v", "vel.u"], "here").channels == [
        "vel.u",
        "vel.v",
    ]
    with pytest.raises(
        VarError,
        match=r"harmonizer:channels \['vel.u', 'vel.v'\] not in the file \(missing \['vel.v'\]",
    ):
        find_channels("motion", mv, ["vel.u"], "here")


def test_declared_color_spaces(tmp_path: Path) -> None:
    stage = make_stage(tmp_path)
    assert resolve(stage).products[0].color_space is None
    # UsdColorSpaceAPI on an ancestor is inherited by the product and its vars.
    Usd.ColorSpaceAPI.Apply(stage.GetPrimAtPath("/Render")).CreateColorSpaceNameAttr(
        "lin_ap1_scene"
    )
    prod = resolve(stage).products[0]
    inherited = ("lin_ap1_scene", "/Render.colorSpace:name")
    assert prod.color_space is None and prod.inherited_color_space == inherited
    assert prod.vars[0].inherited_color_space == inherited
    # The prim's own declaration wins; harmonizer:colorSpace first.
    ci = stage.GetPrimAtPath("/Render/Vars/Ci")
    ci.CreateAttribute("colorSpace", Sdf.ValueTypeNames.String, custom=True).Set(
        "ACEScg"
    )
    assert resolve(stage).products[0].vars[0].color_space == (
        "ACEScg",
        "/Render/Vars/Ci.colorSpace",
    )
    ci.CreateAttribute(
        "harmonizer:colorSpace", Sdf.ValueTypeNames.String, custom=True
    ).Set("lin_rec2020_scene")
    assert resolve(stage).products[0].vars[0].color_space[0] == "lin_rec2020_scene"
    # renderingColorSpace on the settings is read too.
    UsdRender.Settings(
        stage.GetPrimAtPath("/Render/Settings")
    ).CreateRenderingColorSpaceAttr("lin_rec709_scene")
    assert resolve(stage).rendering_color_space == "lin_rec709_scene"
