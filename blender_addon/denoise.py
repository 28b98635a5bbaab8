"""What the library's denoise stage is told about a render, and its guide passes.

The session parameters ``denoise`` (auto/on/off) and ``denoise_quality`` come
from the panel; ``samples`` comes from the render settings (``session_samples``):

- Cycles without its own denoiser: the samples per pixel the view layer
  renders (the scene's, or the view layer's override as Cycles applies it).
  ``denoise auto`` is then on for 1..64 samples and off above.
- Cycles with its own denoiser on this view layer: ``denoise`` is passed
  as ``temporal`` when the panel says Auto (``session_mode``): no second
  spatial pass over frames Cycles already denoised (telling the library "4
  samples" here would denoise twice), only the library's temporal
  accumulation, which removes the frame-to-frame flicker a per-frame
  denoiser leaves (out of domain: 34.80 dB and 0.51x the warping error of
  Cycles' per-frame output, docs/model_card.md). ``samples`` is 0.
- Adaptive sampling whose sample limit is above 64: 0, because Cycles stops
  each pixel once its noise threshold is reached, often long before the
  limit, so the limit says little about the noise left. At most 64 samples
  it is passed as it is: every pixel stopped at or below it, so the frame is
  noisy.
- A time limit, or another engine (EEVEE, Workbench): 0, measured.

The "Denoising Data" passes (``view_layer.cycles.denoising_store_passes``)
give the denoiser its albedo and normal guides, which keep texture and edge
detail. They change what Cycles computes and writes (three more passes in
each file), so the extension switches them on only when the user asks: the
checkbox in the Harmonizer panel (Blender's own property of the view layer)
or the "Set Up Passes" button. Render start never turns them on by itself,
not even with "Enable Needed Passes", which covers the passes the enhancer
cannot work without; when a render will be denoised without them it says so.
"""

from __future__ import annotations

import bpy

#: ``denoise auto`` is on for a sample count of 1 up to this, off above
#: (the library's rule: core/src/params.rs, ``denoise``).
AUTO_MAX_SAMPLES = 64


def cycles_denoises(scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer) -> bool:
    """Whether Cycles' own denoiser runs on ``view_layer``'s final render."""
    if scene.render.engine != "CYCLES":
        return False
    vl_on = getattr(getattr(view_layer, "cycles", None), "use_denoising", True)
    return bool(scene.cycles.use_denoising and vl_on)


def render_samples(scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer) -> int:
    """Cycles' samples per pixel (the upper limit with adaptive sampling) for ``view_layer``."""
    cy = scene.cycles
    samples = int(cy.samples)
    layer = int(getattr(view_layer, "samples", 0))
    mode = getattr(cy, "use_layer_samples", "USE")
    if layer > 0 and mode == "USE":
        samples = layer
    elif layer > 0 and mode == "BOUNDED":
        samples = min(samples, layer)
    return samples


def session_samples(scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer) -> tuple[int, str]:
    """The ``samples`` parameter for a render of ``view_layer``, and why (see the module doc)."""
    engine = scene.render.engine
    if engine != "CYCLES":
        return 0, f"{engine.replace('BLENDER_', '').title()} render"
    if cycles_denoises(scene, view_layer):
        return 0, "Cycles denoises each frame"
    if scene.cycles.time_limit > 0:
        return 0, "Cycles renders to a time limit"
    samples = render_samples(scene, view_layer)
    if scene.cycles.use_adaptive_sampling and samples > AUTO_MAX_SAMPLES:
        return 0, f"adaptive sampling up to {samples} samples"
    return samples, f"{samples} samples, no Cycles denoiser"


def session_mode(scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer | None, mode: str) -> tuple[str, str]:
    """The ``denoise`` parameter for a render of ``view_layer`` with the panel's ``mode``, and why.

    Auto becomes ``temporal`` when Cycles denoises the layer itself (see the
    module doc); On and Off are passed as they are.
    """
    if mode == "auto" and view_layer is not None and cycles_denoises(scene, view_layer):
        return "temporal", "Cycles denoises each frame: its flicker is accumulated away, no second denoiser pass"
    return mode, ""


