"""The out-of-domain benchmark's sequences, built from the rendered passes (numpy only).

Every sequence is a dict of float32 arrays, the same for every method:

- what a host gives the enhancer: ``input [T,H,W,4]`` (RGB premultiplied by
  coverage, A = coverage), ``depth [T,H,W]`` (planar, empty 1e10), ``motion
  [T,H,W,2]`` (pixels, current -> previous, y down), ``normal [T,H,W,3]``
  (world), ``mask_insert [T,H,W]``, optionally ``albedo``/``aux_normal``
  (the noisy render's denoising passes, for the OIDN peer; on the courtyard's
  insert sequences the clean render's albedo, what a Cycles host gives);
- what only the metrics see: ``target [T,H,W,3]`` (the clean render), the clean
  ``gt_depth``/``gt_motion`` (occlusion-masked warping error), ``mask_shadow``;
- ``region``: which region the sequence degrades (``hole``, ``insert``,
  ``shadow`` or ``None``), and ``about``: one line for the report.

Sequences (``SEQUENCES``; the parameters are fixed, so building is deterministic):

| name | scene | input |
|---|---|---|
| ``recon_courtyard`` | courtyard (outdoor) | three static views re-rendered as point splats: holes, ghosting, seams |
| ``recon_hall`` | hall (indoor) | the same with the hall's three views |
| ``recon_ruins`` | ruins (outdoor) | the same with four views of a colonnade the camera arcs round |
| ``insert_tone`` | courtyard | insert A with +0.9 stop, warm white balance, more saturation; its shadow present |
| ``insert_tone_rgb`` | courtyard | the same without the albedo AOV (the frame alone) |
| ``insert_recon`` | courtyard | ``insert_relight``'s insert in ``recon_courtyard``'s reconstruction (its albedo only) |
| ``insert_recon_control`` | courtyard | the same insert correctly lit (the truth's pixels): nothing to change on it |
| ``insert_relight`` | courtyard | insert A lit by another sun and sky (low, warm, from the side); shadow present |
| ``insert_tone_alone`` | courtyard | ``insert_tone``'s change on A rendered alone, composited over the frame |
| ``insert_relight_alone`` | courtyard | A rendered alone under ``insert_relight``'s light, composited over it |
| ``insert_noshadow`` | courtyard | inserts A and B correctly lit, composited over the plate: no contact shadows |
| ``two_inserts`` | courtyard | A tone-shifted (cool, darker) and B relit, over the plate: no contact shadows |
| ``insert_control`` | courtyard | the clean render with both inserts' mask: nothing should change |
| ``clean_hall`` | hall | the clean render, no mask: nothing should change |
| ``noisy_raw`` | hall | 4 samples per pixel, a new seed per frame |
| ``noisy_denoised`` | hall | the same through Cycles' own denoiser (OIDN) per frame: residual flicker |
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from training.synth import degrade

DATA = Path(__file__).resolve().parent / "data"

SEQUENCES = (
    "recon_courtyard",
    "recon_hall",
    "insert_tone",
    "insert_relight",
    "insert_noshadow",
    "two_inserts",
    "insert_control",
    "clean_hall",
    "noisy_raw",
    "noisy_denoised",
    # After the reconstructions, so they keep their seeds (each
    # reconstruction is drawn from its index here).
    "recon_ruins",
    "insert_tone_rgb",
    "insert_recon",
    "insert_recon_control",
    "insert_tone_alone",
    "insert_relight_alone",
)

TONE_A = {"exposure": 0.9, "wb": [1.22, 0.98, 0.72], "gamma": 1.0, "saturation": 1.25}
TONE_A_COOL = {"exposure": -0.7, "wb": [0.8, 1.0, 1.3], "gamma": 1.15, "saturation": 0.8}


#: The courtyard's sky (``training.ood.render.set_sky``: a Sky Texture at
#: 0.35, its disc off, sun at 38 degrees) on a white surface facing up:
#: irradiance per channel (pi times the rendered color), rendered by Cycles
#: with the Blender extension's *Measure Sun to Sky*
#: (``tests/blender/test_light.py::test_the_courtyard_s_light_as_the_benchmark_passes_it``
#: checks it within 3 %).
COURTYARD_SKY_UP = (2.613, 4.476, 7.800)


class SequenceError(RuntimeError):
    """The rendered passes a sequence needs are missing."""


# ---------------------------------------------------------------------------
# Storage: the committed passes are packed so the set stays small (about 40 MB
# for both scenes). Colour stays float16 and depth float32, bit for bit, with
# their bytes shuffled (high bytes together) so zlib finds the redundancy;
# motion is kept to 1/64 pixel, normals to 1/127 and albedo to 1/255. The
# relit pass is kept only on and around the inserts, the only place it is used.

_INT = {"q64": (np.int16, 64.0), "q127": (np.int8, 127.0), "u8": (np.uint8, 255.0)}
PACKING = {
    "motion": "q64",
    "normal": "q127",
    "noisy_normal": "q127",
    "noisy_albedo": "u8",
    "depth": "f32s",
    "ctx_depth": "f32s",
    "mask_a": "f16",
    "mask_b": "f16",
}


def _shuffle(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a.reshape(-1).view(np.uint8).reshape(-1, a.dtype.itemsize).T)


def _unshuffle(b: np.ndarray, dtype, shape) -> np.ndarray:
    return np.ascontiguousarray(b.T).reshape(-1).view(dtype).reshape(shape)


def pack(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Arrays for ``np.savez_compressed`` (``unpack`` is the inverse, up to the stated precision)."""
    out: dict[str, np.ndarray] = {}
    arrays = dict(arrays)
    if "relit" in arrays and "mask_a" in arrays:
        from training.synth.degrade import box_blur

        near = (
            np.stack(
                [
                    box_blur((arrays["mask_a"][t] + arrays["mask_b"][t]).astype(np.float32), 3)
                    for t in range(arrays["relit"].shape[0])
                ]
            )
            > 0
        )
        arrays["relit"] = np.where(near[..., None], arrays["relit"], 0.0)
    for k, a in arrays.items():
        how = PACKING.get(k)
        if k.endswith("world_to_camera") or k.endswith("world_to_ndc"):
            out[k] = a.astype(np.float32)
        elif how in _INT:
            dt, scale = _INT[how]
            lo, hi = np.iinfo(dt).min, np.iinfo(dt).max
            q = np.clip(np.round(a.astype(np.float32) * scale), lo, hi).astype(dt)
            out[f"{k}@{how}"] = _shuffle(q)
            out[f"{k}@shape"] = np.array(a.shape, np.int64)
        elif how == "f32s":
            out[f"{k}@f32s"] = _shuffle(a.astype(np.float32))
            out[f"{k}@shape"] = np.array(a.shape, np.int64)
        elif how == "f16":
            out[k] = a.astype(np.float16)
        else:
            out[f"{k}@f16s"] = _shuffle(a.astype(np.float16))
            out[f"{k}@shape"] = np.array(a.shape, np.int64)
    return out


