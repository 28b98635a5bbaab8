"""The temporal enhancer network and the runtime contract it is trained for.

A small UNet for CPUs: the input (current frame encoded, coverage, insert
mask, K reprojected previous enhanced frames with their validity) is
pixel-unshuffled by 2, runs through dense 3x3 convolutions with leaky ReLU at four
resolutions, is pixel-shuffled back and added to the encoded input color
(residual). Channel names, color encoding and reprojection follow
``training/export_contract.md`` and ``core/src/backend/neural/``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
import torch.nn as nn
import torch.nn.functional as F

LUMA = (0.2126, 0.7152, 0.0722)
COVERAGE_EPSILON = 1e-3
LUMINANCE_FLOOR = 1e-4
FAR_DEPTH = 1e9
DEPTH_TOLERANCE = 0.1


@dataclass
class ModelConfig:
    """Architecture and contract settings (saved in checkpoints and manifests)."""

    context_frames: int = 4
    # Encoding (manifest `encoding`): y = log2(1 + x s) / log_range with s = key / Lavg.
    # key 2, range 4 put the frame's log-average at 0.40, 4 stops above at 1.26 and
    # 4 below at 0.04: a log-like, unit-scale input (key 0.18 / range 8 kept every
    # value under ~0.1, which trained poorly).
    widths: tuple = (24, 32, 48, 64)
    unshuffle: int = 2
    key: float = 2.0
    log_range: float = 4.0
    # In-graph prior: holes filled from the reprojected history, then by push-pull;
    # the network adds a correction to it and the graph returns the complete frame
    # (manifest `residual: false`). Without it the graph returns a correction to
    # the input color (`residual: true`).
    prior: bool = True
    pushpull_levels: int = 8
    # How the prior fills: "chain" composites the history frames under the holes
    # newest first and pulls with the weight clamped to one (the classical
    # backend's fill, `core/src/ops/inpaint.rs`); "mean" (models before 1.1)
    # averaged the valid history frames and pulled plain 2x2 averages, which
    # blurred the fill across the holes (hole PSNR 1.5 dB lower without history).
    prior_fill: str = "chain"
    # The classical fill's two guards (`core/src/backend/classical.rs`), in the prior:
    # a pixel covered below `prior_floor` loses its own color (`coverage_floor`), and
    # a history frame fills a hole pixel only where few covered pixels are near
    # (`prior_gate`: `history_weight` of the share of pixels covered at least
    # max(prior_floor, 0.5) within 3 pixels). Out of domain the faint colors and last
    # frame's fill reprojected into thin gaps were both further from the truth than
    # the spatial fill (model card, 1.2.0).
    prior_floor: float = 0.95
    prior_gate: bool = True
    # Whether the correction network sees the history channels. 1.1 did, and fed
    # back its own outputs it amplified small differences in them (a chunk of a
    # sequence started elsewhere drifted away from the sequential run: 34.5 ->
    # 16.9 dB over 24 frames without stabilization) without gaining from them
    # (K=4 and K=0 scored the same); without, the history reaches it only through
    # the prior.
    correction_history: bool = False
    # How many history frames the prior reads (0: all `context_frames`; manifest
    # `history_read`). The input keeps every slot; the graph skips the rest,
    # which the runtime leaves without a frame (valid 0), so the result is the
    # same and each skipped slot saves its full-resolution products.
    prior_frames: int = 0
    # Manifest `premultiplied`: false = the network sees straight color (color /
    # coverage where coverage >= 1e-3, else 0), so the prior's `coverage * color
    # + (1 - coverage) * fill` blends soft edges correctly (premultiplied input
    # darkened every soft edge twice and pulled the darkening into the holes).
    premultiplied: bool = False
    # Learned history rectification (`HistoryBlend`): after the correction, a
    # small network weighs, per pixel, the spatial estimate against history
    # frame 0 (the previous enhanced frame, reprojected), clamped toward the
    # estimate's 3x3 color range. The blend is convex, so feeding back its own
    # outputs cannot amplify them (the drift of 1.1's history-reading
    # correction); with no valid history it returns the estimate unchanged.
    history_blend: bool = False
    blend_width: int = 8
    # A fixed factor on the blend's weight, settable at export
    # (`--blend-gain`). Trained on the generator's scenes the blend trusts the
    # history more than the procedural demo wants (1.3.0 at 0.75: demo
    # +0.8 dB; model card); 1.3.0 ships at 1.0.
    blend_gain: float = 1.0
    # The share of the network's correction applied in holes (coverage below
    # `prior_floor`), settable at export (`--hole-correction`). At 0 a hole
    # keeps the prior's fill (history, then the background side), and the
    # correction acts on the covered pixels around it; the blend follows
    # either way. Measured with 1.4.x's weights (model card, 1.5.0): 0 gained
    # 0.35 dB in the holes of the ten held-out reconstructions and 0.11-0.17
    # out of domain; the correction had learned to move hole pixels on
    # average away from the truth.
    hole_correction: float = 1.0
    # A factor on the history blend's weight in holes (`--hole-blend`). The
    # history in a hole is an older fill of it; at 0.5 (1.6.0) the holes of
    # the ten held-out reconstructions gained 0.43 dB and the outdoor ones
    # out of domain 0.55 (indoors -0.08), the warping error within 0.04 of
    # 1.0's except indoors (7.08 -> 7.42; model card).
    hole_blend: float = 1.0
    # A factor on the history blend's weight in covered pixels beyond its
    # nearness band (more than 2 px from a hole, `--far-blend`). There the
    # blend steadies a render whose errors are the reconstruction's own,
    # and fixed in the world: the reprojected history repeats them.
    far_blend: float = 1.0
    # Covered pixels (coverage >= prior_floor) farther than this many pixels
    # (Chebyshev) from a hole keep their input color inside the graph, at
    # exactly this distance 0.4 of the network's (the runtime's
    # `repair_margin`, moved before the history blend so the blend also
    # steadies covered pixels; 0: none).
    graph_margin: int = 0
    # Depth-aware push-pull in the prior (0: off). With a tolerance, the input
    # gains a last channel, `disparity` (1 / (1 + planar depth), 0 where the
    # host gave none), and each halving of the push keeps, of the frame's own
    # covered pixels in a 2x2 block, only those within this relative
    # disparity of the block's farthest: holes fill from the background
    # side of a disocclusion, not from the object in front of it. Pixels the
    # history filled carry no depth of their own and are always kept. The
    # correction does not read the disparity (its weights are unchanged).
    prior_depth_tol: float = 0.0
    # The runtime computes the prior (export-time, `--prior-input`): the
    # exported graph reads it as three more input channels, `prior.r|g|b`,
    # and the manifest's `prior` tells the runtime how to compute it
    # (`core/src/backend/neural/prior.rs`, the same operations as `prior`
    # below). Training computes it in the graph either way. In the graph it
    # took 130 of ONNX Runtime's 460 ms at 1920x1088 on 2 threads: dense
    # full-resolution operations, where the runtime's touch only the pixels
    # not fully covered after the pull.
    prior_input: bool = False
    # Width of a 1x1 convolution on the unshuffled input (0: none); it replaces the
    # first 3x3 layer's many input channels with a cheap mix.
    stem: int = 32
    # 3x3 convolutions per encoder level and per decoder level.
    enc_convs: int = 2
    dec_convs: int = 2
    # Decoder skips: "add" (1x1 projection of the coarser level, upsampled and
    # added: cheap) or "cat" (concatenated before the first decoder convolution).
    skip: str = "add"

    def input_channels(self) -> list[str]:
        ch = ["color.r", "color.g", "color.b", "coverage", "insert"]
        for k in range(self.context_frames):
            ch += [f"hist{k}.r", f"hist{k}.g", f"hist{k}.b", f"valid{k}"]
        if self.prior_depth_tol > 0:
            ch.append("disparity")
        return ch

    def graph_channels(self) -> list[str]:
        """The exported graph's input channels: ``input_channels`` and, with
        ``prior_input``, the prior's three."""
        return self.input_channels() + (["prior.r", "prior.g", "prior.b"] if self.prior_input else [])

    def network_channels(self) -> int:
        """Input channels the correction's stem is sized for (the disparity,
        read by the prior alone, is not one)."""
        return len(self.input_channels()) - (1 if self.prior_depth_tol > 0 else 0)

    @property
    def spatial_multiple(self) -> int:
        return self.unshuffle * 2 ** (len(self.widths) - 1)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["widths"] = list(self.widths)
        return d

    @staticmethod
    def from_dict(d: dict) -> ModelConfig:
        d = dict(d)
        d["widths"] = tuple(d["widths"])
        # Configurations saved before the prior existed describe the plain residual UNet.
        # Those saved before the prior's guards fill as 1.1 did.
        for k, v in (
            ("prior", False),
            ("stem", 0),
            ("skip", "cat"),
            ("premultiplied", True),
            ("prior_fill", "mean"),
            ("prior_floor", 0.0),
            ("prior_gate", False),
            ("correction_history", True),
        ):
            d.setdefault(k, v)
        return ModelConfig(**d)


