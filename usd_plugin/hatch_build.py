"""Metadata hook (hatchling): where ``usd_harmonizer`` gets the ``harmonizer``
binding from.

The dependency lists live in ``pyproject.toml`` under
``[tool.hatch.metadata.hooks.custom]`` and name the binding with its release
pin (``harmonizer==0.2.*``). This hook keeps the pin when the package is built
for distribution (``USD_HARMONIZER_BINDING=pin``, which ``scripts/wheels.sh``
sets) or from an sdist, which has no ``../ffi/python``. Built from a checkout
(``pip install ./usd_plugin``, pip builds in place), it turns each
``harmonizer[extras]==0.2.*`` into ``harmonizer[extras] @ file:///.../ffi/python``:
pip then builds the binding, with its library, from the same checkout. The
name ``harmonizer`` on PyPI belongs to an unrelated project, so a checkout
must never let pip look the binding up there.

An sdist keeps the metadata it was built with (hatchling reads its PKG-INFO
back), so an sdist from a checkout would carry this machine's path: its build
hook refuses that and asks for ``USD_HARMONIZER_BINDING=pin``.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

from hatchling.builders.hooks.plugin.interface import BuildHookInterface
from hatchling.metadata.plugin.interface import MetadataHookInterface
from packaging.requirements import Requirement

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

BINDING = "harmonizer"
MODE_VARIABLE = "USD_HARMONIZER_BINDING"


def _binding_version(source: Path) -> str:
    text = (source / "harmonizer" / "__init__.py").read_text(encoding="utf-8")
    m = re.search(r'^__version__ = "([^"]+)"$', text, re.M)
    if not m:
        raise RuntimeError(f"usd_harmonizer: no __version__ in {source / 'harmonizer' / '__init__.py'}")
    return m.group(1)


def _is_binding_source(source: Path) -> bool:
    pyproject = source / "pyproject.toml"
    return pyproject.is_file() and bool(re.search(r'^name = "harmonizer"$', pyproject.read_text(encoding="utf-8"), re.M))


class BindingSourceHook(MetadataHookInterface):
    PLUGIN_NAME = "binding-source"

    def update(self, metadata: dict) -> None:
        mode = os.environ.get(MODE_VARIABLE, "auto")
        if mode not in ("auto", "pin"):
            raise ValueError(f"usd_harmonizer: {MODE_VARIABLE}={mode!r}, expected 'auto' or 'pin'")
        source = Path(self.root).resolve().parent / "ffi" / "python"
        local = mode == "auto" and _is_binding_source(source)

        def resolve(spec: str) -> str:
            req = Requirement(spec)
            if req.name != BINDING or not local:
                return spec
            version = _binding_version(source)
            if not req.specifier.contains(version, prereleases=True):
                raise RuntimeError(
                    f"usd_harmonizer: the checkout's binding {source} is version {version}, "
                    f"outside the pin {spec!r}"
                )
            extras = f"[{','.join(sorted(req.extras))}]" if req.extras else ""
            marker = f" ; {req.marker}" if req.marker else ""
            return f"{BINDING}{extras} @ {source.as_uri()}{marker}"

        metadata["dependencies"] = [resolve(s) for s in self.config.get("dependencies", [])]
        metadata["optional-dependencies"] = {
            extra: [resolve(s) for s in specs] for extra, specs in self.config.get("optional-dependencies", {}).items()
        }


class SdistPinHook(BuildHookInterface):
    PLUGIN_NAME = "sdist-pin"

    def initialize(self, version: str, build_data: dict) -> None:
        core = self.metadata.core
        specs = list(core.dependencies) + [s for specs in core.optional_dependencies.values() for s in specs]
        local = [s for s in specs if Requirement(s).name == BINDING and Requirement(s).url]
        if local:
            raise RuntimeError(
                f"usd_harmonizer: an sdist would carry {local[0]!r}, a path on this machine; "
                f"build it with {MODE_VARIABLE}=pin (scripts/wheels.sh does for the wheels)"
            )
