"""Scenes packed for a GPU machine come back as scenes the trainer reads."""

from __future__ import annotations

import json

import numpy as np
import pytest

from training import pack
from training.synth import dataset


def _scene(root, sid: int, rng) -> None:
    d = root / "train" / f"scene_{sid:06d}"
    d.mkdir(parents=True)
    t, h, w = 4, 24, 40
    target = (rng.random((t, h, w, 3)) * 4).astype(np.float16)
    depth = rng.uniform(0.5, 80, (t, h, w)).astype(np.float32)
    depth[:, :4] = 1e10  # the sky
    cov = np.ones((t, h, w, 1), np.float16)
    cov[:, 6:12, 8:20] = 0
    np.savez(
        d / "scene.npz",
        target=target,
        depth=depth,
        motion=rng.uniform(-9, 9, (t, h, w, 2)).astype(np.float16),
        normal=rng.uniform(-1, 1, (t, h, w, 3)).astype(np.float16),
        mask_insert=np.zeros((t, h, w), np.float16),
        mask_shadow=(rng.random((t, h, w)) > 0.9).astype(np.float16),
        world_to_camera=rng.random((t, 4, 4)).astype(np.float32),
        world_to_ndc=rng.random((t, 4, 4)).astype(np.float32),
    )
    recon_depth = depth * rng.uniform(0.9, 1.1, depth.shape).astype(np.float32)
    np.savez(
        d / "s1_recon.npz",
        input=np.concatenate([target * cov, cov], -1),
        depth=recon_depth,
        mask_insert=np.zeros((t, h, w), np.float16),
    )
    np.savez(d / "s2_tone.npz", input=np.concatenate([target * 0.5, cov * 0 + 1], -1))
    if sid % 2 == 0:  # the context views, kept by scenes rendered since 2026-11-27
        ctx_depth = rng.uniform(0.5, 80, (3, h, w)).astype(np.float32)
        ctx_depth[:, :3] = 1e10
        np.savez(
            d / "ctx.npz",
            color=(rng.random((3, h, w, 3)) * 4).astype(np.float16),
            depth=ctx_depth,
            world_to_camera=rng.random((3, 4, 4)).astype(np.float32),
            world_to_ndc=rng.random((3, 4, 4)).astype(np.float32),
        )
    (d / "meta.json").write_text(json.dumps({"scene_id": sid, "streams": {"s1_recon": {}, "s2_tone": {}}}))


def test_a_packed_scene_unpacks_to_what_the_trainer_reads_within_the_stated_precision(tmp_path):
    rng = np.random.default_rng(5)
    for sid in range(5):
        _scene(tmp_path / "data", sid, rng)
    assert pack.main(["pack", "--data", str(tmp_path / "data"), "--scenes", "3", "--out", str(tmp_path / "pk")]) is None
    # Three spread over five: the first, the middle, the last.
    assert sorted(p.name for p in (tmp_path / "pk" / "train").iterdir()) == [
        "scene_000000.xz",
        "scene_000002.xz",
        "scene_000004.xz",
    ]
    pack.main(["unpack", "--pack", str(tmp_path / "pk"), "--data", str(tmp_path / "out")])
    scenes = dataset.list_scenes(tmp_path / "out", "train")
    assert [s.name for s in scenes] == ["scene_000000", "scene_000002", "scene_000004"]
    for s in scenes:
        # Only the stream that travelled is listed.
        assert dataset.scene_streams(s) == ["s1_recon"]
        a = dataset.load_sample(tmp_path / "data" / "train" / s.name, "s1_recon")
        b = dataset.load_sample(s, "s1_recon")
        assert a["meta"]["scene_id"] == b["meta"]["scene_id"]
        for k, bits in (("input", 7), ("target", 7), ("motion", 8)):
            # float16 with the low mantissa bits cleared: within 2^-bits relative.
            tol = 2.0**-bits * np.abs(a[k]) + 1e-3
            assert np.all(np.abs(a[k] - b[k]) <= tol), k
        # The stream's own depth, the sky clamped to float16's largest.
        near = a["depth"] < 6e4
        assert np.all(np.abs(a["depth"][near] - b["depth"][near]) <= 2.0**-8 * a["depth"][near])
        assert np.all((b["depth"][~near] >= 6.5e4) & np.isfinite(b["depth"][~near]))
        assert np.array_equal(a["mask_shadow"], b["mask_shadow"])
        assert np.array_equal(a["world_to_ndc"], b["world_to_ndc"])
        assert not b["normal"].any() and b["normal"].shape == a["normal"].shape
        # The context views travel with the reconstruction stream; empty depth stays empty.
        assert dataset.has_context(s) == dataset.has_context(tmp_path / "data" / "train" / s.name)
        if dataset.has_context(s):
            with np.load(tmp_path / "data" / "train" / s.name / "ctx.npz") as x, np.load(s / "ctx.npz") as y:
                assert np.all(np.abs(x["color"] - y["color"]) <= 2.0**-7 * np.abs(x["color"]) + 1e-3)
                sky = x["depth"] >= 1e9
                assert y["depth"].dtype == np.float32 and np.all(y["depth"][sky] == 1e10)
                assert np.all(np.abs(x["depth"][~sky] - y["depth"][~sky]) <= 2.0**-8 * x["depth"][~sky])
                assert np.array_equal(x["world_to_ndc"], y["world_to_ndc"])


