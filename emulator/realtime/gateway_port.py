"""A gateway's serial line to the host: a pseudo-terminal, and optionally a TCP port.

pyserial opens the pty's device like ``/dev/ttyUSB0`` and the TCP port as
``socket://127.0.0.1:PORT``; both carry the protocol's COBS stream both ways. Writes
never block the bridge: bytes the host does not read in time are dropped and counted
(``serial_drops``), as a UART with a full FIFO would lose them.

Nor does the pty keep what no host takes: the line is held open while no host has it
(a pty whose slave nobody holds reports a hang-up to every poll), so the bytes would
queue there and a host opening the device seconds later would read seconds-old frames
as new. A queue that no host has emptied for ``STALE_S`` is flushed and counted
(``serial_stale_flushes``, ``serial_stale_bytes``): as on a real UART, what nobody
listened to is gone.

The TCP port serves at most ``MAX_CLIENTS`` clients at once: one more is accepted and
closed at once (``tcp_refused``), so idle connections cannot take the process's
descriptors (each costs one, and every write goes to each). Should accepting fail all
the same (``EMFILE``: no descriptor left), the failure is counted
(``tcp_accept_failed``) and the listener rests for ``ACCEPT_PAUSE_S``, rather than
ending the bridge or spinning on a listener that stays readable.
"""

from __future__ import annotations

import errno
import fcntl
import os
import socket
import struct
import termios
import time
import tty
from collections import Counter

#: TCP clients served at once (a host, a logger, a debugging tap: a handful).
MAX_CLIENTS = 8
#: How long the listener rests after an accept failed for want of descriptors.
ACCEPT_PAUSE_S = 1.0
#: Bytes no host has taken for this long are stale (the queue never emptied meanwhile).
STALE_S = 1.0
#: How often the pty's queue is looked at.
STALE_CHECK_S = 0.1
_TIOCGPTN = getattr(termios, "TIOCGPTN", 0x80045430)


def _slave_of(master: int) -> int | None:
    """A descriptor of the pty's slave side (to look at and flush what it queues), or
    None where it cannot be had (not a pty master: a test's pipe)."""
    try:
        n = struct.unpack("I", fcntl.ioctl(master, _TIOCGPTN, b"\0\0\0\0"))[0]
        return os.open(f"/dev/pts/{n}", os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    except OSError:
        return None


def open_pty() -> tuple[int, int, str]:
    """(master fd, slave fd, device path) of a new raw pseudo-terminal."""
    master, slave = os.openpty()
    tty.setraw(slave)
    os.set_blocking(master, False)
    return master, slave, os.ttyname(slave)


class GatewayPort:
    def __init__(self, master_fd: int | None = None, tcp_port: int | None = None,
                 host: str = "127.0.0.1") -> None:
        self.master = master_fd
        self._slave: int | None = None
        if master_fd is not None:
            os.set_blocking(master_fd, False)
            self._slave = _slave_of(master_fd)
        self._queued_since: float | None = None  # since when the pty's queue has not been empty
        self._check_at = 0.0
        self.listener: socket.socket | None = None
        self.clients: list[socket.socket] = []
        self.counters: Counter[str] = Counter()
        self._accept_at = 0.0  # monotonic time from which the listener is polled again
        if tcp_port is not None:
            self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.listener.bind((host, tcp_port))
            self.listener.listen(4)
            self.listener.setblocking(False)

    @property
    def tcp_port(self) -> int | None:
        return self.listener.getsockname()[1] if self.listener else None

    def fds(self) -> list[int]:
        """Descriptors to poll for input (they change as TCP clients come and go)."""
        out: list[int] = []
        if self.master is not None:
            out.append(self.master)
        if self.listener is not None and time.monotonic() >= self._accept_at:
            out.append(self.listener.fileno())
        out += [c.fileno() for c in self.clients]
        return out

    def read(self, ready: set[int]) -> bytes:
        """Bytes the host wrote, from whichever of our descriptors are ``ready``."""
        data = b""
        if self.master is not None and self.master in ready:
            try:
                data += os.read(self.master, 4096)
            except OSError as exc:  # EIO: no process has the slave open
                if exc.errno not in (errno.EIO, errno.EAGAIN):
                    raise
        if self.listener is not None and self.listener.fileno() in ready:
            self._accept()
        for c in [c for c in self.clients if c.fileno() in ready]:
            try:
                chunk = c.recv(4096)
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:
                chunk = b""
            if not chunk:
                self._drop_client(c)
            data += chunk
        return data

    def expire_unread(self, now: float) -> None:
        """Flush the pty's queue when it has not been empty for ``STALE_S`` (``now``:
        monotonic seconds); a host that reads empties it within milliseconds."""
        if self._slave is None or now < self._check_at:
            return
        self._check_at = now + STALE_CHECK_S
        try:
            queued = struct.unpack("i", fcntl.ioctl(self._slave, termios.FIONREAD, b"\0\0\0\0"))[0]
        except OSError:
            return
        if queued <= 0:
            self._queued_since = None
        elif self._queued_since is None:
            self._queued_since = now
        elif now - self._queued_since >= STALE_S:
            try:
                termios.tcflush(self._slave, termios.TCIFLUSH)
            except termios.error:
                return
            self.counters["serial_stale_flushes"] += 1
            self.counters["serial_stale_bytes"] += queued
            self._queued_since = None

    def _accept(self) -> None:
        try:
            conn, _ = self.listener.accept()  # type: ignore[union-attr]  # called only while listening
        except (BlockingIOError, InterruptedError, ConnectionAbortedError):
            return
        except OSError:  # EMFILE, ENFILE, ENOBUFS: no room for one more descriptor now
            self.counters["tcp_accept_failed"] += 1
            self._accept_at = time.monotonic() + ACCEPT_PAUSE_S
            return
        if len(self.clients) >= MAX_CLIENTS:
            self.counters["tcp_refused"] += 1
            conn.close()
            return
        conn.setblocking(False)
        self.clients.append(conn)

    def write(self, data: bytes) -> None:
        if self.master is not None:
            try:
                n = os.write(self.master, data)
            except OSError as exc:
                if exc.errno not in (errno.EAGAIN, errno.EIO):
                    raise
                n = 0
            if n < len(data):
                self.counters["serial_drops"] += len(data) - n
        for c in list(self.clients):
            try:
                n = c.send(data)
            except BlockingIOError:
                n = 0
            except OSError:
                self._drop_client(c)
                continue
            if n < len(data):
                self.counters["tcp_drops"] += len(data) - n

    def _drop_client(self, c: socket.socket) -> None:
        self.clients.remove(c)
        c.close()

    def close(self) -> None:
        if self._slave is not None:
            os.close(self._slave)
            self._slave = None
        for c in self.clients:
            c.close()
        if self.listener is not None:
            self.listener.close()
