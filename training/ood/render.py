"""Renders the out-of-domain benchmark scenes with Blender (bpy 5.0.1, Cycles on the CPU).

    .venv-bpy/bin/python -m training.ood.render --scene courtyard --out training/ood/data
    .venv-bpy/bin/python -m training.ood.render --scene hall --out training/ood/data
    .venv-bpy/bin/python -m training.ood.render --scene ruins --out training/ood/data

Nothing here comes from the training generator's world: no Sweet Home 3D
furniture, no bundled HDRI, no room of procedural plaster. The geometry is
Blender's own (Suzanne, bevelled boxes, displaced rocks, walls, pillars), the
textures come from two Debian game-data packages (``assets.py``), the light is
a physical sky with a sun (outdoors) or ceiling area lights and a lamp
(indoors), and the camera travels several metres in 24 frames (the training
cameras orbit).

Per frame of ``courtyard`` (outdoor; two inserts ``insert_a`` and ``insert_b``):
``truth``, ``noinsert_ab`` (both inserts hidden), ``relit``
(another sun and sky), ``albedo`` (Cycles' Denoising Albedo of the truth
render: what a host gives as the albedo AOV), ``alone_a`` and
``relit_alone_a`` (``insert_a`` rendered on its own, every other mesh a
holdout on a transparent film, under each light: what a host composites),
plus three static context views for the sparse-view reconstruction
(``--add-albedo`` and ``--add-alone`` add those passes to a render made
before they were kept). Per frame of ``hall`` (indoor): ``truth`` and ``noisy`` (4
samples, a new seed per frame, stored raw and through Cycles' own denoiser,
with the denoiser's albedo and normal passes), plus three context views.
Per frame of ``ruins`` (outdoor, no inserts): ``truth``, plus four context
views; the camera arcs round a colonnade, so pillars uncover what they hid.

Clean passes: ``--samples`` (default 128) samples, adaptive (noise threshold
0.005), then OIDN with albedo and normal, which Cycles' production renders use.
Writes ``<out>/<scene>/scene.npz`` (packed by ``sequences.pack``) and ``meta.json``;
``sequences.py`` builds the benchmark sequences from them.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from pathlib import Path

import numpy as np

try:
    import bpy
    from mathutils import Vector
except ImportError:  # pragma: no cover - run with the bpy venv
    print("ood.render: this script needs the 'bpy' module (.venv-bpy)", file=sys.stderr)
    raise

from training.ood.assets import ASSETS, fetch
from training.ood.sequences import pack
from training.synth import degrade
from training.synth.exr import _channels, read_blender_exr
from training.synth.render_scene import camera_matrices, crypto_mask, reset_blender, scene_checks


def reset(width: int, height: int, threads: int) -> bpy.types.Scene:
    """The training renderer's settings (passes, EXR, 4 bounces, no motion blur)."""
    return reset_blender({"width": width, "height": height, "threads": threads})


def textured(name: str, image: str, scale: float, roughness: float = 0.6, tint=(1, 1, 1), bump: float = 0.0):
    """A material from one of ``assets/`` textures, mapped in object space (``scale`` repeats per metre)."""
    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    bsdf = nt.nodes.get("Principled BSDF")
    tc = nt.nodes.new("ShaderNodeTexCoord")
    mp = nt.nodes.new("ShaderNodeMapping")
    mp.inputs["Scale"].default_value = (scale, scale, scale)
    nt.links.new(tc.outputs["Object"], mp.inputs["Vector"])
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = bpy.data.images.load(str(ASSETS / image))
    tex.projection = "BOX"
    tex.projection_blend = 0.2
    nt.links.new(mp.outputs["Vector"], tex.inputs["Vector"])
    mix = nt.nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    mix.blend_type = "MULTIPLY"
    mix.inputs["Factor"].default_value = 1.0
    nt.links.new(tex.outputs["Color"], mix.inputs["A"])
    mix.inputs["B"].default_value = (*tint, 1.0)
    nt.links.new(mix.outputs["Result"], bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = roughness
    if bump > 0:
        b = nt.nodes.new("ShaderNodeBump")
        b.inputs["Strength"].default_value = bump
        nt.links.new(tex.outputs["Color"], b.inputs["Height"])
        nt.links.new(b.outputs["Normal"], bsdf.inputs["Normal"])
    return mat


def painted(name: str, color, roughness: float, metallic: float = 0.0, coat: float = 0.0):
    mat = bpy.data.materials.new(name)
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Metallic"].default_value = metallic
    bsdf.inputs["Coat Weight"].default_value = coat
    return mat


def box(name, size, loc, rot_z, mat, bevel=0.0):
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=loc, rotation=(0, 0, math.radians(rot_z)))
    o = bpy.context.active_object
    o.name = name
    o.scale = size
    bpy.ops.object.transform_apply(scale=True)
    if bevel > 0:
        m = o.modifiers.new("bevel", "BEVEL")
        m.width = bevel
        m.segments = 3
    o.data.materials.append(mat)
    return o


