"""The "Enhance Rendered Sequence" operator: a folder of multilayer EXRs in, enhanced EXRs out.

From the UI it runs modally, one frame per step, with a progress bar and Esc to
cancel; headless (or via ``execute``) it runs to the end printing progress to
the terminal. Frames are processed in increasing order with one session, so a
missing frame number resets the temporal state (the Frame Jump setting).
With the Light on Scene Sun, the light of each file is the open scene's
strongest Sun at the file's frame number: the scene is moved to that frame
(when it has a Sun) and back to its own frame at the end.
"""

from __future__ import annotations

import os
import sys
import time

import bpy
from bpy.props import BoolProperty, StringProperty

from . import denoise, deps, exrio, processor, reports, runtime, sequence


class _Job:
    def __init__(self, scene, directory: str, output: str, view_layer: str):
        frames = sequence.list_frames(directory)
        if not frames:
            raise processor.FrameError(f"{directory}: no frame-numbered .exr files")
        first = exrio.read(deps.oiio(), frames[0][1])
        if not view_layer:
            view_layer = processor.detect_view_layer(first) or ""
            if not view_layer:
                raise processor.FrameError(f"{frames[0][1]}: no view layer with a Combined pass")
        self.frames = frames
        self.scene = scene
        #: The scene's frame before the job (the Scene Sun light moves it).
        self.start_frame = scene.frame_current
        self.output = output
        self.index = 0
        self.done = 0
        self.failed: list[str] = []
        self.resets: list[tuple[int, str]] = []
        self.denoised = 0
        self.denoise_decision: str | None = None
        # With denoise Auto, what the first file says: Cycles' Noisy Image
        # pass (its denoiser ran: denoise temporal), else its sample count;
        # neither, samples 0 and the first frame's measured noise decides.
        mode, samples, why = denoise.sequence_settings(scene.harmonizer.denoise, first, view_layer)
        self.runner = runtime.Runner(
            scene, view_layer=view_layer, samples=samples, denoise_mode=mode, measure_light=True
        )
        if why:
            reports.post("INFO", f"Harmonizer: {why}")
        for level, text in self.runner.notes:
            reports.post(level, text)
        self.started = time.perf_counter()

    def step(self) -> bool:
        """Process the next frame; False when none are left."""
        if self.index >= len(self.frames):
            return False
        frame, raw = self.frames[self.index]
        self.index += 1
        out = os.path.join(self.output, os.path.basename(raw))
        try:
            light = self.runner.light_at_frame(self.scene, frame)
            result = self.runner.processor.process(raw, out, frame=frame, frame_index=frame, light_direction=light)
        except Exception as exc:
            self.runner.drop_messages()
            msg = f"Harmonizer: frame {frame} not enhanced ({raw}): {exc}"
            self.failed.append(msg)
            reports.post("ERROR", msg)
            return True
        self.runner.post_messages(frame)  # frame_index is the frame number here
        self.done += 1
        self.denoised += bool(result.report.get("denoised"))
        if result.report.get("denoise_decision"):
            self.denoise_decision = str(result.report["denoise_decision"])
        reset = result.report.get("reset")
        if reset:
            self.resets.append((frame, str(reset)))
        return True

    def close(self) -> None:
        self.runner.close()
        if self.scene.frame_current != self.start_frame:
            self.scene.frame_set(self.start_frame)

    def summary(self) -> str:
        dt = time.perf_counter() - self.started
        return (
            f"Harmonizer: {self.done} of {len(self.frames)} frames enhanced into {self.output} "
            f"in {dt:.1f} s ({len(self.failed)} failed, {self.denoised} denoised)"
        )


