"""The quality benchmark: harmonizer against the peers a user would pick instead.

    scripts/quality.sh [--quick]          # sets up, builds, runs this, writes out/quality/
    .venv-quality/bin/python -m training.quality --out out/quality [--quick] [--sets ood,in_domain]

Sets:

- ``ood`` (out of domain, first): ``training/ood/`` renders (assets, light and
  camera motion never used in training; ``training/ood/sequences.py`` lists the
  ten sequences), 24 frames at 320x180;
- ``in_domain``: the training generator's held-out scenes, every stream:
  ``training/data/test`` when they are rendered there (ids 9, 19, 29:
  ``scripts/quality.sh --render-in-domain``), else scene 9, committed in
  ``training/heldout/test``.

Methods, all on the same inputs:

- ``identity``: the input itself;
- ``telea``, ``navier_stokes``: OpenCV inpainting per frame of the holes
  (coverage < 0.5), each channel in 16 bits on ``x ** (1/2.2)`` scaled to the
  frame's maximum (HDR kept), radius 3;
  on sequences without holes they return the input;
- ``oidn``: Intel Open Image Denoise per frame (``pyoidn``; HDR, quality high;
  with the render's noisy albedo and normal where the set has them, taken as
  noisy: one filter run with ``cleanAux`` off, as ``pyoidn.denoise`` runs it);
- ``oidn_prefiltered``: the same with the albedo and normal denoised first
  by their own RT filters and the color filtered with ``cleanAux`` on, as
  OIDN's documentation recommends for noisy auxiliary images (three runs);
- ``ema``: a reprojected exponential moving average of the input (alpha 0.2),
  history taken where the renderer's motion vectors land inside the frame on
  a surface whose depth agrees within 10 %;
- ``oidn_ema``: OIDN, then that average;
- ``classical``, ``neural``, ``neural_k0``, ``neural_nostab``: ``harmonize run``
  (given the same AOVs as the peers: the noisy render's albedo and denoising
  normal where the set has them; the session's defaults otherwise, so
  ``denoise auto``) with
  ``--backend classical``, ``--backend neural`` (the embedded model, K from its
  manifest, which is what ``--backend auto`` runs), the same with
  ``--context 0`` (no history, hence no stabilization either) and with
  ``--set stabilize=false`` (the network alone with its history: against
  ``neural_k0`` it is the network's own use of its temporal context);
- ``classical_tone``: ``--backend classical --set match_tone=true``, the
  inserts' appearance filter that is off by default, kept in view so what
  it does is measured on every run (``docs/inserts.md``).

Metrics on display-encoded values (sRGB transfer of the scene-linear color,
clipped to [0, 1]): PSNR and SSIM (7x7 box window) over the frame and in the
sequence's region (holes: input coverage < 0.5; insert: mask > 0.5; shadow:
where the insert darkens its surroundings, > 0.5); warping error after Lai et
al. 2018: the squared RGB difference between a frame and the previous output
warped by the clean render's motion vectors, averaged over pixels that are not
occluded (the warped previous surface's depth within 10 % of the current one),
then over frames; ``truth`` is the clean render's own warping error (the
floor: what real motion and lighting changes leave). Seconds per frame: the
processing alone (harmonize's ``process_ms``; the peers' call), not file I/O.
On hole sequences also the holes' PSNR by when their surface was last covered
(``hole_ages``: a frame ago, 2-3, 4 or more, never), pooled over the
sequence: where the history helps and where only a spatial fill can.

Writes ``metrics.json`` (every number, per sequence and method, plus per
frame), ``report.md`` (tables), ``per_frame_<set>.png`` and ``strips/<seq>.png``.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from training.evaluate import psnr, read_rgb, srgb, ssim_map
from training.ood import sequences as ood
from training.synth.degrade import warp_bilinear

REPO = Path(__file__).resolve().parent.parent
PEERS = ("identity", "telea", "navier_stokes", "oidn", "oidn_prefiltered", "ema", "oidn_ema")
OURS = {
    "classical": ["--backend", "classical"],
    "neural": ["--backend", "neural"],
    "neural_k0": ["--backend", "neural", "--context", "0"],
    "neural_nostab": ["--backend", "neural", "--set", "stabilize=false"],
    "classical_tone": ["--backend", "classical", "--set", "match_tone=true"],
}
METHODS = PEERS + tuple(OURS)
IN_DOMAIN_REGION = {
    "s1_recon": "hole",
    "s2_tone": "insert",
    "s3_relight": "insert",
    "s4_shadow": "shadow",
    "s5_noise": None,
    "s6_insert": "insert",
}
EMA_ALPHA = 0.2


# ---------------------------------------------------------------------------
# Metrics


def occlusion_mask(gt_depth: np.ndarray, gt_motion: np.ndarray, t: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of frame t whose surface was visible at t-1 (inside the frame, depth within 10 %)."""
    dprev, valid = warp_bilinear(gt_depth[t - 1][..., None], gt_motion[t])
    d = gt_depth[t]
    ok = (valid > 0.999) & (np.abs(dprev[..., 0] - d) <= 0.1 * np.minimum(dprev[..., 0], d)) & (d < 1e9)
    return ok, valid