def unpack(z) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for key in z.files:
        k, _, how = key.partition("@")
        if how == "shape":
            continue
        a = z[key]
        if how == "f16s":
            a = _unshuffle(a, np.float16, tuple(z[f"{k}@shape"]))
        elif how == "f32s":
            a = _unshuffle(a, np.float32, tuple(z[f"{k}@shape"]))
        elif how in _INT:
            dt, scale = _INT[how]
            a = _unshuffle(a, dt, tuple(z[f"{k}@shape"])).astype(np.float32) / scale
        out[k] = a.astype(np.float32)
    return out


def load_scene(name: str, data: Path = DATA) -> dict:
    f = Path(data) / name / "scene.npz"
    if not f.exists():
        raise SequenceError(f"{f} missing: render it with `.venv-bpy/bin/python -m training.ood.render --scene {name}`")
    with np.load(f) as z:
        out = unpack(z)
    out["meta"] = json.loads((f.parent / "meta.json").read_text())
    return out


def _tone(rgb: np.ndarray, p: dict) -> np.ndarray:
    q = dict(p)
    q["wb"] = list(np.asarray(p["wb"], np.float32) / (np.asarray(p["wb"], np.float32) @ degrade.LUMA))
    return degrade.apply_tone(rgb, q)


def build(name: str, data: Path = DATA, cache: dict | None = None, frames: int = 0) -> dict:
    """One sequence (``frames`` > 0: only its first frames)."""
    if name not in SEQUENCES:
        raise SequenceError(f"unknown sequence '{name}' (have {', '.join(SEQUENCES)})")
    if name in ("recon_hall", "clean_hall", "noisy_raw", "noisy_denoised"):
        scene_name = "hall"
    elif name == "recon_ruins":
        scene_name = "ruins"
    else:
        scene_name = "courtyard"
    cache = {} if cache is None else cache
    if scene_name not in cache:
        cache[scene_name] = load_scene(scene_name, data)
    sc = cache[scene_name]
    T = sc["truth"].shape[0] if frames <= 0 else min(frames, sc["truth"].shape[0])
    gt = sc["truth"][:T]
    ones = np.ones(gt.shape[:3] + (1,), np.float32)
    zeros = np.zeros(gt.shape[:3], np.float32)
    s = {
        "name": name,
        "scene": scene_name,
        "kind": sc["meta"]["kind"],
        "target": gt,
        "gt_depth": sc["depth"][:T],
        "gt_motion": sc["motion"][:T],
        "depth": sc["depth"][:T],
        "motion": sc["motion"][:T],
        "normal": sc["normal"][:T],
        "world_to_camera": sc["world_to_camera"][:T],
        "world_to_ndc": sc["world_to_ndc"][:T],
        "mask_insert": zeros,
        "mask_shadow": zeros,
        "region": None,
    }
    if scene_name == "courtyard":
        # The render's albedo, which a Cycles host gives with its inserts
        # (Denoising Albedo): every insert sequence but ``insert_tone_rgb``.
        if "albedo" in sc and name != "insert_tone_rgb":
            s["albedo"] = sc["albedo"][:T]
            if name in ("insert_recon", "insert_recon_control"):
                # A reconstruction has no albedo: the host knows it on the
                # object it renders and inserts, nowhere else.
                s["albedo"] = s["albedo"] * (sc["mask_a"][:T, ..., None] > 0)
        a, b = sc["mask_a"][:T], sc["mask_b"][:T]
        ab = np.clip(a + b, 0.0, 1.0)
        plate = sc["noinsert_ab"][:T]
        s["mask_shadow"] = degrade.shadow_mask(gt, plate, ab)
    if name.startswith("recon_") or name.startswith("insert_recon"):
        # The inserts into a reconstruction reconstruct as ``recon_courtyard`` does.
        seed = SEQUENCES.index("recon_courtyard" if name.startswith("insert_recon") else name)
        rgba, depth, params = degrade.reconstruction_inputs(
            np.random.default_rng([2026, 17, seed]),
            list(sc["ctx_rgb"]),
            list(sc["ctx_depth"]),
            list(zip(sc["ctx_world_to_camera"], sc["ctx_world_to_ndc"], strict=True)),
            list(zip(sc["world_to_camera"][:T], sc["world_to_ndc"][:T], strict=True)),
            gt.shape[2],
            gt.shape[1],
        )
        s.update(input=rgba, depth=depth, region="hole", params=params)
        s["about"] = f"sparse-view reconstruction ({len(sc['ctx_rgb'])} views, point splats), {s['kind']}"
        if name.startswith("insert_recon"):
            # The object is rendered whole (covered) over the reconstruction,
            # at its own depth: lit by another light, or as the scene lights
            # it (the control).
            inside = a > 0.5
            obj = gt if name == "insert_recon_control" else sc["relit"][:T]
            rgb = degrade.composite(rgba, obj, a)
            cov = rgba[..., 3] * (1 - a) + a
            s.update(
                input=np.concatenate([rgb, cov[..., None]], -1).astype(np.float32),
                depth=np.where(inside, sc["depth"][:T], depth).astype(np.float32),
                mask_insert=a,
                region="insert",
            )
            s["about"] = (
                "insert lit by another sun and sky, composited into the courtyard's reconstruction"
                if name == "insert_recon"
                else "insert correctly lit, composited into the courtyard's reconstruction (nothing to change on it)"
            )
    elif name in ("insert_tone", "insert_tone_rgb"):
        s.update(input=np.concatenate([degrade.composite(gt, _tone(gt, TONE_A), a), ones], -1), mask_insert=a)
        s.update(region="insert", about="insert with a tone / white-balance mismatch (shadow present)")
        if name == "insert_tone_rgb":
            s["about"] += ", no albedo AOV"
        elif "albedo" not in s:
            raise SequenceError(
                f"{name}: the courtyard render has no albedo: add it with "
                "`.venv-bpy/bin/python -m training.ood.render --scene courtyard --add-albedo --samples 32`"
            )
    elif name in ("insert_tone_alone", "insert_relight_alone"):
        # What a host composites: the object rendered on its own (its soft
        # edge holds only its own share, premultiplied) over the frame
        # without it. ``insert_tone`` and ``insert_relight`` blend two whole
        # frames by the mask instead, so their soft edge also carries the
        # other frame's background.
        if "alone_a" not in sc:
            raise SequenceError(
                f"{name}: the courtyard render has no insert rendered alone: add it with "
                "`.venv-bpy/bin/python -m training.ood.render --scene courtyard --add-alone`"
            )
        alone = sc["alone_a"][:T]
        share, cov = alone[..., :3], alone[..., 3:4]
        if name == "insert_tone_alone":
            fg = _tone(share / np.maximum(cov, 1e-6), TONE_A) * cov
            s["about"] = "insert rendered alone, tone / white-balance mismatch, over the frame (shadow present)"
        else:
            fg = sc["relit_alone_a"][:T][..., :3]
            s["about"] = "insert rendered alone under another sun and sky, over the frame (shadow present)"
        rgb = np.maximum(gt - share + fg, 0.0).astype(np.float32)
        s.update(input=np.concatenate([rgb, ones], -1), mask_insert=a, region="insert")
    elif name == "insert_relight":
        s.update(input=np.concatenate([degrade.composite(gt, sc["relit"][:T], a), ones], -1), mask_insert=a)
        s.update(region="insert", about="insert lit by another sun and sky (shadow present)")
    elif name == "insert_noshadow":
        s.update(input=np.concatenate([degrade.composite(plate, gt, ab), ones], -1), mask_insert=ab)
        s.update(region="shadow", about="two correctly lit inserts over the plate: contact shadows missing")
    elif name == "two_inserts":
        fg = degrade.composite(_tone(gt, TONE_A_COOL), sc["relit"][:T], b)
        s.update(input=np.concatenate([degrade.composite(plate, fg, ab), ones], -1), mask_insert=ab)
        s.update(region="insert", about="two inserts, one tone-shifted, one relit, no contact shadows")
    elif name == "insert_control":
        s.update(input=np.concatenate([gt, ones], -1), mask_insert=ab)
        s.update(region="insert", about="correctly lit inserts with their shadows (input = truth)")
    elif name == "clean_hall":
        s.update(input=np.concatenate([gt, ones], -1), about="clean render, no mask (input = truth)")
    elif name in ("noisy_raw", "noisy_denoised"):
        key = "noisy" if name == "noisy_raw" else "noisy_denoised"
        s.update(input=np.concatenate([sc[key][:T], ones], -1), albedo=sc["noisy_albedo"][:T])
        s["aux_normal"] = sc["noisy_normal"][:T]
        s["about"] = (
            "4 samples per pixel, raw, new seed per frame"
            if name == "noisy_raw"
            else "4 samples per pixel through Cycles' denoiser per frame"
        )
        # What the renderer knows and a host passes on (the Blender extension
        # does): its sample count, or that it denoised each frame itself.
        s["host_params"] = {"samples": "4"} if name == "noisy_raw" else {"denoise": "temporal"}
    if scene_name == "courtyard" and "light" in sc["meta"]:
        # What a host knows of its scene and passes on, as the Blender
        # extension does: the direction toward the sun (world space), the
        # Sun's irradiance (its strength times its color) and half the sky's
        # on a surface facing up (`COURTYARD_SKY_UP`, what its Measure renders).
        light = sc["meta"]["light"]
        e, a = np.radians(light["sun_elev"]), np.radians(light["sun_azim"])
        sun = (np.cos(e) * np.sin(a), np.cos(e) * np.cos(a), np.sin(e))
        host = s.setdefault("host_params", {})
        host["light_direction"] = ", ".join(f"{c:.6f}" for c in sun)
        host["light_color"] = ", ".join(f"{light['sun_energy'] * c:.6g}" for c in light["sun_color"])
        host["ambient_color"] = ", ".join(f"{0.5 * c:.6g}" for c in COURTYARD_SKY_UP)
    s["frames"] = T
    return s