def cylinder(name, radius, height, loc, mat):
    bpy.ops.mesh.primitive_cylinder_add(vertices=48, radius=radius, depth=height, location=(loc[0], loc[1], height / 2))
    o = bpy.context.active_object
    o.name = name
    bpy.ops.object.shade_smooth()
    o.data.materials.append(mat)
    return o


def rock(name, radius, loc, mat):
    bpy.ops.mesh.primitive_ico_sphere_add(subdivisions=4, radius=radius, location=loc)
    o = bpy.context.active_object
    o.name = name
    o.scale = (1.0, 0.8, 0.6)
    tex = bpy.data.textures.new(f"{name}_noise", "CLOUDS")
    tex.noise_scale = 0.6
    tex.noise_depth = 3
    d = o.modifiers.new("displace", "DISPLACE")
    d.texture = tex
    d.strength = radius * 0.5
    d.texture_coords = "GLOBAL"
    bpy.ops.object.shade_smooth()
    o.data.materials.append(mat)
    return o


def suzanne(name, size, loc, rot_z, mat):
    bpy.ops.mesh.primitive_monkey_add(size=1.0, location=(0, 0, 0), rotation=(0, 0, math.radians(rot_z)))
    o = bpy.context.active_object
    o.name = name
    s = o.modifiers.new("subsurf", "SUBSURF")
    s.levels = s.render_levels = 2
    bpy.ops.object.shade_smooth()
    o.scale = (size, size, size)
    bpy.ops.object.transform_apply(scale=True, rotation=True)
    zs = [v.co.z for v in o.data.vertices]
    o.location = (loc[0], loc[1], -min(zs) + 0.02)
    o.data.materials.append(mat)
    return o


def set_sky(sun_elev: float, sun_azim: float, strength: float) -> None:
    """A physical sky (no sun disc: the sun lamp gives the direct light)."""
    world = bpy.data.worlds.get("World") or bpy.data.worlds.new("World")
    bpy.context.scene.world = world
    nt = world.node_tree
    nt.nodes.clear()
    sky = nt.nodes.new("ShaderNodeTexSky")
    for kind in ("MULTIPLE_SCATTERING", "SINGLE_SCATTERING", "NISHITA", "HOSEK_WILKIE"):
        try:
            sky.sky_type = kind
            break
        except TypeError:
            continue
    if hasattr(sky, "sun_disc"):
        sky.sun_disc = False
    if hasattr(sky, "sun_elevation"):
        sky.sun_elevation = math.radians(sun_elev)
        sky.sun_rotation = math.radians(sun_azim)
    if hasattr(sky, "sun_direction"):
        e, a = math.radians(sun_elev), math.radians(sun_azim)
        sky.sun_direction = (math.cos(e) * math.sin(a), math.cos(e) * math.cos(a), math.sin(e))
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = strength
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(sky.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])


def set_sun(obj, elev: float, azim: float, energy: float, color) -> None:
    e, a = math.radians(elev), math.radians(azim)
    d = Vector((math.cos(e) * math.sin(a), math.cos(e) * math.cos(a), math.sin(e)))
    obj.rotation_euler = (-d).to_track_quat("-Z", "Y").to_euler()
    obj.data.energy = energy
    obj.data.color = color


def add_camera(lens: float, frames: int, pose) -> bpy.types.Object:
    """The scene's camera, keyed on every frame at ``pose(u)`` = (eye, aim), u from 0 to 1."""
    bpy.ops.object.camera_add()
    cam = bpy.context.active_object
    cam.data.lens = lens
    bpy.context.scene.camera = cam
    prev = None
    for t in range(frames):
        eye, aim = pose(t / max(frames - 1, 1))
        cam.location = eye
        quat = (Vector(aim) - Vector(eye)).to_track_quat("-Z", "Y")
        # Compatible with the previous frame's angles, so the keys do not wrap.
        prev = quat.to_euler("XYZ", prev) if prev is not None else quat.to_euler("XYZ")
        cam.rotation_euler = prev
        cam.keyframe_insert("location", frame=t + 1)
        cam.keyframe_insert("rotation_euler", frame=t + 1)
    return cam


