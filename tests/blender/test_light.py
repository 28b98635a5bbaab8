"""The light direction the extension passes for inserts' cast shadows (issue 19).

Scene Sun (the default): the strongest Sun light that renders, at each frame,
its world +Z axis (a Sun shines along its local -Z); Manual; Off. Checked
against Blender's own evaluation of the Sun at each frame, through a real
animation render, the sequence operator, and end to end: the classical
backend darkens the floor on the side of the inserted sphere away from the
Sun (the sphere is rendered without its shadow, as an inserted element often is).
"""

from __future__ import annotations

import math
import os

import bpy
import numpy as np
import pytest
from mathutils import Vector

import scene as fixture
from test_extension import configure, read_exr, render


def _sun_z(name: str = "Sun") -> np.ndarray:
    """The Sun's world +Z, normalized, as Blender has it now (main thread, after frame_set)."""
    m = bpy.data.objects[name].matrix_world
    z = np.array([m[0][2], m[1][2], m[2][2]], dtype=np.float64)
    return z / np.linalg.norm(z)


def _angle(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    c = np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))
    return math.degrees(math.acos(float(np.clip(c, -1.0, 1.0))))


def _small(scene) -> None:
    scene.render.resolution_x, scene.render.resolution_y = 32, 18
    scene.cycles.samples = 1


def _animated_sun_scene(out: str):
    """The fixture over frames 1-3, its Sun turning 50 degrees, plus lights that must not win."""
    scene = fixture.build(os.path.join(out, "raw", "frame_####.exr"), frames=(1, 3))
    _small(scene)
    sun = bpy.data.objects["Sun"]
    sun.rotation_euler = (math.radians(30), math.radians(10), math.radians(20))
    sun.keyframe_insert("rotation_euler", frame=1)
    sun.rotation_euler = (math.radians(60), math.radians(-20), math.radians(60))
    sun.keyframe_insert("rotation_euler", frame=3)
    # A weaker Sun, a stronger Sun disabled for renders, a stronger one in an
    # excluded collection, and a much stronger point light: none of them is the light.
    for name, energy, rot in (
        ("WeakSun", 1.0, (0, 0, 0)),
        ("OffSun", 50.0, (1.0, 0, 0)),
        ("HiddenSun", 50.0, (0, 1.0, 0)),
    ):
        data = bpy.data.lights.new(name, type="SUN")
        data.energy = energy
        obj = bpy.data.objects.new(name, data)
        obj.rotation_euler = rot
        if name == "HiddenSun":
            coll = bpy.data.collections.new("Excluded")
            scene.collection.children.link(coll)
            coll.objects.link(obj)
            scene.view_layers[0].layer_collection.children["Excluded"].exclude = True
        else:
            scene.collection.objects.link(obj)
        obj.hide_render = name == "OffSun"
    lamp = bpy.data.lights.new("Lamp", type="POINT")
    lamp.energy = 5000.0
    lamp_obj = bpy.data.objects.new("Lamp", lamp)
    lamp_obj.location = (1.0, -1.0, 3.0)
    scene.collection.objects.link(lamp_obj)
    return scene


def _animation_render_directions(addon, scene, toward) -> tuple:
    """Renders frames 1-3 of ``scene`` from frame 2 (an animation render
    starting elsewhere than its first frame) and checks that each frame
    passed ``toward()`` as evaluated at that frame (read back from the
    session after the frame). Returns (the run's log, what was wanted by
    frame)."""
    scene.frame_set(2)
    render(scene)
    log = addon.handlers.last_run(scene.name)
    assert not log.errors, log.errors
    assert [f["frame"] for f in log.frames] == [1, 2, 3]
    want = {}
    for f in (1, 2, 3):
        scene.frame_set(f)
        want[f] = toward()
    for entry in log.frames:
        f = entry["frame"]
        assert entry["light_direction"] is not None, entry
        np.testing.assert_allclose(entry["light_direction"], want[f], atol=1e-5, err_msg=f"frame {f}")
    return log, want


def test_scene_sun_is_passed_per_frame_of_an_animation_render(addon, tmp_root):
    out = os.path.join(tmp_root, "light_anim")
    scene = _animated_sun_scene(out)
    configure(scene, backend="bypass", output_path=os.path.join(out, "enhanced", "frame_####.exr"))
    assert scene.harmonizer.light_source == "AUTO"  # the default
    log, want = _animation_render_directions(addon, scene, _sun_z)
    assert _angle(want[1], want[3]) > 20.0, "the Sun does not turn: the test would not see a stale direction"
    for f in (1, 2, 3):
        _, attrs = read_exr(os.path.join(out, "enhanced", f"frame_{f:04d}.exr"))
        np.testing.assert_allclose(
            [float(c) for c in attrs["harmonizer/lightDirection"].split(",")], want[f], atol=1e-5
        )
    # The temporal state is kept across the changing light.
    assert [f["reset"] for f in log.frames] == ["first_frame", None, None]


def test_manual_and_off(addon, tmp_root):
    out = os.path.join(tmp_root, "light_manual")
    scene = fixture.build(os.path.join(out, "raw", "frame_####.exr"), frames=(1, 2))
    _small(scene)
    configure(
        scene,
        backend="bypass",
        output_path=os.path.join(out, "enhanced", "frame_####.exr"),
        light_source="MANUAL",
        light_direction=(0.0, -3.0, 4.0),
    )
    render(scene)
    log = addon.handlers.last_run(scene.name)
    assert not log.errors, log.errors
    for entry in log.frames:
        np.testing.assert_allclose(entry["light_direction"], [0.0, -0.6, 0.8], atol=1e-6)
    scene.harmonizer.light_source = "OFF"
    render(scene)
    log = addon.handlers.last_run(scene.name)
    assert [f["light_direction"] for f in log.frames] == [None, None]
    _, attrs = read_exr(os.path.join(out, "enhanced", "frame_0001.exr"))
    assert "harmonizer/lightDirection" not in attrs
    # No Sun at all: Scene Sun passes none.
    scene.harmonizer.light_source = "AUTO"
    bpy.data.objects.remove(bpy.data.objects["Sun"])
    render(scene)
    assert [f["light_direction"] for f in addon.handlers.last_run(scene.name).frames] == [None, None]


