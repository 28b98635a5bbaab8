"""Renders one training scene with Blender (bpy 5.0, Cycles on CPU) and writes its samples.

Run with the bpy interpreter, one process per scene (``generate.py`` does this):

    .venv-bpy/bin/python -m training.synth.render_scene --scene-id 12 --out training/data/train/scene_000012

A scene is a room (procedural floor and walls), Sweet Home 3D furniture, one
*insert* object near the centre, Blender's HDRI lighting plus an optional sun,
and a camera moving over ``frames`` frames. The passes rendered per frame:
``truth`` (clean, OIDN-denoised, with depth, vector, normal and Cryptomatte),
``noinsert`` (the insert hidden: its shadow is gone), ``relit`` (other light)
and ``noisy`` (few samples, a new seed per frame); plus 2-3 static context
views for the reconstruction stream. ``degrade.py`` turns them into the six
streams; the file layout is documented in ``training/README.md``. With
``--streams recon`` only ``truth`` and the context views are rendered and only
the reconstruction stream is written (a third of the renders per frame;
``mask_shadow`` is then all zeros, as no ``noinsert`` pass measures it).
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
    from mathutils import Matrix, Vector
except ImportError:  # pragma: no cover - run with the bpy venv
    print("render_scene: this script needs the 'bpy' module (.venv-bpy)", file=sys.stderr)
    raise

from training.synth import degrade
from training.synth.dataset import load_sample, redegrade, to_f16
from training.synth.exr import read_blender_exr

FORMAT_VERSION = 1


# ---------------------------------------------------------------------------
# Scene construction


def reset_blender(cfg: dict) -> bpy.types.Scene:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    sc.render.resolution_x = cfg["width"]
    sc.render.resolution_y = cfg["height"]
    sc.render.resolution_percentage = 100
    sc.render.use_motion_blur = False  # the Vector pass is only valid without it
    sc.render.threads_mode = "FIXED"
    sc.render.threads = cfg["threads"]
    sc.render.film_transparent = False
    sc.cycles.max_bounces = 4
    sc.cycles.diffuse_bounces = 3
    sc.cycles.glossy_bounces = 3
    sc.cycles.transmission_bounces = 4
    sc.cycles.use_animated_seed = False
    sc.cycles.use_adaptive_sampling = True
    sc.view_settings.view_transform = "Standard"
    sc.view_settings.look = "None"
    vl = sc.view_layers[0]
    vl.use_pass_z = True
    vl.use_pass_vector = True
    vl.use_pass_normal = True
    vl.use_pass_cryptomatte_object = True
    vl.pass_cryptomatte_depth = 4
    ims = sc.render.image_settings
    ims.media_type = "MULTI_LAYER_IMAGE"
    ims.file_format = "OPEN_EXR_MULTILAYER"
    ims.color_depth = "32"
    ims.exr_codec = "ZIP"
    return sc


def procedural_material(
    rng: np.random.Generator, name: str, textures: list | None = None, size: tuple = (1.0, 1.0)
) -> bpy.types.Material:
    """A random floor/wall material: plaster, tiles, bricks, wood-like or
    plain; with ``textures`` (the catalog's photo textures), half the time
    one of them, repeated every 0.5-2.5 m over the plane of ``size`` metres
    (the unit plane's object coordinates, scaled), at a random brightness
    and saturation. The choice is kept in the material's ``surface``
    property. Without textures the random draws are those of a catalog
    without them (scenes stay reproducible)."""
    mat = bpy.data.materials.new(name)
    nt = mat.node_tree
    bsdf = nt.nodes.get("Principled BSDF")
    tc = nt.nodes.new("ShaderNodeTexCoord")
    mapping = nt.nodes.new("ShaderNodeMapping")
    s = float(rng.uniform(0.5, 3.0))
    mapping.inputs["Scale"].default_value = (s, s, s)
    nt.links.new(tc.outputs["Object"], mapping.inputs["Vector"])
    if textures and rng.random() < 0.5:
        entry = textures[int(rng.integers(len(textures)))]
        tile = float(rng.uniform(0.5, 2.5))
        mapping.inputs["Scale"].default_value = (size[0] / tile, size[1] / tile, 1.0)
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image = bpy.data.images.load(entry["path"], check_existing=True)
        tex.image.colorspace_settings.name = "sRGB"
        nt.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
        shade = nt.nodes.new("ShaderNodeHueSaturation")
        shade.inputs["Hue"].default_value = float(0.5 + rng.normal(0, 0.03))
        shade.inputs["Saturation"].default_value = float(rng.uniform(0.6, 1.2))
        shade.inputs["Value"].default_value = float(rng.uniform(0.6, 1.4))
        nt.links.new(tex.outputs["Color"], shade.inputs["Color"])
        nt.links.new(shade.outputs["Color"], bsdf.inputs["Base Color"])
        bsdf.inputs["Roughness"].default_value = float(rng.uniform(0.35, 0.95))
        mat["surface"] = entry["name"]
        return mat

    def col() -> tuple:
        hsv_h, hsv_s, hsv_v = rng.uniform(0, 1), rng.uniform(0.0, 0.6) ** 1.5, rng.uniform(0.05, 0.8)
        import colorsys

        r, g, b = colorsys.hsv_to_rgb(hsv_h, hsv_s, hsv_v)
        return (r, g, b, 1.0)

    kind = rng.choice(["plaster", "checker", "brick", "wood", "plain"])
    if kind == "checker":
        tex = nt.nodes.new("ShaderNodeTexChecker")
        tex.inputs["Color1"].default_value = col()
        tex.inputs["Color2"].default_value = col()
        tex.inputs["Scale"].default_value = float(rng.uniform(2, 12))
        out = tex.outputs["Color"]
    elif kind == "brick":
        tex = nt.nodes.new("ShaderNodeTexBrick")
        tex.inputs["Color1"].default_value = col()
        tex.inputs["Color2"].default_value = col()
        tex.inputs["Mortar"].default_value = col()
        tex.inputs["Scale"].default_value = float(rng.uniform(2, 8))
        out = tex.outputs["Color"]
    elif kind == "wood":
        tex = nt.nodes.new("ShaderNodeTexWave")
        tex.inputs["Scale"].default_value = float(rng.uniform(1, 6))
        tex.inputs["Distortion"].default_value = float(rng.uniform(2, 12))
        ramp = nt.nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = col()
        ramp.color_ramp.elements[1].color = col()
        nt.links.new(tex.outputs["Fac"], ramp.inputs["Fac"])
        out = ramp.outputs["Color"]
    else:
        tex = nt.nodes.new("ShaderNodeTexNoise")
        tex.inputs["Scale"].default_value = float(rng.uniform(2, 40)) if kind == "plaster" else 1.0
        ramp = nt.nodes.new("ShaderNodeValToRGB")
        c0 = col()
        ramp.color_ramp.elements[0].color = c0
        ramp.color_ramp.elements[1].color = c0 if kind == "plain" else col()
        nt.links.new(tex.outputs["Fac"], ramp.inputs["Fac"])
        out = ramp.outputs["Color"]
    if "Vector" in tex.inputs:
        nt.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    nt.links.new(out, bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = float(rng.uniform(0.25, 0.95))
    mat["surface"] = f"procedural:{kind}"
    return mat


def add_plane(name: str, size: tuple, loc: tuple, rot: tuple, mat) -> bpy.types.Object:
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=loc, rotation=rot)
    o = bpy.context.active_object
    o.name = name
    o.scale = (size[0], size[1], 1.0)
    o.data.materials.append(mat)
    return o


def import_model(entry: dict, assets_dir: Path, name: str) -> bpy.types.Object:
    """Imports a Sweet Home 3D OBJ as one mesh, sized in metres, base at z=0, centred."""
    path = assets_dir / entry["obj"]
    before = set(bpy.data.objects)
    bpy.ops.wm.obj_import(filepath=str(path), forward_axis="NEGATIVE_Z", up_axis="Y")
    new = [o for o in bpy.data.objects if o not in before and o.type == "MESH"]
    if not new:
        raise RuntimeError(f"OBJ import of {path} (model {entry['id']}) produced no mesh")
    for o in bpy.data.objects:
        o.select_set(o in new)
    bpy.context.view_layer.objects.active = new[0]
    if len(new) > 1:
        bpy.ops.object.join()
    obj = bpy.context.view_layer.objects.active
    bpy.ops.object.transform_apply(location=True, rotation=True, scale=True)
    obj.name = name
    me = obj.data
    if entry.get("model_rotation"):
        # modelRotation is a 3x3 matrix in the OBJ's y-up frame; the importer maps
        # (x, y, z)_obj to (x, -z, y)_blender.
        r = np.array(entry["model_rotation"], np.float64).reshape(3, 3)
        c = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], np.float64)
        rb = c @ r @ c.T
        me.transform(Matrix([list(rb[0]) + [0], list(rb[1]) + [0], list(rb[2]) + [0], [0, 0, 0, 1]]))
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    lo, hi = co.min(0), co.max(0)
    ext = np.maximum(hi - lo, 1e-4)
    size = np.array(entry["size_m"], np.float64)  # width (x), depth (y), height (z)
    scale = size / ext
    centre = (lo + hi) / 2
    m = Matrix.Diagonal((scale[0], scale[1], scale[2], 1.0)) @ Matrix.Translation((-centre[0], -centre[1], -lo[2]))
    me.transform(m)
    me.update()
    return obj


def pick_models(rng: np.random.Generator, models: list[dict], n_bg: int) -> tuple[dict, list[dict]]:
    def ok(m, lo, hi):
        s = m["size_m"]
        return (
            not m["door_or_window"]
            and not m["staircase"]
            and m["elevation_m"] < 0.05
            and lo <= max(s) <= hi
            and s[2] >= 0.15
        )

    inserts = [m for m in models if m["movable"] and ok(m, 0.3, 2.0) and m["category"] not in ("Lights",)]
    bg = [m for m in models if ok(m, 0.3, 3.0)]
    insert = inserts[int(rng.integers(len(inserts)))]
    chosen = [bg[int(i)] for i in rng.choice(len(bg), size=min(n_bg, len(bg)), replace=False)]
    return insert, chosen


def setup_world(rng: np.random.Generator, hdri_dir: Path, params: dict | None = None) -> dict:
    """HDRI environment (random file, rotation, strength) and maybe a sun."""
    sc = bpy.context.scene
    hdris = sorted(p for p in hdri_dir.glob("*.exr"))
    if not hdris:
        raise RuntimeError(f"no HDRI (*.exr) in {hdri_dir}")
    if params is None:
        params = {
            "hdri": hdris[int(rng.integers(len(hdris)))].name,
            "rotation": float(rng.uniform(0, 2 * math.pi)),
            "strength": float(np.exp(rng.uniform(math.log(0.4), math.log(2.0)))),
            "sun": bool(rng.random() < 0.65),
            "sun_strength": float(rng.uniform(1.0, 5.0)),
            "sun_elevation": float(rng.uniform(math.radians(25), math.radians(70))),
            "sun_azimuth": float(rng.uniform(0, 2 * math.pi)),
            "sun_angle": float(rng.uniform(math.radians(0.5), math.radians(12))),
            "sun_temperature": float(rng.uniform(3500, 7000)),
        }
    world = sc.world or bpy.data.worlds.new("world")
    sc.world = world
    nt = world.node_tree
    nt.nodes.clear()
    tc = nt.nodes.new("ShaderNodeTexCoord")
    mp = nt.nodes.new("ShaderNodeMapping")
    mp.inputs["Rotation"].default_value = (0.0, 0.0, params["rotation"])
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(str(hdri_dir / params["hdri"]), check_existing=True)
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = params["strength"]
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(tc.outputs["Generated"], mp.inputs["Vector"])
    nt.links.new(mp.outputs["Vector"], env.inputs["Vector"])
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    sun = bpy.data.objects.get("sun")
    if sun is None:
        sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
        sc.collection.objects.link(sun)
    sun.hide_render = not params["sun"]
    sun.data.energy = params["sun_strength"]
    sun.data.angle = params["sun_angle"]
    sun.data.color = blackbody_rgb(params["sun_temperature"])
    sun.rotation_euler = (math.pi / 2 - params["sun_elevation"], 0.0, params["sun_azimuth"])
    return params


def blackbody_rgb(kelvin: float) -> tuple:
    """Approximate linear Rec.709 color of a black body, normalized to max 1."""
    t = kelvin / 100.0
    r = 1.0 if t <= 66 else min(1.0, 1.292936 * (t - 60) ** -0.1332047)
    g = (0.3900816 * math.log(t) - 0.6318414) if t <= 66 else 1.1298909 * (t - 60) ** -0.0755148
    b = 1.0 if t >= 66 else (0.0 if t <= 19 else 0.5432068 * math.log(t - 10) - 1.1962541)
    c = [max(min(x, 1.0), 0.0) ** 2.2 for x in (r, g, b)]
    m = max(c)
    return tuple(x / m for x in c)


def build_scene(rng: np.random.Generator, catalog: dict, cfg: dict) -> dict:
    sc = reset_blender(cfg)
    assets_dir = Path(catalog["assets_dir"])
    room = float(rng.uniform(6.0, 10.0))
    textures = catalog.get("textures") or []
    floor_mat = procedural_material(rng, "floor", textures, (room * 2, room * 2))
    floor = add_plane("floor", (room * 2, room * 2), (0, 0, 0), (0, 0, 0), floor_mat)
    surfaces = {"floor": floor_mat["surface"]}
    walls = []
    if rng.random() < 0.85:
        # The height is drawn after the material (the order of the draws of
        # scenes rendered before the textures).
        wall_mat = procedural_material(rng, "wall", textures, (room * 2, 3.0))
        surfaces["walls"] = wall_mat["surface"]
        h = float(rng.uniform(2.4, 3.5))
        walls.append(add_plane("wall_back", (room * 2, h), (0, room / 2, h / 2), (math.pi / 2, 0, 0), wall_mat))
        if rng.random() < 0.7:
            walls.append(
                add_plane("wall_left", (room * 2, h), (-room / 2, 0, h / 2), (math.pi / 2, 0, math.pi / 2), wall_mat)
            )
    insert_entry, bg_entries = pick_models(rng, catalog["models"], int(rng.integers(3, 8)))
    insert = import_model(insert_entry, assets_dir, "insert")
    ix, iy = rng.uniform(-0.6, 0.6, 2)
    insert.location = (float(ix), float(iy), 0.0)
    insert.rotation_euler = (0, 0, float(rng.uniform(0, 2 * math.pi)))
    isz = insert_entry["size_m"]
    placed = [(ix, iy, 0.5 * math.hypot(isz[0], isz[1]))]
    bg_objs = []
    for k, e in enumerate(bg_entries):
        rad = 0.5 * math.hypot(e["size_m"][0], e["size_m"][1])
        for _ in range(30):
            px, py = rng.uniform(-room / 2 + rad, room / 2 - rad, 2)
            # Keep the space in front of the insert (toward the camera, +x/-y) mostly free.
            if px > 0.8 and py < -0.8 and rng.random() < 0.8:
                continue
            if all(math.hypot(px - qx, py - qy) > rad + qr + 0.05 for qx, qy, qr in placed):
                o = import_model(e, assets_dir, f"bg{k}")
                o.location = (float(px), float(py), 0.0)
                o.rotation_euler = (0, 0, float(rng.uniform(0, 2 * math.pi)))
                placed.append((px, py, rad))
                bg_objs.append((o, e))
                break
    light = setup_world(rng, Path(catalog["hdri_dir"]))

    # Camera: orbit toward the back-left corner (walls behind the insert).
    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    sc.collection.objects.link(cam)
    sc.camera = cam
    cam.data.lens = float(rng.uniform(22, 45))
    cam.data.sensor_fit = "HORIZONTAL"
    cam.data.sensor_width = 36.0
    cam.data.clip_start = 0.05
    cam.data.clip_end = 500.0
    size = max(isz)
    target = Vector((float(ix), float(iy), float(isz[2] * rng.uniform(0.3, 0.7))))
    r0 = float(rng.uniform(max(0.9, 1.5 * size + 0.4), max(2.0, 2.6 * size + 1.2)))
    h0 = float(rng.uniform(0.5, 2.0))
    th0 = float(rng.uniform(math.radians(-80), math.radians(-10)))
    dth = float(rng.choice([-1, 1]) * rng.uniform(math.radians(0.4), math.radians(3.0)))
    dr = float(rng.uniform(-0.08, 0.08))
    dh = float(rng.uniform(-0.04, 0.04))
    jitter = float(rng.uniform(0.0, 0.01))
    traj = []
    for t in range(cfg["frames"]):
        th = th0 + dth * t
        r = r0 + dr * t
        hh = h0 + dh * t
        eye = Vector((target.x + r * math.cos(th), target.y + r * math.sin(th), hh)) + Vector(
            tuple(rng.normal(0, jitter, 3))
        )
        aim = target + Vector(tuple(rng.normal(0, jitter * 2, 3)))
        traj.append((eye, aim))
    for t, (eye, aim) in enumerate(traj):
        cam.location = eye
        cam.rotation_euler = (aim - eye).to_track_quat("-Z", "Y").to_euler()
        cam.keyframe_insert("location", frame=t + 1)
        cam.keyframe_insert("rotation_euler", frame=t + 1)
    for fc in _fcurves(cam):
        for kp in fc.keyframe_points:
            kp.interpolation = "LINEAR"
    # Context views for the reconstruction stream: sparse, off the trajectory.
    ctx = bpy.data.objects.new("ctx_camera", cam.data)
    sc.collection.objects.link(ctx)
    n_ctx = int(rng.integers(2, 4))
    span = dth * (cfg["frames"] - 1)
    ctx_poses = []
    for _ in range(n_ctx):
        th = th0 + span * rng.uniform(-0.6, 1.6) + rng.normal(0, math.radians(12))
        r = r0 * rng.uniform(0.85, 1.3)
        hh = h0 + rng.uniform(-0.3, 0.4)
        eye = Vector((target.x + r * math.cos(th), target.y + r * math.sin(th), max(0.25, hh)))
        aim = target + Vector(tuple(rng.normal(0, 0.15, 3)))
        ctx_poses.append((eye, aim))
    # Keep every view of the insert free: drop background models that stand on
    # the line between a camera (trajectory or context) and the target.
    kept = []
    for o, e in bg_objs:
        rad = 0.5 * math.hypot(e["size_m"][0], e["size_m"][1])
        c = np.array([o.location.x, o.location.y])
        blocked = False
        for eye, _ in traj + ctx_poses:
            a = np.array([eye.x, eye.y])
            b = np.array([target.x, target.y])
            ab = b - a
            u = float(np.clip(np.dot(c - a, ab) / max(float(np.dot(ab, ab)), 1e-9), 0.0, 1.0))
            if np.linalg.norm(a + u * ab - c) < rad + 0.15:
                blocked = True
                break
        if blocked:
            bpy.data.objects.remove(o, do_unlink=True)
        else:
            kept.append((o, e))
    bg_objs = kept
    return {
        "camera": cam,
        "ctx_camera": ctx,
        "ctx_poses": ctx_poses,
        "insert": insert,
        "insert_entry": insert_entry,
        "background": [e for _, e in bg_objs],
        "light": light,
        "room": room,
        "walls": len(walls),
        "floor": floor,
        "surfaces": surfaces,
    }


def _fcurves(obj):
    """The camera's F-curves (Blender 5 keeps them in layered actions)."""
    ad = obj.animation_data
    if ad is None or ad.action is None:
        return []
    act = ad.action
    if hasattr(act, "fcurves") and len(getattr(act, "fcurves", [])):
        return list(act.fcurves)
    out = []
    for layer in getattr(act, "layers", []):
        for strip in layer.strips:
            for bag in strip.channelbags:
                out.extend(bag.fcurves)
    return out


# ---------------------------------------------------------------------------
# Rendering


def camera_matrices(cam_obj, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """OpenEXR row-vector ``worldToCamera`` and ``worldToNDC`` of a Blender camera."""
    dg = bpy.context.evaluated_depsgraph_get()
    cam_eval = cam_obj.evaluated_get(dg)
    view_gl = np.array(cam_eval.matrix_world.inverted(), np.float64)
    proj_gl = np.array(cam_eval.calc_matrix_camera(dg, x=width, y=height, scale_x=1.0, scale_y=1.0), np.float64)
    flip = np.diag([1.0, 1.0, -1.0, 1.0])
    to_ndc = np.array([[0.5, 0, 0, 0.5], [0, -0.5, 0, 0.5], [0, 0, 1, 0], [0, 0, 0, 1]], np.float64)
    w2c = flip @ view_gl
    w2ndc = to_ndc @ proj_gl @ view_gl
    return np.ascontiguousarray(w2c.T, np.float32), np.ascontiguousarray(w2ndc.T, np.float32)


def render_to(path: Path) -> dict:
    sc = bpy.context.scene
    sc.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    if not path.exists():
        raise RuntimeError(f"Blender did not write {path}")
    return read_blender_exr(path)


def crypto_mask(exr: dict, name: str) -> np.ndarray:
    """Anti-aliased coverage of object ``name`` from the Cryptomatte passes."""
    manifest = exr["crypto_manifest"]
    if name not in manifest:
        raise RuntimeError(f"object '{name}' is not in the Cryptomatte manifest {sorted(manifest)}")
    target = np.array([int(manifest[name], 16)], np.uint32).view(np.float32)[0]
    m = np.zeros(exr["crypto"][0][0].shape, np.float32)
    for ids, cov in exr["crypto"]:
        m += np.where(ids == target, cov, 0.0)
    return np.clip(m, 0.0, 1.0)


def render_scene(scene_id: int, out_dir: Path, cfg: dict, catalog: dict) -> dict:
    rng = np.random.default_rng([cfg["seed"], scene_id])
    t_start = time.time()
    info = build_scene(rng, catalog, cfg)
    sc = bpy.context.scene
    W, H, T = cfg["width"], cfg["height"], cfg["frames"]
    tmp = out_dir.with_name(out_dir.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    cam, insert = info["camera"], info["insert"]
    sun = bpy.data.objects["sun"]

    def set_quality(samples: int, denoise: bool, seed: int) -> None:
        sc.cycles.samples = samples
        sc.cycles.use_denoising = denoise
        if denoise:
            sc.cycles.denoiser = "OPENIMAGEDENOISE"
        sc.cycles.seed = seed

    base_light = info["light"]
    truth, noinsert, relit, noisy, cams = [], [], [], [], []
    # Noise: raw low-sample renders, or low-sample renders through the denoiser
    # (blotchy, flickering), each frame with its own seed.
    noisy_denoised = bool(rng.random() < 0.4)
    noisy_samples = int(rng.choice([2, 4, 8])) if noisy_denoised else int(rng.choice([1, 2, 4, 8, 16]))
    relight_rng = np.random.default_rng([cfg["seed"], scene_id, 3])
    relight = dict(setup_world(relight_rng, Path(catalog["hdri_dir"])))
    setup_world(rng, Path(catalog["hdri_dir"]), base_light)
    sc.camera = cam
    recon_only = cfg.get("streams", "all") == "recon"
    # Between the renders of a reconstruction-only scene only the camera
    # moves: Cycles keeps the scene's data from one to the next (scene 150,
    # 8 frames: 36.3 -> 26.5 s, outputs bit for bit the same). Not with
    # every stream, whose renders change the world and the insert's
    # visibility: there it saved 13 % and changed the pixels.
    sc.render.use_persistent_data = recon_only
    for t in range(T):
        sc.frame_set(t + 1)
        cams.append(camera_matrices(cam, W, H))
        set_quality(cfg["samples"], True, scene_id)
        # With the insert streams, the truth keeps the albedo the denoiser
        # saw: what a host gives as its albedo AOV with a composite.
        sc.view_layers[0].cycles.denoising_store_passes = not recon_only
        truth.append(render_to(tmp / f"truth_{t:02d}.exr"))
        sc.view_layers[0].cycles.denoising_store_passes = False
        if recon_only:
            continue
        insert.hide_render = True
        noinsert.append(render_to(tmp / f"noinsert_{t:02d}.exr"))
        insert.hide_render = False
        set_quality(noisy_samples, noisy_denoised, scene_id * 1000 + t + 1)
        noisy.append(render_to(tmp / f"noisy_{t:02d}.exr"))
        setup_world(rng, Path(catalog["hdri_dir"]), relight)
        set_quality(cfg["samples"], True, scene_id)
        relit.append(render_to(tmp / f"relit_{t:02d}.exr"))
        setup_world(rng, Path(catalog["hdri_dir"]), base_light)
    set_quality(cfg["samples"], True, scene_id)
    ctx_imgs, ctx_cams = render_context_views(info, W, H, tmp)
    sc.camera = cam
    del sun

    # Exposure normalization of the whole scene (linear, so every pass alike).
    gt = np.stack([f["rgba"][..., :3] for f in truth])
    med = float(np.median(degrade.luminance(gt)))
    k_exp = float(np.clip(0.18 / max(med, 1e-4), 1 / 64, 64)) * float(np.exp(rng.normal(0, 0.35)))

    def rgb(frames):
        return np.stack([f["rgba"][..., :3] for f in frames]).astype(np.float32) * k_exp

    gt = rgb(truth)
    mask = np.stack([crypto_mask(f, "insert") for f in truth])
    if recon_only:
        ni, shadow = None, np.zeros_like(mask)
    else:
        ni = rgb(noinsert)
        shadow = degrade.shadow_mask(gt, ni, mask)
    depth = np.stack([f["depth"] for f in truth]).astype(np.float32)
    motion = np.stack([f["motion"] for f in truth]).astype(np.float32)
    normal = np.stack([f["normal"] for f in truth]).astype(np.float32)
    w2c = np.stack([c[0] for c in cams])
    w2ndc = np.stack([c[1] for c in cams])
    split = "test" if is_test_scene(scene_id, cfg) else "train"
    meta = {
        "format_version": FORMAT_VERSION,
        "scene_id": scene_id,
        "split": split,
        "seed": cfg["seed"],
        "width": W,
        "height": H,
        "frames": T,
        "samples": cfg["samples"],
        "exposure_scale": k_exp,
        "insert": {k: info["insert_entry"][k] for k in ("id", "name", "library", "creator")},
        "background": [{k: e[k] for k in ("id", "library")} for e in info["background"]],
        "light": base_light,
        "relight": relight,
        "room_m": info["room"],
        "walls": info["walls"],
        "surfaces": info["surfaces"],
        "color_space": "Linear Rec.709 (scene-linear), premultiplied by coverage",
        "motion": "pixels, current -> previous, x right, y down",
        "depth": "planar, empty = 1e10",
        "normal": "world space (Blender +z up), from the clean render",
        "rendered_streams": "recon" if recon_only else "all",
    }
    extra = {}
    if not recon_only:
        extra["albedo"] = np.stack([f["albedo"] for f in truth]).astype(np.float16)
    np.savez_compressed(
        tmp / "scene.npz",
        **extra,
        target=to_f16(gt),
        depth=depth,
        motion=to_f16(motion),
        normal=normal.astype(np.float16),
        mask_insert=mask.astype(np.float16),
        mask_shadow=shadow.astype(np.float16),
        world_to_camera=w2c,
        world_to_ndc=w2ndc,
    )
    # The context views, so the reconstruction stream can be degraded again
    # with other seeds (``degrade.reconstruction_inputs``) without rendering.
    write_context(tmp / "ctx.npz", ctx_imgs, ctx_cams, k_exp)
    streams = {}
    # 1: reconstruction artifacts.
    rec, rec_depth, p1 = degrade.reconstruction_inputs(
        np.random.default_rng([cfg["seed"], scene_id, 1]),
        [f["rgba"][..., :3] * k_exp for f in ctx_imgs],
        [f["depth"] for f in ctx_imgs],
        ctx_cams,
        cams,
        W,
        H,
    )
    streams["s1_recon"] = ({"input": rec, "depth": rec_depth, "mask_insert": np.zeros_like(mask)}, p1)
    if not recon_only:
        noise = {"samples": noisy_samples, "denoised": noisy_denoised, "seed": "per frame"}
        streams.update(_composite_streams(cfg, scene_id, gt, mask, ni, rgb(relit), (rgb(noisy), noise), relight))
    meta["streams"] = {}
    for name, (arrays, params) in streams.items():
        arrays = dict(arrays)
        arrays["input"] = to_f16(arrays["input"])
        if "mask_insert" in arrays:
            arrays["mask_insert"] = arrays["mask_insert"].astype(np.float16)
        np.savez_compressed(tmp / f"{name}.npz", **arrays)
        meta["streams"][name] = params
    meta["render_seconds"] = round(time.time() - t_start, 1)
    meta["checks"] = scene_checks(gt, motion, depth, w2c, w2ndc)
    for f in tmp.glob("*.exr"):
        if not cfg.get("keep_exr"):
            f.unlink()
    (tmp / "meta.json").write_text(json.dumps(meta, indent=1, default=_json_default))
    shutil.rmtree(out_dir, ignore_errors=True)
    tmp.rename(out_dir)
    return meta


def clean_quality(sc, samples: int, seed: int) -> None:
    """The clean renders' settings: ``samples`` through OIDN, a fixed seed."""
    sc.cycles.samples = samples
    sc.cycles.use_denoising = True
    sc.cycles.denoiser = "OPENIMAGEDENOISE"
    sc.cycles.seed = seed


def render_context_views(info: dict, width: int, height: int, tmp: Path) -> tuple[list, list]:
    """The scene's static context views (frame 1, its lighting as set),
    rendered into ``tmp``: their EXR contents and ``camera_matrices``."""
    sc = bpy.context.scene
    sc.frame_set(1)
    ctx = info["ctx_camera"]
    sc.camera = ctx
    imgs, cams = [], []
    for k, (eye, aim) in enumerate(info["ctx_poses"]):
        ctx.location = eye
        ctx.rotation_euler = (aim - eye).to_track_quat("-Z", "Y").to_euler()
        bpy.context.view_layer.update()
        cams.append(camera_matrices(ctx, width, height))
        imgs.append(render_to(tmp / f"ctx_{k:02d}.exr"))
    return imgs, cams


def write_context(path: Path, imgs: list, cams: list, k_exp: float) -> None:
    """``ctx.npz``: the context views scaled like the frames (``k_exp``)."""
    np.savez_compressed(
        path,
        color=to_f16(np.stack([f["rgba"][..., :3] * k_exp for f in imgs])),
        depth=np.stack([f["depth"] for f in imgs]).astype(np.float32),
        world_to_camera=np.stack([c[0] for c in cams]),
        world_to_ndc=np.stack([c[1] for c in cams]),
    )


def context_views(scene_id: int, scene_dir: Path, cfg: dict, catalog: dict) -> dict:
    """Renders the context views of an existing scene again and writes its
    ``ctx.npz`` (scenes rendered before they were kept). The scene is rebuilt
    from its seed with the frame count, size and samples in its
    ``meta.json``, and the views are scaled by its ``exposure_scale``. Kept
    only if the stored reconstruction stream comes back from them with the
    scene's own seed (coverage on at least 99.5 % of the pixels): a scene
    that does not rebuild the same (another asset catalog, generator or
    Blender) gets no ``ctx.npz``."""
    meta = json.loads((scene_dir / "meta.json").read_text())
    t_start = time.time()
    cfg = dict(cfg, width=meta["width"], height=meta["height"], frames=meta["frames"], samples=meta["samples"])
    cfg["seed"] = meta["seed"]
    rng = np.random.default_rng([cfg["seed"], scene_id])
    info = build_scene(rng, catalog, cfg)
    clean_quality(bpy.context.scene, cfg["samples"], scene_id)
    setup_world(rng, Path(catalog["hdri_dir"]), info["light"])
    tmp = scene_dir.with_name(scene_dir.name + ".ctx.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    imgs, cams = render_context_views(info, cfg["width"], cfg["height"], tmp)
    out = tmp / "ctx.npz"
    write_context(out, imgs, cams, float(meta["exposure_scale"]))
    stored = load_sample(scene_dir, "s1_recon")["input"][..., 3]
    again = redegrade(scene_dir, np.random.default_rng([cfg["seed"], scene_id, 1]), ctx=out)["input"][..., 3]
    agree = float((again == stored).mean())
    kept = agree >= 0.995
    if kept:
        shutil.copy(out, scene_dir / "ctx.npz.tmp")
        (scene_dir / "ctx.npz.tmp").rename(scene_dir / "ctx.npz")
    shutil.rmtree(tmp, ignore_errors=True)
    seconds = round(time.time() - t_start, 1)
    return {"scene_id": scene_id, "seconds": seconds, "coverage_agrees": agree, "kept": kept}


def _composite_streams(cfg: dict, scene_id: int, gt, mask, ni, relit, noisy: tuple, relight) -> dict:
    """Streams 2-6, composited from the clean, ``noinsert``, relit and noisy
    renders (``noisy``: the frames and their parameters)."""
    noisy, noise = noisy
    ones = np.ones(gt.shape[:3] + (1,), np.float32)
    streams = {}
    # 2: tone mismatch on the insert.
    tone = degrade.random_tone(np.random.default_rng([cfg["seed"], scene_id, 2]))
    s2 = degrade.composite(gt, degrade.apply_tone(gt, tone), mask)
    streams["s2_tone"] = ({"input": np.concatenate([s2, ones], -1)}, tone)
    # 3: relighting mismatch: the insert from the relit render over the true background.
    s3 = degrade.composite(gt, relit, mask)
    streams["s3_relight"] = ({"input": np.concatenate([s3, ones], -1)}, {"light": relight})
    # 4: missing contact shadow: the insert over the background rendered without it.
    s4 = degrade.composite(ni, gt, mask)
    streams["s4_shadow"] = ({"input": np.concatenate([s4, ones], -1)}, {})
    # 5: render noise and flicker.
    streams["s5_noise"] = ({"input": np.concatenate([noisy, ones], -1), "mask_insert": np.zeros_like(mask)}, noise)
    # 6: an inserted object as hosts really composite it: mismatched (relit or
    # tone-shifted) and without its contact shadow.
    mix_rng = np.random.default_rng([cfg["seed"], scene_id, 6])
    if mix_rng.random() < 0.5:
        fg, p6 = relit, {"insert": "relit", "light": relight}
    else:
        tone6 = degrade.random_tone(mix_rng)
        fg, p6 = degrade.apply_tone(gt, tone6), {"insert": "tone", "tone": tone6}
    s6 = degrade.composite(ni, fg, mask)
    streams["s6_insert"] = ({"input": np.concatenate([s6, ones], -1)}, p6)
    return streams


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))


def scene_checks(gt, motion, depth, w2c, w2ndc) -> dict:
    """Convention checks on the clean render: motion vectors align the previous
    frame, and cameras + depth agree with the motion vectors."""
    errs_mv, errs_id, errs_cam = [], [], []
    T, H, W = depth.shape
    cam_motion = degrade.camera_motion(depth, w2c, w2ndc)
    for t in range(1, T):
        aligned, valid = degrade.warp_bilinear(gt[t - 1], motion[t])
        d = np.abs(aligned - gt[t]).mean(-1)
        d0 = np.abs(gt[t - 1] - gt[t]).mean(-1)
        v = valid > 0
        errs_mv.append(float(np.mean(d[v])))
        errs_id.append(float(np.mean(d0[v])))
        fin = depth[t] < 1e9
        e = np.hypot(*np.moveaxis(cam_motion[t] - motion[t, ..., :2], -1, 0))
        errs_cam.append(float(np.median(e[fin])) if fin.any() else 0.0)
    return {
        "mean_abs_err_warped_prev": float(np.mean(errs_mv)) if errs_mv else 0.0,
        "mean_abs_err_unwarped_prev": float(np.mean(errs_id)) if errs_id else 0.0,
        "median_px_err_camera_vs_motion": float(np.mean(errs_cam)) if errs_cam else 0.0,
    }


def is_test_scene(scene_id: int, cfg: dict) -> bool:
    """Held-out scenes: every ``test_every``-th scene id (never used for training)."""
    return scene_id % cfg["test_every"] == cfg["test_every"] - 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Render one training scene (bpy).")
    ap.add_argument("--scene-id", type=int, required=True)
    ap.add_argument("--out", type=Path, required=True, help="scene directory to write")
    ap.add_argument("--catalog", type=Path, default=Path(__file__).resolve().parent.parent / "assets" / "catalog.json")
    ap.add_argument("--width", type=int, default=256)
    ap.add_argument("--height", type=int, default=144)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--samples", type=int, default=32, help="samples of the clean renders (OIDN-denoised)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--test-every", type=int, default=10)
    ap.add_argument("--keep-exr", action="store_true", help="keep Blender's EXRs beside the samples")
    ap.add_argument(
        "--streams",
        choices=("all", "recon"),
        default="all",
        help="recon: render the clean frames and the context views only, write the reconstruction stream",
    )
    ap.add_argument(
        "--context-only",
        action="store_true",
        help="render only the context views of the existing scene at --out again and write its ctx.npz",
    )
    args = ap.parse_args(argv)
    if not args.catalog.exists():
        print(f"render_scene: no asset catalog at {args.catalog}; run python -m training.synth.assets", file=sys.stderr)
        return 2
    catalog = json.loads(args.catalog.read_text())
    cfg = {
        "width": args.width,
        "height": args.height,
        "frames": args.frames,
        "samples": args.samples,
        "threads": args.threads,
        "seed": args.seed,
        "test_every": args.test_every,
        "keep_exr": args.keep_exr,
        "streams": args.streams,
    }
    if args.context_only:
        res = context_views(args.scene_id, args.out, cfg, catalog)
        print(json.dumps(res))
        return 0 if res["kept"] else 1
    meta = render_scene(args.scene_id, args.out, cfg, catalog)
    print(json.dumps({"scene_id": args.scene_id, "seconds": meta["render_seconds"], "checks": meta["checks"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
