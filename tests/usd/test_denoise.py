"""The denoise stage through the USD hook (issue 20): the albedo and denoising
normal RenderVars, the stage's ``harmonizer:samples`` / ``harmonizer:denoise``
settings and the CLI's flags, with the real Open Image Denoise (run.sh points
``HARMONIZER_OIDN_LIB`` at the pyoidn wheel).

The product is the fixture shot's 4-sample Cycles render with its Denoising
Data passes written as AOVs under other renderers' names (``DiffuseAlbedo``,
``denoising_normal``); the 64-sample render is the reference the noise is
measured against.
"""

from __future__ import annotations

from pathlib import Path

import fixtures
import numpy as np
import pytest
from pxr import Gf, Sdf, Usd, UsdRender
from usd_harmonizer import PostFrameHook, SettingsError
from usd_harmonizer.cli import main
from usd_harmonizer.errors import VarError
from usd_harmonizer.exrio import read_exr
from usd_harmonizer.settings import VarInfo
from usd_harmonizer.varmap import role_of

#: Only the denoise stage and the temporal blend change the image.
PARAMS = {"harmonize": False, "contact_shadows": False}
#: The denoised output must be this much closer to the reference than the input (dB).
MIN_GAIN_DB = 3.0


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR of two linear images after a 1/2.2 display curve (clipped to [0, 1])."""
    da = np.clip(a, 0.0, 1.0) ** (1 / 2.2)
    db = np.clip(b, 0.0, 1.0) ** (1 / 2.2)
    return float(10.0 * np.log10(1.0 / np.mean((da - db) ** 2)))


def noisy_shot(
    rendered: Path,
    root: Path,
    *,
    albedo: str = "RGB",
    settings_attrs: dict[str, object] | None = None,
) -> Path:
    """``root/denoise.usda``: product ``noisy`` (vars color, depth, motion,
    DiffuseAlbedo, denoising_normal), its files from the fixture's Blender
    render; the albedo written with the components in ``albedo`` only."""
    stage = Usd.Stage.CreateNew(str(root / "denoise.usda"))
    stage.SetStartTimeCode(fixtures.FRAMES[0])
    stage.SetEndTimeCode(fixtures.FRAMES[-1])
    paths = []
    for name, source, dtype in (
        ("color", "color", "color4f"),
        ("depth", "depth", "float"),
        ("motion", "Vector", "float4"),
        ("diffuseAlbedo", "DiffuseAlbedo", "color3f"),
        ("denoisingNormal", "denoising_normal", "normal3f"),
    ):
        var = UsdRender.Var.Define(stage, f"/Render/Vars/{name}")
        var.CreateSourceNameAttr(source)
        var.CreateDataTypeAttr(dtype)
        paths.append(var.GetPath())
    # Blender's Vector pass is +y up.
    stage.GetPrimAtPath("/Render/Vars/motion").CreateAttribute(
        "harmonizer:motionVectorScale", Sdf.ValueTypeNames.Float2, custom=True
    ).Set(Gf.Vec2f(1, -1))
    prod = UsdRender.Product.Define(stage, "/Render/Products/noisy")
    prod.CreateProductNameAttr("render/noisy.####.exr")
    prod.CreateOrderedVarsRel().SetTargets(paths)
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateProductsRel().SetTargets([prod.GetPath()])
    settings.CreateResolutionAttr(Gf.Vec2i(fixtures.W, fixtures.H))
    for attr, value in (settings_attrs or {}).items():
        kind = (
            Sdf.ValueTypeNames.Int
            if isinstance(value, int)
            else Sdf.ValueTypeNames.String
        )
        settings.GetPrim().CreateAttribute(attr, kind, custom=True).Set(value)
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.GetRootLayer().Save()
    for f in fixtures.FRAMES:
        src = fixtures._read_parts(rendered / f"blender/blender.{f:04d}.exr")
        vl = "ViewLayer."
        fixtures.write_exr(
            root / f"render/noisy.{f:04d}.exr",
            {
                **{c: src[f"{vl}Combined.{c}"] for c in "RGBA"},
                "Z": src[f"{vl}Depth.Z"],
                **{f"Vector.{c}": src[f"{vl}Vector.{c}"] for c in "XYZW"},
                **{
                    f"DiffuseAlbedo.{c}": src[f"{vl}Denoising Albedo.{c}"]
                    for c in albedo
                },
                **{
                    f"denoising_normal.{c}": src[f"{vl}Denoising Normal.{c}"]
                    for c in "XYZ"
                },
            },
            "float",
            {"colorInteropID": "lin_rec709_scene"},
        )
    return root / "denoise.usda"


def gains(rendered: Path, results: list) -> list[float]:
    """dB closer to the reference than the input, frame by frame."""
    out = []
    for r in results:
        ref = fixtures.reference_rgb(rendered, r.frame)
        a = read_exr(r.source, "in").stack(["R", "G", "B"])
        b = read_exr(r.output, "out").stack(["R", "G", "B"])
        out.append(psnr(b, ref) - psnr(a, ref))
    return out


def test_albedo_and_denoising_normal_vars_denoise(
    rendered: Path, tmp_path: Path
) -> None:
    """harmonizer:samples = 4 on the RenderSettings: denoise auto is on from the first frame."""
    stage = noisy_shot(rendered, tmp_path, settings_attrs={"harmonizer:samples": 4})
    with PostFrameHook(str(stage), backend="classical", params=PARAMS) as hook:
        results = [hook(f)[0] for f in fixtures.FRAMES]
    assert all(r.denoised for r in results), [r.denoise_decision for r in results]
    first = results[0].denoise_decision
    assert (
        first is not None
        and first.startswith("denoise auto: on")
        and "4 samples" in first
    ), first
    assert all(r.denoise_decision is None for r in results[1:])
    for r in results:
        assert "albedo" in r.inputs and "denoise_normal" in r.inputs, r.inputs
        assert read_exr(r.output, "out").attributes()["harmonizer:denoised"] == 1
    g = gains(rendered, results)
    print(f"\ndenoised, dB over the 4-sample input: {[round(x, 2) for x in g]}")
    assert min(g) >= MIN_GAIN_DB, g


def test_cli_denoise_flags_win_over_the_stage(
    rendered: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    stage = noisy_shot(rendered, tmp_path, settings_attrs={"harmonizer:denoise": "on"})
    args = [str(stage), "--backend", "classical", "--no-layer"]
    assert main([*args, "--denoise", "off", "--out-dir", str(tmp_path / "off")]) == 0
    line = capsys.readouterr().out.splitlines()[0]
    assert "denoised: 0" in line, line
    for f in fixtures.FRAMES:
        out = read_exr(tmp_path / f"off/noisy/noisy.{f:04d}.exr", "out")
        assert out.attributes()["harmonizer:denoised"] == 0
    # The stage's harmonizer:denoise = on, the CLI's quality and sample count.
    assert (
        main(
            [
                *args,
                "--denoise-quality",
                "fast",
                "--samples",
                "4",
                "--out-dir",
                str(tmp_path / "on"),
            ]
        )
        == 0
    )
    line = capsys.readouterr().out.splitlines()[0]
    assert f"denoised: {len(fixtures.FRAMES)} (denoise on)" in line, line
    assert "albedo" in line and "denoise_normal" in line, line
    assert main([*args, "--samples", "-1"]) == 1
    assert "--samples: -1 is not a sample count" in capsys.readouterr().err


def test_temporal_accumulates_without_a_second_spatial_pass(
    rendered: Path, tmp_path: Path
) -> None:
    """harmonizer:denoise = temporal (frames the renderer denoised): accumulated only."""
    stage = noisy_shot(
        rendered, tmp_path, settings_attrs={"harmonizer:denoise": "temporal"}
    )
    with PostFrameHook(str(stage), backend="classical", params=PARAMS) as hook:
        results = [hook(f)[0] for f in fixtures.FRAMES]
    assert all(r.denoised for r in results)
    first = results[0].denoise_decision
    assert first is not None and first.startswith("denoise temporal"), first
    assert results[0].noise_level is None
    # The first frame has no history: it comes out as it went in (no OIDN).
    assert abs(gains(rendered, results)[0]) < 0.5


def test_off_is_not_denoised(rendered: Path, tmp_path: Path) -> None:
    stage = noisy_shot(rendered, tmp_path)
    with PostFrameHook(
        str(stage), backend="classical", params={**PARAMS, "denoise": "off"}
    ) as hook:
        results = [hook(f)[0] for f in fixtures.FRAMES]
    assert not any(r.denoised for r in results)
    # The first frame has no history to blend with: it comes out as it went in.
    assert abs(gains(rendered, results)[0]) < 0.5


def test_wrong_albedo_channel_count_names_the_file_and_channel(
    rendered: Path, tmp_path: Path
) -> None:
    stage = noisy_shot(rendered, tmp_path, albedo="RG")
    with PostFrameHook(str(stage), backend="classical") as hook:
        with pytest.raises(
            VarError,
            match=r"/Render/Products/noisy frame 1001 \(.*noisy\.1001\.exr\): RenderVar "
            r"/Render/Vars/diffuseAlbedo \(albedo\): channel 'DiffuseAlbedo\.B' is missing: "
            r"albedo needs 3 channels \(DiffuseAlbedo\.R, DiffuseAlbedo\.G, DiffuseAlbedo\.B\)",
        ):
            hook(fixtures.FRAMES[0])
    assert not (tmp_path / "render/harmonized").exists()


@pytest.mark.parametrize(
    ("attr", "value", "message"),
    [
        ("harmonizer:denoise", "maybe", "'maybe' is not one of auto, on, off, temporal"),
        (
            "harmonizer:denoiseQuality",
            "best",
            "'best' is not one of high, balanced, fast",
        ),
        ("harmonizer:samples", -4, "-4 is not a sample count"),
    ],
)
def test_bad_denoise_setting_names_the_attribute(
    rendered: Path, tmp_path: Path, attr: str, value: object, message: str
) -> None:
    stage = noisy_shot(rendered, tmp_path, settings_attrs={attr: value})
    with pytest.raises(SettingsError, match=rf"/Render/Settings\.{attr}: {message}"):
        PostFrameHook(str(stage), backend="classical")


def test_denoise_settings_on_the_product_win(rendered: Path, tmp_path: Path) -> None:
    stage_path = noisy_shot(
        rendered, tmp_path, settings_attrs={"harmonizer:denoise": "off"}
    )
    stage = Usd.Stage.Open(str(stage_path))
    prim = stage.GetPrimAtPath("/Render/Products/noisy")
    prim.CreateAttribute(
        "harmonizer:denoise", Sdf.ValueTypeNames.Token, custom=True
    ).Set("On")
    prim.CreateAttribute(
        "harmonizer:denoiseQuality", Sdf.ValueTypeNames.String, custom=True
    ).Set("balanced")
    with PostFrameHook(stage, backend="classical") as hook:
        session = hook.runners["/Render/Products/noisy"].session
        assert session.get("denoise") == "on"
        assert session.get("denoise_quality") == "balanced"
        assert session.get("samples") == 0


@pytest.mark.parametrize(
    ("source", "role"),
    [
        ("albedo", "albedo"),
        ("DiffuseAlbedo", "albedo"),
        ("diffuse_albedo", "albedo"),
        ("denoise_albedo", "albedo"),
        ("Denoising Albedo", "albedo"),
        ("denoising_normal", "denoise_normal"),
        ("Denoising Normal", "denoise_normal"),
        ("denoise_normal", "denoise_normal"),
        ("N", "normal"),
    ],
)
def test_guide_var_names(tmp_path: Path, source: str, role: str) -> None:
    stage = Usd.Stage.CreateInMemory()
    var = UsdRender.Var.Define(stage, "/Render/Vars/v")
    var.CreateSourceNameAttr(source)
    assert role_of(VarInfo.from_prim(var.GetPrim())) == role