def _record_frames(addon, monkeypatch, what) -> dict:
    """Records ``what(processor, kw)`` after each frame the extension
    processes (the session's values then), by frame."""
    seen: dict = {}
    process = addon.processor.FrameProcessor.process

    def recording(self, raw_path, output_path, *, frame, **kw):
        result = process(self, raw_path, output_path, frame=frame, **kw)
        seen[frame] = what(self, kw)
        return result

    monkeypatch.setattr(addon.processor.FrameProcessor, "process", recording)
    return seen


def test_sequence_operator_reads_the_sun_at_each_files_frame(addon, tmp_root, monkeypatch):
    out = os.path.join(tmp_root, "light_seq")
    scene = _animated_sun_scene(out)
    configure(scene, backend="bypass", output_path=os.path.join(out, "enhanced", "frame_####.exr"))
    scene.harmonizer.enabled = False  # only render the raw frames
    render(scene)
    seen = _record_frames(
        addon, monkeypatch, lambda p, kw: (kw.get("light_direction"), p.session.get("light_direction"))
    )
    scene.frame_set(2)
    result = bpy.ops.harmonizer.enhance_sequence(
        directory=os.path.join(out, "raw"), output_directory=os.path.join(out, "seq")
    )
    assert result == {"FINISHED"}
    assert scene.frame_current == 2, "the operator did not put the scene's frame back"
    assert sorted(seen) == [1, 2, 3]
    for f in (1, 2, 3):
        scene.frame_set(f)
        passed, in_session = seen[f]
        np.testing.assert_allclose(passed, _sun_z(), atol=1e-6, err_msg=f"frame {f}")
        np.testing.assert_allclose([float(c) for c in in_session.split(",")], _sun_z(), atol=1e-5)


#: Toward the Sun in the end-to-end scene: from the front right, 30 degrees up.
SUN_TOWARD = Vector((0.8, -0.3, 0.5)).normalized()


def _shadow_scene(out: str, light_source: str):
    """The fixture's floor, a still inserted sphere (no shadow in the render) and one Sun."""
    scene = fixture.build(os.path.join(out, "raw", "frame_####.exr"), frames=(1, 2))
    for name in ("Cube", "Pillar"):
        bpy.data.objects.remove(bpy.data.objects[name])
    bpy.data.objects["InsertedSphere"].animation_data_clear()
    bpy.data.objects["InsertedSphere"].location = (0.3, -0.4, 0.6)
    cam = scene.camera
    cam.animation_data_clear()
    cam.location, cam.rotation_euler = (0.0, -7.5, 3.2), (math.radians(70), 0.0, 0.0)
    sun = bpy.data.objects["Sun"]
    sun.rotation_euler = SUN_TOWARD.to_track_quat("Z", "Y").to_euler()
    scene.view_layers[0].use_pass_object_index = True  # only to keep the windows off the sphere
    scene.cycles.samples = 16
    configure(
        scene,
        backend="classical",
        mask_source="COLLECTION",  # the Cryptomatte Object pass, as a user marks an insert
        mask_collection=bpy.data.collections["Inserted"],
        light_source=light_source,
        output_path=os.path.join(out, "enhanced", "frame_####.exr"),
    )
    return scene


def _ratio(raw, enh, w2n, point, half: int = 3) -> float:
    """Mean enhanced / raw luminance in a (2 half + 1)^2 window around the pixel of world ``point``."""
    h, w = raw["ViewLayer.Combined.R"].shape
    p = np.array([*point, 1.0]) @ w2n.astype(np.float64)
    x, y = int(p[0] / p[3] * w), int(p[1] / p[3] * h)
    assert half <= x < w - half and half <= y < h - half, (point, x, y)
    win = (slice(y - half, y + half + 1), slice(x - half, x + half + 1))
    assert (raw["ViewLayer.Object Index.X"][win] == 0).all(), f"window at {point} touches the insert"

    def lum(ch):
        return sum(k * ch[f"ViewLayer.Combined.{c}"][win] for k, c in zip((0.2126, 0.7152, 0.0722), "RGB"))

    return float(lum(enh).mean() / lum(raw).mean())


@pytest.fixture(scope="module")
def shadow_runs(addon, tmp_root):
    runs = {}
    for source in ("AUTO", "OFF"):
        out = os.path.join(tmp_root, "light_shadow", source)
        scene = _shadow_scene(out, source)
        render(scene)
        log = addon.handlers.last_run(scene.name)
        assert not log.errors, log.errors
        scene.frame_set(1)
        runs[source] = (out, log, addon.runtime.camera_matrices(scene)[1])
    return runs


def test_insert_casts_its_shadow_away_from_the_sun(shadow_runs):
    """Next to the sphere, the floor away from the Sun darkens; toward the Sun it does not.

    The sphere (radius 0.6, centre 0.6 above the floor) would cast an
    ellipse around G = C - (C.z / d.z) d (d toward the Sun). Windows of 7x7
    pixels: at G and 0.4 further from the Sun, and at the mirror of G
    through the sphere's foot (lit side). Off: no light, no cast shadow
    there (only the contact shadow right under the sphere).
    """
    c = Vector((0.3, -0.4, 0.6))
    g = c - (c.z / SUN_TOWARD.z) * SUN_TOWARD
    away = Vector((-SUN_TOWARD.x, -SUN_TOWARD.y, 0.0)).normalized()
    points = {
        "shadow": tuple(g),
        "shadow_far": tuple(g + 0.4 * away),
        "lit_side": (2 * c.x - g.x, 2 * c.y - g.y, 0.0),
    }
    ratios = {}
    for source, (out, log, w2n) in shadow_runs.items():
        assert [f["light_direction"] is not None for f in log.frames] == [source == "AUTO"] * 2
        raw, _ = read_exr(os.path.join(out, "raw", "frame_0002.exr"))
        enh, _ = read_exr(os.path.join(out, "enhanced", "frame_0002.exr"))
        ratios[source] = {k: _ratio(raw, enh, w2n, p) for k, p in points.items()}
    print(f"\nenhanced / raw luminance, frame 2: {ratios}")
    auto, off = ratios["AUTO"], ratios["OFF"]
    assert auto["shadow"] < 0.8 and auto["shadow_far"] < 0.85, auto
    assert auto["lit_side"] > 0.95, auto
    assert off["shadow"] > 0.95 and off["shadow_far"] > 0.95, off
    for k in points:  # the two runs differ only by the light
        assert auto[k] <= off[k] + 0.01, (k, auto, off)
    np.testing.assert_allclose(shadow_runs["AUTO"][1].frames[0]["light_direction"], SUN_TOWARD, atol=1e-5)


