"""The harmonizer Blender extension in real Blender 5.0.1 (bpy), headless (issue 4).

Renders are Cycles on the CPU, 160x90, 4 samples (see scene.py).
"""

from __future__ import annotations

import math
import os
import shutil

import bpy
import numpy as np
import pytest

import scene as fixture
from conftest import ADDON_MODULE

FRAMES = list(range(fixture.FRAMES[0], fixture.FRAMES[1] + 1))
COLOR = [f"ViewLayer.Combined.{c}" for c in "RGBA"]


def _oiio():
    from bl_ext.hztest.harmonizer import deps  # the module Blender imported from the zip

    return deps.oiio()


def read_exr(path: str) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Every channel of every part (by full name) and the first part's string attributes."""
    oiio = _oiio()
    inp = oiio.ImageInput.open(path)
    assert inp is not None, f"{path}: {oiio.geterror()}"
    chans: dict[str, np.ndarray] = {}
    attrs: dict[str, str] = {}
    k = 0
    while inp.seek_subimage(k, 0):
        spec = inp.spec(k, 0)
        px = inp.read_image(k, 0, 0, spec.nchannels, oiio.FLOAT).reshape(spec.height, spec.width, spec.nchannels)
        for ci, name in enumerate(spec.channelnames):
            chans[name] = np.array(px[:, :, ci])
        if k == 0:
            attrs = {a.name: str(a.value) for a in spec.extra_attribs}
        k += 1
    inp.close()
    return chans, attrs


def configure(scene, **settings):
    s = scene.harmonizer
    s.enabled = True
    for k, v in settings.items():
        setattr(s, k, v)


def render(scene):
    assert bpy.ops.render.render(animation=True) == {"FINISHED"}


def handlers_of(module_name: str) -> int:
    lists = (
        bpy.app.handlers.render_init,
        bpy.app.handlers.frame_change_post,
        bpy.app.handlers.render_write,
        bpy.app.handlers.render_complete,
        bpy.app.handlers.render_cancel,
    )
    return sum(1 for lst in lists for fn in lst if getattr(fn, "__module__", "").startswith(module_name))


@pytest.fixture(scope="module")
def classical_run(addon, tmp_root):
    """The 8-frame animation rendered with the extension on (classical backend, inserted collection)."""
    out = os.path.join(tmp_root, "classical")
    scene = fixture.build(os.path.join(out, "raw", "frame_####.exr"))
    # Passes off and a PNG output: the extension has to set them up itself.
    vl = scene.view_layers[0]
    vl.use_pass_z = vl.use_pass_vector = vl.use_pass_normal = False
    vl.use_pass_object_index = True  # only to cross-check the Cryptomatte insert mask
    scene.render.image_settings.media_type = "IMAGE"
    scene.render.image_settings.file_format = "PNG"
    configure(
        scene,
        backend="classical",
        mask_source="COLLECTION",
        mask_collection=bpy.data.collections["Inserted"],
        output_path=os.path.join(out, "enhanced", "frame_####.exr"),
    )
    render(scene)
    log = addon.handlers.last_run(scene.name)
    return scene, out, log


def test_installed_from_zip_and_registered(addon):
    assert addon.__name__ == ADDON_MODULE
    # The binding and libharmonizer come from the wheel in the zip, not from the source tree.
    import harmonizer

    assert "extensions" in harmonizer.__file__ or "hz-blender-test" in harmonizer.__file__, harmonizer.__file__
    assert harmonizer.version()
    assert hasattr(bpy.types.Scene, "harmonizer")
    assert hasattr(bpy.ops.harmonizer, "enhance_sequence")
    assert handlers_of(ADDON_MODULE) == 5
    ort = addon.deps.onnxruntime_library()
    assert ort is not None and os.path.isfile(ort), "onnxruntime wheel from the zip not installed"


def test_every_frame_enhanced_with_every_pass_kept(classical_run):
    scene, out, log = classical_run
    assert log is not None and not log.errors, log.errors if log else "no run"
    assert [f["frame"] for f in log.frames] == FRAMES
    for frame in FRAMES:
        raw_path = os.path.join(out, "raw", f"frame_{frame:04d}.exr")
        enh_path = os.path.join(out, "enhanced", f"frame_{frame:04d}.exr")
        assert os.path.isfile(enh_path), enh_path
        raw, _ = read_exr(raw_path)
        enh, attrs = read_exr(enh_path)
        # The extension enabled the passes it needs, and every channel of the raw file is kept.
        for needed in ("ViewLayer.Depth.Z", "ViewLayer.Vector.X", "ViewLayer.Normal.X", "ViewLayer.CryptoObject00.r"):
            assert needed in raw, (raw_path, needed)
        # Each pass holds its own data (planar depth of the scene, not a copy of the color).
        depth = raw["ViewLayer.Depth.Z"]
        assert 2.0 < np.median(depth) < 30.0, np.median(depth)
        assert not np.array_equal(depth, raw["ViewLayer.Combined.R"])
        assert list(enh) == list(raw)
        for name in raw:
            if name not in COLOR:
                np.testing.assert_array_equal(enh[name], raw[name], err_msg=f"{enh_path}: {name} changed")
        rgb = np.stack([enh[c] for c in COLOR[:3]], -1)
        assert np.isfinite(rgb).all()
        assert attrs["harmonizer/frame"] == str(frame)
        assert attrs["harmonizer/backend"] == "classical"
    # The raw render is kept as Blender wrote it (multilayer EXR set by the extension).
    assert scene.render.image_settings.file_format == "OPEN_EXR_MULTILAYER"


