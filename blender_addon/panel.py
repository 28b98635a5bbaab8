"""The Harmonizer panel in Properties > Render."""

from __future__ import annotations

import bpy

from . import handlers, passes, reports


class HARMONIZER_OT_setup_passes(bpy.types.Operator):
    """Enable the passes harmonizer reads and multilayer EXR output for this scene"""

    bl_idname = "harmonizer.setup_passes"
    bl_label = "Set Up Passes"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        msgs = passes.check(context.scene, apply=True)
        for level, text in msgs:
            self.report({level}, text)
        if not msgs:
            self.report({"INFO"}, "Harmonizer: passes and output are already set up")
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
        col.prop(s, "mask_source")
        if s.mask_source == "OBJECT":
            col.prop(s, "mask_object")
        elif s.mask_source == "COLLECTION":
            col.prop(s, "mask_collection")
        elif s.mask_source == "OBJECT_INDEX":
            col.prop(s, "mask_index")
        elif s.mask_source == "CRYPTOMATTE":
            col.prop(s, "mask_crypto_layer")
            col.prop(s, "mask_names")

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
            box.label(text=f"Last render: {ok} frames enhanced, {len(log.errors)} errors", icon="INFO")
            for text in log.errors[-3:]:
                box.label(text=text.removeprefix("Harmonizer: "), icon="CANCEL")
        elif reports.RECENT:
            level, text = reports.RECENT[-1]
            if level == "ERROR":
                layout.label(text=text.removeprefix("Harmonizer: "), icon="CANCEL")


CLASSES = (HARMONIZER_OT_setup_passes, RENDER_PT_harmonizer)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
