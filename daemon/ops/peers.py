"""Bounds on what clients can hold: connections per socket and per address, handshake time, descriptors.

libzmq accepts every TCP connect and keeps its descriptor until the peer goes away,
whether or not it ever speaks ZMTP: about 1 100 idle connects to the control port took
all 1 024 descriptors systemd gives a service, after which control stopped answering
and the gateway line could not be reopened. So:

* ``ZMQ_HANDSHAKE_IVL`` (``[peers] handshake_timeout``): a connection that has not
  finished its handshake by then is dropped by libzmq itself;
* :class:`PeerLimits` (sans-I/O) keeps the count of live connections of one socket, in
  all and per peer address, and says whether a new one may stay;
* :class:`PeerGuard` (a thread) reads the sockets' monitor events and shuts down, at
  once, every accepted connection beyond the limits (libzmq sees the peer hang up and
  frees the descriptor); its counters go to health ``security.peers``;
* :func:`reserve_descriptors` makes sure the process's descriptor limit holds every
  peer admitted plus a reserve for the links, and refuses to start otherwise.

A "peer address" is the remote IP for tcp:// and the peer's user id for ipc://. Every
local client of a loopback endpoint shares the address 127.0.0.1.
"""

from __future__ import annotations

import os
import resource
import socket
import struct
import threading
from collections import Counter
from collections.abc import Callable, Mapping
from typing import Any

import zmq
from cellbridge.daemon.core.config import Config, ControlSection, PeersSection
from zmq.utils.monitor import parse_monitor_message

#: Largest subscription message the PUB socket reads (a topic prefix is a few bytes; the
#: transport also carries the CURVE handshake's commands, a few hundred bytes).
MAX_SUBSCRIPTION_BYTES = 1024
#: A control request over ``max_request_bytes`` gets an error reply up to this many
#: times that size; beyond, the transport drops the connection without reading it.
HARD_REQUEST_FACTOR = 4
#: Requests queued per control client before libzmq stops reading its connection.
CONTROL_RCVHWM = 16
#: Descriptors a link may hold (its line, its capture file).
PER_LINK = 2

_EVENTS = (zmq.EVENT_ACCEPTED | zmq.EVENT_DISCONNECTED | zmq.EVENT_CLOSED
           | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
           | zmq.EVENT_HANDSHAKE_FAILED_AUTH)
_HANDSHAKE_FAILED = (zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
                     | zmq.EVENT_HANDSHAKE_FAILED_AUTH)


class PeerLimits:
    """Live connections of one socket, by descriptor and address, and who must go.

    At a bound, a new connection takes the place of the oldest one (in all, or of its
    address) whose peer has sent nothing yet (``silent``: it has not even begun its
    handshake); when every one has spoken, the new connection is refused. So idle
    connects cannot lock out a client that speaks, and what one address holds is bounded.
    """

    def __init__(self, max_peers: int, max_per_address: int) -> None:
        self.max_peers = max_peers
        self.max_per_address = max_per_address
        self._live: dict[int, str] = {}  # descriptor -> address, oldest first
        self._per_address: Counter[str] = Counter()
        self.accepted_total = 0
        self.refused = 0
        self.evicted = 0

    def accepted(self, fd: int, address: str, silent: Callable[[int], bool] = lambda fd: False) -> list[int]:
        """A connection was accepted on ``fd``: the descriptors to hang up (``[fd]``
        when it is refused, an older silent one when it takes its place, or none)."""
        self.closed(fd)  # a descriptor number reused before its close was seen
        out: list[int] = []
        for group in (address, None):  # its address's bound, then the bound on all
            if group is not None and self._per_address[group] < self.max_per_address:
                continue
            if group is None and len(self._live) < self.max_peers:
                continue
            victim = next((f for f, a in self._live.items() if (group is None or a == group) and silent(f)), None)
            if victim is None:
                self.refused += 1
                return [fd]
            self.closed(victim)
            self.evicted += 1
            out.append(victim)
        self._live[fd] = address
        self._per_address[address] += 1
        self.accepted_total += 1
        return out

    def closed(self, fd: int) -> None:
        address = self._live.pop(fd, None)
        if address is not None:
            self._per_address[address] -= 1
            if not self._per_address[address]:
                del self._per_address[address]

    def stats(self) -> dict[str, int]:
        return {"connected": len(self._live), "accepted": self.accepted_total, "refused": self.refused,
                "evicted": self.evicted, "max": self.max_peers, "max_per_address": self.max_per_address}


_TCP_INFO_BYTES_RECEIVED = 128  # offset of tcpi_bytes_received (u64) in struct tcp_info (Linux >= 4.1)


def silent(fd: int) -> bool:
    """True when the TCP peer on ``fd`` has sent no byte yet (not even a ZMTP greeting).
    Unknown (a unix socket, an old kernel): False, so it is never evicted for silence."""
    try:
        s = socket.socket(fileno=os.dup(fd))
    except OSError:
        return False
    try:
        if s.family not in (socket.AF_INET, socket.AF_INET6):
            return False
        info = s.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 256)
        if len(info) < _TCP_INFO_BYTES_RECEIVED + 8:
            return False
        return struct.unpack_from("<Q", info, _TCP_INFO_BYTES_RECEIVED)[0] == 0
    except OSError:
        return False
    finally:
        s.close()


