"""Finds and loads ``libharmonizer`` and declares the C ABI for ctypes.

Search order: ``$HARMONIZER_LIB`` (a file: an override), the library the wheel
carries (``harmonizer/lib/libharmonizer.so``), the library next to this package
(``harmonizer/libharmonizer.so``, the layout of ``scripts/build-ffi.sh``'s
prefix), then the repository's ``target/release`` and ``target/debug`` (and
``$CARGO_TARGET_DIR``'s), the most recently built first.

The runtimes the library loads itself are located here too when their Python
wheels are installed (``harmonizer[neural]``: onnxruntime, ``harmonizer[denoise]``:
pyoidn); see :func:`ort_library` and :func:`oidn_library`.
"""

from __future__ import annotations

import ctypes
import os
import sys
import threading
from ctypes import (
    CFUNCTYPE,
    POINTER,
    Structure,
    c_bool,
    c_char_p,
    c_double,
    c_float,
    c_int64,
    c_size_t,
    c_uint32,
    c_uint64,
    c_void_p,
)
from pathlib import Path

from .errors import LibraryNotFoundError, error_for

#: The header major version this binding is written against (``HZ_VERSION_MAJOR``).
ABI_MAJOR = 0
#: The header minor version this binding needs at least (``HZ_VERSION_MINOR``).
ABI_MINOR = 2

HZ_FORMAT_F32 = 1
HZ_FORMAT_F16 = 2
HZ_FRAME_RESET = 1
HZ_FRAME_HAS_INDEX = 2
HZ_PARAM_INT = 1
HZ_PARAM_FLOAT = 2
HZ_PARAM_BOOL = 3
HZ_PARAM_STRING = 4
HZ_MESSAGE_INFO = 1
HZ_MESSAGE_WARNING = 2


class hz_image(Structure):  # noqa: N801 (C name)
    _fields_ = [
        ("struct_size", c_size_t),
        ("format", c_uint32),
        ("channels", c_uint32),
        ("width", c_size_t),
        ("height", c_size_t),
        ("offset", c_size_t),
        ("pixel_stride", c_size_t),
        ("row_stride", c_size_t),
        ("data", c_void_p),
    ]


class hz_frame(Structure):  # noqa: N801
    _fields_ = [
        ("struct_size", c_size_t),
        ("color", POINTER(hz_image)),
        ("depth", POINTER(hz_image)),
        ("motion", POINTER(hz_image)),
        ("normal", POINTER(hz_image)),
        ("coverage", POINTER(hz_image)),
        ("insert_mask", POINTER(hz_image)),
        ("world_to_camera", POINTER(c_float)),
        ("world_to_ndc", POINTER(c_float)),
        ("frame_index", c_int64),
        ("flags", c_uint32),
        ("motion_vector_scale", c_float * 2),
        # Appended after the fields above (a library that predates them
        # refuses this struct_size).
        ("albedo", POINTER(hz_image)),
        ("denoise_normal", POINTER(hz_image)),
        ("insert_id", POINTER(hz_image)),
    ]


class hz_device_options(Structure):  # noqa: N801
    _fields_ = [
        ("struct_size", c_size_t),
        ("threads", c_uint32),
        ("memory_limit", c_uint64),
        ("ort_library", c_char_p),
        ("model_path", c_char_p),
        ("model_data", c_void_p),
        ("model_data_size", c_size_t),
        ("model_manifest", c_char_p),
    ]


HZ_RUN_HAS_FRAMES = 1
HZ_RUN_HAS_INSERT_INDEX = 2
HZ_RUN_RENDER_HINTS = 4


class hz_run_options(Structure):  # noqa: N801
    _fields_ = [
        ("struct_size", c_size_t),
        ("input", c_char_p),
        ("output", c_char_p),
        ("layout", c_char_p),
        ("channels", c_char_p),
        ("flags", c_uint32),
        ("frame_first", c_int64),
        ("frame_last", c_int64),
        ("preroll", c_size_t),
        ("insert_index", c_int64),
        ("report", c_char_p),
        ("insert_indices", POINTER(c_int64)),
        ("insert_index_count", c_size_t),
    ]


