"""Scene settings of the extension (``scene.harmonizer``)."""

from __future__ import annotations

import bpy
from bpy.props import (
    BoolProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

BACKENDS = [
    ("auto", "Auto", "Neural model when ONNX Runtime is available, else classical"),
    ("neural", "Neural", "The one-step neural enhancer (ONNX Runtime)"),
    ("classical", "Classical", "Hole filling, harmonization, contact shadows and stabilization without a model"),
    ("bypass", "Bypass", "Pass frames through unchanged (checks the pipeline and color round trip)"),
]

MASK_SOURCES = [
    ("NONE", "None", "No inserted element"),
    ("OBJECT", "Object", "The inserted element is one object (uses the Cryptomatte Object pass)"),
    ("COLLECTION", "Collection", "The inserted element is every object of a collection (Cryptomatte Object pass)"),
    ("OBJECT_INDEX", "Object Index", "Pixels whose Object Index (pass index) equals a value, or one of several"),
    ("CRYPTOMATTE", "Cryptomatte", "Cryptomatte matte names, comma separated"),
]

CRYPTO_LAYERS = [
    ("CryptoObject", "Object", "Cryptomatte Object pass"),
    ("CryptoMaterial", "Material", "Cryptomatte Material pass"),
    ("CryptoAsset", "Asset", "Cryptomatte Asset pass"),
]

DENOISE_MODES = [
    (
        "auto",
        "Auto",
        "Denoise noisy renders: Cycles renders of at most 64 samples without Cycles' own denoiser; "
        "otherwise the first frame's measured noise decides (a frame Cycles denoised is not denoised again)",
    ),
    ("on", "On", "Denoise every frame with Open Image Denoise before it is enhanced"),
    ("off", "Off", "Never denoise"),
]

DENOISE_QUALITIES = [
    ("high", "High", "Open Image Denoise's best quality (slowest)"),
    ("balanced", "Balanced", "Faster, with slightly less detail"),
    ("fast", "Fast", "Fastest, for previews"),
]

LIGHT_SOURCES = [
    (
        "AUTO",
        "Scene Sun",
        "The strongest Sun light that renders, evaluated at each frame (animated suns follow); "
        "without one, the World's sun (a Sky Texture's or its environment image's); with neither, inserts "
        "cast no directional shadow",
    ),
    ("MANUAL", "Manual", "A fixed direction toward the light, in world space"),
    (
        "OFF",
        "Off",
        "No light direction: inserts get only the contact shadow under them, and their shading is kept",
    ),
]

COVERAGE = [
    ("ALPHA", "Alpha", "The Combined alpha is coverage: transparent pixels are holes to fill"),
    ("FULL", "Full", "Every pixel is rendered data (transparent film background is kept as is)"),
]


class HarmonizerSceneSettings(bpy.types.PropertyGroup):
    """Per-scene harmonizer settings."""

    enabled: BoolProperty(
        name="Harmonizer",
        description="Enhance every frame of animation renders with harmonizer",
        default=False,
    )
    backend: EnumProperty(name="Backend", items=BACKENDS, default="auto")
    context_frames: IntProperty(
        name="Context Frames",
        description="Previous enhanced frames that condition the next one (temporal stability)",
        default=4,
        min=0,
        max=8,
    )
    strength: FloatProperty(
        name="Strength",
        description="Blend between the raw (0) and the enhanced (1) frame",
        default=1.0,
        min=0.0,
        max=1.0,
    )
    coverage: EnumProperty(name="Coverage", items=COVERAGE, default="ALPHA")
    denoise: EnumProperty(
        name="Denoise",
        description="Denoise frames with Open Image Denoise before they are enhanced, during the render "
        "as each frame is written (the history of previous frames keeps the result stable)",
        items=DENOISE_MODES,
        default="auto",
    )
    denoise_quality: EnumProperty(name="Quality", items=DENOISE_QUALITIES, default="high")
    mask_source: EnumProperty(name="Insert Mask", items=MASK_SOURCES, default="NONE")
    mask_object: PointerProperty(name="Object", type=bpy.types.Object)
    mask_collection: PointerProperty(name="Collection", type=bpy.types.Collection)
    mask_index: IntProperty(name="Pass Index", default=1, min=0, max=32767)
    mask_more_indices: StringProperty(
        name="More Indices",
        description=(
            "Pass indices of further inserted objects, comma separated: with them each index is one object "
            "(its own harmonization, followed by its index, even where objects touch)"
        ),
    )
    mask_names: StringProperty(name="Mattes", description="Cryptomatte names, comma separated")
    mask_crypto_layer: EnumProperty(name="Cryptomatte Layer", items=CRYPTO_LAYERS, default="CryptoObject")
    match_tone: BoolProperty(
        name="Match Tone",
        description=(
            "Move each inserted object's exposure, white balance and saturation part of the way toward the "
            "background around it. For composites known to carry a tone mismatch: on correctly lit objects "
            "it changes colors that were right"
        ),
        default=False,
    )
    albedo_tone: BoolProperty(
        name="Albedo Tone",
        description=(
            "Correct each inserted object's exposure, white balance and saturation so that its albedo is "
            "shaded as the scene's light shades the background's (needs the Denoising Data passes: the "
            "albedo). A correctly lit object is left as it is"
        ),
        default=True,
    )
    light_source: EnumProperty(
        name="Light",
        description=(
            "Where the direction toward the light comes from: inserts cast their shadow away from it, "
            "and an insert lit by another light gets its shading"
        ),
        items=LIGHT_SOURCES,
        default="AUTO",
    )
    light_ratio: FloatProperty(
        name="Sun to Sky",
        description=(
            "The Sun's light against the sky's: irradiance on a surface facing the Sun over that on a "
            "surface in its shadow. 0: from the Sun's strength and the World where it says its light "
            "(a color or an environment image), else measured from each frame's own shadows. "
            "Measure Sun to Sky renders it for any World"
        ),
        default=0.0,
        min=0.0,
        max=12.0,
    )
    measured_light_color: FloatVectorProperty(
        name="Measured Sun",
        description=(
            "The Sun's irradiance per channel as Measure Sun to Sky rendered it (passed with Sun to Sky "
            "while that is the measured value)"
        ),
        size=3,
        default=(0.0, 0.0, 0.0),
        min=0.0,
    )
    measured_ambient_color: FloatVectorProperty(
        name="Measured Sky",
        description=(
            "The World's irradiance on a surface facing up per channel as Measure Sun to Sky rendered it "
            "(passed with Sun to Sky while that is the measured value)"
        ),
        size=3,
        default=(0.0, 0.0, 0.0),
        min=0.0,
    )
    light_direction: FloatVectorProperty(
        name="Direction",
        description="Direction toward the light, in world space (Z up); normalized when used",
        size=3,
        default=(0.0, 0.0, 1.0),
        subtype="DIRECTION",
    )
    view_layer: StringProperty(
        name="View Layer", description="View layer to enhance (empty: the first one that renders)", default=""
    )
    output_path: StringProperty(
        name="Enhanced Frames",
        description="Where enhanced frames go; '####' is the frame number. Empty: "
        "beside the raw frames, in a 'harmonized' folder with the same file names",
        default="",
        subtype="FILE_PATH",
    )
    overwrite_raw: BoolProperty(
        name="Replace Raw Frames",
        description="Write the enhanced frame over the raw render (the raw render is lost)",
        default=False,
    )
    replace_composite: BoolProperty(
        name="Replace Composite",
        description="Also replace the Composite part of the file with the enhanced frame",
        default=False,
    )
    gap_policy: EnumProperty(
        name="Frame Jump",
        items=[
            ("reset", "Reset", "A jump in frame numbers starts the temporal state over"),
            ("keep", "Keep", "Keep the temporal state across frame jumps"),
        ],
        default="reset",
    )
    threads: IntProperty(name="Threads", description="Worker threads (0: all cores)", default=0, min=0, max=1024)
    manage_passes: BoolProperty(
        name="Enable Needed Passes",
        description="At render start, enable the passes harmonizer reads and multilayer EXR output",
        default=True,
    )


def register() -> None:
    bpy.utils.register_class(HarmonizerSceneSettings)
    bpy.types.Scene.harmonizer = PointerProperty(type=HarmonizerSceneSettings)


def unregister() -> None:
    if hasattr(bpy.types.Scene, "harmonizer"):
        del bpy.types.Scene.harmonizer
    bpy.utils.unregister_class(HarmonizerSceneSettings)
