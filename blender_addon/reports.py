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
_LOCK = threading.RLock()
#: Whether the terminal's last line is a progress line without its newline.
_PROGRESS_OPEN = False
_POLL_SECONDS = 0.5


def post(level: str, text: str) -> None:
    """Report ``text`` at ``level`` ('INFO', 'WARNING' or 'ERROR'); safe from any thread."""
    label = {"INFO": "Info", "WARNING": "Warning", "ERROR": "Error"}.get(level, level)
    with _LOCK:
        RECENT.append((level, text))
        if not bpy.app.background:
            _PENDING.append((level, text))
        _end_progress()
        print(f"{label}: {text}", file=sys.stderr if level != "INFO" else sys.stdout, flush=True)


def progress(text: str) -> None:
    """Show ``text`` as the terminal's progress line (rewritten in place with ``\r``).

    The line stays open until ``end_progress`` or the next ``post``, which ends
    it first, so a message never runs into it.
    """
    global _PROGRESS_OPEN
    with _LOCK:
        print(f"\r{text}", end="", flush=True)
        _PROGRESS_OPEN = True


def end_progress() -> None:
    """End an open progress line (a newline), if there is one."""
    with _LOCK:
        _end_progress()


def _end_progress() -> None:
    global _PROGRESS_OPEN
    if _PROGRESS_OPEN:
        print(flush=True)
        _PROGRESS_OPEN = False


def take_pending() -> list[tuple[str, str]]:
    """Pending messages (cleared)."""
    with _LOCK:
        items = list(_PENDING)
        _PENDING.clear()
    return items


def _poll():
    """Main-thread timer: turn pending messages into Blender reports."""
    if _PENDING:
        try:
            bpy.ops.harmonizer.show_reports()
        except RuntimeError:
            pass  # an ERROR report reaches the UI and is also raised to the caller
        except Exception as exc:  # no window (e.g. while closing): the terminal has the messages
            print(f"Harmonizer: could not show reports: {exc}", file=sys.stderr)
            take_pending()
    return _POLL_SECONDS


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
    if not bpy.app.background:
        bpy.app.timers.register(_poll, first_interval=_POLL_SECONDS, persistent=True)


def unregister() -> None:
    if bpy.app.timers.is_registered(_poll):
        bpy.app.timers.unregister(_poll)
    take_pending()
    bpy.utils.unregister_class(HARMONIZER_OT_show_reports)
