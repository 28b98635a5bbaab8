"""The direction toward the scene's dominant light, for inserts' cast shadows.

The library casts an insert's shadow away from ``light_direction`` (world
space, toward the light). With the panel's Light on *Scene Sun* it is, at
each frame, the +Z axis of the strongest Sun light that renders:

- candidates: Sun lights in the view layer's collections that render
  (collections neither excluded nor disabled for renders, the object not
  disabled for renders), with a strength (``energy``) above 0;
- the strongest at the frame wins (strength evaluated at that frame, so an
  animated strength counts); a tie goes to the first by name;
- a Sun shines along its local -Z, so the direction toward it is its world
  matrix's +Z axis, normalized (Blender's world, Z up: the world of the
  camera matrices the extension passes).

Without a Sun light, the sun of the World lights the scene (common
outdoor setups). An equirectangular environment image (the World's
Background fed by an Environment Texture, unturned or turned by a Mapping
node: ``_env_lookup``) has a sun where the texels within
:data:`SUN_RADIUS_DEG` of its brightest are a compact bright source (the
brightest at least :data:`SUN_CONTRAST` times the mean radiance of the
rest of the sphere, those texels at least :data:`SUN_SHARE` of the image's
power: a clear sky's sun, a studio image's key light; an overcast sky has
none): the direction is toward their power-weighted mean (Blender's
mapping: column ``u = 0.5 - atan2(y, x) / (2 pi)``, row from the bottom
``v = 0.5 + elevation / pi``), when above the horizon. A Sky Texture's sun disc: the World's Sky Texture
of a type that draws a disc (Multiple or Single Scattering), its disc on
and its sun above the horizon, feeding the active Background's Color,
gives the direction of its sun: ``(cos e sin r, cos e cos r, sin e)`` for
elevation ``e`` and rotation ``r``. Both checked against Cycles: a surface
facing the direction gets the most light.

Point, spot and area lights are not used: their direction depends on where
the insert stands. Without a Sun the library casts no directional shadow
(the contact shadow under the insert stays). *Manual* passes a fixed
direction, *Off* none.

The library also takes the scene's direct-to-ambient ratio
(``light_ratio``): the Sun's irradiance on a surface facing it over the
ambient one on a surface in its shadow. The ambient is taken as half the
World's irradiance on a surface facing up: a wall, an object's side, or
ground in the shadow of a wall sees about half the sky (out of domain the
courtyard's own shadows show 2.1-2.6, its Sun over its whole sky 1.0, over
half of it 2.0). Cycles' units: a Sun's strength is its irradiance in
W/m^2, a World's color times strength its radiance, of which a whole sky
gives ``pi`` times as much irradiance. ``scene_ratio`` reads
it where the World says it plainly: a Background shader (its Strength not
linked) whose Color is a constant or an equirectangular Environment
Texture image, unturned or turned by a Mapping node (its upper half,
cosine-weighted; its sun, above, left out of the ambient, and the direct
light without a Sun light), or a World without nodes. Other Worlds (a Sky
Texture, node setups) give None, and the library measures the scene's light from the frame's own
shadows, which a reconstruction's depth cannot give (docs/inserts.md). The
panel's *Sun to Sky* sets it by hand, or *Measure* renders it
(``measure_ratio``): Cycles renders a white diffuse square lit by the World
alone, facing up, with every Sky Texture's sun disc off (the ambient), and
for a Sky Texture's sun the same square facing it with the disc on and off
(the difference is the disc's irradiance); a Sun light's irradiance is its
strength. Any World works, as Cycles renders it. Besides the button, the
sequence operator and a background render's start render it by
themselves (``runtime.Runner``'s ``measure_light``).
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass

import bpy


def _rendered_objects(view_layer: bpy.types.ViewLayer) -> Iterator[bpy.types.Object]:
    """Objects of ``view_layer``'s collections that render (each once)."""
    seen: set[str] = set()
    stack = [view_layer.layer_collection]
    while stack:
        lc = stack.pop()
        if lc.exclude or lc.collection.hide_render:
            continue
        for obj in lc.collection.objects:
            if obj.name not in seen:
                seen.add(obj.name)
                yield obj
        stack.extend(lc.children)


