"""``cellbridge medium``: relays transmissions between bridge processes over UDP.

A thin shell around :class:`~cellbridge.emulator.medium.medium.Medium`: bridges send their
transmissions and contention changes as datagrams to this process's UDP port (the
base port); it sends carrier reports and deliveries back (messages in
:mod:`cellbridge.emulator.medium.medium_wire`). It learns each bridge's address from the
bridge's own messages (every bridge says it is there at least once a second), so a
bridge or this process may die and return at any time.

A transmission its sender started after the cell went busy (its carrier report had not
reached it yet: message latency) is started when the cell is free, as the sender's carrier
sense would have done (:mod:`~cellbridge.emulator.medium.carrier_arbiter`, counted ``deferred``);
deliveries carry the sender's start tick, the frame's start-of-frame instant for mesh time.

Carrier reports go only to bridges that are contending (one that starts contending
first gets the carrier already on its cells): an idle transceiver ignores carrier,
and these messages would otherwise cost every bridge more CPU than its firmware.

Ticks are 50 MHz cycles of the host's monotonic clock (shared by every process on the
host). A message for a bridge not heard from for ``GONE_S`` (dead, not started, or not
heard yet by a restarted medium) is lost and counted (``rx_unreachable``,
``carrier_unreachable``), as a delivery to a dead bridge is; one the kernel could not
queue counts as ``*_backlog``, and datagrams the kernel dropped on arrival as
``udp_drops``.
"""

from __future__ import annotations

import argparse
import gc
import heapq
import itertools
import math
import select
import socket
import sys
import time
from collections import Counter
from collections.abc import Iterable
from typing import Any

from cellbridge.emulator.medium.carrier_arbiter import HOLD, CarrierArbiter
from cellbridge.emulator.medium.medium import Medium, Transmission
from cellbridge.emulator.medium.medium_wire import (
    MAX_DATAGRAM,
    TX,
    WANT,
    decode_tx,
    decode_want,
    encode_carrier,
    encode_rx,
    sender,
)
from cellbridge.emulator.mesh.mesh import MeshError, load_mesh
from cellbridge.emulator.realtime import udp
from cellbridge.emulator.realtime.realtime import (
    CLOCK_HZ,
    StopFlag,
    above_the_chips,
    add_endpoint_arguments,
    add_ready_argument,
    endpoints,
    now_tick,
    signal_ready,
)
from cellbridge.protocol import MAX_FRAME, FrameType, addressed_to
from cellbridge.protocol.frame import Flags

GONE_S = 3.0  #: a bridge silent this long is taken for gone (it says it is there every second)
#: How long transmissions after an ack on the wire wait for that ack to reach this process
#: after its frame (:mod:`~cellbridge.emulator.medium.carrier_arbiter`): its receiver's process must wake, answer
#: and be heard; on a 4×4 skin at 100 Hz on two busy cores that takes up to a few ms.
ACK_GUARD = 4 * CLOCK_HZ // 1000
#: A transmission stamped this far ahead of its arrival at most starts at its stamp (a
#: bridge hands over a transmission due within microseconds without sleeping for them:
#: process_bridge's ``EARLY``); a stamp further ahead (a bridge on another host, whose clock
#: is not this one's) is taken for a start at arrival, as any other.
AHEAD = CLOCK_HZ // 1000
_LINK_ACK, _ACK_REQUEST = int(FrameType.LINK_ACK), int(Flags.ACK_REQUEST)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Relay cell transmissions between bridge processes (collisions, loss and "
                          "bit errors as in the mesh file) over UDP on the base port. Started by "
                          "'cellbridge mesh up'; run it yourself to put bridges on other hosts.")
    parser.add_argument("--mesh", required=True, help="mesh file (TOML)")
    parser.add_argument("--seed", type=int, default=0, help="seed of loss and bit errors (default 0)")
    parser.add_argument("--bind", default=None,
                        help="address to bind (default: the --host address, 127.0.0.1)")
    add_endpoint_arguments(parser)
    add_ready_argument(parser)