NEGATIVE_SLOPE = 0.1

# The classical backend's history gate (`core/src/backend/classical.rs`,
# `GATE_RADIUS` and `history_weight`).
GATE_RADIUS = 3


def history_weight(known_share: torch.Tensor) -> torch.Tensor:
    """How much history a hole pixel takes from the share of covered pixels
    around it: all up to 0.225, none from 0.3."""
    return ((0.3 - known_share) / 0.075).clamp(0, 1)


def act() -> nn.Module:
    """Leaky ReLU: plain ReLU layers died in training (the last decoder layer
    went inactive); ONNX Runtime fuses LeakyRelu into Conv like Relu."""
    return nn.LeakyReLU(NEGATIVE_SLOPE, inplace=True)


# The runtime's `REPAIR_EDGE_SHARE` (core/src/model/manifest.rs): the share of
# the network's output at exactly the margin's distance.
REPAIR_EDGE_SHARE = 0.4
# The history blend's nearness-to-a-hole feature: `margin_share` at 2 px.
BLEND_MARGIN = 2
# The history blend's layers run at 1 / BLEND_STRIDE^2 of the pixels.
BLEND_STRIDE = 4


class HistoryBlend(nn.Module):
    """Per-pixel blend of the spatial estimate with history frame 0.

    Features at full resolution: the estimate (3), the history clamped to the
    estimate's 3x3 min/max box (3), history minus estimate (3), the history's
    validity, the coverage and the nearness to a hole (``margin_share`` with a
    margin of 2: 1 in and next to holes, 0 from 3 px). A 4x4 convolution of stride 4 (an unshuffle and
    a 1x1 layer), a 3x3 layer and a 1x1 layer, all at 1/16 of the pixels, give,
    pixel-shuffled back, a weight per pixel: ``alpha`` (times the validity)
    moves the output from the estimate toward the clamped history. (A second
    weight that moved the history from its clamped toward its raw color
    stayed near zero in training and changed the held-out results by under
    0.1 dB; it cost 13 ms at 1920x1088.)"""

    def __init__(self, width: int):
        super().__init__()
        # At 1/16 of the pixels: at 1/4 (a 2x2 stride) its layers and their
        # layout changes took 60 of ONNX Runtime's 446 ms at 1920x1088.
        self.down = nn.Conv2d(12, width, BLEND_STRIDE, stride=BLEND_STRIDE)
        self.mid = nn.Conv2d(width, width, 3, padding=1)
        self.out = nn.Conv2d(width, BLEND_STRIDE**2, 1)
        for m in (self.down, self.mid):
            nn.init.kaiming_normal_(m.weight, a=NEGATIVE_SLOPE, nonlinearity="leaky_relu")
            nn.init.zeros_(m.bias)
        # Starts as a fixed blend: alpha = sigmoid(0) = 0.5 of the clamped
        # history, close to the runtime's stabilization (0.6).
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def down_features(self, est, clamped, hist, valid, cov, near) -> torch.Tensor:
        """``self.down`` over ``[est, clamped, hist - est, valid, cov, near]``
        (12 channels), computed as one convolution per tensor (its slice of
        the weight, the first with the bias), summed: the same products
        without the full-resolution concatenation, and ONNX Runtime reads an
        input of under 8 channels (its channel block with AVX2; 16 with
        AVX-512) as it is, where the 12 were first copied into blocks (ONNX
        Runtime's profile at 1920x1088 on 2 AVX2 cores: concatenation 6.6 ms,
        layout copy 28.1 and convolution 7.0 became six convolutions and
        their sums, 8).
        `training.export.weights_from_onnx` joins the slices back."""
        w = self.down.weight
        out, at = None, 0
        for t in (est, clamped, hist - est, valid, cov, near):
            # A plain channel count: the slices export as constants, which
            # ONNX Runtime needs to give a convolution its blocked layout.
            n = int(t.shape[1])
            y = F.conv2d(t, w[:, at : at + n], self.down.bias if out is None else None, stride=BLEND_STRIDE)
            out = y if out is None else out + y
            at += n
        assert at == w.shape[1], "the blend's features are its layer's 12 channels"
        return out

    def forward(
        self,
        est: torch.Tensor,
        hist: torch.Tensor,
        valid: torch.Tensor,
        cov: torch.Tensor,
        near: torch.Tensor,
        gain: float | torch.Tensor = 1.0,
    ) -> torch.Tensor:
        """``gain``: a factor on the weight, one number or one per pixel."""
        lo = -F.max_pool2d(-est, 3, stride=1, padding=1)
        hi = F.max_pool2d(est, 3, stride=1, padding=1)
        clamped = torch.minimum(torch.maximum(hist, lo), hi)
        h = F.leaky_relu(self.down_features(est, clamped, hist, valid, cov, near), NEGATIVE_SLOPE)
        h = F.leaky_relu(self.mid(h), NEGATIVE_SLOPE)
        per_pixel = isinstance(gain, torch.Tensor)
        alpha = torch.sigmoid(F.pixel_shuffle(self.out(h), BLEND_STRIDE)) * (
            valid * gain if per_pixel or gain != 1.0 else valid
        )
        return est + alpha * (clamped - est)