def suns(view_layer: bpy.types.ViewLayer) -> list[bpy.types.Object]:
    """The Sun lights of ``view_layer`` that render, by name."""
    found = [
        obj
        for obj in _rendered_objects(view_layer)
        if obj.type == "LIGHT" and obj.data.type == "SUN" and not obj.hide_render
    ]
    return sorted(found, key=lambda o: o.name)


def _evaluated(obj: bpy.types.Object, depsgraph) -> bpy.types.Object:
    if depsgraph is None:
        return obj
    try:
        return obj.evaluated_get(depsgraph)
    except (RuntimeError, ReferenceError):  # not in that depsgraph
        return obj


def dominant_sun(view_layer: bpy.types.ViewLayer, depsgraph=None) -> tuple[bpy.types.Object, float] | None:
    """The strongest Sun (the evaluated object when ``depsgraph`` is given)
    and its strength, or None."""
    best = None
    for sun in suns(view_layer):
        ob = _evaluated(sun, depsgraph)
        energy = float(ob.data.energy)
        if math.isfinite(energy) and energy > 0 and (best is None or energy > best[1]):
            best = (ob, energy)
    return best


def direction_of(obj: bpy.types.Object) -> tuple[float, float, float] | None:
    """The world matrix's +Z axis of ``obj``, normalized (None if degenerate)."""
    m = obj.matrix_world
    z = (m[0][2], m[1][2], m[2][2])
    n = math.sqrt(sum(c * c for c in z))
    if not math.isfinite(n) or n < 1e-12:
        return None
    return (z[0] / n, z[1] / n, z[2] / n)


def scene_direction(
    view_layer: bpy.types.ViewLayer, depsgraph=None, world: bpy.types.World | None = None
) -> tuple[float, float, float] | None:
    """The direction toward the strongest Sun of ``view_layer`` (world space,
    unit); without one, toward ``world``'s Sky Texture sun (``sky_sun``) or
    the sun in its environment image (``env_sun``); else None.

    With ``depsgraph`` (a ``frame_change_post`` handler's) the Sun and the
    World evaluated in it: during an animation render that is the light at
    the frame being rendered, while the originals still hold the frame the
    render started from. Without it, the originals (right in the main
    thread after ``frame_set``).
    """
    best = dominant_sun(view_layer, depsgraph)
    if best is not None:
        return direction_of(best[0])
    world = _evaluated(world, depsgraph) if world is not None else None
    sky = sky_sun(world)
    if sky is not None:
        return sky_sun_direction(sky)
    env = env_sun(world)
    return None if env is None else env[0]


def manual_direction(v) -> tuple[float, float, float] | None:
    """A user's direction, normalized (None for the zero vector)."""
    x, y, z = (float(c) for c in v)
    n = math.sqrt(x * x + y * y + z * z)
    if not math.isfinite(n) or n < 1e-12:
        return None
    return (x / n, y / n, z / n)


#: Rec.709 luminance weights (the library's working space).
LUMA = (0.2126, 0.7152, 0.0722)

#: The largest ratio the library takes (``light_ratio``).
MAX_RATIO = 12.0


def _luma(c) -> float:
    return sum(w * float(v) for w, v in zip(LUMA, c, strict=False))


RGB = tuple[float, float, float]


def _rgb(c, scale: float = 1.0) -> RGB:
    r, g, b = (scale * float(v) for v in tuple(c)[:3])
    return (r, g, b)


def sun_color(sun: bpy.types.Object) -> RGB:
    """The Sun's irradiance on a surface facing it per channel (its strength
    times its color)."""
    return _rgb(sun.data.color, float(sun.data.energy))


def _background(world: bpy.types.World | None):
    """The Background shader the World's active output takes directly, its
    Strength not linked, or None."""
    if world is None or world.node_tree is None:
        return None
    outputs = [n for n in world.node_tree.nodes if n.bl_idname == "ShaderNodeOutputWorld"]
    out = next((n for n in outputs if n.is_active_output), outputs[0] if outputs else None)
    if out is None or not out.inputs["Surface"].is_linked:
        return None
    bg = out.inputs["Surface"].links[0].from_node
    if bg.bl_idname != "ShaderNodeBackground" or bg.inputs["Strength"].is_linked:
        return None
    return bg


