"""How a bench that starts processes stops them when it is stopped itself."""

from __future__ import annotations

import signal
import sys


def unwind_on_signals() -> None:
    """Make SIGTERM (a kill, ``timeout``) and Ctrl-C exit through every ``finally``, so the
    processes a bench started are stopped. The first signal makes the bench deaf to the
    ones that follow: ``timeout`` passes its SIGTERM on, and a second signal raised inside
    the clean-up would cut it short and leave burners or a skin running."""
    signal.signal(signal.SIGTERM, _unwind)
    signal.signal(signal.SIGINT, _unwind)


def _unwind(signum: int, _frame: object) -> None:
    """Exit (128 + the signal) through every ``finally``, deaf to further signals."""
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, signal.SIG_IGN)
    sys.exit(128 + signum)