def pixel_shuffle_2(x: torch.Tensor) -> torch.Tensor:
    """``F.pixel_shuffle(x, 2)``, the same values, as the phases interleaved
    by two stacks (as `upsample_far` does): ONNX Runtime's DepthToSpace took
    14-28 ms for the correction's 12 half-resolution channels at 1920x1088
    on 2 threads, the stacks about 7."""
    n, c4, h, w = x.shape
    c = c4 // 4
    x = x.reshape(n, c, 2, 2, h, w)
    rows = [torch.stack([x[:, :, py, 0], x[:, :, py, 1]], -1).reshape(n, c, h, 2 * w) for py in (0, 1)]
    return torch.stack(rows, -2).reshape(n, c, 2 * h, 2 * w)


def margin_share(cov: torch.Tensor, floor: float, margin: int) -> torch.Tensor:
    """The network's share per pixel under a repair margin: 1 in holes
    (coverage below ``floor``) and within ``margin - 1`` pixels of one,
    ``REPAIR_EDGE_SHARE`` at exactly ``margin``, 0 farther (Chebyshev)."""
    hole = (cov < floor).to(cov.dtype)
    near = F.max_pool2d(hole, 2 * margin - 1, stride=1, padding=margin - 1) if margin > 1 else hole
    edge = F.max_pool2d(hole, 2 * margin + 1, stride=1, padding=margin)
    return torch.maximum(near, REPAIR_EDGE_SHARE * edge)


def conv(cin: int, cout: int) -> nn.Module:
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1), act())


def push_pull(c: torch.Tensor, w: torch.Tensor, levels: int) -> torch.Tensor:
    """Fills ``c`` (premultiplied by the weight ``w`` in [0, 1]) everywhere.

    Push: ``levels`` halvings of ``(c, w)`` by 2x2 averages (zero-padded to even
    sizes, so any size works and padding carries no weight). Pull: from the
    coarsest level up, each level's normalized color ``c / w`` is blended over
    the bilinear upsampling of the level below with opacity ``min(1, 2 w)``."""
    cs, ws = [c], [w]
    for _ in range(levels):
        c = F.avg_pool2d(F.pad(c, (0, 1, 0, 1)), 2)
        w = F.avg_pool2d(F.pad(w, (0, 1, 0, 1)), 2)
        cs.append(c)
        ws.append(w)
    f = cs[-1] / ws[-1].clamp(min=1e-4)
    for lv in range(levels - 1, -1, -1):
        up = F.interpolate(f, size=cs[lv].shape[-2:], mode="bilinear", align_corners=False)
        a = (2 * ws[lv]).clamp(0, 1)
        f = cs[lv] / ws[lv].clamp(min=1e-4) * a + up * (1 - a)
    return f


