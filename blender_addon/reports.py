"""Getting messages to the user from handlers, where no operator is running.

Render handlers run outside any operator (in the render thread when rendering
from the UI), so they cannot call ``Operator.report`` themselves. ``post``
records the message, prints it to the terminal (what a headless render shows)
and, in the UI, hands it to the main thread, where the
``harmonizer.show_reports`` operator turns it into a regular Blender report
(status bar and Info editor).
"""

from __future__ import annotations

import collections
import sys
import threading

import bpy

#: The latest messages, newest last: (level, text).
RECENT: collections.deque = collections.deque(maxlen=200)
_PENDING: collections.deque = collections.deque()
_LOCK = threading.Lock()
_TIMER_ON = False


def post(level: str, text: str) -> None:
    """Report ``text`` at ``level`` ('INFO', 'WARNING' or 'ERROR')."""
    global _TIMER_ON
    with _LOCK:
        RECENT.append((level, text))
        _PENDING.append((level, text))
    label = {"INFO": "Info", "WARNING": "Warning", "ERROR": "Error"}.get(level, level)
    print(f"{label}: {text}", file=sys.stderr if level != "INFO" else sys.stdout, flush=True)
    if bpy.app.background:
        with _LOCK:
            _PENDING.clear()
        return
    with _LOCK:
        if _TIMER_ON:
            return
        _TIMER_ON = True
    bpy.app.timers.register(_flush, first_interval=0.0)


def take_pending() -> list[tuple[str, str]]:
    """Pending messages (cleared)."""
    with _LOCK:
        items = list(_PENDING)
        _PENDING.clear()
    return items


def _flush():
    global _TIMER_ON
    with _LOCK:
        _TIMER_ON = False
    try:
        bpy.ops.harmonizer.show_reports()
    except Exception as exc:  # no window (e.g. closing): the terminal has the messages
        print(f"Harmonizer: could not show reports: {exc}", file=sys.stderr)
    return None


class HARMONIZER_OT_show_reports(bpy.types.Operator):
    """Show harmonizer messages from rendering as Blender reports"""

    bl_idname = "harmonizer.show_reports"
    bl_label = "Show Harmonizer Messages"
    bl_options = {"INTERNAL"}

    def execute(self, context):
        for level, text in take_pending():
            self.report({level}, text)
        return {"FINISHED"}


def register() -> None:
    bpy.utils.register_class(HARMONIZER_OT_show_reports)


def unregister() -> None:
    global _TIMER_ON
    if bpy.app.timers.is_registered(_flush):
        bpy.app.timers.unregister(_flush)
    _TIMER_ON = False
    bpy.utils.unregister_class(HARMONIZER_OT_show_reports)
