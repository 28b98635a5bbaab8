"""The quality benchmark's harness: metrics, peers and the committed out-of-domain set.

Runs in .venv-quality (scripts/quality.sh creates it):

    .venv-quality/bin/python -m pytest -q training/tests/test_quality.py
"""

from __future__ import annotations

import numpy as np
import pytest

from training import quality
from training.ood import sequences as ood

H, W = 48, 64


def _seq(frames: list[np.ndarray], motion_x: float = 0.0, depth: float = 5.0) -> dict:
    T = len(frames)
    motion = np.zeros((T, H, W, 2), np.float32)
    motion[..., 0] = motion_x
    d = np.full((T, H, W), depth, np.float32)
    return {
        "frames": T,
        "input": np.concatenate([np.stack(frames), np.ones((T, H, W, 1), np.float32)], -1),
        "target": np.stack(frames),
        "depth": d,
        "motion": motion,
        "gt_depth": d,
        "gt_motion": motion,
        "mask_insert": np.zeros((T, H, W), np.float32),
        "mask_shadow": np.zeros((T, H, W), np.float32),
    }


def _texture(shift: int = 0) -> np.ndarray:
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    x = x + shift
    return np.stack([0.3 + 0.2 * np.sin(x / 5), 0.3 + 0.2 * np.cos(y / 7), 0.2 + 0.1 * np.sin((x + y) / 9)], -1)


def test_warp_error_is_zero_for_motion_the_vectors_explain_and_counts_flicker():
    # The image moves 2 px right per frame; motion (current -> previous) is -2 px.
    frames = [_texture(-2 * t) for t in range(4)]
    s = _seq(frames, motion_x=-2.0)
    enc = [quality.srgb(f) for f in frames]
    err = quality.warp_error(enc, s)
    assert err[0] is None
    assert max(err[1:]) < 1e-6
    flicker = [quality.srgb(f * (1.0 + 0.2 * (t % 2))) for t, f in enumerate(frames)]
    assert min(quality.warp_error(flicker, s)[1:]) > 1e-3


def test_occlusion_mask_drops_pixels_whose_surface_was_not_visible():
    frames = [_texture(), _texture()]
    s = _seq(frames)
    s["gt_depth"][0, :, :20] = 1.0  # an occluder in the previous frame only
    ok, _ = quality.occlusion_mask(s["gt_depth"], s["gt_motion"], 1)
    assert not ok[:, :20].any() and ok[:, 25:].all()


def test_psnr_and_ssim_of_identical_frames():
    a = quality.srgb(_texture())
    assert quality.psnr(a, a) == pytest.approx(120.0)
    assert quality.ssim_map(a, a).mean() == pytest.approx(1.0, abs=1e-4)
    assert quality.psnr(a, a, np.zeros((H, W), bool)) is None


def test_inpainting_peers_fill_holes_and_leave_hole_free_frames_alone():
    img = _texture()
    inp = np.concatenate([img, np.ones((H, W, 1), np.float32)], -1)
    holed = inp.copy()
    holed[20:28, 30:38] = 0.0
    tgt = quality.srgb(img)
    hole = holed[..., 3] < 0.5
    before = quality.psnr(quality.srgb(holed[..., :3]), tgt, hole)
    for m in ("telea", "navier_stokes"):
        out = quality.inpaint(holed, m)
        assert quality.psnr(quality.srgb(out), tgt, hole) > before + 15
        np.testing.assert_array_equal(quality.inpaint(inp, m), img)