def push_pull_clamped(c: torch.Tensor, w: torch.Tensor, levels: int) -> torch.Tensor:
    """The classical backend's push-pull (``core/src/ops/inpaint.rs``): ``c``
    premultiplied by ``w`` in [0, 1]; returns ``c + (1 - w) * fill``.

    Pull: 2x2 sums, with the weight clamped to 1 and the color scaled with it
    (a coarse pixel is complete as soon as one fine pixel's worth of data falls
    into it, so known data is not diluted by the holes around it). Push: from
    the coarsest level up, each level's missing part ``1 - w`` takes the
    bilinear upsampling of the completed level below."""
    cs, ws = [c], [w]
    for _ in range(levels):
        c = F.avg_pool2d(F.pad(c, (0, 1, 0, 1)), 2) * 4
        w = F.avg_pool2d(F.pad(w, (0, 1, 0, 1)), 2) * 4
        k = w.clamp(max=1) / w.clamp(min=1e-12)
        c = c * k
        w = w.clamp(max=1)
        cs.append(c)
        ws.append(w)
    f = cs[-1] / ws[-1].clamp(min=1e-4)
    for lv in range(levels - 1, -1, -1):
        up = F.interpolate(f, size=cs[lv].shape[-2:], mode="bilinear", align_corners=False)
        f = cs[lv] + (1 - ws[lv]) * up
    return f


# The bilinear weights of a 2x upsampling (pixel centres, align_corners=False)
# along one axis: fine pixel 2i (phase 0) takes coarse i-1 and i with 1/4 and
# 3/4; 2i+1 (phase 1) takes i and i+1 with 3/4 and 1/4. On the grid padded by
# one, a phase's two taps are offsets 0 and 1 of the pair starting at i + phase.
_PHASE_WEIGHTS = {0: (0.25, 0.75), 1: (0.75, 0.25)}


def upsample_far(f: torch.Tensor, fd: torch.Tensor, size, tol: float) -> torch.Tensor:
    """The 2x bilinear upsampling of ``f`` to ``size``, each fine pixel
    taking of its four taps only those whose disparity ``fd`` is within the
    relative ``tol`` of the farthest (smallest), renormalized.

    A fine pixel's four taps are a 2x2 window of the coarse grid (edges
    replicated); which window and the bilinear weights depend on its phase.
    Computed once per window rather than per phase and tap (the taps' masked
    colours and masks are shared by the phases that read the same window),
    then the bilinear weights as separable multiply-adds, and the phases
    interleaved by concatenations: 41 ms against 119
    for the per-phase, per-tap form (``training/tests/test_model.py``
    keeps it as the reference) from 960x544 to 1920x1088 in ONNX Runtime on
    2 threads."""
    h, w = fd.shape[-2:]
    n, ch = f.shape[:2]
    pf = F.pad(f, (1, 1, 1, 1), mode="replicate")
    pd = F.pad(fd, (1, 1, 1, 1), mode="replicate")
    # Each 2x2 window of the padded grid, (h + 1) x (w + 1) of them, by its corner.
    limit = -F.max_pool2d(-pd, 2, stride=1) * (1 + tol)
    taps = {}
    for oy in (0, 1):
        for ox in (0, 1):
            keep = (pd[..., oy : oy + h + 1, ox : ox + w + 1] <= limit).to(f.dtype)
            taps[oy, ox] = torch.cat([keep * pf[..., oy : oy + h + 1, ox : ox + w + 1], keep], 1)
    cols = {
        (oy, px): taps[oy, 0] * _PHASE_WEIGHTS[px][0] + taps[oy, 1] * _PHASE_WEIGHTS[px][1]
        for oy in (0, 1)
        for px in (0, 1)
    }
    phases = []
    for py in (0, 1):
        for px in (0, 1):
            v = cols[0, px] * _PHASE_WEIGHTS[py][0] + cols[1, px] * _PHASE_WEIGHTS[py][1]
            v = v[..., py : py + h, px : px + w]
            phases.append(v[:, :ch] / v[:, ch:])
    # Interleaved as columns, then rows (two concatenations; ONNX Runtime's
    # DepthToSpace of the stacked phases took twice as long: 14.7 ms against
    # 7.2 at 1920x1088).
    rows = [torch.stack(phases[2 * py : 2 * py + 2], -1).reshape(n, ch, h, 2 * w) for py in (0, 1)]
    out = torch.stack(rows, -2).reshape(n, ch, 2 * h, 2 * w)
    if tuple(out.shape[-2:]) != tuple(size):  # odd sizes (never in the exported graph: multiples of 16)
        out = out[..., : size[0], : size[1]]
    return out


def _pad_odd(x: torch.Tensor, even: bool, value: float = 0.0) -> torch.Tensor:
    """``x`` with a row and a column of ``value`` added before a 2x2 halving,
    unless ``even`` (the halving would drop them)."""
    return x if even else F.pad(x, (0, 1, 0, 1), value=value)


# Larger than any disparity (1 / (1 + depth) <= 1): "no depth of its own".
NO_DISPARITY = 4.0


