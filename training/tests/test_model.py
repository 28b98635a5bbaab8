"""Checks of the network, its runtime contract and the ONNX export (PyTorch + ONNX Runtime)."""

import json
import math
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from training import export as hz_export  # noqa: E402
from training.model import (  # noqa: E402
    Enhancer,
    ModelConfig,
    assemble_input,
    count_macs,
    decode,
    encode,
    frame_scale,
    margin_share,
    reproject_hop,
)
from training.synth import degrade  # noqa: E402


def test_encoding_matches_the_runtime_formula():
    rng = np.random.default_rng(0)
    rgba = rng.random((1, 4, 6, 7)).astype(np.float32)
    rgba[:, 3, :2] = 0.0  # holes
    rgba[:, :3] *= rgba[:, 3:4]
    a = rgba[0, 3]
    lum = 0.2126 * rgba[0, 0] + 0.7152 * rgba[0, 1] + 0.0722 * rgba[0, 2]
    ok = a >= 1e-3
    lavg = math.exp((a[ok] * np.log(1e-4 + lum[ok] / a[ok])).sum() / a[ok].sum())
    s = frame_scale(torch.from_numpy(rgba), 0.18)
    assert abs(float(s[0]) - 0.18 / lavg) < 1e-4 * (0.18 / lavg)
    x = torch.from_numpy(rgba[:, :3])
    y = encode(x, s, 8.0)
    assert torch.allclose(y, torch.log2(1 + x * s.view(-1, 1, 1, 1)) / 8.0, atol=1e-6)
    assert torch.allclose(decode(y, s, 8.0), x, atol=1e-5)


def test_reprojection_hop_agrees_with_the_convention():
    rng = np.random.default_rng(1)
    prev = rng.random((12, 20, 3)).astype(np.float32)
    mv = rng.uniform(-3, 3, (12, 20, 2)).astype(np.float32)
    ref, valid = degrade.warp_bilinear(prev, mv)
    img = torch.from_numpy(prev.transpose(2, 0, 1))[None]
    ones = torch.ones(1, 1, 12, 20)
    got, val = reproject_hop(img, ones, None, None, torch.from_numpy(mv.transpose(2, 0, 1))[None])
    inside = (val[0, 0].numpy() > 0.999) & (valid > 0)
    assert inside.mean() > 0.5
    assert np.abs(got[0].numpy().transpose(1, 2, 0)[inside] - ref[inside]).max() < 1e-5


def test_reprojection_depth_test_invalidates_disocclusions():
    img = torch.ones(1, 3, 4, 4)
    ones = torch.ones(1, 1, 4, 4)
    d_prev = torch.full((1, 1, 4, 4), 2.0)
    d_cur = torch.full((1, 1, 4, 4), 2.0)
    d_cur[..., 0, 0] = 5.0  # a surface that was hidden in the previous frame
    _, val = reproject_hop(img, ones, d_prev, d_cur, torch.zeros(1, 2, 4, 4))
    assert val[0, 0, 0, 0] == 0 and val[0, 0, 1:, 1:].min() == 1


def test_network_shapes_cost_and_history_dropout():
    cfg = ModelConfig()
    m = Enhancer(cfg)
    assert cfg.spatial_multiple == 16
    assert len(cfg.input_channels()) == 5 + 4 * cfg.context_frames
    macs, params = count_macs(m, 576, 1024)
    assert params * 4 < 8 * 1024 * 1024
    assert macs < 20e9
    rgba = torch.rand(2, 4, 32, 48)
    s = frame_scale(rgba, cfg.key)
    x = assemble_input(cfg, rgba, torch.zeros(2, 1, 32, 48), [], s)
    assert x.shape == (2, 21, 32, 48)
    assert x[:, 5:].abs().max() == 0  # no history: zeros and validity 0
    assert m(x).shape == (2, 3, 32, 48)


def test_prior_fills_holes_from_history_then_push_pull():
    cfg = ModelConfig(widths=(8, 8, 12, 16), prior_floor=0.0, prior_gate=False)
    m = Enhancer(cfg)
    h, w = 48, 64
    x = torch.zeros(1, len(cfg.input_channels()), h, w)
    x[:, 0:3] = 0.4
    x[:, 3] = 1.0
    x[:, 3, 10:30, 20:50] = 0.0  # a hole
    x[:, 0:3, 10:30, 20:50] = 0.0
    p = m.prior(x)
    # Covered pixels keep the input; a hole in a flat image is filled with its colour.
    assert torch.allclose(p, torch.full_like(p, 0.4), atol=1e-5)
    # Valid history wins over push-pull inside the hole, and only there.
    x[:, 5:8] = 0.9
    x[:, 8, 10:20] = 1.0
    p = m.prior(x)
    assert torch.allclose(p[:, :, 10:20, 20:50], torch.full((1, 3, 10, 30), 0.9), atol=1e-5)
    assert torch.allclose(p[:, :, 30:, :], torch.full((1, 3, h - 30, w), 0.4), atol=1e-5)
    # A hole reaching the window's edge, and odd sizes, still fill without NaN.
    y = torch.rand(1, len(cfg.input_channels()), 37, 53)
    y[:, 3, :, :40] = 0.0
    assert torch.isfinite(m.prior(y)).all()


