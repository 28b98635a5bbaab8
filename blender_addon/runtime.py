"""Opening a harmonizer session for a scene (shared by the handlers and the operator)."""

from __future__ import annotations

import re
from collections.abc import Callable

import bpy

from . import denoise, deps, light, passes, processor, reports


#: A frame number in a library message ("frame 12", "frame -3").
_FRAME_REF = re.compile(r"\bframe (-?\d+)\b")


def renumber(text: str, frame_of: Callable[[int], int] | None) -> str:
    """``text`` with every "frame N" of the library (its ``frame_index``) as Blender's frame."""
    if frame_of is None:
        return text
    return _FRAME_REF.sub(lambda m: f"frame {frame_of(int(m.group(1)))}", text)


class Runner:
    """A device, a session and a frame processor for one sequence; close() frees them."""

    def __init__(
        self,
        scene: bpy.types.Scene,
        *,
        view_layer: str | None = None,
        samples: int | None = None,
        denoise_mode: str | None = None,
        measure_light: bool = False,
    ):
        """A session for ``scene``'s settings.

        ``view_layer``: the layer in the files (default: the panel's, else the
        first that renders). ``samples``: the denoise stage's ``samples``
        parameter (default: from the scene's render settings, see
        ``denoise.session_samples``; the sequence operator passes what the
        files say, ``denoise.sequence_settings``). ``denoise_mode``: the
        ``denoise`` parameter (default: the panel's, see below).
        ``measure_light``: where the World does not say its light, render
        the Sun to Sky (``light.measure_ratio``, a second or two; from a
        render handler only in a background render: ``handlers``).
        """
        s = scene.harmonizer
        hz = deps.harmonizer()
        oiio = deps.oiio()
        ocio = deps.ocio()
        if view_layer is None:
            vl = passes.render_view_layer(scene, s.view_layer)
            if vl is None:
                raise processor.FrameError(f"view layer {s.view_layer!r} not found in scene {scene.name!r}")
            view_layer = vl.name
        #: Notes for the user at the start (posted by the caller).
        self.notes: list[tuple[str, str]] = []
        #: The denoise stage's ``denoise`` (the panel's, or ``temporal`` for
        #: a render Cycles denoises, see ``denoise.session_mode``; the
        #: sequence operator, which cannot tell, passes the panel's).
        self.denoise = denoise_mode or s.denoise
        if samples is None:
            vl = scene.view_layers.get(view_layer)
            self.denoise, mode_why = denoise.session_mode(scene, vl, s.denoise)
            samples, why = denoise.session_samples(scene, vl) if vl is not None else (0, "")
            if mode_why:
                self.notes.append(("INFO", f"Harmonizer: denoise temporal: {mode_why}"))
            elif samples == 0 and s.denoise == "auto" and why:
                # The library's decision on the first frame names the noise it measured.
                self.notes.append(("INFO", f"Harmonizer: denoise auto: the first frame's noise decides ({why})"))
        #: The denoise stage's ``samples`` (0: unknown).
        self.samples = int(samples)
        if s.denoise != "off" and deps.use_oidn_library() is None:
            self.notes.append(
                (
                    "WARNING" if s.denoise == "on" else "INFO",
                    "Harmonizer: this extension build bundles no Open Image Denoise (pyoidn wheel); "
                    "the library looks for it elsewhere and says what to install if it finds none",
                )
            )
        mask_source = s.mask_source
        names = passes.mask_names(scene)
        crypto_layer = s.mask_crypto_layer
        if mask_source in {"OBJECT", "COLLECTION"}:
            mask_source, crypto_layer = "CRYPTOMATTE", "CryptoObject"
        self.options = processor.Options(
            view_layer=view_layer,
            coverage=s.coverage,
            mask_source=mask_source,
            mask_index=s.mask_index,
            mask_indices=passes.mask_indices(scene),
            mask_names=names,
            mask_crypto_layer=crypto_layer,
            working_space=bpy.data.colorspace.working_space,
            replace_composite=s.replace_composite,
        )
        self.scene_name = scene.name
        #: The panel's Light at the start: 'AUTO', 'MANUAL' or 'OFF', and the
        #: manual direction (see ``light_at``).
        self.light_source = s.light_source
        self.manual_light = light.manual_direction(s.light_direction)
        if self.light_source == "MANUAL" and self.manual_light is None:
            self.notes.append(("WARNING", "Harmonizer: the manual light direction is (0, 0, 0): no cast shadows"))
        #: The session's ``light_ratio`` (see ``light.scene_ratio``), None
        #: to let the library measure it.
        self.light_ratio, ratio_from, colors = light_ratio_of(
            s, scene.view_layers.get(view_layer), scene.world, measure=measure_light
        )
        #: The session's ``light_color`` and ``ambient_color`` (empty where
        #: unknown): the light an insert over a background without albedo
        #: (a reconstruction) is matched to.
        self.light_colors = colors
        extra = {} if self.light_ratio is None else {"light_ratio": self.light_ratio, **colors}
        if self.light_ratio is not None:
            self.notes.append(("INFO", f"Harmonizer: Sun to Sky {self.light_ratio:.2f} ({ratio_from})"))
        self._messages: list[tuple[str, str]] = []
        self.device = hz.Device(threads=s.threads, ort_library=deps.onnxruntime_library())
        try:
            self.session = hz.Session(
                self.device,
                backend=s.backend,
                context_frames=s.context_frames,
                strength=s.strength,
                gap_policy=s.gap_policy,
                depth_kind="planar",
                light_space="world",  # Blender's world: the camera matrices' and the Sun's
                match_tone=s.match_tone,
                albedo_tone=s.albedo_tone,
                denoise=self.denoise,
                denoise_quality=s.denoise_quality,
                samples=self.samples,
                on_message=self._on_message,
                **extra,
            )
        except BaseException:
            self.device.close()
            raise
        self.processor = processor.FrameProcessor(
            self.session,
            oiio=oiio,
            ocio=ocio,
            ocio_config=deps.ocio_config_path(),
            options=self.options,
        )
        self.error_type = hz.HarmonizerError

    def light_at(self, scene: bpy.types.Scene, depsgraph=None) -> tuple[float, float, float] | None:
        """The direction toward the light for the frame ``scene`` (or
        ``depsgraph``) is evaluated at: the panel's manual one, none, or the
        strongest Sun's or the Sky Texture's sun (``light.scene_direction``)."""
        if self.light_source == "OFF":
            return None
        if self.light_source == "MANUAL":
            return self.manual_light
        vl = scene.view_layers.get(self.options.view_layer) or passes.render_view_layer(scene, "")
        return None if vl is None else light.scene_direction(vl, depsgraph, scene.world)

    def light_at_frame(self, scene: bpy.types.Scene, frame: int) -> tuple[float, float, float] | None:
        """``light_at`` for ``frame`` of the open scene, moving the scene to
        that frame (``frame_set``) when a Sun or a sky may be animated; the caller
        puts the frame back when done."""
        if self.light_source == "AUTO" and scene.frame_current != frame:
            vl = scene.view_layers.get(self.options.view_layer) or passes.render_view_layer(scene, "")
            if vl is not None and (light.suns(vl) or light.sky_sun(scene.world) is not None):
                scene.frame_set(frame)
        return self.light_at(scene)

    def _on_message(self, level: str, text: str) -> None:
        # Kept until the frame is done: post_messages reports each once, with
        # Blender's frame numbers (the library numbers frames by frame_index).
        self._messages.append((str(level).lower(), text))

    def post_messages(self, frame: int, frame_of: Callable[[int], int] | None = None) -> list[str]:
        """Report the library's warnings about the frame just processed, once each.

        ``frame_of`` turns the library's frame numbers (the ``frame_index``
        passed) into Blender's; every "frame N" of a message is rewritten, and a
        message that does not start with the frame gets it in front. The
        library's notes on a temporal reset are not repeated: the caller's own
        line about the frame names the reset. Returns the warnings posted.
        """
        messages, self._messages = self._messages, []
        posted = []
        for level, text in messages:
            if level not in ("warning", "warn", "error"):
                continue
            text = renumber(text, frame_of)
            if not text.startswith(f"frame {frame}:"):
                text = f"frame {frame}: {text}"
            text = f"Harmonizer: {text}"
            reports.post("ERROR" if level == "error" else "WARNING", text)
            posted.append(text)
        return posted

    def drop_messages(self) -> None:
        """Forget messages of a frame that failed (the error says what happened)."""
        self._messages = []

    def close(self) -> None:
        """Free the session and the device."""
        session, self.session = getattr(self, "session", None), None
        device, self.device = getattr(self, "device", None), None
        if session is not None:
            session.close()
        if device is not None:
            device.close()


