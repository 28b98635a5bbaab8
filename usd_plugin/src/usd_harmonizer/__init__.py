"""usd_harmonizer: post-process the render products of a USD stage with harmonizer.

Resolves the stage's RenderSettings, RenderProducts and RenderVars, enhances
each product's frames in order with one temporal session per product
(through the ``harmonizer`` Python binding), writes enhanced EXRs keeping
every channel and attribute, and records them as new RenderProducts in a
separate layer. ``PostFrameHook`` does the same one frame per call for
render farms.
"""

from .errors import (
    BindingError,
    CameraError,
    ColorSpaceError,
    FrameError,
    ProductFileError,
    SettingsError,
    UsdHarmonizerError,
    VarError,
)
from .frames import expand_frame_tokens, parse_frame_range
from .hook import PostFrameHook
from .layer import write_layer
from .process import FrameResult, Options, ProductRunner
from .run import RunSummary, run_stage
from .settings import ProductInfo, SettingsInfo, VarInfo, open_stage, resolve

__version__ = "0.2.0"

__all__ = [
    "BindingError",
    "CameraError",
    "ColorSpaceError",
    "FrameError",
    "FrameResult",
    "Options",
    "PostFrameHook",
    "ProductFileError",
    "ProductInfo",
    "ProductRunner",
    "RunSummary",
    "SettingsError",
    "SettingsInfo",
    "UsdHarmonizerError",
    "VarError",
    "VarInfo",
    "__version__",
    "expand_frame_tokens",
    "open_stage",
    "parse_frame_range",
    "resolve",
    "run_stage",
    "write_layer",
]
