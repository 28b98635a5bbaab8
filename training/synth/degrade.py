"""Degradations that turn clean Cycles renders into training inputs (numpy only).

Every function takes and returns float32 arrays in the library's conventions:
color scene-linear Linear Rec.709, premultiplied by coverage, ``[H, W, C]``;
planar depth ``[H, W]`` with empty pixels at ``EMPTY_DEPTH``; cameras as
OpenEXR row-vector ``worldToCamera`` / ``worldToNDC`` matrices (``p' = [x y z 1] M``,
camera +z forward, NDC (0,0) top-left, (1,1) bottom-right).
"""

from __future__ import annotations

import numpy as np

EMPTY_DEPTH = 1e10
LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec.709 luminance of ``[..., 3]`` linear color."""
    return rgb[..., :3] @ LUMA


# ---------------------------------------------------------------------------
# Cameras


def unproject(depth: np.ndarray, w2c: np.ndarray, w2ndc: np.ndarray) -> np.ndarray:
    """World points ``[H, W, 3]`` of every pixel centre at planar ``depth``."""
    h, w = depth.shape
    c2w = np.linalg.inv(w2c.T.astype(np.float64))  # column form
    cam_to_ndc = w2ndc.T.astype(np.float64) @ c2w
    u = (np.arange(w) + 0.5) / w
    v = (np.arange(h) + 0.5) / h
    u, v = np.meshgrid(u, v)
    d = depth.astype(np.float64)
    r0, r1, r3 = cam_to_ndc[0], cam_to_ndc[1], cam_to_ndc[3]
    a = r0[None, None, :] - u[..., None] * r3[None, None, :]
    b = r1[None, None, :] - v[..., None] * r3[None, None, :]
    ac = -(a[..., 2] * d + a[..., 3])
    bc = -(b[..., 2] * d + b[..., 3])
    det = a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]
    det = np.where(np.abs(det) < 1e-18, 1e-18, det)
    x = (ac * b[..., 1] - a[..., 1] * bc) / det
    y = (a[..., 0] * bc - ac * b[..., 0]) / det
    pc = np.stack([x, y, d, np.ones_like(d)], -1)
    pw = pc @ c2w.T
    return pw[..., :3]


def project(points: np.ndarray, w2c: np.ndarray, w2ndc: np.ndarray, width: int, height: int):
    """Pixel positions (centres at +0.5) and planar depth of world ``points [N, 3]``."""
    p = np.concatenate([points.astype(np.float64), np.ones((len(points), 1))], 1)
    cam = p @ w2c.astype(np.float64)
    ndc = p @ w2ndc.astype(np.float64)
    wz = np.where(np.abs(ndc[:, 3]) < 1e-12, 1e-12, ndc[:, 3])
    x = ndc[:, 0] / wz * width
    y = ndc[:, 1] / wz * height
    return x, y, cam[:, 2]


def camera_motion(depth: np.ndarray, w2c: np.ndarray, w2ndc: np.ndarray) -> np.ndarray:
    """The motion vectors ``[T, H, W, 2]`` (pixels, to the previous frame) of a
    world that stands still while the camera moves: each pixel at its depth
    seen from the previous camera. Frame 0, and pixels the previous camera
    cannot place, get none."""
    t, h, w = depth.shape
    out = np.zeros((t, h, w, 2), np.float32)
    jj, ii = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    for k in range(1, t):
        x, y, _ = project(unproject(depth[k], w2c[k], w2ndc[k]).reshape(-1, 3), w2c[k - 1], w2ndc[k - 1], w, h)
        m = np.stack([x.reshape(h, w) - jj, y.reshape(h, w) - ii], -1)
        out[k] = np.where(np.isfinite(m) & (np.abs(m) < 1e4), m, 0.0)
    return out


def focal_px(w2c: np.ndarray, w2ndc: np.ndarray, width: int) -> float:
    """Horizontal focal length in pixels."""
    cam_to_ndc = w2ndc.T.astype(np.float64) @ np.linalg.inv(w2c.T.astype(np.float64))
    # u = (m00 x + m02 z) / z for a pinhole; du/dx at z=1.
    return float(cam_to_ndc[0, 0] / max(cam_to_ndc[3, 2], 1e-12) * width)


# ---------------------------------------------------------------------------
# Small image helpers


def box_blur(img: np.ndarray, radius: int) -> np.ndarray:
    """Separable box blur with edge clamping (``[H, W]`` or ``[H, W, C]``)."""
    if radius <= 0:
        return img
    out = img.astype(np.float32)
    for axis in (0, 1):
        pad = [(0, 0)] * out.ndim
        pad[axis] = (radius + 1, radius)
        c = np.cumsum(np.pad(out, pad, mode="edge"), axis=axis, dtype=np.float64)
        n = out.shape[axis]
        hi = np.take(c, np.arange(2 * radius + 1, 2 * radius + 1 + n), axis=axis)
        lo = np.take(c, np.arange(0, n), axis=axis)
        out = ((hi - lo) / (2 * radius + 1)).astype(np.float32)
    return out


def smooth_noise(rng: np.random.Generator, h: int, w: int, cell: int) -> np.ndarray:
    """Low-frequency noise in about [-1, 1]: bilinear upsampling of a coarse grid."""
    gh, gw = h // cell + 2, w // cell + 2
    g = rng.standard_normal((gh, gw)).astype(np.float32)
    ys = (np.arange(h) + 0.5) / cell
    xs = (np.arange(w) + 0.5) / cell
    y0 = np.floor(ys).astype(int)
    x0 = np.floor(xs).astype(int)
    fy = (ys - y0)[:, None]
    fx = (xs - x0)[None, :]
    a = g[y0][:, x0]
    b = g[y0][:, x0 + 1]
    c = g[y0 + 1][:, x0]
    d = g[y0 + 1][:, x0 + 1]
    return (a * (1 - fx) * (1 - fy) + b * fx * (1 - fy) + c * (1 - fx) * fy + d * fx * fy).astype(np.float32)


def warp_bilinear(prev: np.ndarray, motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Aligns ``prev`` onto the current frame with library motion vectors.

    ``aligned(i, j) = prev(x = j + 0.5 + mv.x, y = i + 0.5 + mv.y)``, bilinear,
    pixel centres at +0.5. Returns the aligned image and a validity mask
    (1 where the sample lies inside ``prev``).
    """
    h, w = motion.shape[:2]
    jj, ii = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    x = jj + motion[..., 0]  # sample position minus the 0.5 centre offset
    y = ii + motion[..., 1]
    valid = ((x > -0.5) & (x < w - 0.5) & (y > -0.5) & (y < h - 0.5)).astype(np.float32)
    x = np.clip(x, 0, w - 1)
    y = np.clip(y, 0, h - 1)
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx = (x - x0)[..., None] if prev.ndim == 3 else x - x0
    fy = (y - y0)[..., None] if prev.ndim == 3 else y - y0
    p = prev
    out = (
        p[y0, x0] * (1 - fx) * (1 - fy)
        + p[y0, x0 + 1] * fx * (1 - fy)
        + p[y0 + 1, x0] * (1 - fx) * fy
        + p[y0 + 1, x0 + 1] * fx * fy
    )
    return out.astype(np.float32), valid