class _Layout:
    """Records what a panel's draw() puts in its layout (no UI headless)."""

    def __init__(self):
        self.props: list[str] = []
        self.labels: list[str] = []

    def column(self, **_kw):
        return self

    box = row = column

    def prop(self, _data, name, **_kw):
        self.props.append(name)

    def prop_search(self, _data, name, *_a, **_kw):
        self.props.append(name)

    def label(self, text="", **_kw):
        self.labels.append(text)

    def separator(self, **_kw):
        pass

    def operator(self, *_a, **_kw):
        pass


def _panel(addon, tmp_root: str, name: str):
    """A fixture scene with the extension enabled, and a function that draws
    its panel into a recording layout."""
    from types import SimpleNamespace

    scene = fixture.build(os.path.join(tmp_root, name, "frame_####.exr"))
    scene.harmonizer.enabled = True

    def draw() -> _Layout:
        layout = _Layout()
        addon.panel.RENDER_PT_harmonizer.draw(SimpleNamespace(layout=layout), bpy.context)
        return layout

    return scene, draw


def test_panel_shows_the_light(addon, tmp_root):
    scene, draw = _panel(addon, tmp_root, "light_panel")
    shown = draw()
    assert "light_source" in shown.props and "light_direction" not in shown.props
    assert "Sun (strength 3)" in shown.labels, shown.labels
    scene.harmonizer.light_source = "MANUAL"
    assert "light_direction" in draw().props
    scene.harmonizer.light_source = "AUTO"
    bpy.data.objects["Sun"].hide_render = True
    assert "No Sun light: no cast shadows" in draw().labels


def test_match_tone_reaches_the_session(addon, tmp_root):
    """The panel's Match Tone (shown once an insert mask is chosen, off by
    default) is the session's ``match_tone``."""
    scene, draw = _panel(addon, tmp_root, "match_tone")
    scene.harmonizer.mask_source = "NONE"
    assert "match_tone" not in draw().props
    scene.harmonizer.mask_source = "OBJECT_INDEX"
    assert "match_tone" in draw().props
    for want in (False, True):
        scene.harmonizer.match_tone = want
        runner = addon.runtime.Runner(scene)
        try:
            assert runner.session.get("match_tone") is want
        finally:
            runner.close()


def test_albedo_tone_reaches_the_session_and_asks_for_its_passes(addon, tmp_root):
    """Issue 19: the panel's Albedo Tone (shown once an insert mask is
    chosen, on by default) is the session's ``albedo_tone``; it reads the
    Denoising Data passes' albedo, which "Set Up Passes" / Enable Needed
    Passes switch on and whose absence the panel warns about."""
    scene, draw = _panel(addon, tmp_root, "albedo_tone")
    s = scene.harmonizer
    vl = addon.passes.render_view_layer(scene, s.view_layer)
    vl.cycles.denoising_store_passes = False
    s.mask_source = "NONE"
    assert "albedo_tone" not in draw().props
    assert not any("Albedo Tone" in t for _level, t in addon.passes.check(scene, apply=False))
    s.mask_source = "OBJECT_INDEX"
    assert s.albedo_tone and "albedo_tone" in draw().props
    assert "Albedo Tone reads the Denoising Data passes" in draw().labels
    msgs = addon.passes.check(scene, apply=False)
    assert any(level == "WARNING" and "Albedo Tone" in t for level, t in msgs), msgs
    assert not vl.cycles.denoising_store_passes
    msgs = addon.passes.check(scene, apply=True)
    assert vl.cycles.denoising_store_passes, msgs
    assert not any("Albedo Tone" in t for _level, t in addon.passes.check(scene, apply=False))
    # Off: no albedo asked for.
    vl.cycles.denoising_store_passes = False
    s.albedo_tone = False
    assert not any("Albedo Tone" in t for _level, t in addon.passes.check(scene, apply=False))
    for want in (False, True):
        s.albedo_tone = want
        runner = addon.runtime.Runner(scene)
        try:
            assert runner.session.get("albedo_tone") is want
        finally:
            runner.close()


def _insert_log_error(path: str, truth: np.ndarray) -> float:
    """Mean |log2| ratio of a frame's color to the truth's over the inserted
    sphere's fully covered pixels (its Object Index)."""
    chans, _ = read_exr(path)
    rgb = np.stack([chans[f"ViewLayer.Combined.{c}"] for c in "RGB"], -1)
    ins = chans["ViewLayer.Object Index.X"] == fixture.INSERT_PASS_INDEX
    # Its inner pixels: the edge's pixels mix in the background.
    ins[1:-1, 1:-1] &= ins[:-2, 1:-1] & ins[2:, 1:-1] & ins[1:-1, :-2] & ins[1:-1, 2:]
    ins[[0, -1], :] = False
    ins[:, [0, -1]] = False
    return float(np.abs(np.log2((rgb[ins] + 1e-3) / (truth[ins] + 1e-3))).mean())