def push_pull_depth(
    c: torch.Tensor, w: torch.Tensor, own: torch.Tensor, disp: torch.Tensor, levels: int, tol: float
) -> torch.Tensor:
    """``push_pull_clamped`` filled from the background side.

    ``own`` (at most ``w``) is the part of each pixel's weight that is the
    frame's own data, at disparity ``disp``. Pull: before each halving, a
    pixel with data of its own whose disparity exceeds its 2x2 block's
    smallest by more than the relative ``tol`` (a nearer surface) is left
    out of the block's sum (the level itself keeps all its data); the coarse
    level's disparity is the own-weighted mean of what it kept. Push: as
    ``push_pull_clamped``, but the last step, into the full resolution,
    takes of each pixel's four bilinear taps only the far ones
    (``upsample_far``) with the disparity completed on the way down.
    Measured on the held-out reconstructions (the prior alone, one frame):
    the far side in the last step only gained 1.1 dB on average over the
    plain fill (-0.2 at worst); in every step 0.7 dB on average but -2.3 and
    -0.5 dB on two sequences (a wide unseen area takes the far wall behind
    it). Pixels the history filled (weight without own data) are never left
    out."""
    cs, ws, owns, ds = [c], [w], [own], [disp]
    for lv in range(levels):
        # An even level needs no padding row and column (the halving drops
        # them). Only the first four: the exported graph bakes this choice in
        # at the export's size, and only those levels are even at every
        # multiple of 16 (at 1920x1088 the pads took 15 ms of the fill).
        even = lv < 4 and c.shape[-2] % 2 == 0 and c.shape[-1] % 2 == 0
        has = own > 0
        key = torch.where(has, disp, torch.full_like(disp, NO_DISPARITY))
        limit = -F.max_pool2d(-_pad_odd(key, even, NO_DISPARITY), 2) * (1 + tol)
        limit = F.interpolate(limit, size=key.shape[-2:], mode="nearest")
        keep = (~(has & (disp > limit))).to(c.dtype)
        c, w, own = c * keep, w * keep, own * keep
        c = F.avg_pool2d(_pad_odd(c, even), 2) * 4
        w = F.avg_pool2d(_pad_odd(w, even), 2) * 4
        od = F.avg_pool2d(_pad_odd(own * disp, even), 2) * 4
        own = F.avg_pool2d(_pad_odd(own, even), 2) * 4
        disp = od / own.clamp(min=1e-12)
        k = w.clamp(max=1) / w.clamp(min=1e-12)
        c = c * k
        w = w.clamp(max=1)
        cs.append(c)
        ws.append(w)
        owns.append(own)
        ds.append(disp)
    f = cs[-1] / ws[-1].clamp(min=1e-4)
    # Where the coarsest level has no depth of its own: the farthest there is.
    fd = torch.where(owns[-1] > 0, ds[-1], torch.zeros_like(ds[-1]))
    for lv in range(levels - 1, 0, -1):
        up = F.interpolate(f, size=cs[lv].shape[-2:], mode="bilinear", align_corners=False)
        upd = F.interpolate(fd, size=cs[lv].shape[-2:], mode="bilinear", align_corners=False)
        f = cs[lv] + (1 - ws[lv]) * up
        fd = torch.where(owns[lv] > 0, ds[lv], upd)
    # The far side only in this last step, the costliest place for it (in
    # 1.4.0's graph, 70-90 ms of the fill at 1920x1088 on 2 threads against
    # 20-30 one level up; `upsample_far` now takes 41 of those ms), because
    # one level up gave back 0.3-1.6 dB of the holes' gain on most held-out
    # reconstructions (model card, 1.4.0).
    return cs[0] + (1 - ws[0]) * upsample_far(f, fd, cs[0].shape[-2:], tol)


