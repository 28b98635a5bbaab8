"""Renders a USD stage with Blender's Cycles (CPU) into Blender multilayer EXRs.

Runs in ``.venv-bpy`` (bpy 5.0.1, which ships its own ``pxr``), never in the
usd-core venv. Usage:

    python blender_render.py STAGE OUT_DIR WIDTH HEIGHT SAMPLES FIRST LAST INSERT_NAMES

Writes ``OUT_DIR/blender.####.exr`` (parts ViewLayer.Combined, .Depth, .Vector,
.Normal, .Object Index, and the Denoising Data passes .Denoising Albedo,
.Denoising Normal, .Denoising Depth for the denoise tests) for frames FIRST..LAST. Objects named in the
comma-separated INSERT_NAMES (prims the stage marks ``harmonizer:insert``) get
pass index 1 (the insert mask). The stage is read only through Blender's USD
importer; the caller resolves the stage with usd-core.
Motion blur is off so the Vector pass is valid.
"""

from __future__ import annotations

import os
import sys

import bpy


def main(argv: list[str]) -> int:
    stage_path, out_dir, width, height, samples, first, last, names = argv
    first, last = int(first), int(last)
    insert_names = {n for n in names.split(",") if n}

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.wm.usd_import(
        filepath=os.path.abspath(stage_path),
        set_frame_range=True,
        import_usd_preview=True,
    )
    scene = bpy.context.scene
    cams = [o for o in scene.objects if o.type == "CAMERA"]
    if len(cams) != 1:
        print(
            f"expected one camera in {stage_path}, found {[c.name for c in cams]}",
            file=sys.stderr,
        )
        return 2
    scene.camera = cams[0]
    found = set()
    for obj in scene.objects:
        if obj.name in insert_names:
            obj.pass_index = 1
            found.add(obj.name)
    if found != insert_names:
        print(
            f"insert prims not imported: {sorted(insert_names - found)}",
            file=sys.stderr,
        )
        return 2

    if scene.world is None:
        scene.world = bpy.data.worlds.new("World")
    scene.world.color = (0.05, 0.06, 0.08)
    scene.frame_start, scene.frame_end = first, last
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(samples)
    scene.cycles.use_denoising = False
    scene.cycles.seed = 7
    scene.render.threads_mode = "FIXED"
    scene.render.threads = 1
    scene.render.use_motion_blur = False
    scene.render.resolution_x = int(width)
    scene.render.resolution_y = int(height)
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    vl = scene.view_layers[0]
    vl.use_pass_z = True
    vl.use_pass_vector = True
    vl.use_pass_normal = True
    vl.use_pass_object_index = True
    vl.cycles.denoising_store_passes = True
    settings = scene.render.image_settings
    settings.media_type = "MULTI_LAYER_IMAGE"
    settings.file_format = "OPEN_EXR_MULTILAYER"
    settings.color_depth = "32"
    settings.exr_codec = "ZIP"
    scene.render.filepath = os.path.join(os.path.abspath(out_dir), "blender.####.exr")
    bpy.ops.render.render(animation=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
