"""Render handlers: one harmonizer session per render (an animation or a written still).

- ``render_init``: check (and set) the passes, open the session.
- ``frame_change_post``: while rendering, keep the camera and the direction
  toward the strongest Sun evaluated at each frame (in ``render_write`` the
  scene's objects are still those of the frame the render started from).
- ``render_write``: after Blender saved a frame, enhance it and write the
  enhanced EXR (beside the raw one unless configured otherwise). A written
  still (``render(write_still=True)``) is enhanced as a frame on its own.
- ``render_complete`` / ``render_cancel``: free the session.

A failed frame is reported and skipped; it never aborts the render, and the
session's temporal state stays as it was before that frame.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field

import bpy
from bpy.app.handlers import persistent

from . import passes, reports, runtime


@dataclass
class RunLog:
    """What one render did, frame by frame (kept after the render for the UI and scripts)."""

    scene: str
    frames: list[dict] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)
    finished: bool = False
    #: The denoise stage's latest decision (``denoise auto: on (the host renders 4
    #: samples per pixel, 1 to 64)``), or None.
    denoise_decision: str | None = None

    @property
    def denoised(self) -> int:
        """How many frames were denoised."""
        return sum(1 for f in self.frames if f.get("denoised"))


@dataclass
class _Render:
    """A render in progress: its session and what render_write needs to know."""

    runner: runtime.Runner
    #: Frame number -> (worldToCamera, worldToNDC) of the camera evaluated at that
    #: frame (frame_change_post), or None for a camera the library cannot use.
    cameras: dict[int, tuple | None] = field(default_factory=dict)
    #: Frame number -> the direction toward the light at that frame
    #: (``Runner.light_at`` with the frame's depsgraph), or None for none.
    lights: dict[int, tuple | None] = field(default_factory=dict)
    #: The file a still render writes and its state at render start (None: absent).
    still_path: str = ""
    still_before: tuple | None = None
    #: The library's frame number (frame_index: render order) -> Blender's frame.
    frames: dict[int, int] = field(default_factory=dict)


_RENDERS: dict[str, _Render] = {}
_LOGS: dict[str, RunLog] = {}


def last_run(scene_name: str) -> RunLog | None:
    """The log of the latest render of ``scene_name`` (None before the first)."""
    return _LOGS.get(scene_name)


def _file_state(path: str) -> tuple | None:
    """What changes when a file is written (None: no file)."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns)


def _close(scene_name: str) -> None:
    render = _RENDERS.pop(scene_name, None)
    if render is not None:
        render.runner.close()
    log = _LOGS.get(scene_name)
    if log is not None:
        log.finished = True


def _can_render_here() -> bool:
    """Whether a render may start from this handler: in a background
    render (``blender -b``, the ``bpy`` module) the handlers run on the main
    thread before the render, and Cycles renders the Sun to Sky probe
    there; an interactive render runs them on its own thread, where Blender
    cannot start another (the panel's *Measure Sun to Sky* does it)."""
    return bool(bpy.app.background) and threading.current_thread() is threading.main_thread()


@persistent
def on_render_init(scene, *_args):
    """Render start: set up passes, open the session."""
    if not getattr(scene, "harmonizer", None) or not scene.harmonizer.enabled:
        return
    _close(scene.name)
    log = RunLog(scene.name)
    _LOGS[scene.name] = log
    for level, text in passes.check(scene, apply=scene.harmonizer.manage_passes, at_render=True):
        reports.post(level, text)
    try:
        runner = runtime.Runner(scene, measure_light=_can_render_here())
    except Exception as exc:  # reported; the render itself goes on unchanged
        msg = f"Harmonizer: cannot start for scene {scene.name!r}: {exc}"
        log.errors.append(msg)
        reports.post("ERROR", msg)
        return
    for level, text in runner.notes:
        reports.post(level, text)
    # Whether this render is a still is only known when a file is written:
    # a still goes to passes.still_path(), which an animation never writes.
    still = passes.still_path(scene)
    _RENDERS[scene.name] = _Render(runner, still_path=still, still_before=_file_state(still))


@persistent
def on_frame_change_post(scene, depsgraph=None, *_args):
    """A frame was evaluated for rendering: keep its camera and light for ``render_write``."""
    render = _RENDERS.get(scene.name)
    if render is None or depsgraph is None or scene.frame_subframe != 0.0:
        return
    try:
        render.cameras[scene.frame_current] = runtime.camera_matrices(scene, depsgraph)
    except Exception as exc:  # render_write falls back to the scene camera
        reports.post("WARNING", f"Harmonizer: frame {scene.frame_current}: cannot read the camera: {exc}")
    try:
        render.lights[scene.frame_current] = render.runner.light_at(scene, depsgraph)
    except Exception as exc:  # render_write falls back to the scene as it is
        reports.post("WARNING", f"Harmonizer: frame {scene.frame_current}: cannot read the light: {exc}")


