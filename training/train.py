"""Trains the temporal enhancer on rendered samples (PyTorch; CPU, or a GPU with --device cuda).

    .venv-train/bin/python -m training.train --data training/data --run training/runs/main --steps 20000

Resumable and seeded: ``--run`` keeps ``ckpt_last.pt`` (model, optimizer,
step, config); rerunning the same command continues from it, and the data
drawn at step ``i`` depends only on ``(seed, i)`` and the scenes rendered so
far (the scene list is re-read every ``--rescan-every`` steps, so training can
start while the generator still renders). Each step unrolls the
network over a few consecutive frames of one window per batch item: the
history fed to frame t is the reprojection (runtime's motion-vector hop with
the depth test) of the network's own previous outputs, prefilled with
near-truth frames for the frames before the window. A share of the batches is
non-temporal (history all invalid) so the model stays good without history.

Losses, all on the encoded (log) color: L2; multi-scale random-patch SSIM
and gradient terms (patch sizes drawn per step, against checkerboard
artifacts, no pretrained network needed); a temporal warping loss between
consecutive outputs where the target itself is temporally consistent.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from training.model import Enhancer, ModelConfig, assemble_input, decode, encode, frame_scale, reproject_hop
from training.synth.dataset import has_context, list_scenes, load_sample, redegrade, scene_streams

TRAINING_DIR = Path(__file__).resolve().parent


# ---------------------------------------------------------------------------
# Batches


class SampleCache:
    """Loads samples on demand and keeps the most recent ``size`` in memory."""

    def __init__(
        self, scenes: list[Path], size: int = 64, only: tuple[str, ...] = (), redegrade: int = 1, seed: int = 1
    ):
        self.size = size
        self.only = only
        # Variants of a scene's reconstruction stream (`--redegrade`): 0 is
        # the stored one, k > 0 made again from its context views with the
        # seed [seed, scene id, 1, k] (scenes that kept them).
        self.redegrade = redegrade
        self.seed = seed
        self.cache: dict = {}
        self.rescan(scenes)

    def rescan(self, scenes: list[Path]) -> None:
        """Takes this scene list, each with its streams (only those asked for);
        scenes with none of them are left out."""
        streams = {str(p): [n for n in scene_streams(p) if not self.only or n in self.only] for p in scenes}
        self.scenes = [p for p in scenes if streams[str(p)]]
        self.streams = {k: v for k, v in streams.items() if v}
        redo = self.redegrade > 1
        self.variants = {
            str(p): self.redegrade if redo and "s1_recon" in self.streams[str(p)] and has_context(p) else 1
            for p in self.scenes
        }

    def get(self, scene: Path, stream: str, variant: int = 0) -> dict:
        key = (str(scene), stream, variant)
        if key not in self.cache:
            if len(self.cache) >= self.size:
                self.cache.pop(next(iter(self.cache)))
            s = load_sample(scene, stream)
            if variant > 0:
                scene_id = int(Path(scene).name.split("_")[-1])
                s.update(redegrade(scene, np.random.default_rng([self.seed, scene_id, 1, variant])))
            self.cache[key] = {k: s[k] for k in ("input", "target", "depth", "motion", "mask_insert", "mask_shadow")}
        return self.cache[key]


def make_batch(cache: SampleCache, rng: np.random.Generator, cfg: dict, key: float = 0.18) -> dict:
    """A batch of windows: frames ``[B, F, C, H, W]`` tensors, F = prefill + unroll."""
    B, K, L = cfg["batch"], cfg["context_frames"], cfg["unroll"]
    crop_h, crop_w = cfg["crop"]
    items = []
    temporal = rng.random() >= cfg["p_no_history"]
    # Frames before the window that fill the history (one count for the whole
    # batch, so the windows stack): mostly a full history of K frames, as in
    # a long sequence, sometimes fewer (the start of a sequence, a reset).
    want_pre = 0
    if temporal:
        want_pre = K if rng.random() < cfg.get("p_full_prefill", 0.7) else int(rng.integers(0, K + 1))
    for _ in range(B):
        scene = cache.scenes[int(rng.integers(len(cache.scenes)))]
        names = cache.streams[str(scene)]
        stream = names[int(rng.integers(len(names)))]
        n_var = cache.variants[str(scene)] if stream == "s1_recon" else 1
        s = cache.get(scene, stream, int(rng.integers(n_var)) if n_var > 1 else 0)
        T, H, W = s["input"].shape[:3]
        unroll = min(L, T) if temporal else 1
        pre = min(want_pre, T - unroll)
        start = int(rng.integers(pre, T - unroll + 1))
        fr = list(range(start - pre, start + unroll))
        ch = min(crop_h, H) // 16 * 16
        cw = min(crop_w, W) // 16 * 16
        y0 = int(rng.integers(0, H - ch + 1))
        x0 = int(rng.integers(0, W - cw + 1))
        sl = (fr, slice(y0, y0 + ch), slice(x0, x0 + cw))
        inp = s["input"][sl].copy()
        tgt = s["target"][sl].copy()
        dep = s["depth"][sl].copy()
        mot = s["motion"][sl].copy()
        ins = s["mask_insert"][sl].copy()
        shd = s["mask_shadow"][sl].copy()
        # The insert mask is sometimes absent (hosts without one).
        if rng.random() < cfg["p_drop_insert"]:
            ins[:] = 0
        if rng.random() < 0.5:  # horizontal flip: motion x changes sign
            inp, tgt, dep, mot, ins, shd = (a[:, :, ::-1].copy() for a in (inp, tgt, dep, mot, ins, shd))
            mot[..., 0] *= -1
        # Exposure augmentation (the encoding normalizes per frame, but not exactly).
        g = float(np.exp(rng.normal(0, 0.5)))
        inp[..., :3] *= g
        tgt *= g
        # The runtime computes the exposure scale over the whole frame, not the crop.
        full = s["input"][fr].copy()
        full[..., :3] *= g
        # Exposure and white-balance flicker (per-view appearance of a
        # reconstruction, auto exposure): a gain per frame on the input only;
        # the target stays steady, so the history is what tells the network
        # the right level.
        if rng.random() < cfg.get("p_flicker", 0.0):
            sigma = rng.uniform(0.03, 0.15)
            gain = rng.normal(0, sigma, (len(fr), 1, 1, 1)) + rng.normal(0, 0.3 * sigma, (len(fr), 1, 1, 3))
            gain = np.exp(gain).astype(np.float32)
            inp[..., :3] *= gain
            full[..., :3] *= gain
        with torch.no_grad():
            scale = frame_scale(torch.from_numpy(full.transpose(0, 3, 1, 2).copy()), key).numpy()
        items.append((inp, tgt, dep, mot, ins, shd, pre, scale))
    pre = min(it[6] for it in items)
    scales = np.stack([it[7][len(it[7]) - min(len(i[0]) for i in items) :] for it in items])
    F_ = min(len(it[0]) for it in items)

    def stack(i):
        arrs = [it[i][len(it[i]) - F_ :] for it in items]
        a = np.stack(arrs)
        if a.ndim == 4:
            a = a[..., None]
        return torch.from_numpy(np.ascontiguousarray(a.transpose(0, 1, 4, 2, 3)))

    return {
        "input": stack(0),
        "target": stack(1),
        "depth": stack(2),
        "motion": stack(3),
        "insert": stack(4),
        "shadow": stack(5),
        "scale": torch.from_numpy(scales.astype(np.float32)),
        "prefill": min(pre, F_ - 1),
        "temporal": temporal,
    }


def batch_rng(seed: int, step: int) -> np.random.Generator:
    """The generator that draws batch ``step``."""
    return np.random.default_rng([seed, step])


class Batches(torch.utils.data.Dataset):
    """Batches ``first..last`` by index, for a ``DataLoader`` with workers
    (each worker loads and caches samples itself)."""

    def __init__(self, cache: SampleCache, cfg: dict, key: float, first: int, last: int):
        self.cache, self.cfg, self.key, self.first, self.last = cache, cfg, key, first, last

    def __len__(self) -> int:
        return max(self.last - self.first, 0)

    def __getitem__(self, i: int) -> dict:
        step = self.first + i
        return make_batch(self.cache, batch_rng(self.cfg["seed"], step), self.cfg, self.key)


# ---------------------------------------------------------------------------
# Losses


def ssim(x: torch.Tensor, y: torch.Tensor, win: int = 7) -> torch.Tensor:
    c1, c2 = 0.01**2, 0.03**2
    pad = win // 2
    mu_x = F.avg_pool2d(x, win, 1, pad, count_include_pad=False)
    mu_y = F.avg_pool2d(y, win, 1, pad, count_include_pad=False)
    sxx = F.avg_pool2d(x * x, win, 1, pad, count_include_pad=False) - mu_x**2
    syy = F.avg_pool2d(y * y, win, 1, pad, count_include_pad=False) - mu_y**2
    sxy = F.avg_pool2d(x * y, win, 1, pad, count_include_pad=False) - mu_x * mu_y
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    return s.mean()


def display(x: torch.Tensor) -> torch.Tensor:
    """Linear color to the sRGB transfer, clipped to 0..1 as the benchmark
    encodes its frames (``training.evaluate.srgb``); differentiable (the
    power's input kept above the linear segment's end)."""
    c = x.clamp(0.0, 1.0)
    return torch.where(c <= 0.0031308, 12.92 * c, 1.055 * c.clamp(min=0.0031308) ** (1 / 2.4) - 0.055)


def patch_loss(out: torch.Tensor, gt: torch.Tensor, rng: np.random.Generator, n: int) -> torch.Tensor:
    """Multi-scale random-patch SSIM + gradient loss: ``n`` patches of random
    size and position, each compared at its own scale."""
    _, _, h, w = out.shape
    total = out.new_zeros(())
    for _ in range(n):
        size = int(rng.choice([16, 32, 64, 96]))
        size = min(size, h, w)
        y0 = int(rng.integers(0, h - size + 1))
        x0 = int(rng.integers(0, w - size + 1))
        o = out[:, :, y0 : y0 + size, x0 : x0 + size]
        g = gt[:, :, y0 : y0 + size, x0 : x0 + size]
        down = int(rng.choice([1, 1, 2, 4]))
        if down > 1 and size // down >= 8:
            o = F.avg_pool2d(o, down)
            g = F.avg_pool2d(g, down)
        grad = (o[..., 1:, :] - o[..., :-1, :] - (g[..., 1:, :] - g[..., :-1, :])).abs().mean() + (
            o[..., :, 1:] - o[..., :, :-1] - (g[..., :, 1:] - g[..., :, :-1])
        ).abs().mean()
        total = total + (1 - ssim(o, g)) + grad
    return total / max(n, 1)


# ---------------------------------------------------------------------------
# One step


def run_window(model: Enhancer, batch: dict, cfg: dict, rng: np.random.Generator, train: bool = True):
    """Unrolls the model over a batch window; returns (loss, parts, outputs)."""
    mcfg = model.cfg
    inp, tgt, dep, mot, ins = batch["input"], batch["target"], batch["depth"], batch["motion"], batch["insert"]
    Fr = inp.shape[1]
    pre = batch["prefill"]
    # History: newest first, each (linear color, validity), aligned to the frame being processed.
    hist: list[tuple[torch.Tensor, torch.Tensor]] = []
    outs = []
    parts = {"l2": 0.0, "patch": 0.0, "temporal": 0.0}
    loss = inp.new_zeros(())
    prev_out = None
    n_frames = 0
    self_prefill = rng.random() < cfg.get("p_self_prefill", 0.0)
    for f in range(Fr):
        if f > 0:
            d_prev, d_cur, mv = dep[:, f - 1], dep[:, f], mot[:, f]
            hist = [reproject_hop(c, v, d_prev, d_cur, mv) for c, v in hist]
            # The depth of history frames is only needed one hop back (chaining).
        rgba = inp[:, f]
        scale = batch["scale"][:, f] if "scale" in batch else frame_scale(rgba, mcfg.key)
        gt_enc = encode(tgt[:, f], scale, mcfg.log_range)
        if f < pre:
            if self_prefill:
                # Prefill with the model's own outputs (no gradient), as at run
                # time: the history then holds the model's own errors, and the
                # network learns not to amplify them frame after frame.
                with torch.no_grad():
                    x = assemble_input(mcfg, rgba, ins[:, f], hist, scale, dep[:, f])
                    pseudo = decode(model(x), scale, mcfg.log_range)
            else:
                # A near-truth "enhanced" frame (small random gain and blur).
                g = np.exp(rng.normal(0, 0.03, (tgt.shape[0], 3, 1, 1))).astype(np.float32)
                g = torch.from_numpy(g).to(tgt.device)
                pseudo = tgt[:, f] * g
                if rng.random() < 0.5:
                    pseudo = F.avg_pool2d(pseudo, 3, 1, 1, count_include_pad=False)
            hist = [(pseudo, torch.ones_like(rgba[:, 3:4]))] + hist
            hist = hist[: mcfg.context_frames]
            continue
        x = assemble_input(mcfg, rgba, ins[:, f], hist, scale, dep[:, f])
        out = model(x)
        # Losses see the encoding times loss_gain (the default encoding puts the log-average at 0.4).
        lg = cfg["loss_gain"]
        # Holes (coverage below 1) weigh 1 + w_hole: they are a small share of
        # the pixels but where the input says nothing.
        wmap = 1 + cfg.get("w_hole", 0.0) * (1 - rgba[:, 3:4].clamp(0, 1))
        out_lin = decode(out, scale, mcfg.log_range)
        if cfg.get("l2_space", "encoded") == "display":
            # The benchmark's space: its PSNR is over sRGB-encoded frames, and
            # the best answer for an uncertain pixel (a hole) in the log
            # encoding is brighter or darker there than the sRGB mean,
            # depending on the frame's exposure scale.
            d = display(out_lin) - display(tgt[:, f])
            l2 = ((d * lg) ** 2 * wmap).mean()
        else:
            l2 = (((out - gt_enc) * lg) ** 2 * wmap).mean()
        pl = patch_loss(out * lg, gt_enc * lg, rng, cfg["patches"])
        loss = loss + l2 * cfg["w_l2"] + pl * cfg["w_patch"]
        parts["l2"] += l2.item()
        parts["patch"] += pl.item()
        if prev_out is not None:
            po, ps, pg = prev_out
            d_prev, d_cur, mv = dep[:, f - 1], dep[:, f], mot[:, f]
            ones = torch.ones_like(rgba[:, 3:4])
            warped, val = reproject_hop(torch.cat([po, pg], 1), ones, d_prev, d_cur, mv)
            w_out = encode(warped[:, :3], scale, mcfg.log_range)
            w_gt = encode(warped[:, 3:], scale, mcfg.log_range)
            consistent = ((w_gt - gt_enc).abs().mean(1, keepdim=True) < 0.02).to(out.dtype) * val
            tl = ((out - w_out).abs() * lg * consistent).sum() / (consistent.sum() * 3 + 1.0)
            loss = loss + tl * cfg["w_temporal"]
            parts["temporal"] += tl.item()
        prev_out = (out_lin, scale, tgt[:, f])
        outs.append(out)
        n_frames += 1
        if batch["temporal"]:
            hist = [(out_lin.detach(), torch.ones_like(rgba[:, 3:4]))] + hist
            hist = hist[: mcfg.context_frames]
    n = max(n_frames, 1)
    return loss / n, {k: v / n for k, v in parts.items()}, outs


# ---------------------------------------------------------------------------
# Checkpoints


def save_checkpoint(path: Path, model, opt, step: int, cfg: dict, seconds: float = 0.0) -> None:
    """Writes the checkpoint atomically; ``seconds``: training time so far, over all resumptions."""
    tmp = path.with_suffix(".tmp")
    torch.save(
        {
            "model": model.state_dict(),
            "opt": opt.state_dict(),
            "step": step,
            "seconds": seconds,
            "cfg": cfg,
            "model_cfg": model.cfg.to_dict(),
        },
        tmp,
    )
    os.replace(tmp, path)


def load_checkpoint(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False)


def add_args(ap: argparse.ArgumentParser) -> None:
    ap.add_argument("--data", type=Path, default=TRAINING_DIR / "data")
    ap.add_argument("--run", type=Path, default=TRAINING_DIR / "runs" / "main", help="checkpoints and log")
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--crop", type=int, nargs=2, default=[128, 128], metavar=("H", "W"))
    ap.add_argument("--unroll", type=int, default=3, help="frames per window trained with gradients")
    ap.add_argument("--lr", type=float, default=7e-4)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--clip", type=float, default=0.5, help="gradient norm clip")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--device",
        default="cpu",
        help="torch device of the network and losses (cpu, cuda); batches are made on the CPU",
    )
    ap.add_argument("--widths", type=int, nargs="+", default=[16, 32, 48, 64])
    ap.add_argument("--stem", type=int, default=24, help="1x1 stem width (0: none)")
    ap.add_argument("--enc-convs", type=int, default=2)
    ap.add_argument("--dec-convs", type=int, default=2)
    ap.add_argument("--skip", choices=("add", "cat"), default="add")
    ap.add_argument("--no-prior", action="store_true", help="plain residual UNet, no in-graph prior")
    ap.add_argument("--prior-fill", choices=("chain", "mean"), default="chain", help="how the prior fills holes")
    ap.add_argument(
        "--init",
        type=Path,
        help="start from this checkpoint's weights and architecture (fine-tuning; --prior-fill still applies)",
    )
    ap.add_argument(
        "--init-onnx",
        type=Path,
        help="start from the weights of an exported model (its .json beside it), e.g. core/models/default.onnx",
    )
    ap.add_argument(
        "--history-blend",
        action="store_true",
        help="add the learned history blend (ModelConfig.history_blend) to the model started from",
    )
    ap.add_argument(
        "--fresh-blend",
        action="store_true",
        help="with --init: the history blend starts from its initialization (the rest from the checkpoint)",
    )
    ap.add_argument(
        "--graph-margin",
        type=int,
        default=None,
        help="in-graph repair margin in px (ModelConfig.graph_margin; 0: none; default: the --init/--init-onnx "
        "model's, else none)",
    )
    ap.add_argument(
        "--hole-correction",
        type=float,
        default=None,
        help="the share of the correction applied in holes while training (ModelConfig.hole_correction; "
        "at 0 the network gets no gradient from hole pixels; default: the --init/--init-onnx model's)",
    )
    ap.add_argument(
        "--train-only",
        choices=("all", "blend"),
        default="all",
        help="blend: only the history blend learns; the rest keeps the weights it started from",
    )
    ap.add_argument(
        "--prior-depth-tol",
        type=float,
        default=None,
        help="the prior's depth-aware push-pull (ModelConfig.prior_depth_tol; 0: off; default: off, "
        "or the --init checkpoint's)",
    )
    ap.add_argument(
        "--streams",
        default="",
        help="comma-separated streams to train on (e.g. s1_recon); default: every stream of a scene",
    )
    ap.add_argument("--rescan-every", type=int, default=200, help="pick up newly rendered scenes every N steps")
    ap.add_argument("--context-frames", type=int, default=4)
    ap.add_argument("--p-no-history", type=float, default=0.3, help="share of non-temporal batches")
    ap.add_argument(
        "--p-full-prefill",
        type=float,
        default=0.7,
        help="share of temporal batches whose history starts full (K frames before the window); else 0..K",
    )
    ap.add_argument("--p-drop-insert", type=float, default=0.2)
    ap.add_argument("--p-flicker", type=float, default=0.25, help="share of items with per-frame exposure flicker")
    ap.add_argument(
        "--p-self-prefill",
        type=float,
        default=0.5,
        help="share of windows whose history frames come from the model itself (else near-truth frames)",
    )
    ap.add_argument("--patches", type=int, default=4)
    ap.add_argument("--loss-gain", type=float, default=1.0, help="encoded color is scaled by this in the losses")
    ap.add_argument("--w-l2", type=float, default=1.0)
    ap.add_argument("--w-patch", type=float, default=0.2)
    ap.add_argument("--w-temporal", type=float, default=0.5)
    ap.add_argument("--w-hole", type=float, default=2.0, help="extra L2 weight in holes (coverage 0)")
    ap.add_argument(
        "--l2-space",
        choices=("encoded", "display"),
        default="encoded",
        help="where the L2 loss compares: the network's log encoding, or sRGB-encoded frames (the benchmark's PSNR)",
    )
    ap.add_argument(
        "--workers",
        type=int,
        default=0,
        help="processes that make batches ahead (the scene list is then read once, at the start); "
        "0: batches are made in the training loop",
    )
    ap.add_argument(
        "--time-limit",
        type=float,
        default=0.0,
        help="seconds of training over all resumptions: the learning-rate schedule also follows the time and "
        "training ends when it is up (a checkpoint is written; the steps reached then depend on the machine)",
    )
    ap.add_argument(
        "--stop-after",
        type=float,
        default=0.0,
        help="seconds: end this run with a checkpoint after this long; rerunning continues the same schedule",
    )
    ap.add_argument(
        "--redegrade",
        type=int,
        default=1,
        help="variants of each scene's reconstruction stream drawn from: the stored one and N-1 made again from "
        "its context views with other seeds (scenes that kept them, ctx.npz); each is made once per cache stay",
    )
    ap.add_argument("--cache-samples", type=int, default=64, help="(scene, stream) samples kept in memory")
    ap.add_argument("--ckpt-every", type=int, default=200)
    ap.add_argument("--log-every", type=int, default=20)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_args(ap)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    scenes = list_scenes(args.data, "train")
    if not scenes:
        print(
            f"train: no complete scene under {args.data / 'train'} (render some with training.synth.generate)",
            file=sys.stderr,
        )
        return 2
    args.run.mkdir(parents=True, exist_ok=True)
    cfg = {
        "batch": args.batch,
        "crop": list(args.crop),
        "unroll": args.unroll,
        "context_frames": args.context_frames,
        "p_no_history": args.p_no_history,
        "p_full_prefill": args.p_full_prefill,
        "p_drop_insert": args.p_drop_insert,
        "p_flicker": args.p_flicker,
        "p_self_prefill": args.p_self_prefill,
        "patches": args.patches,
        "loss_gain": args.loss_gain,
        "w_l2": args.w_l2,
        "w_patch": args.w_patch,
        "w_temporal": args.w_temporal,
        "w_hole": args.w_hole,
        "l2_space": args.l2_space,
        "lr": args.lr,
        "seed": args.seed,
        "train_only": args.train_only,
        "streams": args.streams,
        "redegrade": args.redegrade,
    }
    ckpt_path = args.run / "ckpt_last.pt"
    torch.manual_seed(args.seed)
    step = 0
    seconds_before = 0.0
    ck = None
    # ModelConfig changes from the command line, applied however the model
    # starts (a fresh one, --init, --init-onnx); a resumed run keeps its own.
    given = {
        "graph_margin": args.graph_margin,
        "prior_depth_tol": args.prior_depth_tol,
        "hole_correction": args.hole_correction,
    }
    changes = {k: v for k, v in given.items() if v is not None}
    if ckpt_path.exists():
        ck = load_checkpoint(ckpt_path)
        mcfg = ModelConfig.from_dict(ck["model_cfg"])
        model = Enhancer(mcfg)
        model.load_state_dict(ck["model"])
        step = ck["step"]
        seconds_before = float(ck.get("seconds", 0.0))
        cfg = {**ck["cfg"], **{k: cfg[k] for k in ("lr",)}}
        print(f"train: resumed {ckpt_path} at step {step}", flush=True)
    elif args.init:
        init = load_checkpoint(args.init)
        mcfg = ModelConfig.from_dict({**init["model_cfg"], "prior_fill": args.prior_fill, **changes})
        weights = init["model"]
        if args.fresh_blend:
            # The rest of the weights, with a history blend from its initialization.
            mcfg.history_blend = True
            mcfg.blend_width = ModelConfig.blend_width
            weights = {k: v for k, v in weights.items() if not k.startswith("blend.")}
        model = Enhancer(mcfg)
        if args.fresh_blend:
            weights |= {k: v for k, v in model.state_dict().items() if k.startswith("blend.")}
        from training.export import drop_blend_beta

        model.load_state_dict(drop_blend_beta(weights, model))
        cfg["init"] = str(args.init)
        print(f"train: starting from the weights of {args.init} (step {init['step']})", flush=True)
    elif args.init_onnx:
        from training.export import weights_from_onnx

        blend = {"history_blend": True} if args.history_blend else {}
        model = weights_from_onnx(args.init_onnx, **changes, **blend)
        mcfg = model.cfg
        cfg["init"] = str(args.init_onnx)
        print(f"train: starting from the weights of {args.init_onnx}", flush=True)
    else:
        mcfg = ModelConfig(
            context_frames=args.context_frames,
            widths=tuple(args.widths),
            stem=args.stem,
            enc_convs=args.enc_convs,
            dec_convs=args.dec_convs,
            skip=args.skip,
            prior=not args.no_prior,
            prior_fill=args.prior_fill,
            **changes,
        )
        model = Enhancer(mcfg)
    device = torch.device(args.device)
    if device.type == "cuda":
        # Few distinct shapes (the crop and the patch sizes): let cuDNN pick its kernels.
        torch.backends.cudnn.benchmark = True
    model.to(device)
    if cfg.get("train_only", "all") == "blend":
        if model.blend is None:
            print("train: --train-only blend needs a model with a history blend (--history-blend)", file=sys.stderr)
            return 2
        for name, prm in model.named_parameters():
            prm.requires_grad_(name.startswith("blend."))
    # Made after the move, so a resumed optimizer state lands on the parameters' device.
    opt = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=args.lr)
    if ck is not None:
        opt.load_state_dict(ck["opt"])
    cache = SampleCache(
        scenes,
        args.cache_samples,
        tuple(n for n in cfg.get("streams", "").split(",") if n),
        cfg.get("redegrade", 1),
        cfg["seed"],
    )
    if not cache.scenes:
        print(f"train: no training scene has the streams {cfg['streams']}", file=sys.stderr)
        return 2
    log = open(args.run / "train.log", "a")
    t0 = time.time()
    model.train()
    batches = None
    if args.workers > 0:
        # Batch i is made from (seed, i) alone, so workers give the same batches in the same order.
        loader = torch.utils.data.DataLoader(
            Batches(cache, cfg, mcfg.key, step, args.steps),
            batch_size=None,
            num_workers=args.workers,
            prefetch_factor=4,
            persistent_workers=False,
        )
        batches = iter(loader)
    while step < args.steps:
        if batches is None and args.rescan_every > 0 and step % args.rescan_every == 0:
            found = list_scenes(args.data, "train")
            if len(found) != len(cache.scenes):
                cache.rescan(found)
                print(f"train: {len(cache.scenes)} training scenes", flush=True)
        torch.manual_seed(cfg["seed"] * 1_000_003 + step)
        if batches is None:
            batch = make_batch(cache, batch_rng(cfg["seed"], step), cfg, mcfg.key)
        else:
            batch = next(batches)
        rng = np.random.default_rng([cfg["seed"], step, 1])
        batch = {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
        # Cosine learning rate with a short warm-up, over the steps or, with
        # --time-limit, over whichever of steps and time runs out first.
        progress = step / max(args.steps, 1)
        if args.time_limit > 0:
            progress = max(progress, (seconds_before + time.time() - t0) / args.time_limit)
            if progress >= 1.0:
                print(f"train: time limit of {args.time_limit:.0f} s reached at step {step}", flush=True)
                break
        if args.stop_after > 0 and time.time() - t0 >= args.stop_after:
            print(f"train: stopping after {args.stop_after:.0f} s at step {step} (rerun to continue)", flush=True)
            break
        warmup = max(1, min(200, args.steps // 10))
        lr = cfg["lr"] * min(1.0, (step + 1) / warmup) * 0.5 * (1 + math.cos(math.pi * min(progress, 1.0)))
        for gparam in opt.param_groups:
            gparam["lr"] = lr
        loss, parts, _ = run_window(model, batch, cfg, rng)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_([p for p in model.parameters() if p.requires_grad], args.clip)
        opt.step()
        step += 1
        loss_value = loss.item()
        if not math.isfinite(loss_value):
            print(f"train: loss is {loss_value} at step {step}; stopping", file=sys.stderr)
            return 1
        if step % args.log_every == 0 or step == args.steps:
            rec = {"step": step, "loss": loss_value, **parts, "lr": lr, "sec": round(time.time() - t0, 1)}
            print("train: " + json.dumps(rec), flush=True)
            log.write(json.dumps(rec) + "\n")
            log.flush()
        if step % args.ckpt_every == 0 or step == args.steps:
            save_checkpoint(ckpt_path, model, opt, step, cfg, seconds_before + time.time() - t0)
    save_checkpoint(ckpt_path, model, opt, step, cfg, seconds_before + time.time() - t0)
    print(f"train: done at step {step}; checkpoint {ckpt_path}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
