"""Packs rendered scenes small enough to travel to a GPU machine, and unpacks them there.

    .venv-train/bin/python -m training.pack pack --data training/data --streams s1_recon \\
        --scenes 40 --out .pack
    python3 -m training.pack unpack --pack .pack --data /tmp/data

More scenes than one call carries: ``--budget-mb 57 --parts`` writes
``.pack/part01``, ``.pack/part02``, ... each within the budget; each device
call carries one and unpacks it into the same ignored directory of the
checkout, which stays on the machine between calls while it is held.

A device call carries 64 MiB with the checkout. A scene's ``scene.npz`` and
``s1_recon.npz`` are about 5 MB as written; packed they are about 1.7 MB:
only the arrays the trainer reads (``normal`` comes back as zeros, a stream's
own arrays replace the scene's), as float16 with the low mantissa bits cleared
(colour and coverage keep 7 of 10 bits, a relative step of 0.4 %; depth and
motion 8), bytes split into high and low planes, and LZMA. Depth is clamped to
float16's range (the sky's 1e10 becomes 65504: a disparity of 1.5e-5 instead
of 1e-10). A scene's context views (``ctx.npz``) travel with ``s1_recon``
(colors as the input, depth exactly) and, where its ``meta.json`` has its
seed, instead of that stream's input and depth: unpacking makes them again
from the views with the scene's own seed (``dataset.reconstruct``; coverage
and depth as rendered, colors within the packed precision, but for pixels
that were beyond float16's range), 34-42 % less to carry. The motion vectors
travel as what the cameras and the scene's depth do not explain
(silhouettes, the sky, moving things), in steps of 1/256 px, and unpacking
adds back the cameras' motion (``degrade.camera_motion``): 3-6x finer than 8
mantissa bits, and 20-32 % less to carry. Packed with both, an 8-frame scene
is 1.08 MiB (scene 120; packed before either, 2.07 MiB), a 16-frame one 1.58
MiB (scene 160; 3.61 before); 1-1.5 s each to unpack on this machine.
Unpacked, a scene is a normal scene directory that
``training.synth.dataset.load_sample`` reads.
"""

from __future__ import annotations

import argparse
import io
import json
import lzma
import shutil
from pathlib import Path

import numpy as np

from training.ood.sequences import _shuffle, _unshuffle
from training.synth.dataset import SCENE_KEYS, list_scenes, reconstruct, scene_streams, to_f16
from training.synth.degrade import camera_motion

# Mantissa bits kept (of float16's 10) per array.
KEEP_BITS = {"input": 7, "target": 7, "color": 7, "depth": 8, "motion": 8, "mask_insert": 10, "mask_shadow": 10}


# The motion vectors travel as what the cameras and the depth do not explain,
# in steps of 1 / MOTION_STEPS px (int16: up to 128 px either way).
MOTION_STEPS = 256


def _squeeze(a: np.ndarray, keep: int) -> np.ndarray:
    h = np.ascontiguousarray(to_f16(a)).view(np.uint16)
    return _shuffle(h & np.uint16((0xFFFF << (10 - keep)) & 0xFFFF))


def _as_unpacked(a: np.ndarray, keep: int) -> np.ndarray:
    """``a`` as ``unpack_scene`` gives it back from ``_squeeze``."""
    return _unshuffle(_squeeze(a.astype(np.float32), keep), np.float16, a.shape).astype(np.float32)


