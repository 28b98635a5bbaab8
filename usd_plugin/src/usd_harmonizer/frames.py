"""Frame tokens in file names and frame-range parsing.

USD defines no frame token for ``productName``; renderers and pipelines use
``####`` (as many digits as ``#``), ``%04d``, ``$F4`` / ``$F``, ``${F4}`` and
``<F4>`` / ``<F>``. All of them are expanded here.
"""

from __future__ import annotations

import re

from .errors import SettingsError

_TOKEN = re.compile(
    r"(?P<hash>#+)"
    r"|%(?P<pct>0?\d*)d"
    r"|\$\{F(?P<brace>\d*)\}"
    r"|\$F(?P<dollar>\d*)"
    r"|<F(?P<angle>\d*)>"
)


def has_frame_token(pattern: str) -> bool:
    """True when ``pattern`` contains a frame token."""
    return _TOKEN.search(pattern) is not None


def _pad(frame: int, width: int) -> str:
    if frame < 0:
        return "-" + str(-frame).zfill(max(width - 1, 0))
    return str(frame).zfill(width)


def expand_frame_tokens(pattern: str, frame: int) -> str:
    """Replaces every frame token in ``pattern`` with ``frame``, zero-padded to
    the token's width (``####`` -> 4, ``%04d`` -> 4, ``$F`` -> 1, ``<F4>`` -> 4)."""

    def sub(m: re.Match[str]) -> str:
        if m.group("hash") is not None:
            return _pad(frame, len(m.group("hash")))
        for key in ("pct", "brace", "dollar", "angle"):
            g = m.group(key)
            if g is not None:
                return _pad(frame, int(g) if g else 1)
        raise AssertionError(m.group(0))

    return _TOKEN.sub(sub, pattern)


def to_hash_pattern(pattern: str) -> str:
    """Rewrites every frame token of ``pattern`` as ``#`` characters of the same width."""

    def sub(m: re.Match[str]) -> str:
        if m.group("hash") is not None:
            return m.group("hash")
        for key in ("pct", "brace", "dollar", "angle"):
            g = m.group(key)
            if g is not None:
                return "#" * (int(g) if g else 1)
        raise AssertionError(m.group(0))

    return _TOKEN.sub(sub, pattern)


def parse_frame_range(text: str) -> list[int]:
    """Parses ``1001``, ``1001-1024``, ``1001-1024x2`` and comma-separated lists
    of those into a sorted list of unique frames."""
    frames: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        m = re.fullmatch(r"(-?\d+)(?:\s*(?:-|:)\s*(-?\d+)(?:\s*x\s*(\d+))?)?", part)
        if not m:
            raise SettingsError(
                f"--frames: cannot parse {part!r} (expected e.g. 1001, 1001-1024 or 1001-1024x2)"
            )
        first = int(m.group(1))
        last = int(m.group(2)) if m.group(2) is not None else first
        step = int(m.group(3)) if m.group(3) is not None else 1
        if last < first or step < 1:
            raise SettingsError(f"--frames: empty range {part!r}")
        frames.update(range(first, last + 1, step))
    return sorted(frames)
