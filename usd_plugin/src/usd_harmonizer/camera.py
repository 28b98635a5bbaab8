"""USD cameras to OpenEXR ``worldToCamera`` / ``worldToNDC`` matrices.

USD (Gf) matrices are row-vector (``p' = p M``) like OpenEXR's, but a USD
camera looks down -z and its projection maps to clip space with +y up. The
OpenEXR convention is camera space +z forward and NDC (0,0) at the top-left:

    worldToCamera = inverse(camera transform) * diag(1, 1, -1, 1)
    worldToNDC    = inverse(camera transform) * projection * clipToNDC

where ``clipToNDC`` maps x to (x + w) / 2 and y to (w - y) / 2. The frustum's
window is first conformed to the render product's aspect ratio
(``aspectRatioConformPolicy``), as UsdRender specifies.
"""

from __future__ import annotations

import numpy as np
from pxr import Gf, Usd, UsdGeom

from .errors import CameraError

_FLIP_Z = np.diag([1.0, 1.0, -1.0, 1.0])
_CLIP_TO_NDC = np.array(
    [
        [0.5, 0.0, 0.0, 0.0],
        [0.0, -0.5, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
        [0.5, 0.5, 0.0, 1.0],
    ]
)


def _np(m: Gf.Matrix4d) -> np.ndarray:
    return np.array([[m[i][j] for j in range(4)] for i in range(4)], dtype=np.float64)


def conform_window(window: Gf.Range2d, policy: str, target_aspect: float) -> Gf.Range2d:
    """Conforms a frustum window to ``target_aspect`` (width / height) per a
    UsdRender ``aspectRatioConformPolicy``."""
    lo, hi = window.GetMin(), window.GetMax()
    w, h = hi[0] - lo[0], hi[1] - lo[1]
    if w <= 0 or h <= 0 or target_aspect <= 0:
        return window
    aspect = w / h
    if policy == "adjustPixelAspectRatio" or abs(aspect - target_aspect) < 1e-12:
        return window
    if policy == "expandAperture":
        policy = (
            "adjustApertureHeight" if aspect > target_aspect else "adjustApertureWidth"
        )
    elif policy == "cropAperture":
        policy = (
            "adjustApertureWidth" if aspect > target_aspect else "adjustApertureHeight"
        )
    cx, cy = (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2
    if policy == "adjustApertureWidth":
        w = h * target_aspect
    elif policy == "adjustApertureHeight":
        h = w / target_aspect
    else:
        raise CameraError(
            f"aspectRatioConformPolicy {policy!r} is not a UsdRender policy"
        )
    return Gf.Range2d(
        Gf.Vec2d(cx - w / 2, cy - h / 2), Gf.Vec2d(cx + w / 2, cy + h / 2)
    )


def exr_matrices(
    prim: Usd.Prim,
    frame: float,
    resolution: tuple[int, int],
    pixel_aspect: float = 1.0,
    conform_policy: str = "expandAperture",
) -> tuple[np.ndarray, np.ndarray]:
    """``(worldToCamera, worldToNDC)`` of the camera ``prim`` at ``frame`` as
    4x4 float64 row-vector arrays (OpenEXR convention)."""
    cam = UsdGeom.Camera(prim)
    if not cam:
        raise CameraError(f"camera {prim.GetPath()}: not a UsdGeom.Camera")
    gf = cam.GetCamera(Usd.TimeCode(frame))
    frustum = gf.frustum
    target = resolution[0] * pixel_aspect / resolution[1]
    frustum.window = conform_window(frustum.window, conform_policy, target)
    view = _np(frustum.ComputeViewMatrix())
    proj = _np(frustum.ComputeProjectionMatrix())
    w2c = view @ _FLIP_Z
    w2n = view @ proj @ _CLIP_TO_NDC
    if not (np.isfinite(w2c).all() and np.isfinite(w2n).all()):
        raise CameraError(
            f"camera {prim.GetPath()} at frame {frame}: the transform or frustum is degenerate"
        )
    return w2c, w2n


def project(w2n: np.ndarray, points: np.ndarray, width: int, height: int) -> np.ndarray:
    """Pixel positions (pixel centres at +0.5) of world ``points`` (N, 3)."""
    p = np.concatenate([points, np.ones((len(points), 1))], axis=1) @ w2n
    return np.stack([p[:, 0] / p[:, 3] * width, p[:, 1] / p[:, 3] * height], axis=1)


def unproject(
    w2c: np.ndarray,
    w2n: np.ndarray,
    px: np.ndarray,
    depth: np.ndarray,
    width: int,
    height: int,
) -> np.ndarray:
    """World points seen through pixel positions ``px`` (N, 2) at planar ``depth`` (N,)."""
    c2n = np.linalg.inv(w2c) @ w2n  # camera -> NDC (row-vector)
    u = px[:, 0] / width
    v = px[:, 1] / height
    # [x y d 1] c2n = (nx, ny, nz, nw); nx = u nw, ny = v nw -> two linear equations in x, y.
    a = c2n[:, 0] - u[:, None] * c2n[:, 3]
    b = c2n[:, 1] - v[:, None] * c2n[:, 3]
    rhs_a = -(a[:, 2] * depth + a[:, 3])
    rhs_b = -(b[:, 2] * depth + b[:, 3])
    det = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    x = (rhs_a * b[:, 1] - a[:, 1] * rhs_b) / det
    y = (a[:, 0] * rhs_b - rhs_a * b[:, 0]) / det
    cam = np.stack([x, y, depth, np.ones_like(depth)], axis=1)
    return (cam @ np.linalg.inv(w2c))[:, :3]
