"""pytest setup: the binding from this checkout, the library it finds."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import harmonizer  # noqa: E402
from harmonizer import _native  # noqa: E402


def pytest_report_header(config: pytest.Config) -> str:
    lib = _native.lib()  # fails loudly (LibraryNotFoundError) when the library is not built
    return f"libharmonizer {harmonizer.version()} from {lib._name}"


@pytest.fixture(scope="session")
def device() -> harmonizer.Device:
    with harmonizer.Device(threads=2) as d:
        yield d