def test_temporal_state_within_a_render(classical_run):
    _scene, _out, log = classical_run
    resets = [f["reset"] for f in log.frames]
    assert resets[0] == "first_frame"
    assert all(r is None for r in resets[1:]), resets
    assert [f["history_used"] for f in log.frames][-1] >= 1
    ms = [f["ms"] for f in log.frames]
    print(
        f"\nclassical backend, 160x90, per frame (read + enhance + write): {np.mean(ms):.1f} ms mean, {max(ms):.1f} max"
    )


def test_node_group_feeds_enhanced_frames_through_compositor(addon, classical_run, tmp_root):
    scene, out, _log = classical_run
    scene.harmonizer.enabled = False  # only the compositor runs now
    tree = bpy.data.node_groups.new("Compositing", "CompositorNodeTree")
    tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    scene.compositing_node_group = tree
    group_node = addon.nodes.add_to_tree(scene, tree)
    output = tree.nodes.new("NodeGroupOutput")
    tree.links.new(group_node.outputs["Image"], output.inputs["Image"])
    scene.render.use_compositing = True
    comp_dir = os.path.join(tmp_root, "comp")
    scene.render.filepath = os.path.join(comp_dir, "comp_####.exr")
    fmt = scene.render.image_settings
    fmt.media_type = "IMAGE"
    fmt.file_format = "OPEN_EXR"
    fmt.color_depth = "32"
    # Frame 4's enhanced file is given a known change, so the check below does not
    # depend on how much the backend changed the frame.
    deps, exrio = addon.deps, addon.exrio
    marked = os.path.join(out, "enhanced", "frame_0004.exr")
    exr = exrio.read(deps.oiio(), marked)
    exr.set_channels(COLOR[:3], exr.channels(COLOR[:3]) * 0.5 + 0.25)
    exrio.write(deps.oiio(), exr, marked)
    scene.frame_start, scene.frame_end = 3, 5
    try:
        render(scene)  # no Render Layers node: a compositor-only render
    finally:
        scene.frame_start, scene.frame_end = fixture.FRAMES
    for frame in (3, 4, 5):
        comp, _ = read_exr(os.path.join(comp_dir, f"comp_{frame:04d}.exr"))
        enh, _ = read_exr(os.path.join(out, "enhanced", f"frame_{frame:04d}.exr"))
        raw, _ = read_exr(os.path.join(out, "raw", f"frame_{frame:04d}.exr"))
        got = np.stack([comp[c] for c in "RGB"], -1)
        want = np.stack([enh[c] for c in COLOR[:3]], -1)
        np.testing.assert_allclose(got, want, atol=1e-5, err_msg=f"frame {frame}")
        if frame == 4:  # the compositor read the enhanced file, not the raw one
            raw_rgb = np.stack([raw[c] for c in COLOR[:3]], -1)
            assert np.abs(got - raw_rgb).max() > 0.1


@pytest.mark.parametrize("space", ["Linear Rec.709", "Linear Rec.2020", "ACEScg"])
def test_ocio_round_trip_is_exact_with_bypass(addon, tmp_root, space):
    out = os.path.join(tmp_root, "ocio", space.replace(" ", "_"))
    scene = fixture.build(os.path.join(out, "raw", "frame_####.exr"), frames=(1, 2))
    # The working space belongs to the blend file (scene.build starts a new one).
    if bpy.data.colorspace.working_space != space:
        assert bpy.ops.wm.set_working_color_space(working_space=space, convert_colors=True) == {"FINISHED"}
    assert bpy.data.colorspace.working_space == space
    configure(scene, backend="bypass", output_path=os.path.join(out, "enhanced", "frame_####.exr"))
    render(scene)
    log = addon.handlers.last_run(scene.name)
    assert not log.errors, log.errors
    for frame in (1, 2):
        raw, raw_attrs = read_exr(os.path.join(out, "raw", f"frame_{frame:04d}.exr"))
        enh, attrs = read_exr(os.path.join(out, "enhanced", f"frame_{frame:04d}.exr"))
        assert attrs["harmonizer/colorspace"] == space, (
            attrs.get("harmonizer/colorspace"),
            raw_attrs.get("colorInteropID"),
        )
        for c in COLOR:
            np.testing.assert_allclose(enh[c], raw[c], atol=1e-4, rtol=0, err_msg=f"{space} frame {frame} {c}")