def warp_error(frames_srgb: list[np.ndarray], s: dict) -> list[float | None]:
    out: list[float | None] = [None]
    for t in range(1, len(frames_srgb)):
        ok, _ = occlusion_mask(s["gt_depth"], s["gt_motion"], t)
        aligned, _ = warp_bilinear(frames_srgb[t - 1], s["gt_motion"][t])
        e = ((frames_srgb[t] - aligned) ** 2).sum(-1)
        out.append(float(e[ok].mean()) if ok.sum() >= 16 else None)
    return out


# A hole pixel's age: how many frames ago its surface was last covered in the
# input (1: the previous frame), followed back along the true motion, the
# chain broken where the surface was hidden (``occlusion_mask``); never
# covered since the sequence began: ``AGE_NEVER``. Where the surface was seen
# a frame ago the history has it; the longer ago, the more the history is its
# own earlier fills; never seen, only a spatial fill (or an older fill) has
# anything to give.
AGE_NEVER = 1 << 20
AGE_BUCKETS = (("1", 1, 1), ("2-3", 2, 3), ("4+", 4, AGE_NEVER - 1), ("never", AGE_NEVER, AGE_NEVER))


def hole_ages(s: dict) -> np.ndarray:
    """Per frame and pixel: 0 where the input covers it (coverage >= 0.5),
    else the frames since its surface was last covered, ``AGE_NEVER`` if
    never (nearest-pixel chain along the true motion)."""
    cov = s["input"][..., 3] >= 0.5
    T, H, W = cov.shape
    yy, xx = np.mgrid[0:H, 0:W]
    ages = np.zeros((T, H, W), np.int64)
    ages[0] = np.where(cov[0], 0, AGE_NEVER)
    for t in range(1, T):
        ok, _ = occlusion_mask(s["gt_depth"], s["gt_motion"], t)
        mv = s["gt_motion"][t]
        px = np.clip(np.round(xx + mv[..., 0]).astype(np.int64), 0, W - 1)
        py = np.clip(np.round(yy + mv[..., 1]).astype(np.int64), 0, H - 1)
        prev = ages[t - 1][py, px]
        carried = np.where(ok & (prev < AGE_NEVER), prev + 1, AGE_NEVER)
        ages[t] = np.where(cov[t], 0, carried)
    return ages


def regions(s: dict, t: int) -> dict[str, np.ndarray]:
    return {
        "hole": s["input"][t, ..., 3] < 0.5,
        "insert": s["mask_insert"][t] > 0.5,
        "shadow": s["mask_shadow"][t] > 0.5,
    }


def frame_metrics(outs: list[np.ndarray], s: dict, ages: np.ndarray | None = None) -> list[dict]:
    """Per frame: PSNR, SSIM, warping error, the region's; on a hole
    sequence the squared error per hole age (``ages``: ``hole_ages(s)``,
    computed here when not given; one sequence's methods share it)."""
    tgt = [srgb(x) for x in s["target"]]
    enc = [srgb(x) for x in outs]
    warp = warp_error(enc, s)
    if ages is None and s.get("region") == "hole":
        ages = hole_ages(s)
    rows = []
    for t in range(len(outs)):
        sm = ssim_map(enc[t], tgt[t]).mean(-1)
        m: dict = {"psnr": psnr(enc[t], tgt[t]), "ssim": float(sm.mean()), "warp_err": warp[t]}
        reg = s.get("region")
        if reg:
            mask = regions(s, t)[reg]
            m["psnr_region"] = psnr(enc[t], tgt[t], mask)
            m["ssim_region"] = float(sm[mask].mean()) if mask.sum() >= 16 else None
        if ages is not None:
            # Squared error summed over each age's hole pixels and their count,
            # pooled over the sequence by ``age_psnr`` (a frame's share of one
            # age is often a few pixels).
            se = ((enc[t] - tgt[t]) ** 2).mean(-1)
            m["hole_age_se"] = {}
            for name, lo, hi in AGE_BUCKETS:
                sel = (ages[t] >= lo) & (ages[t] <= hi)
                m["hole_age_se"][name] = [float(se[sel].sum()), int(sel.sum())]
        rows.append(m)
    return rows