def peer_address(fd: int) -> str | None:
    """The remote IP of a TCP connection, ``uid:N`` of a unix one; None when it is already gone."""
    try:
        s = socket.socket(fileno=os.dup(fd))
    except OSError:
        return None
    try:
        if s.family == socket.AF_UNIX:
            _, uid, _ = struct.unpack("3i", s.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, 12))
            return f"uid:{uid}"
        return str(s.getpeername()[0])
    except OSError:
        return None
    finally:
        s.close()


def hang_up(fd: int) -> None:
    """End the connection on ``fd`` without closing libzmq's descriptor: libzmq reads the
    end of the stream and closes it itself (closing it here would race with its use)."""
    try:
        s = socket.socket(fileno=os.dup(fd))
    except OSError:
        return
    try:
        s.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    finally:
        s.close()


class PeerGuard:
    """A thread that enforces :class:`PeerLimits` on sockets through their monitor events.

    A thread, not an event-loop task: connections must be refused as fast as an
    attacker makes them, also while the loop is busy. Call :meth:`watch` for each socket
    before it binds (the thread starts with the first); :meth:`stop` before the context
    terminates.
    """

    def __init__(self, context: zmq.Context) -> None:
        self._ctx = context
        self._watched: list[tuple[str, zmq.Socket, PeerLimits]] = []
        self._new: list[tuple[str, zmq.Socket, PeerLimits]] = []
        self._lock = threading.Lock()
        self.handshakes_failed: Counter[str] = Counter()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    def watch(self, name: str, sock: zmq.Socket, limits: PeerLimits) -> None:
        addr = f"inproc://cellbridge-peers-{name}-{id(self)}"
        sock.monitor(addr, _EVENTS)
        pair = self._ctx.socket(zmq.PAIR)
        pair.setsockopt(zmq.RCVHWM, 0)  # never lose an event: the counts would drift
        pair.setsockopt(zmq.LINGER, 0)
        pair.connect(addr)
        with self._lock:  # handed to the guard's thread, which alone uses it from now on
            self._new.append((name, pair, limits))
            self._watched.append((name, pair, limits))
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="cellbridge peer guard", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        poller = zmq.Poller()
        by_socket: dict[zmq.Socket, tuple[str, PeerLimits]] = {}
        try:
            while not self._stop.is_set():
                with self._lock:
                    new, self._new = self._new, []
                for name, pair, limits in new:
                    poller.register(pair, zmq.POLLIN)
                    by_socket[pair] = (name, limits)
                for pair, _ in poller.poll(100):
                    name, limits = by_socket[pair]
                    while True:
                        try:
                            frames = pair.recv_multipart(zmq.NOBLOCK)
                        except zmq.Again:
                            break
                        self._event(name, limits, parse_monitor_message(frames))
        finally:
            for pair in by_socket:
                pair.close(linger=0)

    def _event(self, name: str, limits: PeerLimits, ev: Mapping[str, Any]) -> None:
        kind, fd = ev["event"], ev["value"]
        if kind == zmq.EVENT_ACCEPTED:
            address = peer_address(fd)
            if address is not None:
                for gone in limits.accepted(fd, address, silent):
                    hang_up(gone)
        elif kind in (zmq.EVENT_DISCONNECTED, zmq.EVENT_CLOSED):
            limits.closed(fd)
        elif kind & _HANDSHAKE_FAILED:
            self.handshakes_failed[name] += 1

    def stats(self) -> dict[str, dict[str, int]]:
        return {name: {**limits.stats(), "handshakes_failed": self.handshakes_failed[name]}
                for name, _, limits in self._watched}

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
            self._thread = None
        with self._lock:
            for _, pair, _ in self._new:  # never picked up by the thread
                pair.close(linger=0)
            self._new = []


def bound_socket(sock: zmq.Socket, role: str, peers: PeersSection, control: ControlSection) -> None:
    """Socket options that bound one peer: handshake time, message size, queued requests.

    ``role`` is ``"pub"`` or ``"control"``; call before bind."""
    sock.setsockopt(zmq.HANDSHAKE_IVL, max(1, round(peers.handshake_timeout * 1000)))
    if role == "pub":
        sock.setsockopt(zmq.MAXMSGSIZE, MAX_SUBSCRIPTION_BYTES)
    else:
        sock.setsockopt(zmq.MAXMSGSIZE, HARD_REQUEST_FACTOR * control.max_request_bytes)
        sock.setsockopt(zmq.RCVHWM, CONTROL_RCVHWM)


def descriptors_needed(config: Config) -> int:
    """Descriptors the daemon may hold: every peer admitted, the links, and the reserve."""
    p = config.peers
    return p.max_pub + p.max_control + p.fd_reserve + PER_LINK * len(config.links)


def reserve_descriptors(config: Config) -> int:
    """Raise the soft descriptor limit to what the bounds need (up to the hard limit);
    ValueError naming the numbers when even the hard limit is too low. Returns the limit."""
    need = descriptors_needed(config)
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= need:
        return int(need if soft == resource.RLIM_INFINITY else soft)
    p = config.peers
    why = (f"the descriptor limit ({soft}, at most {hard}) cannot hold peers.max_pub {p.max_pub} + "
           f"peers.max_control {p.max_control} + peers.fd_reserve {p.fd_reserve} + {PER_LINK} per link "
           f"= {need}: raise LimitNOFILE= in the unit (ulimit -n) or lower those settings")
    if hard != resource.RLIM_INFINITY and hard < need:
        raise ValueError(why)
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (need, hard))
    except (OSError, ValueError):  # under the unit's system-call filter, setrlimit is refused
        raise ValueError(why) from None
    return need
