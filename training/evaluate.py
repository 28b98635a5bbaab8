"""Evaluates backends on held-out scenes through the real runtime (`harmonize run`).

    .venv-train/bin/python -m training.evaluate --data training/data --split test \
        --model training/runs/main/model.onnx --out training/runs/main/eval

For every (scene, stream) of the split it writes the input as `generic`-layout
EXR frames, runs ``harmonize run`` with each method and compares the outputs
with the clean render:

- ``input``: the degraded input itself;
- ``classical``: ``--backend classical``;
- ``neural``: ``--backend neural --model M`` (K from the manifest);
- ``neural_k0``: the same network with ``--context 0`` (no temporal context);
- ``neural_post``: the network followed by the classical operations
  (``--set classical_post=true``).

Metrics (on sRGB-encoded color clipped to [0,1]): PSNR and SSIM over the
frame, in holes (input coverage < 0.5), on the insert (mask > 0.5) and in its
shadow region (shadow mask > 0.5); temporal warping error: mean absolute
difference between a frame and the previous output aligned with the
renderer's motion vectors, over pixels whose depth agrees within 10%.
Writes ``metrics.json``, ``metrics.md`` and ``per_frame.json`` to ``--out``;
with ``--figures DIR`` also ``per_frame.png`` (PSNR and warping error per
frame) and ``before_after_<stream>.png`` (one held-out sequence per stream).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import OpenEXR

from training.synth.dataset import list_scenes, load_sample, scene_streams
from training.synth.degrade import warp_bilinear
from training.synth.to_exr import sample_to_exr

REPO = Path(__file__).resolve().parent.parent
DEFAULT_ORT = REPO / ".venv/lib/python3.11/site-packages/onnxruntime/capi/libonnxruntime.so.1.31.1"


def srgb(x: np.ndarray) -> np.ndarray:
    c = np.clip(x, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1 / 2.4) - 0.055)


def psnr(a: np.ndarray, b: np.ndarray, mask: np.ndarray | None = None) -> float | None:
    d = (a - b) ** 2
    if mask is not None:
        if mask.sum() < 16:
            return None
        mse = float(d[mask].mean())
    else:
        mse = float(d.mean())
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))


def ssim_map(a: np.ndarray, b: np.ndarray, r: int = 3) -> np.ndarray:
    """Per-pixel SSIM with a box window of side ``2r + 1``."""
    from training.synth.degrade import box_blur

    c1, c2 = 0.01**2, 0.03**2
    mu_a, mu_b = box_blur(a, r), box_blur(b, r)
    saa = box_blur(a * a, r) - mu_a**2
    sbb = box_blur(b * b, r) - mu_b**2
    sab = box_blur(a * b, r) - mu_a * mu_b
    return ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2))


def ssim(a: np.ndarray, b: np.ndarray, win: int = 7, mask: np.ndarray | None = None) -> float | None:
    """Mean SSIM (box window ``win``) over the frame, or over ``mask`` (None when
    the mask has fewer than 16 pixels)."""
    if mask is not None and mask.sum() < 16:
        return None
    s = ssim_map(a, b, win // 2)
    return float(s[mask].mean()) if mask is not None else float(s.mean())


def read_rgb(path: Path) -> np.ndarray:
    with OpenEXR.File(str(path), separate_channels=True) as f:
        ch = f.channels()
        return np.stack([np.asarray(ch[c].pixels, np.float32) for c in "RGB"], -1)


def run_harmonize(exe: Path, in_dir: Path, out_dir: Path, extra: list[str], threads: int) -> None:
    out_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.setdefault("ORT_DYLIB_PATH", str(DEFAULT_ORT))
    cmd = [
        str(exe),
        "run",
        str(in_dir / "input.####.exr"),
        "-o",
        str(out_dir / "out.####.exr"),
        "--layout",
        "generic",
        "--threads",
        str(threads),
        *extra,
    ]
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {p.returncode}): {p.stderr[-2000:]}")


def sequence_metrics(outs: list[np.ndarray], s: dict) -> dict:
    T = len(outs)
    tgt = srgb(s["target"])
    cov = s["input"][..., 3]
    per = []
    for t in range(T):
        o = srgb(outs[t])
        regions = {"hole": cov[t] < 0.5, "insert": s["mask_insert"][t] > 0.5, "shadow": s["mask_shadow"][t] > 0.5}
        m = {"psnr": psnr(o, tgt[t]), "ssim": ssim(o, tgt[t])}
        for name, mask in regions.items():
            m[f"psnr_{name}"] = psnr(o, tgt[t], mask)
            m[f"ssim_{name}"] = ssim(o, tgt[t], mask=mask)
        if t > 0:
            aligned, valid = warp_bilinear(srgb(outs[t - 1]), s["motion"][t])
            dprev, _ = warp_bilinear(s["depth"][t - 1][..., None], s["motion"][t])
            d = s["depth"][t]
            ok = (valid > 0) & (np.abs(dprev[..., 0] - d) <= 0.1 * np.minimum(dprev[..., 0], d))
            m["warp_err"] = float(np.abs(o - aligned)[ok].mean()) if ok.any() else None
        per.append(m)
    return per


def mean_of(rows: list[dict], key: str) -> float | None:
    v = [r[key] for r in rows if r.get(key) is not None]
    return float(np.mean(v)) if v else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=REPO / "training" / "data")
    ap.add_argument("--split", default="test")
    ap.add_argument("--model", type=Path, help="ONNX model (manifest beside it); omit to skip the neural rows")
    ap.add_argument(
        "--harmonize", type=Path, default=Path(os.environ.get("HZ_HARMONIZE", REPO / "target/release/harmonize"))
    )
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--max-scenes", type=int, default=0)
    ap.add_argument("--figures", type=Path, help="also write a per-frame plot and before/after sheets (PNG) here")
    ap.add_argument(
        "--method",
        action="append",
        default=[],
        metavar="NAME=ARGS",
        help="another row: `harmonize run` arguments, space separated ({model} is the --model path); repeatable",
    )
    args = ap.parse_args(argv)
    if not args.harmonize.exists():
        print(
            f"evaluate: {args.harmonize} not found (cargo build --release -p harmonize-cli, or --harmonize)",
            file=sys.stderr,
        )
        return 2
    scenes = list_scenes(args.data, args.split)
    if args.max_scenes:
        scenes = scenes[: args.max_scenes]
    if not scenes:
        print(f"evaluate: no scene in {args.data / args.split}", file=sys.stderr)
        return 2
    methods: dict[str, list[str] | None] = {"input": None, "classical": ["--backend", "classical"]}
    if args.model:
        methods["neural"] = ["--backend", "neural", "--model", str(args.model)]
        methods["neural_k0"] = ["--backend", "neural", "--model", str(args.model), "--context", "0"]
        methods["neural_post"] = ["--backend", "neural", "--model", str(args.model), "--set", "classical_post=true"]
    for m in args.method:
        name, sep, rest = m.partition("=")
        if not sep or not name:
            print(f"evaluate: --method {m!r} is not NAME=ARGS", file=sys.stderr)
            return 2
        methods[name] = [a.replace("{model}", str(args.model)) for a in rest.split()]
    rows: list[dict] = []
    # Last frame of the first scene of each stream, per method, for the before/after sheets.
    shown: dict[str, dict[str, np.ndarray]] = {}
    work = Path(tempfile.mkdtemp(prefix="hz-eval."))
    try:
        for scene in scenes:
            for stream in scene_streams(scene):
                s = load_sample(scene, stream)
                in_dir = work / "in"
                shutil.rmtree(in_dir, ignore_errors=True)
                T = sample_to_exr(scene, stream, in_dir)
                for name, extra in methods.items():
                    if extra is None:
                        outs = list(s["input"][..., :3])
                    else:
                        out_dir = work / name
                        shutil.rmtree(out_dir, ignore_errors=True)
                        run_harmonize(args.harmonize, in_dir, out_dir, extra, args.threads)
                        outs = [read_rgb(out_dir / f"out.{t + 1:04d}.exr") for t in range(T)]
                    for t, m in enumerate(sequence_metrics(outs, s)):
                        rows.append({"scene": scene.name, "stream": stream, "method": name, "frame": t, **m})
                    if stream not in shown or shown[stream]["scene"] == scene.name:
                        shown.setdefault(stream, {"scene": scene.name, "truth": s["target"][-1]})[name] = outs[-1]
                print(f"evaluate: {scene.name} {stream} done", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    keys = ["psnr", "ssim"] + [f"{m}_{r}" for r in ("hole", "insert", "shadow") for m in ("psnr", "ssim")]
    keys.append("warp_err")
    summary: dict = {}
    for method in methods:
        mrows = [r for r in rows if r["method"] == method]
        summary[method] = {"all": {k: mean_of(mrows, k) for k in keys}}
        for stream in sorted({r["stream"] for r in mrows}):
            sr = [r for r in mrows if r["stream"] == stream]
            summary[method][stream] = {k: mean_of(sr, k) for k in keys}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "per_frame.json").write_text(json.dumps(rows, indent=0))
    (args.out / "metrics.json").write_text(
        json.dumps({"scenes": [p.name for p in scenes], "summary": summary}, indent=1)
    )
    lines = ["| method | subset | " + " | ".join(keys) + " |", "|---" * (len(keys) + 2) + "|"]
    for method, subs in summary.items():
        for sub, vals in subs.items():
            cells = [
                ("-" if vals[k] is None else f"{vals[k]:.4f}" if k in ("ssim", "warp_err") else f"{vals[k]:.2f}")
                for k in keys
            ]
            lines.append(f"| {method} | {sub} | " + " | ".join(cells) + " |")
    (args.out / "metrics.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    if args.figures:
        write_figures(args.figures, rows, list(methods), shown)
    return 0


def write_figures(out: Path, rows: list[dict], methods: list[str], shown: dict) -> None:
    """``per_frame.png``: PSNR and warping error against the frame index (mean over
    the split's sequences); ``before_after_<stream>.png``: the last frame of one
    held-out sequence per stream, each method beside the clean render."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    frames = sorted({r["frame"] for r in rows})
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for method in methods:
        for ax, key in zip(axes, ("psnr", "warp_err"), strict=True):
            ys = [mean_of([r for r in rows if r["method"] == method and r["frame"] == f], key) for f in frames]
            xs = [f for f, y in zip(frames, ys, strict=True) if y is not None]
            ax.plot(xs, [y for y in ys if y is not None], marker="o", label=method)
    axes[0].set(xlabel="frame", ylabel="PSNR (dB, sRGB)", title="PSNR per frame (held-out)")
    axes[1].set(xlabel="frame", ylabel="mean |frame - warped previous|", title="temporal warping error")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out / "per_frame.png", dpi=110)
    plt.close(fig)
    for stream, imgs in shown.items():
        cols = [m for m in methods if m in imgs] + ["truth"]
        tiles = [np.clip(srgb(imgs[c]), 0, 1) for c in cols]
        fig, axes = plt.subplots(1, len(cols), figsize=(3.2 * len(cols), 2.2))
        for ax, c, im in zip(np.atleast_1d(axes), cols, tiles, strict=True):
            ax.imshow(im)
            ax.set_title(c, fontsize=9)
            ax.axis("off")
        fig.suptitle(f"{stream} ({imgs['scene']}, last frame)", fontsize=9)
        fig.tight_layout()
        fig.savefig(out / f"before_after_{stream}.png", dpi=110)
        plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