def test_the_budget_stops_the_pack_before_it_is_exceeded(tmp_path):
    rng = np.random.default_rng(6)
    for sid in range(4):
        _scene(tmp_path / "data", sid, rng)
    one = len(pack.pack_scene(tmp_path / "data" / "train" / "scene_000000", ["s1_recon"]))
    budget = 2.5 * one / 2**20
    pack.main(["pack", "--data", str(tmp_path / "data"), "--budget-mb", str(budget), "--out", str(tmp_path / "pk")])
    files = list((tmp_path / "pk" / "train").iterdir())
    assert 1 <= len(files) <= 2 and sum(f.stat().st_size for f in files) <= budget * 2**20


def test_parts_carry_every_scene_once_each_within_the_budget(tmp_path):
    rng = np.random.default_rng(8)
    for sid in range(5):
        _scene(tmp_path / "data", sid, rng)
    sizes = [len(pack.pack_scene(d, ["s1_recon"])) for d in sorted((tmp_path / "data" / "train").iterdir())]
    budget = 2.2 * max(sizes) / 2**20
    args = ["pack", "--data", str(tmp_path / "data"), "--budget-mb", str(budget), "--out", str(tmp_path / "pk")]
    pack.main([*args, "--parts"])
    parts = sorted((tmp_path / "pk").iterdir())
    assert [p.name for p in parts] == [f"part{i:02d}" for i in range(1, len(parts) + 1)] and len(parts) >= 3
    names = []
    for p in parts:
        files = list((p / "train").iterdir())
        assert files and sum(f.stat().st_size for f in files) <= budget * 2**20
        names += [f.stem for f in files]
        pack.main(["unpack", "--pack", str(p), "--data", str(tmp_path / "back")])
    assert sorted(names) == [f"scene_{i:06d}" for i in range(5)]
    # Packing again over them is refused: a stale part would travel as one of the new ones.
    with pytest.raises(SystemExit):
        pack.main([*args, "--parts"])
    back = dataset.list_scenes(tmp_path / "back", "train")
    assert [d.name for d in back] == sorted(names)
    assert dataset.load_sample(back[-1], "s1_recon")["input"].shape[0] == 4
    # Unpacked by several processes: the same scenes, bit for bit.
    pack.main(["unpack", "--pack", str(parts[0]), "--data", str(tmp_path / "par"), "--jobs", "2"])
    par = dataset.list_scenes(tmp_path / "par", "train")
    assert par and [d.name for d in par] == [f.stem for f in sorted((parts[0] / "train").iterdir())]
    for d in par:
        a, b = dataset.load_sample(d, "s1_recon"), dataset.load_sample(tmp_path / "back" / "train" / d.name, "s1_recon")
        assert all(np.array_equal(a[k], b[k]) for k in ("input", "target", "depth", "motion"))
    # A scene larger than one part is an error, not a part over the budget.
    with pytest.raises(SystemExit, match="more than the budget"):
        pack.main(
            [
                "pack",
                "--data",
                str(tmp_path / "data"),
                "--budget-mb",
                str(0.5 * min(sizes) / 2**20),
                "--out",
                str(tmp_path / "small"),
                "--parts",
            ]
        )