# ---------------------------------------------------------------------------
# Stream 1: few-view reconstruction re-rendered along a novel trajectory


def noisy_depth(rng: np.random.Generator, depth: np.ndarray, level: float) -> np.ndarray:
    """Depth as a few-view reconstruction or a depth sensor would give it.

    Relative low-frequency bias, per-pixel noise, flying pixels at depth
    discontinuities (snapped to a neighbour's depth) and dropped pixels
    (returned as ``EMPTY_DEPTH``). ``level`` scales everything (about 0.5-2).
    """
    h, w = depth.shape
    d = depth.astype(np.float32).copy()
    finite = d < 1e9
    bias = 1.0 + level * 0.02 * smooth_noise(rng, h, w, 24)
    pix = 1.0 + level * 0.006 * rng.standard_normal((h, w)).astype(np.float32)
    d = np.where(finite, d * bias * pix, d)
    # Flying pixels at discontinuities: take the neighbour across the edge.
    dl = np.log(np.clip(np.where(finite, depth, 1e3), 1e-3, None))
    edge = np.zeros((h, w), bool)
    for axis in (0, 1):
        g = np.abs(np.diff(dl, axis=axis))
        e = g > 0.05
        if axis == 0:
            edge[1:] |= e
            edge[:-1] |= e
        else:
            edge[:, 1:] |= e
            edge[:, :-1] |= e
    flip = edge & (rng.random((h, w)) < 0.5 * min(level, 1.5))
    shift = rng.integers(-2, 3, size=(2, h, w))
    yy = np.clip(np.arange(h)[:, None] + shift[0], 0, h - 1)
    xx = np.clip(np.arange(w)[None, :] + shift[1], 0, w - 1)
    d = np.where(flip, d[yy, xx], d)
    drop = rng.random((h, w)) < 0.01 * level
    drop |= smooth_noise(rng, h, w, 16) > 2.2 - 0.3 * level
    d = np.where(drop, EMPTY_DEPTH, d)
    return d