def lerp(a, b, u):
    return tuple(x + (y - x) * u for x, y in zip(a, b, strict=True))


def build_courtyard(frames: int) -> dict:
    ground = textured("grass", "grass.png", 0.35, 0.9, bump=0.3)
    bpy.ops.mesh.primitive_plane_add(size=80.0)
    bpy.context.active_object.data.materials.append(ground)
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(0.5, -1.0, 0.003))
    path = bpy.context.active_object
    path.scale = (24.0, 2.2, 1.0)
    path.data.materials.append(textured("pave", "pave.png", 0.6, 0.7, bump=0.4))
    wall = textured("blocks", "blocks.jpg", 0.5, 0.8, bump=0.3)
    box("wall_back", (14.0, 0.6, 2.8), (0.0, 4.2, 1.4), 0, wall)
    box("wall_side", (0.6, 9.0, 2.2), (-6.5, 0.5, 1.1), 0, wall)
    conc = textured("concrete", "concrete.jpg", 0.8, 0.7, tint=(1.6, 1.5, 1.4))
    for i, x in enumerate((-3.5, 3.2, 6.0)):
        cylinder(f"pillar_{i}", 0.28, 3.2, (x, 2.6, 0), conc)
    rk = textured("rock", "rock.png", 1.2, 0.85, bump=0.6)
    for i, (x, y, r) in enumerate(((-2.4, 0.9, 0.45), (2.7, -2.8, 0.35), (4.6, 1.4, 0.6), (-4.8, -2.6, 0.5))):
        rock(f"rock_{i}", r, (x, y, r * 0.25), rk)
    crate = textured("crates", "diamond.jpg", 1.0, 0.5)
    box("crate_0", (0.8, 0.8, 0.8), (-1.2, 2.9, 0.4), 12, crate, bevel=0.03)
    box("crate_1", (0.6, 0.6, 0.6), (-0.7, 3.1, 1.1), -8, crate, bevel=0.03)
    ins_a = suzanne("insert_a", 0.6, (0.2, 0.0), 200, painted("paint_a", (0.75, 0.32, 0.08), 0.32, coat=0.4))
    ins_b = box("insert_b", (0.7, 0.7, 0.7), (1.55, 0.7, 0.35), 28, textured("rust", "rusted.jpg", 1.2, 0.55), 0.04)
    bpy.ops.object.light_add(type="SUN")
    sun = bpy.context.active_object
    sun.name = "sun"
    sun.data.angle = math.radians(1.2)
    light = {"sun_elev": 38.0, "sun_azim": 150.0, "sun_energy": 4.5, "sun_color": (1.0, 0.96, 0.9), "sky": 0.35}
    relit = {"sun_elev": 14.0, "sun_azim": 255.0, "sun_energy": 3.0, "sun_color": (1.0, 0.66, 0.38), "sky": 0.2}
    # Camera: a lateral dolly of 5 m with a rise and a push-in, aimed at the inserts.
    cam = add_camera(
        30, frames, lambda u: (lerp((-2.4, -3.9, 1.2), (2.4, -3.1, 1.8), u), lerp((0.2, 0.4, 0.45), (1.0, 0.6, 0.4), u))
    )
    ctx_poses = [
        ((-3.2, -3.6, 1.5), (0.3, 0.5, 0.5)),
        ((0.5, -4.6, 1.0), (0.6, 0.5, 0.4)),
        ((3.2, -2.8, 2.2), (0.8, 0.5, 0.4)),
    ]
    return {
        "camera": cam,
        "sun": sun,
        "light": light,
        "relit": relit,
        "inserts": [ins_a, ins_b],
        "ctx_poses": ctx_poses,
        "kind": "outdoor",
        "seed": 7,
    }


