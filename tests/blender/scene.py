"""Fixture scene for the Blender extension tests.

A small animated scene: a floor, a few objects, a moving camera and an
"inserted" object (collection ``Inserted``, pass index 7). Cycles on the CPU,
160x90, few samples, 8 frames, written as multilayer EXR. Nothing here depends
on the extension: it builds what a user would have before enabling it.
"""

from __future__ import annotations

import math

import bpy

WIDTH, HEIGHT = 160, 90
FRAMES = (1, 8)
INSERT_PASS_INDEX = 7


def _material(name: str, rgb: tuple[float, float, float], roughness: float = 0.5) -> bpy.types.Material:
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (*rgb, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    return mat


def _link(obj: bpy.types.Object, collection: bpy.types.Collection) -> None:
    for c in list(obj.users_collection):
        c.objects.unlink(obj)
    collection.objects.link(obj)


def _render_settings(
    scene: bpy.types.Scene, output_pattern: str, samples: int, size: tuple[int, int], frames: tuple[int, int]
) -> bpy.types.RenderSettings:
    """Cycles on the CPU, no denoising or motion blur, one thread, float multilayer EXR output."""
    render = scene.render
    render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    scene.cycles.use_adaptive_sampling = False
    render.resolution_x, render.resolution_y = size
    render.resolution_percentage = 100
    render.use_motion_blur = False
    render.threads_mode = "FIXED"
    render.threads = 1
    render.filepath = output_pattern
    settings = render.image_settings
    settings.media_type = "MULTI_LAYER_IMAGE"
    settings.file_format = "OPEN_EXR_MULTILAYER"
    settings.color_depth = "32"
    scene.frame_start, scene.frame_end = frames
    return render


def build(output_pattern: str, *, samples: int = 4, frames: tuple[int, int] = FRAMES) -> bpy.types.Scene:
    """Reset Blender to an empty file and build the fixture scene.

    ``output_pattern`` is the render output path (``####`` is the frame number).
    """
    # An empty file; the preferences (and so the enabled extension) are kept.
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.name = "Fixture"

    render = _render_settings(scene, output_pattern, samples, (WIDTH, HEIGHT), frames)
    render.film_transparent = False
    render.image_settings.exr_codec = "ZIP"

    world = bpy.data.worlds.new("World")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.25, 0.35, 0.55, 1.0)
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.6
    scene.world = world

    base = scene.collection
    inserted = bpy.data.collections.new("Inserted")
    base.children.link(inserted)

    bpy.ops.mesh.primitive_plane_add(size=30.0, location=(0, 0, 0))
    floor = bpy.context.active_object
    floor.name = "Floor"
    floor.data.materials.append(_material("FloorMat", (0.55, 0.5, 0.45), 0.8))

    bpy.ops.mesh.primitive_cube_add(size=1.4, location=(-1.6, 0.8, 0.7))
    cube = bpy.context.active_object
    cube.name = "Cube"
    cube.data.materials.append(_material("CubeMat", (0.7, 0.12, 0.08), 0.4))
    cube.rotation_euler = (0, 0, math.radians(25))

    bpy.ops.mesh.primitive_cylinder_add(radius=0.5, depth=2.0, location=(1.8, 1.6, 1.0))
    cyl = bpy.context.active_object
    cyl.name = "Pillar"
    cyl.data.materials.append(_material("PillarMat", (0.15, 0.45, 0.2), 0.3))

    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.6, location=(0.3, -0.4, 0.6), segments=24, ring_count=12)
    ins = bpy.context.active_object
    ins.name = "InsertedSphere"
    ins.pass_index = INSERT_PASS_INDEX
    # Inserted the way a composited element often is: it casts no shadow on the floor.
    ins.visible_shadow = False
    ins.data.materials.append(_material("InsertedMat", (0.9, 0.85, 0.2), 0.25))
    _link(ins, inserted)
    # The inserted object moves on its own, so the motion vectors carry object motion too.
    ins.keyframe_insert("location", frame=frames[0])
    ins.location.x += 0.6
    ins.keyframe_insert("location", frame=frames[1])

    bpy.ops.object.light_add(type="SUN", location=(0, 0, 5))
    sun = bpy.context.active_object
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(40), math.radians(15), math.radians(30))

    bpy.ops.object.camera_add(location=(0.0, -7.5, 3.2))
    cam = bpy.context.active_object
    cam.name = "Camera"
    cam.data.lens = 28
    cam.rotation_euler = (math.radians(70), 0, 0)
    scene.camera = cam
    cam.keyframe_insert("location", frame=frames[0])
    cam.keyframe_insert("rotation_euler", frame=frames[0])
    cam.location.x += 1.2
    cam.rotation_euler.z += math.radians(6)
    cam.keyframe_insert("location", frame=frames[1])
    cam.keyframe_insert("rotation_euler", frame=frames[1])
    for obj in (cam, ins):
        for fc in obj.animation_data.action.fcurves if hasattr(obj.animation_data.action, "fcurves") else ():
            for kp in fc.keyframe_points:
                kp.interpolation = "LINEAR"

    vl = scene.view_layers[0]
    vl.name = "ViewLayer"
    return scene


#: Emission colors of the wide-gamut scene, in ACEScg: primaries and mixes, most
#: of them outside Rec.709 (negative components in Linear Rec.709).
WIDE_GAMUT_COLORS = (
    (1.0, 0.0, 0.0),
    (0.0, 1.0, 0.0),
    (0.0, 0.0, 1.0),
    (0.0, 0.9, 0.9),
    (0.9, 0.0, 0.9),
    (0.9, 0.9, 0.0),
    (2.5, 0.05, 0.1),
    (0.3, 0.3, 0.3),
)


def build_wide_gamut(output_pattern: str, *, frames: tuple[int, int] = (1, 2)) -> bpy.types.Scene:
    """An empty file in the ACEScg working space: emissive tiles of saturated ACEScg colors.

    48x27, 1 sample (emission only, nothing to converge), a still camera over
    a 4x2 grid of tiles on a saturated green background.
    """
    bpy.ops.wm.read_homefile(use_empty=True)
    if bpy.data.colorspace.working_space != "ACEScg":
        assert bpy.ops.wm.set_working_color_space(working_space="ACEScg", convert_colors=False) == {"FINISHED"}
    scene = bpy.context.scene
    scene.name = "WideGamut"
    render = _render_settings(scene, output_pattern, 1, (48, 27), frames)

    world = bpy.data.worlds.new("World")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.0, 0.8, 0.1, 1.0)
    scene.world = world
    for k, rgb in enumerate(WIDE_GAMUT_COLORS):
        mat = bpy.data.materials.new(f"Tile{k}")
        mat.use_nodes = True
        nodes = mat.node_tree.nodes
        nodes.remove(nodes["Principled BSDF"])
        emission = nodes.new("ShaderNodeEmission")
        emission.inputs["Color"].default_value = (*rgb, 1.0)
        mat.node_tree.links.new(emission.outputs["Emission"], nodes["Material Output"].inputs["Surface"])
        bpy.ops.mesh.primitive_plane_add(size=0.9, location=(-1.5 + (k % 4), 0.5 - (k // 4), 0.0))
        bpy.context.active_object.data.materials.append(mat)
    bpy.ops.object.camera_add(location=(0.0, 0.0, 4.0))
    scene.camera = bpy.context.active_object
    scene.view_layers[0].name = "ViewLayer"
    return scene