@persistent
def on_render_write(scene, *_args):
    """A frame was saved: enhance it."""
    render = _RENDERS.get(scene.name)
    if render is None:
        return
    runner = render.runner
    log = _LOGS[scene.name]
    frame = scene.frame_current
    still = _file_state(render.still_path) not in (None, render.still_before)
    raw = render.still_path if still else scene.render.frame_path(frame=frame)
    out = passes.enhanced_path(scene, raw, frame, still=still)
    # Render order, so that frames frame_step apart are consecutive for the library.
    step = max(1, scene.frame_step)
    index = (frame - scene.frame_start) // step
    render.frames[index] = frame
    if frame in render.cameras:
        camera = render.cameras.pop(frame)
    else:  # no evaluation seen for this frame: the scene camera as it is
        camera = runtime.camera_matrices(scene)
    if frame in render.lights:
        light = render.lights.pop(frame)
    else:  # a still, or no evaluation seen: the scene's Sun as it is
        light = runner.light_at(scene)
    start = time.perf_counter()
    try:
        result = runner.processor.process(
            raw,
            out,
            frame=frame,
            frame_index=index,
            camera=camera,
            allow_overwrite=scene.harmonizer.overwrite_raw,
            light_direction=light,
        )
    except Exception as exc:  # one failed frame never aborts the user's render
        runner.drop_messages()
        msg = f"Harmonizer: frame {frame} not enhanced ({raw}): {exc}"
        log.errors.append(msg)
        log.frames.append({"frame": frame, "raw": raw, "output": None, "error": str(exc), "still": still})
        reports.post("ERROR", msg)
        return
    report = result.report

    def frame_of(i: int) -> int:
        return render.frames.get(i, scene.frame_start + i * step)

    entry = {
        "frame": frame,
        "raw": raw,
        "output": out,
        "still": still,
        "reset": report.get("reset"),
        "backend": report.get("backend"),
        "history_used": report.get("history_used"),
        "denoised": bool(report.get("denoised")),
        "denoise_decision": runtime.renumber(report["denoise_decision"], frame_of)
        if report.get("denoise_decision")
        else None,
        "noise_level": report.get("noise_level"),
        "inputs": result.inputs,
        "light_direction": result.light_direction,
        "ms": (time.perf_counter() - start) * 1000.0,
        "warnings": runner.post_messages(frame, frame_of),
    }
    log.frames.append(entry)
    decision = entry["denoise_decision"]
    if decision:
        # Decided on the first frame of the sequence (and after each reset);
        # a decision that is also a warning (no library) was posted as one.
        log.denoise_decision = decision
        if not any(decision in w for w in entry["warnings"]):
            reports.post("INFO", f"Harmonizer: frame {frame}: {decision}")
    reset = entry["reset"]
    note = ", denoised" if entry["denoised"] else ""
    note += f", temporal state reset ({reset})" if reset else ""
    reports.post("INFO", f"Harmonizer: frame {frame} -> {out} ({entry['ms']:.0f} ms{note})")


@persistent
def on_render_done(scene, *_args):
    """Render finished or cancelled: free the session."""
    _close(scene.name)


HANDLERS = (
    (bpy.app.handlers.render_init, on_render_init),
    (bpy.app.handlers.frame_change_post, on_frame_change_post),
    (bpy.app.handlers.render_write, on_render_write),
    (bpy.app.handlers.render_complete, on_render_done),
    (bpy.app.handlers.render_cancel, on_render_done),
)


def register() -> None:
    for handler_list, fn in HANDLERS:
        if fn not in handler_list:
            handler_list.append(fn)


def unregister() -> None:
    for handler_list, fn in HANDLERS:
        # Remove by identity and, after a reload, by qualified name.
        for existing in list(handler_list):
            if existing is fn or (
                getattr(existing, "__module__", None) == fn.__module__
                and getattr(existing, "__name__", None) == fn.__name__
            ):
                handler_list.remove(existing)
    for name in list(_RENDERS):
        _close(name)


def registered_count() -> int:
    """How many of this module's handlers are installed (0 after unregister)."""
    return sum(
        1
        for handler_list, fn in HANDLERS
        for existing in handler_list
        if getattr(existing, "__module__", None) == fn.__module__
    )