def build_hall(frames: int) -> dict:
    sc = bpy.context.scene
    W, D, Hh = 11.0, 8.0, 3.6
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(0, 0, 0))
    floor = bpy.context.active_object
    floor.scale = (W, D, 1)
    floor.data.materials.append(textured("tiles", "tiles.jpg", 0.5, 0.35, bump=0.2))
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(0, 0, Hh), rotation=(math.pi, 0, 0))
    ceil = bpy.context.active_object
    ceil.scale = (W, D, 1)
    ceil.data.materials.append(painted("ceiling", (0.55, 0.55, 0.52), 0.9))
    wmat = textured("patch", "patch.jpg", 0.45, 0.7, tint=(1.3, 1.25, 1.2), bump=0.3)
    box("wall_n", (W, 0.2, Hh), (0, D / 2, Hh / 2), 0, wmat)
    box("wall_s", (W, 0.2, Hh), (0, -D / 2, Hh / 2), 0, wmat)
    box("wall_e", (0.2, D, Hh), (W / 2, 0, Hh / 2), 0, wmat)
    box("wall_w", (0.2, D, Hh), (-W / 2, 0, Hh / 2), 0, textured("blocks", "blocks.jpg", 0.5, 0.8))
    metal = textured("bluemetal", "bluemetal.jpg", 0.8, 0.3)
    for i, (x, y) in enumerate(((-2.5, 1.5), (2.5, 1.5), (-2.5, -1.5), (2.5, -1.5))):
        cylinder(f"column_{i}", 0.3, Hh, (x, y, 0), metal)
    crate = textured("crates", "diamond.jpg", 1.0, 0.5)
    for i, (x, y, s, r) in enumerate(((0.4, 2.6, 0.9, 10), (1.3, 2.9, 0.6, -15), (-4.0, -2.5, 0.8, 30))):
        box(f"crate_{i}", (s, s, s), (x, y, s / 2), r, crate, bevel=0.03)
    suzanne("statue", 0.5, (-0.6, 0.4), 160, painted("marble", (0.8, 0.78, 0.74), 0.25))
    box("bench", (2.0, 0.5, 0.45), (3.6, -2.8, 0.225), 0, textured("rust", "rusted.jpg", 0.9, 0.6), 0.02)
    # Light: two warm ceiling panels and a cool lamp; a faint ambient world.
    for i, (x, y) in enumerate(((-2.0, 0.5), (2.6, -0.8))):
        bpy.ops.object.light_add(type="AREA", location=(x, y, Hh - 0.05))
        a = bpy.context.active_object
        a.name = f"panel_{i}"
        a.data.shape = "RECTANGLE"
        a.data.size, a.data.size_y = 1.6, 0.6
        a.data.energy = 260.0
        a.data.color = (1.0, 0.82, 0.62)
    bpy.ops.object.light_add(type="POINT", location=(4.6, 3.2, 1.8))
    p = bpy.context.active_object
    p.data.energy = 120.0
    p.data.color = (0.6, 0.75, 1.0)
    p.data.shadow_soft_size = 0.15
    world = bpy.data.worlds.new("World")
    sc.world = world
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.02, 0.025, 0.03, 1)

    def walk(u: float):
        eye = lerp((-4.3, -3.3, 1.6), (-0.5, -2.2, 1.5), u)
        ang = math.radians(40 + 70 * u)
        return eye, (eye[0] + 3 * math.cos(ang), eye[1] + 3 * math.sin(ang), 1.1)

    # Camera: a 4 m walk with a 70 degree pan.
    cam = add_camera(24, frames, walk)
    ctx_poses = [
        ((-4.0, -3.0, 1.7), (-1.0, 0.5, 1.0)),
        ((-1.5, -3.2, 1.4), (0.5, 1.0, 1.0)),
        ((0.0, -2.0, 1.8), (2.0, 2.5, 1.0)),
    ]
    return {
        "camera": cam,
        "light": {"panels": 2, "lamp": 1},
        "inserts": [],
        "ctx_poses": ctx_poses,
        "kind": "indoor",
        "seed": 11,
        # Also rendered at 4 samples, raw and through Cycles' denoiser.
        "noisy": True,
    }


