"""systemd's service notification protocol (sd_notify(3)) for the daemon.

Hand-written rather than taken from PyPI: the protocol is one ``sendto`` of
``KEY=VALUE`` lines on a unix datagram socket, and the libraries on offer either
are unmaintained (sdnotify, last release 2017), need libsystemd's headers and a
compiler at install time (systemd-python, cysystemd), or read ``os.environ``
themselves and expose no STOPPING/RELOADING (systemd-watchdog). Taking the
environment as a mapping is what lets a test speak the other side.

Every method is a no-op when ``NOTIFY_SOCKET`` is unset, so the daemon runs the
same from a terminal as under systemd.
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Mapping

#: s a notification waits for room in the service manager's queue (then it is counted as an error)
SEND_TIMEOUT = 0.1


class Notifier:
    """Tells systemd the daemon's state: READY, STATUS, WATCHDOG, RELOADING, STOPPING.

    A failed send (the manager went away) is counted in :attr:`send_errors`, never
    raised: losing the service manager must not take the skin's data down with it.
    """

    def __init__(self, env: Mapping[str, str] | None = None) -> None:
        env = os.environ if env is None else env
        self._address = _socket_address(env.get("NOTIFY_SOCKET", ""))
        self._watchdog_usec = _watchdog_usec(env)
        self._socket: socket.socket | None = None
        self.send_errors = 0
        self._stuck = False  # the last send found the manager's queue full

    @property
    def enabled(self) -> bool:
        """True when a service manager listens (``NOTIFY_SOCKET`` is set)."""
        return self._address is not None

    @property
    def watchdog_interval(self) -> float | None:
        """Seconds between :meth:`watchdog` calls: half of ``WATCHDOG_USEC``, as sd_watchdog_enabled(3) advises."""
        return None if self._watchdog_usec is None else self._watchdog_usec / 2e6

    def ready(self, status: str = "") -> None:
        """Start-up (or a reload) is complete: links and sockets are up."""
        self._send("READY=1", *([_status_line(status)] if status else []))

    def status(self, text: str) -> None:
        """A one-line summary shown by ``systemctl status``."""
        self._send(_status_line(text))

    def watchdog(self) -> None:
        """The event loop is alive; sent from the loop itself so that a stall is caught."""
        self._send("WATCHDOG=1")

    def reloading(self) -> None:
        """A reload (SIGHUP) began; :meth:`ready` ends it.

        MONOTONIC_USEC lets systemd ≥ 253 tell this reload from an older one.
        """
        self._send("RELOADING=1", f"MONOTONIC_USEC={time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000}")

    def stopping(self) -> None:
        """Shutdown began (SIGTERM): the daemon drains and exits."""
        self._send("STOPPING=1")

    def close(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None

    def _send(self, *lines: str) -> None:
        if self._address is None:
            return
        message = "\n".join(lines)
        try:
            if self._socket is None:
                self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            # A manager whose queue is full (busy, stuck) held a blocking send for ever, and
            # STOPPING=1 is a stop's first act: at most SEND_TIMEOUT, none while it stays full.
            self._socket.settimeout(0.0 if self._stuck else SEND_TIMEOUT)
            self._socket.sendto(message.encode(), self._address)
            self._stuck = False
        except OSError as exc:
            self.send_errors += 1
            self._stuck = isinstance(exc, (TimeoutError, BlockingIOError))


def _status_line(text: str) -> str:
    # One datagram holds newline-separated assignments: a newline in the text would start a new one.
    return "STATUS=" + " ".join(text.splitlines())


def _socket_address(value: str) -> str | bytes | None:
    """``NOTIFY_SOCKET`` as a sendto address: a path, or ``@name`` for the abstract namespace."""
    if not value:
        return None
    if value.startswith("@"):
        return b"\0" + value[1:].encode()
    if value.startswith("/"):
        return value
    return None  # systemd also speaks vsock (vsock:CID:PORT); the daemon runs on the host, not in a VM


def _watchdog_usec(env: Mapping[str, str]) -> int | None:
    """``WATCHDOG_USEC`` when it is meant for this process (``WATCHDOG_PID`` unset or ours)."""
    usec, pid = env.get("WATCHDOG_USEC", ""), env.get("WATCHDOG_PID", "")
    if not usec.isdigit() or int(usec) == 0:
        return None
    if pid and pid != str(os.getpid()):
        return None
    return int(usec)