PROGRESS_FN = CFUNCTYPE(c_bool, c_void_p, c_double)
RUN_FRAME_FN = CFUNCTYPE(c_bool, c_void_p, c_char_p)
MESSAGE_FN = CFUNCTYPE(None, c_void_p, c_uint32, c_char_p)

_STR_OUT = [c_void_p, c_char_p, c_size_t, POINTER(c_size_t)]

# name: (argument types); every function returns hz_status (uint32) unless listed in _RESTYPE.
_PROTOTYPES: dict[str, list] = {
    "hz_version": [],
    "hz_last_error_message": [],
    "hz_status_name": [c_uint32],
    "hz_check_version": [c_uint32, c_uint32],
    "hz_device_new": [c_uint32, POINTER(hz_device_options), POINTER(c_void_p)],
    "hz_device_free": [c_void_p],
    "hz_device_get_threads": [c_void_p, POINTER(c_uint32)],
    "hz_session_new": [c_void_p, POINTER(c_void_p)],
    "hz_session_free": [c_void_p],
    "hz_session_set_int": [c_void_p, c_char_p, c_int64],
    "hz_session_set_float": [c_void_p, c_char_p, c_double],
    "hz_session_set_bool": [c_void_p, c_char_p, c_bool],
    "hz_session_set_string": [c_void_p, c_char_p, c_char_p],
    "hz_session_get_type": [c_void_p, c_char_p, POINTER(c_uint32)],
    "hz_session_get_int": [c_void_p, c_char_p, POINTER(c_int64)],
    "hz_session_get_float": [c_void_p, c_char_p, POINTER(c_double)],
    "hz_session_get_bool": [c_void_p, c_char_p, POINTER(c_bool)],
    "hz_session_get_string": [c_void_p, c_char_p, c_char_p, c_size_t, POINTER(c_size_t)],
    "hz_session_commit": [c_void_p],
    "hz_session_reset": [c_void_p],
    "hz_session_set_progress_callback": [c_void_p, PROGRESS_FN, c_void_p],
    "hz_session_set_message_callback": [c_void_p, MESSAGE_FN, c_void_p],
    "hz_session_process": [c_void_p, POINTER(hz_frame), POINTER(hz_image)],
    "hz_session_get_history_length": [c_void_p, POINTER(c_size_t)],
    "hz_session_get_memory_bytes": [c_void_p, POINTER(c_size_t)],
    "hz_session_get_tile_overlap": [c_void_p, POINTER(c_size_t)],
    "hz_session_get_backend_name": _STR_OUT,
    "hz_session_get_model_name": _STR_OUT,
    "hz_session_get_model_version": _STR_OUT,
    "hz_session_get_report_json": _STR_OUT,
}
# Added after 0.2.0's first release (issue 22): looked up when used, so this
# binding still loads a library without them.
_OPTIONAL: dict[str, list] = {
    "hz_run_sequence": [c_void_p, POINTER(hz_run_options), RUN_FRAME_FN, c_void_p],
}
_RESTYPE = {"hz_version": c_char_p, "hz_last_error_message": c_char_p, "hz_status_name": c_char_p}


def _lib_name() -> str:
    if sys.platform == "darwin":
        return "libharmonizer.dylib"
    if os.name == "nt":
        return "harmonizer.dll"
    return "libharmonizer.so"


def candidates() -> list[Path]:
    """Paths searched for the library, in order."""
    env = os.environ.get("HARMONIZER_LIB")
    if env:
        return [Path(env)]
    name = _lib_name()
    here = Path(__file__).resolve().parent
    targets = []
    if os.environ.get("CARGO_TARGET_DIR"):
        targets.append(Path(os.environ["CARGO_TARGET_DIR"]))
    if len(here.parents) >= 3:
        targets.append(here.parents[2] / "target")  # <repo>/ffi/python/harmonizer -> <repo>/target
    built = [t / profile / name for t in targets for profile in ("release", "debug")]
    # In a checkout, the most recently built library wins (a stale release build
    # must not shadow a fresh debug one).
    built.sort(key=lambda p: p.stat().st_mtime if p.is_file() else float("-inf"), reverse=True)
    return [here / "lib" / name, here / name, *built]