def file_hints(exr, view_layer: str) -> tuple[int, bool]:
    """What a rendered multilayer EXR says about its noise: Cycles' samples
    (``cycles.<view layer>.samples``, 0 when absent) and whether Cycles'
    denoiser ran (its ``Noisy Image`` pass is in the file)."""
    try:
        samples = int(str(exr.attribute(f"cycles.{view_layer}.samples", 0)).strip())
    except ValueError:
        samples = 0
    denoised = any(c.startswith(f"{view_layer}.Noisy Image.") for c in exr.channel_names())
    return max(samples, 0), denoised


def sequence_settings(mode: str, exr, view_layer: str) -> tuple[str, int, str]:
    """``denoise``, ``samples`` and why for the sequence operator: with the
    panel's Auto, what the first file says (``file_hints``): ``temporal``
    for frames Cycles denoised, else its sample count (0: the library
    measures the first frame); other modes as they are, samples 0."""
    if mode != "auto":
        return mode, 0, ""
    samples, denoised = file_hints(exr, view_layer)
    if denoised:
        return "temporal", 0, "the files have Cycles' Noisy Image pass: its denoiser ran, so denoise temporal"
    if samples:
        return "auto", samples, f"the files say Cycles took {samples} samples per pixel"
    return "auto", 0, ""


def expected(scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer) -> bool:
    """Whether this render will be denoised as far as the settings tell.

    ``on``, or ``auto`` with a known sample count the library denoises. An
    unknown count (0) is decided on the first frame and not counted here.
    """
    mode = scene.harmonizer.denoise
    if mode == "off":
        return False
    if mode == "on":
        return True
    samples, _why = session_samples(scene, view_layer)
    return 1 <= samples <= AUTO_MAX_SAMPLES


def auto_summary(scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer) -> str:
    """One line for the panel: what ``denoise auto`` will do with this render."""
    if session_mode(scene, view_layer, "auto")[0] == "temporal":
        return "Auto: temporal only (Cycles denoises each frame)"
    samples, why = session_samples(scene, view_layer)
    if samples == 0:
        return f"Auto: the first frame's noise decides ({why})"
    return f"Auto: {'on' if samples <= AUTO_MAX_SAMPLES else 'off'} ({why})"


def guides_available(scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer) -> bool:
    """Whether the Denoising Data passes exist for this render (Cycles only)."""
    return scene.render.engine == "CYCLES" and hasattr(getattr(view_layer, "cycles", None), "denoising_store_passes")


def guides_on(view_layer: bpy.types.ViewLayer) -> bool:
    """Whether ``view_layer`` stores the Denoising Data passes."""
    return bool(getattr(getattr(view_layer, "cycles", None), "denoising_store_passes", False))


def check_guides(
    scene: bpy.types.Scene, view_layer: bpy.types.ViewLayer, *, apply: bool, at_render: bool = False
) -> list[tuple[str, str]]:
    """The Denoising Data passes of a render that will be denoised: on (``apply``) or a note.

    Returns (level, message) pairs as ``passes.check`` does; nothing when the
    render will not be denoised, the engine has no such passes, or they are on.
    The note is a 'WARNING' for the panel (beside the button that fixes it)
    and an 'INFO' at render start (``at_render``): a render denoised without
    guides is still denoised, and the user may want it so.
    """
    if not expected(scene, view_layer) or not guides_available(scene, view_layer) or guides_on(view_layer):
        return []
    if apply:
        view_layer.cycles.denoising_store_passes = True
        return [
            (
                "INFO",
                f"Harmonizer: enabled the Denoising Data passes on view layer {view_layer.name!r} "
                "(albedo and normal guides for the denoiser)",
            )
        ]
    return [
        (
            "INFO" if at_render else "WARNING",
            f"Harmonizer: frames will be denoised without the Denoising Data passes of view layer "
            f"{view_layer.name!r} (albedo and normal guides keep texture detail); turn on Denoising Data",
        )
    ]