def test_conversion_to_library_space_is_the_real_transform(addon):
    """ACEScg red in Linear Rec.709 is about (1.705, -0.130, -0.024): the conversion is not an identity."""
    deps, colorspace = addon.deps, addon.colorspace
    conv = colorspace.Converter(deps.ocio(), deps.ocio_config_path(), "ACEScg")
    px = np.array([[[1.0, 0.0, 0.0]]], dtype=np.float32)
    conv.to_library(px)
    np.testing.assert_allclose(px[0, 0], [1.7051, -0.1302, -0.0240], atol=2e-3)
    conv.from_library(px)
    np.testing.assert_allclose(px[0, 0], [1.0, 0.0, 0.0], atol=1e-5)


def test_frame_jump_resets_temporal_state(addon, tmp_root):
    out = os.path.join(tmp_root, "jump")
    raw_dir = os.path.join(out, "raw")
    scene = fixture.build(os.path.join(raw_dir, "frame_####.exr"), frames=(1, 6))
    configure(scene, backend="bypass", output_path=os.path.join(out, "enhanced", "frame_####.exr"))
    # Frame 4 exists already and overwriting is off: Blender skips it, so the handler sees 1, 2, 3, 5, 6.
    os.makedirs(raw_dir, exist_ok=True)
    with open(os.path.join(raw_dir, "frame_0004.exr"), "wb") as fh:
        fh.write(b"placeholder")
    scene.render.use_overwrite = False
    scene.render.image_settings.color_depth = "16"  # half float, as many productions write
    render(scene)
    log = addon.handlers.last_run(scene.name)
    by_frame = {f["frame"]: f["reset"] for f in log.frames}
    assert list(by_frame) == [1, 2, 3, 5, 6], by_frame
    assert by_frame[1] == "first_frame"
    assert by_frame[2] is None and by_frame[3] is None and by_frame[6] is None
    assert by_frame[5] == "frame_gap", by_frame
    _, attrs = read_exr(os.path.join(out, "enhanced", "frame_0005.exr"))
    assert attrs["harmonizer/reset"] == "frame_gap"
    # Every part keeps its stored precision (color in half here; Blender keeps depth in float).
    oiio = _oiio()
    formats = {}
    for name in ("raw", "enhanced"):
        inp = oiio.ImageInput.open(os.path.join(out, name, "frame_0005.exr"))
        k, per_part = 0, []
        while inp.seek_subimage(k, 0):
            spec = inp.spec(k, 0)
            per_part.append([str(f) for f in spec.channelformats] or [str(spec.format)] * spec.nchannels)
            k += 1
        inp.close()
        formats[name] = per_part
    assert formats["enhanced"] == formats["raw"]
    assert formats["raw"][0] == ["half"] * 4, formats["raw"][0]