# ---------------------------------------------------------------------------
# Peers


def _unpremultiply(inp: np.ndarray) -> np.ndarray:
    a = inp[..., 3:4]
    return np.where(a > 1e-4, inp[..., :3] / np.maximum(a, 1e-4), 0.0).astype(np.float32)


def inpaint(inp: np.ndarray, method: str) -> np.ndarray:
    import cv2

    holes = inp[..., 3] < 0.5
    rgb = _unpremultiply(inp)
    if not holes.any():
        return inp[..., :3].copy()
    flag = cv2.INPAINT_TELEA if method == "telea" else cv2.INPAINT_NS
    # 16-bit per channel (OpenCV's float path does not interpolate) on x ** (1/2.2), HDR kept by the scale.
    enc = np.power(np.maximum(rgb, 0.0), 1 / 2.2)
    top = max(float(enc[~holes].max()) if (~holes).any() else 1.0, 1e-6)
    q = np.round(np.clip(enc / top, 0.0, 1.0) * 65535).astype(np.uint16)
    mask = holes.astype(np.uint8) * 255
    out = np.stack([cv2.inpaint(np.ascontiguousarray(q[..., c]), mask, 3, flag) for c in range(3)], -1)
    return np.power(out.astype(np.float32) / 65535 * top, 2.2).astype(np.float32)


def oidn(inp: np.ndarray, albedo: np.ndarray | None, normal: np.ndarray | None) -> np.ndarray:
    import pyoidn

    c = np.ascontiguousarray(np.maximum(inp[..., :3], 0.0), np.float32)
    kw = {}
    if albedo is not None:
        kw["albedo"] = np.ascontiguousarray(np.clip(albedo, 0.0, 1.0), np.float32)
        if normal is not None:
            kw["normal"] = np.ascontiguousarray(np.clip(normal, -1.0, 1.0), np.float32)
    return np.asarray(pyoidn.denoise(c, hdr=True, quality="high", **kw), np.float32)


_PREFILTER: dict = {}


def oidn_prefiltered(inp: np.ndarray, albedo: np.ndarray, normal: np.ndarray | None) -> np.ndarray:
    """OIDN with the albedo and normal prefiltered (each by an RT filter of its own), then ``cleanAux``."""
    import pyoidn

    if "device" not in _PREFILTER:
        dev = pyoidn.Device()
        dev.commit()
        _PREFILTER["device"] = dev
    dev = _PREFILTER["device"]
    f3 = pyoidn.OIDN_FORMAT_FLOAT3

    def run(key: str, images: dict, out: np.ndarray, **opts) -> None:
        # One filter per role, kept across frames (as OIDN's users do: a
        # filter is set up once, committed again only when its images change).
        flt = _PREFILTER.get(key)
        if flt is None:
            flt = pyoidn.Filter(dev, pyoidn.OIDN_FILTER_TYPE_RT)
            for k, v in opts.items():
                flt.set_bool(k, v)
            flt.set_quality(pyoidn.OIDN_QUALITY_HIGH)
            _PREFILTER[key] = flt
        for k, v in images.items():
            flt.set_image(k, v, f3)
        flt.set_image(pyoidn.OIDN_IMAGE_OUTPUT, out, f3)
        flt.commit()
        flt.execute()
        err = dev.get_error()
        if err is not None:
            raise RuntimeError(f"OIDN: {err}")

    c = np.ascontiguousarray(np.maximum(inp[..., :3], 0.0), np.float32)
    a = np.ascontiguousarray(np.clip(albedo, 0.0, 1.0), np.float32)
    a_clean = np.zeros_like(a)
    run("albedo", {pyoidn.OIDN_IMAGE_ALBEDO: a}, a_clean)
    images = {pyoidn.OIDN_IMAGE_COLOR: c, pyoidn.OIDN_IMAGE_ALBEDO: a_clean}
    if normal is not None:
        n = np.ascontiguousarray(np.clip(normal, -1.0, 1.0), np.float32)
        n_clean = np.zeros_like(n)
        run("normal", {pyoidn.OIDN_IMAGE_NORMAL: n}, n_clean)
        images[pyoidn.OIDN_IMAGE_NORMAL] = n_clean
    out = np.zeros_like(c)
    run("color+normal" if normal is not None else "color", images, out, hdr=True, cleanAux=True)
    return out


