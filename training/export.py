"""Exports a trained checkpoint to ONNX (IR version <= 13) with its manifest.

    .venv-train/bin/python -m training.export --ckpt training/runs/main/ckpt_last.pt --out out/model

or re-exports the weights of an exported model (its checkpoint need not
exist) with the prior and wiring of the current ``ModelConfig`` defaults, or
as the flags say (``--prior-floor``, ``--[no-]prior-gate``,
``--[no-]correction-history``):

    .venv-train/bin/python -m training.export --from-onnx core/models/default.onnx --out out/model

writes ``out/model.onnx`` and ``out/model.json`` (``training/export_contract.md``),
then checks the file with ONNX Runtime against PyTorch on a random input at two
sizes and prints parameters, GMAC at 1024x576 and the largest difference.
To ship it as the library default: copy both files to ``core/models/default.onnx``
and ``core/models/default.json`` and rebuild.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

from training.model import BLEND_STRIDE, Enhancer, ModelConfig, activation_bytes_per_pixel, count_macs

MAX_IR_VERSION = 13
# The ONNX metadata key that holds the exported ModelConfig (`weights_from_onnx`).
CONFIG_METADATA = "harmonizer.model_cfg"
OPSET = 17


def effective_radius(model: Enhancer, size: int = 256, mass: float = 0.99) -> int:
    """Radius (px) around an output pixel holding ``mass`` of the input-gradient
    magnitude, on a random input in [0, 0.3]: the effective receptive field."""
    cin = len(model.cfg.input_channels())
    gen = torch.Generator().manual_seed(0)
    x = torch.rand((1, cin, size, size), generator=gen) * 0.3
    # Full coverage: the prior is then the input color and its push-pull (global
    # in holes, by design) does not count; the network's own reach remains.
    x[:, 3] = 1.0
    x.requires_grad_(True)
    y = graph_of(model)(x)
    c = size // 2
    y[0, :, c, c].sum().backward()
    g = x.grad[0].abs().sum(0)
    total = float(g.sum())
    if total <= 0:
        return 0
    yy, xx = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    dist = torch.maximum((yy - c).abs(), (xx - c).abs())
    for r in range(size // 2):
        if float(g[dist <= r].sum()) >= mass * total:
            return r
    return size // 2


def history_read_of(cfg: ModelConfig) -> int | None:
    """Manifest `history_read`: the history slots the graph reads, where it reads
    fewer than `context_frames` (the prior's `prior_frames`, with a correction
    blind to the history), else None (all)."""
    if cfg.prior_frames <= 0 or cfg.prior_frames >= cfg.context_frames:
        return None
    if cfg.correction_history or not cfg.prior:
        raise ValueError("prior_frames below context_frames needs a prior and a correction blind to the history")
    return cfg.prior_frames


def manifest_for(
    model: Enhancer,
    name: str,
    version: str,
    stabilize: bool = True,
    repair_margin: int | None = None,
    edge_fill: float | None = None,
) -> dict:
    cfg = model.cfg
    history_read = history_read_of(cfg)
    if repair_margin is not None and not 1 <= repair_margin <= 64:
        raise ValueError(f"repair_margin {repair_margin} is out of range 1..=64")
    if edge_fill and not (0 < edge_fill <= 1 and cfg.prior and cfg.prior_input):
        raise ValueError(f"edge_fill {edge_fill} needs a prior computed by the runtime and a share in 0..=1")
    prior = prior_spec(cfg) if cfg.prior and cfg.prior_input else None
    if prior is not None and edge_fill:
        # The runtime's edge-continuing fill in what the history left missing
        # (not in the trainer's prior; the network does not correct holes).
        prior["edge_fill"] = edge_fill
    # Tiled equals untiled output when overlap - overlap/2 >= the receptive radius;
    # the 256 px tile allows at most 63 px (tile_size >= 4 * overlap + 2).
    overlap = int(min(max(2 * effective_radius(model), 16), 62))
    return (
        {
            "format_version": 1,
            "name": name,
            "version": version,
            "context_frames": cfg.context_frames,
            "input": {"name": "input", "channels": cfg.graph_channels()},
            "output": {"name": "output", "channels": ["color.r", "color.g", "color.b"]},
            "residual": not cfg.prior,
            "premultiplied": cfg.premultiplied,
            "encoding": {"kind": "log", "key": cfg.key, "exposure": "frame", "log_range": cfg.log_range},
            # With the prior a 1920x1080 frame is one window, as 1024x576 is
            # (push-pull reaches across the whole window; at 1080p one window ran
            # 11-15 % less inference than two, see the model card); the memory
            # limit may shrink tiles.
            "tile_size": 1920 if cfg.prior else 256,
            "tile_overlap": overlap,
            "spatial_multiple": cfg.spatial_multiple,
            "bytes_per_pixel": activation_bytes_per_pixel(model),
            # The runtime blends the output with its reprojected history, clamped
            # to the local color range (held-out warping error 0.0215 -> 0.0189 for
            # harmonizer-small 1.1.x, PSNR 30.30 -> 30.58 dB).
            "stabilize": stabilize,
        }
        | ({"history_read": history_read} if history_read is not None else {})
        | ({"prior": prior} if prior is not None else {})
        | (
            # Covered pixels farther than this from a hole keep their rendered
            # color (the runtime; measured per model, see the model card).
            {"repair_margin": repair_margin} if repair_margin is not None else {}
        )
    )


class _ResidualFree(torch.nn.Module):
    """The graph of a model without the prior: ``residual: true`` means the runtime
    adds the encoded input color itself, so the exported network returns only the
    correction."""

    def __init__(self, model: Enhancer):
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model.correction(x)


class _PriorInput(torch.nn.Module):
    """The graph of a model whose prior the runtime computes
    (``ModelConfig.prior_input``): the prior is the input's last three
    channels."""

    def __init__(self, model: Enhancer):
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # The model slices its channel groups from the front of `x` and
        # never reads past them: `x[:, :-3]` first would copy every plane
        # (ONNX Runtime fused it with the prior's slice into one Split:
        # 14 ms at 1920x1088 on 2 threads).
        return self.model(x, prior=x[:, -3:])


def graph_of(model: Enhancer) -> torch.nn.Module:
    """The module exported: the complete model with the prior (``residual: false``;
    with ``prior_input`` the prior read from the input), else the correction
    alone (``residual: true``)."""
    if not model.cfg.prior:
        return _ResidualFree(model)
    return _PriorInput(model) if model.cfg.prior_input else model


def prior_spec(cfg: ModelConfig) -> dict:
    """Manifest `prior`: how the runtime computes the prior of a model with
    ``prior_input`` (``Enhancer.prior`` with the "chain" fill)."""
    if cfg.prior_fill != "chain":
        raise ValueError(f"the runtime computes only the chain prior, not {cfg.prior_fill!r}")
    k = cfg.context_frames
    return {
        "floor": cfg.prior_floor,
        "gate": cfg.prior_gate,
        "frames": min(k, cfg.prior_frames) if cfg.prior_frames > 0 else k,
        "levels": cfg.pushpull_levels,
        "depth_tol": cfg.prior_depth_tol,
    }


def trace_to_onnx(net: torch.nn.Module, dummy: torch.Tensor, path: Path):
    """``net`` traced on ``dummy`` into ``path`` (one input ``input``, one
    output ``output``, height and width dynamic, opset ``OPSET``), and the
    file loaded back as an ``onnx.ModelProto``."""
    import onnx

    torch.onnx.export(
        net,
        (dummy,),
        str(path),
        input_names=["input"],
        output_names=["output"],
        dynamic_axes={"input": {2: "height", 3: "width"}, "output": {2: "height", 3: "width"}},
        opset_version=OPSET,
        dynamo=False,
    )
    return onnx.load(str(path))


def export(
    model: Enhancer,
    out_stem: Path,
    name: str = "harmonizer-small",
    version: str = "0.1.0",
    stabilize: bool = True,
    repair_margin: int | None = None,
    edge_fill: float | None = None,
) -> dict:
    import onnx

    model.eval()
    # First: a bad manifest field writes nothing.
    manifest = manifest_for(model, name, version, stabilize, repair_margin, edge_fill)
    net = graph_of(model).eval()
    cin = len(model.cfg.graph_channels())
    m = model.cfg.spatial_multiple
    dummy = torch.zeros(1, cin, 4 * m, 4 * m)
    onnx_path = out_stem.with_suffix(".onnx")
    onnx_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = onnx_path.with_suffix(".onnx.tmp")
    proto = trace_to_onnx(net, dummy, tmp)
    if proto.ir_version > MAX_IR_VERSION:
        proto.ir_version = MAX_IR_VERSION
    # The whole configuration, for `weights_from_onnx`: the graph alone does
    # not say everything (the depth-aware prior's tolerance, the in-graph
    # margin). ONNX Runtime and the runtime's manifest ignore it.
    entry = proto.metadata_props.add()
    entry.key, entry.value = CONFIG_METADATA, json.dumps(model.cfg.to_dict(), sort_keys=True)
    onnx.checker.check_model(proto)
    onnx.save(proto, str(tmp))
    tmp.replace(onnx_path)
    json_path = out_stem.with_suffix(".json")
    json_path.write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


def verify(model: Enhancer, onnx_path: Path, sizes=((144, 256), (96, 160))) -> float:
    """Largest |ONNX Runtime - PyTorch| over random inputs at ``sizes``."""
    import onnxruntime as ort

    sess = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    cin = len(model.cfg.graph_channels())
    rng = np.random.default_rng(0)
    worst = 0.0
    for h, w in sizes:
        x = rng.random((1, cin, h, w), dtype=np.float32) * 0.3
        with torch.no_grad():
            ref = graph_of(model)(torch.from_numpy(x)).numpy()
        got = sess.run(["output"], {"input": x})[0]
        if got.shape != ref.shape:
            raise RuntimeError(f"ONNX output shape {got.shape} != PyTorch {ref.shape} at {h}x{w}")
        worst = max(worst, float(np.abs(got - ref).max()))
    return worst


def weights_from_onnx(path: Path, **changes) -> Enhancer:
    """The model exported at ``path`` (with its manifest ``.json`` beside it) as
    an ``Enhancer``: weights from the initializers (the stem's, exported as one
    strided convolution, reshaped back); the configuration from the file's
    metadata (``CONFIG_METADATA``, exports since 1.4.1) with ``changes``, else
    the architecture read from the weights' shapes and the prior and wiring
    from ``ModelConfig``'s defaults with ``changes``. A file without that
    metadata whose input has a ``disparity`` channel needs ``prior_depth_tol``
    among the changes (it was exported with a depth-aware prior whose
    tolerance the file does not say)."""
    import onnx
    from onnx import numpy_helper

    manifest = json.loads(path.with_suffix(".json").read_text())
    if manifest.get("residual", False):
        raise ValueError(f"{path}: a residual model (no in-graph prior) cannot be re-exported with a prior")
    proto = onnx.load(str(path))
    # A graph exported through a wrapper (`_PriorInput`) names the model's
    # weights and nodes under `model.` and `/model/`.
    init = {
        i.name.removeprefix("model."): torch.from_numpy(numpy_helper.to_array(i).copy())
        for i in proto.graph.initializer
    }
    saved = {p.key: p.value for p in proto.metadata_props}.get(CONFIG_METADATA)
    if saved is None and "disparity" in manifest["input"]["channels"] and "prior_depth_tol" not in changes:
        raise ValueError(
            f"{path}: its input has a disparity channel (a depth-aware prior) and the file does not say the "
            "prior's tolerance: pass prior_depth_tol (--prior-depth-tol; 1.4.0 used 0.05)"
        )
    levels = sorted({int(k.split(".")[1]) for k in init if k.startswith("enc.")})
    widths = tuple(int(init[f"enc.{i}.0.0.weight"].shape[0]) for i in levels)

    # The history blend's first layer as one convolution per feature tensor
    # (1.7.1 on: `HistoryBlend.down_features`), in graph order: their weight
    # slices joined are the layer's weight.
    def weight_of(n) -> str:
        return n.input[1].removeprefix("model.")

    split = [
        weight_of(n)
        for n in proto.graph.node
        if n.op_type == "Conv"
        and n.name.removeprefix("/model").startswith("/blend/")
        and weight_of(n) in init
        and init[weight_of(n)].dim() == 4
        and init[weight_of(n)].shape[-1] == BLEND_STRIDE
    ]
    if len(split) > 1 and "blend.down.weight" not in init:
        init["blend.down.weight"] = torch.cat([init[k] for k in split], 1)
        for k in set(split):
            del init[k]
    # The stem as one r x r convolution of stride r: [stem, channels, r, r].
    folded = [v for k, v in init.items() if k.startswith("onnx::") and v.dim() == 4 and v.shape[-1] > 1]
    if "stem.0.bias" not in init or len(folded) != 1:
        raise ValueError(f"{path}: no folded stem convolution found (not a model this trainer exported)")
    stem_w = folded[0]
    context = int(manifest["context_frames"])
    if saved is not None:
        return _load_onnx_weights(ModelConfig.from_dict({**json.loads(saved), **changes}), init, stem_w, path)
    changes.setdefault("prior_frames", int(manifest.get("history_read", 0)))
    if "blend.down.weight" in init:
        # A history blend: its width from its first layer. (An in-graph
        # margin leaves no weights: pass `graph_margin` as a change.)
        changes.setdefault("history_blend", True)
        changes.setdefault("blend_width", int(init["blend.down.weight"].shape[0]))
    cfg = ModelConfig(
        context_frames=context,
        widths=widths,
        unshuffle=int(stem_w.shape[-1]),
        key=float(manifest["encoding"]["key"]),
        log_range=float(manifest["encoding"]["log_range"]),
        stem=int(init["stem.0.bias"].shape[0]),
        enc_convs=len({k.split(".")[2] for k in init if k.startswith("enc.0.") and k.endswith(".weight")}),
        dec_convs=len({k.split(".")[2] for k in init if k.startswith("dec.0.") and k.endswith(".weight")}),
        skip="add" if any(k.startswith("proj.") for k in init) else "cat",
        premultiplied=bool(manifest.get("premultiplied", False)),
        **changes,
    )
    return _load_onnx_weights(cfg, init, stem_w, path)


def _load_onnx_weights(cfg: ModelConfig, init: dict, stem_w: torch.Tensor, path: Path) -> Enhancer:
    """An ``Enhancer`` of ``cfg`` with the exported initializers ``init``."""
    model = Enhancer(cfg)
    own = model.state_dict()
    weights = {k: init[k] for k in own if k in init}
    full = own["stem.0.weight"].shape[1] // cfg.unshuffle**2
    if stem_w.shape[1] == full - 4 * cfg.context_frames:
        # A graph without the history channels in the correction's input
        # (1.2.1 on): their rows come back as zeros, which they weighed before.
        hist = torch.zeros(stem_w.shape[0], 4 * cfg.context_frames, *stem_w.shape[2:], dtype=stem_w.dtype)
        stem_w = torch.cat([stem_w[:, :5], hist, stem_w[:, 5:]], 1)
    weights["stem.0.weight"] = stem_w.reshape(own["stem.0.weight"].shape)
    fresh = sorted(k for k in set(own) - set(weights) if k.startswith("blend."))
    if fresh:
        # A history blend added to a model exported without one starts at its
        # initialization (`HistoryBlend`), to be trained.
        weights.update({k: own[k] for k in fresh})
    missing = sorted(set(own) - set(weights))
    if missing:
        # The exporter shares equal initializers (fresh zero biases): only
        # trained weights, all distinct, come back by name.
        raise ValueError(f"{path}: weights missing for {missing} (shared or renamed initializers)")
    model.load_state_dict(weights)
    return model.eval()


def drop_blend_beta(weights: dict, model: Enhancer) -> dict:
    """Checkpoints whose history blend had a second weight per pixel (the
    share of the raw history, trained in the first runs of 2026-11-26)
    load with it left out: it stayed near zero, and the blend without it
    is ``HistoryBlend`` now."""
    if model.blend is None or "blend.out.bias" not in weights:
        return weights
    n = model.blend.out.out_channels
    if weights["blend.out.bias"].shape[0] == 2 * n:
        weights = dict(weights)
        for k in ("blend.out.weight", "blend.out.bias"):
            weights[k] = weights[k][:n].clone()
    return weights


def average_weights(weights: dict, other: Path, share: float, model: Enhancer) -> dict:
    """``share`` of ``weights`` plus ``1 - share`` of checkpoint ``other``'s, which
    must have the same parameters (a fine-tuning's start: averaging a fine-tuned
    network with the one it started from keeps part of what each does best)."""
    if not 0.0 <= share <= 1.0:
        raise ValueError(f"--average-share {share} is outside 0..1")
    ck = torch.load(other, map_location="cpu", weights_only=False)
    theirs = drop_blend_beta(ck["model"], model)
    if set(theirs) != set(weights) or any(theirs[k].shape != v.shape for k, v in weights.items()):
        raise ValueError(f"{other}: its weights do not match the checkpoint's (another architecture)")
    return {k: share * v + (1 - share) * theirs[k] for k, v in weights.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--ckpt", type=Path)
    src.add_argument("--from-onnx", type=Path, help="re-export the weights of this exported model")
    # Changes to the source's ModelConfig: each one left out keeps the
    # source's (a checkpoint's, or an exported file's, saved in it since
    # 1.4.1; in files before that, ModelConfig's default).
    ap.add_argument("--prior-floor", type=float, default=None, help="ModelConfig.prior_floor")
    ap.add_argument("--prior-gate", action=argparse.BooleanOptionalAction, default=None, help="ModelConfig.prior_gate")
    ap.add_argument(
        "--correction-history",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="ModelConfig.correction_history",
    )
    ap.add_argument("--graph-margin", type=int, default=None, help="the in-graph repair margin (ModelConfig)")
    ap.add_argument(
        "--prior-depth-tol",
        type=float,
        default=None,
        help="the prior's depth-aware push-pull tolerance (ModelConfig.prior_depth_tol; 0: off; default: the source's)",
    )
    ap.add_argument(
        "--average-with",
        type=Path,
        default=None,
        help="with --ckpt: average its weights with this checkpoint's (same architecture), e.g. the run it was "
        "fine-tuned from",
    )
    ap.add_argument(
        "--average-share",
        type=float,
        default=0.5,
        help="with --average-with: the share of --ckpt's weights in the average (the rest from --average-with)",
    )
    ap.add_argument("--out", type=Path, required=True, help="output path without extension")
    ap.add_argument("--name", default="harmonizer-small")
    ap.add_argument("--version", default="0.1.0")
    ap.add_argument("--tolerance", type=float, default=1e-4)
    ap.add_argument(
        "--stabilize",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="manifest `stabilize`: the runtime stabilizes the output over time (default on)",
    )
    ap.add_argument(
        "--history-read",
        type=int,
        default=None,
        help="the prior reads only the first N history slots (manifest `history_read`; default: as the source)",
    )
    ap.add_argument(
        "--blend-gain",
        type=float,
        default=None,
        help="a fixed factor on the history blend's weight (ModelConfig.blend_gain; default: the checkpoint's)",
    )
    ap.add_argument(
        "--hole-correction",
        type=float,
        default=None,
        help="the share of the network's correction applied in holes (ModelConfig.hole_correction; default: "
        "the source's)",
    )
    ap.add_argument(
        "--hole-blend",
        type=float,
        default=None,
        help="a factor on the history blend's weight in holes (ModelConfig.hole_blend; default: the source's)",
    )
    ap.add_argument(
        "--far-blend",
        type=float,
        default=None,
        help="a factor on the history blend's weight in covered pixels more than 2 px from a hole "
        "(ModelConfig.far_blend; default: the source's)",
    )
    ap.add_argument(
        "--repair-margin",
        type=int,
        default=None,
        help="manifest `repair_margin`: covered pixels farther than N px from a hole keep their rendered "
        "color (default: none; with --from-onnx, the source's)",
    )
    ap.add_argument(
        "--edge-fill",
        type=float,
        default=None,
        help="manifest `prior.edge_fill`: the share of the runtime's edge-continuing fill in what the history "
        "left missing (0: none; default: none; with --from-onnx, the source's)",
    )
    ap.add_argument(
        "--prior-input",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="the runtime computes the prior and the graph reads it as input channels prior.r|g|b "
        "(ModelConfig.prior_input; default: the source's)",
    )
    args = ap.parse_args(argv)
    source = args.ckpt or args.from_onnx
    if not source.exists():
        print(f"export: {source} not found", file=sys.stderr)
        return 2
    given = {
        "prior_floor": args.prior_floor,
        "prior_gate": args.prior_gate,
        "correction_history": args.correction_history,
        "graph_margin": args.graph_margin,
        "prior_frames": args.history_read,
        "prior_depth_tol": args.prior_depth_tol,
        "blend_gain": args.blend_gain,
        "hole_correction": args.hole_correction,
        "hole_blend": args.hole_blend,
        "far_blend": args.far_blend,
        "prior_input": args.prior_input,
    }
    changes = {k: v for k, v in given.items() if v is not None}
    if args.from_onnx:
        try:
            model = weights_from_onnx(args.from_onnx, **changes)
        except ValueError as e:
            print(f"export: {e}", file=sys.stderr)
            return 2
        step = None
        # The runtime's settings that the graph does not hold: the source's,
        # unless given.
        source_manifest = json.loads(args.from_onnx.with_suffix(".json").read_text())
        if args.repair_margin is None:
            args.repair_margin = source_manifest.get("repair_margin")
        if args.edge_fill is None:
            args.edge_fill = source_manifest.get("prior", {}).get("edge_fill")
    else:
        ck = torch.load(args.ckpt, map_location="cpu", weights_only=False)
        model = Enhancer(ModelConfig.from_dict(ck["model_cfg"]))
        weights = drop_blend_beta(ck["model"], model)
        if args.average_with is not None:
            try:
                weights = average_weights(weights, args.average_with, args.average_share, model)
            except (ValueError, OSError) as e:
                print(f"export: {e}", file=sys.stderr)
                return 2
        model.load_state_dict(weights)
        for k, v in changes.items():
            setattr(model.cfg, k, v)
        model.eval()
        step = ck["step"]
    try:
        manifest = export(model, args.out, args.name, args.version, args.stabilize, args.repair_margin, args.edge_fill)
    except ValueError as e:
        print(f"export: {e}", file=sys.stderr)
        return 2
    onnx_path = args.out.with_suffix(".onnx")
    diff = verify(model, onnx_path)
    macs, params = count_macs(model, 576, 1024)
    size = onnx_path.stat().st_size
    print(
        json.dumps(
            {
                "onnx": str(onnx_path),
                "manifest": str(args.out.with_suffix(".json")),
                "step": step,
                "source": str(source),
                "params": params,
                "gmac_1024x576": round(macs / 1e9, 3),
                "onnx_bytes": size,
                "max_abs_diff_ort_vs_torch": diff,
                "spatial_multiple": manifest["spatial_multiple"],
            }
        )
    )
    if diff > args.tolerance:
        print(f"export: ONNX Runtime differs from PyTorch by {diff} > {args.tolerance}", file=sys.stderr)
        return 1
    if size > 8 * 1024 * 1024:
        print(f"export: {onnx_path} is {size} bytes, over the 8 MB budget", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
