"""How a view stops: SIGTERM, SIGHUP and Ctrl-C (SIGINT) once, and never again.

Each view stops on the first of these signals (``systemctl stop``, a closed SSH session,
Ctrl-C): it closes its clients and exits within a second. A second signal meanwhile
must change nothing, no traceback, no half-done stop: from the first on, the three are
ignored. Ignored, not handled: Python sets a signal it handles back to its default
while the interpreter shuts down (and asyncio does when its loop closes), and a second
SIGTERM arriving then killed the view (exit status -15).
"""

from __future__ import annotations

import signal
from collections.abc import Callable
from types import FrameType
from typing import Any

STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)


def on_stop_signal(stop: Callable[[], Any]) -> None:
    """Call ``stop`` (in the main thread, between two bytecodes: it should only set a flag or
    schedule the stop) on the first SIGTERM, SIGHUP or SIGINT, and ignore every later one."""
    def handler(signum: int, frame: FrameType | None) -> None:
        ignore_stop_signals()
        stop()

    for sig in STOP_SIGNALS:
        signal.signal(sig, handler)


def ignore_stop_signals() -> None:
    """From now on SIGTERM, SIGHUP and SIGINT change nothing (the view is stopping)."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)