class Enhancer(nn.Module):
    """UNet on pixel-unshuffled input.

    ``forward(x)`` takes ``[N, C_in, H, W]`` (channels in
    ``ModelConfig.input_channels()`` order, H and W multiples of
    ``spatial_multiple``) and returns the encoded complete frame ``[N, 3, H, W]``:
    the prior (``cfg.prior``: holes filled from history, then push-pull; else the
    input color) plus the network's correction.
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        r = cfg.unshuffle
        cin = (cfg.network_channels() + (3 if cfg.prior else 0)) * r * r
        w = list(cfg.widths)
        prev = cin
        self.stem = None
        if cfg.stem > 0:
            self.stem = nn.Sequential(nn.Conv2d(cin, cfg.stem, 1), act())
            prev = cfg.stem
        self.enc = nn.ModuleList()
        self.down = nn.ModuleList()
        for i, c in enumerate(w):
            if i > 0:
                self.down.append(nn.Sequential(nn.Conv2d(prev, c, 3, stride=2, padding=1), act()))
                prev = c
            layers = [conv(prev, c)] + [conv(c, c) for _ in range(cfg.enc_convs - 1)]
            self.enc.append(nn.Sequential(*layers))
            prev = c
        self.dec = nn.ModuleList()
        self.proj = nn.ModuleList()
        for i in range(len(w) - 2, -1, -1):
            if cfg.skip == "add":
                self.proj.append(nn.Conv2d(w[i + 1], w[i], 1))
                layers = [conv(w[i], w[i]) for _ in range(cfg.dec_convs)]
            else:
                layers = [conv(w[i + 1] + w[i], w[i])] + [conv(w[i], w[i]) for _ in range(cfg.dec_convs - 1)]
            self.dec.append(nn.Sequential(*layers))
        self.head = nn.Conv2d(w[0], 3 * r * r, 3, padding=1)
        # He initialization for the leaky ReLU layers keeps activations (and the
        # gradients flowing back) at unit scale through the depth. The head starts
        # at zero: the model starts exactly at its prior. A random head made the
        # first steps harmful and the optimizer shut the last decoder level off
        # (measured: the correction collapsed to a constant within 20 steps).
        for mod in self.modules():
            if isinstance(mod, nn.Conv2d) and mod is not self.head:
                nn.init.kaiming_normal_(mod.weight, a=NEGATIVE_SLOPE, nonlinearity="leaky_relu")
                nn.init.zeros_(mod.bias)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        self.blend = HistoryBlend(cfg.blend_width) if cfg.history_blend else None

    def _folds_history_out(self) -> bool:
        """Whether the correction drops the history channels in its stem's
        weight (free in the graph) rather than by zeroing its input."""
        return not self.cfg.correction_history and self.cfg.unshuffle > 1 and self.stem is not None

    def split(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The input's channel groups: color, coverage, insert, then each
        history frame's color and validity (then the disparity). Each group is
        one slice, taken once per call; the export drops the slices nothing
        reads (the history frames past ``prior_frames``), so the graph copies
        14 of the 22 full-resolution planes, not all of them as one Split did.
        (Before that, a slice per use copied the same planes several times.)"""
        sizes = [3, 1, 1] + [3, 1] * self.cfg.context_frames + ([1] if self.cfg.prior_depth_tol > 0 else [])
        parts, at = [], 0
        for n in sizes:
            parts.append(x[:, at : at + n])
            at += n
        return parts

    def forward(self, x: torch.Tensor, prior: torch.Tensor | None = None) -> torch.Tensor:
        """``prior``: the prior given (``prior_input``: the runtime's), else
        computed here."""
        parts = self.split(x)
        if self._folds_history_out() and self.cfg.prior:
            # The correction never reads the history channels: they are left out
            # of its input (a 24-channel full-resolution concatenation became 8,
            # 1.2.1: 71 ms less inference at 1920x1088 on 2 threads).
            p = self.prior(x, parts) if prior is None else prior
            est = p + self.in_holes(self.correction(torch.cat(parts[:3] + [p], 1)), parts)
            return self.after_network(est, parts)
        seen = x[:, : self.cfg.network_channels()]
        if self._folds_history_out():
            seen = x[:, :5]
        elif not self.cfg.correction_history and seen.shape[1] > 5:
            seen = torch.cat([seen[:, :5], torch.zeros_like(seen[:, 5:])], 1)
        if self.cfg.prior:
            p = self.prior(x, parts) if prior is None else prior
            est = p + self.in_holes(self.correction(torch.cat([seen, p], 1)), parts)
        else:
            est = parts[0] + self.correction(seen)
        return self.after_network(est, parts)

    def holes(self, parts: list[torch.Tensor]) -> torch.Tensor:
        """The pixels covered below ``prior_floor``: those the prior fills."""
        return parts[1].clamp(0, 1) < self.cfg.prior_floor

    def in_holes(self, corr: torch.Tensor, parts: list[torch.Tensor]) -> torch.Tensor:
        """The correction with ``hole_correction`` of it in holes."""
        if self.cfg.hole_correction == 1.0:
            return corr
        hole = self.holes(parts)
        if self.cfg.hole_correction == 0.0:
            return torch.where(hole, 0.0, corr)  # one operation at full resolution
        return corr * torch.where(hole, self.cfg.hole_correction, 1.0)

    def after_network(self, est: torch.Tensor, parts: list[torch.Tensor]) -> torch.Tensor:
        """The in-graph repair margin and the history blend on the network's
        estimate (identity without them); ``parts``: the input's ``split``."""
        color = parts[0]
        cov = parts[1].clamp(0, 1)
        near = None
        if self.cfg.graph_margin > 0:
            share = margin_share(cov, self.cfg.prior_floor, self.cfg.graph_margin)
            est = color + share * (est - color)
            near = share if self.cfg.graph_margin == BLEND_MARGIN else None
        if self.blend is not None:
            if near is None:
                near = margin_share(cov, self.cfg.prior_floor, BLEND_MARGIN)
            gain = self.cfg.blend_gain
            if self.cfg.hole_blend != 1.0:
                gain = torch.where(self.holes(parts), gain * self.cfg.hole_blend, gain)
            if self.cfg.far_blend != 1.0:
                gain = torch.where(near > 0, gain, gain * self.cfg.far_blend)
            est = self.blend(est, parts[3], parts[4].clamp(0, 1), cov, near, gain)
        return est

    def history_frames_read(self) -> int:
        """History frames the prior reads (``prior_frames``, else all)."""
        k = self.cfg.context_frames
        return min(k, self.cfg.prior_frames) if self.cfg.prior_frames > 0 else k

    def prior(self, x: torch.Tensor, parts: list[torch.Tensor] | None = None) -> torch.Tensor:
        """The input color with its holes filled: reprojected history first
        (newer frames weigh more), then push-pull of what is known."""
        parts = parts if parts is not None else self.split(x)
        color = parts[0]
        cov = parts[1].clamp(0, 1)
        if self.cfg.prior_floor > 0:
            cov = cov * (cov >= self.cfg.prior_floor).to(cov.dtype)
        gate = None
        if self.cfg.prior_gate:
            covered = (cov >= max(self.cfg.prior_floor, 0.5)).to(cov.dtype)
            # The share over the (2r+1)^2 square, clipped at the edges, as a row
            # then a column average (a clipped square is a rectangle): 2 (2r+1)
            # additions per pixel instead of (2r+1)^2.
            r = GATE_RADIUS
            share = F.avg_pool2d(covered, (1, 2 * r + 1), stride=1, padding=(0, r), count_include_pad=False)
            share = F.avg_pool2d(share, (2 * r + 1, 1), stride=1, padding=(r, 0), count_include_pad=False)
            gate = history_weight(share)
        if self.cfg.prior_fill == "chain":
            # Newest history first, each under what is still missing.
            known = cov * color
            weight = cov
            for k in range(self.history_frames_read()):
                v = parts[4 + 2 * k].clamp(0, 1)
                if gate is not None:
                    v = v * gate
                m = (1 - weight) * v
                known = known + m * parts[3 + 2 * k]
                weight = weight + m
            if self.cfg.prior_depth_tol > 0:
                return push_pull_depth(
                    known, weight, cov, parts[-1], self.cfg.pushpull_levels, self.cfg.prior_depth_tol
                )
            return push_pull_clamped(known, weight, self.cfg.pushpull_levels)
        hsum = torch.zeros_like(color)
        wsum = torch.zeros_like(cov)
        vsum = torch.zeros_like(cov)
        for k in range(self.history_frames_read()):
            v = parts[4 + 2 * k].clamp(0, 1)
            wk = v * 0.5**k
            hsum = hsum + parts[3 + 2 * k] * wk
            wsum = wsum + wk
            vsum = vsum + v
        hist = hsum / wsum.clamp(min=1e-4)
        avail = (1 - cov) * vsum.clamp(0, 1)
        known = cov * color + avail * hist
        weight = cov + avail
        return known + (1 - weight) * push_pull(known, weight, self.cfg.pushpull_levels)

    def correction(self, x: torch.Tensor) -> torch.Tensor:
        """The network's output before the prior or input color is added (with
        ``cfg.prior`` its input also holds the prior's three channels)."""
        r = self.cfg.unshuffle
        if r > 1 and self.stem is not None:
            # Pixel-unshuffle followed by the 1x1 stem is one r x r convolution
            # of stride r (stem weight [o, c*r*r + i*r + j] = [o, c, i, j]): the
            # same products, without the 6-D transpose that the unshuffle exports
            # as (58 of 152 ms of ONNX Runtime's time at 1024x576 on 2 threads).
            stem = self.stem[0]
            weight = stem.weight.reshape(stem.out_channels, -1, r, r)
            if self._folds_history_out():
                # The history channels (5 .. 5 + 4K) are not read: `forward`
                # leaves them out of the input, and the weight drops their rows
                # here (it keeps its shape, so checkpoints load either way).
                k = 4 * self.cfg.context_frames
                if x.shape[1] == weight.shape[1]:
                    x = torch.cat([x[:, :5], x[:, 5 + k :]], 1)
                weight = torch.cat([weight[:, :5], weight[:, 5 + k :]], 1)
            h = self.stem[1](F.conv2d(x, weight, stem.bias, stride=r))
        else:
            h = F.pixel_unshuffle(x, r) if r > 1 else x
            if self.stem is not None:
                h = self.stem(h)
        skips = []
        for i, block in enumerate(self.enc):
            if i > 0:
                h = self.down[i - 1](h)
            h = block(h)
            skips.append(h)
        for j, block in enumerate(self.dec):
            skip = skips[len(skips) - 2 - j]
            if self.cfg.skip == "add":
                h = block(F.interpolate(self.proj[j](h), scale_factor=2.0, mode="nearest") + skip)
            else:
                h = F.interpolate(h, scale_factor=2.0, mode="nearest")
                h = block(torch.cat([h, skip], 1))
        out = self.head(h)
        if r > 1:
            out = pixel_shuffle_2(out) if r == 2 else F.pixel_shuffle(out, r)
        return out