def camera_params(scene: bpy.types.Scene, depsgraph=None) -> processor.CameraParams | None:
    """The scene camera as plain values (perspective only), or None.

    With ``depsgraph`` (a ``frame_change_post`` handler's), the camera evaluated
    in it: during an animation render that is the camera at the frame being
    rendered, while ``scene.camera.matrix_world`` still holds the camera at the
    frame the render started from. Without it, the original object's
    properties (right in the main thread after ``frame_set``).
    """
    import numpy as np

    cam = scene.camera
    if cam is None or cam.type != "CAMERA":
        return None
    if depsgraph is not None:
        cam = cam.evaluated_get(depsgraph)
    data = cam.data
    if data.type != "PERSP":
        return None  # orthographic/panoramic: the library reprojects with motion vectors only
    r = scene.render
    return processor.CameraParams(
        matrix_world=np.array(cam.matrix_world, dtype=np.float64),
        lens=data.lens,
        sensor_width=data.sensor_width,
        sensor_height=data.sensor_height,
        sensor_fit=data.sensor_fit,
        shift_x=data.shift_x,
        shift_y=data.shift_y,
        clip_start=data.clip_start,
        width=max(1, int(r.resolution_x * r.resolution_percentage / 100)),
        height=max(1, int(r.resolution_y * r.resolution_percentage / 100)),
        pixel_aspect_x=r.pixel_aspect_x,
        pixel_aspect_y=r.pixel_aspect_y,
    )


