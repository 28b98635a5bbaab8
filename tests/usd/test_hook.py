"""``PostFrameHook``: state across calls, resets on out-of-order frames and
gaps, a failed frame leaves the state unchanged, the layer of what was done."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from pxr import Usd
from usd_harmonizer import PostFrameHook, ProductFileError, SettingsError
from usd_harmonizer.exrio import read_exr


def resets(results: list) -> list[str | None]:
    return [r.reset for r in results]


def test_hook_in_order_then_out_of_order(shot: Path) -> None:
    with PostFrameHook(str(shot), products=["beauty"], backend="bypass") as hook:
        seen = [hook(f)[0] for f in (1001, 1002, 1003)]
        assert resets(seen) == ["first_frame", None, None]
        assert [r.history_used for r in seen][1:] != [0, 0]
        # Farm retry of an earlier frame: out of order -> reset.
        again = hook(1002)[0]
        assert again.reset == "requested"
        assert again.history_used == 0
        assert hook(1003)[0].reset is None
        # A gap resets through the library's gap policy.
        assert hook(1005)[0].reset == "frame_gap"
        out = read_exr(shot.parent / "render/harmonized/beauty.1002.exr", "out")
        assert out.attributes()["harmonizer:reset"] == "requested"
        layer = hook.write_layer()
    stage = Usd.Stage.Open(str(layer))
    prim = stage.GetPrimAtPath("/Render/Products/beauty_harmonized")
    assert list(prim.GetAttribute("harmonizer:frames").Get()) == [
        1001,
        1002,
        1003,
        1005,
    ]
    assert list(prim.GetAttribute("harmonizer:resetFrames").Get()) == [1001, 1002, 1005]
    name = prim.GetAttribute("productName")
    assert name.Get(1005) == "render/harmonized/beauty.1005.exr"


def test_failed_frame_leaves_state(shot: Path, tmp_path: Path) -> None:
    src = shot.parent / "render/beauty.1003.exr"
    shutil.move(src, tmp_path / "held.exr")
    with PostFrameHook(str(shot), products=["beauty"], backend="bypass") as hook:
        hook(1001)
        hook(1002)
        with pytest.raises(
            ProductFileError,
            match=r"/Render/Products/beauty frame 1003 .*beauty.1003.exr does not exist",
        ):
            hook(1003)
        assert not (shot.parent / "render/harmonized/beauty.1003.exr").exists()
        shutil.move(tmp_path / "held.exr", src)
        r = hook(1003)[0]
        assert r.reset is None and r.history_used >= 1


def test_hook_all_products(shot: Path) -> None:
    with PostFrameHook(str(shot), backend="bypass") as hook:
        out = hook(1001)
        assert [r.product for r in out] == [
            "/Render/Products/beauty",
            "/Render/Products/nomv",
        ]
        assert [r.color_space for r in out] == ["Linear Rec.709 (sRGB)", "ACEScg"]
        assert (
            out[1].output == shot.parent / "render/nomv/harmonized/shot_nomv_f1001.exr"
        )
        assert "camera" in out[1].inputs and "motion" not in out[1].inputs


def test_hook_checks_outputs_before_any_product(shot: Path) -> None:
    """Issue 10: out_dir=render writes nomv over its own files: the call stops
    before any product of the frame is written (beauty would go to
    render/beauty/)."""
    render = shot.parent / "render"
    with PostFrameHook(str(shot), backend="bypass", out_dir=render) as hook:
        with pytest.raises(SettingsError, match="would overwrite the input"):
            hook(1001)
    assert not (render / "beauty").exists()
