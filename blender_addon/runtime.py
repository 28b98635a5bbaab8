"""Opening a harmonizer session for a scene (shared by the handlers and the operator)."""

from __future__ import annotations

import bpy

from . import deps, passes, processor, reports


class Runner:
    """A device, a session and a frame processor for one sequence; close() frees them."""

    def __init__(self, scene: bpy.types.Scene, *, view_layer: str | None = None):
        s = scene.harmonizer
        hz = deps.harmonizer()
        oiio = deps.oiio()
        ocio = deps.ocio()
        if view_layer is None:
            vl = passes.render_view_layer(scene, s.view_layer)
            if vl is None:
                raise processor.FrameError(f"view layer {s.view_layer!r} not found in scene {scene.name!r}")
            view_layer = vl.name
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
            mask_names=names,
            mask_crypto_layer=crypto_layer,
            working_space=bpy.data.colorspace.working_space,
            replace_composite=s.replace_composite,
        )
        self.scene_name = scene.name
        self.device = hz.Device(threads=s.threads, ort_library=deps.onnxruntime_library())
        try:
            self.session = hz.Session(
                self.device,
                backend=s.backend,
                context_frames=s.context_frames,
                strength=s.strength,
                gap_policy=s.gap_policy,
                depth_kind="planar",
                on_message=self._on_message,
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

    def _on_message(self, level: str, text: str) -> None:
        lvl = {"error": "ERROR", "warning": "WARNING", "warn": "WARNING"}.get(str(level).lower(), "INFO")
        reports.post(lvl, f"Harmonizer: {text}")

    def close(self) -> None:
        """Free the session and the device."""
        session, self.session = getattr(self, "session", None), None
        device, self.device = getattr(self, "device", None), None
        if session is not None:
            session.close()
        if device is not None:
            device.close()


def camera_matrices(scene: bpy.types.Scene):
    """OpenEXR worldToCamera/worldToNDC of the scene camera at the current frame, or None."""
    import numpy as np

    cam = scene.camera
    if cam is None or cam.type != "CAMERA":
        return None
    r = scene.render
    x = max(1, int(r.resolution_x * r.resolution_percentage / 100))
    y = max(1, int(r.resolution_y * r.resolution_percentage / 100))
    try:
        depsgraph = bpy.context.evaluated_depsgraph_get()
        cam_eval = cam.evaluated_get(depsgraph)
        proj = cam_eval.calc_matrix_camera(depsgraph, x=x, y=y, scale_x=r.pixel_aspect_x, scale_y=r.pixel_aspect_y)
        world = cam_eval.matrix_world
    except Exception:
        return None
    if cam.data.type != "PERSP":
        # Orthographic/panoramic cameras: reproject with motion vectors only.
        return None
    return processor.blender_camera_matrices(np.array(world, dtype=np.float64), np.array(proj, dtype=np.float64))
