"""The denoise stage through the Blender extension (issue 20), real bpy 5.0.1 and Cycles.

The fixture animation (scene.py) at 4 samples per pixel, 4 frames, 160x90,
rendered with the extension: Open Image Denoise from the bundled pyoidn wheel,
the Denoising Data passes switched on by the "Set Up Passes" button, frames
denoised during the render. A 256-sample render of the same frames is the
reference the noise is measured against.
"""

from __future__ import annotations

import os
import shutil

import bpy
import numpy as np
import pytest

import scene as fixture
from test_extension import COLOR, configure, read_exr, render

FRAMES = (1, 4)
REFERENCE_SAMPLES = 256
#: The denoised output must be this much closer to the reference than the raw render (dB).
MIN_GAIN_DB = 4.0


def _rgb(chans: dict[str, np.ndarray], names=COLOR[:3]) -> np.ndarray:
    return np.stack([chans[c] for c in names], axis=-1)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR of two linear images after a 1/2.2 display curve (clipped to [0, 1])."""
    da = np.clip(a, 0.0, 1.0) ** (1 / 2.2)
    db = np.clip(b, 0.0, 1.0) ** (1 / 2.2)
    return float(10.0 * np.log10(1.0 / np.mean((da - db) ** 2)))


def _frames(out: str, kind: str) -> list[str]:
    return [os.path.join(out, kind, f"frame_{f:04d}.exr") for f in range(FRAMES[0], FRAMES[1] + 1)]


@pytest.fixture(scope="module")
def reference(addon, tmp_root):
    """The fixture frames at 256 samples, rendered without the extension."""
    out = os.path.join(tmp_root, "denoise", "reference")
    scene = fixture.build(os.path.join(out, "frame_####.exr"), samples=REFERENCE_SAMPLES, frames=FRAMES)
    scene.harmonizer.enabled = False
    render(scene)
    return [_rgb(read_exr(p)[0]) for p in _frames(out, "")]


def _denoise_render(addon, tmp_root, name: str, **settings):
    """The 4-sample fixture rendered with the extension (classical backend, ``settings``)."""
    out = os.path.join(tmp_root, "denoise", name)
    scene = fixture.build(os.path.join(out, "raw", "frame_####.exr"), samples=4, frames=FRAMES)
    configure(
        scene,
        backend="classical",
        output_path=os.path.join(out, "enhanced", "frame_####.exr"),
        **settings,
    )
    return scene, out


@pytest.fixture(scope="module")
def auto_run(addon, tmp_root, reference):
    """denoise auto, the Denoising Data passes switched on by the user with "Set Up Passes"."""
    scene, out = _denoise_render(addon, tmp_root, "auto")
    vl = scene.view_layers["ViewLayer"]
    assert not vl.cycles.denoising_store_passes
    # The panel warns (the render will be denoised without guides) and offers the button.
    problems = addon.passes.check(scene, apply=False)
    assert any(level == "WARNING" and "Denoising Data" in text for level, text in problems), problems
    assert bpy.ops.harmonizer.setup_passes() == {"FINISHED"}
    assert vl.cycles.denoising_store_passes
    n_reports = len(addon.reports.RECENT)
    render(scene)
    return scene, out, addon.handlers.last_run(scene.name), list(addon.reports.RECENT)[n_reports:]


def test_the_bundled_open_image_denoise_is_used(addon, auto_run):
    path = addon.deps.oidn_library()
    assert path is not None and os.path.isfile(path), "pyoidn wheel from the zip not installed"
    assert "extensions" in path or "hz-blender-test" in path, path
    assert os.path.basename(path).startswith("libOpenImageDenoise.so.2"), path
    assert os.environ.get("HARMONIZER_OIDN_LIB") == path


def test_auto_denoises_a_4_sample_render_with_the_denoising_passes(auto_run, reference):
    scene, out, log, new_reports = auto_run
    assert not log.errors, log.errors
    assert [f["frame"] for f in log.frames] == list(range(FRAMES[0], FRAMES[1] + 1))
    assert all(f["denoised"] for f in log.frames), [f["denoise_decision"] for f in log.frames]
    assert log.denoised == len(log.frames)
    # Decided once, on the first frame, from the sample count the extension passed.
    assert log.frames[0]["denoise_decision"].startswith("denoise auto: on"), log.frames[0]
    assert "4" in log.frames[0]["denoise_decision"], log.frames[0]
    assert all(f["denoise_decision"] is None for f in log.frames[1:])
    assert log.denoise_decision == log.frames[0]["denoise_decision"]
    assert any("denoised" in text for level, text in new_reports if level == "INFO"), new_reports
    # The Denoising Data passes were rendered and passed to the library.
    raw, _ = read_exr(_frames(out, "raw")[0])
    for name in ("ViewLayer.Denoising Albedo.R", "ViewLayer.Denoising Normal.Z"):
        assert name in raw, sorted(raw)
    for f in log.frames:
        assert "albedo" in f["inputs"] and "denoise_normal" in f["inputs"], f["inputs"]
    gains = []
    for raw_path, enh_path, ref in zip(_frames(out, "raw"), _frames(out, "enhanced"), reference, strict=True):
        raw, _ = read_exr(raw_path)
        enh, attrs = read_exr(enh_path)
        assert attrs["harmonizer/denoised"] == "1"
        # The guide passes are kept as rendered; only the Combined pass is replaced.
        np.testing.assert_array_equal(enh["ViewLayer.Denoising Albedo.G"], raw["ViewLayer.Denoising Albedo.G"])
        before, after = psnr(_rgb(raw), ref), psnr(_rgb(enh), ref)
        gains.append(after - before)
        print(f"\n{os.path.basename(raw_path)}: raw {before:.2f} dB, denoised + enhanced {after:.2f} dB")
    assert min(gains) >= MIN_GAIN_DB, gains


def test_off_is_not_denoised(addon, tmp_root, auto_run, reference):
    scene, out = _denoise_render(addon, tmp_root, "off", denoise="off")
    render(scene)
    log = addon.handlers.last_run(scene.name)
    assert not log.errors, log.errors
    assert log.denoised == 0 and not any(f["denoised"] for f in log.frames)
    assert log.denoise_decision is None or "off" in log.denoise_decision, log.denoise_decision
    # No Denoising Data pass asked for: nothing will be denoised.
    assert not any("Denoising Data" in t for _level, t in addon.passes.check(scene, apply=False))
    _, auto_out, _, _ = auto_run
    for off_path, auto_path, ref in zip(
        _frames(out, "enhanced"), _frames(auto_out, "enhanced"), reference, strict=True
    ):
        off, attrs = read_exr(off_path)
        assert attrs["harmonizer/denoised"] == "0"
        auto, _ = read_exr(auto_path)
        assert psnr(_rgb(auto), ref) > psnr(_rgb(off), ref) + MIN_GAIN_DB / 2


def test_frames_cycles_denoised_are_not_denoised_again(addon, tmp_root):
    """Cycles' own denoiser on, panel Auto: denoise temporal, no second OIDN pass, the flicker accumulated."""
    scene, out = _denoise_render(addon, tmp_root, "cycles_denoiser")
    scene.cycles.use_denoising = True
    vl = scene.view_layers["ViewLayer"]
    assert addon.denoise.session_samples(scene, vl)[0] == 0
    assert addon.denoise.session_mode(scene, vl, "auto")[0] == "temporal"
    assert addon.denoise.session_mode(scene, vl, "off")[0] == "off"
    render(scene)
    log = addon.handlers.last_run(scene.name)
    assert not log.errors, log.errors
    decision = log.frames[0]["denoise_decision"]
    assert decision.startswith("denoise temporal"), decision
    assert log.frames[0]["noise_level"] is None  # nothing measured
    # Every frame went through the stage (the accumulation), none through OIDN.
    assert log.denoised == len(log.frames) and all(f["denoised"] for f in log.frames)


