"""Real-Blender test session: bpy 5.0.1 headless, the extension zip installed from disk.

Blender's user folders point into a temporary directory *before* ``bpy`` is
imported, so the tests never touch the user's preferences or extensions.
The extension zip comes from ``$HARMONIZER_BLENDER_ZIP`` (``run.sh`` builds it
with ``blender_addon/build.py``). ``$HARMONIZER_LIB`` is removed so the library
bundled in the zip is the one that runs.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile

import pytest

_ROOT = tempfile.mkdtemp(prefix="hz-blender-test-")
for _var, _sub in (
    ("BLENDER_USER_RESOURCES", "resources"),
    ("BLENDER_USER_CONFIG", "config"),
    ("BLENDER_USER_SCRIPTS", "scripts"),
    ("BLENDER_USER_EXTENSIONS", "extensions"),
    ("BLENDER_USER_DATAFILES", "datafiles"),
):
    os.environ[_var] = os.path.join(_ROOT, _sub)
os.environ.pop("HARMONIZER_LIB", None)
os.environ.pop("OCIO", None)

import bpy  # noqa: E402  (after the environment above)

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, HERE)

REPO_MODULE = "hztest"
ADDON_MODULE = f"bl_ext.{REPO_MODULE}.harmonizer"


def pytest_sessionfinish(session, exitstatus):
    if os.environ.get("HZ_KEEP_TMP") != "1":
        shutil.rmtree(_ROOT, ignore_errors=True)
    else:
        print(f"\nkept test files in {_ROOT}")


@pytest.fixture(scope="session")
def tmp_root() -> str:
    return _ROOT


@pytest.fixture(scope="session")
def extension_zip() -> str:
    path = os.environ.get("HARMONIZER_BLENDER_ZIP") or os.path.join(REPO, "dist", "harmonizer-0.2.0-linux-x64.zip")
    if not os.path.isfile(path):
        pytest.fail(
            f"extension zip not found: {path}. Build it with `python blender_addon/build.py` "
            "(tests/blender/run.sh does this).",
            pytrace=False,
        )
    return path


@pytest.fixture(scope="session")
def addon(extension_zip, tmp_root):
    """Install the zip into a fresh user repository with Blender's own operator and enable it."""
    repos = bpy.context.preferences.extensions.repos
    directory = os.path.join(tmp_root, "repo")
    os.makedirs(directory, exist_ok=True)
    repos.new(name="harmonizer test", module=REPO_MODULE, custom_directory=directory, source="USER")
    result = bpy.ops.extensions.package_install_files(repo=REPO_MODULE, filepath=extension_zip, enable_on_install=True)
    assert result == {"FINISHED"}, result
    assert os.path.isfile(os.path.join(directory, "harmonizer", "blender_manifest.toml"))
    assert ADDON_MODULE in bpy.context.preferences.addons, list(bpy.context.preferences.addons.keys())
    return sys.modules[ADDON_MODULE]
