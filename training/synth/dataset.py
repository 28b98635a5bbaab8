"""Reads rendered samples (numpy only; shared by the trainer and the tools).

Layout (``training/README.md`` has the full table)::

    <data>/<split>/scene_<id>/scene.npz      clean render + AOVs shared by the streams
    <data>/<split>/scene_<id>/s<k>_<name>.npz degraded input of one stream (+ overrides)
    <data>/<split>/scene_<id>/meta.json      parameters, assets, checks

A scene directory exists only when complete (it is renamed into place last).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

STREAMS = ("s1_recon", "s2_tone", "s3_relight", "s4_shadow", "s5_noise", "s6_insert")
#: The streams that carry the scene's ``albedo`` when it has one.
ALBEDO_STREAMS = ("s2_tone", "s3_relight", "s4_shadow", "s6_insert")
SCENE_KEYS = ("target", "depth", "motion", "normal", "mask_insert", "mask_shadow", "world_to_camera", "world_to_ndc")


class DataError(RuntimeError):
    """A sample is missing or malformed."""


#: float16's largest value: stored arrays saturate there.
F16_MAX = 65504.0


def to_f16(a: np.ndarray) -> np.ndarray:
    """float16 for storage, saturating at its largest value: a sun disk or a
    specular glint scaled by the exposure can exceed it, and would be stored
    as infinity."""
    return np.clip(a, -F16_MAX, F16_MAX).astype(np.float16)


def saturate(arrays: dict, where: str) -> None:
    """Infinities in float arrays (float16 overflow in scenes stored before
    the generator saturated: a sun disk times the exposure) become float16's
    largest value, in place; NaN is an error naming the array."""
    for k, a in arrays.items():
        if not isinstance(a, np.ndarray) or a.dtype.kind != "f" or np.isfinite(a).all():
            continue
        if np.isnan(a).any():
            raise DataError(f"{where}: array '{k}' has NaN")
        np.clip(a, -F16_MAX, F16_MAX, out=a)


def list_scenes(data_dir: Path, split: str) -> list[Path]:
    """Complete scene directories of a split, sorted by id."""
    d = Path(data_dir) / split
    if not d.is_dir():
        return []
    return sorted(p for p in d.iterdir() if p.is_dir() and p.name.startswith("scene_") and (p / "meta.json").exists())


def scene_streams(scene_dir: Path) -> list[str]:
    """The streams a scene has (scenes rendered by older generators may lack some)."""
    meta = json.loads((Path(scene_dir) / "meta.json").read_text())
    return [s for s in STREAMS if s in meta.get("streams", {})]


def load_sample(scene_dir: Path, stream: str) -> dict:
    """One sample as float32 arrays: ``input [T,H,W,4]`` (RGB premultiplied,
    A = coverage), ``target [T,H,W,3]``, ``depth [T,H,W]``, ``motion [T,H,W,2]``,
    ``normal [T,H,W,3]``, ``mask_insert``/``mask_shadow [T,H,W]``,
    ``world_to_camera``/``world_to_ndc [T,4,4]`` (OpenEXR row-vector), ``meta``,
    and ``albedo [T,H,W,3]`` on the insert streams of scenes that kept it."""
    scene_dir = Path(scene_dir)
    if stream not in STREAMS:
        raise DataError(f"unknown stream '{stream}' (expected one of {', '.join(STREAMS)})")
    out: dict = {}
    for f in (scene_dir / "scene.npz", scene_dir / f"{stream}.npz"):
        if not f.exists():
            raise DataError(f"{f} missing")
        try:
            with np.load(f) as z:
                for k in z.files:
                    out[k] = z[k].astype(np.float32)
        except (OSError, ValueError) as e:
            raise DataError(f"{f}: cannot read ({e})") from e
    for k in SCENE_KEYS + ("input",):
        if k not in out:
            raise DataError(f"{scene_dir}: array '{k}' missing for stream {stream}")
    # The clean render's albedo (scenes rendered since 2026-11-28) goes with
    # the insert streams, as a host gives it with its composite; not with the
    # reconstruction (no renderer's albedo behind a splat fit) nor the noisy
    # frames (whose own albedo would be noisy too).
    if stream not in ALBEDO_STREAMS:
        out.pop("albedo", None)
    saturate(out, f"{scene_dir} ({stream})")
    out["meta"] = json.loads((scene_dir / "meta.json").read_text())
    out["stream"] = stream
    return out


def has_context(scene_dir: Path) -> bool:
    """Whether the scene kept its context views (``ctx.npz``, scenes rendered
    since 2026-11-27), so its reconstruction stream can be degraded again."""
    return (Path(scene_dir) / "ctx.npz").exists()


def redegrade(scene_dir: Path, rng: np.random.Generator, ctx: Path | None = None) -> dict:
    """The reconstruction stream of a scene made again from its context views
    with ``rng``: ``input [T,H,W,4]`` and ``depth [T,H,W]`` as ``load_sample``
    gives them (the input through float16, as stored). With the scene's own
    seed (``[seed, scene_id, 1]``) it is the stored ``s1_recon``, colors
    within float16 rounding (the views are kept in float16). ``ctx``: the
    views from another file than the scene's ``ctx.npz``."""
    scene_dir = Path(scene_dir)
    try:
        with np.load(ctx or scene_dir / "ctx.npz") as c:
            colors = list(c["color"].astype(np.float32))
            depths = list(c["depth"])
            ctx_cams = list(zip(c["world_to_camera"], c["world_to_ndc"], strict=True))
        with np.load(scene_dir / "scene.npz") as z:
            cams = list(zip(z["world_to_camera"], z["world_to_ndc"], strict=True))
    except (OSError, ValueError, KeyError) as e:
        raise DataError(f"{scene_dir}: cannot read the context views ({e})") from e
    for c in colors:
        saturate({"color": c}, f"{ctx or scene_dir / 'ctx.npz'}")
    return reconstruct(colors, depths, ctx_cams, cams, rng)


def reconstruct(colors: list, depths: list, ctx_cams: list, cams: list, rng: np.random.Generator) -> dict:
    """``redegrade`` on arrays in memory: the context views' colors ``[H,W,3]``
    and depths, their cameras and the frames' (``(world_to_camera,
    world_to_ndc)`` pairs)."""
    from training.synth import degrade

    h, w = depths[0].shape
    rec, depth, _ = degrade.reconstruction_inputs(rng, colors, depths, ctx_cams, cams, w, h)
    return {"input": to_f16(rec).astype(np.float32), "depth": depth.astype(np.float32)}
