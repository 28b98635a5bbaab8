"""Build hook (hatchling): puts libharmonizer into the wheel as
``harmonizer/lib/libharmonizer.so`` and tags the wheel for this platform
(``py3-none-linux_x86_64``; ``scripts/wheels.sh`` then gives the wheel it
distributes its manylinux tag with ``auditwheel repair``).

From the source tree (``ffi/python`` of the workspace) the library is built
with ``cargo build --release --locked -p harmonizer-ffi`` into
``$CARGO_TARGET_DIR`` when set, else into a temporary directory removed after
the build: nothing is written into the checkout. From the prefix that
``scripts/build-ffi.sh`` installs (``PREFIX/python``, the library already in
``harmonizer/lib/``) the library is taken as it is.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path

from hatchling.builders.hooks.plugin.interface import BuildHookInterface

# hatchling imports this file from the source tree, and Python caches its
# bytecode in __pycache__ beside it before running it: take that back, so a
# build writes nothing into the checkout (a read-only checkout just fails to
# write it), and write no more bytecode in this build process.
sys.dont_write_bytecode = True
try:
    _cached = Path(__cached__)  # type: ignore[name-defined]  # noqa: F821
    _cached.unlink(missing_ok=True)
    _cached.parent.rmdir()  # only when empty
except (NameError, TypeError, OSError):
    pass


# The same names as harmonizer._native._lib_name: a build hook cannot import
# the package it is building.
def _lib_name() -> str:
    if sys.platform == "darwin":
        return "libharmonizer.dylib"
    if os.name == "nt":
        return "harmonizer.dll"
    return "libharmonizer.so"


class CargoLibraryHook(BuildHookInterface):
    PLUGIN_NAME = "cargo-library"

    def initialize(self, version: str, build_data: dict) -> None:
        if self.target_name != "wheel" or version == "editable":
            return
        # ctypes: any Python 3, no Python ABI, but this platform's library.
        platform = sysconfig.get_platform().replace("-", "_").replace(".", "_")
        build_data["pure_python"] = False
        build_data["tag"] = f"py3-none-{platform}"
        root = Path(self.root)
        name = _lib_name()
        if (root / "harmonizer" / "lib" / name).is_file():
            return  # an installed prefix: the package already holds its library
        workspace = root.parent.parent
        if not (workspace / "Cargo.toml").is_file() or not (workspace / "ffi" / "Cargo.toml").is_file():
            raise RuntimeError(
                f"harmonizer wheel: no library in {root / 'harmonizer' / 'lib'} and no cargo workspace at "
                f"{workspace}; build from the harmonizer checkout's ffi/python or a scripts/build-ffi.sh prefix"
            )
        self._tmp = None
        target = os.environ.get("CARGO_TARGET_DIR")
        if not target:
            self._tmp = tempfile.mkdtemp(prefix="harmonizer-wheel-")
            target = self._tmp
        env = dict(os.environ, CARGO_TARGET_DIR=target)
        cmd = ["cargo", "build", "--release", "--locked", "-p", "harmonizer-ffi"]
        self.app.display_info(f"harmonizer wheel: {' '.join(cmd)} (CARGO_TARGET_DIR={target})")
        subprocess.run(cmd, cwd=workspace, env=env, check=True)
        built = Path(target) / "release" / name
        if not built.is_file():
            raise RuntimeError(f"harmonizer wheel: cargo built no {built}")
        build_data["force_include"][str(built)] = f"harmonizer/lib/{name}"

    def finalize(self, version: str, build_data: dict, artifact_path: str) -> None:
        tmp = getattr(self, "_tmp", None)
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