def test_a_glowing_insert_is_brought_back_by_its_albedo(addon, tmp_root):
    """Issue 19, real Cycles: the inserted sphere rendered too bright (an
    emission of its own color, which its Denoising Albedo does not see)
    comes out of the extension closer to the sphere rendered without it,
    with Albedo Tone on (the default) and the Denoising Data passes the
    panel's check turned on; with Albedo Tone off it stays as rendered."""
    out = os.path.join(tmp_root, "albedo_tone_render")
    frames = (1, 3)
    truth_scene = fixture.build(os.path.join(out, "truth", "frame_####.exr"), samples=32, frames=frames)
    truth_scene.view_layers["ViewLayer"].use_pass_object_index = True
    truth_scene.harmonizer.enabled = False
    render(truth_scene)
    truths = []
    for f in range(frames[0], frames[1] + 1):
        chans, _ = read_exr(os.path.join(out, "truth", f"frame_{f:04d}.exr"))
        truths.append(np.stack([chans[f"ViewLayer.Combined.{c}"] for c in "RGB"], -1))
    errors = {}
    for name, on in (("on", True), ("off", False)):
        scene = fixture.build(os.path.join(out, name, "raw", "frame_####.exr"), samples=32, frames=frames)
        bsdf = bpy.data.materials["InsertedMat"].node_tree.nodes["Principled BSDF"]
        bsdf.inputs["Emission Color"].default_value = bsdf.inputs["Base Color"].default_value
        bsdf.inputs["Emission Strength"].default_value = 1.5
        configure(
            scene,
            backend="classical",
            denoise="off",
            mask_source="OBJECT_INDEX",
            mask_index=fixture.INSERT_PASS_INDEX,
            light_source="OFF",
            albedo_tone=on,
            output_path=os.path.join(out, name, "enhanced", "frame_####.exr"),
        )
        addon.passes.check(scene, apply=True)
        assert scene.view_layers["ViewLayer"].cycles.denoising_store_passes is on
        render(scene)
        log = addon.handlers.last_run(scene.name)
        assert not log.errors, log.errors
        for f, truth in zip(range(frames[0], frames[1] + 1), truths, strict=True):
            raw = _insert_log_error(os.path.join(out, name, "raw", f"frame_{f:04d}.exr"), truth)
            enh = _insert_log_error(os.path.join(out, name, "enhanced", f"frame_{f:04d}.exr"), truth)
            errors.setdefault(name, []).append((raw, enh))
    print(f"\ninsert error (stops), raw -> enhanced: {errors}")
    for raw, enh in errors["on"]:
        assert raw > 0.5 and enh < 0.6 * raw, errors
    for raw, enh in errors["off"]:
        assert abs(enh - raw) < 0.05 * raw, errors


def _session_ratio(addon, scene) -> float:
    return float(_session_light(addon, scene)[0])


def _session_light(addon, scene) -> tuple[float, list[float] | None, list[float] | None]:
    """The session's ``light_ratio``, ``light_color`` and ``ambient_color``
    (None: unset)."""
    runner = addon.runtime.Runner(scene)
    try:
        colors = [runner.session.get(k) for k in ("light_color", "ambient_color")]
        rgb = [[float(v) for v in c.split(",")] if c else None for c in colors]
        return float(runner.session.get("light_ratio")), rgb[0], rgb[1]
    finally:
        runner.close()


def test_sun_to_sky_reaches_the_session(addon, tmp_root):
    """Issue 19: the session's ``light_ratio`` is the Sun's irradiance over
    half the World's where the World says its light (a color, an environment
    image), the panel's Sun to Sky when set, and unset (0: the library
    measures it) for a Sky Texture or with the Light off."""
    scene, draw = _panel(addon, tmp_root, "sun_to_sky")
    s = scene.harmonizer
    # The fixture: a Sun of strength 3 (white) under a World of color
    # (0.25, 0.35, 0.55) at strength 0.6.
    world_lum = 0.2126 * 0.25 + 0.7152 * 0.35 + 0.0722 * 0.55
    want = 3.0 / (0.5 * math.pi * 0.6 * world_lum)
    ratio, light_color, ambient_color = _session_light(addon, scene)
    assert ratio == pytest.approx(want, rel=1e-5)
    # The lights themselves: the Sun's strength times its color, half the
    # World's irradiance on a surface facing up.
    assert light_color == pytest.approx([3.0, 3.0, 3.0], rel=1e-5)
    assert ambient_color == pytest.approx([0.5 * math.pi * 0.6 * c for c in (0.25, 0.35, 0.55)], rel=1e-5)
    assert f"Sun to Sky {want:.2f} (Sun and World)" in draw().labels
    assert "light_ratio" in draw().props

    # An environment image: its upper half gives the light (cosine-weighted),
    # the lower half (below the horizon) none.
    img = bpy.data.images.new("sky_probe", 64, 32, float_buffer=True)
    px = np.zeros((32, 64, 4), np.float32)
    px[..., 3] = 1.0
    px[16:, :, :3] = 0.5  # rows from the bottom: the upper half
    img.pixels.foreach_set(px.ravel())
    nt = scene.world.node_tree
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = img
    nt.links.new(env.outputs["Color"], nt.nodes["Background"].inputs["Color"])
    got, _, ambient_color = _session_light(addon, scene)
    assert got == pytest.approx(3.0 / (0.5 * math.pi * 0.6 * 0.5), rel=0.01)
    assert ambient_color == pytest.approx([0.5 * math.pi * 0.6 * 0.5] * 3, rel=0.01)

    # A Sky Texture does not say its light: the library measures it.
    sky = nt.nodes.new("ShaderNodeTexSky")
    nt.links.new(sky.outputs["Color"], nt.nodes["Background"].inputs["Color"])
    assert _session_ratio(addon, scene) == 0.0
    assert "Sun to Sky: measured from each frame" in draw().labels
    assert _session_light(addon, scene)[1:] == (None, None)
    # The user's value wins (without colors: none measured); with the Light
    # off, nothing is passed.
    s.light_ratio = 2.5
    assert _session_light(addon, scene) == (pytest.approx(2.5), None, None)
    s.light_ratio = 0.0
    nt.links.new(env.outputs["Color"], nt.nodes["Background"].inputs["Color"])
    s.light_source = "OFF"
    assert _session_ratio(addon, scene) == 0.0
    assert "light_ratio" not in draw().props