def ema(frames: list[np.ndarray], s: dict) -> list[np.ndarray]:
    """Reprojected exponential moving average with the host's own motion and depth."""
    out = [frames[0]]
    for t in range(1, len(frames)):
        prev, valid = warp_bilinear(out[-1], s["motion"][t])
        dprev, _ = warp_bilinear(s["depth"][t - 1][..., None], s["motion"][t])
        d = s["depth"][t]
        ok = (valid > 0.999) & (np.abs(dprev[..., 0] - d) <= 0.1 * np.minimum(dprev[..., 0], d))
        out.append(np.where(ok[..., None], EMA_ALPHA * frames[t] + (1 - EMA_ALPHA) * prev, frames[t]))
    return out


def run_peer(name: str, s: dict, cache: dict) -> tuple[list[np.ndarray], float]:
    T = s["frames"]
    inp = s["input"]
    t0 = time.perf_counter()
    if name == "identity":
        outs = [inp[t, ..., :3] for t in range(T)]
    elif name in ("telea", "navier_stokes"):
        outs = [inpaint(inp[t], name) for t in range(T)]
    elif name == "oidn":
        alb, nrm = s.get("albedo"), s.get("aux_normal")
        outs = [oidn(inp[t], None if alb is None else alb[t], None if nrm is None else nrm[t]) for t in range(T)]
        cache["oidn"] = (outs, time.perf_counter() - t0)
    elif name == "oidn_prefiltered":
        alb, nrm = s.get("albedo"), s.get("aux_normal")
        if alb is None:
            # No guides: the same as ``oidn`` (its run and its time).
            if "oidn" not in cache:
                run_peer("oidn", s, cache)
            outs, secs = cache["oidn"]
            t0 = time.perf_counter() - secs
        else:
            outs = [oidn_prefiltered(inp[t], alb[t], None if nrm is None else nrm[t]) for t in range(T)]
    elif name == "ema":
        outs = ema([inp[t, ..., :3] for t in range(T)], s)
    elif name == "oidn_ema":
        if "oidn" not in cache:
            run_peer("oidn", s, cache)
        base, secs = cache["oidn"]
        t0 = time.perf_counter() - secs  # the average runs on OIDN's frames: its time counts
        outs = ema(base, s)
    else:
        raise ValueError(name)
    return outs, (time.perf_counter() - t0) / T


# ---------------------------------------------------------------------------
# harmonize


def write_inputs(s: dict, d: Path) -> None:
    from training.synth.to_exr import frame_channels, write_exr

    d.mkdir(parents=True, exist_ok=True)
    for t in range(s["frames"]):
        write_exr(d / f"input.{t + 1:04d}.exr", *frame_channels(s, t))


def run_ours(exe: Path, in_dir: Path, out_dir: Path, extra: list[str], T: int, threads: int):
    shutil.rmtree(out_dir, ignore_errors=True)
    out_dir.mkdir(parents=True)
    report = out_dir / "report.json"
    cmd = [str(exe), "run", str(in_dir / "input.####.exr"), "-o", str(out_dir / "out.####.exr")]
    cmd += ["--layout", "generic", "--threads", str(threads), "--report", str(report), *extra]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed (exit {p.returncode}): {p.stderr[-2000:]}")
    rep = json.loads(report.read_text())
    ms = [f["process_ms"] for f in rep["frames"]]
    outs = [read_rgb(out_dir / f"out.{t + 1:04d}.exr") for t in range(T)]
    return outs, float(np.mean(ms)) / 1000.0


# ---------------------------------------------------------------------------
# Sets


def ood_sequences(frames: int, only: set[str]):
    cache: dict = {}
    for name in ood.SEQUENCES:
        if only and name not in only:
            continue
        yield name, ood.build(name, cache=cache, frames=frames)