def splat_points(
    points: np.ndarray,
    colors: np.ndarray,
    radii_src: np.ndarray,
    w2c: np.ndarray,
    w2ndc: np.ndarray,
    width: int,
    height: int,
    depth_tol: float = 0.03,
    max_radius: float = 3.5,
    weight_full: float = 0.35,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Renders colored points as depth-tested Gaussian splats.

    ``radii_src`` is each point's footprint as a world-space radius. Points
    within ``depth_tol`` (relative) of the nearest surface blend, which makes
    ghosting and seams where views disagree. Returns premultiplied RGB
    ``[H, W, 3]``, coverage ``[H, W]`` (0 = hole, soft at borders) and planar
    depth ``[H, W]`` (``EMPTY_DEPTH`` in holes).
    """
    x, y, z = project(points, w2c, w2ndc, width, height)
    f = focal_px(w2c, w2ndc, width)
    ok = (z > 1e-3) & (x > -max_radius) & (x < width + max_radius) & (y > -max_radius) & (y < height + max_radius)
    x, y, z, col = x[ok], y[ok], z[ok], colors[ok]
    r = np.clip(radii_src[ok] * f / z, 0.5, max_radius)
    sigma = np.maximum(r * 0.6, 0.45)
    rmax = int(np.ceil(max_radius))
    npx = width * height
    zbuf = np.full(npx, np.inf)
    cx = np.floor(x).astype(np.int64)
    cy = np.floor(y).astype(np.int64)
    offsets = [(dx, dy) for dy in range(-rmax, rmax + 1) for dx in range(-rmax, rmax + 1)]
    # Pass 1: nearest depth per pixel among splats that reach it.
    hits = []
    for dx, dy in offsets:
        px = cx + dx
        py = cy + dy
        ddx = px + 0.5 - x
        ddy = py + 0.5 - y
        d2 = ddx * ddx + ddy * ddy
        m = (d2 <= (r + 0.5) ** 2) & (px >= 0) & (px < width) & (py >= 0) & (py < height)
        if not m.any():
            continue
        idx = np.nonzero(m)[0]
        pix = py[idx] * width + px[idx]
        wgt = np.exp(-d2[idx] / (2 * sigma[idx] ** 2))
        np.minimum.at(zbuf, pix, z[idx])
        hits.append((idx, pix, wgt))
    acc = np.zeros((npx, 3))
    wsum = np.zeros(npx)
    zsum = np.zeros(npx)
    for idx, pix, wgt in hits:
        front = z[idx] <= zbuf[pix] * (1 + depth_tol)
        idx, pix, wgt = idx[front], pix[front], wgt[front]
        np.add.at(acc, pix, col[idx] * wgt[:, None])
        np.add.at(wsum, pix, wgt)
        np.add.at(zsum, pix, z[idx] * wgt)
    cov = np.clip(wsum / weight_full, 0.0, 1.0)
    safe = np.maximum(wsum, 1e-12)
    rgb = acc / safe[:, None] * cov[:, None]
    depth = np.where(wsum > 1e-6, zsum / safe, EMPTY_DEPTH)
    return (
        rgb.reshape(height, width, 3).astype(np.float32),
        cov.reshape(height, width).astype(np.float32),
        depth.reshape(height, width).astype(np.float32),
    )


def reconstruction_inputs(
    rng: np.random.Generator,
    ctx_colors: list[np.ndarray],
    ctx_depths: list[np.ndarray],
    ctx_cams: list[tuple[np.ndarray, np.ndarray]],
    cams: list[tuple[np.ndarray, np.ndarray]],
    width: int,
    height: int,
    sky_depth: float = 200.0,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """Stream 1: a point reconstruction of the context views re-rendered per frame.

    Returns RGBA ``[T, H, W, 4]`` (premultiplied, A = coverage), planar depth
    ``[T, H, W]`` and the degradation parameters.
    """
    level = float(rng.uniform(0.5, 2.0))
    pts, cols, rads = [], [], []
    params = {"depth_noise": level, "views": []}
    for color, depth, (w2c, w2ndc) in zip(ctx_colors, ctx_depths, ctx_cams, strict=True):
        h, w = depth.shape
        # Per-view exposure/white-balance drift (seams) and loss of detail.
        gain = np.exp(rng.normal(0, 0.06, 3) + rng.normal(0, 0.08)).astype(np.float32)
        blur = int(rng.integers(0, 2))
        c = box_blur(color[..., :3], blur) * gain
        dn = noisy_depth(rng, depth, level)
        sky = dn >= 1e9
        dn = np.where(sky & (depth >= 1e9), sky_depth, dn)
        keep = dn < 1e9
        p = unproject(dn, w2c, w2ndc)
        f = focal_px(w2c, w2ndc, w)
        # World radius of a pixel footprint, a bit larger (splats overlap).
        rad = dn / f * rng.uniform(0.6, 1.1)
        pts.append(p[keep])
        cols.append(c[keep])
        rads.append(rad[keep])
        params["views"].append({"gain": gain.tolist(), "blur": blur})
    pts = np.concatenate(pts)
    cols = np.concatenate(cols)
    rads = np.concatenate(rads)
    # Floaters: a few points pulled toward the camera that saw them.
    n_float = int(len(pts) * rng.uniform(0.0005, 0.003))
    if n_float:
        sel = rng.integers(0, len(pts), n_float)
        w2c0 = ctx_cams[0][0]
        eye = np.linalg.inv(w2c0.T)[:3, 3]
        t = rng.uniform(0.05, 0.4, (n_float, 1))
        pts = np.concatenate([pts, pts[sel] + (eye - pts[sel]) * t])
        cols = np.concatenate([cols, cols[sel]])
        rads = np.concatenate([rads, rads[sel] * rng.uniform(1.0, 3.0, n_float)])
    params["floaters"] = n_float
    rgba, depths = [], []
    for w2c, w2ndc in cams:
        rgb, cov, dep = splat_points(pts, cols, rads, w2c, w2ndc, width, height)
        dep = np.where(dep >= sky_depth * 0.9, EMPTY_DEPTH, dep)
        rgba.append(np.concatenate([rgb, cov[..., None]], -1))
        depths.append(dep)
    return np.stack(rgba), np.stack(depths), params


# ---------------------------------------------------------------------------
# Stream 2: tone mismatch on the insert


def random_tone(rng: np.random.Generator) -> dict:
    """Random exposure (stops), white-balance gains, tone-curve gamma, saturation."""
    exposure = float(rng.choice([-1, 1]) * rng.uniform(0.3, 1.6))
    wb = np.exp(rng.normal(0, 0.15, 3))
    wb = (wb / (wb @ LUMA)).tolist()
    return {
        "exposure": exposure if rng.random() < 0.85 else 0.0,
        "wb": wb if rng.random() < 0.7 else [1.0, 1.0, 1.0],
        "gamma": float(np.exp(rng.normal(0, 0.25))) if rng.random() < 0.6 else 1.0,
        "saturation": float(np.exp(rng.normal(0, 0.3))) if rng.random() < 0.5 else 1.0,
    }


def apply_tone(rgb: np.ndarray, p: dict) -> np.ndarray:
    """Applies a tone change to linear RGB (curve pivots on mid grey 0.18)."""
    c = np.maximum(rgb[..., :3], 0.0) * (2.0 ** p["exposure"]) * np.asarray(p["wb"], np.float32)
    if p["gamma"] != 1.0:
        c = 0.18 * (c / 0.18) ** p["gamma"]
    if p["saturation"] != 1.0:
        y = luminance(c)[..., None]
        c = np.maximum(y + (c - y) * p["saturation"], 0.0)
    return c.astype(np.float32)


def composite(background: np.ndarray, foreground: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``background * (1 - mask) + foreground * mask`` on RGB; mask ``[..., H, W]``."""
    m = mask[..., None]
    return (background[..., :3] * (1 - m) + foreground[..., :3] * m).astype(np.float32)


def shadow_mask(full: np.ndarray, without_insert: np.ndarray, insert: np.ndarray) -> np.ndarray:
    """Where the insert darkens its surroundings (its shadow), soft, in [0, 1].

    Compares the full render with the render without the insert; the insert's
    own pixels are excluded.
    """
    lf = luminance(full)
    lb = luminance(without_insert)
    rel = (lb - lf) / np.maximum(lb, 1e-3)
    m = np.clip((rel - 0.04) / 0.16, 0.0, 1.0)
    return (m * (1.0 - np.clip(insert * 4.0, 0.0, 1.0))).astype(np.float32)
