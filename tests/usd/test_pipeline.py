"""``usd-harmonize`` on the Cycles-rendered shot: every output frame,
channel and attribute, the new layer, the untouched original, the exact
bypass color round trip (Linear Rec.709 and ACEScg products) and the errors."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import fixtures
import handmade
import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Gf, Sdf, Usd, UsdRender
from usd_harmonizer import resolve
from usd_harmonizer.cli import main
from usd_harmonizer.exrio import read_exr

CLI = Path(sys.executable).with_name("usd-harmonize")
HARMONIZER_ATTRS = (
    "harmonizer:version",
    "harmonizer:backend",
    "harmonizer:model",
    "harmonizer:frame",
    "harmonizer:reset",
)


def digest(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(CLI), *args], capture_output=True, text=True, timeout=600, check=False
    )


def run_classical_beauty(shot: Path, out_dir: Path, layer: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    """The CLI's classical backend on the ``beauty`` product, its outputs in
    ``out_dir`` and its layer at ``layer``."""
    return run_cli(str(shot), "--backend", "classical", "--product", "beauty", "--out-dir", str(out_dir), "--layer", str(layer), *extra)


def spec_of(path: Path) -> oiio.ImageSpec:
    inp = oiio.ImageInput.open(str(path))
    spec = oiio.ImageSpec(inp.spec())
    inp.close()
    return spec


def check_products(
    shot: Path, layer: Path, backend: str, exact: bool
) -> dict[str, list[Path]]:
    """Checks every output frame of both products; returns the output files."""
    stage = Usd.Stage.Open(str(shot))
    info = resolve(stage)
    outputs: dict[str, list[Path]] = {}
    for prod in info.products:
        outs = []
        for i, f in enumerate(fixtures.FRAMES):
            src = prod.file_for(f)
            out = src.parent / "harmonized" / src.name
            assert out.is_file(), out
            outs.append(out)
            a, b = read_exr(src, "src"), read_exr(out, "out")
            # Every channel kept, same pixel types, same size.
            assert sorted(a.channel_names) == sorted(b.channel_names)
            sa, sb = spec_of(src), spec_of(out)
            assert (
                (sa.width, sa.height)
                == (sb.width, sb.height)
                == (fixtures.W, fixtures.H)
            )
            assert [str(sa.channelformat(k)) for k in range(sa.nchannels)] == [
                str(sb.channelformat(k)) for k in range(sb.nchannels)
            ]
            # Every attribute kept, harmonizer:* added.
            attrs_a, attrs_b = a.attributes(), b.attributes()
            for k in ("renderer", "capDate", "colorInteropID"):
                assert attrs_a.get(k) == attrs_b.get(k), k
            for k in HARMONIZER_ATTRS:
                assert k in attrs_b, k
            assert attrs_b["harmonizer:frame"] == f
            assert attrs_b["harmonizer:backend"] == backend
            assert attrs_b["harmonizer:reset"] == ("first_frame" if i == 0 else "none")
            assert attrs_b["harmonizer:version"]
            assert attrs_b["harmonizer:product"] == prod.path
            # Non-color channels untouched, bit for bit.
            color = {"R", "G", "B", "A"}
            for c in a.channel_names:
                if c not in color:
                    assert np.array_equal(a.channel(c), b.channel(c)), (out, c)
            rgb_a, rgb_b = a.stack(["R", "G", "B"]), b.stack(["R", "G", "B"])
            assert np.isfinite(rgb_b).all()
            if exact:
                assert np.abs(rgb_a - rgb_b).max() < 1e-4, (
                    out,
                    np.abs(rgb_a - rgb_b).max(),
                )
                assert np.abs(a.channel("A") - b.channel("A")).max() < 1e-6
        outputs[prod.path] = outs
    return outputs


def check_layer(
    shot: Path, layer: Path, outputs: dict[str, list[Path]], backend: str
) -> None:
    text = layer.read_text()
    assert "@shot.usda@" in text  # sublayers the original, relative
    stage = Usd.Stage.Open(str(layer))
    assert stage.GetRootLayer().subLayerPaths[0] == "shot.usda"
    info = resolve(stage, settings="/Render/Settings_harmonized")
    assert [p.path for p in info.products] == [
        "/Render/Products/beauty_harmonized",
        "/Render/Products/nomv_harmonized",
    ]
    for prod, (src_path, outs) in zip(info.products, outputs.items()):
        prim = stage.GetPrimAtPath(prod.path)
        assert prim.GetRelationship("harmonizer:sourceProduct").GetTargets() == [
            Sdf.Path(src_path)
        ]
        assert prim.GetAttribute("harmonizer:backend").Get() == backend
        assert list(prim.GetAttribute("harmonizer:frames").Get()) == fixtures.FRAMES
        assert list(prim.GetAttribute("harmonizer:resetFrames").Get()) == [
            fixtures.FRAMES[0]
        ]
        src_prod = UsdRender.Product(stage.GetPrimAtPath(src_path))
        assert [
            str(t) for t in UsdRender.Product(prim).GetOrderedVarsRel().GetTargets()
        ] == [str(t) for t in src_prod.GetOrderedVarsRel().GetTargets()]
        assert prod.camera_path == "/World/Cam"
        for f, out in zip(fixtures.FRAMES, outs):
            assert prod.file_for(f).resolve() == out.resolve()


def test_cli_bypass_round_trip(shot: Path) -> None:
    """Bypass: Linear Rec.709 (beauty) and ACEScg (nomv, half) round trips
    exact within 1e-4; every frame, channel and attribute; the new layer; the
    original layer untouched."""
    before = digest(shot)
    inputs_before = {p: digest(p) for p in shot.parent.glob("render/**/*.exr")}
    r = run_cli(str(shot), "--backend", "bypass")
    assert r.returncode == 0, r.stderr
    assert (
        "/Render/Products/beauty: 6 frames 1001-1006, backend bypass, color space Linear Rec.709 (sRGB)"
        in r.stdout
    )
    assert "inputs color+depth+motion+normal+coverage+insert_mask+camera" in r.stdout
    assert (
        "/Render/Products/nomv: 6 frames 1001-1006, backend bypass, color space ACEScg"
        in r.stdout
    )
    assert "inputs color+depth+normal+coverage+camera" in r.stdout
    layer = shot.with_name("shot.harmonized.usda")
    assert f"layer: {layer}" in r.stdout
    assert digest(shot) == before
    assert {p: digest(p) for p in inputs_before} == inputs_before
    outputs = check_products(shot, layer, "bypass", exact=True)
    check_layer(shot, layer, outputs, "bypass")


def test_cli_classical_enhances_with_history(shot: Path, tmp_path: Path) -> None:
    """The classical backend runs with temporal state: outputs differ from the
    input, are finite, and frames after the first use history. The shot is a
    clean render with a correctly lit insert, which the defaults leave as it
    is; ``stabilize_all`` blends every pixel with the reprojected history."""
    out_dir = tmp_path / "enh"
    layer = tmp_path / "layers" / "enh.usda"
    r = run_classical_beauty(shot, out_dir, layer, "--param", "stabilize_all=true")
    assert r.returncode == 0, r.stderr
    files = sorted((out_dir / "beauty").glob("beauty.*.exr"))
    assert [p.name for p in files] == [f"beauty.{f}.exr" for f in fixtures.FRAMES]
    diffs = []
    for f, p in zip(fixtures.FRAMES, files):
        a = read_exr(shot.parent / f"render/beauty.{f}.exr", "src")
        b = read_exr(p, "out")
        rgb_b = b.stack(["R", "G", "B"])
        assert np.isfinite(rgb_b).all()
        diffs.append(float(np.abs(rgb_b - a.stack(["R", "G", "B"])).mean()))
        assert b.attributes()["harmonizer:backend"] == "classical"
    assert max(diffs[1:]) > 1e-4, diffs
    stage = Usd.Stage.Open(str(layer))
    prod = resolve(stage, settings="/Render/Settings_harmonized").products[0]
    assert (
        prod.file_for(1003).resolve() == (out_dir / "beauty/beauty.1003.exr").resolve()
    )
    assert stage.GetRootLayer().subLayerPaths[0] == os.path.relpath(shot, layer.parent)


def test_insert_ids_are_passed_through(shot: Path, tmp_path: Path) -> None:
    """A var with role ``insert_id`` (here the Object Index, mapped by name as
    ``insertId``) reaches the library beside the insert mask: the run names
    the input and its output differs from the run without ids only on the
    inserts (the rest of the frame comes out the same)."""
    outs = {}
    for name, extra in (("ids", ["--map", "objectIndex=insertId"]), ("plain", [])):
        out_dir = tmp_path / name
        r = run_classical_beauty(shot, out_dir, tmp_path / f"{name}.usda", *extra)
        assert r.returncode == 0, r.stderr
        want = "insert_mask+insert_id+camera" if extra else "insert_mask+camera"
        assert f"inputs color+depth+motion+normal+coverage+{want}" in r.stdout, r.stdout
        outs[name] = read_exr(out_dir / "beauty/beauty.1001.exr", name).stack(["R", "G", "B"])
    src = read_exr(shot.parent / "render/beauty.1001.exr", "src")
    far = src.channel("mask.insert") == 0.0
    np.testing.assert_allclose(outs["ids"][far], outs["plain"][far], atol=1e-6)


def test_frames_option_and_in_place(shot: Path) -> None:
    assert (
        main(
            [
                str(shot),
                "--backend",
                "bypass",
                "--frames",
                "1002-1003",
                "--product",
                "nomv",
                "--in-place",
                "--quiet",
            ]
        )
        == 0
    )
    stage = Usd.Stage.Open(str(shot))
    prim = stage.GetPrimAtPath("/Render/Products/nomv_harmonized")
    assert prim.IsValid() and list(prim.GetAttribute("harmonizer:frames").Get()) == [
        1002,
        1003,
    ]
    assert not stage.GetPrimAtPath("/Render/Products/beauty_harmonized").IsValid()
    out = sorted(p.name for p in (shot.parent / "render/nomv/harmonized").glob("*.exr"))
    assert out == ["shot_nomv_f1002.exr", "shot_nomv_f1003.exr"]


def test_missing_product_file(shot: Path) -> None:
    missing = shot.parent / "render/beauty.1004.exr"
    missing.unlink()
    r = run_cli(str(shot), "--backend", "bypass")
    assert r.returncode == 1
    assert (
        f"render product /Render/Products/beauty frame 1004 ({missing}): file {missing} does not exist"
        in r.stderr
    )
    assert "Traceback" not in r.stderr


def test_missing_var_channels(shot: Path) -> None:
    stage = Usd.Stage.Open(str(shot))
    stage.GetPrimAtPath("/Render/Vars/insert").GetAttribute(
        "driver:parameters:aov:name"
    ).Set("mask.hero")
    stage.Save()
    r = run_cli(str(shot), "--backend", "bypass", "--no-layer")
    assert r.returncode == 1
    assert "render product /Render/Products/beauty frame 1001" in r.stderr
    assert (
        "RenderVar /Render/Vars/insert (insert_mask, dataType float): no matching channels (tried mask.hero;"
        in r.stderr
    )
    assert "channels present: ['A', 'B', 'G', 'N.X'" in r.stderr


def test_missing_var_prim(shot: Path) -> None:
    stage = Usd.Stage.Open(str(shot))
    UsdRender.Product(
        stage.GetPrimAtPath("/Render/Products/beauty")
    ).GetOrderedVarsRel().AddTarget("/Render/Vars/albedo")
    stage.Save()
    r = run_cli(str(shot), "--backend", "bypass")
    assert r.returncode == 1
    assert (
        "render product /Render/Products/beauty: RenderVar /Render/Vars/albedo (orderedVars) does not exist on the stage"
        in r.stderr
    )


def test_unknown_color_space(shot: Path) -> None:
    stage = Usd.Stage.Open(str(shot))
    stage.GetPrimAtPath("/Render/Vars/color").CreateAttribute(
        "colorSpace", Sdf.ValueTypeNames.String, custom=True
    ).Set("Kodak 5219")
    stage.Save()
    r = run_cli(str(shot), "--backend", "bypass", "--product", "beauty")
    assert r.returncode == 1
    assert (
        "color space 'Kodak 5219' (declared by /Render/Vars/color.colorSpace) is unknown to the OCIO config ocio://default"
        in r.stderr
    )


def test_aspect_mismatch(shot: Path) -> None:
    stage = Usd.Stage.Open(str(shot))
    UsdRender.Settings(stage.GetPrimAtPath("/Render/Settings")).GetResolutionAttr().Set(
        Gf.Vec2i(100, 100)
    )
    stage.Save()
    r = run_cli(str(shot), "--backend", "bypass", "--product", "beauty")
    assert r.returncode == 1
    assert (
        "frame 1001" in r.stderr
        and "the file is 128x72 but the product's resolution is 100x100" in r.stderr
    )


def test_output_never_overwrites_input(shot: Path) -> None:
    """--out-dir render writes nomv to render/nomv/, where its own files are:
    refused before any frame is written."""
    src = shot.parent / "render/nomv/shot_nomv_f1001.exr"
    before = digest(src)
    r = run_cli(
        str(shot),
        "--backend",
        "bypass",
        "--out-dir",
        str(shot.parent / "render"),
    )
    assert r.returncode == 1
    assert (
        f"render product /Render/Products/nomv frame 1001 ({src}): the output would "
        "overwrite the input; choose another --out-dir" in r.stderr
    )
    assert digest(src) == before
    assert not (shot.parent / "render/beauty").exists()


def test_bad_backend_parameter(shot: Path) -> None:
    r = run_cli(str(shot), "--backend", "bypass", "--param", "strength=7")
    assert r.returncode == 1
    assert "strength" in r.stderr and "7" in r.stderr


def test_multipart_blender_product(rendered: Path, tmp_path: Path) -> None:
    """A product whose files are Blender's own multi-part EXRs: channels found
    through the AOV names, every part, channel and header kept, exact bypass."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "mp.usda"))
    stage.GetRootLayer().subLayerPaths.append(str(rendered / "scene.usda"))
    stage.SetStartTimeCode(fixtures.FRAMES[0])
    stage.SetEndTimeCode(fixtures.FRAMES[-1])
    vars_ = []
    for name, src, dtype, aov in (
        ("combined", "Combined", "color4f", "ViewLayer.Combined"),
        ("depth", "depth", "float", "ViewLayer.Depth"),
        ("vector", "Vector", "float4", "ViewLayer.Vector"),
        ("normal", "Normal", "normal3f", "ViewLayer.Normal"),
        ("index", "Object Index", "float", "ViewLayer.Object Index"),
    ):
        v = UsdRender.Var.Define(stage, f"/Render/Vars/{name}")
        v.CreateSourceNameAttr(src)
        v.CreateDataTypeAttr(dtype)
        p = v.GetPrim()
        p.CreateAttribute(
            "driver:parameters:aov:name", Sdf.ValueTypeNames.String, custom=True
        ).Set(aov)
        vars_.append(v.GetPath())
    stage.GetPrimAtPath("/Render/Vars/vector").CreateAttribute(
        "harmonizer:motionVectorScale", Sdf.ValueTypeNames.Float2, custom=True
    ).Set(Gf.Vec2f(1, -1))
    stage.GetPrimAtPath("/Render/Vars/index").CreateAttribute(
        "harmonizer:role", Sdf.ValueTypeNames.String, custom=True
    ).Set("insert_mask")
    prod = UsdRender.Product.Define(stage, "/Render/Products/blender")
    prod.CreateProductNameAttr("blender/blender.$F4.exr")
    prod.CreateOrderedVarsRel().SetTargets(vars_)
    prod.CreateCameraRel().SetTargets([Sdf.Path("/World/Cam")])
    prod.CreateResolutionAttr(Gf.Vec2i(fixtures.W, fixtures.H))
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateProductsRel().SetTargets([prod.GetPath()])
    stage.GetRootLayer().Save()
    out_dir = tmp_path / "out"
    before = digest(rendered / "blender/blender.1001.exr")
    r = run_cli(
        str(tmp_path / "mp.usda"),
        "--backend",
        "bypass",
        "--base-dir",
        str(rendered),
        "--out-dir",
        str(out_dir),
        "--settings",
        "/Render/Settings",
    )
    assert r.returncode == 0, r.stderr
    assert "inputs color+depth+motion+normal+coverage+insert_mask+camera" in r.stdout
    assert digest(rendered / "blender/blender.1001.exr") == before
    for f in fixtures.FRAMES:
        a = read_exr(rendered / f"blender/blender.{f}.exr", "src")
        b = read_exr(out_dir / f"blender/blender.{f}.exr", "out")
        assert [p.names for p in a.parts] == [p.names for p in b.parts]
        assert [p.spec.get_string_attribute("name") for p in b.parts] == [
            "ViewLayer.Combined",
            "ViewLayer.Depth",
            "ViewLayer.Normal",
            "ViewLayer.Vector",
            "ViewLayer.Object Index",
            "ViewLayer.Denoising Normal",
            "ViewLayer.Denoising Albedo",
            "ViewLayer.Denoising Depth",
        ]
        for k in ("Software", "Camera", "Frame", "colorInteropID"):
            assert a.attributes()[k] == b.attributes()[k], k
        assert b.attributes()["harmonizer:frame"] == f
        for pa, pb in zip(a.parts, b.parts, strict=True):
            assert np.abs(pa.pixels - pb.pixels).max() < 1e-4