def test_sun_to_sky_is_what_cycles_renders(addon, tmp_root):
    """The ratio's units are Cycles': a white diffuse floor under the Sun
    alone (overhead) against under the World alone renders half the ratio
    the extension passes (its ambient is half the sky's)."""
    scene = fixture.build(os.path.join(tmp_root, "sun_to_sky_probe", "frame_####.exr"))
    want = _session_ratio(addon, scene)
    probe = bpy.data.scenes.new("sun_to_sky_probe")
    probe.render.engine = "CYCLES"
    probe.cycles.device = "CPU"
    probe.cycles.samples = 64
    probe.render.resolution_x = probe.render.resolution_y = 16
    probe.view_settings.view_transform = "Standard"
    probe.render.image_settings.file_format = "OPEN_EXR"
    mesh = bpy.data.meshes.new("floor")
    mesh.from_pydata([(-4, -4, 0), (4, -4, 0), (4, 4, 0), (-4, 4, 0)], [], [(0, 1, 2, 3)])
    mat = bpy.data.materials.new("white")
    mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    diffuse = nt.nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(diffuse.outputs["BSDF"], out.inputs["Surface"])
    mesh.materials.append(mat)
    probe.collection.objects.link(bpy.data.objects.new("floor", mesh))
    cam = bpy.data.cameras.new("top")
    cam.type = "ORTHO"
    cam.ortho_scale = 2.0
    cam_obj = bpy.data.objects.new("top", cam)
    cam_obj.location = (0.0, 0.0, 5.0)
    probe.collection.objects.link(cam_obj)
    probe.camera = cam_obj
    sun = bpy.data.objects.new("probe_sun", bpy.data.objects["Sun"].data.copy())
    probe.collection.objects.link(sun)  # rotation 0: straight down

    def mean_luminance(world, with_sun: bool, name: str) -> float:
        probe.world = world
        sun.hide_render = not with_sun
        probe.render.filepath = os.path.join(tmp_root, "sun_to_sky_probe", f"{name}.exr")
        assert bpy.ops.render.render(write_still=True, scene=probe.name) == {"FINISHED"}
        chans, _ = read_exr(probe.render.filepath)
        rgb = [next(v for k, v in chans.items() if k.split(".")[-1] == c) for c in "RGB"]
        return float(np.mean(0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]))

    # Blender 5.0 renders a World's nodes (a new World's Background is a
    # grey of 0.05): black through its Background.
    black = bpy.data.worlds.new("black")
    black.use_nodes = True
    black.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    sun_alone = mean_luminance(black, True, "sun")
    sky_alone = mean_luminance(scene.world, False, "sky")
    assert 2.0 * sun_alone / sky_alone == pytest.approx(want, rel=0.03), (sun_alone, sky_alone, want)


def _sky(scene, disc: bool, elevation: float = 38.0, rotation: float = 150.0):
    """The fixture's World lit by a Sky Texture (Blender 5.0's default
    Multiple Scattering) at strength 0.35, its sun at ``elevation`` and
    ``rotation`` (degrees)."""
    nt = scene.world.node_tree
    sky = nt.nodes.new("ShaderNodeTexSky")
    sky.sun_disc = disc
    sky.sun_elevation = math.radians(elevation)
    sky.sun_rotation = math.radians(rotation)
    bg = nt.nodes["Background"]
    bg.inputs["Strength"].default_value = 0.35
    nt.links.new(sky.outputs["Color"], bg.inputs["Color"])
    return sky


def _blocks() -> dict[str, int]:
    """Data-blocks by kind (Blender's own Render Result image aside)."""
    got = {k: len(getattr(bpy.data, k)) for k in ("scenes", "objects", "meshes", "materials", "cameras", "worlds")}
    got["images"] = sum(1 for i in bpy.data.images if i.type != "RENDER_RESULT")
    return got


def test_a_sky_texture_s_sun_gives_the_direction(addon, tmp_root):
    """Issue 19: without a Sun light, the World's Sky Texture's sun disc is
    the light: the direction passed is the one Cycles lights from (a white
    square facing it gets more light than one turned 10 degrees in any of
    four ways); none with the disc off or the sun below the horizon; a Sun
    light wins over the sky."""
    scene, draw = _panel(addon, tmp_root, "sky_sun")
    sun = bpy.data.objects["Sun"]
    sun.hide_render = True
    sky = _sky(scene, disc=True)
    runner = addon.runtime.Runner(scene)
    try:
        got = runner.light_at(scene)
        assert got is not None
        assert any(t.startswith("Sky Texture sun (elevation 38.0") for t in draw().labels), draw().labels
        probe = addon.light._Probe()
        try:
            facing = probe.irradiance(scene.world, got)
            d = Vector(got)
            side = d.cross(Vector((0.0, 0.0, 1.0))).normalized()
            up = side.cross(d).normalized()
            turned = []
            for axis in (side, -side, up, -up):
                v = (d * math.cos(math.radians(10)) + axis * math.sin(math.radians(10))).normalized()
                turned.append(probe.irradiance(scene.world, tuple(v)))
        finally:
            probe.close()
        print(f"\nsky sun: facing {facing:.3f}, turned 10 degrees {[round(t, 3) for t in turned]}")
        assert all(t < facing for t in turned), (facing, turned)
        # The disc's light is most of it: a cosine of 10 degrees takes 1.5 % off.
        assert all(t < 0.995 * facing for t in turned), (facing, turned)

        sky.sun_disc = False
        assert runner.light_at(scene) is None
        sky.sun_disc = True
        sky.sun_elevation = math.radians(-2.0)
        assert runner.light_at(scene) is None
        sky.sun_elevation = math.radians(38.0)
        sun.hide_render = False
        assert _angle(runner.light_at(scene), _sun_z()) < 1e-4
    finally:
        runner.close()


