"""How a view stops: SIGTERM, SIGHUP and Ctrl-C (SIGINT) once, and never again, and
within a bounded time.

Each view stops on the first of these signals (``systemctl stop``, a closed SSH session,
Ctrl-C): it closes its clients and exits within a second. A second signal meanwhile
must change nothing, no traceback, no half-done stop: from the first on, the three are
ignored. Ignored, not handled: Python sets a signal it handles back to its default
while the interpreter shuts down (and asyncio does when its loop closes), and a second
SIGTERM arriving then killed the view (exit status -15).

Ignoring the signals makes a stop that hangs (a terminal library waiting on a writer
thread that a full terminal blocks, a client that never reads its close frame) a process
nothing but SIGKILL ends. So the first signal also sets a deadline: a view still running
:data:`STOP_DEADLINE_S` seconds later puts the terminal back if it was given the bytes for
it (``watch``: the terminal's modes and screen), says so on stderr and exits with status 1
at once, whatever its threads are doing.
"""

from __future__ import annotations

import fcntl
import os
import signal
import threading
from collections.abc import Callable
from types import FrameType
from typing import Any

STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)
STOP_DEADLINE_S = 5.0  # a view stops in about 0.3 s; this is for a stop that hangs


def on_stop_signal(stop: Callable[[], Any], deadline: float = STOP_DEADLINE_S,
                   restore: Callable[[], Any] | None = None) -> None:
    """Call ``stop`` (in the main thread, between two bytecodes: it should only set a flag or
    schedule the stop) on the first SIGTERM, SIGHUP or SIGINT, and ignore every later one.

    From that first signal on the process has ``deadline`` seconds to end; after them it
    calls ``restore`` (which must not block; errors are ignored), writes a line to stderr
    and exits with status 1.
    """
    def handler(signum: int, frame: FrameType | None) -> None:
        ignore_stop_signals()
        timer = threading.Timer(deadline, _give_up, args=(signal.Signals(signum).name, deadline, restore))
        timer.daemon = True
        timer.start()
        stop()

    for sig in STOP_SIGNALS:
        signal.signal(sig, handler)


def ignore_stop_signals() -> None:
    """From now on SIGTERM, SIGHUP and SIGINT change nothing (the view is stopping)."""
    for sig in STOP_SIGNALS:
        signal.signal(sig, signal.SIG_IGN)


def _give_up(signame: str, deadline: float, restore: Callable[[], Any] | None) -> None:
    """The stop hung: end the process now. Every write here is non-blocking, since a
    terminal nobody reads is one reason a stop hangs."""
    if restore is not None:
        try:
            restore()
        except Exception:  # exiting whatever happens
            pass
    write_now(2, f"cellbridge: still stopping {deadline:g} s after {signame}; exiting without finishing the stop\n"
               .encode())
    os._exit(1)


def write_now(target: str | int, data: bytes) -> None:
    """Write ``data`` to a path (opened for it) or a descriptor without ever blocking; a
    part that does not fit, or any error, is dropped. A descriptor's flags are put back
    after: O_NONBLOCK belongs to the open file, which a terminal's shell shares with the
    view, and left set it made the shell's terminal non-blocking after the view was gone."""
    if isinstance(target, str):
        try:
            fd = os.open(target, os.O_WRONLY | os.O_NONBLOCK | os.O_NOCTTY)
        except OSError:
            return
        try:
            os.write(fd, data)
        except OSError:
            pass
        finally:
            os.close(fd)
        return
    try:
        flags = fcntl.fcntl(target, fcntl.F_GETFL)
    except OSError:
        return
    try:
        fcntl.fcntl(target, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        os.write(target, data)
    except OSError:
        pass
    finally:
        try:
            fcntl.fcntl(target, fcntl.F_SETFL, flags)
        except OSError:
            pass
