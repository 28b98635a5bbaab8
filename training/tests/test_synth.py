"""Checks of the numpy side of the data generator (conventions, degradations)."""

import numpy as np

from training.synth import degrade


def look_at(eye, target, fov_y, aspect):
    """OpenEXR row-vector worldToCamera/worldToNDC of a pinhole camera (+z forward, y up world)."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    fwd = target - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0, 1, 0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    rot = np.eye(4)
    rot[0, :3], rot[1, :3], rot[2, :3] = right, up, fwd
    tr = np.eye(4)
    tr[:3, 3] = -eye
    w2c = rot @ tr
    f = 1 / np.tan(fov_y / 2)
    c2n = np.array([[0.5 * f / aspect, 0, 0.5, 0], [0, -0.5 * f, 0.5, 0], [0, 0, 1, -0.1], [0, 0, 1, 0]])
    return w2c.T.astype(np.float32), (c2n @ w2c).T.astype(np.float32)


def test_unproject_project_round_trip():
    w2c, w2ndc = look_at([1, 2, -5], [0, 0, 0], 0.8, 16 / 9)
    rng = np.random.default_rng(0)
    depth = rng.uniform(1, 20, (9, 16)).astype(np.float32)
    pts = degrade.unproject(depth, w2c, w2ndc)
    x, y, z = degrade.project(pts.reshape(-1, 3), w2c, w2ndc, 16, 9)
    jj, ii = np.meshgrid(np.arange(16) + 0.5, np.arange(9) + 0.5)
    assert np.allclose(x, jj.ravel(), atol=1e-3)
    assert np.allclose(y, ii.ravel(), atol=1e-3)
    assert np.allclose(z, depth.ravel(), rtol=1e-5)


def test_warp_follows_library_motion_convention():
    # Content moves 2 px right and 1 px down from t-1 to t: mv = (-2, -1).
    rng = np.random.default_rng(1)
    prev = rng.random((20, 30, 3)).astype(np.float32)
    cur = np.zeros_like(prev)
    cur[1:, 2:] = prev[:-1, :-2]
    mv = np.zeros((20, 30, 2), np.float32)
    mv[..., 0], mv[..., 1] = -2, -1
    aligned, valid = degrade.warp_bilinear(prev, mv)
    assert np.allclose(aligned[1:, 2:], cur[1:, 2:], atol=1e-6)
    assert valid[0].max() == 0 and valid[:, :2].max() == 0 and valid[1:, 2:].min() == 1


def test_splats_reproduce_a_view_and_leave_holes_where_unseen():
    w2c, w2ndc = look_at([0, 1, -4], [0, 0.5, 0], 0.9, 2.0)
    h, w = 24, 48
    depth = np.full((h, w), 4.0, np.float32)
    color = np.random.default_rng(2).random((h, w, 3)).astype(np.float32)
    pts = degrade.unproject(depth, w2c, w2ndc).reshape(-1, 3)
    f = degrade.focal_px(w2c, w2ndc, w)
    rad = np.full(len(pts), 4.0 / f * 0.7)
    rgb, cov, dep = degrade.splat_points(pts, color.reshape(-1, 3), rad, w2c, w2ndc, w, h)
    assert cov[4:-4, 4:-4].min() > 0.99
    assert np.abs(dep[4:-4, 4:-4] - 4.0).max() < 1e-3
    # Seen from the side, part of the frame was never observed: holes.
    w2c2, w2ndc2 = look_at([3, 1, -3], [0, 0.5, 0], 0.9, 2.0)
    _, cov2, dep2 = degrade.splat_points(pts, color.reshape(-1, 3), rad, w2c2, w2ndc2, w, h)
    assert (cov2 == 0).mean() > 0.1
    assert np.all(dep2[cov2 == 0] == degrade.EMPTY_DEPTH)


def test_tone_identity_and_composite():
    rng = np.random.default_rng(3)
    rgb = rng.random((8, 8, 3)).astype(np.float32)
    ident = {"exposure": 0.0, "wb": [1, 1, 1], "gamma": 1.0, "saturation": 1.0}
    assert np.allclose(degrade.apply_tone(rgb, ident), rgb, atol=1e-6)
    up = dict(ident, exposure=1.0)
    assert np.allclose(degrade.apply_tone(rgb, up), 2 * rgb, atol=1e-6)
    mask = np.zeros((8, 8), np.float32)
    mask[2:4, 2:4] = 1
    out = degrade.composite(rgb, 2 * rgb, mask)
    assert np.allclose(out[2:4, 2:4], 2 * rgb[2:4, 2:4]) and np.allclose(out[5:], rgb[5:])


def test_shadow_mask_finds_darkening_outside_the_insert():
    full = np.full((10, 10, 3), 0.5, np.float32)
    without = full.copy()
    full[6:, :3] = 0.2  # shadow
    insert = np.zeros((10, 10), np.float32)
    insert[6:, 5:] = 1
    m = degrade.shadow_mask(full, without, insert)
    assert m[6:, :3].min() == 1.0 and m[:5].max() == 0.0 and m[6:, 5:].max() == 0.0


def test_texture_selection_keeps_surface_colors_only():
    """The photo textures for floors and walls: color maps of surfaces, no
    normal/gloss/glow maps, effects, trims or tiny files."""
    from training.synth.assets import texture_wanted

    big = 50_000
    assert texture_wanted("textures/egyptsoc_floor/woodmgrid2a.tga", big)
    assert texture_wanted("textures/evil1_walls/wallpaperd_old.jpg", big)
    assert not texture_wanted("textures/evil1_walls/wallpaperd_old_norm.jpg", big)
    assert not texture_wanted("textures/evil1_walls/wallpaperd_old_gloss.tga", big)
    assert not texture_wanted("textures/evil8_trim/metal_trim.jpg", big)
    assert not texture_wanted("textures/evil4_lights/wall_light.jpg", big)
    assert not texture_wanted("textures/evil1_walls/wallpaperd_old.jpg", 1_000)
    assert not texture_wanted("models/evil1_walls/wall.jpg", big)
    assert not texture_wanted("textures/evil1_walls/wall.png", big)


def test_a_render_stopped_from_outside_is_not_a_failed_scene(tmp_path):
    """A render ended by SIGTERM (someone freeing the cores) stops the run
    and is rendered again on the next one; a render that exits with an error
    is noted as failed and skipped."""
    import signal
    import stat

    from training.synth import generate

    fake = tmp_path / "python"
    fake.write_text(
        "#!/bin/sh\n"
        'case "$*" in\n'
        '  *"--scene-id 5 "*) kill -TERM $$ ;;\n'
        '  *"--scene-id 6 "*) echo "render broke"; exit 3 ;;\n'
        "esac\n"
        "exit 0\n"
    )
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    out = tmp_path / "data"
    handlers = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    try:
        assert generate.main(["--out", str(out), "--scenes", "5:7", "--bpy-python", str(fake)]) == 130
        assert not (out / "failed").exists()
        generate.main(["--out", str(out), "--scenes", "6", "--bpy-python", str(fake)])
        note = out / "failed" / "scene_000006.txt"
        assert note.exists() and "exit 3" in note.read_text()
    finally:
        signal.signal(signal.SIGTERM, handlers[0])
        signal.signal(signal.SIGINT, handlers[1])


def test_stored_infinities_saturate_and_nan_is_named(tmp_path):
    import pytest

    from training.synth.dataset import DataError, saturate

    a = np.array([1.0, np.inf, -np.inf], np.float32)
    saturate({"target": a}, "scene")
    assert a.tolist() == [1.0, 65504.0, -65504.0]
    with pytest.raises(DataError, match="'input' has NaN"):
        saturate({"input": np.array([np.nan], np.float32)}, "scene")


def test_training_scenes_take_their_own_sample_count_held_out_scenes_keep_theirs(tmp_path):
    import stat

    from training.synth import generate

    log = tmp_path / "calls.txt"
    fake = tmp_path / "python"
    fake.write_text(f'#!/bin/sh\necho "$*" >> {log}\nexit 0\n')
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    args = ["--scenes", "8:11", "--bpy-python", str(fake), "--samples", "32"]
    generate.main([*args, "--out", str(tmp_path / "a"), "--train-samples", "16", "--train-streams", "recon"])
    calls = [c.split() for c in log.read_text().splitlines() if "--scene-id" in c]
    got = {int(c[c.index("--scene-id") + 1]): (c[c.index("--samples") + 1], c[c.index("--streams") + 1]) for c in calls}
    assert got == {8: ("16", "recon"), 9: ("32", "all"), 10: ("16", "recon")}  # 9: held out (k*10-1)
    log.unlink()
    generate.main([*args, "--out", str(tmp_path / "b")])  # without --train-samples every scene takes --samples
    calls = [c.split() for c in log.read_text().splitlines() if "--scene-id" in c]
    assert {c[c.index("--samples") + 1] for c in calls} == {"32"}
