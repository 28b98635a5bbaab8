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
Texture image with the default mapping (its upper half, cosine-weighted),
or a World without nodes. Other Worlds (a Sky Texture, node setups) give
None, and the library measures the scene's light from the frame's own
shadows; the panel's *Sun to Sky* sets it by hand.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

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


def scene_direction(view_layer: bpy.types.ViewLayer, depsgraph=None) -> tuple[float, float, float] | None:
    """The direction toward the strongest Sun of ``view_layer`` (world space,
    unit), or None.

    With ``depsgraph`` (a ``frame_change_post`` handler's) the Sun evaluated
    in it: during an animation render that is the Sun at the frame being
    rendered, while the original objects still hold the frame the render
    started from. Without it, the original objects (right in the main thread
    after ``frame_set``).
    """
    best = dominant_sun(view_layer, depsgraph)
    return None if best is None else direction_of(best[0])


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


def sun_irradiance(sun: bpy.types.Object) -> float:
    """The Sun's irradiance on a surface facing it (its strength times its
    color's luminance)."""
    return float(sun.data.energy) * _luma(sun.data.color)


def _image_upper_irradiance(image: bpy.types.Image) -> float | None:
    """Irradiance on a surface facing up from an equirectangular image
    (Blender's mapping: the top row is the zenith), per unit of strength:
    the upper half's luminance weighted by the cosine to the zenith and
    each row's solid angle."""
    import numpy as np

    w, h = image.size
    c = image.channels
    if w < 2 or h < 2 or c < 3:
        return None
    px = np.empty(w * h * c, np.float32)
    image.pixels.foreach_get(px)
    # Rows from the bottom (Blender's pixel order): the upper half, each
    # row's mean luminance.
    rows = px.reshape(h, w, c)[h // 2 :, :, :3].astype(np.float64)
    lum = (rows @ np.asarray(LUMA)).mean(axis=1)
    elev = np.pi * ((np.arange(h // 2, h) + 0.5) / h - 0.5)
    # Per row: 2 pi cos(elev) d_elev of solid angle, times sin(elev) (the
    # cosine to a surface facing up).
    total = float((lum * np.sin(elev) * np.cos(elev)).sum() * (np.pi / h) * 2.0 * np.pi)
    return total if math.isfinite(total) else None


def world_ambient(world: bpy.types.World | None) -> float | None:
    """The World's irradiance on a surface facing up (see the module's
    notes), or None where the World does not say it plainly."""
    if world is None:
        return None
    if world.node_tree is None:
        # Blender 5.0 renders a World's nodes whatever ``use_nodes`` says.
        return math.pi * _luma(world.color)
    nodes = world.node_tree.nodes
    outputs = [n for n in nodes if n.bl_idname == "ShaderNodeOutputWorld"]
    out = next((n for n in outputs if n.is_active_output), outputs[0] if outputs else None)
    if out is None or not out.inputs["Surface"].is_linked:
        return None
    bg = out.inputs["Surface"].links[0].from_node
    if bg.bl_idname != "ShaderNodeBackground" or bg.inputs["Strength"].is_linked:
        return None
    strength = float(bg.inputs["Strength"].default_value)
    color = bg.inputs["Color"]
    if not color.is_linked:
        return math.pi * strength * _luma(color.default_value)
    tex = color.links[0].from_node
    if (
        tex.bl_idname != "ShaderNodeTexEnvironment"
        or tex.image is None
        or tex.projection != "EQUIRECTANGULAR"
        or tex.inputs["Vector"].is_linked
    ):
        return None
    e = _image_upper_irradiance(tex.image)
    return None if e is None else strength * e


def scene_ratio(view_layer: bpy.types.ViewLayer, world: bpy.types.World | None) -> float | None:
    """The strongest rendered Sun's irradiance over half the World's on a
    surface facing up (the library's ``light_ratio``, at most
    :data:`MAX_RATIO`; see the module's notes), or None without a Sun or
    where the World does not say its light."""
    best = dominant_sun(view_layer)
    ambient = world_ambient(world)
    if best is None or ambient is None or not math.isfinite(ambient) or ambient <= 0:
        return None
    r = sun_irradiance(best[0]) / (0.5 * ambient)
    return min(r, MAX_RATIO) if math.isfinite(r) and r > 0 else None