def camera_matrices(scene: bpy.types.Scene, depsgraph=None):
    """OpenEXR worldToCamera/worldToNDC of the scene camera (see ``camera_params``), or None."""
    params = camera_params(scene, depsgraph)
    return None if params is None else processor.blender_camera_matrices(params)


def light_ratio_of(
    s, view_layer: bpy.types.ViewLayer | None, world, measure: bool = False
) -> tuple[float | None, str, dict[str, str]]:
    """The session's ``light_ratio``, where it came from, and the library's
    ``light_color`` and ``ambient_color`` where known (else empty): the
    panel's *Sun to Sky* when set (with the colors *Measure* stored, while
    the value is the one it measured); else, with the Light on *Scene Sun*,
    the Sun's light and the World's where the World says it
    (``light.scene_light``), or with ``measure`` as Cycles renders them
    (``light.measure_ratio``); else None (the library measures it)."""
    if s.light_ratio > 0:
        colors = {}
        got = light.RatioMeasure.of(tuple(s.measured_light_color), tuple(s.measured_ambient_color), "")
        if got is not None and abs(got.ratio - s.light_ratio) <= 0.01 * s.light_ratio:
            colors = got.params()
        return float(s.light_ratio), "the panel's", colors
    if s.light_source != "AUTO" or view_layer is None:
        return None, "none", {}
    got = light.scene_light(view_layer, world)
    if got is not None:
        return got.ratio, "Sun and World", got.params()
    if measure:
        got = light.measure_ratio(view_layer, world)
        if got is not None:
            return got.ratio, f"rendered: {got.source} over the World", got.params()
    return None, "none", {}