def test_missing_camera(shot: Path) -> None:
    stage = Usd.Stage.Open(str(shot))
    UsdRender.Settings(
        stage.GetPrimAtPath("/Render/Settings")
    ).GetCameraRel().SetTargets([Sdf.Path("/World/NoCam")])
    stage.Save()
    r = subprocess.run(
        [sys.executable, "-m", "usd_harmonizer", str(shot), "--backend", "bypass"],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert r.returncode == 1
    assert (
        "usd-harmonize: error: render product /Render/Products/beauty: "
        "camera /World/NoCam does not exist on the stage"
    ) in r.stderr


MODELS = fixtures.REPO / "core/tests/fixtures/models"


def test_neural_backend_with_a_model(shot: Path, tmp_path: Path) -> None:
    """The neural backend through real ONNX Runtime with the committed 3x3 box
    model: it runs on every frame (``neural_clean_frames``: the shot has no
    holes), the model is recorded, the output differs."""
    r = run_cli(
        str(shot),
        "--backend",
        "neural",
        "--model",
        str(MODELS / "box3.onnx"),
        "--param",
        "neural_clean_frames=true",
        "--product",
        "beauty",
        "--out-dir",
        str(tmp_path / "nn"),
    )
    assert r.returncode == 0, r.stderr
    assert "backend neural" in r.stdout
    for f in fixtures.FRAMES:
        a = read_exr(shot.parent / f"render/beauty.{f}.exr", "src")
        b = read_exr(tmp_path / f"nn/beauty/beauty.{f}.exr", "out")
        assert b.attributes()["harmonizer:model"] == "box3"
        assert b.attributes()["harmonizer:backend"] == "neural"
        rgb_a, rgb_b = a.stack(["R", "G", "B"]), b.stack(["R", "G", "B"])
        assert np.isfinite(rgb_b).all()
        assert np.abs(rgb_a - rgb_b).mean() > 1e-4


def test_missing_onnx_runtime_is_named(shot: Path, tmp_path: Path) -> None:
    r = run_cli(
        str(shot),
        "--backend",
        "neural",
        "--model",
        str(MODELS / "box3.onnx"),
        "--ort-library",
        str(tmp_path / "libonnxruntime.so.0"),
    )
    assert r.returncode == 1
    assert "libonnxruntime.so.0" in r.stderr and "Traceback" not in r.stderr


def test_user_map_and_params(shot: Path, tmp_path: Path) -> None:
    r = run_cli(
        str(shot),
        "--backend",
        "bypass",
        "--product",
        "beauty",
        "--frames",
        "1001-1002",
        "--map",
        "insert=ignore",
        "--map",
        "N=ignore",
        "--param",
        "context_frames=2",
        "--no-layer",
        "--out-dir",
        str(tmp_path / "m"),
    )
    assert r.returncode == 0, r.stderr
    assert "inputs color+depth+motion+coverage+camera," in r.stdout
    assert sorted(p.name for p in (tmp_path / "m/beauty").iterdir()) == [
        "beauty.1001.exr",
        "beauty.1002.exr",
    ]
    assert not shot.with_name("shot.harmonized.usda").exists()
    r = run_cli(str(shot), "--backend", "bypass", "--param", "bogus=1")
    assert r.returncode == 1
    assert 'unknown parameter "bogus"' in r.stderr
    r = run_cli(str(shot), "--backend", "bypass", "--map", "insert=specular")
    assert r.returncode == 1
    assert "--map insert: unknown role 'specular'" in r.stderr


def test_progress_bar(capsys: pytest.CaptureFixture[str], rendered: Path) -> None:
    from usd_harmonizer.cli import _Progress

    prod = resolve(Usd.Stage.Open(str(rendered / "shot.usda"))).products[0]
    bar = _Progress(True)
    bar(3, 12, prod, 1004)
    bar(12, 12, prod, 1006)
    err = capsys.readouterr().err
    assert "\r[#######.......................] 3/12 beauty frame 1004" in err
    assert "\r[##############################] 12/12 beauty frame 1006" in err
    assert err.endswith("\n")
    _Progress(False)(1, 2, prod, 1001)
    assert capsys.readouterr().err == ""


def test_color_space_precedence_end_to_end(shot: Path) -> None:
    """An ancestor's UsdColorSpaceAPI applies to products without their own
    declaration (over the file's colorInteropID); a product's own wins."""
    stage = Usd.Stage.Open(str(shot))
    Usd.ColorSpaceAPI.Apply(stage.GetPrimAtPath("/Render")).CreateColorSpaceNameAttr(
        "lin_rec2020_scene"
    )
    stage.Save()
    r = run_cli(str(shot), "--backend", "bypass")
    assert r.returncode == 0, r.stderr
    assert (
        "/Render/Products/beauty: 6 frames 1001-1006, backend bypass, color space Linear Rec.2020,"
        in r.stdout
    )
    assert (
        "/Render/Products/nomv: 6 frames 1001-1006, backend bypass, color space ACEScg,"
        in r.stdout
    )
    b = read_exr(shot.parent / "render/harmonized/beauty.1001.exr", "out")
    assert b.attributes()["harmonizer:colorSpace"] == "Linear Rec.2020"
    # The new products declare the same spaces with UsdColorSpaceAPI (issue 9).
    stage = Usd.Stage.Open(str(shot.with_name("shot.harmonized.usda")))
    for name, token in (("beauty", "lin_rec2020_scene"), ("nomv", "lin_ap1_scene")):
        src = stage.GetPrimAtPath(f"/Render/Products/{name}")
        new = stage.GetPrimAtPath(f"/Render/Products/{name}_harmonized")
        assert color_space_name(src) == token
        assert new.HasAPI(Usd.ColorSpaceAPI)
        assert color_space_name(new) == token


def color_space_name(prim: Usd.Prim) -> str:
    """What UsdColorSpaceAPI says the prim's color space is ('' when none)."""
    return Usd.ColorSpaceAPI.ComputeColorSpaceName(prim, None)


def test_new_products_declare_their_color_space(shot: Path, tmp_path: Path) -> None:
    """Issue 9: each new product carries its color space with UsdColorSpaceAPI
    (not only harmonizer:colorSpace): the source product's token (nomv:
    lin_ap1_scene), else the token of the space its pixels were read in
    (beauty: the file's colorInteropID; an OCIO name mapped to its token)."""
    r = run_cli(str(shot), "--backend", "bypass", "--frames", "1001")
    assert r.returncode == 0, r.stderr
    stage = Usd.Stage.Open(str(shot.with_name("shot.harmonized.usda")))
    nomv = stage.GetPrimAtPath("/Render/Products/nomv")
    new_nomv = stage.GetPrimAtPath("/Render/Products/nomv_harmonized")
    assert color_space_name(nomv) == "lin_ap1_scene"
    assert new_nomv.HasAPI(Usd.ColorSpaceAPI)
    assert color_space_name(new_nomv) == color_space_name(nomv)
    new_beauty = stage.GetPrimAtPath("/Render/Products/beauty_harmonized")
    assert color_space_name(new_beauty) == "lin_rec709_scene"
    assert new_beauty.GetAttribute("harmonizer:colorSpace").Get() == (
        "Linear Rec.709 (sRGB)"
    )

    # An OCIO name (harmonizer:colorSpace) becomes its USD token.
    src = Usd.Stage.Open(str(shot))
    src.GetPrimAtPath("/Render/Products/beauty").CreateAttribute(
        "harmonizer:colorSpace", Sdf.ValueTypeNames.String, custom=True
    ).Set("Linear Rec.2020")
    src.Save()
    layer = tmp_path / "cs.usda"
    r = run_cli(
        str(shot),
        *("--backend", "bypass", "--frames", "1001", "--product", "beauty"),
        *("--layer", str(layer)),
    )
    assert r.returncode == 0, r.stderr
    stage = Usd.Stage.Open(str(layer))
    new_beauty = stage.GetPrimAtPath("/Render/Products/beauty_harmonized")
    assert color_space_name(new_beauty) == "lin_rec2020_scene"


def stereo(root: Path, names: tuple[str, str], patterns: tuple[str, str]) -> tuple[
    Path, dict[str, dict[int, np.ndarray]]
]:
    """A hand-made stage with two Linear Rec.709 products (distinct pixels)
    over frames 1-2."""
    rng = np.random.default_rng(10)
    rgb = {
        n: {f: rng.uniform(0, 2, (handmade.H, handmade.W, 3)) for f in (1, 2)}
        for n in names
    }
    stage = handmade.author(
        root,
        [
            handmade.Product(f"/Render/Products/{n}", p, rgb[n], "lin_rec709_scene")
            for n, p in zip(names, patterns)
        ],
        [1, 2],
    )
    return stage, rgb


def test_out_dir_gives_each_product_its_folder(tmp_path: Path) -> None:
    """Issue 10: stereo products render/left/frame.####.exr and
    render/right/frame.####.exr with --out-dir DIR go to DIR/left/ and
    DIR/right/ (each product's prim name), never to one DIR/frame.####.exr;
    each new product points at its own files."""
    stage, rgb = stereo(
        tmp_path / "st",
        ("left", "right"),
        ("render/left/frame.####.exr", "render/right/frame.####.exr"),
    )
    out_dir = tmp_path / "out"
    r = run_cli(str(stage), "--backend", "bypass", "--out-dir", str(out_dir))
    assert r.returncode == 0, r.stderr
    assert sorted(str(p.relative_to(out_dir)) for p in out_dir.rglob("*.exr")) == [
        "left/frame.0001.exr",
        "left/frame.0002.exr",
        "right/frame.0001.exr",
        "right/frame.0002.exr",
    ]
    layer = Usd.Stage.Open(str(stage.with_name("stage.harmonized.usda")))
    new = resolve(layer, settings="/Render/Settings_harmonized")
    for prod in new.products:
        eye = prod.name.removesuffix("_harmonized")
        for f in (1, 2):
            out = out_dir / eye / f"frame.{f:04d}.exr"
            assert prod.file_for(f).resolve() == out.resolve()
            assert np.abs(handmade.read_rgb(out) - rgb[eye][f]).max() < 1e-5


def test_products_never_share_an_output(tmp_path: Path) -> None:
    """Issue 10: a run that would write two frames to one file, or over any
    product's input, stops before writing anything."""
    # Two products reading the same files: both would write render/harmonized/.
    stage, _ = stereo(
        tmp_path / "same",
        ("a", "b"),
        ("render/frame.####.exr", "render/frame.####.exr"),
    )
    r = run_cli(str(stage), "--backend", "bypass")
    assert r.returncode == 1
    out = stage.parent / "render/harmonized/frame.0001.exr"
    assert (
        f"render products /Render/Products/a frame 1 and /Render/Products/b frame 1 "
        f"would both be written to {out}" in r.stderr
    )
    assert "use --out-dir" in r.stderr
    assert not (stage.parent / "render/harmonized").exists()

    # --out-dir DIR writes a to DIR/a/, where b's input is.
    stage, _ = stereo(
        tmp_path / "over",
        ("a", "b"),
        ("render/frame.####.exr", "out/a/frame.####.exr"),
    )
    before = digest(stage.parent / "out/a/frame.0001.exr")
    r = run_cli(
        str(stage), "--backend", "bypass", "--out-dir", str(stage.parent / "out")
    )
    assert r.returncode == 1
    out = stage.parent / "out/a/frame.0001.exr"
    assert (
        f"render product /Render/Products/a frame 1: the output {out} would overwrite "
        f"the input of render product /Render/Products/b frame 1" in r.stderr
    )
    assert digest(out) == before
    assert not (stage.parent / "out/b").exists()

    # One product whose frames differ only in their folders.
    stage, _ = stereo(
        tmp_path / "dirs", ("a", "b"), ("render/<F4>/a.exr", "render/<F4>/b.exr")
    )
    r = run_cli(str(stage), "--backend", "bypass", "--out-dir", str(tmp_path / "o"))
    assert r.returncode == 1
    assert (
        f"render products /Render/Products/a frame 1 and /Render/Products/a frame 2 "
        f"would both be written to {tmp_path / 'o/a/a.exr'}" in r.stderr
    )
    assert not (tmp_path / "o").exists()