def test_oidn_peer_removes_noise_with_and_without_auxiliary_images():
    rng = np.random.default_rng(0)
    img = _texture()
    noisy = np.maximum(img * rng.exponential(1.0, img.shape).astype(np.float32), 0.0)
    inp = np.concatenate([noisy, np.ones((H, W, 1), np.float32)], -1)
    tgt = quality.srgb(img)
    base = quality.psnr(quality.srgb(noisy), tgt)
    assert quality.psnr(quality.srgb(quality.oidn(inp, None, None)), tgt) > base + 5
    normal = np.zeros_like(img)
    normal[..., 2] = 1.0
    assert quality.psnr(quality.srgb(quality.oidn(inp, img, normal)), tgt) > base + 5
    # Prefiltered: the (noisy) guides denoised first, then the color with them.
    noisy_albedo = np.clip(img * rng.uniform(0.8, 1.2, img.shape).astype(np.float32), 0.0, 1.0)
    pre = quality.oidn_prefiltered(inp, noisy_albedo, normal)
    assert pre.shape == img.shape and np.isfinite(pre).all()
    assert quality.psnr(quality.srgb(pre), tgt) > base + 5


def test_ema_peer_steadies_a_flickering_static_sequence_and_keeps_disocclusions():
    rng = np.random.default_rng(1)
    frames = [_texture() * np.float32(1 + rng.normal(0, 0.1)) for _ in range(6)]
    s = _seq(frames)
    out = quality.ema(frames, s)
    e_in = np.mean(quality.warp_error([quality.srgb(f) for f in frames], s)[1:])
    e_out = np.mean(quality.warp_error([quality.srgb(f) for f in out], s)[1:])
    assert e_out < 0.5 * e_in
    s["depth"][3, :, :10] = 1.0  # a surface that was not there before: no history
    out = quality.ema(frames, s)
    np.testing.assert_array_equal(out[3][:, :10], frames[3][:, :10])


@pytest.mark.parametrize("name", ood.SEQUENCES)
def test_committed_out_of_domain_sequences_build(name):
    s = ood.build(name, frames=2)
    T, h, w = s["input"].shape[:3]
    assert (T, s["frames"]) == (2, 2) and (h, w) == (180, 320)
    for k in ("target", "depth", "motion", "normal", "mask_insert", "mask_shadow", "gt_depth", "gt_motion"):
        assert s[k].shape[:3] == (T, h, w), k
        assert np.isfinite(s[k]).all(), k
    diff = np.abs(s["input"][..., :3] - s["target"]).max()
    if name in ("insert_control", "clean_hall"):
        assert diff == 0.0
    else:
        assert diff > 0.05
    if s["region"]:
        assert quality.regions(s, 1)[s["region"]].sum() > 200, "the degraded region must be visible"
    if name.startswith("recon_"):
        assert (s["input"][..., 3] < 0.5).mean() > 0.005
    # The courtyard's insert sequences carry the render's albedo (a Cycles
    # host's Denoising Albedo); the frame-alone twin does not.
    if s["scene"] == "courtyard" and name != "insert_tone_rgb":
        alb = s["albedo"]
        assert alb.shape == (T, h, w, 3) and np.isfinite(alb).all()
        inside = s["mask_insert"] > 0.5 if s["mask_insert"].any() else np.ones((T, h, w), bool)
        assert 0.02 < float(np.median(alb[inside])) < 1.0
    else:
        assert "albedo" not in s or name.startswith("noisy")


def test_the_report_counts_the_reconstructions_one_db_above_the_best_inpainting_peer(tmp_path):
    def row(neural, telea, ns):
        return {
            "neural": {"psnr": 30.0, "psnr_region": neural},
            "telea": {"psnr": 29.0, "psnr_region": telea},
            "navier_stokes": {"psnr": 29.0, "psnr_region": ns},
            "truth": {"warp_err": 0.001},
        }

    summary = {
        "ood": {"recon_a": row(22.0, 20.5, 20.9), "insert_b": row(15.0, 14.0, 14.0)},
        "in_domain": {"scene_9/s1_recon": row(25.0, 24.8, 24.2), "scene_9/s2_tone": row(9.0, 1.0, 1.0)},
    }
    regions = {
        "ood": {"recon_a": "hole", "insert_b": "insert"},
        "in_domain": {"scene_9/s1_recon": "hole", "scene_9/s2_tone": "insert"},
    }
    m = quality.hole_margins(summary, regions)
    # Only the hole sequences, each against its better peer.
    assert [(x["sequence"], x["peer"], round(x["margin"], 2)) for x in m] == [
        ("recon_a", "navier_stokes", 1.1),
        ("scene_9/s1_recon", "telea", 0.2),
    ]
    info = {"command": "test", "machine": "test", "seconds": 0.0, "about": {"ood": {}}, "region": regions}
    quality.write_report(tmp_path, summary, info, ("telea", "navier_stokes", "neural"))
    report = (tmp_path / "report.md").read_text()
    assert "Navier-Stokes in the holes: 1 of 2 sequences." in report
    assert "| in_domain | scene_9/s1_recon | 25.00 | telea 24.80 | +0.20 |" in report
    # Without a peer that ran there is nothing to compare with.
    assert quality.hole_margins({"ood": {"recon_a": {"neural": {"psnr_region": 22.0}}}}, regions) == []


