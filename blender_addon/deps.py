"""Finding the modules the extension runs on.

- ``OpenImageIO`` and ``PyOpenColorIO``: Blender ships both with its Python.
  The ``bpy`` module from PyPI keeps them in ``<bpy>/5.0/python/lib/pythonX.Y/
  site-packages``, which is not on ``sys.path``; that folder is appended (at the
  end, so nothing already importable is shadowed) when the plain import fails.
- ``harmonizer``: the Python binding of libharmonizer, installed from the wheel
  bundled in the extension (or from the environment during development).
- The ONNX Runtime shared library, from the bundled ``onnxruntime`` wheel; it is
  located, never imported (its Python package needs dependencies Blender lacks).
- The Open Image Denoise shared library (the denoise stage), from the bundled
  ``pyoidn`` wheel, located the same way (``pyoidn`` needs ``cffi``, which
  Blender lacks) and handed to the library through ``$HARMONIZER_OIDN_LIB``.
"""

from __future__ import annotations

import glob
import importlib
import importlib.util
import os
import sys

import bpy


class MissingDependency(ImportError):
    """A module the extension needs cannot be imported; the message says which and why."""


def _blender_site_packages() -> str:
    local = bpy.utils.resource_path("LOCAL")
    return os.path.join(
        local, "python", "lib", f"python{sys.version_info.major}.{sys.version_info.minor}", "site-packages"
    )


def _import_blender_module(name: str):
    try:
        return importlib.import_module(name)
    except ImportError:
        pass
    path = _blender_site_packages()
    if os.path.isdir(path) and path not in sys.path:
        sys.path.append(path)
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        raise MissingDependency(
            f"Python module {name!r} is not importable in this Blender (looked in sys.path and {path}): {exc}"
        ) from exc


def oiio():
    """Blender's OpenImageIO module."""
    return _import_blender_module("OpenImageIO")


def ocio():
    """Blender's PyOpenColorIO module."""
    return _import_blender_module("PyOpenColorIO")


def harmonizer():
    """The ``harmonizer`` Python binding (ctypes over libharmonizer)."""
    try:
        return importlib.import_module("harmonizer")
    except ImportError as exc:
        raise MissingDependency(
            f"the harmonizer Python binding is not importable ({exc}); reinstall the extension zip, "
            "which bundles it as a wheel"
        ) from exc
    except OSError as exc:  # the binding failed to load libharmonizer
        raise MissingDependency(f"libharmonizer could not be loaded: {exc}") from exc


def ocio_config_path() -> str:
    """The OCIO config Blender uses: ``$OCIO`` when set, else Blender's own config."""
    env = os.environ.get("OCIO")
    if env and os.path.isfile(env):
        return env
    return os.path.join(bpy.utils.system_resource("DATAFILES"), "colormanagement", "config.ocio")


def onnxruntime_library() -> str | None:
    """Path of ``libonnxruntime`` from the bundled ``onnxruntime`` wheel, or None.

    ``$ORT_DYLIB_PATH`` wins when set (the variable ONNX Runtime loaders use).
    """
    env = os.environ.get("ORT_DYLIB_PATH")
    if env and os.path.isfile(env):
        return env
    spec = importlib.util.find_spec("onnxruntime")
    if spec is None or not spec.submodule_search_locations:
        return None
    for root in spec.submodule_search_locations:
        names = ("libonnxruntime.so*", "libonnxruntime*.dylib", "onnxruntime.dll")
        for pattern in names:
            hits = sorted(glob.glob(os.path.join(root, "capi", pattern)))
            # Prefer the fully versioned file (libonnxruntime.so.1.31.1).
            hits.sort(key=len, reverse=True)
            if hits:
                return hits[0]
    return None


#: The variable the library reads for the Open Image Denoise library's path.
OIDN_ENV = "HARMONIZER_OIDN_LIB"


def oidn_library() -> str | None:
    """Path of ``libOpenImageDenoise`` from the bundled ``pyoidn`` wheel, or None.

    ``$HARMONIZER_OIDN_LIB`` wins when set (the library reports it when it
    names no file).
    """
    env = os.environ.get(OIDN_ENV)
    if env:
        return env
    spec = importlib.util.find_spec("pyoidn")
    if spec is None or not spec.submodule_search_locations:
        return None
    for root in spec.submodule_search_locations:
        for pattern in ("libOpenImageDenoise.so.2*", "libOpenImageDenoise.2*.dylib", "OpenImageDenoise.dll"):
            hits = sorted(glob.glob(os.path.join(root, "oidn", "lib", pattern)))
            hits += sorted(glob.glob(os.path.join(root, "oidn", "bin", pattern)))
            # Prefer the fully versioned file (libOpenImageDenoise.so.2.5.1).
            hits.sort(key=len, reverse=True)
            if hits:
                return hits[0]
    return None


def use_oidn_library() -> str | None:
    """Point the library at the bundled Open Image Denoise (``$HARMONIZER_OIDN_LIB``); returns the path.

    The library loads Open Image Denoise on the first frame it denoises and
    reads the variable then. Without a bundled copy (an extension built with
    ``--no-oidn``) nothing is set: the library then looks for the ``pyoidn``
    wheel in a ``.venv`` and for the system's library, and when it finds none,
    ``denoise on`` fails each frame and ``auto`` goes on without denoising,
    both with the library's message saying what to install.
    """
    path = oidn_library()
    if path and not os.environ.get(OIDN_ENV):
        os.environ[OIDN_ENV] = path
    return path