def build_ruins(frames: int) -> dict:
    ground = textured("mud", "mud.png", 0.4, 0.95, bump=0.4)
    bpy.ops.mesh.primitive_plane_add(size=80.0)
    bpy.context.active_object.data.materials.append(ground)
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(0.0, 0.0, 0.004))
    court = bpy.context.active_object
    court.scale = (7.0, 5.0, 1.0)
    court.data.materials.append(textured("pebbles", "pebbles.png", 0.8, 0.8, bump=0.5))
    stone = textured("blocks", "blocks.jpg", 0.45, 0.8, tint=(1.2, 1.1, 1.0), bump=0.4)
    # A broken back wall: segments of different heights with gaps between them.
    segments = ((-4.6, 1.8, 2.6), (-2.2, 1.4, 1.5), (0.4, 2.2, 3.0), (3.4, 1.2, 1.1), (5.2, 1.4, 2.2))
    for i, (x, w, hgt) in enumerate(segments):
        box(f"wall_{i}", (w, 0.5, hgt), (x, 3.6, hgt / 2), 2 * i - 4, stone, bevel=0.02)
    conc = textured("concrete", "concrete.jpg", 0.9, 0.75, tint=(1.7, 1.6, 1.45), bump=0.2)
    # A colonnade across the middle, some columns broken off.
    for i, (x, hgt) in enumerate(((-3.6, 2.9), (-1.8, 1.3), (0.0, 2.9), (1.8, 2.1), (3.6, 2.9))):
        cylinder(f"column_{i}", 0.24, hgt, (x, 1.2, 0), conc)
    box("lintel", (4.3, 0.5, 0.35), (-1.8, 1.2, 3.07), 0, conc, bevel=0.02)
    rk = textured("rock", "rock.png", 1.1, 0.85, bump=0.6)
    rocks = ((-1.0, -0.6, 0.4), (2.4, -1.4, 0.3), (-3.0, 2.2, 0.55), (4.4, 0.2, 0.45), (0.9, 2.6, 0.35))
    for i, (x, y, r) in enumerate(rocks):
        rock(f"rock_{i}", r, (x, y, r * 0.25), rk)
    crate = textured("crates", "diamond.jpg", 1.0, 0.5)
    box("block_0", (0.9, 0.6, 0.5), (-2.6, -1.6, 0.25), 25, crate, bevel=0.03)
    box("block_1", (0.5, 0.5, 0.9), (1.2, -0.2, 0.45), -12, textured("rust", "rusted.jpg", 1.0, 0.55), 0.03)
    bpy.ops.object.light_add(type="SUN")
    sun = bpy.context.active_object
    sun.name = "sun"
    sun.data.angle = math.radians(0.8)
    light = {"sun_elev": 24.0, "sun_azim": 235.0, "sun_energy": 4.0, "sun_color": (1.0, 0.86, 0.7), "sky": 0.45}

    def orbit(u: float):
        # An arc of 60 degrees round the colonnade, 6-7 m out, descending.
        ang = math.radians(-120 + 60 * u)
        rad = 7.0 - 1.0 * u
        eye = (rad * math.cos(ang), 1.2 + rad * math.sin(ang), 2.2 - 0.8 * u)
        return eye, (0.0, 1.6, 1.0)

    cam = add_camera(28, frames, orbit)
    ctx_poses = [
        ((-4.2, -4.0, 2.0), (-0.5, 1.5, 1.0)),
        ((0.0, -5.4, 1.6), (0.0, 1.6, 1.0)),
        ((3.6, -3.8, 2.4), (0.5, 1.5, 1.0)),
        ((-1.8, -3.0, 1.2), (0.0, 2.0, 1.2)),
    ]
    return {
        "camera": cam,
        "sun": sun,
        "light": light,
        "inserts": [],
        "ctx_poses": ctx_poses,
        "kind": "outdoor",
        "seed": 13,
    }


BUILDERS = {"courtyard": build_courtyard, "hall": build_hall, "ruins": build_ruins}
SCENES = tuple(BUILDERS)


def render(path: Path) -> tuple[dict, dict]:
    sc = bpy.context.scene
    sc.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    if not path.exists():
        raise RuntimeError(f"Blender did not write {path}")
    chans, _ = _channels(path)
    return read_blender_exr(path), chans


def quality(samples: int, denoise: bool, seed: int, adaptive: bool = True) -> None:
    sc = bpy.context.scene
    sc.cycles.samples = samples
    sc.cycles.use_adaptive_sampling = adaptive
    sc.cycles.adaptive_threshold = 0.005
    sc.cycles.use_denoising = denoise
    if denoise:
        sc.cycles.denoiser = "OPENIMAGEDENOISE"
        sc.cycles.denoising_input_passes = "RGB_ALBEDO_NORMAL"
    sc.cycles.seed = seed


def pass_rgb(chans: dict, names: list[str]) -> np.ndarray:
    for n in names:
        keys = [f"ViewLayer.{n}.{c}" for c in "RGB"]
        if all(k in chans for k in keys):
            return np.stack([chans[k] for k in keys], -1).astype(np.float32)
        keys = [f"ViewLayer.{n}.{c}" for c in "XYZ"]
        if all(k in chans for k in keys):
            return np.stack([chans[k] for k in keys], -1).astype(np.float32)
    raise RuntimeError(f"passes {names} missing (have {sorted(k for k in chans if 'Crypto' not in k)})")