def _wheel_library(package: str, subdir: str, patterns: tuple[str, ...]) -> Path | None:
    """A shared library inside an installed Python package, found without
    importing the package (``importlib.util.find_spec`` of a top-level name
    reads no module code). The highest-named match wins (``.so.1.31.1`` over
    ``.so.1``)."""
    import importlib.util

    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    for root in spec.submodule_search_locations:
        d = Path(root) / subdir
        found = sorted(p for pat in patterns for p in d.glob(pat) if p.is_file())
        if found:
            return found[-1]
    return None


def ort_library() -> Path | None:
    """``libonnxruntime`` of the installed ``onnxruntime`` wheel
    (``pip install harmonizer[neural]``), or None."""
    return _wheel_library("onnxruntime", "capi", ("libonnxruntime.so*", "libonnxruntime*.dylib", "onnxruntime.dll"))


def oidn_library() -> Path | None:
    """``libOpenImageDenoise`` of the installed ``pyoidn`` wheel
    (``pip install harmonizer[denoise]``), or None."""
    return _wheel_library(
        "pyoidn", "oidn/lib", ("libOpenImageDenoise.so*", "libOpenImageDenoise*.dylib", "OpenImageDenoise.dll")
    )


_lock = threading.Lock()
_lib: ctypes.CDLL | None = None


def lib() -> ctypes.CDLL:
    """The loaded library (loaded once, on first use)."""
    global _lib
    if _lib is not None:
        return _lib
    with _lock:
        if _lib is None:
            _lib = _load()
    return _lib


def _load() -> ctypes.CDLL:
    tried = candidates()
    path = next((p for p in tried if p.is_file()), None)
    if path is None:
        where = ", ".join(str(p) for p in tried)
        raise LibraryNotFoundError(
            f"libharmonizer not found (looked at {where}); build it with "
            "`cargo build --release -p harmonizer-ffi` or set HARMONIZER_LIB to its path"
        )
    try:
        cdll = ctypes.CDLL(str(path))
    except OSError as e:
        raise LibraryNotFoundError(f"cannot load {path}: {e}") from e
    for name, args in _PROTOTYPES.items():
        try:
            fn = getattr(cdll, name)
        except AttributeError as e:
            raise LibraryNotFoundError(f"{path} has no symbol {name}: the library is too old for this binding") from e
        fn.argtypes = args
        fn.restype = _RESTYPE.get(name, c_uint32)
    for name, args in _OPTIONAL.items():
        fn = getattr(cdll, name, None)
        if fn is not None:
            fn.argtypes = args
            fn.restype = c_uint32
    st = cdll.hz_check_version(ABI_MAJOR, ABI_MINOR)
    if st != 0:
        raise error_for(st, f"{path}: " + cdll.hz_last_error_message().decode("utf-8", "replace"))
    return cdll


def optional(name: str):
    """An optional function of the library (see ``_OPTIONAL``), or raises
    :class:`NotSupportedError` naming it when the library predates it."""
    fn = getattr(lib(), name, None)
    if fn is None:
        from .errors import NotSupportedError

        raise NotSupportedError(f"{lib()._name} has no {name}: the library is older than this binding")
    return fn


def check(status: int) -> None:
    """Raises the exception for a failed call (reads this thread's last error)."""
    if status != 0:
        msg = lib().hz_last_error_message().decode("utf-8", "replace")
        raise error_for(status, msg)


def get_string(func, handle, *args) -> str:
    """Calls a string query (``buffer``, ``size``, ``length`` last) and decodes the result."""
    n = c_size_t(0)
    check(func(handle, *args, None, 0, ctypes.byref(n)))
    buf = ctypes.create_string_buffer(n.value + 1)
    check(func(handle, *args, buf, len(buf), ctypes.byref(n)))
    return buf.value.decode("utf-8")
