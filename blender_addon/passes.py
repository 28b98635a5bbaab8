"""The render settings harmonizer needs, checked and set at render start."""

from __future__ import annotations

import os

import bpy

from . import denoise


def render_view_layer(scene: bpy.types.Scene, name: str = "") -> bpy.types.ViewLayer | None:
    """The view layer to enhance: ``name`` if given, else the first one that renders."""
    if name:
        return scene.view_layers.get(name)
    for vl in scene.view_layers:
        if vl.use:
            return vl
    return scene.view_layers[0] if scene.view_layers else None


def mask_names(scene: bpy.types.Scene) -> list[str]:
    """Cryptomatte names of the insert mask (objects, collection members, or typed names)."""
    s = scene.harmonizer
    if s.mask_source == "OBJECT":
        return [s.mask_object.name] if s.mask_object else []
    if s.mask_source == "COLLECTION":
        return sorted({o.name for o in s.mask_collection.all_objects}) if s.mask_collection else []
    if s.mask_source == "CRYPTOMATTE":
        return [n.strip() for n in s.mask_names.split(",") if n.strip()]
    return []


def mask_indices(scene: bpy.types.Scene) -> list[int]:
    """The pass indices of the inserted objects when there are several (the
    Pass Index, then More Indices, each once), else an empty list."""
    s = scene.harmonizer
    if s.mask_source != "OBJECT_INDEX":
        return []
    out = [s.mask_index]
    for part in s.mask_more_indices.split(","):
        part = part.strip()
        if part.isdigit() and int(part) not in out:
            out.append(int(part))
    return out if len(out) > 1 else []


