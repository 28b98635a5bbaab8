"""Reference for the denoise stage's temporal accumulation (numpy), measured on the out-of-domain set.

    .venv-quality/bin/python -m training.experiments.temporal_denoise

OIDN per frame (as the session's stage runs it), then the previous output
reprojected with the renderer's motion vectors, sampled with Catmull-Rom
(bilinear blurs: each frame resamples the history once more), clipped to the
mean +- ``gamma`` standard deviations of the current frame's 3x3 neighbourhood
in YCoCg of log1p(colour) (variance clipping), and blended with weight
``alpha`` on the current frame; no history where the depth disagrees by more
than 10 % or the position leaves the frame.

Printed: PSNR and warping error (x 1000, as ``training/quality.py``) for
``noisy_raw`` (input: OIDN per frame) and ``noisy_denoised`` (input: the
Cycles-denoised frames) with bilinear and Catmull-Rom history. Measured on
this 2-core machine: ``noisy_raw`` OIDN 33.62 dB / 2.09, Catmull-Rom alpha 0.5
gamma 2: 34.21 dB / 0.85; ``noisy_denoised`` input 34.26 / 1.95, the same
settings 34.64 / 0.83. Bilinear history with the same settings gave 0.3 dB less
(33.90 and 34.33 dB), and 0.5-0.6 dB less at alpha 0.3.
"""

from __future__ import annotations

import numpy as np

from training import quality as q
from training.ood import sequences as ood
from training.synth.degrade import box_blur, warp_bilinear


def ycocg(x: np.ndarray) -> np.ndarray:
    r, g, b = x[..., 0], x[..., 1], x[..., 2]
    return np.stack([0.25 * r + 0.5 * g + 0.25 * b, 0.5 * r - 0.5 * b, -0.25 * r + 0.5 * g - 0.25 * b], -1)


def from_ycocg(y: np.ndarray) -> np.ndarray:
    t = y[..., 0] - y[..., 2]
    return np.stack([t + y[..., 1], y[..., 0] + y[..., 2], t - y[..., 1]], -1)


def catmull_rom(t: np.ndarray) -> list[np.ndarray]:
    t2, t3 = t * t, t * t * t
    return [-0.5 * t3 + t2 - 0.5 * t, 1.5 * t3 - 2.5 * t2 + 1, -1.5 * t3 + 2 * t2 + 0.5 * t, 0.5 * t3 - 0.5 * t2]


def warp_cubic(prev: np.ndarray, motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``prev`` sampled at pixel + motion (pixel centres at integers here, as ``warp_bilinear``)."""
    h, w = prev.shape[:2]
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    sx, sy = xx + motion[..., 0], yy + motion[..., 1]
    x0, y0 = np.floor(sx).astype(int), np.floor(sy).astype(int)
    wx, wy = catmull_rom(sx - x0), catmull_rom(sy - y0)
    out = np.zeros_like(prev)
    for j in range(4):
        yi = np.clip(y0 - 1 + j, 0, h - 1)
        for i in range(4):
            xi = np.clip(x0 - 1 + i, 0, w - 1)
            out += (wx[i] * wy[j])[..., None] * prev[yi, xi]
    inside = (sx >= 0) & (sx <= w - 1) & (sy >= 0) & (sy <= h - 1)
    return out, inside.astype(np.float32)


def accumulate(frames: list[np.ndarray], s: dict, alpha: float, gamma: float, cubic: bool) -> list[np.ndarray]:
    out = [frames[0]]
    for t in range(1, len(frames)):
        prev, inside = (warp_cubic if cubic else warp_bilinear)(out[-1], s["motion"][t])
        dprev, _ = warp_bilinear(s["depth"][t - 1][..., None], s["motion"][t])
        d = s["depth"][t]
        ok = (inside > 0.999) & (np.abs(dprev[..., 0] - d) <= 0.1 * np.minimum(dprev[..., 0], d))
        c = ycocg(np.log1p(np.maximum(frames[t], 0.0)))
        hist = ycocg(np.log1p(np.maximum(prev, 0.0)))
        m, m2 = box_blur(c, 1), box_blur(c * c, 1)
        sd = np.sqrt(np.maximum(m2 - m * m, 0.0))
        hist = np.clip(hist, m - gamma * sd, m + gamma * sd)
        wgt = np.where(ok, alpha, 1.0)[..., None]
        out.append(np.expm1(from_ycocg(wgt * c + (1 - wgt) * hist)).astype(np.float32))
    return out


def score(outs: list[np.ndarray], s: dict) -> tuple[float, float]:
    rows = q.frame_metrics(outs, s)
    return float(np.mean([r["psnr"] for r in rows])), 1000 * float(np.mean([r["warp_err"] for r in rows[1:]]))


def main() -> None:
    for name in ("noisy_raw", "noisy_denoised"):
        s = ood.build(name)
        T = s["frames"]
        if name == "noisy_raw":
            base = [q.oidn(s["input"][t], s["albedo"][t], s["aux_normal"][t]) for t in range(T)]
        else:
            base = [s["input"][t, ..., :3] for t in range(T)]
        print(f"{name}: per frame {score(base, s)[0]:.2f} dB / {score(base, s)[1]:.3f}")
        for cubic in (False, True):
            for alpha in (0.3, 0.5):
                for gamma in (1.0, 2.0):
                    p, w = score(accumulate(base, s, alpha, gamma, cubic), s)
                    kind = "catmull-rom" if cubic else "bilinear"
                    print(f"  {kind:11s} alpha {alpha} gamma {gamma}: {p:.2f} dB / {w:.3f}")


if __name__ == "__main__":
    main()