def test_sequence_operator_denoises_files_with_the_denoising_passes(addon, auto_run, tmp_root):
    """Existing multilayer EXRs: the guides are read from the files as during a render.

    With the panel's Auto the operator passes what the first file says:
    ``cycles.ViewLayer.samples`` 4, so ``auto`` denoises (the noise
    estimate alone finds these sunlit frames clean).
    """
    _scene, out, _log, _ = auto_run
    scene = bpy.context.scene
    src = os.path.join(tmp_root, "denoise", "sequence", "raw")
    os.makedirs(src, exist_ok=True)
    for path in _frames(out, "raw"):
        shutil.copy(path, src)
    configure(scene, backend="classical", denoise="auto", denoise_quality="balanced")
    assert addon.denoise.sequence_settings("auto", addon.exrio.read(addon.deps.oiio(), _frames(out, "raw")[0]),
                                           "ViewLayer") == ("auto", 4, "the files say Cycles took 4 samples per pixel")
    dst = os.path.join(tmp_root, "denoise", "sequence", "enhanced")
    assert bpy.ops.harmonizer.enhance_sequence(directory=src, output_directory=dst) == {"FINISHED"}
    written = sorted(os.listdir(dst))
    assert written == [os.path.basename(p) for p in _frames(out, "raw")], written
    for path in written:
        _, attrs = read_exr(os.path.join(dst, path))
        assert attrs["harmonizer/denoised"] == "1", path
    # The guides came from the files: the same frames without them come out differently.
    bare = os.path.join(tmp_root, "denoise", "sequence", "bare")
    os.makedirs(bare, exist_ok=True)
    exrio, oiio = addon.exrio, addon.deps.oiio()
    for path in _frames(out, "raw"):
        exr = exrio.read(oiio, path)
        exr.parts = [p for p in exr.parts if not p.name.startswith("ViewLayer.Denoising")]
        exrio.write(oiio, exr, os.path.join(bare, os.path.basename(path)))
    bare_out = os.path.join(tmp_root, "denoise", "sequence", "bare_enhanced")
    assert bpy.ops.harmonizer.enhance_sequence(directory=bare, output_directory=bare_out) == {"FINISHED"}
    with_guides, _ = read_exr(os.path.join(dst, written[0]))
    without, attrs = read_exr(os.path.join(bare_out, written[0]))
    assert attrs["harmonizer/denoised"] == "1"
    assert np.abs(_rgb(with_guides) - _rgb(without)).max() > 1e-3


