"""Harmonizer for Blender 5.0: enhanced, temporally stable frames from animation renders.

Modules:
- ``props``: the scene settings (``scene.harmonizer``);
- ``panel``: the Harmonizer panel in Properties > Render;
- ``passes``: the passes and output format harmonizer needs;
- ``denoise``: the denoise stage's ``samples`` and its Denoising Data passes;
- ``handlers``: render_init / render_write / render_complete / render_cancel;
- ``processor``, ``exrio``, ``colorspace``, ``sequence``: frames through the
  library (no ``bpy``);
- ``nodes``: the "Harmonizer" compositor node group;
- ``ops``: the "Enhance Rendered Sequence" operator;
- ``reports``: messages from handlers as Blender reports;
- ``deps``: the modules it runs on (OpenImageIO, PyOpenColorIO, the binding).
"""

from __future__ import annotations

if "bpy" in locals():  # reload (Reload Scripts / disable + enable)
    import importlib

    for _name in (
        "deps",
        "denoise",
        "exrio",
        "colorspace",
        "sequence",
        "processor",
        "light",
        "props",
        "passes",
        "reports",
        "runtime",
        "handlers",
        "nodes",
        "ops",
        "panel",
    ):
        if _name in locals():
            importlib.reload(locals()[_name])

import bpy  # noqa: E402, F401  (the reload check above looks for it)

from . import (  # noqa: E402
    colorspace,
    denoise,
    deps,
    exrio,
    handlers,
    light,
    nodes,
    ops,
    panel,
    passes,
    processor,
    props,
    reports,
    runtime,
    sequence,
)

_MODULES = (props, reports, handlers, nodes, ops, panel)


def register() -> None:
    for m in _MODULES:
        m.register()


def unregister() -> None:
    for m in reversed(_MODULES):
        m.unregister()


__all__ = [
    "colorspace",
    "denoise",
    "deps",
    "exrio",
    "handlers",
    "nodes",
    "ops",
    "panel",
    "passes",
    "processor",
    "props",
    "register",
    "reports",
    "runtime",
    "sequence",
    "unregister",
]