def check(
    scene: bpy.types.Scene, *, apply: bool, denoising_data: bool = False, at_render: bool = False
) -> list[tuple[str, str]]:
    """Check (and with ``apply``, fix) what harmonizer needs.

    Returns (level, message) pairs: 'INFO' for what was changed, 'WARNING' for
    what the user has to look at, 'ERROR' for what stops harmonizer. The
    Denoising Data passes of a render that will be denoised are switched on
    only with ``apply`` and ``denoising_data`` both (the user asked: the "Set
    Up Passes" button); otherwise they are a warning, or a note at render
    start (``at_render``; see ``denoise``).
    """
    s = scene.harmonizer
    out: list[tuple[str, str]] = []
    vl = render_view_layer(scene, s.view_layer)
    if vl is None:
        return [("ERROR", f"Harmonizer: view layer {s.view_layer!r} not found in scene {scene.name!r}")]

    wanted = {
        "use_pass_combined": "Combined",
        "use_pass_z": "Depth",
        "use_pass_vector": "Vector",
        "use_pass_normal": "Normal",
    }
    if s.mask_source == "OBJECT_INDEX":
        wanted["use_pass_object_index"] = "Object Index"
    elif s.mask_source in {"OBJECT", "COLLECTION"}:
        wanted["use_pass_cryptomatte_object"] = "Cryptomatte Object"
    elif s.mask_source == "CRYPTOMATTE":
        prop = {
            "CryptoObject": "use_pass_cryptomatte_object",
            "CryptoMaterial": "use_pass_cryptomatte_material",
            "CryptoAsset": "use_pass_cryptomatte_asset",
        }[s.mask_crypto_layer]
        wanted[prop] = "Cryptomatte"
    for prop, label in wanted.items():
        if not getattr(vl, prop):
            if apply:
                setattr(vl, prop, True)
                out.append(("INFO", f"Harmonizer: enabled the {label} pass on view layer {vl.name!r}"))
            else:
                out.append(("WARNING", f"Harmonizer: the {label} pass is off on view layer {vl.name!r}"))

    render = scene.render
    if render.use_motion_blur:
        out.append(
            (
                "WARNING",
                "Harmonizer: motion blur is on; the Vector pass is then not the per-frame motion "
                "harmonizer needs, so temporal reprojection will be poor. Turn motion blur off.",
            )
        )
    fmt = render.image_settings
    if fmt.file_format != "OPEN_EXR_MULTILAYER":
        if apply:
            fmt.media_type = "MULTI_LAYER_IMAGE"
            fmt.file_format = "OPEN_EXR_MULTILAYER"
            if fmt.color_depth not in {"16", "32"}:
                fmt.color_depth = "32"
            out.append(("INFO", "Harmonizer: output set to multilayer OpenEXR (harmonizer reads the passes from it)"))
        else:
            out.append(
                ("WARNING", f"Harmonizer: output format is {fmt.file_format}; harmonizer needs multilayer OpenEXR")
            )
    if s.mask_source == "OBJECT" and s.mask_object is None:
        out.append(("WARNING", "Harmonizer: insert mask source is Object but no object is set"))
    if s.mask_source == "COLLECTION" and s.mask_collection is None:
        out.append(("WARNING", "Harmonizer: insert mask source is Collection but no collection is set"))
    if s.mask_source == "OBJECT_INDEX":
        bad = [p.strip() for p in s.mask_more_indices.split(",") if p.strip() and not p.strip().isdigit()]
        if bad:
            out.append(("WARNING", f"Harmonizer: More Indices {', '.join(map(repr, bad))} are not pass indices"))
        if mask_indices(scene) and 0 in mask_indices(scene):
            out.append(("WARNING", "Harmonizer: pass index 0 is every object without one; it cannot name an object"))
    # The inserts' albedo (Albedo Tone) is the Denoising Data passes' albedo.
    if s.mask_source != "NONE" and s.albedo_tone and denoise.guides_available(scene, vl) and not denoise.guides_on(vl):
        if apply:
            vl.cycles.denoising_store_passes = True
            out.append(
                (
                    "INFO",
                    f"Harmonizer: enabled the Denoising Data passes on view layer {vl.name!r} "
                    "(the albedo Albedo Tone corrects the inserts' colors with)",
                )
            )
        else:
            out.append(
                (
                    "WARNING",
                    f"Harmonizer: the Denoising Data passes are off on view layer {vl.name!r}: "
                    "Albedo Tone has no albedo and leaves the inserts' colors as rendered",
                )
            )
    out += denoise.check_guides(scene, vl, apply=apply and denoising_data, at_render=at_render)
    return out


def still_path(scene: bpy.types.Scene) -> str:
    """The file Blender 5.0 writes for a still (``render(write_still=True)``).

    Not ``frame_path()``: a still is named after the output path with no frame
    number (``####`` stays as it is, a path without ``#`` gets no digits), and
    the format's extension is made sure of (``shot.png`` -> ``shot.exr``).
    """
    render = scene.render
    path = bpy.path.abspath(render.filepath)
    if render.use_file_extension:
        ext = render.file_extension
        if not path.lower().endswith(ext.lower()):
            root, old = os.path.splitext(path)
            if old.lower() in bpy.path.extensions_image:
                path = root
            path += ext
    return path


def enhanced_path(scene: bpy.types.Scene, raw_path: str, frame: int, *, still: bool = False) -> str:
    """Where the enhanced frame for ``raw_path`` goes.

    A still (``still``) is named as Blender names the raw still: the Enhanced
    Frames path with its frame tokens kept, so it never takes the place of an
    animation frame.
    """
    s = scene.harmonizer
    if s.overwrite_raw:
        return raw_path
    if s.output_path:
        base = bpy.path.abspath(s.output_path)
        if os.path.isdir(base) or base.endswith(("/", os.sep)):
            return os.path.join(base, os.path.basename(raw_path))
        from . import sequence

        path = base if still else sequence.expand(base, frame)
        if not path.lower().endswith(".exr"):
            path += ".exr"
        return path
    return os.path.join(os.path.dirname(raw_path), "harmonized", os.path.basename(raw_path))
