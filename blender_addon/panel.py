"""The Harmonizer panel in Properties > Render."""

from __future__ import annotations

import math

import bpy

from . import denoise, handlers, light, passes, reports


class HARMONIZER_OT_setup_passes(bpy.types.Operator):
    """Enable the passes harmonizer reads (Denoising Data too when frames will be denoised) and multilayer EXR output"""

    bl_idname = "harmonizer.setup_passes"
    bl_label = "Set Up Passes"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        msgs = passes.check(context.scene, apply=True, denoising_data=True)
        for level, text in msgs:
            self.report({level}, text)
        if not msgs:
            self.report({"INFO"}, "Harmonizer: passes and output are already set up")
        return {"FINISHED"}


class HARMONIZER_OT_measure_light_ratio(bpy.types.Operator):
    """Render the Sun's light against the World's with Cycles (a white square under each) and set Sun to Sky"""

    bl_idname = "harmonizer.measure_light_ratio"
    bl_label = "Measure Sun to Sky"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        scene = context.scene
        vl = passes.render_view_layer(scene, scene.harmonizer.view_layer)
        got = None if vl is None else light.measure_ratio(vl, scene.world)
        if got is None:
            self.report(
                {"WARNING"},
                "Harmonizer: no Sun to Sky to measure: it needs a World and a Sun light "
                "or a Sky Texture with its sun disc on",
            )
            return {"CANCELLED"}
        scene.harmonizer.light_ratio = got.ratio
        scene.harmonizer.measured_light_color = got.direct_rgb
        scene.harmonizer.measured_ambient_color = got.ambient_rgb
        clipped = " (the largest taken)" if got.ratio < got.direct / (0.5 * got.ambient) else ""
        self.report(
            {"INFO"},
            f"Harmonizer: Sun to Sky {got.ratio:.2f}{clipped}: {got.source} {got.direct:.3g} "
            f"over half the World's {got.ambient:.3g} (irradiance, rendered by Cycles)",
        )
        return {"FINISHED"}


class RENDER_PT_harmonizer(bpy.types.Panel):
    bl_label = "Harmonizer"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    bl_options = {"DEFAULT_CLOSED"}

    def draw_header(self, context):
        self.layout.prop(context.scene.harmonizer, "enabled", text="")

    def draw(self, context):
        scene = context.scene
        s = scene.harmonizer
        layout = self.layout
        layout.use_property_split = True
        layout.use_property_decorate = False
        col = layout.column()
        col.active = s.enabled
        col.prop(s, "backend")
        col.prop(s, "context_frames")
        col.prop(s, "strength", slider=True)
        col.prop(s, "gap_policy")
        col.prop(s, "coverage")

        col.separator()
        col.prop(s, "denoise")
        sub = col.column()
        sub.active = s.enabled and s.denoise != "off"
        sub.prop(s, "denoise_quality")
        vl = passes.render_view_layer(scene, s.view_layer)
        if vl is not None and denoise.guides_available(scene, vl):
            # Blender's own setting of the view layer: ticking it is the user asking for the passes.
            sub.prop(vl.cycles, "denoising_store_passes", text="Denoising Data")
        if vl is not None and s.denoise == "auto":
            sub.label(text=denoise.auto_summary(scene, vl), icon="INFO")

        col.separator()
        col.prop(s, "mask_source")
        if s.mask_source == "OBJECT":
            col.prop(s, "mask_object")
        elif s.mask_source == "COLLECTION":
            col.prop(s, "mask_collection")
        elif s.mask_source == "OBJECT_INDEX":
            col.prop(s, "mask_index")
            col.prop(s, "mask_more_indices")
        elif s.mask_source == "CRYPTOMATTE":
            col.prop(s, "mask_crypto_layer")
            col.prop(s, "mask_names")
        if s.mask_source != "NONE":
            col.prop(s, "albedo_tone")
            if s.albedo_tone and vl is not None and not denoise.guides_on(vl):
                col.label(text="Albedo Tone reads the Denoising Data passes", icon="INFO")
            col.prop(s, "match_tone")
        col.prop(s, "light_source")
        if s.light_source == "MANUAL":
            col.prop(s, "light_direction")
        elif s.light_source == "AUTO" and vl is not None:
            best = light.dominant_sun(vl)
            sky = None if best is not None else light.sky_sun(scene.world)
            if best is not None:
                col.label(text=f"{best[0].name} (strength {best[1]:g})", icon="LIGHT_SUN")
            elif sky is not None:
                elev = math.degrees(float(sky.sun_elevation))
                col.label(text=f"Sky Texture sun (elevation {elev:.1f}\u00b0)", icon="LIGHT_SUN")
            elif (env := light.env_sun(scene.world)) is not None:
                elev = math.degrees(math.asin(max(-1.0, min(1.0, env[0][2]))))
                col.label(text=f"Environment image sun (elevation {elev:.1f}\u00b0)", icon="LIGHT_SUN")
            else:
                col.label(text="No Sun light: no cast shadows", icon="INFO")
        if s.light_source != "OFF":
            col.prop(s, "light_ratio")
            if s.light_ratio <= 0:
                auto = light.scene_ratio(vl, scene.world) if s.light_source == "AUTO" and vl is not None else None
                if auto is None:
                    col.label(text="Sun to Sky: measured from each frame", icon="INFO")
                    col.operator(HARMONIZER_OT_measure_light_ratio.bl_idname, icon="WORLD")
                else:
                    col.label(text=f"Sun to Sky {auto:.2f} (Sun and World)", icon="WORLD")

        col.separator()
        col.prop_search(s, "view_layer", scene, "view_layers")
        col.prop(s, "output_path")
        col.prop(s, "overwrite_raw")
        col.prop(s, "replace_composite")
        col.prop(s, "threads")
        col.prop(s, "manage_passes")

        problems = [m for m in passes.check(scene, apply=False) if m[0] != "INFO"]
        if problems:
            box = col.box()
            for _level, text in problems:
                box.label(text=text.removeprefix("Harmonizer: "), icon="ERROR")
            box.operator(HARMONIZER_OT_setup_passes.bl_idname, icon="RENDERLAYERS")
        col.separator()
        col.operator("harmonizer.enhance_sequence", icon="SEQUENCE")

        log = handlers.last_run(scene.name)
        if log is not None and (log.frames or log.errors):
            box = layout.box()
            ok = sum(1 for f in log.frames if f.get("output"))
            box.label(
                text=f"Last render: {ok} frames enhanced, {log.denoised} denoised, {len(log.errors)} errors",
                icon="INFO",
            )
            if log.denoise_decision:
                box.label(text=log.denoise_decision)
            for text in log.errors[-3:]:
                box.label(text=text.removeprefix("Harmonizer: "), icon="CANCEL")
        elif reports.RECENT:
            level, text = reports.RECENT[-1]
            if level == "ERROR":
                layout.label(text=text.removeprefix("Harmonizer: "), icon="CANCEL")


CLASSES = (HARMONIZER_OT_setup_passes, HARMONIZER_OT_measure_light_ratio, RENDER_PT_harmonizer)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