def test_the_courtyard_s_light_as_the_benchmark_passes_it(addon, tmp_root):
    """Issue 19: the out-of-domain courtyard's light (its Sky Texture World
    and Sun, built by the benchmark's own renderer) measured by the
    extension gives the ``light_color`` and ``ambient_color`` the benchmark
    passes as the host's (``training.ood.sequences.COURTYARD_SKY_UP``); the
    Measure button stores them and the session gets them with the panel's
    Sun to Sky, until that is edited by hand."""
    import json
    import sys

    root = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
    if root not in sys.path:
        sys.path.insert(0, root)
    from training.ood import render as ood_render
    from training.ood import sequences

    with open(os.path.join(root, "training", "ood", "data", "courtyard", "meta.json")) as f:
        meta = json.load(f)
    lit = meta["light"]
    scene, _ = _panel(addon, tmp_root, "courtyard_light")
    ood_render.set_sky(lit["sun_elev"], lit["sun_azim"], lit["sky"])
    scene.world = bpy.data.worlds["World"]
    ood_render.set_sun(bpy.data.objects["Sun"], lit["sun_elev"], lit["sun_azim"], lit["sun_energy"], lit["sun_color"])
    vl = scene.view_layers["ViewLayer"]
    assert addon.light.scene_light(vl, scene.world) is None  # a Sky Texture: rendered only
    got = addon.light.measure_ratio(vl, scene.world)
    print(f"\ncourtyard: {got}")
    assert got.direct_rgb == pytest.approx([lit["sun_energy"] * c for c in lit["sun_color"]], rel=1e-5)
    assert got.ambient_rgb == pytest.approx(sequences.COURTYARD_SKY_UP, rel=0.03)
    assert got.ratio == pytest.approx(2.0, rel=0.03)
    s = sequences.build("insert_recon", frames=1)
    host = s["host_params"]
    for name in ("light_color", "ambient_color"):
        want = [float(v) for v in host[name].split(",")]
        have = [float(v) for v in got.params()[name].split(",")]
        assert have == pytest.approx(want, rel=0.03), (name, have, want)

    # The Measure button stores the colors; the session gets them with the
    # panel's value, and not once the value is edited by hand.
    assert bpy.ops.harmonizer.measure_light_ratio() == {"FINISHED"}
    assert tuple(scene.harmonizer.measured_ambient_color) == pytest.approx(got.ambient_rgb, rel=0.03)
    runner = addon.runtime.Runner(scene)
    try:
        colors = [float(v) for v in runner.session.get("ambient_color").split(",")]
        assert colors == pytest.approx([0.5 * c for c in got.ambient_rgb], rel=0.03)
        assert runner.session.get("light_color") != ""
    finally:
        runner.close()
    scene.harmonizer.light_ratio = 3.0
    runner = addon.runtime.Runner(scene)
    try:
        assert runner.session.get("light_ratio") == pytest.approx(3.0)
        assert runner.session.get("ambient_color") == "" and runner.session.get("light_color") == ""
    finally:
        runner.close()


def test_sun_to_sky_measured_by_cycles(addon, tmp_root):
    """Issue 19: *Measure Sun to Sky* renders the ratio for any World. Where
    the World says its light (a color, an environment image) it agrees with
    the ratio read from it; a Sky Texture under a Sun light, which cannot be
    read, gets its own; a Sky Texture's sun disc alone gives its light
    (nothing on a surface facing away); nothing is left behind."""
    scene, draw = _panel(addon, tmp_root, "sun_to_sky_measured")
    vl = scene.view_layers["ViewLayer"]
    before = _blocks()
    got = addon.light.measure_ratio(vl, scene.world)
    want = addon.light.scene_ratio(vl, scene.world)
    assert got.source == "Sun light 'Sun'"
    assert got.ratio == pytest.approx(want, rel=0.03), (got, want)

    img = bpy.data.images.new("sky_probe", 64, 32, float_buffer=True)
    px = np.zeros((32, 64, 4), np.float32)
    px[..., 3] = 1.0
    px[16:, :, :3] = 0.5
    px[16:, :8, :3] = 3.0  # a bright patch: not uniform in azimuth
    img.pixels.foreach_set(px.ravel())
    nt = scene.world.node_tree
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = img
    nt.links.new(env.outputs["Color"], nt.nodes["Background"].inputs["Color"])
    got = addon.light.measure_ratio(vl, scene.world)
    want = addon.light.scene_ratio(vl, scene.world)
    assert got.ratio == pytest.approx(want, rel=0.03), (got, want)
    before["images"] += 1

    sky = _sky(scene, disc=False)
    assert addon.light.scene_ratio(vl, scene.world) is None
    assert "Sun to Sky: measured from each frame" in draw().labels
    assert bpy.ops.harmonizer.measure_light_ratio() == {"FINISHED"}
    measured = scene.harmonizer.light_ratio
    again = addon.light.measure_ratio(vl, scene.world)
    print(f"\nSky Texture under the Sun: {again}")
    assert measured == pytest.approx(again.ratio, rel=0.03)
    assert _session_ratio(addon, scene) == pytest.approx(measured)
    scene.harmonizer.light_ratio = 0.0
    runner = addon.runtime.Runner(scene, measure_light=True)
    try:
        assert runner.light_ratio == pytest.approx(measured, rel=0.03)
        assert (
            "INFO",
            f"Harmonizer: Sun to Sky {runner.light_ratio:.2f} (rendered: Sun light 'Sun' over the World)",
        ) in runner.notes
    finally:
        runner.close()

    # The sky's own sun: the disc's light on a surface facing it, none facing away.
    bpy.data.objects["Sun"].hide_render = True
    sky.sun_disc = True
    disc = addon.light.measure_ratio(vl, scene.world)
    assert disc.source == f"Sky Texture '{sky.name}'" and disc.ratio > 1.0, disc
    toward = addon.light.sky_sun_direction(sky)
    probe = addon.light._Probe()
    try:
        away = tuple(-c for c in toward)
        bare = probe.without_discs(scene.world)
        on, off = probe.irradiance(scene.world, away), probe.irradiance(bare, away)
    finally:
        probe.close()
    assert abs(on - off) < 0.02 * disc.direct, (on, off, disc)
    assert _blocks() == before

    # Without any direct light there is nothing to measure.
    sky.sun_disc = False
    assert addon.light.measure_ratio(vl, scene.world) is None
    assert bpy.ops.harmonizer.measure_light_ratio() == {"CANCELLED"}


