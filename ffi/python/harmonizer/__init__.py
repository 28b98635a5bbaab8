"""harmonizer: Python binding of ``libharmonizer`` (ctypes + numpy).

Shared by the Blender extension and the USD hook; imports neither ``bpy`` nor
``pxr``. The library is found through ``$HARMONIZER_LIB`` (an override), inside
this package (the wheel's ``harmonizer/lib/``, or next to it), or in the
repository's ``target/release`` / ``target/debug``.

Conventions: color is scene-linear Linear Rec.709 premultiplied by coverage;
depth planar; motion vectors in pixels from the current pixel to where the
surface was in the previous frame, x right, y down; camera matrices are
OpenEXR row-vector ``worldToCamera`` / ``worldToNDC``.
"""

from ._api import Device, Session, parse_param, version
from .errors import (
    CancelledError,
    HarmonizerError,
    InvalidArgumentError,
    InvalidOperationError,
    IoError,
    LibraryNotFoundError,
    ModelError,
    NotSupportedError,
    OutOfMemoryError,
    RuntimeMissingError,
    Status,
    UnknownError,
)

#: Version of this binding (equals the library's version it ships with).
__version__ = "0.2.0"

__all__ = [
    "CancelledError",
    "Device",
    "HarmonizerError",
    "InvalidArgumentError",
    "InvalidOperationError",
    "IoError",
    "LibraryNotFoundError",
    "ModelError",
    "NotSupportedError",
    "OutOfMemoryError",
    "RuntimeMissingError",
    "Session",
    "Status",
    "UnknownError",
    "__version__",
    "parse_param",
    "version",
]