class Bridges:
    """Where each bridge process is, as its own messages say, and whether it still is."""

    def __init__(self, sock: socket.socket, ids: Iterable[int], counters: Counter[str]) -> None:
        self.sock = sock
        self.known = set(ids)
        self.addr: dict[int, Any] = {}  # bridge -> its UDP (host, port)
        self.heard: dict[int, int] = {}
        self.counters = counters
        self.gone = int(GONE_S * CLOCK_HZ)

    def heard_from(self, bridge: int, addr: Any, tick: int) -> None:
        self.addr[bridge] = addr  # a restarted bridge comes from a new port: it takes its id back
        self.heard[bridge] = tick

    def send(self, bridge: int, msg: bytes, tick: int, what: str) -> None:
        addr = self.addr.get(bridge)
        if addr is None or tick - self.heard[bridge] > self.gone:
            self.counters[f"{what}_unreachable"] += 1
            return
        try:
            self.sock.sendto(msg, addr)
        except BlockingIOError:
            self.counters[f"{what}_backlog"] += 1
        except OSError:
            self.counters[f"{what}_unreachable"] += 1


def serve(medium: Medium, sock: socket.socket, stop: StopFlag) -> None:
    """Relay until ``stop``; ``sock`` is the bound, non-blocking UDP socket."""
    poller = select.poll()
    poller.register(sock, select.POLLIN)
    counters = medium.counters
    bridges = Bridges(sock, medium.mesh.ids, counters)
    cells_of = {b.id: b.cells for b in medium.mesh.bridges}
    cells_set = {b: frozenset(cs) for b, cs in cells_of.items()}
    pending: list[tuple[int, int, Transmission]] = []
    busy: dict[int, tuple[int, int]] = {}  # cell -> (start, end) of its latest transmission
    contending: set[int] = set()
    arbiter = CarrierArbiter(medium.bit_cycles, ack_guard=ACK_GUARD)
    arbiter.counters = counters  # deferred, deferred_cycles, held_for_ack: with the medium's own
    starting: list[tuple[int, int, int, tuple[int, ...], bytes, int]] = []  # deferred starts
    held: list[tuple[int, tuple[int, ...], bytes, int]] = []  # waiting for an ack, in arrival order
    order = itertools.count()

    def admit(src: int, cells: tuple[int, ...], frame: bytes, sent: int, tick: int) -> bool:
        """Start (now or later) or hold a transmission; whether it was an ack that started."""
        dst = (frame[5] << 8 | frame[6]) if len(frame) > 6 else -1
        ack_for = dst if dst >= 0 and frame[2] == _LINK_ACK else -1  # dst: 7 bytes or more
        acker = dst if dst >= 0 and frame[1] & _ACK_REQUEST else -1
        # a stamp a little ahead of its arrival: the sender handed it over early (AHEAD)
        at = arbiter.admit(cells, sent, sent if 0 < sent - tick <= AHEAD else tick, medium.airtime(len(frame)),
                           src, ack_for, acker)
        if at == HOLD:
            held.append((src, cells, frame, sent))
            return False
        if at > tick:  # its sender's carrier sense would have held it back: start it later
            heapq.heappush(starting, (at, next(order), src, cells, frame, sent))
        else:
            begin(src, cells, frame, tick, sent)
        return ack_for >= 0

    def release(tick: int) -> None:
        """Admit the held transmissions again, in arrival order (an ack came, or a hold ran
        out); one pass: acks are never held, so none of them can end another's hold."""
        waiting = held[:]
        held.clear()
        for src, cells, frame, sent in waiting:
            admit(src, cells, frame, sent, tick)

    def begin(src: int, cells: tuple[int, ...], frame: bytes, tick: int, sent: int) -> None:
        tx = medium.start(src, frame, cells, tick, sent)
        for c in cells:
            old = busy.get(c)
            busy[c] = (old[0], max(old[1], tx.end)) if old and old[1] > tick else (tick, tx.end)
        for r, cell in tx.receivers:
            if r in contending:
                bridges.send(r, encode_carrier(cell, tick, tx.end), tick, "carrier")
        heapq.heappush(pending, (tx.end, tx.id, tx))

    def want(src: int, on: bool, tick: int) -> None:
        if on:
            if src not in contending:
                contending.add(src)
                for c in cells_of[src]:
                    if c in busy and busy[c][1] > tick:
                        bridges.send(src, encode_carrier(c, *busy[c]), tick, "carrier")
        else:
            contending.discard(src)

    while not stop.stopped:
        timeout = 100
        release_at = arbiter.next_release() if held else None
        if pending or starting or release_at is not None:
            # the earliest of the three (no lists built: this runs at every wake)
            first = pending[0][0] if pending else -1
            if starting and (first < 0 or starting[0][0] < first):
                first = starting[0][0]
            if release_at is not None and (first < 0 or release_at < first):
                first = release_at
            wait = first - now_tick()
            timeout = max(0, math.ceil(wait * 1000 / CLOCK_HZ))
            if 0 < wait < CLOCK_HZ // 1000 and not poller.poll(0):
                # under a millisecond: slept for exactly (poll counts milliseconds, and a
                # delivery or deferred start a millisecond late delays every hop). Not select
                # with a microsecond timeout: it ends at each message that comes meanwhile,
                # and the wakes that split what one sleep gathers cost more CPU than they save.
                time.sleep(wait / CLOCK_HZ)
                timeout = 0
        if poller.poll(timeout):
            while True:
                try:
                    msg, addr = sock.recvfrom(MAX_DATAGRAM)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:  # an error queued by an earlier send: the bridge went away
                    continue
                tick = now_tick()
                src = sender(msg)
                if src not in bridges.known:
                    counters["bad_messages"] += 1
                    continue
                kind = msg[0]
                if kind == WANT and (w := decode_want(msg)) is not None:
                    bridges.heard_from(src, addr, tick)
                    want(src, w[1], tick)
                    continue
                tx_msg = decode_tx(msg) if kind == TX else None
                # A bridge sends a frame (at most MAX_FRAME bytes; a datagram cut to
                # MAX_DATAGRAM on receipt is longer) on cells it is on: anything else is no
                # transmission, and its cells would stay in ``busy`` for ever.
                if (tx_msg is None or len(tx_msg[2]) > MAX_FRAME
                        or not set(tx_msg[1]) <= cells_set[src]):
                    counters["bad_messages"] += 1
                    continue
                bridges.heard_from(src, addr, tick)
                _, cells, frame, still, sent = tx_msg
                sent = sent or tick
                if admit(src, cells, frame, sent, tick) and held:
                    release(tick)
                want(src, still, tick)
        now = now_tick()
        if held and (release_at := arbiter.next_release()) is not None and release_at <= now:
            release(now)
        elif held and release_at is None:
            release(now)  # every hold ended (its ack came)
        while starting and starting[0][0] <= now:
            at, _, src, cells, frame, sent = heapq.heappop(starting)
            begin(src, cells, frame, at, sent)  # at its reserved tick: the next reservation follows it
        while pending and pending[0][0] <= now:
            tx = heapq.heappop(pending)[2]
            acker = (tx.data[5] << 8 | tx.data[6]) if len(tx.data) > 6 and tx.data[1] & _ACK_REQUEST else -1
            for r, cell, data in medium.finish(tx):
                if addressed_to(data, r):  # a bridge drops others' unicasts anyway: save the message
                    bridges.send(r, encode_rx(cell, data, tx.sent), now, "rx")
                    if r == acker:
                        acker = -1
            if acker >= 0:  # it did not reach its addressee: no ack comes
                arbiter.no_ack(tx.src, acker)
                release(now)


def run(args: argparse.Namespace) -> int:
    try:
        mesh = load_mesh(args.mesh)
    except MeshError as exc:
        print(f"cellbridge medium: {exc}", file=sys.stderr)
        return 2
    host = args.bind or endpoints(args).host
    stop = StopFlag()
    try:
        sock = udp.bind(host, args.base_port)
    except OSError as exc:
        print(f"cellbridge medium: cannot bind UDP {host}:{args.base_port}: {exc.strerror or exc}",
              file=sys.stderr)
        return 1
    medium = Medium(mesh, args.seed)
    above_the_chips()  # the wire never waits behind a chip (real-time runs only)
    signal_ready(args.ready_fd)
    gc.freeze()  # start-up's objects out of the collector's reach: no long pauses while relaying
    try:
        serve(medium, sock, stop)
    finally:
        medium.counters["udp_drops"] = udp.drops(sock)
        sock.close()
    print(f"medium: {dict(medium.counters)}", file=sys.stderr)
    return 0