def count_macs(model: nn.Module, height: int, width: int) -> tuple[int, int]:
    """Multiply-adds of one forward pass at ``height`` x ``width``, and parameters."""
    macs = 0

    def hook(m, inp, out):
        nonlocal macs
        if isinstance(m, nn.Conv2d):
            k = m.kernel_size[0] * m.kernel_size[1]
            macs += out.numel() // out.shape[0] * (m.in_channels // m.groups) * k

    hs = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Conv2d)]
    cin = len(model.cfg.input_channels())
    with torch.no_grad():
        model(torch.zeros(1, cin, height, width))
    for h in hs:
        h.remove()
    r = model.cfg.unshuffle
    if r > 1 and model.stem is not None:
        # The stem runs as a strided convolution on its reshaped weight (see
        # `Enhancer.correction`), not through its module: the same products.
        stem = model.stem[0]
        macs += stem.out_channels * stem.in_channels * (height // r) * (width // r)
    params = sum(p.numel() for p in model.parameters())
    return macs, params


def activation_bytes_per_pixel(model: Enhancer) -> int:
    """Upper estimate of the peak working memory per input pixel (f32)."""
    cfg = model.cfg
    r2 = cfg.unshuffle**2
    total = len(cfg.input_channels()) + 3
    if cfg.history_blend:
        # Its features, box, clamped history and weights at full resolution,
        # its layers at a quarter of the pixels.
        total += 3 * 3 + 12 + 2 + 2 * cfg.blend_width / 16
    if cfg.prior:
        # The prior, its push-pull pyramid (color and weight, 4/3 of a level) and
        # the concatenated network input.
        total += 3 + 2 * 4 * 4 / 3 + len(cfg.input_channels()) + 3
    total += cfg.stem / r2
    for i, c in enumerate(cfg.widths):
        area = r2 * 4**i
        total += 3 * c / area * (2 if i < len(cfg.widths) - 1 else 1)
    return int(math.ceil(total * 4 * 1.5))


# ---------------------------------------------------------------------------
# Color encoding (exactly the runtime's: core/src/backend/neural/encoding.rs)


def frame_scale(rgba: torch.Tensor, key: float) -> torch.Tensor:
    """``s = key / Lavg`` per frame; ``rgba`` premultiplied ``[N, 4, H, W]``.

    ``Lavg = exp(mean(ln(1e-4 + L)))`` over covered pixels (coverage-weighted,
    straight luminance), clamped to [1e-6, 1e6]; 1 when nothing is covered."""
    a = rgba[:, 3]
    lum = LUMA[0] * rgba[:, 0] + LUMA[1] * rgba[:, 1] + LUMA[2] * rgba[:, 2]
    ok = a >= COVERAGE_EPSILON
    straight = torch.where(ok, lum / a.clamp(min=COVERAGE_EPSILON), torch.zeros_like(lum))
    w = torch.where(ok, a, torch.zeros_like(a))
    s = (w * torch.log(LUMINANCE_FLOOR + straight.clamp(min=0))).sum((1, 2))
    wsum = w.sum((1, 2))
    avg = torch.exp(s / wsum.clamp(min=1e-12))
    scale = (key / avg).clamp(1e-6, 1e6)
    return torch.where(wsum > 0, scale, torch.ones_like(scale))


def encode(x: torch.Tensor, scale: torch.Tensor, log_range: float) -> torch.Tensor:
    """``log2(1 + x s) / log_range``; ``scale`` is ``[N]``."""
    return torch.log1p(x.clamp(min=0) * scale.view(-1, 1, 1, 1)) / (math.log(2.0) * log_range)


def decode(y: torch.Tensor, scale: torch.Tensor, log_range: float) -> torch.Tensor:
    return torch.expm1((y * log_range * math.log(2.0)).clamp(max=80.0)).clamp(min=0) / scale.view(-1, 1, 1, 1)


# ---------------------------------------------------------------------------
# Reprojection (the runtime's motion-vector hop: core/src/temporal/reproject.rs)


def reproject_hop(
    img: torch.Tensor,
    valid: torch.Tensor,
    depth_prev: torch.Tensor | None,
    depth_cur: torch.Tensor | None,
    motion: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Moves ``img`` (and its validity) from the previous frame into the current one.

    ``aligned(i, j) = prev(x = j + 0.5 + mv.x, y = i + 0.5 + mv.y)``, bilinear over
    the taps that are inside the image and whose depth matches the current
    depth (relative ``DEPTH_TOLERANCE``), renormalized; the kept weight is the
    hop's validity, multiplied with the incoming validity.
    Shapes: img ``[N, C, H, W]``, valid/depths ``[N, 1, H, W]``, motion ``[N, 2, H, W]``.
    """
    n, c, h, w = img.shape
    dev = img.device
    jj = torch.arange(w, device=dev, dtype=img.dtype).view(1, 1, w).expand(n, h, w)
    ii = torch.arange(h, device=dev, dtype=img.dtype).view(1, h, 1).expand(n, h, w)
    x = jj + motion[:, 0]
    y = ii + motion[:, 1]
    x0 = torch.floor(x)
    y0 = torch.floor(y)
    fx = x - x0
    fy = y - y0
    src = torch.cat([img * valid, valid] + ([depth_prev] if depth_prev is not None else []), 1)
    flat = src.reshape(n, src.shape[1], h * w)
    acc = torch.zeros(n, c + 1, h, w, device=dev, dtype=img.dtype)
    wsum = torch.zeros(n, h, w, device=dev, dtype=img.dtype)
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        xi = x0 + dx
        yi = y0 + dy
        wt = (fx if dx else 1 - fx) * (fy if dy else 1 - fy)
        inside = (xi >= 0) & (xi <= w - 1) & (yi >= 0) & (yi <= h - 1)
        idx = (yi.clamp(0, h - 1) * w + xi.clamp(0, w - 1)).long().view(n, 1, h * w)
        tap = torch.gather(flat, 2, idx.expand(n, src.shape[1], h * w)).view(n, src.shape[1], h, w)
        keep = inside.to(img.dtype)
        if depth_prev is not None and depth_cur is not None:
            seen = tap[:, c + 1]
            exp = depth_cur[:, 0]
            far_e = exp >= FAR_DEPTH
            far_s = seen >= FAR_DEPTH
            close = (exp - seen).abs() <= DEPTH_TOLERANCE * torch.minimum(exp, seen)
            keep = keep * torch.where(far_e | far_s, far_e & far_s, close).to(img.dtype)
        wk = wt * keep
        acc = acc + tap[:, : c + 1] * wk.unsqueeze(1)
        wsum = wsum + wk
    # tap[:, :c] holds img*valid and tap[:, c] valid: renormalize by the kept valid weight.
    vw = acc[:, c]
    color = torch.where(
        vw.unsqueeze(1) > 1e-6, acc[:, :c] / vw.clamp(min=1e-6).unsqueeze(1), torch.zeros_like(acc[:, :c])
    )
    return color, vw.clamp(0, 1).unsqueeze(1)


def assemble_input(
    cfg: ModelConfig,
    rgba: torch.Tensor,
    insert: torch.Tensor,
    history: list[tuple[torch.Tensor, torch.Tensor]],
    scale: torch.Tensor,
    depth: torch.Tensor | None = None,
) -> torch.Tensor:
    """The network input tensor for one frame.

    ``rgba`` premultiplied linear ``[N, 4, H, W]``; ``insert [N, 1, H, W]``;
    ``history``: up to K (reprojected linear color ``[N, 3, H, W]``, validity)
    pairs, newest first; missing ones are zeros with validity 0; ``depth``
    (planar ``[N, 1, H, W]``) for the ``disparity`` channel of a depth-aware
    prior (zeros without it, as the runtime gives without depth)."""
    n, _, h, w = rgba.shape
    rgb = rgba[:, :3]
    if not cfg.premultiplied:
        a = rgba[:, 3:4]
        ok = a >= COVERAGE_EPSILON
        rgb = torch.where(ok, rgb / a.clamp(min=COVERAGE_EPSILON), torch.zeros_like(rgb))
    parts = [encode(rgb, scale, cfg.log_range), rgba[:, 3:4], insert]
    zero3 = torch.zeros(n, 3, h, w, dtype=rgba.dtype, device=rgba.device)
    zero1 = torch.zeros(n, 1, h, w, dtype=rgba.dtype, device=rgba.device)
    for k in range(cfg.context_frames):
        if k < len(history):
            col, val = history[k]
            parts += [encode(col, scale, cfg.log_range) * (val > 0).to(col.dtype), val]
        else:
            parts += [zero3, zero1]
    if cfg.prior_depth_tol > 0:
        parts.append(1 / (1 + depth.clamp(min=0)) if depth is not None else zero1)
    return torch.cat(parts, 1)
