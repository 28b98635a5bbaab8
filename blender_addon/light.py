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
