"""Frame-numbered file names: patterns and folder listing (no ``bpy``).

Patterns follow the project convention: ``####`` (as many digits as ``#``),
``%04d``, ``$F4``, ``${F4}`` and ``<F4>``. A name without one gets the frame
number appended before the extension, as Blender does.
"""

from __future__ import annotations

import os
import re

_TOKENS = re.compile(r"(#+)|%0?(\d*)d|\$\{F(\d*)\}|\$F(\d*)|<F(\d*)>")
_NUMBERED = re.compile(r"^(?P<head>.*?)(?P<num>-?\d+)(?P<tail>\.[^.]+)$")


def has_token(pattern: str) -> bool:
    """Whether ``pattern`` holds a frame-number token."""
    return _TOKENS.search(pattern) is not None


def expand(pattern: str, frame: int) -> str:
    """``pattern`` with its frame tokens replaced by ``frame``."""
    if not has_token(pattern):
        root, ext = os.path.splitext(pattern)
        return f"{root}{frame:04d}{ext}"

    def sub(m: re.Match) -> str:
        if m.group(1):
            width = len(m.group(1))
        else:
            digits = next((g for g in m.groups()[1:] if g is not None), "")
            width = int(digits) if digits else 1
        return f"{frame:0{width}d}" if frame >= 0 else f"-{-frame:0{width}d}"

    return _TOKENS.sub(sub, pattern)


def list_frames(directory: str, *, extension: str = ".exr") -> list[tuple[int, str]]:
    """(frame, path) of the frame-numbered files in ``directory``, by frame.

    When the folder holds several sequences (different name prefixes), the
    largest one is returned.
    """
    groups: dict[tuple[str, str], list[tuple[int, str]]] = {}
    for name in sorted(os.listdir(directory)):
        if name.startswith(".") or not name.lower().endswith(extension):
            continue
        m = _NUMBERED.match(name)
        if not m:
            continue
        key = (m.group("head"), m.group("tail"))
        groups.setdefault(key, []).append((int(m.group("num")), os.path.join(directory, name)))
    if not groups:
        return []
    best = max(groups.values(), key=len)
    return sorted(best)