def _upsample_far_reference(f, fd, size, tol):
    """The far-side upsampling as defined: per output phase and per tap."""
    import torch.nn.functional as F

    taps = {0: ((-1, 0.25), (0, 0.75)), 1: ((0, 0.75), (1, 0.25))}
    h, w = fd.shape[-2:]
    pf = F.pad(f, (1, 1, 1, 1), mode="replicate")
    pd = F.pad(fd, (1, 1, 1, 1), mode="replicate")
    limit = -F.max_pool2d(-pd, 2, stride=1) * (1 + tol)
    phases = []
    for py in (0, 1):
        for px in (0, 1):
            lim = limit[..., py : py + h, px : px + w]
            acc = wsum = 0
            for dy, wy in taps[py]:
                for dx, wx in taps[px]:
                    d = pd[..., 1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
                    k = (d <= lim).to(f.dtype) * (wy * wx)
                    acc = acc + k * pf[..., 1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
                    wsum = wsum + k
            phases.append(acc / wsum)
    n, ch = f.shape[:2]
    return F.pixel_shuffle(torch.stack(phases, 2).reshape(n, ch * 4, h, w), 2)[..., : size[0], : size[1]]


def test_the_far_side_upsampling_is_the_per_tap_definition():
    from training.model import upsample_far

    torch.manual_seed(3)
    for h, w, size in ((37, 51, (73, 101)), (37, 51, (74, 102)), (8, 16, (16, 32))):
        f = torch.rand(2, 3, h, w)
        fd = torch.rand(2, 1, h, w)
        fd[..., 2:6, 3:9] *= 0.01  # a far patch: its neighbours take it alone
        fd[..., 0, :] = fd[..., 1, :]  # ties take every tap
        got = upsample_far(f, fd, size, 0.05)
        assert got.shape[-2:] == size
        assert torch.allclose(got, _upsample_far_reference(f, fd, size, 0.05), atol=1e-6)


def test_the_depth_aware_prior_fills_a_disocclusion_from_the_background():
    from training.model import push_pull_clamped, push_pull_depth

    h, w = 48, 64

    def scene(lo, hi):
        # A near object (left, dark) and the far background (right, bright);
        # the hole between them is what the object uncovered.
        c = torch.full((1, 3, h, w), 0.8)
        c[..., :lo] = 0.2
        disp = torch.full((1, 1, h, w), 0.1)
        disp[..., :lo] = 0.5
        cov = torch.ones(1, 1, h, w)
        cov[..., lo:hi] = 0.0
        return c, disp, cov

    # A crack two pixels wide takes the background alone; the plain fill mixes in the object.
    c, disp, cov = scene(29, 31)
    plain = push_pull_clamped(c * cov, cov, 8)
    aware = push_pull_depth(c * cov, cov, cov.clone(), disp, 8, 0.05)
    assert torch.allclose(aware[..., 29:31], torch.full((1, 3, h, 2), 0.8))
    assert plain[..., 29].max() < 0.4
    # A wider hole: every pixel of it nearer the background's color than the plain fill.
    c, disp, cov = scene(28, 36)
    known = c * cov
    plain = push_pull_clamped(known, cov, 8)
    aware = push_pull_depth(known, cov, cov.clone(), disp, 8, 0.05)
    assert (aware[..., 28:36] >= plain[..., 28:36] - 1e-6).all()
    assert aware[..., 28:36].mean() > plain[..., 28:36].mean() + 0.02
    # Known pixels keep their color; without depth differences the fill is plain push-pull.
    assert torch.allclose(aware[..., :28], c[..., :28]) and torch.allclose(aware[..., 36:], c[..., 36:])
    flat = push_pull_depth(known, cov, cov.clone(), torch.full_like(disp, 0.3), 8, 0.05)
    assert torch.allclose(flat, plain, atol=1e-6)
    # In the model: the last input channel is the disparity, read by the prior alone.
    cfg = ModelConfig(widths=(8, 8, 12, 16), prior_floor=0.0, prior_gate=False, prior_depth_tol=0.05)
    assert cfg.input_channels()[-1] == "disparity" and cfg.network_channels() == len(cfg.input_channels()) - 1
    m = Enhancer(cfg)
    assert m.stem[0].in_channels == Enhancer(ModelConfig(widths=(8, 8, 12, 16))).stem[0].in_channels
    x = torch.zeros(1, len(cfg.input_channels()), h, w)
    x[:, 0:3], x[:, 3:4], x[:, -1:] = c, cov, disp
    assert torch.allclose(m.prior(x), aware, atol=1e-6)
    rgba = torch.cat([known, cov], 1)
    depth = 1 / disp - 1
    y = assemble_input(cfg, rgba, torch.zeros(1, 1, h, w), [], frame_scale(rgba, cfg.key), depth)
    assert torch.allclose(y[:, -1:], disp, atol=1e-6)
    # Odd sizes, holes at the edges: finite everywhere.
    z = torch.rand(1, len(cfg.input_channels()), 37, 53)
    z[:, 3, :, :20] = 0.0
    assert torch.isfinite(m.prior(z)).all()


def test_prior_drops_faint_colors_and_gates_the_history_by_covered_neighbours():
    cfg = ModelConfig(widths=(8, 8, 12, 16))
    assert cfg.prior_floor == 0.95 and cfg.prior_gate and not cfg.correction_history
    m = Enhancer(cfg)
    h, w = 48, 64
    x = torch.zeros(1, len(cfg.input_channels()), h, w)
    x[:, 0:3] = 0.4
    x[:, 3] = 1.0
    # A crack one pixel wide (col 50) and a wide hole (rows 10..30, cols 10..40).
    x[:, 3, 5:40, 50] = 0.0
    x[:, 3, 10:30, 10:40] = 0.0
    # A faint pixel with a wrong color, in the middle of the wide hole's row band.
    x[:, 3, 20, 45] = 0.5
    x[:, 0:3, 20, 45] = 5.0
    # History: 0.9, valid everywhere.
    x[:, 5:8] = 0.9
    x[:, 8] = 1.0
    p = m.prior(x)
    # The crack takes its neighbours (0.4), not the history.
    assert torch.allclose(p[:, :, 8:37, 50], torch.full((1, 3, 29), 0.4), atol=1e-5)
    # The faint pixel lost its color and took its neighbours too.
    assert torch.allclose(p[:, :, 20, 45], torch.full((1, 3), 0.4), atol=1e-5)
    # The wide hole's inside (over 3 pixels from covered ones) takes the history.
    assert torch.allclose(p[:, :, 14:26, 14:36], torch.full((1, 3, 12, 22), 0.9), atol=1e-5)
    # Covered pixels keep their color.
    assert torch.allclose(p[:, :, 35:, :45], torch.full((1, 3, h - 35, 45), 0.4), atol=1e-5)


def test_the_correction_sees_the_history_only_when_configured():
    torch.manual_seed(0)
    x = torch.rand(1, 21, 32, 48)
    y = x.clone()
    y[:, 5:] = torch.rand(1, 16, 32, 48)
    # Covered everywhere: the prior is the input color whatever the history.
    x[:, 3] = y[:, 3] = 1.0
    for seen in (False, True):
        m = Enhancer(ModelConfig(widths=(8, 8, 12, 16), correction_history=seen))
        torch.nn.init.normal_(m.head.weight, std=0.1)
        with torch.no_grad():
            same = torch.equal(m(x), m(y))
        assert same is (not seen)


def test_weights_from_onnx_rebuild_the_exported_model(tmp_path):
    from training.export import export, weights_from_onnx

    torch.manual_seed(1)
    m = Enhancer(ModelConfig(widths=(8, 8, 12, 16), stem=16, correction_history=True, prior_gate=False))
    # Distinct values everywhere, as trained weights have (the exporter shares
    # equal initializers, such as the zero biases of a fresh model).
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(std=0.1)
    export(m, tmp_path / "m")
    back = weights_from_onnx(tmp_path / "m.onnx", correction_history=True, prior_gate=False, prior_floor=0.95)
    assert back.cfg.widths == (8, 8, 12, 16) and back.cfg.stem == 16
    for k, v in m.state_dict().items():
        assert torch.equal(back.state_dict()[k], v), k
    # Old exported models (no guards in their prior) can be re-exported as they were.
    old = weights_from_onnx(tmp_path / "m.onnx", correction_history=True, prior_gate=False, prior_floor=0.0)
    x = torch.rand(1, 21, 32, 48)
    m.cfg.prior_floor = 0.0
    with torch.no_grad():
        assert torch.allclose(old(x), m(x), atol=1e-6)


def test_an_exported_file_says_its_whole_configuration(tmp_path):
    """What the graph cannot tell (the depth-aware prior's tolerance, the
    in-graph margin) comes back from the file's metadata; a file without it
    whose input reads depth is refused rather than rebuilt without it."""
    import onnx

    from training.export import CONFIG_METADATA, export, weights_from_onnx

    m = _blend_model(prior_depth_tol=0.05, graph_margin=2, prior_frames=2)
    export(m, tmp_path / "m")
    back = weights_from_onnx(tmp_path / "m.onnx")
    assert back.cfg == m.cfg
    x = torch.rand(1, len(m.cfg.input_channels()), 32, 48)
    x[:, 3] = (torch.rand(32, 48) > 0.3).float()
    x[:, -1] = torch.where(torch.rand(32, 48) > 0.5, 0.5, 0.1)
    with torch.no_grad():
        assert torch.allclose(back(x), m(x), atol=1e-6)
    assert weights_from_onnx(tmp_path / "m.onnx", graph_margin=0).cfg.graph_margin == 0
    # Exported before the metadata: refused without the tolerance.
    proto = onnx.load(str(tmp_path / "m.onnx"))
    kept = [p for p in proto.metadata_props if p.key != CONFIG_METADATA]
    del proto.metadata_props[:]
    proto.metadata_props.extend(kept)
    onnx.save(proto, str(tmp_path / "m.onnx"))
    with pytest.raises(ValueError, match="prior_depth_tol"):
        weights_from_onnx(tmp_path / "m.onnx")
    old = weights_from_onnx(tmp_path / "m.onnx", prior_depth_tol=0.05, graph_margin=2)
    with torch.no_grad():
        assert torch.allclose(old(x), m(x), atol=1e-6)


def test_hole_correction_leaves_holes_to_the_prior_and_the_rest_to_the_network(tmp_path):
    from training.export import export, verify, weights_from_onnx

    torch.manual_seed(8)
    full = Enhancer(ModelConfig(widths=(8, 8, 12, 16), prior_depth_tol=0.05))
    with torch.no_grad():
        for p in full.parameters():
            p.normal_(std=0.1)
    none = Enhancer(ModelConfig.from_dict({**full.cfg.to_dict(), "hole_correction": 0.0}))
    none.load_state_dict(full.state_dict())
    prior_only = Enhancer(full.cfg)
    prior_only.load_state_dict(full.state_dict())
    with torch.no_grad():
        prior_only.head.weight.zero_()
        prior_only.head.bias.zero_()
    x = torch.rand(1, len(full.cfg.input_channels()), 32, 48)
    x[:, 3] = 1.0
    x[:, 3, 8:20, 10:30] = 0.0  # a hole
    x[:, 3, 4, 4] = 0.97  # covered above the floor: not a hole
    hole = (x[:, 3:4] < full.cfg.prior_floor).expand(-1, 3, -1, -1)
    with torch.no_grad():
        got, ref, fill = none(x), full(x), prior_only(x)
    assert torch.equal(got[hole], fill[hole]) and torch.equal(got[~hole], ref[~hole])
    assert not torch.allclose(ref[hole], fill[hole])
    export(none, tmp_path / "m")
    assert verify(none, tmp_path / "m.onnx") < 1e-4
    assert weights_from_onnx(tmp_path / "m.onnx").cfg.hole_correction == 0.0


def test_a_lean_graph_reads_only_its_history_frames_and_comes_back_whole(tmp_path):
    """The default wiring leaves the history channels out of the correction's
    input and, with `prior_frames`, the prior reads the first frames only: the
    same output where the later slots carry no frame, a manifest that says
    `history_read`, and weights that re-export to the same model."""
    from training.export import export, weights_from_onnx

    torch.manual_seed(2)
    full = Enhancer(ModelConfig(widths=(8, 8, 12, 16)))
    with torch.no_grad():
        for p in full.parameters():
            p.normal_(std=0.1)
    lean = Enhancer(ModelConfig(widths=(8, 8, 12, 16), prior_frames=2))
    lean.load_state_dict(full.state_dict())
    x = torch.rand(1, 21, 32, 48)
    x[:, 3] = (torch.rand(32, 48) > 0.4).float()
    x[:, 3, 8:24, 10:40] = 0.0  # a wide hole, which the history may fill
    x[:, 8, 8:24, 10:40] = 0.0  # slot 0 has no data there
    x[:, 13:] = 0.0  # slots 2 and 3: no frame
    with torch.no_grad():
        assert torch.allclose(lean(x), full(x), atol=1e-6)
        # Slot 2 with a frame: the lean prior does not read it.
        y = x.clone()
        y[:, 13:16] = 5.0
        y[:, 16] = 1.0
        assert torch.equal(lean(y), lean(x)) and not torch.equal(full(y), full(x))
    manifest = export(lean, tmp_path / "m", repair_margin=2)
    assert manifest["history_read"] == 2 and manifest["context_frames"] == 4
    assert manifest["repair_margin"] == 2 and "repair_margin" not in export(full, tmp_path / "f")
    back = weights_from_onnx(tmp_path / "m.onnx")
    assert back.cfg.prior_frames == 2
    with torch.no_grad():
        assert torch.allclose(back(y), lean(y), atol=1e-6)
    # The correction reading the history cannot skip slots.
    with pytest.raises(ValueError, match="blind to the history"):
        export(Enhancer(ModelConfig(widths=(8, 8, 12, 16), prior_frames=2, correction_history=True)), tmp_path / "h")


def test_the_edge_fill_is_a_manifest_field_of_a_runtime_prior(tmp_path):
    """``--edge-fill``: the runtime's edge-continuing fill, set in the manifest's
    prior; a model whose prior the runtime does not compute refuses it and
    writes nothing."""
    from training.export import export

    torch.manual_seed(3)
    model = Enhancer(ModelConfig(widths=(8, 8, 12, 16), prior_input=True))
    manifest = export(model, tmp_path / "e", edge_fill=0.5)
    assert manifest["prior"]["edge_fill"] == 0.5
    assert json.loads((tmp_path / "e.json").read_text())["prior"]["edge_fill"] == 0.5
    assert "edge_fill" not in export(model, tmp_path / "n")["prior"]
    with pytest.raises(ValueError, match="edge_fill"):
        export(Enhancer(ModelConfig(widths=(8, 8, 12, 16))), tmp_path / "g", edge_fill=0.5)
    assert not (tmp_path / "g.onnx").exists() and not (tmp_path / "g.json").exists()


@pytest.mark.parametrize("prior,depth_tol", [(True, 0.0), (False, 0.0), (True, 0.05)])
def test_export_matches_pytorch_in_onnx_runtime(tmp_path, prior, depth_tol):
    pytest.importorskip("onnxruntime")
    torch.manual_seed(0)
    m = Enhancer(ModelConfig(widths=(8, 8, 12, 16), prior=prior, prior_depth_tol=depth_tol))
    torch.nn.init.normal_(m.head.weight, std=0.05)  # a non-trivial residual
    manifest = hz_export.export(m, tmp_path / "model")
    diff = hz_export.verify(m, tmp_path / "model.onnx", sizes=((48, 64), (32, 96), (144, 256)))
    assert diff < 1e-4
    import onnx

    proto = onnx.load(str(tmp_path / "model.onnx"))
    assert proto.ir_version <= 13
    assert [i.name for i in proto.graph.input] == ["input"]
    on_disk = json.loads((tmp_path / "model.json").read_text())
    assert on_disk == manifest and on_disk["residual"] is (not prior)
    assert 16 <= on_disk["tile_overlap"] <= 62 and on_disk["tile_size"] >= 4 * on_disk["tile_overlap"] + 2
    assert on_disk["input"]["channels"][:5] == ["color.r", "color.g", "color.b", "coverage", "insert"]


@pytest.mark.parametrize("space", ["encoded", "display"])
def test_training_steps_reduce_the_loss_on_a_fixed_window(space):
    from training.train import run_window

    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    n, fr, h, w = 2, 3, 32, 32
    base = torch.from_numpy(rng.random((n, fr, 3, 4, 4)).astype(np.float32))
    tgt = torch.nn.functional.interpolate(base.view(n * fr, 3, 4, 4), size=(h, w), mode="bilinear").view(n, fr, 3, h, w)
    cov = torch.ones(n, fr, 1, h, w)
    cov[..., 10:16, 12:20] = 0.0  # a hole
    noisy = (tgt * 0.7 + 0.05 * torch.randn_like(tgt)).clamp(min=0) * cov
    batch = {
        "input": torch.cat([noisy, cov], 2),
        "target": tgt,
        "depth": torch.full((n, fr, 1, h, w), 3.0),
        "motion": torch.zeros(n, fr, 2, h, w),
        "insert": torch.zeros(n, fr, 1, h, w),
        "shadow": torch.zeros(n, fr, 1, h, w),
        "prefill": 1,
        "temporal": True,
    }
    cfg = {"loss_gain": 4.0, "w_l2": 1.0, "w_patch": 0.2, "w_temporal": 0.5, "patches": 2, "l2_space": space}
    model = Enhancer(ModelConfig(widths=(8, 8, 12, 16)))
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for step in range(100):
        loss, parts, outs = run_window(model, batch, cfg, np.random.default_rng([0, step]))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(parts["l2"])
    assert len(outs) == fr - 1  # the prefilled frame is not predicted
    assert np.mean(losses[-5:]) < 0.3 * np.mean(losses[:3])


@pytest.mark.parametrize("scale", [1.0, 40.0])
def test_the_display_l2_fits_the_benchmarks_mean_where_the_encoded_one_misses_it(scale):
    from training.evaluate import srgb
    from training.train import display

    x = np.linspace(-0.5, 2.0, 401, dtype=np.float32)
    np.testing.assert_allclose(display(torch.from_numpy(x)).numpy(), srgb(x), atol=1e-6)
    # A hole pixel whose truth is dark in half the training items and light
    # in the other half: the best single answer under each loss. The
    # encoding's optimum depends on the frame's exposure scale (brighter than
    # the sRGB mean in a bright frame, darker in a dark one).
    y = torch.tensor([0.02, 0.6]).view(2, 1, 1, 1)
    scale = torch.tensor([scale])
    enc = encode(y, scale, 4.0).mean()  # the encoded L2's optimum: the mean code
    c = enc.clone().requires_grad_(True)
    opt = torch.optim.Adam([c], lr=1e-2)
    for _ in range(600):
        loss = ((display(decode(c.view(1, 1, 1, 1), scale, 4.0)) - display(y)) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    want = srgb(y.numpy()).mean()
    got = display(decode(c.detach().view(1, 1, 1, 1), scale, 4.0)).item()
    encoded = display(decode(enc.view(1, 1, 1, 1), scale, 4.0)).item()
    assert abs(got - want) < 2e-3
    assert abs(encoded - want) > 0.05


class _FakeCache:
    """A SampleCache stand-in: one scene, one stream, T frames of noise."""

    def __init__(self, t=8, h=32, w=48):
        rng = np.random.default_rng(3)
        self.scenes = ["scene"]
        self.streams = {"scene": ["s5_noise"]}
        self.variants = {"scene": 1}
        rgb = rng.random((t, h, w, 3)).astype(np.float32) + 0.05
        self.sample = {
            "input": np.concatenate([rgb, np.ones((t, h, w, 1), np.float32)], -1),
            "target": rgb.copy(),
            "depth": np.full((t, h, w), 3.0, np.float32),
            "motion": np.zeros((t, h, w, 2), np.float32),
            "mask_insert": np.zeros((t, h, w), np.float32),
            "mask_shadow": np.zeros((t, h, w), np.float32),
        }

    def get(self, scene, stream, variant=0):
        return self.sample


def _batch_cfg(**kw):
    cfg = {
        "batch": 3,
        "context_frames": 4,
        "unroll": 3,
        "crop": [32, 48],
        "p_no_history": 0.0,
        "p_drop_insert": 0.0,
        "p_full_prefill": 1.0,
        "p_flicker": 0.0,
    }
    cfg.update(kw)
    return cfg


def test_batches_carry_a_full_history_before_the_window():
    from training.train import make_batch

    cache = _FakeCache()
    for step in range(6):
        b = make_batch(cache, np.random.default_rng([0, step]), _batch_cfg())
        # K = 4 frames before the 3 trained ones, for every item of the batch.
        assert b["prefill"] == 4 and b["input"].shape[1] == 7
    b = make_batch(cache, np.random.default_rng(1), _batch_cfg(p_no_history=1.0))
    assert b["prefill"] == 0 and b["input"].shape[1] == 1 and not b["temporal"]


def test_flicker_changes_the_input_per_frame_and_not_the_target():
    from training.train import make_batch

    cache = _FakeCache()
    # One item: the flicker's own draws come after everything else of it.
    steady = make_batch(cache, np.random.default_rng(5), _batch_cfg(batch=1))
    flicker = make_batch(cache, np.random.default_rng(5), _batch_cfg(batch=1, p_flicker=1.0))
    assert torch.equal(steady["target"], flicker["target"])
    ratio = (flicker["input"][:, :, :3] / steady["input"][:, :, :3]).mean(dim=(3, 4))  # [1, F, 3]
    assert (ratio.std(dim=1) > 1e-3).all()  # a different gain every frame
    assert torch.equal(flicker["input"][:, :, 3], steady["input"][:, :, 3])  # coverage untouched


def _blend_model(**kw):
    torch.manual_seed(4)
    m = Enhancer(ModelConfig(widths=(8, 8, 12, 16), history_blend=True, **kw))
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(std=0.1)
    return m


def test_hole_blend_scales_the_blend_in_holes_only():
    full = _blend_model()
    none = _blend_model(hole_blend=0.0)
    half = _blend_model(hole_blend=0.5)
    plain = _blend_model()
    plain.blend = None  # the estimate before the blend
    x = torch.rand(1, len(full.cfg.input_channels()), 32, 48)
    x[:, 3] = 1.0
    x[:, 3, 8:20, 10:30] = 0.0
    x[:, 8] = 1.0  # history frame 0 valid everywhere
    hole = (x[:, 3:4] < full.cfg.prior_floor).expand(-1, 3, -1, -1)
    with torch.no_grad():
        a, b, c, est = full(x), none(x), half(x), plain(x)
    assert torch.equal(b[~hole], a[~hole]) and torch.equal(c[~hole], a[~hole])
    assert torch.allclose(b[hole], est[hole]) and not torch.allclose(a[hole], est[hole])
    assert torch.allclose(c[hole], (a[hole] + est[hole]) / 2, atol=1e-6)


def test_far_blend_scales_the_blend_beyond_its_nearness_band_only():
    full = _blend_model(graph_margin=2)
    none = _blend_model(graph_margin=2, far_blend=0.0)
    half = _blend_model(graph_margin=2, far_blend=0.5)
    x = torch.rand(1, len(full.cfg.input_channels()), 32, 48)
    x[:, 3] = 1.0
    x[:, 3, 8:20, 10:30] = 0.0
    x[:, 8] = 1.0  # history frame 0 valid everywhere
    near = (margin_share(x[:, 3:4], full.cfg.prior_floor, 2) > 0).expand(-1, 3, -1, -1)
    with torch.no_grad():
        a, b, c = full(x), none(x), half(x)
    assert torch.equal(b[near], a[near]) and torch.equal(c[near], a[near])
    # Beyond the band the repair margin gives the input color back, so
    # without the blend the output is the input there.
    assert torch.equal(b[~near], x[:, :3][~near]) and not torch.allclose(a[~near], x[:, :3][~near])
    assert torch.allclose(c[~near], (a[~near] + b[~near]) / 2, atol=1e-6)


def test_the_blend_layer_split_per_tensor_is_the_layer_on_their_concatenation():
    """`HistoryBlend.down_features` (one convolution per tensor) is the
    stride-4 layer on the 12 concatenated features, within float rounding,
    and trains the same weight."""
    torch.manual_seed(3)
    b = _blend_model().blend
    nn_init = torch.nn.init
    nn_init.normal_(b.down.bias)
    est, clamped, hist = (torch.rand(2, 3, 16, 24) for _ in range(3))
    valid, cov, near = (torch.rand(2, 1, 16, 24) for _ in range(3))
    want = b.down(torch.cat([est, clamped, hist - est, valid, cov, near], 1))
    got = b.down_features(est, clamped, hist, valid, cov, near)
    assert torch.allclose(got, want, atol=1e-5)
    (g1,) = torch.autograd.grad(want.square().sum(), b.down.weight)
    (g2,) = torch.autograd.grad(got.square().sum(), b.down.weight)
    assert torch.allclose(g1, g2, atol=1e-4)


def test_the_history_blend_is_convex_and_silent_without_history():
    """The blend returns the network's estimate where history frame 0 is not
    valid, and elsewhere a point between the estimate and the history (never
    beyond either: fed back, it cannot amplify)."""
    m = _blend_model()
    x = torch.rand(2, 21, 32, 48)
    x[:, 3] = 1.0
    x[:, 8] = 0.0  # no valid history frame 0
    with torch.no_grad():
        est = m.prior(x) + m.correction(torch.cat([x[:, :5], m.prior(x)], 1))
        assert torch.allclose(m(x), est, atol=1e-6)
        x[:, 8] = 1.0
        x[:, 5:8] = est + 0.5  # history brighter than the estimate everywhere
        out = m(x)
    assert not torch.allclose(out, est, atol=1e-4)
    lo = torch.minimum(est, x[:, 5:8]) - 1e-6
    hi = torch.maximum(est, x[:, 5:8]) + 1e-6
    assert bool(((out >= lo) & (out <= hi)).all())
    # `blend_gain` scales the step toward the history.
    m.cfg.blend_gain = 0.5
    with torch.no_grad():
        half = m(x)
    assert torch.allclose(half - est, 0.5 * (out - est), atol=1e-5)


def test_an_in_graph_margin_keeps_covered_colors_away_from_holes():
    """With `graph_margin` 2: covered pixels 3+ px from a hole keep the input
    color, 2 px take 0.4 of the network, holes and 1 px the network's."""
    m = Enhancer(ModelConfig(widths=(8, 8, 12, 16), graph_margin=2))
    plain = Enhancer(ModelConfig(widths=(8, 8, 12, 16)))
    torch.manual_seed(5)
    with torch.no_grad():
        for p in m.parameters():
            p.normal_(std=0.1)
    plain.load_state_dict(m.state_dict())
    x = torch.rand(1, 21, 32, 48)
    x[:, 3] = 1.0
    x[:, 3, 10:14, 20:26] = 0.0
    with torch.no_grad():
        out, net = m(x), plain(x)
    inp = x[:, :3]
    assert torch.equal(out[..., 0:7, :], inp[..., 0:7, :])  # rows 3+ px above the hole
    assert torch.allclose(out[..., 10:14, 20:26], net[..., 10:14, 20:26])
    assert torch.allclose(out[..., 9, 21], net[..., 9, 21])  # 1 px
    assert torch.allclose(out[..., 8, 22], inp[..., 8, 22] + 0.4 * (net[..., 8, 22] - inp[..., 8, 22]), atol=1e-6)


def test_a_blend_model_exports_and_its_weights_come_back(tmp_path):
    pytest.importorskip("onnxruntime")
    from training.export import export, verify, weights_from_onnx

    m = _blend_model(graph_margin=2, prior_frames=2)
    manifest = export(m, tmp_path / "b", stabilize=False)
    assert manifest["history_read"] == 2 and manifest["stabilize"] is False and "repair_margin" not in manifest
    assert verify(m, tmp_path / "b.onnx", sizes=((48, 64), (144, 256))) < 1e-4
    back = weights_from_onnx(tmp_path / "b.onnx", graph_margin=2)
    assert back.cfg.history_blend and back.cfg.blend_width == m.cfg.blend_width
    x = torch.rand(1, 21, 32, 48)
    with torch.no_grad():
        assert torch.allclose(back(x), m(x), atol=1e-6)
    # A model exported without a blend comes back with a fresh one to train.
    plain = _blend_model()
    plain.blend = None
    plain.cfg.history_blend = False
    export(plain, tmp_path / "p")
    fresh = weights_from_onnx(tmp_path / "p.onnx", history_blend=True)
    assert fresh.blend is not None


def test_blend_only_training_leaves_the_rest_of_the_network_as_it_was(tmp_path):
    """`--train-only blend` from an exported model: the blend's weights move,
    every other weight stays bit for bit (the model without history is the one
    it started from)."""
    pytest.importorskip("onnxruntime")
    from training.export import export
    from training.synth import dataset
    from training.train import main

    start = _blend_model()
    start.blend = None
    start.cfg.history_blend = False
    export(start, tmp_path / "start")
    # One tiny scene in the dataset layout, with a hole and camera motion.
    scene = tmp_path / "data" / "train" / "scene_000000"
    scene.mkdir(parents=True)
    rng = np.random.default_rng(0)
    t, h, w = 6, 32, 48
    target = rng.random((t, h, w, 3)).astype(np.float16) + 0.1
    cov = np.ones((t, h, w, 1), np.float16)
    cov[:, 8:16, 10:30] = 0
    np.savez(
        scene / "scene.npz",
        target=target,
        depth=np.full((t, h, w), 3.0, np.float32),
        motion=np.zeros((t, h, w, 2), np.float16),
        normal=np.zeros((t, h, w, 3), np.float16),
        mask_insert=np.zeros((t, h, w), np.float16),
        mask_shadow=np.zeros((t, h, w), np.float16),
        world_to_camera=np.tile(np.eye(4, dtype=np.float32), (t, 1, 1)),
        world_to_ndc=np.tile(np.eye(4, dtype=np.float32), (t, 1, 1)),
    )
    noisy = (target * (1 + 0.2 * rng.standard_normal((t, 1, 1, 3)))).astype(np.float16)
    np.savez(scene / "s1_recon.npz", input=np.concatenate([noisy * cov, cov], -1))
    (scene / "meta.json").write_text(json.dumps({"streams": {"s1_recon": {}}}))
    assert dataset.list_scenes(tmp_path / "data", "train")
    run = tmp_path / "run"
    args = ["--data", str(tmp_path / "data"), "--run", str(run), "--init-onnx", str(tmp_path / "start.onnx")]
    args += ["--history-blend", "--graph-margin", "2", "--train-only", "blend", "--steps", "4", "--batch", "2"]
    args += ["--crop", "32", "48", "--p-no-history", "0", "--log-every", "2"]
    assert main(args) == 0
    ck = torch.load(run / "ckpt_last.pt", weights_only=False)
    assert ck["model_cfg"]["history_blend"] and ck["model_cfg"]["graph_margin"] == 2
    fresh = Enhancer(ModelConfig.from_dict(ck["model_cfg"])).state_dict()
    # As exported (the stem's unread history rows come back as zeros).
    ref = hz_export.weights_from_onnx(tmp_path / "start.onnx").state_dict()
    for k, v in ck["model"].items():
        if k.startswith("blend."):
            continue
        assert torch.equal(v, ref[k]), k
    assert any(not torch.equal(ck["model"][k], fresh[k]) for k in fresh if k.startswith("blend."))


def test_averaged_weights_are_the_share_of_each_and_need_one_architecture(tmp_path):
    cfg = ModelConfig(widths=(8, 8, 12, 16), history_blend=True)
    torch.manual_seed(0)
    a, b = Enhancer(cfg), Enhancer(cfg)
    torch.save({"model": b.state_dict(), "model_cfg": cfg.to_dict()}, tmp_path / "b.pt")
    avg = hz_export.average_weights(a.state_dict(), tmp_path / "b.pt", 0.25, a)
    for k, v in a.state_dict().items():
        assert torch.allclose(avg[k], 0.25 * v + 0.75 * b.state_dict()[k])
    other = Enhancer(ModelConfig(widths=(8, 8, 12, 24), history_blend=True))
    torch.save({"model": other.state_dict(), "model_cfg": other.cfg.to_dict()}, tmp_path / "o.pt")
    with pytest.raises(ValueError, match="do not match"):
        hz_export.average_weights(a.state_dict(), tmp_path / "o.pt", 0.5, a)


@pytest.mark.parametrize("name,tol", [("prior_graph_far", 0.05), ("prior_graph_plain", 0.0)])
def test_the_committed_prior_fixtures_compute_the_trainers_prior(name, tol):
    """`core/tests/fixtures/models/prior_graph_*.onnx` stand for `Enhancer.prior`
    in the runtime's parity test (`the_runtime_prior_is_the_trainers`): they
    must still compute it (else rerun `make_prior_fixtures.py`)."""
    ort = pytest.importorskip("onnxruntime")
    import importlib.util

    here = Path(__file__).resolve().parents[2] / "core/tests/fixtures/models"
    spec = importlib.util.spec_from_file_location("make_prior_fixtures", here / "make_prior_fixtures.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    model = Enhancer(mod.config(tol)).eval()
    sess = ort.InferenceSession(str(here / f"{name}.onnx"), providers=["CPUExecutionProvider"])
    g = torch.Generator().manual_seed(3)
    x = torch.rand(1, len(model.cfg.input_channels()), 48, 80, generator=g)
    cov = x[:, 3:4]
    x[:, 3:4] = torch.where(cov < 0.3, 0.0, torch.where(cov > 0.6, 1.0, cov))
    with torch.no_grad():
        want = model.prior(x).numpy()
    got = sess.run(["output"], {"input": x.numpy()})[0]
    assert np.abs(got - want).max() < 1e-5