def test_hole_ages_follow_the_surface_and_restart_where_it_was_hidden():
    # A 1x8 strip panned one pixel a frame: the surface at x was at x + 1 the
    # frame before (motion = current -> previous, +1 px).
    T, W = 4, 8
    cov = np.ones((T, 1, W), np.float32)
    cov[1, 0, 3] = 0  # a hole over a surface covered in frame 0 (at x = 4)
    cov[2, 0, 2] = 0  # the same surface, still a hole: seen 2 frames ago
    cov[3, 0, 1] = 0
    cov[0, 0, 6] = 0  # a surface never covered: at x = 5 in frame 1 (covered there)
    cov[2, 0, 6] = cov[3, 0, 5] = 0  # a surface hidden in frame 2: its hole in frame 3 is "never"
    s = {
        "input": np.concatenate([np.zeros((T, 1, W, 3), np.float32), cov[..., None]], -1),
        "gt_motion": np.tile(np.array([1.0, 0.0], np.float32), (T, 1, W, 1)),
        "gt_depth": np.ones((T, 1, W), np.float32),
    }
    s["gt_depth"][2, 0, 6] = 0.5  # something nearer there in frame 2: frame 3's x = 5 was hidden
    ages = quality.hole_ages(s)
    assert ages[1, 0, 3] == 1 and ages[2, 0, 2] == 2 and ages[3, 0, 1] == 3
    assert ages[0, 0, 6] == quality.AGE_NEVER
    assert ages[3, 0, 5] == quality.AGE_NEVER
    assert (ages[cov >= 0.5] == 0).all()


def test_the_report_gives_the_holes_psnr_by_when_their_surface_was_last_seen(tmp_path):
    # Frame rows as frame_metrics writes them: squared error and count per age.
    def rows(e_recent, e_never):
        return [
            {"hole_age_se": {"1": [e_recent * 100, 100], "2-3": [0.0, 0], "4+": [0.0, 0], "never": [e_never * 50, 50]}}
            for _ in range(3)
        ]

    hist, share = quality.age_psnr(rows(1e-3, 1e-2))
    assert round(hist["1"], 2) == 30.0 and round(hist["never"], 2) == 20.0
    assert hist["2-3"] is None and hist["4+"] is None
    assert abs(share["1"] - 2 / 3) < 1e-9 and share["2-3"] == 0
    summary = {"ood": {"recon_a": {}}}
    for m, e in (("neural", 1e-3), ("navier_stokes", 1e-2)):
        p, sh = quality.age_psnr(rows(e, 1e-2))
        summary["ood"]["recon_a"][m] = {"psnr": 20.0, "psnr_age": p, "age_share": sh}
    lines = quality.age_table(summary, ("navier_stokes", "neural"))
    assert "| ood | recon_a | 1 | 66.7 % | 20.00 | **30.00** |" in lines
    assert "| ood | recon_a | never | 33.3 % | 20.00 | 20.00 |" in lines
    assert quality.age_table({"ood": {"insert_b": {"neural": {"psnr": 30.0}}}}, ("neural",)) == []
