"""A gateway's serial line to the host: a pseudo-terminal, and optionally a TCP port.

pyserial opens the pty's device like ``/dev/ttyUSB0`` and the TCP port as
``socket://127.0.0.1:PORT``; both carry the protocol's COBS stream both ways. Writes
never block the bridge: bytes the host does not read in time are dropped and counted
(``serial_drops``), as a UART with a full FIFO would lose them.
"""

from __future__ import annotations

import errno
import os
import socket
import tty
from collections import Counter


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
        if master_fd is not None:
            os.set_blocking(master_fd, False)
        self.listener: socket.socket | None = None
        self.clients: list[socket.socket] = []
        self.counters: Counter[str] = Counter()
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
        if self.listener is not None:
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
            try:
                conn, _ = self.listener.accept()
                conn.setblocking(False)
                self.clients.append(conn)
            except BlockingIOError:
                pass
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
        for c in self.clients:
            c.close()
        if self.listener is not None:
            self.listener.close()