def pack_scene(scene_dir: Path, streams: list[str]) -> bytes:
    """One scene's arrays for ``streams`` as one compressed blob."""
    arrays: dict[str, np.ndarray] = {}
    shapes: dict[str, list[int]] = {}
    with np.load(scene_dir / "scene.npz") as z:
        scene = {k: z[k] for k in z.files}
    meta = json.loads((scene_dir / "meta.json").read_text())
    # With its context views the reconstruction stream is made again on
    # unpacking (with the scene's own seed: the same coverage and depth), so
    # its input and depth do not travel: 34-42 % of a packed scene.
    rebuild = "s1_recon" in streams and (scene_dir / "ctx.npz").exists() and {"seed", "scene_id"} <= set(meta)
    own: dict[str, set] = {}
    for s in streams:
        with np.load(scene_dir / f"{s}.npz") as z:
            for k in z.files:
                if not (rebuild and s == "s1_recon" and k in ("input", "depth")):
                    arrays[f"{s}/{k}"] = z[k]
            own[s] = set(z.files)
    # Scene arrays some stream reads (a stream's own array hides the scene's).
    for k in SCENE_KEYS:
        if k == "normal" or all(k in own[s] for s in streams):
            continue
        arrays[f"scene/{k}"] = scene[k]
    # Motion: the cameras and the scene's depth (as it unpacks) explain it but
    # at silhouettes, in the sky and where something moves, so only the rest
    # travels, rounded to 1 / MOTION_STEPS px (34 % of a packed
    # reconstruction scene was motion). Falls back to the motion itself where
    # the rest exceeds int16.
    residual = None
    if "scene/motion" in arrays:
        depth = _as_unpacked(scene["depth"], KEEP_BITS["depth"])
        pred = camera_motion(depth, scene["world_to_camera"], scene["world_to_ndc"])
        q = np.round((scene["motion"].astype(np.float32) - pred) * MOTION_STEPS)
        if np.all(np.abs(q) <= np.iinfo(np.int16).max):
            residual = q.astype(np.int16)
            del arrays["scene/motion"]
            arrays["scene/depth"] = scene["depth"]
    # The context views travel with the reconstruction stream (`train --redegrade`).
    if "s1_recon" in streams and (scene_dir / "ctx.npz").exists():
        with np.load(scene_dir / "ctx.npz") as z:
            for k in z.files:
                arrays[f"ctx/{k}"] = z[k]
    blob: dict[str, np.ndarray] = {}
    for name, a in arrays.items():
        key = name.split("/", 1)[1]
        if key.startswith("world_") or name == "ctx/depth":  # the views' depth exactly: it places the splats
            blob[name] = a.astype(np.float32)
        else:
            blob[name] = _squeeze(a.astype(np.float32), KEEP_BITS.get(key, 10))
        shapes[name] = list(a.shape)
    if residual is not None:
        blob["motion_residual"] = _shuffle(residual.view(np.uint16))
    header = {
        "meta": meta,
        "rebuild_recon": rebuild,
        "motion_from_cameras": residual is not None,
        "streams": streams,
        "shapes": shapes,
        "normal_shape": list(scene["normal"].shape),
    }
    buf = io.BytesIO()
    np.savez(buf, header=np.frombuffer(json.dumps(header).encode(), np.uint8), **blob)
    return lzma.compress(buf.getvalue(), preset=6)