def test_byte_planes_stored_flat_read_the_same(tmp_path):
    import io
    import lzma

    _scene(tmp_path / "data", 0, np.random.default_rng(7))
    scene = tmp_path / "data" / "train" / "scene_000000"
    blob = pack.pack_scene(scene, ["s1_recon"])
    with np.load(io.BytesIO(lzma.decompress(blob))) as z:
        flat = {k: (z[k] if k == "header" or "/world_" in k else z[k].reshape(-1)) for k in z.files}
    buf = io.BytesIO()
    np.savez(buf, **flat)
    pack.unpack_scene(blob, tmp_path / "a")
    pack.unpack_scene(lzma.compress(buf.getvalue()), tmp_path / "b")
    a, b = dataset.load_sample(tmp_path / "a", "s1_recon"), dataset.load_sample(tmp_path / "b", "s1_recon")
    for k in ("input", "target", "depth", "motion"):
        assert np.array_equal(a[k], b[k]) and np.isfinite(b[k]).all()


def test_the_reconstruction_is_made_again_from_the_context_views_on_unpacking(tmp_path):
    from training.synth import degrade
    from training.tests.test_synth import look_at

    rng = np.random.default_rng(7)
    sid, seed, t, h, w = 12, 1, 3, 36, 64
    d = tmp_path / "data" / "train" / f"scene_{sid:06d}"
    d.mkdir(parents=True)
    views = [look_at([x, 1.2, -4], [0, 0.5, 0], 0.9, w / h) for x in (-1.0, 1.5)]
    frames = [look_at([0.4 * k, 1.0, -3.5], [0, 0.5, 0], 0.9, w / h) for k in range(t)]
    ctx_depth = rng.uniform(3, 6, (2, h, w)).astype(np.float32)
    ctx_depth[:, :5] = 1e10  # the sky
    ctx_color = (rng.random((2, h, w, 3)) * 3).astype(np.float16)
    np.savez(
        d / "ctx.npz",
        color=ctx_color,
        depth=ctx_depth,
        world_to_camera=np.stack([v[0] for v in views]),
        world_to_ndc=np.stack([v[1] for v in views]),
    )
    rec, rec_depth, _ = degrade.reconstruction_inputs(
        np.random.default_rng([seed, sid, 1]), list(ctx_color.astype(np.float32)), list(ctx_depth), views, frames, w, h
    )
    target = (rng.random((t, h, w, 3)) * 3).astype(np.float16)
    np.savez(
        d / "scene.npz",
        target=target,
        depth=rng.uniform(3, 6, (t, h, w)).astype(np.float32),
        motion=np.zeros((t, h, w, 2), np.float16),
        normal=np.zeros((t, h, w, 3), np.float16),
        mask_insert=np.zeros((t, h, w), np.float16),
        mask_shadow=np.zeros((t, h, w), np.float16),
        world_to_camera=np.stack([f[0] for f in frames]),
        world_to_ndc=np.stack([f[1] for f in frames]),
    )
    zeros = np.zeros((t, h, w), np.float16)
    np.savez(d / "s1_recon.npz", input=rec.astype(np.float16), depth=rec_depth, mask_insert=zeros)
    (d / "meta.json").write_text(json.dumps({"scene_id": sid, "seed": seed, "streams": {"s1_recon": {}}}))
    assert (rec[..., 3] < 0.5).any() and (rec[..., 3] > 0.95).any()  # holes and covered pixels

    blob = pack.pack_scene(d, ["s1_recon"])
    pack.unpack_scene(blob, tmp_path / "out" / d.name)
    a = dataset.load_sample(d, "s1_recon")
    b = dataset.load_sample(tmp_path / "out" / d.name, "s1_recon")
    # Coverage and depth as made from the views; colors within the views' packed precision.
    assert np.array_equal(a["input"][..., 3], b["input"][..., 3])
    assert np.array_equal(a["depth"], b["depth"])
    assert np.all(np.abs(a["input"][..., :3] - b["input"][..., :3]) <= 2.0**-6 * np.abs(a["input"][..., :3]) + 1e-3)
    assert dataset.has_context(tmp_path / "out" / d.name)
    # Without its views the stream's input and depth travel instead.
    (d / "ctx.npz").unlink()
    assert len(pack.pack_scene(d, ["s1_recon"])) > len(blob)