def render_scene(name: str, out_root: Path, cfg: dict) -> dict:
    fetch()
    t0 = time.time()
    sc = reset(cfg["width"], cfg["height"], cfg["threads"])
    T = cfg["frames"]
    info = BUILDERS[name](T)
    W, H = cfg["width"], cfg["height"]
    out = out_root / name
    tmp = out_root / f"{name}.tmp"
    tmp.mkdir(parents=True, exist_ok=True)
    cam = info["camera"]
    sky = info["kind"] == "outdoor"

    if sky:
        set_lights(info, info["light"])
    passes: dict[str, list] = {}
    cams = []

    def keep(key: str, arr: np.ndarray) -> None:
        passes.setdefault(key, []).append(arr)

    seed = info["seed"]
    for t in range(T):
        sc.frame_set(t + 1)
        cams.append(camera_matrices(cam, W, H))
        cache = tmp / f"frame_{t:02d}.npz"
        if cache.exists():  # resumable: a finished frame is kept across runs
            with np.load(cache) as z:
                for k in z.files:
                    keep(k, z[k])
            print(f"ood.render: {name} frame {t} (cached)", flush=True)
            continue
        fr: dict[str, np.ndarray] = {}
        quality(cfg["samples"], True, seed)
        # A scene with inserts keeps the albedo the denoiser saw (a host's
        # albedo AOV: what tells an insert's tone from its paint).
        sc.view_layers[0].cycles.denoising_store_passes = bool(info["inserts"])
        truth, chans = render(tmp / "truth.exr")
        sc.view_layers[0].cycles.denoising_store_passes = False
        fr["truth"] = truth["rgba"][..., :3]
        if info["inserts"]:
            fr["albedo"] = pass_rgb(chans, ["Denoising Albedo"])
        fr["depth"] = truth["depth"]
        fr["motion"] = truth["motion"]
        fr["normal"] = truth["normal"]
        for i, o in enumerate(info["inserts"]):
            fr[f"mask_{'ab'[i]}"] = crypto_mask(truth, o.name)
        if info["inserts"]:
            a, b = info["inserts"]
            a.hide_render = b.hide_render = True
            fr["noinsert_ab"] = render(tmp / "noinsert_ab.exr")[0]["rgba"][..., :3]
            a.hide_render = b.hide_render = False
            set_lights(info, info["relit"])
            fr["relit"] = render(tmp / "relit.exr")[0]["rgba"][..., :3]
            set_lights(info, info["light"])
            fr.update(render_alone(info, tmp, cfg["samples"]))
        if info.get("noisy"):
            vl = sc.view_layers[0]
            vl.cycles.denoising_store_passes = True
            quality(4, True, 1000 + t, adaptive=False)
            noisy, chans = render(tmp / "noisy.exr")
            vl.cycles.denoising_store_passes = False
            fr["noisy_denoised"] = noisy["rgba"][..., :3]
            fr["noisy"] = pass_rgb(chans, ["Noisy Image", "Noisy"])
            fr["noisy_albedo"] = pass_rgb(chans, ["Denoising Albedo"])
            fr["noisy_normal"] = pass_rgb(chans, ["Denoising Normal"])
        np.savez(cache, **fr)
        for k, v in fr.items():
            keep(k, v)
        print(f"ood.render: {name} frame {t} {time.time() - t0:.0f} s", flush=True)
    # Static context views (frame 1's light) for the sparse-view reconstruction.
    sc.frame_set(1)
    ctx = bpy.data.objects.new("ctx_camera", cam.data)
    sc.collection.objects.link(ctx)
    sc.camera = ctx
    quality(cfg["samples"], True, seed)
    ctx_rgb, ctx_depth, ctx_cams = [], [], []
    for k, (eye, aim) in enumerate(info["ctx_poses"]):
        ctx.location = eye
        ctx.rotation_euler = (Vector(aim) - Vector(eye)).to_track_quat("-Z", "Y").to_euler()
        bpy.context.view_layer.update()
        ctx_cams.append(camera_matrices(ctx, W, H))
        f, _ = render(tmp / f"ctx_{k}.exr")
        ctx_rgb.append(f["rgba"][..., :3])
        ctx_depth.append(f["depth"])
    sc.camera = cam
    # One linear exposure for every pass of the scene: clean median luminance 0.18.
    gt = np.stack(passes["truth"]).astype(np.float32)
    k_exp = float(np.clip(0.18 / max(float(np.median(degrade.luminance(gt))), 1e-4), 1 / 256, 256))
    arrays: dict[str, np.ndarray] = {}
    for k, v in passes.items():
        a = np.stack(v).astype(np.float32)
        if k in ("truth", "noinsert_ab", "relit", "noisy", "noisy_denoised"):
            a = a * k_exp
        elif k in ALONE_PASSES:
            a[..., :3] *= k_exp
        arrays[k] = a
    arrays["ctx_rgb"] = np.stack(ctx_rgb) * k_exp
    arrays["ctx_depth"] = np.stack(ctx_depth)
    arrays.update(
        world_to_camera=np.stack([c[0] for c in cams]),
        world_to_ndc=np.stack([c[1] for c in cams]),
        ctx_world_to_camera=np.stack([c[0] for c in ctx_cams]),
        ctx_world_to_ndc=np.stack([c[1] for c in ctx_cams]),
    )
    np.savez_compressed(tmp / "scene.npz", **pack(arrays))
    meta = {
        "scene": name,
        "kind": info["kind"],
        "width": W,
        "height": H,
        "frames": T,
        "samples_clean": cfg["samples"],
        "clean": "adaptive (threshold 0.005) + OIDN with albedo and normal, fixed seed",
        "noisy": "4 samples, no adaptive sampling, seed per frame; raw and Cycles OIDN" if info.get("noisy") else None,
        "exposure_scale": k_exp,
        "light": info["light"],
        "relit": info.get("relit"),
        "inserts": [o.name for o in info["inserts"]],
        "albedo": "Cycles' Denoising Albedo of the truth render" if info["inserts"] else None,
        "render_seconds": round(time.time() - t0, 1),
        "checks": scene_checks(
            gt * k_exp,
            arrays["motion"],
            arrays["depth"],
            np.stack([c[0] for c in cams]),
            np.stack([c[1] for c in cams]),
        ),
        "color_space": "Linear Rec.709 (scene-linear)",
        "motion": "pixels, current -> previous, x right, y down",
        "depth": "planar, empty = 1e10",
    }
    (tmp / "meta.json").write_text(json.dumps(meta, indent=1))
    out.mkdir(parents=True, exist_ok=True)
    for f in ("scene.npz", "meta.json"):
        (tmp / f).replace(out / f)
    shutil.rmtree(tmp, ignore_errors=True)
    return meta