def test_sequence_operator_renders_the_sky_s_light(addon, tmp_root, monkeypatch):
    """The sequence operator (not a render handler: it may render) passes a
    Sky Texture's sun as the light and its Sun to Sky as Cycles renders it;
    a render's own session, which cannot, leaves the ratio to the library."""
    out = os.path.join(tmp_root, "sky_seq")
    scene = fixture.build(os.path.join(out, "raw", "frame_####.exr"), frames=(1, 2))
    _small(scene)
    bpy.data.objects["Sun"].hide_render = True
    sky = _sky(scene, disc=True, elevation=30.0, rotation=200.0)
    configure(scene, backend="bypass", output_path=os.path.join(out, "enhanced", "frame_####.exr"))
    scene.harmonizer.enabled = False  # only render the raw frames
    render(scene)
    seen = _record_frames(
        addon, monkeypatch, lambda p, _kw: (p.session.get("light_direction"), float(p.session.get("light_ratio")))
    )
    result = bpy.ops.harmonizer.enhance_sequence(
        directory=os.path.join(out, "raw"), output_directory=os.path.join(out, "seq")
    )
    assert result == {"FINISHED"}
    want = addon.light.measure_ratio(scene.view_layers["ViewLayer"], scene.world)
    assert want is not None and want.source == f"Sky Texture '{sky.name}'"
    assert sorted(seen) == [1, 2]
    for direction, ratio in seen.values():
        assert _angle([float(c) for c in direction.split(",")], addon.light.sky_sun_direction(sky)) < 1e-3
        assert ratio == pytest.approx(want.ratio, rel=0.03), (ratio, want)
    assert _session_ratio(addon, scene) == 0.0


def _env_world(scene, name: str, px: np.ndarray, mapping: tuple[str, tuple, tuple] | None = None):
    """The fixture's World lit by an equirectangular image (rows from the
    bottom, RGBA) at strength 1; ``mapping``: (type, rotation in degrees,
    location) of a Mapping node fed by the Generated coordinates."""
    img = bpy.data.images.new(name, px.shape[1], px.shape[0], float_buffer=True)
    img.pixels.foreach_set(px.ravel())
    world = scene.world.copy()
    nt = world.node_tree
    env = nt.nodes.new("ShaderNodeTexEnvironment")
    env.image = img
    bg = nt.nodes["Background"]
    bg.inputs["Strength"].default_value = 1.0
    nt.links.new(env.outputs["Color"], bg.inputs["Color"])
    if mapping is not None:
        kind, rotation, location = mapping
        coords = nt.nodes.new("ShaderNodeTexCoord")
        node = nt.nodes.new("ShaderNodeMapping")
        node.vector_type = kind
        node.inputs["Rotation"].default_value = tuple(math.radians(a) for a in rotation)
        node.inputs["Location"].default_value = location
        nt.links.new(coords.outputs["Generated"], node.inputs["Vector"])
        nt.links.new(node.outputs["Vector"], env.inputs["Vector"])
    return world


def _image_sun_direct(addon, world, plain_world, toward) -> tuple[float, list[float]]:
    """Cycles' light from an image's sun alone (the World less the same
    without its sun) on a white square facing ``toward`` and turned 10
    degrees from it in four ways."""
    probe = addon.light._Probe()
    try:

        def direct(v) -> float:
            return probe.irradiance(world, v) - probe.irradiance(plain_world, v)

        d = Vector(toward)
        side = d.cross(Vector((0.0, 0.0, 1.0))).normalized()
        up = side.cross(d).normalized()
        turned = [
            direct(tuple((d * math.cos(math.radians(10)) + a * math.sin(math.radians(10))).normalized()))
            for a in (side, -side, up, -up)
        ]
        return direct(toward), turned
    finally:
        probe.close()