#: Sky Texture types that draw a sun disc (NISHITA before Blender 5.0).
SKY_DISC_TYPES = frozenset({"MULTIPLE_SCATTERING", "SINGLE_SCATTERING", "NISHITA"})


def sky_sun(world: bpy.types.World | None):
    """The World's Sky Texture whose sun disc lights the scene, or None: a
    Sky Texture of a type in :data:`SKY_DISC_TYPES` feeding the active
    Background's Color, its disc on, its sun's intensity above 0 and its
    elevation above the horizon, the Background's Strength above 0."""
    bg = _background(world)
    if bg is None or not bg.inputs["Color"].is_linked or float(bg.inputs["Strength"].default_value) <= 0:
        return None
    sky = bg.inputs["Color"].links[0].from_node
    if (
        sky.bl_idname != "ShaderNodeTexSky"
        or sky.mute
        or sky.sky_type not in SKY_DISC_TYPES
        or not sky.sun_disc
        or float(sky.sun_intensity) <= 0
        or float(sky.sun_elevation) <= 0
    ):
        return None
    return sky


def sky_sun_direction(sky) -> tuple[float, float, float]:
    """The direction toward a Sky Texture's sun (world space, unit)."""
    e, r = float(sky.sun_elevation), float(sky.sun_rotation)
    return (math.cos(e) * math.sin(r), math.cos(e) * math.cos(r), math.sin(e))


#: A World image's sun: the texels within this angle (degrees) of its
#: brightest one (the disc, block-averaged, and its aureole) ...
SUN_RADIUS_DEG = 6.0
#: ... when the brightest texel is at least this many times the mean
#: radiance of the rest of the sphere ...
SUN_CONTRAST = 20.0
#: ... and those texels carry at least this share of the image's power.
SUN_SHARE = 0.05
#: A World image is read at most this many texels wide (block means; half
#: as many rows): the irradiance is a smooth integral.
ENV_TEXELS = 256


@dataclass(frozen=True)
class EnvLight:
    """What an equirectangular World image gives, per unit of the
    Background's strength (Blender's world, Z up)."""

    #: Irradiance on a surface facing up, the sun's texels left out (RGB).
    ambient_up_rgb: RGB
    #: The direction toward the image's sun (unit), or None: no compact
    #: bright source, or one below the horizon.
    sun: tuple[float, float, float] | None
    #: The sun's irradiance on a surface facing it (RGB; 0 without).
    sun_rgb: RGB

    @property
    def sun_irradiance(self) -> float:
        """``sun_rgb``'s luminance."""
        return _luma(self.sun_rgb)


#: The block-averaged pixels of the last World image read, by
#: ``_env_key``.
_ENV_CACHE: dict[tuple, object] = {}


def _env_key(image: bpy.types.Image) -> tuple | None:
    """What identifies an image's pixels while it is not edited in Blender
    (a file's version, a packed file's size), or None (read it again)."""
    if image.is_dirty:
        return None
    w, h = image.size
    key = (image.name_full, image.source, image.filepath, w, h, image.channels)
    if image.packed_file is not None:
        return (*key, "packed", image.packed_file.size)
    path = bpy.path.abspath(image.filepath) if image.source == "FILE" and image.filepath else ""
    if path and os.path.isfile(path):
        return (*key, "file", os.path.getmtime(path), os.path.getsize(path))
    return None


