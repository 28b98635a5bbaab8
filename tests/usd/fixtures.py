"""Fixture shot: a USD stage rendered with Blender's Cycles, and its render
products written the way the stage's RenderSettings declare them.

1. ``author_scene.py`` (usd-core) writes ``scene.usda``: floor, box, an insert
   sphere (``harmonizer:insert``), a sun and a camera animated over 1001-1006.
2. ``blender_render.py`` runs in ``.venv-bpy``: bpy imports ``scene.usda`` and
   renders it with Cycles CPU (128x72, 4 samples) into Blender multilayer EXRs.
3. ``write_products`` (here, usd-core + OpenImageIO) writes ``shot.usda``
   (sublayers the scene; RenderSettings, RenderProducts, RenderVars) and each
   product's files from the Blender parts:

   - ``beauty``: ``render/beauty.####.exr``, Linear Rec.709 (the file's
     ``colorInteropID``), float; vars ``color`` (R,G,B,A), ``depth`` (Z),
     ``motion`` (Blender's Vector.X,Y,Z,W kept, ``harmonizer:motionVectorScale``
     (1, -1)), ``N`` (N.X,N.Y,N.Z), ``insert`` (mask.insert) and
     ``objectIndex`` (not a harmonizer input; kept as is).
   - ``nomv``: no motion vectors (the library reprojects from depth and the
     per-frame cameras); ``productName`` time-sampled per frame, no token;
     ACEScg declared with UsdColorSpaceAPI on the product; half float.

A 64-sample render of the same frames (``reference/``) is the converged
reference for the temporal tests. Everything is generated into a cache directory keyed by the hash of these
scripts, so a test run renders once.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import PyOpenColorIO as ocio
from pxr import Gf, Sdf, Usd, UsdRender

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
sys.path.insert(0, str(HERE))

import author_scene

FRAMES = list(range(author_scene.FIRST_FRAME, author_scene.LAST_FRAME + 1))
#: Cycles samples of the product renders and of the converged reference.
SAMPLES = 4
REFERENCE_SAMPLES = 64
W, H = author_scene.WIDTH, author_scene.HEIGHT


def bpy_python() -> Path:
    """The ``.venv-bpy`` interpreter (``$HZ_BPY_VENV`` overrides the venv)."""
    venv = Path(os.environ.get("HZ_BPY_VENV", REPO / ".venv-bpy"))
    return venv / "bin" / "python"


def _key() -> str:
    h = hashlib.sha256()
    for f in ("author_scene.py", "blender_render.py", "fixtures.py"):
        h.update((HERE / f).read_bytes())
    return h.hexdigest()[:16]


def cache_root() -> Path:
    """Where generated fixtures live (``$HZ_USD_CACHE``, else ``build/usd_fixtures``)."""
    return Path(os.environ.get("HZ_USD_CACHE", REPO / "build" / "usd_fixtures"))


def _read_parts(path: Path) -> dict[str, np.ndarray]:
    """Blender multilayer EXR -> {full channel name: (H, W) float32}."""
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise RuntimeError(f"cannot open {path}: {oiio.geterror()}")
    out: dict[str, np.ndarray] = {}
    i = 0
    while inp.seek_subimage(i, 0):
        spec = inp.spec()
        data = np.asarray(inp.read_image(i, 0, 0, spec.nchannels, "float"), np.float32)
        data = data.reshape(spec.height, spec.width, spec.nchannels)
        for c, name in enumerate(spec.channelnames):
            out[name] = data[..., c].copy()
        i += 1
    inp.close()
    return out


def reference_rgb(root: Path, frame: int) -> np.ndarray:
    """The 64-sample render of ``frame`` (Linear Rec.709, premultiplied)."""
    parts = _read_parts(root / f"reference/blender.{frame:04d}.exr")
    return np.stack([parts[f"ViewLayer.Combined.{c}"] for c in "RGB"], axis=-1)


def write_exr(
    path: Path, channels: dict[str, np.ndarray], fmt: str, attrs: dict[str, object]
) -> None:
    """Single-part EXR with the channels in the given order."""
    path.parent.mkdir(parents=True, exist_ok=True)
    names = list(channels)
    spec = oiio.ImageSpec(W, H, len(names), fmt)
    spec.channelnames = tuple(names)
    spec.attribute("compression", "zip")
    for k, v in attrs.items():
        spec.attribute(k, v) if isinstance(v, str) else spec.attribute(k, "int", int(v))
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec), out.geterror()
    assert out.write_image(
        np.stack([channels[n] for n in names], axis=-1).astype(np.float32)
    )
    assert out.close()


def aces_from_lin709(rgb: np.ndarray) -> np.ndarray:
    """Linear Rec.709 -> ACEScg with ocio://default."""
    cfg = ocio.Config.CreateFromFile("ocio://default")
    cpu = cfg.getProcessor("lin_rec709_srgb", "ACEScg").getDefaultCPUProcessor()
    out = np.ascontiguousarray(rgb, np.float32).copy()
    cpu.applyRGB(out)
    return out


def _var(
    stage: Usd.Stage, name: str, source: str, dtype: str, **attrs: object
) -> Sdf.Path:
    v = UsdRender.Var.Define(stage, f"/Render/Vars/{name}")
    v.CreateSourceNameAttr(source)
    v.CreateDataTypeAttr(dtype)
    p = v.GetPrim()
    for k, val in attrs.items():
        k = k.replace("__", ":")
        if isinstance(val, tuple):
            p.CreateAttribute(k, Sdf.ValueTypeNames.Float2, custom=True).Set(
                Gf.Vec2f(*val)
            )
        else:
            p.CreateAttribute(k, Sdf.ValueTypeNames.String, custom=True).Set(val)
    return v.GetPath()