class HARMONIZER_OT_enhance_sequence(bpy.types.Operator):
    """Enhance a folder of rendered multilayer EXR frames with harmonizer (the scene's settings)"""

    bl_idname = "harmonizer.enhance_sequence"
    bl_label = "Enhance Rendered Sequence"
    bl_options = {"REGISTER"}

    directory: StringProperty(name="Rendered Frames", subtype="DIR_PATH")
    output_directory: StringProperty(
        name="Output",
        description="Where enhanced frames go (empty: a 'harmonized' folder inside the input)",
        subtype="DIR_PATH",
    )
    view_layer: StringProperty(name="View Layer", description="View layer in the files (empty: the first one)")
    use_modal: BoolProperty(options={"HIDDEN", "SKIP_SAVE"}, default=False)

    _job: _Job | None = None
    _timer = None

    def _start(self, context) -> _Job | None:
        directory = bpy.path.abspath(self.directory)
        if not directory or not os.path.isdir(directory):
            self.report({"ERROR"}, f"Harmonizer: input folder not found: {directory!r}")
            return None
        output = (
            bpy.path.abspath(self.output_directory) if self.output_directory else os.path.join(directory, "harmonized")
        )
        if os.path.abspath(output) == os.path.abspath(directory):
            self.report(
                {"ERROR"},
                f"Harmonizer: the output folder is the input folder ({directory}); raw frames are never overwritten",
            )
            return None
        try:
            return _Job(context.scene, directory, output, self.view_layer or context.scene.harmonizer.view_layer)
        except Exception as exc:
            self.report({"ERROR"}, f"Harmonizer: {exc}")
            return None

    def _finish(self, job: _Job) -> set[str]:
        job.close()
        self.report({"WARNING"} if job.failed else {"INFO"}, job.summary())
        for frame, reason in job.resets:
            print(f"Harmonizer: frame {frame}: temporal state reset ({reason})")
        if job.denoise_decision:
            print(f"Harmonizer: {job.denoise_decision}")
        return {"FINISHED"} if job.done else {"CANCELLED"}

    def execute(self, context):
        if self.use_modal and not bpy.app.background and context.window is not None:
            # Chosen in the file browser: run with a progress bar and Esc to cancel.
            return self._begin_modal(context)
        job = self._start(context)
        if job is None:
            return {"CANCELLED"}
        total = len(job.frames)
        try:
            while job.step():
                if sys.stdout.isatty() or bpy.app.background:
                    reports.progress(f"Harmonizer: {job.index}/{total} frames")
        except KeyboardInterrupt:
            reports.end_progress()
            self.report({"WARNING"}, "Harmonizer: cancelled")
            job.close()
            return {"CANCELLED"}
        reports.end_progress()
        return self._finish(job)

    def invoke(self, context, event):
        self.use_modal = True
        if not self.directory:
            context.window_manager.fileselect_add(self)
            return {"RUNNING_MODAL"}
        return self._begin_modal(context)

    def _begin_modal(self, context):
        job = self._start(context)
        if job is None:
            return {"CANCELLED"}
        self._job = job
        wm = context.window_manager
        wm.progress_begin(0, len(job.frames))
        self._timer = wm.event_timer_add(0.01, window=context.window)
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        job = self._job
        wm = context.window_manager
        if event.type == "ESC":
            self._end_modal(context)
            job.close()
            self.report({"WARNING"}, f"Harmonizer: cancelled after {job.done} of {len(job.frames)} frames")
            return {"CANCELLED"}
        if event.type == "TIMER":
            more = job.step()
            wm.progress_update(job.index)
            if context.area is not None:
                context.area.header_text_set(f"Harmonizer: frame {job.index}/{len(job.frames)} (Esc to cancel)")
            if not more:
                self._end_modal(context)
                return self._finish(job)
        return {"PASS_THROUGH"}

    def _end_modal(self, context):
        wm = context.window_manager
        if self._timer is not None:
            wm.event_timer_remove(self._timer)
            self._timer = None
        wm.progress_end()
        if context.area is not None:
            context.area.header_text_set(None)


def register() -> None:
    bpy.utils.register_class(HARMONIZER_OT_enhance_sequence)


def unregister() -> None:
    bpy.utils.unregister_class(HARMONIZER_OT_enhance_sequence)
