"""Temporal state through the USD hook, judged against a converged render.

The fixture shot is rendered with 4 samples (the products) and 64 samples
(the reference). With history reprojected correctly, the classical
backend's temporal blend must bring each frame after the first closer to
the reference than the input is; fed wrong motion (the vertical axis not
flipped) or wrong cameras (the animation dropped), it must do worse. This
checks that the hook's motion-vector scale and USD camera matrices reach
the library right, end to end. Harmonization and contact shadows are off so
that only the temporal part changes the image; ``stabilize_all`` asks for
the whole-frame blend (since 10cd7de a frame without holes is stabilized
only on its insert, which left these frames as they came).
"""

from __future__ import annotations

import shutil
from pathlib import Path

import fixtures
import numpy as np
from pxr import Sdf, Usd, UsdGeom
from usd_harmonizer import PostFrameHook
from usd_harmonizer.exrio import read_exr

PARAMS = {"harmonize": False, "contact_shadows": False, "stabilize_all": True}


def errors(
    rendered: Path, shot: Path, product: str, aces: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Mean absolute error to the reference of input and output, frames 1002+."""
    with PostFrameHook(
        str(shot), products=[product], backend="classical", params=PARAMS
    ) as hook:
        results = [hook(f)[0] for f in fixtures.FRAMES]
    e_in, e_out = [], []
    for r in results[1:]:
        assert r.reset is None and r.history_used >= 1
        ref = fixtures.reference_rgb(rendered, r.frame)
        if aces:
            ref = fixtures.aces_from_lin709(ref)
        a = read_exr(r.source, "in").stack(["R", "G", "B"])
        b = read_exr(r.output, "out").stack(["R", "G", "B"])
        e_in.append(np.abs(a - ref).mean())
        e_out.append(np.abs(b - ref).mean())
    return np.array(e_in), np.array(e_out)


def test_motion_vectors_denoise(rendered: Path, shot: Path) -> None:
    e_in, e_out = errors(rendered, shot, "beauty", aces=False)
    assert (e_out < 0.8 * e_in).all(), (e_in, e_out)


def test_wrong_motion_convention_hurts(rendered: Path, shot: Path) -> None:
    good = errors(rendered, shot, "beauty", aces=False)[1]
    for f in fixtures.FRAMES:
        (shot.parent / f"render/harmonized/beauty.{f}.exr").unlink()
    stage = Usd.Stage.Open(str(shot))
    stage.GetPrimAtPath("/Render/Vars/motion").GetAttribute(
        "harmonizer:motionVectorScale"
    ).Set((1.0, 1.0))
    stage.Save()
    bad = errors(rendered, shot, "beauty", aces=False)[1]
    assert (bad > 1.3 * good).all(), (good, bad)


def test_depth_and_cameras_denoise(rendered: Path, shot: Path) -> None:
    """``nomv`` has no motion vectors: the history is reprojected from depth
    and the per-frame USD cameras."""
    e_in, e_out = errors(rendered, shot, "nomv", aces=True)
    assert (e_out < 0.8 * e_in).all(), (e_in, e_out)


def test_wrong_cameras_hurt(rendered: Path, shot: Path) -> None:
    good = errors(rendered, shot, "nomv", aces=True)[1]
    shutil.rmtree(shot.parent / "render/nomv/harmonized")
    # Drop the camera animation in a stronger layer: every frame gets 1001's camera.
    stage = Usd.Stage.Open(str(shot))
    cam = UsdGeom.Xformable(stage.GetPrimAtPath("/World/Cam"))
    op = cam.GetOrderedXformOps()[0]
    assert op.GetOpName() == "xformOp:translate"
    held = op.GetAttr().Get(fixtures.FRAMES[0])
    spec = Sdf.CreatePrimInLayer(stage.GetRootLayer(), "/World/Cam")
    spec.specifier = Sdf.SpecifierOver
    attr = Sdf.AttributeSpec(spec, "xformOp:translate", Sdf.ValueTypeNames.Double3)
    attr.default = held
    stage.GetRootLayer().SetTimeSample(attr.path, fixtures.FRAMES[0], held)
    stage.Save()
    assert (
        Usd.Stage.Open(str(shot))
        .GetPrimAtPath("/World/Cam")
        .GetAttribute("xformOp:translate")
        .Get(fixtures.FRAMES[-1])
        == held
    )
    bad = errors(rendered, shot, "nomv", aces=True)[1]
    assert (bad > 1.3 * good).all(), (good, bad)
