"""UDP sockets of the bridge ↔ medium link, and what the kernel dropped on them.

A datagram that finds its receiver's buffer full is dropped by the kernel; the
count is per socket in ``/proc/net/udp`` (column ``drops``) and the processes report
it (``udp_drops``) with their other counters, so nothing is lost without a count.
"""

from __future__ import annotations

import os
import socket

RCVBUF = 4 << 20  #: asked for; the kernel caps it at net.core.rmem_max


def _family(host: str) -> socket.AddressFamily:
    return socket.AF_INET6 if ":" in host else socket.AF_INET


def bind(host: str, port: int) -> socket.socket:
    """The medium's socket; OSError (e.g. the port in use) for the caller to report."""
    s = socket.socket(_family(host), socket.SOCK_DGRAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF)
        s.bind((host, port))
    except OSError:
        s.close()
        raise
    s.setblocking(False)
    return s


def connect(host: str, port: int) -> socket.socket:
    """A bridge's socket, connected to the medium: it then receives only from the medium,
    and a send while no medium listens fails (ConnectionRefusedError) instead of vanishing."""
    s = socket.socket(_family(host), socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF)
    s.connect((host, port))
    s.setblocking(False)
    return s


def drops(sock: socket.socket) -> int:
    """Datagrams the kernel dropped on arrival at ``sock`` (receive buffer full); 0 where
    the count cannot be read."""
    try:
        inode = str(os.fstat(sock.fileno()).st_ino)
        for name in ("/proc/net/udp", "/proc/net/udp6"):
            with open(name) as f:
                next(f)
                for line in f:
                    fields = line.split()
                    if len(fields) >= 13 and fields[9] == inode:
                        return int(fields[12])
    except (OSError, ValueError, StopIteration):
        pass
    return 0