def test_failed_frame_is_reported_and_render_goes_on(addon, tmp_root):
    out = os.path.join(tmp_root, "failed")
    scene = fixture.build(os.path.join(out, "raw", "frame_####.exr"), frames=(1, 5))
    configure(scene, backend="bypass", output_path=os.path.join(out, "enhanced", "frame_####.exr"))

    def corrupt_frame_3(sc, *_):
        if sc.frame_current == 3:
            path = sc.render.frame_path(frame=3)
            with open(path, "r+b") as fh:
                fh.truncate(os.path.getsize(path) // 3)

    # Runs before the extension's handler: frame 3 on disk is truncated when harmonizer reads it.
    bpy.app.handlers.render_write.insert(0, corrupt_frame_3)
    try:
        n_reports = len(addon.reports.RECENT)
        render(scene)
    finally:
        bpy.app.handlers.render_write.remove(corrupt_frame_3)
    log = addon.handlers.last_run(scene.name)
    assert [f["frame"] for f in log.frames] == [1, 2, 3, 4, 5]
    assert len(log.errors) == 1 and "frame 3" in log.errors[0], log.errors
    assert "frame_0003.exr" in log.errors[0]
    new = list(addon.reports.RECENT)[n_reports:]
    assert any(level == "ERROR" and "frame 3" in text for level, text in new), new
    for frame in (1, 2, 4, 5):
        assert os.path.isfile(os.path.join(out, "enhanced", f"frame_{frame:04d}.exr"))
    assert not os.path.exists(os.path.join(out, "enhanced", "frame_0003.exr"))
    # No temporary files left behind by the failed frame.
    assert all(not n.startswith(".") for n in os.listdir(os.path.join(out, "enhanced")))


def test_enhance_rendered_sequence_operator(addon, classical_run, tmp_root):
    _scene, out, _log = classical_run
    scene = bpy.context.scene  # later tests replaced the file; the raw frames are still on disk
    src = os.path.join(tmp_root, "operator", "raw")
    os.makedirs(src, exist_ok=True)
    for frame in FRAMES:
        if frame != 5:  # a missing frame: the operator's session resets after the gap
            shutil.copy(os.path.join(out, "raw", f"frame_{frame:04d}.exr"), src)
    dst = os.path.join(tmp_root, "operator", "enhanced")
    scene.harmonizer.backend = "bypass"
    assert bpy.ops.harmonizer.enhance_sequence(directory=src, output_directory=dst) == {"FINISHED"}
    names = sorted(os.listdir(dst))
    assert names == [f"frame_{f:04d}.exr" for f in FRAMES if f != 5]
    _, attrs6 = read_exr(os.path.join(dst, "frame_0006.exr"))
    _, attrs4 = read_exr(os.path.join(dst, "frame_0004.exr"))
    assert attrs6["harmonizer/reset"] == "frame_gap"
    assert attrs4["harmonizer/reset"] == "none"
    # The input is never the output.
    with pytest.raises(RuntimeError):
        bpy.ops.harmonizer.enhance_sequence(directory=src, output_directory=src)


def test_disable_and_enable_leave_no_handlers_behind(addon):
    assert handlers_of(ADDON_MODULE) == 5
    for _ in range(2):
        bpy.ops.preferences.addon_disable(module=ADDON_MODULE)
        assert handlers_of(ADDON_MODULE) == 0
        assert not hasattr(bpy.types.Scene, "harmonizer")
        assert not hasattr(bpy.types, "RENDER_PT_harmonizer")
        bpy.ops.preferences.addon_enable(module=ADDON_MODULE)
        assert handlers_of(ADDON_MODULE) == 5
        assert hasattr(bpy.types.Scene, "harmonizer")


def test_insert_mask_from_collection_matches_object_index(addon, classical_run):
    """Cryptomatte (collection/object names) and Object Index agree on the inserted object's pixels."""
    _scene, out, _log = classical_run
    processor, exrio, deps = addon.processor, addon.exrio, addon.deps
    exr = exrio.read(deps.oiio(), os.path.join(out, "raw", "frame_0004.exr"))
    by_index = processor.insert_mask(
        exr, processor.Options(mask_source="OBJECT_INDEX", mask_index=fixture.INSERT_PASS_INDEX), 4
    )
    by_crypto = processor.insert_mask(
        exr, processor.Options(mask_source="CRYPTOMATTE", mask_names=["InsertedSphere"]), 4
    )
    assert by_index.sum() > 50, "the inserted sphere is not in frame 4"
    agree = ((by_crypto > 0.5) == (by_index > 0.5)).mean()
    assert agree > 0.995, agree
    # The hash the extension computes equals the id Blender wrote in the manifest.
    import struct

    want = struct.unpack("<f", struct.pack("<I", int("6d8f740b", 16)))[0]
    assert processor.cryptomatte_hash("InsertedSphere") == want


def test_insert_ids_from_cryptomatte_names_and_pass_indices(addon, classical_run):
    """Several inserted objects: each Cryptomatte name is one object (ids 1, 2 in
    the list's order) and several pass indices give each index as its id; one
    index gives the mask alone, as before."""
    _scene, out, _log = classical_run
    processor, exrio, deps = addon.processor, addon.exrio, addon.deps
    exr = exrio.read(deps.oiio(), os.path.join(out, "raw", "frame_0004.exr"))
    one = processor.Options(mask_source="OBJECT_INDEX", mask_index=fixture.INSERT_PASS_INDEX)
    by_index, no_ids = processor.insert_mask_and_ids(exr, one, 4)
    assert no_ids is None and by_index.sum() > 50
    several = processor.Options(
        mask_source="OBJECT_INDEX", mask_index=fixture.INSERT_PASS_INDEX, mask_indices=[fixture.INSERT_PASS_INDEX, 9]
    )
    mask, ids = processor.insert_mask_and_ids(exr, several, 4)
    np.testing.assert_array_equal(mask, by_index)
    assert set(np.unique(ids)) == {0.0, float(fixture.INSERT_PASS_INDEX)}
    np.testing.assert_array_equal(ids > 0, by_index > 0)
    crypto = processor.Options(mask_source="CRYPTOMATTE", mask_names=["InsertedSphere", "Cube"])
    mask, ids = processor.insert_mask_and_ids(exr, crypto, 4)
    sphere_only = processor.insert_mask(
        exr, processor.Options(mask_source="CRYPTOMATTE", mask_names=["InsertedSphere"]), 4
    )
    assert (ids == 2.0).sum() > 50, "the cube has no pixels of its own id"
    assert ((ids == 1.0) == (by_index > 0.5)).mean() > 0.995
    assert ((ids > 0) == (mask > 0)).all()
    assert (mask >= sphere_only - 1e-6).all() and mask[ids == 2.0].min() > 0.0


def test_more_indices_in_the_panel(addon, tmp_root):
    """The panel's Pass Index and More Indices become the library's several
    objects (each index once); what is not a pass index is warned about."""
    scene = fixture.build(os.path.join(tmp_root, "indices", "frame_####.exr"))
    configure(scene, mask_source="OBJECT_INDEX", mask_index=fixture.INSERT_PASS_INDEX)
    assert addon.passes.mask_indices(scene) == []
    scene.harmonizer.mask_more_indices = " 9, 7,x,-2"
    assert addon.passes.mask_indices(scene) == [fixture.INSERT_PASS_INDEX, 9]
    warnings = [t for level, t in addon.passes.check(scene, apply=False) if level == "WARNING"]
    assert any("'x', '-2' are not pass indices" in t for t in warnings), warnings


def test_before_after_image(addon, classical_run, tmp_root):
    """Side by side: raw render | enhanced frame (display sRGB), for the docs.

    Written to $HZ_DOCS_IMAGE when set (run.sh --docs-image), else into the temp folder.
    """
    _scene, out, _log = classical_run
    deps = addon.deps
    ocio, oiio = deps.ocio(), deps.oiio()
    config = ocio.Config.CreateFromFile(deps.ocio_config_path())
    to_display = config.getProcessor("Linear Rec.709", "sRGB").getDefaultCPUProcessor()
    frame = 6
    raw, _ = read_exr(os.path.join(out, "raw", f"frame_{frame:04d}.exr"))
    enh, _ = read_exr(os.path.join(out, "enhanced", f"frame_{frame:04d}.exr"))
    panels = []
    for chans in (raw, enh):
        rgb = np.ascontiguousarray(np.stack([chans[c] for c in COLOR[:3]], -1), dtype=np.float32)
        to_display.applyRGB(rgb)
        panels.append(np.clip(rgb, 0.0, 1.0))
    gap = np.ones((panels[0].shape[0], 4, 3), dtype=np.float32)
    image = np.concatenate([panels[0], gap, panels[1]], axis=1)
    image = np.repeat(np.repeat(image, 2, axis=0), 2, axis=1)  # 2x, nearest: pixels stay visible
    path = os.environ.get("HZ_DOCS_IMAGE") or os.path.join(tmp_root, "before_after.png")
    spec = oiio.ImageSpec(image.shape[1], image.shape[0], 3, oiio.UINT8)
    outf = oiio.ImageOutput.create(path)
    assert outf.open(path, spec), oiio.geterror()
    assert outf.write_image((image * 255.0 + 0.5).astype(np.uint8))
    outf.close()
    assert os.path.getsize(path) > 1000


def test_camera_matrices_match_blender_projection(addon, tmp_root):
    """worldToNDC from the camera settings projects like Blender's own world_to_camera_view."""
    from bpy_extras.object_utils import world_to_camera_view

    scene = fixture.build(os.path.join(tmp_root, "cam", "frame_####.exr"))
    cam = scene.camera
    cases = [
        dict(),
        dict(shift_x=0.1, shift_y=-0.05),
        dict(sensor_fit="VERTICAL", lens=50.0),
        dict(sensor_fit="HORIZONTAL", shift_y=0.2),
    ]
    for case in cases:
        for k, v in case.items():
            setattr(cam.data, k, v)
        for frame in (1, 8):
            scene.frame_set(frame)
            w2c, w2n = addon.runtime.camera_matrices(scene)
            for obj in ("Cube", "Pillar", "InsertedSphere"):
                p = bpy.data.objects[obj].matrix_world.translation
                ref = world_to_camera_view(scene, cam, p)
                h = np.array([p.x, p.y, p.z, 1.0]) @ w2n.astype(np.float64)
                c = np.array([p.x, p.y, p.z, 1.0]) @ w2c.astype(np.float64)
                np.testing.assert_allclose(
                    [h[0] / h[3], h[1] / h[3]], [ref.x, 1.0 - ref.y], atol=1e-5, err_msg=f"{case} {obj}"
                )
                assert abs(c[2] - ref.z) < 1e-4  # planar depth along +z


def test_frame_patterns_and_motion_blur_warning(addon, tmp_root):
    seq = addon.sequence
    for pattern in ("f_####.exr", "f_%04d.exr", "f_$F4.exr", "f_${F4}.exr", "f_<F4>.exr"):
        assert seq.expand(pattern, 7) == "f_0007.exr", pattern
    assert seq.expand("f_.exr", 12) == "f_0012.exr"
    scene = fixture.build(os.path.join(tmp_root, "warn", "frame_####.exr"))
    scene.harmonizer.enabled = True
    scene.render.use_motion_blur = True
    msgs = addon.passes.check(scene, apply=False)
    assert any(level == "WARNING" and "motion blur" in text for level, text in msgs), msgs
    scene.harmonizer.output_path = os.path.join(tmp_root, "warn", "hz", "shot_<F4>")
    raw = scene.render.frame_path(frame=3)
    assert addon.passes.enhanced_path(scene, raw, 3) == os.path.join(tmp_root, "warn", "hz", "shot_0003.exr")
    scene.harmonizer.output_path = ""
    assert addon.passes.enhanced_path(scene, raw, 3) == os.path.join(tmp_root, "warn", "harmonized", "frame_0003.exr")


def _rgb(chans: dict[str, np.ndarray]) -> np.ndarray:
    return np.stack([chans[c] for c in COLOR[:3]], -1)


def test_animated_camera_reprojects_with_the_camera_of_each_frame(addon, tmp_root, monkeypatch):
    """Issue 6: every frame gets its own camera, not the first frame's.

    A static scene seen by a panning camera, rendered twice with the classical
    backend: with the Vector pass (history aligned by motion vectors) and without
    it (aligned by depth and the per-frame cameras). The matrices passed for
    frame N are the camera at frame N, and the two runs agree: mean |RGB|
    difference below 0.001 on every frame (about 0.0002; the raw frames are
    identical). With the render's starting camera passed for every frame it was
    0.004-0.007 on frames 2-7.
    """
    passed: dict[int, tuple] = {}
    process = addon.processor.FrameProcessor.process

    def recording(self, raw_path, output_path, *, frame, camera=None, **kw):
        passed[frame] = camera
        return process(self, raw_path, output_path, frame=frame, camera=camera, **kw)

    monkeypatch.setattr(addon.processor.FrameProcessor, "process", recording)
    runs, wrong = {}, []
    for name, vector in (("vector", True), ("camera", False)):
        out = os.path.join(tmp_root, "anim_camera", name)
        scene = fixture.build(os.path.join(out, "raw", "frame_####.exr"))
        bpy.data.objects["InsertedSphere"].animation_data_clear()  # only the camera moves
        cam = scene.camera
        cam.rotation_euler.z += math.radians(6)  # a faster pan than the fixture's: 12 degrees in 7 frames
        cam.keyframe_insert("rotation_euler", frame=fixture.FRAMES[1])
        vl = scene.view_layers[0]
        vl.use_pass_z = vl.use_pass_normal = True
        vl.use_pass_vector = vector
        configure(
            scene,
            backend="classical",
            manage_passes=False,
            output_path=os.path.join(out, "enhanced", "frame_####.exr"),
        )
        passed.clear()
        render(scene)
        log = addon.handlers.last_run(scene.name)
        assert not log.errors, log.errors
        assert [f["frame"] for f in log.frames] == FRAMES
        raw, _ = read_exr(os.path.join(out, "raw", "frame_0002.exr"))
        assert ("ViewLayer.Vector.X" in raw) == vector
        for frame in FRAMES:
            scene.frame_set(frame)  # in the main thread the camera is evaluated at the frame
            want = addon.runtime.camera_matrices(scene)
            got = passed[frame]
            if got is None or any(not np.allclose(g, w, atol=1e-5) for g, w in zip(got, want, strict=True)):
                wrong.append(f"{name} run, frame {frame}")
        runs[name] = out
    diffs = []
    for frame in FRAMES:
        path = f"frame_{frame:04d}.exr"
        raw_v, _ = read_exr(os.path.join(runs["vector"], "raw", path))
        raw_c, _ = read_exr(os.path.join(runs["camera"], "raw", path))
        np.testing.assert_array_equal(_rgb(raw_v), _rgb(raw_c))
        enh_v, _ = read_exr(os.path.join(runs["vector"], "enhanced", path))
        enh_c, _ = read_exr(os.path.join(runs["camera"], "enhanced", path))
        diffs.append(float(np.abs(_rgb(enh_v) - _rgb(enh_c)).mean()))
    print(f"\nanimated camera: mean |vector run - camera run| per frame: {np.round(diffs, 4).tolist()}")
    assert not wrong, f"worldToCamera/worldToNDC passed are not the camera at the frame: {wrong}"
    assert max(diffs) < 0.001, diffs


def test_written_still_is_enhanced_as_one_frame(addon, tmp_root):
    """Issue 7: ``render(write_still=True)`` is enhanced, under the name Blender wrote.

    Blender names a still after the output path without frame numbers (``####``
    kept, the format's extension made sure of), not ``frame_path()``. A stale
    animation frame with the same number must not be taken for it.
    """
    out = os.path.join(tmp_root, "still")
    scene = fixture.build(os.path.join(out, "raw", "frame_####.exr"), frames=(1, 3))
    scene.render.resolution_x, scene.render.resolution_y = 32, 18
    configure(scene, backend="bypass")
    os.makedirs(os.path.join(out, "raw"), exist_ok=True)
    stale = os.path.join(out, "raw", "frame_0002.exr")
    with open(stale, "wb") as fh:
        fh.write(b"an older animation frame")
    os.utime(stale, (1.0e9, 1.0e9))
    scene.frame_set(2)
    cases = [
        # render output, enhanced output setting, (file Blender writes, enhanced file)
        ("frame_####.exr", "", ("raw/frame_####.exr", "raw/harmonized/frame_####.exr")),
        ("still_", "", ("raw/still_.exr", "raw/harmonized/still_.exr")),
        ("shot.png", "", ("raw/shot.exr", "raw/harmonized/shot.exr")),
        ("frame_####.exr", "enhanced/hz_####", ("raw/frame_####.exr", "enhanced/hz_####.exr")),
    ]
    for name, output_path, (want_raw, want_enh) in cases:
        scene.render.filepath = os.path.join(out, "raw", name)
        scene.harmonizer.output_path = os.path.join(out, output_path) if output_path else ""
        n_reports = len(addon.reports.RECENT)
        assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
        assert os.path.isfile(os.path.join(out, want_raw)), sorted(os.listdir(os.path.join(out, "raw")))
        new = list(addon.reports.RECENT)[n_reports:]
        assert not [t for level, t in new if level != "INFO"], new
        log = addon.handlers.last_run(scene.name)
        assert not log.errors, log.errors
        assert [(f["frame"], f["raw"], f["output"]) for f in log.frames] == [
            (2, os.path.join(out, want_raw), os.path.join(out, want_enh))
        ], (name, log.frames)
        assert log.frames[0]["reset"] == "first_frame"
        raw, _ = read_exr(os.path.join(out, want_raw))
        enh, attrs = read_exr(os.path.join(out, want_enh))
        assert attrs["harmonizer/frame"] == "2"
        np.testing.assert_allclose(_rgb(enh), _rgb(raw), atol=1e-4)
    # A still's warnings name its frame, also off the Frame Step grid (frame 2 of 1, 3, 5, ...).
    scene.frame_step = 2
    scene.harmonizer.backend = "classical"

    def nan_in_still(sc, *_):
        _put_nan(addon, addon.passes.still_path(sc))

    bpy.app.handlers.render_write.insert(0, nan_in_still)
    try:
        n_reports = len(addon.reports.RECENT)
        assert bpy.ops.render.render(write_still=True) == {"FINISHED"}
    finally:
        bpy.app.handlers.render_write.remove(nan_in_still)
    warnings = _warnings(list(addon.reports.RECENT)[n_reports:])
    assert len(warnings) == 1 and warnings[0].startswith("Harmonizer: frame 2: 15 color samples were NaN"), warnings
    # A still render that writes nothing is not enhanced, quietly.
    n_reports = len(addon.reports.RECENT)
    assert bpy.ops.render.render() == {"FINISHED"}
    assert addon.handlers.last_run(scene.name).frames == []
    assert not [t for level, t in list(addon.reports.RECENT)[n_reports:] if level != "INFO"]


def _put_nan(addon, path: str, count: int = 5) -> None:
    """Write NaN into the first ``count`` pixels of the Combined pass of ``path``."""
    exr = addon.exrio.read(addon.deps.oiio(), path)
    rgb = np.array(exr.channels(COLOR[:3]))
    rgb.reshape(-1, 3)[:count] = np.nan
    exr.set_channels(COLOR[:3], rgb)
    addon.exrio.write(addon.deps.oiio(), exr, path)


def _warnings(recent) -> list[str]:
    return [text for level, text in recent if level == "WARNING"]


def test_library_warnings_reported_once_with_the_blender_frame(addon, tmp_root, capsys):
    """Issue 8: one message per library warning, naming Blender's frame numbers.

    Frames 1-9 every 2nd frame, frame 5 skipped (its file exists, Overwrite off),
    NaN written into frame 3: the library numbers frames 0, 1, 3 and its
    warnings said "frame 1: ..." and again "frame 3: frame 1: ...".
    """
    out = os.path.join(tmp_root, "messages")
    raw_dir = os.path.join(out, "raw")
    scene = fixture.build(os.path.join(raw_dir, "frame_####.exr"), frames=(1, 7), samples=1)
    scene.render.resolution_x, scene.render.resolution_y = 32, 18
    scene.frame_step = 2
    configure(scene, backend="classical", output_path=os.path.join(out, "enhanced", "frame_####.exr"))
    os.makedirs(raw_dir, exist_ok=True)
    with open(os.path.join(raw_dir, "frame_0005.exr"), "wb") as fh:
        fh.write(b"placeholder")
    scene.render.use_overwrite = False

    def nan_in_frame_3(sc, *_):
        if sc.frame_current == 3:
            _put_nan(addon, sc.render.frame_path(frame=3))

    bpy.app.handlers.render_write.insert(0, nan_in_frame_3)
    try:
        n_reports = len(addon.reports.RECENT)
        capsys.readouterr()
        render(scene)
    finally:
        bpy.app.handlers.render_write.remove(nan_in_frame_3)
    printed = capsys.readouterr()
    log = addon.handlers.last_run(scene.name)
    assert not log.errors, log.errors
    assert [f["frame"] for f in log.frames] == [1, 3, 7]
    warnings = _warnings(list(addon.reports.RECENT)[n_reports:])
    assert len(warnings) == 2, warnings
    assert warnings[0].startswith("Harmonizer: frame 3: 15 color samples were NaN"), warnings
    assert warnings[1].startswith("Harmonizer: frame 7: not consecutive to frame 3;"), warnings
    # What the terminal shows: the same two lines, once each.
    shown = [line for line in (printed.out + printed.err).splitlines() if "Warning:" in line]
    assert shown == [f"Warning: {w}" for w in warnings], shown


def test_batch_progress_line_ends_before_a_message(addon, classical_run, tmp_root):
    """Issue 8: the operator's progress line ("\\r" updated) is ended before a warning or error."""
    import contextlib
    import io

    _scene, out, _log = classical_run
    scene = bpy.context.scene
    src = os.path.join(tmp_root, "batch_messages", "raw")
    os.makedirs(src, exist_ok=True)
    for frame in (1, 2, 3, 4, 6):
        shutil.copy(os.path.join(out, "raw", f"frame_{frame:04d}.exr"), src)
    _put_nan(addon, os.path.join(src, "frame_0003.exr"))
    with open(os.path.join(src, "frame_0004.exr"), "r+b") as fh:
        fh.truncate(1000)
    configure(scene, backend="classical")
    n_reports = len(addon.reports.RECENT)
    terminal = io.StringIO()
    with contextlib.redirect_stdout(terminal), contextlib.redirect_stderr(terminal):
        result = bpy.ops.harmonizer.enhance_sequence(
            directory=src, output_directory=os.path.join(tmp_root, "batch_messages", "enhanced")
        )
    assert result == {"FINISHED"}
    new = list(addon.reports.RECENT)[n_reports:]
    warnings = _warnings(new)
    assert len(warnings) == 2, new
    assert warnings[0].startswith("Harmonizer: frame 3: 15 color samples were NaN"), warnings
    assert warnings[1].startswith("Harmonizer: frame 6: not consecutive to frame 3;"), warnings
    errors = [text for level, text in new if level == "ERROR"]
    assert len(errors) == 1 and "frame 4" in errors[0], new
    lines = terminal.getvalue().split("\n")
    messages = [line for line in lines if "Warning:" in line or "Error:" in line]
    for line in messages:  # each on a line of its own (the operator's summary is a warning too)
        assert line.startswith(("Warning: Harmonizer: ", "Error: Harmonizer: ")), repr(line)
    about_frames = [
        line for line in messages if line.startswith(("Warning: Harmonizer: frame ", "Error: Harmonizer: frame "))
    ]
    assert len(about_frames) == 3, lines
    assert lines[-1] == "" and "\r" not in lines[-2], lines[-3:]  # the output ends with a complete line


@pytest.mark.parametrize("settings", [{"backend": "bypass"}, {"backend": "classical", "strength": 0.0}])
def test_wide_gamut_colors_round_trip(addon, tmp_root, settings):
    """Colors outside Rec.709 (ACEScg working space) come back unchanged with bypass or strength 0.

    In Linear Rec.709, what the library works in, they have negative components;
    every finite color of the raw render must round-trip within 1e-4.
    """
    name = "_".join(f"{k}-{v}" for k, v in settings.items())
    out = os.path.join(tmp_root, "wide_gamut", name)
    scene = fixture.build_wide_gamut(os.path.join(out, "raw", "frame_####.exr"))
    assert bpy.data.colorspace.working_space == "ACEScg"
    configure(scene, output_path=os.path.join(out, "enhanced", "frame_####.exr"), **settings)
    render(scene)
    log = addon.handlers.last_run(scene.name)
    assert not log.errors, log.errors
    conv = addon.colorspace.Converter(addon.deps.ocio(), addon.deps.ocio_config_path(), "ACEScg")
    for frame in (scene.frame_start, scene.frame_end):
        raw, _ = read_exr(os.path.join(out, "raw", f"frame_{frame:04d}.exr"))
        enh, attrs = read_exr(os.path.join(out, "enhanced", f"frame_{frame:04d}.exr"))
        assert attrs["harmonizer/colorspace"] == "ACEScg"
        rec709 = np.ascontiguousarray(_rgb(raw), dtype=np.float32)
        conv.to_library(rec709)
        outside = (rec709 < -0.01).any(axis=-1).mean()
        assert outside > 0.5, f"only {outside:.0%} of the pixels are outside Rec.709"
        for c in COLOR:
            finite = np.isfinite(raw[c])
            np.testing.assert_allclose(
                enh[c][finite], raw[c][finite], atol=1e-4, rtol=0, err_msg=f"{settings} frame {frame} {c}"
            )