def add_arrays(out: Path, tmp: Path, arrays: dict[str, np.ndarray]) -> Path:
    """Writes ``arrays`` (packed) into the scene file ``out`` beside its
    arrays, which are copied as they are (bit for bit), through ``tmp``
    (removed after)."""
    with np.load(out) as z:
        raw = {k: z[k] for k in z.files}
    raw.update(pack(arrays))
    np.savez_compressed(tmp / "scene.npz", **raw)
    (tmp / "scene.npz").replace(out)
    shutil.rmtree(tmp, ignore_errors=True)
    return out


def reopen(name: str, out_root: Path, cfg: dict, what: str) -> tuple[Path, bpy.types.Scene, dict, Path]:
    """An insert scene rendered before, set up again to add pass ``what``:
    its ``scene.npz``, the Blender scene built as for the render (assets
    fetched), the builder's info and a work directory ``<name>.<what>.tmp``."""
    out = out_root / name / "scene.npz"
    if not out.exists():
        raise SystemExit(f"ood.render: {out} missing: render the scene first")
    fetch()
    sc = reset(cfg["width"], cfg["height"], cfg["threads"])
    info = BUILDERS[name](cfg["frames"])
    if not info["inserts"]:
        raise SystemExit(f"ood.render: {name} has no inserts; only insert scenes keep the {what} pass")
    tmp = out_root / f"{name}.{what}.tmp"
    tmp.mkdir(parents=True, exist_ok=True)
    return out, sc, info, tmp


