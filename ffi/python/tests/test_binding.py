"""Tests of the Python binding against the real libharmonizer."""

from __future__ import annotations

import logging
import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

import harmonizer as hz
from harmonizer import _api

REPO = Path(__file__).resolve().parents[3]


def frame(h: int = 24, w: int = 32, t: int = 0, channels: int = 4, hole: bool = True):
    """A deterministic frame moving one pixel right per step, with a hole."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    sx = x - t
    rgb = np.stack([0.5 + 0.3 * np.sin(sx * 0.4), 0.4 + 0.2 * np.cos(y * 0.3), 0.3 + 0.1 * ((sx // 5) % 2)], -1)
    cov = np.ones((h, w), np.float32)
    if hole:
        cov[h // 3 : h // 2, w // 3 : w // 2] = 0.0
    color = np.zeros((h, w, channels), np.float32)
    color[..., :3] = rgb * cov[..., None]
    if channels == 4:
        color[..., 3] = cov
    motion = np.zeros((h, w, 2), np.float32)
    motion[..., 0] = -1.0
    depth = np.full((h, w), 5.0, np.float32)
    return color, cov, motion, depth


def test_versions_agree_with_cargo_toml():
    toml = (REPO / "Cargo.toml").read_text()
    section = toml.split("[workspace.package]", 1)[1]
    cargo = re.search(r'^version = "([^"]+)"', section, re.M).group(1)
    assert hz.version() == cargo
    assert hz.__version__ == cargo


def test_bypass_round_trip_is_exact(device):
    color, cov, _, _ = frame()
    with hz.Session(device, backend="bypass") as s:
        out = s.process(color, coverage=cov, frame_index=1)
    assert out.shape == (*color.shape[:2], 4) and out.dtype == np.float32
    np.testing.assert_array_equal(out[..., :3], color[..., :3])
    np.testing.assert_array_equal(out[..., 3], cov)


def test_strided_rgb_view_in_place_without_copy(device):
    color, cov, _, _ = frame()
    rgba = color.copy()
    rgb = rgba[..., :3]  # pixel stride 16 bytes, only RGB is color
    img, used = _api._array_image(rgb, "color")
    assert used is rgb and img.pixel_stride == 16 and img.channels == 3, "float32 views are passed without a copy"
    with hz.Session(device, backend="classical") as a, hz.Session(device, backend="classical") as b:
        for t in range(3):
            c, cov, m, d = frame(t=t)
            rgba[...] = c
            expected = a.process(c, coverage=cov, motion=m, depth=d, frame_index=t)
            result = b.process(rgb, coverage=cov, motion=m, depth=d, frame_index=t, out=rgb)
            assert result is rgb
            np.testing.assert_array_equal(rgba[..., :3], expected[..., :3])
            np.testing.assert_array_equal(rgba[..., 3], c[..., 3])  # the 4th channel is left alone


def test_float16_and_odd_layouts(device):
    color, cov, _, _ = frame()
    with hz.Session(device, backend="bypass") as s:
        half = color.astype(np.float16)
        out16 = np.zeros((*color.shape[:2], 4), np.float16)
        s.process(half, out=out16, coverage=cov.astype(np.float16))
        np.testing.assert_array_equal(out16[..., :3], half[..., :3])
        flipped = color[::-1, ::-1]  # negative strides: copied, still correct
        out = s.process(flipped)
        np.testing.assert_array_equal(out[..., :3], flipped[..., :3])
        planar = np.ascontiguousarray(color.transpose(2, 0, 1)).transpose(1, 2, 0)  # channel stride != 4
        np.testing.assert_array_equal(s.process(planar)[..., :3], color[..., :3])
        out_f = np.zeros((*color.shape[:2], 4), np.float32, order="F")  # not describable: written through a copy
        s.process(color, out=out_f)
        np.testing.assert_array_equal(out_f[..., :3], color[..., :3])


def test_classical_sequence_with_every_input(device):
    h, w = 24, 32
    w2c = np.eye(4, dtype=np.float32)
    w2n = np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0.5, 0.5, 1, 1], [0, 0, 0, 0]], np.float32)
    with hz.Session(device, backend="classical", context_frames=3) as s:
        for t in range(5):
            c, cov, m, d = frame(h, w, t)
            out = s.process(
                c,
                depth=d[..., None],
                motion=m,
                normal=np.zeros((h, w, 3), np.float32),
                coverage=cov,
                insert_mask=np.zeros((h, w), np.float32),
                world_to_camera=w2c,
                world_to_ndc=w2n,
                frame_index=t,
            )
            assert np.isfinite(out).all()
            assert out[h // 3 + 1, w // 3 + 1, 3] > 0.99, "the hole is filled"
        r = s.last_report
        assert r["frame_index"] == 4 and r["reset"] is None and r["backend"] == "classical"
        assert r["history_used"] == 3 and s.history_length == 3
        assert s.memory_bytes >= 3 * h * w * 4 * 4
        assert isinstance(r["stages"], dict) and r["total_ms"] > 0
        assert s.backend_name == "classical" and s.model_name is None and s.model_version is None


def test_reset_reasons(device):
    with hz.Session(device, backend="classical") as s:
        assert s.last_report is None
        c, *_ = frame()
        s.process(c, frame_index=0)
        assert s.last_report["reset"] == "first_frame"
        s.process(c, frame_index=1)
        assert s.last_report["reset"] is None
        s.process(c, frame_index=5)
        assert s.last_report["reset"] == "frame_gap"
        s.process(c, frame_index=6, reset=True)
        assert s.last_report["reset"] == "requested"
        s.process(frame(h=12, w=16)[0], frame_index=7)
        assert s.last_report["reset"] == "size_changed"
        s.reset()
        assert s.history_length == 0


def test_parameters(device):
    with hz.Session(device, backend="bypass", context_frames=2, strength=0.5, fill_holes=False, gap_policy="keep") as s:
        assert s.get("backend") == "bypass"
        assert s.get("context_frames") == 2 and isinstance(s.get("context_frames"), int)
        assert s.get("strength") == 0.5
        assert s.get("fill_holes") is False
        assert s.get("gap_policy") == "keep"
        s.set("strength", 1)  # an int for a float parameter is accepted
        with pytest.raises(hz.InvalidOperationError, match="hz_session_commit"):
            s.process(frame()[0])
        s.commit()
        s.process(frame()[0])
        with pytest.raises(hz.InvalidArgumentError) as e:
            s.set("context_frames", 9)
        assert e.value.status == hz.Status.INVALID_ARGUMENT
        assert "context_frames" in e.value.message and "9" in str(e.value)
        assert isinstance(e.value, ValueError)
        with pytest.raises(hz.InvalidArgumentError, match="no_such"):
            s.set("no_such", 1)
        with pytest.raises(hz.InvalidArgumentError, match="gpu"):
            s.set("backend", "gpu")
        with pytest.raises(hz.InvalidArgumentError):
            s.set("strength", [1.0])
    with pytest.raises(hz.InvalidArgumentError, match="context_frames"):
        hz.Session(device, context_frames=-1)


def test_bad_arrays(device):
    with hz.Session(device, backend="bypass") as s:
        c, cov, *_ = frame()
        with pytest.raises(hz.InvalidArgumentError, match="depth: size 16x24 differs"):
            s.process(c, depth=np.ones((24, 16), np.float32))
        with pytest.raises(hz.InvalidArgumentError, match="motion: needs 2"):
            s.process(c, motion=np.ones((24, 32), np.float32))
        with pytest.raises(hz.InvalidArgumentError, match="color"):
            s.process(np.ones((24, 32), np.float32))
        with pytest.raises(hz.InvalidArgumentError, match="empty"):
            s.process(np.ones((0, 32, 4), np.float32))
        with pytest.raises(hz.InvalidArgumentError, match="out"):
            s.process(c, out=np.zeros((24, 32, 2), np.float32))
        with pytest.raises(hz.InvalidArgumentError, match="together"):
            s.process(c, world_to_camera=np.eye(4))
        with pytest.raises(hz.InvalidArgumentError, match="4x4"):
            s.process(c, world_to_camera=np.eye(3), world_to_ndc=np.eye(4))
        with pytest.raises(hz.InvalidArgumentError, match="dtype"):
            s.process(c.astype(np.complex64))
        assert s.last_report is None, "failed calls leave no report"


def noisy_frame(h: int = 64, w: int = 96, seed: int = 7):
    """A noisy render and what it should be: a lit two-albedo checker, each
    pixel times the mean of 4 exponential samples (the Monte Carlo noise of
    4 samples per pixel, deviation half the signal). Returns the clean and
    noisy RGB and the albedo, float32 (H, W, 3)."""
    y, x = np.mgrid[0:h, 0:w]
    tile = ((x // 12 + y // 12) % 2).astype(np.float32)
    albedo = np.stack([0.2 + 0.6 * tile, np.full_like(tile, 0.5), 0.8 - 0.5 * tile], -1)
    clean = albedo * (0.4 + 1.2 * x / w)[..., None]
    noise = np.random.default_rng(seed).gamma(4.0, 0.25, size=(h, w, 1))
    return clean.astype(np.float32), (clean * noise).astype(np.float32), albedo.astype(np.float32)


def _denoise_or_fail(session, color, **kw):
    try:
        return session.process(color, **kw)
    except hz.RuntimeMissingError as e:
        pytest.fail(
            "denoise on needs Open Image Denoise: run scripts/setup-venv.sh in the repository root "
            f"(it installs pyoidn into .venv) or set HARMONIZER_OIDN_LIB ({e})"
        )


def test_denoise_with_albedo(device):
    """Issue 20: ``denoise on`` with an albedo (float32, or float16 with the
    denoiser's normals) denoises a noisy frame with the real Open Image
    Denoise (a missing library fails the test), and the report says so;
    ``denoise auto`` measures the noise level and turns itself on."""
    clean, noisy, albedo = noisy_frame()
    before = float(np.mean((noisy - clean) ** 2))
    with hz.Session(device, backend="bypass", denoise="on") as s:
        out = _denoise_or_fail(s, noisy, albedo=albedo, frame_index=1)
        after = float(np.mean((out[..., :3] - clean) ** 2))
        print(f"denoise on, albedo: MSE {before:.5f} noisy, {after:.5f} denoised")
        assert after < 0.1 * before, f"denoising cuts the error at least tenfold: MSE {before} -> {after}"
        r = s.last_report
        assert (r["denoised"], r["denoise_decision"], r["noise_level"]) == (True, "denoise on", None)
        s.process(noisy, albedo=albedo, frame_index=2)
        r = s.last_report
        assert r["denoised"] and r["denoise_decision"] is None
    normal = np.zeros_like(albedo)
    normal[..., 2] = 1.0
    with hz.Session(device, backend="bypass", denoise="on") as s:
        out16 = _denoise_or_fail(
            s, noisy, albedo=albedo.astype(np.float16), denoise_normal=normal.astype(np.float16), frame_index=1
        )
        assert s.last_report["denoised"]
        assert float(np.mean((out16[..., :3] - clean) ** 2)) < 0.1 * before
    with hz.Session(device, backend="classical") as s:  # denoise auto, samples 0
        _denoise_or_fail(s, noisy, albedo=albedo, frame_index=1)
        r = s.last_report
        print(r["denoise_decision"])
        assert r["denoised"] and r["noise_level"] > 0.2, r
        assert r["denoise_decision"].startswith("denoise auto: on (noise level"), r
    with hz.Session(device, backend="bypass") as s:
        s.process(clean, albedo=albedo, frame_index=1)
        r = s.last_report
        assert not r["denoised"] and r["denoise_decision"].startswith("denoise auto: off"), r


def test_albedo_and_denoise_normal_errors(device):
    c, *_ = frame(hole=False)
    h, w = c.shape[:2]
    with hz.Session(device, backend="bypass") as s:
        for name in ("albedo", "denoise_normal"):
            with pytest.raises(hz.InvalidArgumentError, match=f"{name}: needs 3 channel\\(s\\), got 2"):
                s.process(c, **{name: np.ones((h, w, 2), np.float32)})
            with pytest.raises(hz.InvalidArgumentError, match=f"{name}: needs 3 channel\\(s\\), got 1"):
                s.process(c, **{name: np.ones((h, w), np.float32)})
            with pytest.raises(hz.InvalidArgumentError, match=f"{name}: size 16x24 differs from color 32x24"):
                s.process(c, **{name: np.ones((h, 16, 3), np.float32)})
            with pytest.raises(hz.InvalidArgumentError, match=f"{name}: dtype complex64"):
                s.process(c, **{name: np.ones((h, w, 3), np.complex64)})
            with pytest.raises(hz.InvalidArgumentError, match=f"{name}: expected shape"):
                s.process(c, **{name: np.ones((1, h, w, 3), np.float32)})
        assert s.last_report is None, "failed calls leave no report"
        s.process(c, albedo=np.full((h, w, 3), 0.5, np.float32), denoise_normal=np.ones((h, w, 3), np.float16))
        assert s.last_report["denoised"] is False


def two_boxes():
    """Two touching boxes on a grey ground (float32 (H, W, 3)), ids 7 and 2:
    box 7 is 16 times too bright and blue, box 2 has the ground's color."""
    h, w = 64, 96
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    t = 0.5 + 0.3 * np.sin(x * 0.13) * np.cos(y * 0.11)
    color = np.stack([0.55 * t, 0.5 * t, 0.45 * t], -1)
    ids = np.zeros((h, w), np.float32)
    ids[16:48, 16:48] = 7.0
    ids[16:48, 48:80] = 2.0
    color[ids == 7.0] *= np.array([16.0, 16.0, 48.0], np.float32)
    return color.astype(np.float32), ids


def test_insert_id_tells_touching_objects_apart(device):
    """``insert_id=``: each id is its own object (the correct box 2 is left
    as it came, the wrong box 7 darkened); as one connected mask both share
    one filter and box 2 changes too. The ids alone make the mask."""
    color, ids = two_boxes()
    mask = (ids > 0).astype(np.float32)
    right = ids == 2.0
    params = dict(backend="classical", contact_shadows=False, stabilize=False, match_tone=True)
    with hz.Session(device, **params) as s:
        merged = s.process(color, insert_mask=mask, frame_index=0)
    with hz.Session(device, **params) as s:
        apart = s.process(color, insert_mask=mask, insert_id=ids, frame_index=0)
    with hz.Session(device, **params) as s:
        alone = s.process(color, insert_id=ids[..., None], frame_index=0)
    change = lambda out: np.abs(np.log2((out[..., :3][right] + 1e-3) / (color[right] + 1e-3))).mean()  # noqa: E731
    assert change(merged) > 0.1, change(merged)
    assert change(apart) < 0.02, change(apart)
    assert (apart[ids == 7.0][:, :3] < 0.8 * color[ids == 7.0]).all()
    np.testing.assert_array_equal(alone, apart)


def test_insert_id_errors_and_warnings(device):
    c, *_ = frame(hole=False)
    h, w = c.shape[:2]
    with hz.Session(device, backend="classical") as s:
        with pytest.raises(hz.InvalidArgumentError, match="insert_id: size 16x24 differs from color 32x24"):
            s.process(c, insert_id=np.ones((h, 16), np.float32))
        with pytest.raises(hz.InvalidArgumentError, match="insert_id: dtype complex64"):
            s.process(c, insert_id=np.ones((h, w), np.complex64))
        ids = np.zeros((h, w), np.float32)
        ids[4:12, 4:12] = 3.0
        ids[0, 0] = np.nan
        ids[0, 1] = np.inf
        s.process(c, insert_id=ids, frame_index=0)
        warnings = s.last_report["warnings"]
        assert any("2 AOV samples" in m for m in warnings), warnings


def lit_insert(grade=(1.0, 1.0, 1.0), h: int = 72, w: int = 96):
    """A ground (normal up) and a wall (normal toward the camera) of textured
    albedo under a sun and sky, and a ball of orange albedo lit by the same
    light, its color times ``grade``: color, albedo, normals (camera space)
    and the ball's mask, float32."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32) + 0.5
    tex = 0.5 + 0.35 * np.sin(x * 0.37) * np.cos(y * 0.23)
    albedo = np.where(
        (y < h / 2)[..., None],
        np.stack([0.5 * tex, 0.45 * tex, 0.4 * tex], -1),
        np.stack([0.3 + 0.3 * tex, 0.35 + 0.2 * tex, 0.1 + 0.2 * tex], -1),
    )
    normal = np.where((y < h / 2)[..., None], np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0]))
    dx, dy = (x - w / 2) / 20, (y - h / 2) / 20
    ball = dx**2 + dy**2 < 1
    nz = np.sqrt(np.clip(1 - dx**2 - dy**2, 0, 1))
    normal = np.where(ball[..., None], np.stack([dx, -dy, nz], -1), normal)
    albedo = np.where(ball[..., None], np.array([0.75, 0.32, 0.08]), albedo)
    sun = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])
    d = np.clip(normal @ sun, 0, None)[..., None]
    color = albedo * (np.array([0.25, 0.3, 0.4]) + d * np.array([1.6, 1.5, 1.3]))
    color = np.where(ball[..., None], color * np.asarray(grade), color)
    f = lambda a: np.ascontiguousarray(a, np.float32)  # noqa: E731
    return f(color), f(albedo), f(normal), f(ball)


def test_albedo_tone_brings_a_graded_insert_back(device):
    """Issue 19: with the albedo and normals, an insert graded 1.3 stops too
    bright and warm comes back toward its true color; a correctly lit one is
    returned exactly; ``albedo_tone=False`` leaves the graded one alone."""
    truth, albedo, normal, mask = lit_insert()
    graded, *_ = lit_insert(grade=(3.0, 2.4, 1.6))
    ball = mask > 0
    err = lambda out: np.abs(np.log2((out[..., :3][ball] + 1e-3) / (truth[ball] + 1e-3))).mean()  # noqa: E731
    params = dict(backend="classical", contact_shadows=False, stabilize=False, temporal_blend=0.0)
    with hz.Session(device, **params) as s:
        fixed = s.process(graded, albedo=albedo, normal=normal, insert_mask=mask, frame_index=0)
        assert s.get("albedo_tone") is True
    with hz.Session(device, **params) as s:
        kept = s.process(truth, albedo=albedo, normal=normal, insert_mask=mask, frame_index=0)
    with hz.Session(device, albedo_tone=False, **params) as s:
        off = s.process(graded, albedo=albedo, normal=normal, insert_mask=mask, frame_index=0)
    print(f"insert error (stops): graded {err(graded):.3f}, corrected {err(fixed):.3f}")
    assert err(fixed) < 0.25 * err(graded)
    np.testing.assert_array_equal(kept[..., :3][ball], truth[ball])
    np.testing.assert_array_equal(off[..., :3][ball], graded[ball])


def _run(session, frames, cancel=None):
    outs = []
    for t, (c, cov, m, d) in enumerate(frames):
        if cancel is not None and t == cancel[0]:
            calls = []

            def progress(p, calls=calls):
                assert 0.0 <= p <= 1.0
                calls.append(p)
                return len(calls) < cancel[1]

            before = session.history_length
            with pytest.raises(hz.CancelledError, match="cancelled"):
                session.process(c, coverage=cov, motion=m, depth=d, frame_index=t, progress=progress)
            assert session.history_length == before
            assert calls == sorted(calls), "progress is monotonic"
        outs.append(session.process(c, coverage=cov, motion=m, depth=d, frame_index=t))
    return outs


def test_cancel_leaves_state_unchanged(device):
    frames = [frame(t=t) for t in range(5)]
    with hz.Session(device, backend="classical") as probe:
        calls = []
        probe.process(frames[0][0], progress=lambda p: calls.append(p) or True)
    total = len(calls)
    assert total >= 2 and calls[-1] == 1.0
    for at in (1, (total + 1) // 2, total):
        with hz.Session(device, backend="classical") as ref, hz.Session(device, backend="classical") as s:
            expected = _run(ref, frames)
            got = _run(s, frames, cancel=(2, at))
            for e, g in zip(expected, got):
                np.testing.assert_array_equal(e, g)


def test_progress_exception_cancels_and_propagates(device):
    with hz.Session(device, backend="classical") as s:

        def boom(p):
            raise KeyError("from the host")

        with pytest.raises(hz.CancelledError) as e:
            s.process(frame()[0], progress=boom)
        assert isinstance(e.value.__cause__, KeyError)
        assert s.history_length == 0


def test_messages(device, caplog):
    c, *_ = frame(hole=False)
    c[0, 0, 0] = np.nan
    c[1, 1, 1] = -np.inf
    got = []
    with hz.Session(device, backend="bypass", on_message=lambda level, text: got.append((level, text))) as s:
        out = s.process(c, frame_index=0)
        assert np.isfinite(out).all()
        assert s.last_report["sanitized"] == 2
    assert any(level == "warning" and "NaN" in text for level, text in got), got
    with caplog.at_level(logging.INFO, logger="harmonizer"), hz.Session(device, backend="bypass") as s:
        s.process(c, frame_index=0)
        s.process(c, frame_index=3)
    texts = [r.getMessage() for r in caplog.records if r.name == "harmonizer"]
    assert any("NaN" in t for t in texts) and any("not consecutive" in t for t in texts), texts


def test_two_sessions_on_two_threads(device):
    seqs = [[frame(t=t + 10 * k) for t in range(5)] for k in range(2)]

    def run(k, results):
        with hz.Session(device, backend="classical") as s:
            results[k] = _run(s, seqs[k])

    sequential, threaded = {}, {}
    for k in range(2):
        run(k, sequential)
    threads = [threading.Thread(target=run, args=(k, threaded)) for k in range(2)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    for k in range(2):
        for a, b in zip(sequential[k], threaded[k]):
            np.testing.assert_array_equal(a, b)


def test_lifetimes(device):
    d = hz.Device(threads=1)
    assert d.threads == 1
    s = hz.Session(d, backend="bypass")
    d.close()  # sessions keep their device alive
    s.process(frame()[0])
    s.close()
    s.close()
    with pytest.raises(hz.InvalidOperationError, match="closed"):
        s.process(frame()[0])
    with pytest.raises(hz.InvalidOperationError, match="closed"):
        hz.Session(d)
    with pytest.raises(hz.InvalidArgumentError):
        hz.Device(threads=-1)


def test_missing_library_is_reported():
    env = dict(os.environ, HARMONIZER_LIB="/nonexistent/libharmonizer.so")
    code = "import harmonizer as hz\ntry:\n    hz.version()\nexcept hz.LibraryNotFoundError as e:\n    print(e)\n"
    r = subprocess.run(
        [sys.executable, "-c", code], env=env, cwd=REPO / "ffi" / "python", capture_output=True, text=True, check=True
    )
    assert "/nonexistent/libharmonizer.so" in r.stdout and "cargo build" in r.stdout


FIXTURES = REPO / "core" / "tests" / "fixtures" / "models"


def test_neural_model_from_file_and_bytes():
    """The real ONNX Runtime through the ABI, on the core's identity fixture model."""
    onnx = FIXTURES / "identity.onnx"
    color, cov, *_ = frame(hole=False)
    for model in (onnx, (onnx.read_bytes(), (FIXTURES / "identity.json").read_text())):
        with hz.Device(threads=2, model=model) as d, hz.Session(d, backend="neural", stabilize=False) as s:
            assert s.backend_name == "neural"
            assert (s.model_name, s.model_version) == ("identity", "1.0.0")
            out = s.process(color, coverage=cov, frame_index=0)
            np.testing.assert_allclose(out[..., :3], color[..., :3], rtol=1e-3, atol=1e-4)
            assert s.last_report["backend"] == "neural"


def test_model_and_runtime_errors():
    onnx = FIXTURES / "identity.onnx"
    with hz.Device(model=onnx, ort_library="/nonexistent/libonnxruntime.so") as d:
        with pytest.raises(hz.RuntimeMissingError) as e:
            hz.Session(d, backend="neural")
        assert e.value.status == hz.Status.RUNTIME_MISSING and "/nonexistent/libonnxruntime.so" in str(e.value)
    # A missing or garbage model is refused by the device, naming it (issue 12).
    with pytest.raises(hz.IoError) as e:
        hz.Device(model=FIXTURES / "no_such_model.onnx")
    assert "no_such_model" in str(e.value)
    with pytest.raises(hz.ModelError, match="not an ONNX model"):
        hz.Device(model=(b"this is not an ONNX model", (FIXTURES / "identity.json").read_text()))
    with pytest.raises(hz.InvalidArgumentError, match="model"):
        hz.Device(model=(b"", "{}"))


def test_packaged_library_and_wheel_runtimes_are_found(tmp_path, monkeypatch):
    """Issue 21: without HARMONIZER_LIB the wheel's ``harmonizer/lib/`` is
    searched first (HARMONIZER_LIB stays an override); the onnxruntime and
    pyoidn wheels of this interpreter are located without importing them, and
    ``Device()`` puts pyoidn's library into HARMONIZER_OIDN_LIB only when unset."""
    from harmonizer import _native

    here = Path(_native.__file__).resolve().parent
    monkeypatch.delenv("HARMONIZER_LIB", raising=False)
    assert _native.candidates()[:2] == [here / "lib" / _native._lib_name(), here / _native._lib_name()]
    monkeypatch.setenv("HARMONIZER_LIB", str(tmp_path / "x.so"))
    assert _native.candidates() == [tmp_path / "x.so"]

    # A fake installed wheel layout: found by find_spec, never imported.
    pkg = tmp_path / "site" / "onnxruntime"
    (pkg / "capi").mkdir(parents=True)
    (pkg / "__init__.py").write_text("raise RuntimeError('imported')\n")
    for name in ("libonnxruntime.so.1", "libonnxruntime.so.1.31.1"):
        (pkg / "capi" / name).write_bytes(b"")
    oidn = tmp_path / "site" / "pyoidn"
    (oidn / "oidn" / "lib").mkdir(parents=True)
    (oidn / "__init__.py").write_text("raise RuntimeError('imported')\n")
    (oidn / "oidn" / "lib" / "libOpenImageDenoise.so.2").write_bytes(b"")
    monkeypatch.syspath_prepend(str(tmp_path / "site"))
    for mod in ("onnxruntime", "pyoidn"):
        monkeypatch.delitem(sys.modules, mod, raising=False)
    assert _native.ort_library() == pkg / "capi" / "libonnxruntime.so.1.31.1"
    assert _native.oidn_library() == oidn / "oidn" / "lib" / "libOpenImageDenoise.so.2"
    assert "onnxruntime" not in sys.modules and "pyoidn" not in sys.modules

    monkeypatch.delenv("HARMONIZER_OIDN_LIB", raising=False)
    monkeypatch.setattr(_native, "oidn_library", lambda: Path("/opt/pyoidn/libOpenImageDenoise.so.2"))
    monkeypatch.setattr(_native, "ort_library", lambda: None)  # not the empty fake file
    with hz.Device(threads=1):
        pass
    assert os.environ["HARMONIZER_OIDN_LIB"] == "/opt/pyoidn/libOpenImageDenoise.so.2"
    monkeypatch.setenv("HARMONIZER_OIDN_LIB", "/given/libOpenImageDenoise.so.2")
    with hz.Device(threads=1):
        pass
    assert os.environ["HARMONIZER_OIDN_LIB"] == "/given/libOpenImageDenoise.so.2"


def test_parse_param_reads_command_line_values():
    assert hz.parse_param("TRUE") is True and hz.parse_param("off") is False
    assert hz.parse_param("3") == 3 and isinstance(hz.parse_param("3"), int)
    assert hz.parse_param("0.25") == 0.25
    assert hz.parse_param("0.4,-0.7,0.6") == "0.4,-0.7,0.6"
