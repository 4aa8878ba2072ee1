"""Whether a process has ended, read from /proc (a zombie counts as ended: its parent,
this test process perhaps, has not reaped it yet, but it runs no more)."""

from __future__ import annotations

import time


def gone(pid: int) -> bool:
    """``pid`` is not running (no such process, or a zombie)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] == "Z"
    except FileNotFoundError:
        return True


def until_gone(pid: int, limit: float = 10.0) -> bool:
    """Wait up to ``limit`` s for ``pid`` to end; whether it did."""
    end = time.monotonic() + limit
    while not gone(pid) and time.monotonic() < end:
        time.sleep(0.02)
    return gone(pid)