def test_missing_library_is_reported(addon, tmp_root, auto_run, monkeypatch):
    """A missing Open Image Denoise: on fails each frame naming it, auto goes on without denoising."""
    _scene, out, _log, _ = auto_run
    scene = bpy.context.scene
    src = os.path.join(tmp_root, "denoise", "missing", "raw")
    os.makedirs(src, exist_ok=True)
    for path in _frames(out, "raw")[:2]:
        shutil.copy(path, src)
    gone = os.path.join(tmp_root, "nowhere", "libOpenImageDenoise.so.2")
    monkeypatch.setenv("HARMONIZER_OIDN_LIB", gone)
    configure(scene, backend="classical", denoise="on")
    n_reports = len(addon.reports.RECENT)
    bpy.ops.harmonizer.enhance_sequence(
        directory=src, output_directory=os.path.join(tmp_root, "denoise", "missing", "on")
    )
    errors = [t for level, t in list(addon.reports.RECENT)[n_reports:] if level == "ERROR"]
    assert len(errors) == 2, errors
    assert all("Open Image Denoise" in e and gone in e for e in errors), errors

    # auto during a render of 4 samples: on, the library is missing, so off with one warning.
    scene, out = _denoise_render(addon, tmp_root, "missing_auto")
    n_reports = len(addon.reports.RECENT)
    render(scene)
    log = addon.handlers.last_run(scene.name)
    new = list(addon.reports.RECENT)[n_reports:]
    assert not log.errors, log.errors
    warnings = [t for level, t in new if level == "WARNING" and "Open Image Denoise" in t]
    assert len(warnings) == 1 and gone in warnings[0], new
    assert warnings[0].startswith("Harmonizer: frame 1: "), warnings
    assert log.denoised == 0
    assert "cannot be used" in log.frames[0]["denoise_decision"], log.frames[0]


