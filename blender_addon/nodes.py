"""The "Harmonizer" compositor node group: the enhanced sequence inside the compositing tree.

No Python runs while Blender composites, so the enhancement happens when each
frame is written (see ``handlers``) and the compositor reads the result back:
the group holds an Image node on the enhanced EXR sequence and outputs its
Image and Alpha. Re-running a compositor-only render picks up the enhanced
frames like any other image sequence.
"""

from __future__ import annotations

import os

import bpy

from . import passes

GROUP_NAME = "Harmonizer"
_SCENE_KEY = "harmonizer_scene"


def enhanced_sequence(scene: bpy.types.Scene) -> tuple[str, int, int]:
    """(path of the first enhanced frame, first frame, number of frames) for ``scene``."""
    first = scene.frame_start
    raw = scene.render.frame_path(frame=first)
    return passes.enhanced_path(scene, raw, first), first, scene.frame_end - scene.frame_start + 1


def _sequence_image(path: str) -> bpy.types.Image:
    abspath = os.path.abspath(bpy.path.abspath(path))
    for img in bpy.data.images:
        if img.source == "SEQUENCE" and os.path.abspath(bpy.path.abspath(img.filepath)) == abspath:
            return img
    if os.path.isfile(abspath):
        img = bpy.data.images.load(abspath, check_existing=False)
    else:
        # Not rendered yet: an image that points at the sequence; it loads once the files exist.
        img = bpy.data.images.new(os.path.basename(abspath), 4, 4, float_buffer=True)
        img.source = "FILE"
        img.filepath = abspath
    img.source = "SEQUENCE"
    img.name = "Harmonizer " + os.path.basename(abspath)
    return img


def group_for_scene(scene: bpy.types.Scene) -> bpy.types.NodeTree:
    """Create or update the Harmonizer node group reading ``scene``'s enhanced sequence."""
    tree = None
    for ng in bpy.data.node_groups:
        if ng.bl_idname == "CompositorNodeTree" and ng.get(_SCENE_KEY) == scene.name:
            tree = ng
            break
    if tree is None:
        tree = bpy.data.node_groups.new(GROUP_NAME, "CompositorNodeTree")
        tree[_SCENE_KEY] = scene.name
        tree.description = "Enhanced frames written by harmonizer (an Image node on the enhanced EXR sequence)"
    tree.nodes.clear()
    tree.interface.clear()
    tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
    tree.interface.new_socket("Alpha", in_out="OUTPUT", socket_type="NodeSocketFloat")

    path, first, count = enhanced_sequence(scene)
    img_node = tree.nodes.new("CompositorNodeImage")
    img_node.name = img_node.label = "Enhanced Sequence"
    img_node.image = _sequence_image(path)
    img_node.frame_start = first
    img_node.frame_duration = count
    img_node.frame_offset = first - 1
    img_node.use_auto_refresh = True
    img_node.location = (-300, 0)
    if getattr(img_node, "has_layers", False):
        vl = passes.render_view_layer(scene, scene.harmonizer.view_layer)
        if vl is not None:
            try:
                img_node.layer = vl.name
            except TypeError:
                pass  # file not rendered yet: Blender picks the layer once it loads
    out = tree.nodes.new("NodeGroupOutput")
    out.location = (100, 0)
    image_socket = img_node.outputs.get("Combined") or img_node.outputs.get("Image") or img_node.outputs[0]
    tree.links.new(image_socket, out.inputs["Image"])
    tree.links.new(img_node.outputs["Alpha"], out.inputs["Alpha"])
    return tree


class HARMONIZER_OT_add_node(bpy.types.Operator):
    """Add the Harmonizer node: the enhanced frames of this scene in the compositing tree"""

    bl_idname = "node.harmonizer_add"
    bl_label = "Harmonizer"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        space = context.space_data
        return (
            space is not None
            and space.type == "NODE_EDITOR"
            and space.tree_type == "CompositorNodeTree"
            and space.edit_tree is not None
        )

    def execute(self, context):
        scene = context.scene
        group = group_for_scene(scene)
        tree = context.space_data.edit_tree
        for n in tree.nodes:
            n.select = False
        node = tree.nodes.new("CompositorNodeGroup")
        node.node_tree = group
        node.label = GROUP_NAME
        node.location = context.space_data.cursor_location
        node.select = True
        tree.nodes.active = node
        path, _first, _count = enhanced_sequence(scene)
        if not os.path.isfile(bpy.path.abspath(path)):
            self.report({"WARNING"}, f"Harmonizer: no enhanced frames yet at {path}; render the animation first")
        return {"FINISHED"}


def add_to_tree(scene: bpy.types.Scene, tree: bpy.types.NodeTree) -> bpy.types.Node:
    """Add a Harmonizer group node for ``scene`` to ``tree`` (for scripts)."""
    node = tree.nodes.new("CompositorNodeGroup")
    node.node_tree = group_for_scene(scene)
    node.label = GROUP_NAME
    return node


def _menu_draw(self, context):
    space = context.space_data
    if space is not None and getattr(space, "tree_type", "") == "CompositorNodeTree":
        self.layout.separator()
        self.layout.operator(HARMONIZER_OT_add_node.bl_idname, text="Harmonizer", icon="SHADERFX")


_MENU = "NODE_MT_category_compositor_input"


def register() -> None:
    bpy.utils.register_class(HARMONIZER_OT_add_node)
    menu = getattr(bpy.types, _MENU, None)
    if menu is not None:
        menu.append(_menu_draw)


def unregister() -> None:
    menu = getattr(bpy.types, _MENU, None)
    if menu is not None:
        menu.remove(_menu_draw)
    bpy.utils.unregister_class(HARMONIZER_OT_add_node)
