"""``PostFrameHook``: per-frame post-processing for render farms.

A farm task that renders one frame at a time calls the hook after each frame;
the hook keeps one session per product across calls in the same process, so
consecutive frames share temporal state. A frame that arrives out of order
(not after the previous one) resets that product's state; a gap is handled
by the library's ``gap_policy`` (reset by default).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Self

from . import binding
from .layer import write_layer
from .process import (
    FrameResult,
    Options,
    ProductRunner,
    check_outputs,
    make_device,
)
from .settings import SettingsInfo, open_stage, resolve


class PostFrameHook:
    """Enhances each product's file of one frame per call.

    ``stage``: a stage file path or an open ``Usd.Stage``; ``settings``: a
    RenderSettings prim path (default: the stage's); ``products``: product
    names or paths (default: all); ``options``: :class:`Options`, or keyword
    options (``backend="classical"``, ``out_dir=...``, ``params={...}``).
    """

    def __init__(
        self,
        stage: Any,
        settings: str | None = None,
        products: list[str] | None = None,
        options: Options | None = None,
        base_dir: str | os.PathLike[str] | None = None,
        **kw: Any,
    ) -> None:
        if options is None:
            options = Options(**kw)
        elif kw:
            raise TypeError("pass either options or keyword options, not both")
        self.options = options
        self.stage = (
            open_stage(stage) if isinstance(stage, (str, os.PathLike)) else stage
        )
        self._settings_path = settings
        self._products = products
        self._base_dir = base_dir
        self.info: SettingsInfo = resolve(
            self.stage, settings, products, frames=[], base_dir=base_dir
        )
        self.device = make_device(options)
        self.runners: dict[str, ProductRunner] = {
            p.path: ProductRunner(p, self.info, self.device, options)
            for p in self.info.products
        }

    def __call__(self, frame: int) -> list[FrameResult]:
        """Processes ``frame`` of every product; returns one result per product.
        Nothing is written when two products would write one file or over an
        input (:func:`~usd_harmonizer.process.check_outputs`)."""
        products = [r.product for r in self.runners.values()]
        check_outputs(products, [int(frame)], self.options.out_dir)
        out = []
        for runner in self.runners.values():
            reset = runner.last_frame is not None and frame <= runner.last_frame
            r = runner.process_frame(int(frame), reset=reset)
            out.append(r)
        return out

    def reset(self) -> None:
        """Drops every product's temporal state."""
        for r in self.runners.values():
            r.session.reset()
            r.last_frame = None

    def write_layer(
        self, path: str | os.PathLike[str] | None = None, in_place: bool = False
    ) -> Path:
        """Records the outputs so far as new RenderProducts (see :mod:`usd_harmonizer.layer`)."""
        results = {p: (r.product, _latest(r.results)) for p, r in self.runners.items()}
        return write_layer(
            self.info,
            results,
            Path(path) if path else None,
            in_place=in_place,
            version=binding.load().version(),
        )

    def close(self) -> None:
        """Releases the sessions and the device."""
        for r in self.runners.values():
            r.close()
        self.runners.clear()
        self.device.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _latest(results: list[FrameResult]) -> list[FrameResult]:
    """The last result per frame, in frame order."""
    by_frame = {r.frame: r for r in results}
    return [by_frame[f] for f in sorted(by_frame)]