def write_products(root: Path, blender_dir: Path) -> Path:
    """Writes ``shot.usda`` and the product files; returns the stage path."""
    stage = Usd.Stage.CreateNew(str(root / "shot.usda"))
    stage.GetRootLayer().subLayerPaths.append("scene.usda")
    stage.SetStartTimeCode(FRAMES[0])
    stage.SetEndTimeCode(FRAMES[-1])
    stage.SetTimeCodesPerSecond(24)
    color = _var(stage, "color", "color", "color4f")
    depth = _var(stage, "depth", "depth", "float", driver__parameters__aov__name="Z")
    motion = _var(
        stage, "motion", "Vector", "float4", harmonizer__motionVectorScale=(1.0, -1.0)
    )
    normal = _var(stage, "N", "normal", "normal3f")
    insert = _var(
        stage,
        "insert",
        "insertMask",
        "float",
        driver__parameters__aov__name="mask.insert",
    )
    index = _var(stage, "objectIndex", "object_index", "float")

    beauty = UsdRender.Product.Define(stage, "/Render/Products/beauty")
    beauty.CreateProductNameAttr("render/beauty.####.exr")
    beauty.CreateOrderedVarsRel().SetTargets(
        [color, depth, motion, normal, insert, index]
    )

    nomv = UsdRender.Product.Define(stage, "/Render/Products/nomv")
    name = nomv.CreateProductNameAttr("render/nomv/shot_nomv.exr")
    for f in FRAMES:
        name.Set(f"render/nomv/shot_nomv_f{f}.exr", Usd.TimeCode(f))
    nomv.CreateOrderedVarsRel().SetTargets([color, depth, normal])
    Usd.ColorSpaceAPI.Apply(nomv.GetPrim()).CreateColorSpaceNameAttr("lin_ap1_scene")

    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateProductsRel().SetTargets([beauty.GetPath(), nomv.GetPath()])
    settings.CreateCameraRel().SetTargets([Sdf.Path("/World/Cam")])
    settings.CreateResolutionAttr(Gf.Vec2i(W, H))
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.GetRootLayer().Save()

    for f in FRAMES:
        src = _read_parts(blender_dir / f"blender.{f:04d}.exr")
        vl = "ViewLayer."
        rgba = {c: src[f"{vl}Combined.{c}"] for c in "RGBA"}
        mask = (np.abs(src[f"{vl}Object Index.X"] - 1.0) < 0.5).astype(np.float32)
        common = {"renderer": "Blender Cycles (fixture)", "capDate": f"frame {f}"}
        write_exr(
            root / f"render/beauty.{f:04d}.exr",
            {
                **rgba,
                "Z": src[f"{vl}Depth.Z"],
                **{f"Vector.{c}": src[f"{vl}Vector.{c}"] for c in "XYZW"},
                **{f"N.{c}": src[f"{vl}Normal.{c}"] for c in "XYZ"},
                "mask.insert": mask,
                "objectIndex": src[f"{vl}Object Index.X"],
            },
            "float",
            {**common, "colorInteropID": "lin_rec709_scene"},
        )
        aces = aces_from_lin709(np.stack([rgba[c] for c in "RGB"], axis=-1))
        write_exr(
            root / f"render/nomv/shot_nomv_f{f}.exr",
            {
                "R": aces[..., 0],
                "G": aces[..., 1],
                "B": aces[..., 2],
                "A": rgba["A"],
                "Z": src[f"{vl}Depth.Z"],
                **{f"N.{c}": src[f"{vl}Normal.{c}"] for c in "XYZ"},
            },
            "half",
            common,
        )
    return root / "shot.usda"


def build() -> Path:
    """The fixture directory (rendered on first use): ``shot.usda``,
    ``scene.usda``, ``blender/``, ``render/``."""
    root = cache_root() / _key()
    done = root / "DONE"
    if done.is_file():
        return root
    py = bpy_python()
    if not py.is_file():
        raise RuntimeError(
            f"Blender's bpy venv is missing ({py}); run tests/usd/run.sh, which creates it"
        )
    # Drop fixtures of older script versions, then render afresh.
    if root.parent.is_dir():
        for stale in root.parent.iterdir():
            if (
                stale.is_dir()
                and stale.name != root.name
                and (stale / "DONE").is_file()
            ):
                shutil.rmtree(stale)
    if root.exists():
        shutil.rmtree(root)
    root.mkdir(parents=True)
    author_scene.author_scene(str(root / "scene.usda"))
    for out, samples in (("blender", SAMPLES), ("reference", REFERENCE_SAMPLES)):
        cmd = [
            str(py),
            str(HERE / "blender_render.py"),
            str(root / "scene.usda"),
            str(root / out),
            str(W),
            str(H),
            str(samples),
            str(FRAMES[0]),
            str(FRAMES[-1]),
            author_scene.INSERT_PRIM.rsplit("/", 1)[1],
        ]
        r = subprocess.run(
            ["nice", "-n", "10", *cmd],
            capture_output=True,
            text=True,
            timeout=900,
            check=False,
        )
        if r.returncode != 0:
            raise RuntimeError(
                f"Blender render failed ({r.returncode}):\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
            )
    write_products(root, root / "blender")
    done.write_text("ok\n")
    return root
