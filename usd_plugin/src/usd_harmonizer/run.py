"""Runs every selected product of a stage, frame by frame, and records the
outputs in a layer: what ``usd-harmonize`` does."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from . import binding
from .layer import write_layer
from .process import (
    FrameResult,
    Options,
    ProductRunner,
    check_outputs,
    make_device,
)
from .errors import SettingsError
from .settings import ProductInfo, SettingsInfo, open_stage, resolve


@dataclass
class RunSummary:
    """Results of one run."""

    settings: SettingsInfo
    results: dict[str, tuple[ProductInfo, list[FrameResult]]] = field(
        default_factory=dict
    )
    layer: Path | None = None
    #: Pre-roll frames processed (not written), over all products.
    preroll_frames: int = 0


def run_stage(
    stage_path: str | os.PathLike[str],
    settings: str | None = None,
    products: list[str] | None = None,
    frames: list[int] | None = None,
    options: Options | None = None,
    layer: str | os.PathLike[str] | None = None,
    in_place: bool = False,
    write_layer_file: bool = True,
    base_dir: str | os.PathLike[str] | None = None,
    on_frame: Callable[[int, int, ProductInfo, int], None] | None = None,
    preroll: int = 0,
) -> RunSummary:
    """Processes ``frames`` (default: the stage's range) of each product in
    increasing order, one session per product; writes the layer unless
    ``write_layer_file`` is False. ``on_frame(done, total, product, frame)``
    is called before each frame.

    ``preroll`` (needs ``frames``): each product first processes the
    frames ``first - preroll .. first - 1`` whose files exist, without
    writing them, so a chunk of a shot starts with the temporal state of a
    sequential run (``harmonize run --frames A-B --preroll N``)."""
    options = options or Options()
    if preroll < 0:
        raise SettingsError(f"--preroll {preroll}: expected a number of frames >= 0")
    if preroll and frames is None:
        raise SettingsError(
            "--preroll needs --frames A-B: the frames before A warm the temporal state"
        )
    stage = open_stage(stage_path)
    info = resolve(stage, settings, products, frames, base_dir)
    order = sorted(info.frames)
    for p in info.products:
        p.check_frames_distinct(order)
    check_outputs(info.products, order, options.out_dir)
    summary = RunSummary(info)
    # The pre-roll frames of each product that exist (fewer at the start
    # of a shot; a missing one in between is a gap, as in any run).
    warm = {
        p.path: [
            f
            for f in range(order[0] - preroll, order[0])
            if preroll and p.file_for(f).is_file()
        ]
        for p in info.products
    }
    total = sum(len(order) + len(warm[p.path]) for p in info.products)
    done = 0
    device = make_device(options)
    try:
        for prod in info.products:
            runner = ProductRunner(prod, info, device, options)
            try:
                for f in warm[prod.path]:
                    if on_frame:
                        on_frame(done, total, prod, f)
                    runner.process_frame(f, write=False)
                    summary.preroll_frames += 1
                    done += 1
                for f in order:
                    if on_frame:
                        on_frame(done, total, prod, f)
                    runner.process_frame(f)
                    done += 1
            finally:
                summary.results[prod.path] = (prod, list(runner.results))
                runner.close()
    finally:
        device.close()
    if on_frame:
        on_frame(done, total, info.products[-1], order[-1])
    if write_layer_file:
        summary.layer = write_layer(
            info,
            summary.results,
            Path(layer) if layer else None,
            in_place,
            version=binding.load().version(),
        )
    return summary