def add_albedo(name: str, out_root: Path, cfg: dict) -> Path:
    """Adds the albedo pass to a scene rendered before it kept one.

    Renders only what the albedo needs (the same scene, cameras and seed,
    ``cfg["samples"]`` samples, no adaptive sampling) and writes it into the
    existing ``scene.npz`` beside the packed arrays, which are copied as they
    are (bit for bit).
    """
    out, sc, info, tmp = reopen(name, out_root, cfg, "albedo")
    # No light to set: the albedo does not depend on it.
    sc.view_layers[0].cycles.denoising_store_passes = True
    albedo = []
    for t in range(cfg["frames"]):
        sc.frame_set(t + 1)
        quality(cfg["samples"], True, info["seed"], adaptive=False)
        _, chans = render(tmp / "albedo.exr")
        albedo.append(pass_rgb(chans, ["Denoising Albedo"]))
        print(f"ood.render: {name} albedo frame {t}", flush=True)
    return add_arrays(out, tmp, {"albedo": np.stack(albedo).astype(np.float32)})


#: The passes of the first insert rendered alone (RGBA, premultiplied).
ALONE_PASSES = ("alone_a", "relit_alone_a")


def set_lights(info: dict, p: dict) -> None:
    """The sky and sun of light settings ``p`` (``info["light"]`` or ``info["relit"]``)."""
    set_sky(p["sun_elev"], p["sun_azim"], p["sky"])
    set_sun(info["sun"], p["sun_elev"], p["sun_azim"], p["sun_energy"], p["sun_color"])


def render_alone(info: dict, tmp: Path, samples: int) -> dict[str, np.ndarray]:
    """The first insert rendered on its own, under the scene's light and under
    its ``relit`` light: every other mesh a holdout (still shadowing and
    lighting it, invisible) on a transparent film, the truth's samples and
    seed. RGBA at the render's exposure; the scene is left as it was."""
    sc = bpy.context.scene
    alone = info["inserts"][0]
    others = [o for o in sc.objects if o.type == "MESH" and o is not alone]
    for o in others:
        o.is_holdout = True
    sc.render.film_transparent = True
    out = {}
    try:
        for key, p in zip(ALONE_PASSES, (info["light"], info["relit"]), strict=True):
            set_lights(info, p)
            quality(samples, True, info["seed"])
            out[key] = render(tmp / f"{key}.exr")[0]["rgba"].astype(np.float32)
    finally:
        for o in others:
            o.is_holdout = False
        sc.render.film_transparent = False
        set_lights(info, info["light"])
    return out


def add_alone(name: str, out_root: Path, cfg: dict) -> Path:
    """Adds the first insert rendered alone to a scene rendered before it.

    An object rendered on its own (every other object a holdout: still
    shadowing and lighting it, invisible; transparent film) is what a host
    composites over its frame: its premultiplied color, whose soft edge
    holds none of the background. Two passes a frame, RGBA, at the scene's
    exposure: ``alone_a`` under the scene's light, ``relit_alone_a`` under
    its ``relit`` light (the same samples and seed as the truth). The
    other arrays are copied as they are (bit for bit).
    """
    out, sc, info, tmp = reopen(name, out_root, cfg, "alone")
    set_lights(info, info["light"])
    k_exp = float(json.loads((out_root / name / "meta.json").read_text())["exposure_scale"])
    passes: dict[str, list] = {k: [] for k in ALONE_PASSES}
    for t in range(cfg["frames"]):
        sc.frame_set(t + 1)
        cache = tmp / f"frame_{t:02d}.npz"
        if cache.exists():  # resumable
            with np.load(cache) as z:
                for k in passes:
                    passes[k].append(z[k])
            continue
        fr = render_alone(info, tmp, cfg["samples"])
        for v in fr.values():
            v[..., :3] *= k_exp
        np.savez(cache, **fr)
        for k, v in fr.items():
            passes[k].append(v)
        print(f"ood.render: {name} alone frame {t}", flush=True)
    return add_arrays(out, tmp, {k: np.stack(v) for k, v in passes.items()})


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", choices=SCENES, required=True)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "data")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=180)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--samples", type=int, default=128)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--add-albedo",
        action="store_true",
        help="add the albedo pass to an existing render of an insert scene (its other passes unchanged)",
    )
    ap.add_argument(
        "--add-alone",
        action="store_true",
        help="add the first insert rendered alone (under the scene's and the relit light) to an existing render",
    )
    args = ap.parse_args(argv)
    cfg = vars(args)
    if args.add_alone:
        print(f"ood.render: wrote {add_alone(args.scene, args.out, cfg)}")
        return 0
    if args.add_albedo:
        print(f"ood.render: wrote {add_albedo(args.scene, args.out, cfg)}")
        return 0
    meta = render_scene(args.scene, args.out, cfg)
    print(json.dumps({"scene": args.scene, "seconds": meta["render_seconds"], "checks": meta["checks"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