def _env_rgb(image: bpy.types.Image):
    """An image's RGB, rows from the bottom, block-averaged to at most
    :data:`ENV_TEXELS` wide (float64), or None. An image not edited in
    Blender (a file or a packed file) is read once per version (the panel
    draws often; an 8k image takes seconds); other images each time."""
    import numpy as np

    w, h = image.size
    c = image.channels
    if w < 2 or h < 2 or c < 3:
        return None
    key = _env_key(image)
    if key is not None and key in _ENV_CACHE:
        return _ENV_CACHE[key]
    px = np.empty(w * h * c, np.float32)
    image.pixels.foreach_get(px)
    # In place (an 8k image is half a gigabyte as it is): no NaN, infinity
    # or negative light; then block means, summed in float64.
    np.nan_to_num(px, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    np.maximum(px, 0.0, out=px)
    f = max(1, math.ceil(w / ENV_TEXELS))
    hh, ww = h // f, w // f
    blocks = px.reshape(h, w, c)[: hh * f, : ww * f].reshape(hh, f, ww, f, c)
    rgb = blocks.mean(axis=(1, 3), dtype=np.float64)[..., :3]
    if key is not None:
        _ENV_CACHE.clear()  # one World image at a time
        _ENV_CACHE[key] = rgb
    return rgb


#: The last few ``env_light`` results of images read once (``_env_key``),
#: by (key, lookup): the panel asks on every draw.
_ENV_LIGHTS: dict[tuple, EnvLight | None] = {}


def env_light(image: bpy.types.Image, lookup=None) -> EnvLight | None:
    """What an equirectangular image gives (see the module's notes), or None
    where it cannot be read. ``lookup``: the 3x3 rotation taking a world
    direction to the direction the image is looked up with (a Mapping
    node's, ``_env_lookup``); None: the identity (the default mapping)."""
    key = _env_key(image)
    if key is not None:
        memo = (key, None if lookup is None else tuple(tuple(float(c) for c in row) for row in lookup))
        if memo not in _ENV_LIGHTS:
            if len(_ENV_LIGHTS) >= 8:
                _ENV_LIGHTS.clear()
            _ENV_LIGHTS[memo] = _env_light(image, lookup)
        return _ENV_LIGHTS[memo]
    return _env_light(image, lookup)


def _env_light(image: bpy.types.Image, lookup) -> EnvLight | None:
    import numpy as np

    rgb = _env_rgb(image)
    if rgb is None:
        return None
    h, w = rgb.shape[:2]
    # Blender's mapping: column u = 0.5 - atan2(y, x) / (2 pi), row v (from
    # the bottom) = 0.5 + elevation / pi.
    lat = math.pi * ((np.arange(h) + 0.5) / h - 0.5)
    phi = math.pi * (1.0 - 2.0 * (np.arange(w) + 0.5) / w)
    clat, slat = np.cos(lat)[:, None], np.sin(lat)[:, None]
    d = np.stack(np.broadcast_arrays(clat * np.cos(phi)[None], clat * np.sin(phi)[None], slat), -1)
    if lookup is not None:
        # Looked up with e = M d, a texel's world direction is d = M^T e
        # (row vectors: e @ M).
        d = d @ np.asarray(lookup, np.float64)
    solid = np.broadcast_to(clat * (math.pi / h) * (2.0 * math.pi / w), (h, w))
    lum = rgb @ np.asarray(LUMA)
    facing_up = np.maximum(d[..., 2], 0.0) * solid
    k = np.unravel_index(int(np.argmax(lum)), lum.shape)
    near = d @ d[k] >= math.cos(math.radians(SUN_RADIUS_DEG))
    power = lum * solid
    total, sun = float(power.sum()), float(power[near].sum())
    rest = (total - sun) / max(float(solid[~near].sum()), 1e-12)
    none = (0.0, 0.0, 0.0)
    if total <= 0 or sun < SUN_SHARE * total or lum[k] < SUN_CONTRAST * rest:
        ambient = (rgb * facing_up[..., None]).sum(axis=(0, 1))
        return EnvLight(_rgb(ambient), None, none) if np.isfinite(ambient).all() else None
    ambient = (rgb * facing_up[..., None])[~near].sum(axis=0)
    toward = (d[near] * power[near][:, None]).sum(axis=0)
    n = float(np.linalg.norm(toward))
    if not np.isfinite(ambient).all() or not math.isfinite(n) or n <= 0:
        return None
    toward /= n
    if toward[2] <= 0:  # below the horizon: no direct light on the ground
        return EnvLight(_rgb(ambient), None, none)
    facing = solid[near] * np.maximum(d[near] @ toward, 0.0)
    direct = (rgb[near] * facing[:, None]).sum(axis=0)
    return EnvLight(_rgb(ambient), (float(toward[0]), float(toward[1]), float(toward[2])), _rgb(direct))


def _env_lookup(tex):
    """The 3x3 rotation (nested lists) taking a world direction to the one
    ``tex`` looks its image up with: None for the default (its Vector not
    linked); a Mapping node's rotation where the Vector comes from a
    Mapping node fed by the Texture Coordinate's Generated output (the
    world direction), with no location and a uniform scale (rotating an
    image this way is how a World's image is turned); else False (not read).
    """
    vec = tex.inputs["Vector"]
    if not vec.is_linked:
        return None
    node = vec.links[0].from_node
    if node.bl_idname != "ShaderNodeMapping" or node.mute or not node.inputs["Vector"].is_linked:
        return False
    src = node.inputs["Vector"].links[0]
    if src.from_node.bl_idname != "ShaderNodeTexCoord" or src.from_socket.name != "Generated":
        return False
    if any(node.inputs[k].is_linked for k in ("Location", "Rotation", "Scale") if k in node.inputs):
        return False
    if node.vector_type in ("POINT", "TEXTURE") and any(
        abs(float(c)) > 1e-9 for c in node.inputs["Location"].default_value
    ):
        return False
    sx, sy, sz = (float(c) for c in node.inputs["Scale"].default_value)
    if not (sx > 0 and abs(sy - sx) <= 1e-6 * sx and abs(sz - sx) <= 1e-6 * sx):
        return False
    from mathutils import Euler

    r = Euler(tuple(float(c) for c in node.inputs["Rotation"].default_value), "XYZ").to_matrix()
    if node.vector_type == "TEXTURE":  # the inverse transform
        r.transpose()
    return [list(row) for row in r]


def _env_texture(world: bpy.types.World | None):
    """(the World's Environment Texture node, the Background's strength,
    the lookup rotation of ``_env_lookup``) where the World is lit plainly
    by an equirectangular image (see the module's notes), else None."""
    bg = _background(world)
    if bg is None or not bg.inputs["Color"].is_linked:
        return None
    tex = bg.inputs["Color"].links[0].from_node
    if (
        tex.bl_idname != "ShaderNodeTexEnvironment"
        or tex.mute
        or tex.image is None
        or tex.projection != "EQUIRECTANGULAR"
    ):
        return None
    lookup = _env_lookup(tex)
    if lookup is False:
        return None
    return tex, float(bg.inputs["Strength"].default_value), lookup


def env_sun(world: bpy.types.World | None) -> tuple[tuple[float, float, float], float, RGB] | None:
    """The direction toward the sun in the World's image and its irradiance
    on a surface facing it (times the Background's strength; luminance and
    RGB), or None."""
    found = _env_texture(world)
    if found is None or found[1] <= 0:
        return None
    got = env_light(found[0].image, found[2])
    if got is None or got.sun is None:
        return None
    return got.sun, found[1] * got.sun_irradiance, _rgb(got.sun_rgb, found[1])


def world_ambient_rgb(world: bpy.types.World | None) -> RGB | None:
    """The World's irradiance on a surface facing up per channel (see the
    module's notes), or None where the World does not say it plainly."""
    if world is None:
        return None
    if world.node_tree is None:
        # Blender 5.0 renders a World's nodes whatever ``use_nodes`` says.
        return _rgb(world.color, math.pi)
    bg = _background(world)
    if bg is None:
        return None
    strength = float(bg.inputs["Strength"].default_value)
    color = bg.inputs["Color"]
    if not color.is_linked:
        return _rgb(color.default_value, math.pi * strength)
    found = _env_texture(world)
    got = None if found is None else env_light(found[0].image, found[2])
    return None if got is None else _rgb(got.ambient_up_rgb, strength)


def scene_ratio(view_layer: bpy.types.ViewLayer, world: bpy.types.World | None) -> float | None:
    """The strongest rendered Sun's irradiance (without one, the World
    image's sun's) over half the World's on a surface facing up (the
    library's ``light_ratio``, at most :data:`MAX_RATIO`; see the module's
    notes), or None without a Sun or where the World does not say its
    light."""
    got = scene_light(view_layer, world)
    return None if got is None else got.ratio


def scene_light(view_layer: bpy.types.ViewLayer, world: bpy.types.World | None) -> RatioMeasure | None:
    """``scene_ratio`` with its parts: the direct light's and the World's
    irradiance per channel (the library's ``light_color``, and twice its
    ``ambient_color``), or None."""
    best = dominant_sun(view_layer)
    ambient = world_ambient_rgb(world)
    if ambient is None or not all(math.isfinite(c) for c in ambient) or _luma(ambient) <= 0:
        return None
    if best is not None:
        direct, source = sun_color(best[0]), f"Sun light '{best[0].name}'"
    else:
        found = env_sun(world)
        if found is None:
            return None
        direct, source = found[2], "the World image's sun"
    return RatioMeasure.of(direct, ambient, f"{source} and the World")


#: The probe's render: pixels per side and Cycles samples per pixel (about
#: 0.4 s a render on 2 cores; the mean of 8192 paths is within 1 % on the
#: skies of the tests).
PROBE_SIZE = 8
PROBE_SAMPLES = 128


def color_text(c) -> str:
    """A color parameter's text: "r, g, b" (negative values as 0)."""
    return ", ".join(f"{max(float(v), 0.0):.6g}" for v in c)


@dataclass(frozen=True)
class RatioMeasure:
    """A ``light_ratio`` and its parts (Cycles' irradiance units)."""

    #: ``direct / (0.5 * ambient)``, at most :data:`MAX_RATIO`.
    ratio: float
    #: The direct light's irradiance on a surface facing it (luminance).
    direct: float
    #: The World's irradiance on a surface facing up, sun discs off (luminance).
    ambient: float
    #: Where the direct light came from ("Sun light 'NAME'" or "Sky Texture 'NAME'").
    source: str
    #: ``direct`` per channel: the library's ``light_color``.
    direct_rgb: RGB = (0.0, 0.0, 0.0)
    #: ``ambient`` per channel; half of it is the library's ``ambient_color``.
    ambient_rgb: RGB = (0.0, 0.0, 0.0)

    @classmethod
    def of(cls, direct: RGB, ambient: RGB, source: str) -> RatioMeasure | None:
        """From the two irradiances per channel; None unless both are finite
        and positive."""
        d, a = _luma(direct), _luma(ambient)
        if not (math.isfinite(d) and math.isfinite(a)) or d <= 0 or a <= 0:
            return None
        return cls(min(d / (0.5 * a), MAX_RATIO), d, a, source, _rgb(direct), _rgb(ambient))

    def params(self) -> dict[str, str]:
        """The library's ``light_color`` and ``ambient_color`` ("r, g, b")."""
        return {
            "light_color": color_text(self.direct_rgb),
            "ambient_color": color_text(tuple(0.5 * v for v in self.ambient_rgb)),
        }


class _Probe:
    """A scene of its own with a white diffuse square and an orthographic
    camera looking at it, rendered with Cycles under a given World; every
    data-block it makes is removed on close."""

    def __init__(self) -> None:
        self.dir = tempfile.mkdtemp(prefix="harmonizer_probe_")
        self.made: list = []
        self.scene = bpy.data.scenes.new("harmonizer_probe")
        self.made.append((bpy.data.scenes, self.scene))
        r = self.scene.render
        r.engine = "CYCLES"
        self.scene.cycles.device = "CPU"
        self.scene.cycles.samples = PROBE_SAMPLES
        self.scene.cycles.use_denoising = False
        r.resolution_x = r.resolution_y = PROBE_SIZE
        r.resolution_percentage = 100
        r.use_compositing = False
        r.use_sequencer = False
        r.image_settings.file_format = "OPEN_EXR"
        self.scene.view_settings.view_transform = "Standard"
        mesh = bpy.data.meshes.new("harmonizer_probe")
        self.made.append((bpy.data.meshes, mesh))
        mesh.from_pydata([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], [], [(0, 1, 2, 3)])
        mat = bpy.data.materials.new("harmonizer_probe")
        self.made.append((bpy.data.materials, mat))
        mat.use_nodes = True
        nt = mat.node_tree
        nt.nodes.clear()
        diffuse = nt.nodes.new("ShaderNodeBsdfDiffuse")
        diffuse.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        nt.links.new(diffuse.outputs["BSDF"], out.inputs["Surface"])
        mesh.materials.append(mat)
        self.square = bpy.data.objects.new("harmonizer_probe", mesh)
        self.made.append((bpy.data.objects, self.square))
        cam = bpy.data.cameras.new("harmonizer_probe")
        self.made.append((bpy.data.cameras, cam))
        cam.type = "ORTHO"
        cam.ortho_scale = 0.5
        self.camera = bpy.data.objects.new("harmonizer_probe_camera", cam)
        self.made.append((bpy.data.objects, self.camera))
        self.scene.collection.objects.link(self.square)
        self.scene.collection.objects.link(self.camera)
        self.scene.camera = self.camera

    def irradiance(self, world: bpy.types.World, toward: tuple[float, float, float]) -> float:
        """The irradiance ``world`` alone gives a surface facing ``toward``:
        pi times the white square's rendered luminance."""
        return _luma(self.irradiance_rgb(world, toward))

    def irradiance_rgb(self, world: bpy.types.World, toward: tuple[float, float, float]) -> RGB:
        """``irradiance`` per channel: pi times the white square's rendered
        color."""
        from mathutils import Vector

        n = Vector(toward).normalized()
        turn = n.to_track_quat("Z", "Y").to_euler()
        self.square.rotation_euler = turn
        self.camera.rotation_euler = turn
        self.camera.location = n * 3.0
        self.scene.world = world
        path = os.path.join(self.dir, "probe.exr")
        self.scene.render.filepath = path
        if bpy.ops.render.render(write_still=True, scene=self.scene.name) != {"FINISHED"}:
            raise RuntimeError("Harmonizer: the probe render of the World did not finish")
        img = bpy.data.images.load(path, check_existing=False)
        try:
            import numpy as np

            px = np.empty(len(img.pixels), np.float32)
            img.pixels.foreach_get(px)
            rgb = px.reshape(-1, img.channels)[:, :3].astype(np.float64)
            return _rgb(rgb.mean(axis=0), math.pi)
        finally:
            bpy.data.images.remove(img)

    def without_discs(self, world: bpy.types.World) -> bpy.types.World:
        """A copy of ``world`` (removed on close), every Sky Texture's sun
        disc off."""
        w = world.copy()
        self.made.append((bpy.data.worlds, w))
        if w.node_tree is not None:
            for node in w.node_tree.nodes:
                if node.bl_idname == "ShaderNodeTexSky":
                    node.sun_disc = False
        return w

    def close(self) -> None:
        for coll, block in reversed(self.made):
            try:
                coll.remove(block)
            except (ReferenceError, RuntimeError):
                pass
        shutil.rmtree(self.dir, ignore_errors=True)


def measure_ratio(view_layer: bpy.types.ViewLayer, world: bpy.types.World | None) -> RatioMeasure | None:
    """The scene's ``light_ratio`` rendered by Cycles (see the module's
    notes): the strongest rendered Sun's irradiance, or else the World's Sky
    Texture sun's, over half the World's irradiance on a surface facing up.
    None without a direct light or a World, or when the World gives no
    light. Renders two or three small probe images (a second or two)."""
    if world is None:
        return None
    best = dominant_sun(view_layer)
    sky = None if best is not None else sky_sun(world)
    if best is None and sky is None:
        return None
    probe = _Probe()
    try:
        sky_only = probe.without_discs(world)
        ambient = probe.irradiance_rgb(sky_only, (0.0, 0.0, 1.0))
        if best is not None:
            direct, source = sun_color(best[0]), f"Sun light '{best[0].name}'"
        else:
            toward = sky_sun_direction(sky)
            on, off = probe.irradiance_rgb(world, toward), probe.irradiance_rgb(sky_only, toward)
            direct = _rgb(max(a - b, 0.0) for a, b in zip(on, off, strict=True))
            source = f"Sky Texture '{sky.name}'"
    finally:
        probe.close()
    return RatioMeasure.of(direct, ambient, source)