def test_samples_from_the_render_settings(addon):
    """What the extension tells the library about the render (``denoise.session_samples``)."""
    scene = fixture.build("//unused_####.exr", samples=16, frames=(1, 1))
    vl = scene.view_layers["ViewLayer"]
    samples = addon.denoise.session_samples
    assert samples(scene, vl)[0] == 16
    scene.cycles.use_adaptive_sampling = True
    assert samples(scene, vl)[0] == 16  # at most 64: every pixel stops at or below it, still noisy
    scene.cycles.samples = 1024
    assert samples(scene, vl) == (0, "adaptive sampling up to 1024 samples")
    scene.cycles.use_adaptive_sampling = False
    assert samples(scene, vl)[0] == 1024
    vl.samples = 8  # the view layer's override
    assert samples(scene, vl)[0] == 8
    scene.cycles.use_layer_samples = "IGNORE"
    assert samples(scene, vl)[0] == 1024
    scene.cycles.time_limit = 10.0
    assert samples(scene, vl)[0] == 0
    scene.cycles.time_limit = 0.0
    scene.cycles.use_denoising = True
    assert samples(scene, vl) == (0, "Cycles denoises each frame")
    vl.cycles.use_denoising = False  # the view layer opts out of Cycles' denoiser
    assert samples(scene, vl)[0] == 1024
    scene.render.engine = "BLENDER_EEVEE"
    assert samples(scene, vl)[0] == 0
    assert not addon.denoise.guides_available(scene, vl)
    assert addon.denoise.auto_summary(scene, vl).startswith("Auto: the first frame's noise decides")


def _harmonize_run(src_dir: str, dst_dir: str) -> dict:
    """``harmonize run`` (the release CLI) over the raw frames in ``src_dir``; its report."""
    import json
    import subprocess

    from conftest import REPO

    exe = os.path.join(REPO, "target", "release", "harmonize")
    assert os.path.isfile(exe), f"{exe} missing: cargo build --release -p harmonizer-cli"
    report = os.path.join(dst_dir, "report.json")
    p = subprocess.run(
        [exe, "run", os.path.join(src_dir, "frame_####.exr"), "-o", os.path.join(dst_dir, "frame_####.exr"),
         "--backend", "classical", "--threads", "2", "--report", report],
        capture_output=True, text=True,
    )
    assert p.returncode == 0, p.stdout + p.stderr
    with open(report) as f:
        rep = json.load(f)
    rep["stdout"] = p.stdout
    return rep


def test_the_cli_reads_what_cycles_recorded_in_the_files(addon, auto_run, tmp_root):
    """Blender's files say how they were rendered; ``harmonize run`` with nothing set uses it.

    Raw 4-sample frames carry ``cycles.ViewLayer.samples 4``: the CLI passes
    samples 4 and ``denoise auto`` denoises (the noise estimate alone finds
    these sunlit frames clean). Frames Cycles denoised carry its Noisy Image
    pass: the CLI passes ``denoise temporal``.
    """
    _scene, out, _log, _ = auto_run
    rep = _harmonize_run(os.path.join(out, "raw"), os.path.join(tmp_root, "denoise", "cli", "raw"))
    assert "samples 4" in rep["stdout"], rep["stdout"]
    assert rep["frames"][0]["denoise_decision"].startswith("denoise auto: on (the host renders 4 samples"), rep
    assert all(f["denoised"] for f in rep["frames"])

    scene, dn_out = _denoise_render(addon, tmp_root, "cli_cycles_denoised")
    scene.cycles.use_denoising = True
    scene.harmonizer.enabled = False
    render(scene)
    rep = _harmonize_run(os.path.join(dn_out, "raw"), os.path.join(tmp_root, "denoise", "cli", "denoised"))
    assert "denoise temporal" in rep["stdout"], rep["stdout"]
    assert rep["frames"][0]["denoise_decision"].startswith("denoise temporal"), rep
    # The extension's sequence operator reads the same.
    first = addon.exrio.read(addon.deps.oiio(), _frames(dn_out, "raw")[0])
    assert addon.denoise.sequence_settings("auto", first, "ViewLayer")[:2] == ("temporal", 0)
    assert addon.denoise.sequence_settings("on", first, "ViewLayer")[:2] == ("on", 0)
