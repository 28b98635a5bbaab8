"""Shared fixtures of the USD hook tests (real usd-core, OpenImageIO,
OpenColorIO, Blender's Cycles for the rendered shot, libharmonizer)."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import fixtures


@pytest.fixture(scope="session")
def rendered() -> Path:
    """The cached rendered shot (read-only: copy before writing next to it)."""
    return fixtures.build()


@pytest.fixture
def shot(rendered: Path, tmp_path: Path) -> Path:
    """A private copy of the rendered shot; returns its ``shot.usda``."""
    dst = tmp_path / "shot"
    shutil.copytree(
        rendered,
        dst,
        ignore=shutil.ignore_patterns(
            "blender", "reference", "harmonized", "*.harmonized.usda"
        ),
    )
    return dst / "shot.usda"