def _sky_images() -> tuple[np.ndarray, np.ndarray]:
    """Two 128x64 World images (RGBA, rows from the bottom): a sky of 0.4
    over a ground of 0.1, and the same with a 2x2 sun of 400 at elevation
    pi * (45 / 64 - 0.5) (36.6 degrees)."""
    h, w = 64, 128
    plain = np.zeros((h, w, 4), np.float32)
    plain[..., 3] = 1.0
    plain[h // 2 :, :, :3] = 0.4
    plain[: h // 2, :, :3] = 0.1
    sunny = plain.copy()
    sunny[44:46, 80:82, :3] = 400.0
    return plain, sunny


def test_the_sun_in_the_world_s_image_is_the_light(addon, tmp_root):
    """Issue 19: an environment image with a sun and no Sun light: the
    direction passed is the one Cycles lights from (a white square facing it
    gets more light than one turned 10 degrees in any of four ways), and Sun
    to Sky is the sun's irradiance over half the rest of the sky's, as
    Cycles renders them (the image with and without its sun); the same image
    without its sun has none; a Sun light wins."""
    scene, draw = _panel(addon, tmp_root, "env_sun")
    vl = scene.view_layers["ViewLayer"]
    bpy.data.objects["Sun"].hide_render = True
    plain, sunny = _sky_images()
    scene.world = _env_world(scene, "plain", plain)
    plain_world = scene.world
    assert addon.light.env_sun(plain_world) is None
    scene.world = _env_world(scene, "sunny", sunny)
    runner = addon.runtime.Runner(scene)
    try:
        got = runner.light_at(scene)
    finally:
        runner.close()
    assert got is not None
    assert math.degrees(math.asin(got[2])) == pytest.approx(180.0 * (45 / 64 - 0.5), abs=0.5)
    assert any(t.startswith("Environment image sun (elevation 36.") for t in draw().labels), draw().labels
    ratio = addon.light.scene_ratio(vl, scene.world)
    assert ratio is not None and f"Sun to Sky {ratio:.2f} (Sun and World)" in draw().labels
    facing, turned = _image_sun_direct(addon, scene.world, plain_world, got)
    probe = addon.light._Probe()
    try:
        ambient = probe.irradiance(plain_world, (0.0, 0.0, 1.0))
    finally:
        probe.close()
    rendered = facing / (0.5 * ambient)
    print(f"\nimage sun: direct facing {facing:.3f}, turned {[round(t, 3) for t in turned]}; ratio {ratio:.3f}, rendered {rendered:.3f}")
    assert all(t < 0.995 * facing for t in turned), (facing, turned)
    assert ratio == pytest.approx(rendered, rel=0.05)
    # The image without its sun: none (the library measures it).
    scene.world = plain_world
    runner = addon.runtime.Runner(scene)
    try:
        assert runner.light_at(scene) is None
    finally:
        runner.close()
    # A Sun light wins the direction.
    bpy.data.objects["Sun"].hide_render = False
    runner = addon.runtime.Runner(scene)
    try:
        assert _angle(runner.light_at(scene), _sun_z()) < 1e-4
    finally:
        runner.close()


def test_a_world_image_turned_by_a_mapping_node(addon, tmp_root):
    """A World's image turned by a Mapping node (Generated coordinates, the
    usual way to turn an HDRI): the sun's direction turns with it, for the
    Point and the Texture (inverse) types, as Cycles lights it; a Mapping
    with a location is not read (no direction, no Sun to Sky)."""
    scene, _draw = _panel(addon, tmp_root, "env_mapping")
    vl = scene.view_layers["ViewLayer"]
    bpy.data.objects["Sun"].hide_render = True
    plain, sunny = _sky_images()
    unturned = None
    for kind, rotation in (("POINT", (0.0, 0.0, 0.0)), ("POINT", (20.0, 0.0, 90.0)), ("TEXTURE", (20.0, 0.0, 90.0))):
        mapping = (kind, rotation, (0.0, 0.0, 0.0))
        scene.world = _env_world(scene, f"sunny_{kind}", sunny, mapping)
        plain_world = _env_world(scene, f"plain_{kind}", plain, mapping)
        got = addon.light.scene_direction(vl, None, scene.world)
        assert got is not None, (kind, rotation)
        if unturned is None:
            unturned = got
        else:
            assert _angle(got, unturned) > 30.0, (kind, rotation, got, unturned)
        facing, turned = _image_sun_direct(addon, scene.world, plain_world, got)
        print(f"\n{kind} {rotation}: toward {np.round(got, 3)}, direct facing {facing:.3f}, turned {[round(t, 3) for t in turned]}")
        assert all(t < 0.995 * facing for t in turned), (kind, rotation, facing, turned)
        assert addon.light.scene_ratio(vl, scene.world) is not None
    scene.world = _env_world(scene, "sunny_moved", sunny, ("POINT", (0.0, 0.0, 90.0), (0.1, 0.0, 0.0)))
    assert addon.light.scene_direction(vl, None, scene.world) is None
    assert addon.light.scene_ratio(vl, scene.world) is None


def test_an_animated_sky_sun_is_passed_per_frame_of_an_animation_render(addon, tmp_root):
    """A Sky Texture's sun turning over an animation render (its rotation
    keyframed, no Sun light): each frame passes its own direction, read
    from the World evaluated at the frame being rendered."""
    out = os.path.join(tmp_root, "sky_anim")
    scene = fixture.build(os.path.join(out, "raw", "frame_####.exr"), frames=(1, 3))
    _small(scene)
    bpy.data.objects["Sun"].hide_render = True
    sky = _sky(scene, disc=True, elevation=35.0, rotation=0.0)
    sky.sun_rotation = math.radians(0.0)
    sky.keyframe_insert("sun_rotation", frame=1)
    sky.sun_rotation = math.radians(60.0)
    sky.keyframe_insert("sun_rotation", frame=3)
    configure(scene, backend="bypass", output_path=os.path.join(out, "enhanced", "frame_####.exr"))
    _, want = _animation_render_directions(
        addon, scene, lambda: addon.light.sky_sun_direction(scene.world.node_tree.nodes[sky.name])
    )
    assert _angle(want[1], want[3]) > 30.0


def test_a_world_image_file_is_read_once_per_version(addon, tmp_root):
    """A World image from a file is read once (the panel draws often; an 8k
    image takes seconds) and again when the file changes."""
    h, w = 32, 64
    path = os.path.join(tmp_root, "world_image", "sky.exr")
    os.makedirs(os.path.dirname(path), exist_ok=True)

    def write(col: int) -> None:
        px = np.zeros((h, w, 4), np.float32)
        px[..., 3] = 1.0
        px[h // 2 :, :, :3] = 0.3
        px[22:24, col : col + 2, :3] = 300.0
        img = bpy.data.images.new("sky_writer", w, h, float_buffer=True)
        img.pixels.foreach_set(px.ravel())
        img.filepath_raw = path
        img.file_format = "OPEN_EXR"
        img.save()
        bpy.data.images.remove(img)

    write(10)
    image = bpy.data.images.load(path, check_existing=False)
    first = addon.light.env_light(image)
    assert first is not None and first.sun is not None
    assert len(addon.light._ENV_CACHE) == 1 and next(iter(addon.light._ENV_CACHE))[-3] == "file"
    assert addon.light.env_light(image) == first
    st = os.stat(path)
    write(40)  # the sun elsewhere; the file's time moves on
    os.utime(path, (st.st_atime, st.st_mtime + 5.0))
    image.reload()
    second = addon.light.env_light(image)
    assert second is not None and second.sun is not None
    assert _angle(first.sun, second.sun) > 90.0, (first.sun, second.sun)


def test_a_background_render_measures_the_sky_s_sun_to_sky(addon, tmp_root, monkeypatch):
    """A background render (``blender -b``, as here) of a World whose light
    cannot be read (a Sky Texture under a Sun) renders its Sun to Sky when
    it starts and passes it on every frame; the panel's value wins."""
    out = os.path.join(tmp_root, "sky_render")
    scene = fixture.build(os.path.join(out, "raw", "frame_####.exr"), frames=(1, 2))
    _small(scene)
    _sky(scene, disc=False)
    configure(scene, backend="bypass", output_path=os.path.join(out, "enhanced", "frame_####.exr"))
    assert addon.light.scene_ratio(scene.view_layers["ViewLayer"], scene.world) is None
    want = addon.light.measure_ratio(scene.view_layers["ViewLayer"], scene.world)
    passed = _record_frames(addon, monkeypatch, lambda p, _kw: float(p.session.get("light_ratio")))
    addon.reports.RECENT.clear()  # a bounded deque: what this render posts
    render(scene)
    log = addon.handlers.last_run(scene.name)
    assert not log.errors, log.errors
    assert [f["frame"] for f in log.frames] == [1, 2]
    posted = [t for _l, t in addon.reports.RECENT]
    seen = [t for t in posted if t.startswith("Harmonizer: Sun to Sky ")]
    assert seen and "(rendered: Sun light 'Sun' over the World)" in seen[0], posted
    assert sorted(passed) == [1, 2]
    assert all(r == pytest.approx(want.ratio, rel=0.03) for r in passed.values()), (passed, want)
    # The panel's value wins, and nothing is rendered for it.
    scene.harmonizer.light_ratio = 2.5
    render(scene)
    assert all(r == pytest.approx(2.5) for r in passed.values()), passed