def in_domain_sequences(data: Path, quick: bool, frames: int):
    from training.synth.dataset import list_scenes, load_sample, scene_streams

    scenes = list_scenes(data, "test")
    for scene in scenes[:1] if quick else scenes:
        with np.load(scene / "scene.npz") as z:
            gt_depth = z["depth"].astype(np.float32)
        if frames > 0:
            gt_depth = gt_depth[:frames]
        for stream in scene_streams(scene):
            s = load_sample(scene, stream)
            if frames > 0:
                for k in ("input", "target", "depth", "motion", "normal", "mask_insert", "mask_shadow"):
                    s[k] = s[k][:frames]
                s["world_to_camera"], s["world_to_ndc"] = s["world_to_camera"][:frames], s["world_to_ndc"][:frames]
            s.update(
                name=f"{scene.name}/{stream}",
                gt_depth=gt_depth,
                gt_motion=s["motion"],
                region=IN_DOMAIN_REGION[stream],
                frames=s["input"].shape[0],
                about=stream,
            )
            yield s["name"], s


def evaluate(s: dict, exe: Path, work: Path, threads: int, methods: tuple[str, ...]):
    T = s["frames"]
    results: dict[str, dict] = {}
    shown: dict[str, np.ndarray] = {}
    in_dir = work / "in"
    shutil.rmtree(in_dir, ignore_errors=True)
    if any(m in OURS for m in methods):
        write_inputs(s, in_dir)
    cache: dict = {}
    ages = hole_ages(s) if s.get("region") == "hole" else None
    for m in methods:
        if m in OURS:
            host = [x for k, v in s.get("host_params", {}).items() for x in ("--set", f"{k}={v}")]
            outs, spf = run_ours(exe, in_dir, work / m, OURS[m] + host, T, threads)
        else:
            outs, spf = run_peer(m, s, cache)
        rows = frame_metrics(outs, s, ages)
        results[m] = {"frames": rows, "seconds_per_frame": spf}
        shown[m] = outs[T // 2]
    truth_warp = warp_error([srgb(x) for x in s["target"]], s)
    return results, truth_warp, shown


def mean(vals) -> float | None:
    v = [x for x in vals if x is not None]
    return float(np.mean(v)) if v else None


def summarize(results: dict, truth_warp: list) -> dict:
    out = {}
    for m, r in results.items():
        rows = r["frames"]
        out[m] = {k: mean(x.get(k) for x in rows) for k in ("psnr", "ssim", "psnr_region", "ssim_region", "warp_err")}
        out[m]["seconds_per_frame"] = r["seconds_per_frame"]
        if any("hole_age_se" in x for x in rows):
            out[m]["psnr_age"], out[m]["age_share"] = age_psnr(rows)
    out["truth"] = {"warp_err": mean(truth_warp)}
    return out


def age_psnr(rows: list[dict]) -> tuple[dict, dict]:
    """PSNR per hole age pooled over the frames (the squared error of all
    their pixels of that age), and each age's share of the hole pixels."""
    se = {name: 0.0 for name, _, _ in AGE_BUCKETS}
    n = {name: 0 for name, _, _ in AGE_BUCKETS}
    for x in rows:
        for name, (e, c) in x.get("hole_age_se", {}).items():
            se[name] += e
            n[name] += c
    total = max(sum(n.values()), 1)
    out = {k: (float(10 * np.log10(1.0 / max(se[k] / n[k], 1e-12))) if n[k] >= 16 else None) for k in se}
    return out, {k: n[k] / total for k in n}


INPAINTING_PEERS = ("telea", "navier_stokes")


def hole_margins(summary: dict, regions: dict) -> list[dict]:
    """Per sequence whose region is the holes: ``neural``'s PSNR there (the
    default's) against the best single-frame inpainting peer's (issue 18 asks
    +1 dB on every reconstruction sequence). Empty unless ``neural`` and a
    peer both ran."""
    out = []
    for set_name, rows in summary.items():
        for seq, row in rows.items():
            if regions.get(set_name, {}).get(seq) != "hole":
                continue
            mine = (row.get("neural") or {}).get("psnr_region")
            peers = {p: (row.get(p) or {}).get("psnr_region") for p in INPAINTING_PEERS}
            peers = {p: v for p, v in peers.items() if v is not None}
            if mine is None or not peers:
                continue
            best = max(peers, key=peers.get)
            out.append(
                {
                    "set": set_name,
                    "sequence": seq,
                    "neural": mine,
                    "peer": best,
                    "peer_psnr": peers[best],
                    "margin": mine - peers[best],
                }
            )
    return out


# ---------------------------------------------------------------------------
# Report


def fmt(v, digits=2) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def table(set_rows: dict, key: str, methods: tuple[str, ...], digits: int, extra_truth: bool = False) -> list[str]:
    cols = list(methods) + (["truth"] if extra_truth else [])
    lines = ["| sequence | " + " | ".join(cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for seq, summ in set_rows.items():
        vals = [summ.get(c, {}).get(key) for c in cols]
        cand = [fmt(v, digits) for v, c in zip(vals, cols, strict=True) if v is not None and c != "truth"]
        best = None
        if len(set(cand)) > 1:
            num = [float(x) for x in cand]
            best = fmt(min(num) if key in ("warp_err", "seconds_per_frame") else max(num), digits)
        cells = [
            f"**{fmt(v, digits)}**" if c != "truth" and fmt(v, digits) == best else fmt(v, digits)
            for v, c in zip(vals, cols, strict=True)
        ]
        lines.append(f"| {seq} | " + " | ".join(cells) + " |")
    return lines


def write_report(out: Path, summary: dict, info: dict, methods: tuple[str, ...]) -> None:
    L = [
        "# Quality benchmark",
        "",
        f"Command: `{info['command']}`. Machine: {info['machine']}. Total {info['seconds']:.0f} s.",
        "PSNR/SSIM on sRGB-encoded color clipped to [0, 1] against the clean render; warping error after",
        "Lai et al. (squared RGB difference to the previous output warped by the true motion, non-occluded",
        "pixels; `truth` is the clean render's own, the floor). Best value per row in bold.",
        "`neural` is what `--backend auto` (the default) runs with the embedded model.",
        "",
    ]
    for set_name, rows in summary.items():
        if not rows:
            continue
        title = "Out of domain" if set_name == "ood" else "In domain (the training generator's held-out scenes)"
        L += [f"## {title}", ""]
        if set_name == "ood":
            L += ["| sequence | region | what |", "|---|---|---|"]
            for seq, about in info["about"][set_name].items():
                L.append(f"| {seq} | {info['region'][set_name][seq] or '-'} | {about} |")
            L.append("")
        for key, label, digits, tr in (
            ("psnr", "PSNR over the frame (dB)", 2, False),
            ("psnr_region", "PSNR in the degraded region (dB; holes, insert or shadow, see above)", 2, False),
            ("ssim", "SSIM over the frame", 4, False),
            ("warp_err", "Warping error (x 1000, lower is steadier)", 3, True),
            ("seconds_per_frame", "Seconds per frame (processing only)", 4, False),
        ):
            rr = rows
            if key == "warp_err":
                rr = {
                    s: {
                        m: {"warp_err": None if v.get("warp_err") is None else 1000 * v["warp_err"]}
                        for m, v in r.items()
                    }
                    for s, r in rows.items()
                }
            if key == "psnr_region":
                rr = {s: r for s, r in rows.items() if any(v.get("psnr_region") is not None for v in r.values())}
            L += [f"### {label}", ""] + table(rr, key, methods, digits, tr) + [""]
    margins = hole_margins(summary, info["region"])
    if margins:
        ahead = sum(m["margin"] >= 1.0 for m in margins)
        L += [
            "## Holes against the best inpainting peer",
            "",
            f"`neural` at least 1 dB above the better of Telea and Navier-Stokes in the holes: {ahead} of "
            f"{len(margins)} sequences.",
            "",
            "| set | sequence | neural | best peer | margin (dB) |",
            "|---|---|---|---|---|",
        ]
        for m in margins:
            L.append(
                f"| {m['set']} | {m['sequence']} | {fmt(m['neural'])} | {m['peer']} {fmt(m['peer_psnr'])} | "
                f"{m['margin']:+.2f} |"
            )
        L.append("")
    L += age_table(summary, methods)
    (out / "report.md").write_text("\n".join(L) + "\n")


def age_table(summary: dict, methods: tuple[str, ...]) -> list[str]:
    """The holes' PSNR by how long ago their surface was last seen
    (``hole_ages``): history against spatial fill, where each wins."""
    rows = [(st, seq, row) for st, seqs in summary.items() for seq, row in seqs.items()]
    rows = [(st, seq, row) for st, seq, row in rows if any("psnr_age" in (row.get(m) or {}) for m in methods)]
    if not rows:
        return []
    cols = [m for m in methods if any("psnr_age" in (row.get(m) or {}) for _, _, row in rows)]
    L = [
        "## Holes by when their surface was last seen",
        "",
        "PSNR (dB) over the hole pixels whose surface the input last covered 1, 2-3 or 4 or more frames",
        "before (followed along the true motion, broken where it was hidden), or never, pooled over the",
        "sequence; the share is of the sequence's hole pixels. Seen a frame ago the history has the",
        "surface; never seen, only a spatial fill has anything to give.",
        "",
        "| set | sequence | last seen | share | " + " | ".join(cols) + " |",
        "|---" * (len(cols) + 4) + "|",
    ]
    for st, seq, row in rows:
        share = next(row[m]["age_share"] for m in cols if "age_share" in (row.get(m) or {}))
        for name, _, _ in AGE_BUCKETS:
            vals = [(row.get(m) or {}).get("psnr_age", {}).get(name) for m in cols]
            got = [v for v in vals if v is not None]
            best = max(got) if len({fmt(v) for v in got}) > 1 else None
            cells = [
                f"**{fmt(v)}**" if v is not None and best is not None and fmt(v) == fmt(best) else fmt(v) for v in vals
            ]
            L.append(f"| {st} | {seq} | {name} | {100 * share[name]:.1f} % | " + " | ".join(cells) + " |")
    L.append("")
    return L


def write_figures(out: Path, per_frame: dict, shown: dict, methods: tuple[str, ...]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for set_name, seqs in per_frame.items():
        if not seqs:
            continue
        n = len(seqs)
        fig, axes = plt.subplots(n, 2, figsize=(11, 2.2 * n), squeeze=False)
        for i, (seq, res) in enumerate(seqs.items()):
            for j, key in enumerate(("psnr", "warp_err")):
                ax = axes[i, j]
                for m in methods:
                    ys = [r.get(key) for r in res[m]["frames"]]
                    xs = [t for t, y in enumerate(ys) if y is not None]
                    ax.plot(xs, [y for y in ys if y is not None], label=m, lw=1.2)
                if key == "psnr":
                    ax.set_ylim(top=min(ax.get_ylim()[1], 60.0))  # identical frames score 120 dB
                ax.set_title(f"{seq}: {'PSNR (dB)' if key == 'psnr' else 'warping error'}", fontsize=8)
                ax.tick_params(labelsize=7)
        axes[0, 0].legend(fontsize=6, ncol=3)
        fig.tight_layout()
        fig.savefig(out / f"per_frame_{set_name}.png", dpi=80)
        plt.close(fig)
    strips = out / "strips"
    strips.mkdir(exist_ok=True)
    for seq, imgs in shown.items():
        cols = ["input"] + [m for m in methods if m != "identity"] + ["truth"]
        fig, axes = plt.subplots(1, len(cols), figsize=(2.4 * len(cols), 1.8))
        for ax, c in zip(axes, cols, strict=True):
            ax.imshow(srgb(imgs[c]))
            ax.set_title(c, fontsize=8)
            ax.axis("off")
        fig.suptitle(f"{seq} (middle frame)", fontsize=8)
        fig.tight_layout()
        fig.savefig(strips / f"{seq.replace('/', '_')}.png", dpi=80)
        plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=REPO / "out" / "quality")
    ap.add_argument("--quick", action="store_true", help="12 frames per sequence, one in-domain scene")
    ap.add_argument("--frames", type=int, default=0, help="only the first N frames of each sequence")
    ap.add_argument("--sets", default="ood,in_domain")
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--only", default="", help="comma-separated sequence names")
    ap.add_argument(
        "--data",
        type=Path,
        help="in-domain data with a test split (default: training/data when it has held-out scenes, "
        "else the one committed in training/heldout)",
    )
    ap.add_argument("--harmonize", type=Path, default=REPO / "target" / "release" / "harmonize")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        metavar="NAME=ARGS",
        help="one more method: harmonize run with these arguments (e.g. 'noshadow=--backend classical "
        "--set contact_shadows=false'); repeatable",
    )
    args = ap.parse_args(argv)
    for v in args.variant:
        name, sep, rest = v.partition("=")
        if not sep or not name or name in METHODS:
            print(f"quality: --variant wants NAME=ARGS with a new name, got '{v}'", file=sys.stderr)
            return 2
        OURS[name] = rest.split()
    METHODS_ALL = PEERS + tuple(OURS)
    methods = tuple(m for m in args.methods.split(",") if m)
    bad = [m for m in methods if m not in METHODS_ALL]
    if bad:
        print(f"quality: unknown method(s) {bad}; have {', '.join(METHODS_ALL)}", file=sys.stderr)
        return 2
    if any(m in OURS for m in methods) and not args.harmonize.exists():
        print(f"quality: {args.harmonize} not found (cargo build --release -p harmonize-cli)", file=sys.stderr)
        return 2
    t_start = time.time()
    frames = args.frames or (12 if args.quick else 0)
    only = {x for x in args.only.split(",") if x}
    sets = [x for x in args.sets.split(",") if x]
    summary: dict = {}
    per_frame: dict = {}
    shown_all: dict = {}
    info: dict = {"about": {}, "region": {}, "skipped": {}}
    work = Path(tempfile.mkdtemp(prefix="hz-quality."))
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    try:
        for set_name in sets:
            if set_name == "ood":
                gen = ood_sequences(frames, only)
            elif set_name == "in_domain":
                from training.synth.dataset import list_scenes

                if args.data is None:
                    rendered = REPO / "training" / "data"
                    args.data = rendered if list_scenes(rendered, "test") else REPO / "training" / "heldout"
                if not list_scenes(args.data, "test"):
                    msg = (
                        f"no held-out scene in {args.data / 'test'}: render them with "
                        "`scripts/quality.sh --render-in-domain` (Blender, about 5 minutes a scene)"
                    )
                    print(f"quality: in_domain skipped: {msg}", file=sys.stderr)
                    info["skipped"][set_name] = msg
                    continue
                gen = in_domain_sequences(args.data, args.quick, frames)
            else:
                print(f"quality: unknown set '{set_name}' (ood, in_domain)", file=sys.stderr)
                return 2
            summary[set_name], per_frame[set_name] = {}, {}
            info["about"][set_name], info["region"][set_name] = {}, {}
            for name, s in gen:
                if only and name not in only:
                    continue
                t0 = time.time()
                res, truth_warp, shown = evaluate(s, args.harmonize, work, args.threads, methods)
                summary[set_name][name] = summarize(res, truth_warp)
                per_frame[set_name][name] = res
                info["about"][set_name][name] = s.get("about", "")
                info["region"][set_name][name] = s.get("region")
                shown["truth"] = s["target"][s["frames"] // 2]
                shown["input"] = s["input"][s["frames"] // 2, ..., :3]
                shown_all[name] = shown
                row = summary[set_name][name]
                print(
                    f"quality: {set_name}/{name} ({s['frames']} frames, {time.time() - t0:.0f} s): "
                    + ", ".join(f"{m} {fmt(row[m]['psnr'])}" for m in methods),
                    flush=True,
                )
    finally:
        shutil.rmtree(work, ignore_errors=True)
    args.out.mkdir(parents=True, exist_ok=True)
    info["command"] = "scripts/quality.sh " + " ".join(argv if argv is not None else sys.argv[1:])
    info["machine"] = f"{os.cpu_count()} cores, {args.threads} threads"
    info["seconds"] = time.time() - t_start
    (args.out / "metrics.json").write_text(
        json.dumps(
            {
                "methods": list(methods),
                "quick": args.quick,
                "summary": summary,
                "sequences": {k: {"about": info["about"][k], "region": info["region"][k]} for k in info["about"]},
                "skipped": info["skipped"],
                "hole_margins": hole_margins(summary, info["region"]),
                "per_frame": {
                    st: {sq: {m: r["frames"] for m, r in res.items()} for sq, res in seqs.items()}
                    for st, seqs in per_frame.items()
                },
                "seconds": info["seconds"],
            },
            indent=1,
        )
    )
    write_report(args.out, summary, info, methods)
    write_figures(args.out, per_frame, shown_all, methods)
    print(f"quality: wrote {args.out / 'report.md'} and metrics.json ({info['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
