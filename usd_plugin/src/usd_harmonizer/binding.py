"""Finds the harmonizer Python binding (``import harmonizer``).

Search order: an installed ``harmonizer`` package; ``$HARMONIZER_PYTHON`` (the
directory holding the ``harmonizer`` package); the repository's
``ffi/python`` when this package runs from a checkout. The binding itself
finds ``libharmonizer`` (``$HARMONIZER_LIB``, next to the binding, or the
repository's ``target/release`` / ``target/debug``).
"""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path
from types import ModuleType

from .errors import BindingError

_module: ModuleType | None = None


def _candidates() -> list[Path]:
    out: list[Path] = []
    env = os.environ.get("HARMONIZER_PYTHON")
    if env:
        out.append(Path(env))
    here = Path(__file__).resolve()
    # <repo>/usd_plugin/src/usd_harmonizer/binding.py -> <repo>/ffi/python
    for parent in here.parents:
        cand = parent / "ffi" / "python"
        if (cand / "harmonizer" / "__init__.py").is_file():
            out.append(cand)
            break
    return out


def load() -> ModuleType:
    """The ``harmonizer`` module, imported once."""
    global _module
    if _module is not None:
        return _module
    try:
        _module = importlib.import_module("harmonizer")
        return _module
    except ImportError:
        pass
    tried = _candidates()
    for c in tried:
        if (c / "harmonizer" / "__init__.py").is_file():
            sys.path.insert(0, str(c))
            try:
                _module = importlib.import_module("harmonizer")
                return _module
            finally:
                if _module is None:
                    sys.path.remove(str(c))
    raise BindingError(
        "the harmonizer Python binding is not importable: install it, or set HARMONIZER_PYTHON to the "
        f"directory holding the harmonizer package (looked in: {', '.join(map(str, tried)) or 'nothing'})"
    )