def test_motion_travels_as_what_the_cameras_do_not_explain(tmp_path):
    import io
    import lzma

    from training.synth import degrade
    from training.tests.test_synth import look_at

    rng = np.random.default_rng(8)
    t, h, w = 4, 36, 64
    frames = [look_at([0.3 * k, 1.0 + 0.05 * k, -3.5], [0, 0.5, 0], 0.9, w / h) for k in range(t)]
    w2c, w2ndc = np.stack([f[0] for f in frames]), np.stack([f[1] for f in frames])
    depth = np.broadcast_to(np.linspace(2, 9, h, dtype=np.float32)[:, None], (t, h, w)).copy()
    depth[:, :4] = 1e10  # the sky
    motion = degrade.camera_motion(pack._as_unpacked(depth, pack.KEEP_BITS["depth"]), w2c, w2ndc)
    assert np.abs(motion[1:, 8:]).max() > 1.0  # the cameras move the pixels
    motion[:, :4] = 0.0  # the renderer gives the sky none
    motion[:, 20:23, 30:40] += rng.uniform(-6, 6, (t, 3, 10, 2))  # a silhouette's mixed vectors
    motion = motion.astype(np.float16)
    zeros = np.zeros((t, h, w), np.float16)
    d = tmp_path / "data" / "train" / "scene_000003"
    d.mkdir(parents=True)
    target = (rng.random((t, h, w, 3)) * 3).astype(np.float16)
    np.savez(
        d / "scene.npz",
        target=target,
        depth=depth,
        motion=motion,
        normal=np.zeros((t, h, w, 3), np.float16),
        mask_insert=zeros,
        mask_shadow=zeros,
        world_to_camera=w2c,
        world_to_ndc=w2ndc,
    )
    cov = np.ones((t, h, w, 1), np.float16)
    np.savez(d / "s1_recon.npz", input=np.concatenate([target, cov], -1), depth=depth * 1.01, mask_insert=zeros)
    (d / "meta.json").write_text(json.dumps({"scene_id": 3, "streams": {"s1_recon": {}}}))

    blob = pack.pack_scene(d, ["s1_recon"])
    with np.load(io.BytesIO(lzma.decompress(blob))) as z:
        assert "motion_residual" in z.files and "scene/motion" not in z.files
    pack.unpack_scene(blob, tmp_path / "out" / d.name)
    a = dataset.load_sample(d, "s1_recon")
    b = dataset.load_sample(tmp_path / "out" / d.name, "s1_recon")
    m_a, m_b = a["motion"].astype(np.float32), b["motion"].astype(np.float32)
    # Within half a step of 1/256 px and float16's own rounding: finer than the
    # 8 mantissa bits the motion kept when it travelled itself.
    assert np.all(np.abs(m_a - m_b) <= 0.5 / pack.MOTION_STEPS + 2.0**-11 * np.abs(m_a) + 1e-6)
    near = a["depth"] < 6e4  # the stream's own depth still, not the scene's that travelled with the motion
    assert np.all(np.abs(a["depth"][near] - b["depth"][near]) <= 2.0**-8 * a["depth"][near])
    # Motion no camera explains within int16's steps travels as itself.
    np.savez(d / "scene.npz", **{**dict(np.load(d / "scene.npz")), "motion": (motion + 200).astype(np.float16)})
    with np.load(io.BytesIO(lzma.decompress(pack.pack_scene(d, ["s1_recon"])))) as z:
        assert "motion_residual" not in z.files and "scene/motion" in z.files