def unpack_scene(data: bytes, out_dir: Path) -> None:
    """Writes a scene directory from ``pack_scene``'s blob."""
    with np.load(io.BytesIO(lzma.decompress(data))) as z:
        header = json.loads(z["header"].tobytes())
        arrays = {}
        for name, shape in header["shapes"].items():
            a = z[name]
            if not name.split("/", 1)[1].startswith("world_") and a.dtype != np.float32:
                a = _unshuffle(a.reshape(2, -1), np.float16, tuple(shape))  # its two byte planes
            arrays[name] = a
        if header.get("motion_from_cameras"):
            depth = arrays["scene/depth"]
            q = _unshuffle(z["motion_residual"].reshape(2, -1), np.int16, (*depth.shape, 2))
            pred = camera_motion(
                depth.astype(np.float32), arrays["scene/world_to_camera"], arrays["scene/world_to_ndc"]
            )
            arrays["scene/motion"] = to_f16(pred + q.astype(np.float32) / MOTION_STEPS)
    tmp = out_dir.with_name(out_dir.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    ctx = {k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith("ctx/")}
    meta = header["meta"]
    if header.get("rebuild_recon"):
        cams = list(zip(arrays["scene/world_to_camera"], arrays["scene/world_to_ndc"], strict=True))
        ctx_cams = list(zip(ctx["world_to_camera"], ctx["world_to_ndc"], strict=True))
        rng = np.random.default_rng([meta["seed"], meta["scene_id"], 1])
        rec = reconstruct(list(ctx["color"].astype(np.float32)), list(ctx["depth"]), ctx_cams, cams, rng)
        arrays["s1_recon/input"] = rec["input"].astype(np.float16)
        arrays["s1_recon/depth"] = rec["depth"]
    scene = {k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith("scene/")}
    scene["normal"] = np.zeros(header["normal_shape"], np.float16)
    first = header["streams"][0]
    for k in SCENE_KEYS:  # a key every stream overrides still has to be in scene.npz
        if k not in scene:
            scene[k] = arrays[f"{first}/{k}"]
    np.savez(tmp / "scene.npz", **scene)
    for s in header["streams"]:
        np.savez(tmp / f"{s}.npz", **{k.split("/", 1)[1]: v for k, v in arrays.items() if k.startswith(f"{s}/")})
    if ctx:
        np.savez(tmp / "ctx.npz", **ctx)
    if isinstance(meta.get("streams"), dict):  # only the streams that travelled
        meta["streams"] = {k: v for k, v in meta["streams"].items() if k in header["streams"]}
    (tmp / "meta.json").write_text(json.dumps(meta))
    shutil.rmtree(out_dir, ignore_errors=True)
    tmp.rename(out_dir)


def _unpack_file(f: Path, out: Path) -> None:
    unpack_scene(f.read_bytes(), out)


def spread(items: list, n: int) -> list:
    """``n`` items spread evenly over the list, the last included."""
    if n >= len(items):
        return list(items)
    idx = np.unique(np.round(np.linspace(0, len(items) - 1, n)).astype(int))
    return [items[i] for i in idx]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("pack")
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--split", default="train")
    p.add_argument("--streams", nargs="+", default=["s1_recon"])
    p.add_argument("--scenes", type=int, default=0, help="that many scenes spread over the ids (0: all)")
    p.add_argument("--budget-mb", type=float, default=0, help="stop adding scenes past this size (0: none)")
    p.add_argument(
        "--parts",
        action="store_true",
        help="past the budget, go on into the next part instead of stopping: OUT/part01, OUT/part02, ... "
        "each within the budget (one device call each; unpack each with --pack OUT/partNN)",
    )
    p.add_argument("--out", type=Path, required=True)
    u = sub.add_parser("unpack")
    u.add_argument("--pack", type=Path, required=True)
    u.add_argument("--data", type=Path, required=True)
    u.add_argument("--jobs", type=int, default=1, help="scenes unpacked at once (processes)")
    args = ap.parse_args(argv)
    if args.cmd == "pack":
        scenes = [d for d in list_scenes(args.data, args.split) if set(args.streams) <= set(scene_streams(d))]
        if args.scenes:
            scenes = spread(scenes, args.scenes)
        if args.parts and not args.budget_mb:
            ap.error("--parts needs --budget-mb")
        if args.parts and any(args.out.glob("part[0-9]*")):
            # A part left from an earlier pack would travel as if it were one of these.
            ap.error(f"{args.out} already holds parts: remove them or pack elsewhere")
        budget = args.budget_mb * 2**20
        part, total = 1, 0
        for d in scenes:
            blob = pack_scene(d, args.streams)
            if budget and total + len(blob) > budget:
                if not args.parts:
                    break
                if len(blob) > budget:
                    raise SystemExit(f"{d}: {len(blob) / 2**20:.2f} MiB packed, more than the budget of one part")
                part, total = part + 1, 0
            out = (args.out / f"part{part:02d}" if args.parts else args.out) / args.split
            out.mkdir(parents=True, exist_ok=True)
            (out / f"{d.name}.xz").write_bytes(blob)
            total += len(blob)
            where = f"part {part:02d}, " if args.parts else ""
            print(f"{d.name}: {len(blob) / 2**20:.2f} MiB ({where}total {total / 2**20:.1f})", flush=True)
    else:
        for split_dir in sorted(p for p in args.pack.iterdir() if p.is_dir()):
            files = sorted(split_dir.glob("*.xz"))
            outs = [args.data / split_dir.name / f.stem for f in files]
            if args.jobs > 1 and files:
                from concurrent.futures import ProcessPoolExecutor

                with ProcessPoolExecutor(args.jobs) as pool:
                    list(pool.map(_unpack_file, files, outs))
            else:
                for f, out in zip(files, outs, strict=True):
                    _unpack_file(f, out)
            print(f"{split_dir.name}: {len(files)} scenes -> {args.data / split_dir.name}")


if __name__ == "__main__":
    main()
