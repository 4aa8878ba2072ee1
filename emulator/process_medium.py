"""``cellbridge medium``: relays transmissions between bridge processes over ZeroMQ.

A thin shell around :class:`~cellbridge.emulator.medium.Medium`: bridges connect a
DEALER socket (identity = bridge id) to this ROUTER. The messages (transmissions with
the sender's contention state, contention changes, carrier reports, deliveries; one
ZeroMQ frame each) are in :mod:`cellbridge.emulator.medium_wire`.

Carrier reports go only to bridges that are contending (one that starts contending
first gets the carrier already on its cells): an idle transceiver ignores carrier,
and these messages would otherwise cost every bridge more CPU than its firmware.

Ticks are 50 MHz cycles of the host's monotonic clock (shared by every process on the
host). ZeroMQ reconnects by itself, so a bridge or this process may die and return;
a message for a bridge that is not connected (or not reading) is lost and counted
(``rx_unreachable``, ``rx_backlog``, ``carrier_*``), as a delivery to a dead bridge is.
"""

from __future__ import annotations

import argparse
import heapq
import math
import sys
from collections import Counter

import zmq

from cellbridge.emulator.medium import Medium, Transmission
from cellbridge.emulator.mesh import MeshError, load_mesh
from cellbridge.emulator.medium_wire import (
    EVENTS, MORE_NOBLOCK, NOBLOCK, POLLIN, TX, WANT, WANT_OFF, WANT_ON, decode_tx, encode_carrier, encode_rx,
)
from cellbridge.emulator.rawframe import addressed_to
from cellbridge.emulator.realtime import (
    CLOCK_HZ, StopFlag, add_endpoint_arguments, endpoints, now_tick,
)

def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Relay cell transmissions between bridge processes (collisions, loss and "
                          "bit errors as in the mesh file). Started by 'cellbridge mesh up'; run it "
                          "yourself to put bridges on other hosts.")
    parser.add_argument("--mesh", required=True, help="mesh file (TOML)")
    parser.add_argument("--seed", type=int, default=0, help="seed of loss and bit errors (default 0)")
    parser.add_argument("--bind", default=None,
                        help="address to bind (default: the --host address, 127.0.0.1)")
    add_endpoint_arguments(parser)


def _send(sock: zmq.Socket, to: bytes, msg: bytes, counters: Counter[str], what: str) -> None:
    """Send to one bridge without blocking; a bridge not connected (dead, not started, or
    not heard yet by a restarted medium) or not reading counts as ``<what>_unreachable``
    or ``<what>_backlog``. (The identity part fails or the whole message goes.)"""
    try:
        sock.send(to, MORE_NOBLOCK)
        sock.send(msg, NOBLOCK)
    except zmq.Again:
        counters[f"{what}_backlog"] += 1
    except zmq.ZMQError as exc:
        if exc.errno != zmq.EHOSTUNREACH:
            raise
        counters[f"{what}_unreachable"] += 1


def serve(medium: Medium, endpoint: str, stop: StopFlag) -> None:
    ctx = zmq.Context.instance()
    sock = ctx.socket(zmq.ROUTER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.ROUTER_HANDOVER, 1)  # a restarted bridge takes its identity back
    sock.setsockopt(zmq.ROUTER_MANDATORY, 1)  # an unroutable message raises: counted, not silent
    sock.bind(endpoint)
    poller = zmq.Poller()  # one, not one per wait (Socket.poll builds a Poller each call)
    poller.register(sock, zmq.POLLIN)
    known = {str(b).encode(): b for b in medium.mesh.ids}
    ident = {b: str(b).encode() for b in medium.mesh.ids}
    cells_of = {b.id: b.cells for b in medium.mesh.bridges}
    pending: list[tuple[int, int, Transmission]] = []
    busy: dict[int, tuple[int, int]] = {}  # cell -> (start, end) of its latest transmission
    contending: set[int] = set()
    counters = medium.counters
    rcvmore = zmq.RCVMORE

    def want(src: int, on: bool, tick: int) -> None:
        if on:
            if src not in contending:
                contending.add(src)
                for c in cells_of[src]:
                    if c in busy and busy[c][1] > tick:
                        _send(sock, ident[src], encode_carrier(c, *busy[c]), counters, "carrier")
        else:
            contending.discard(src)

    try:
        while not stop.stopped:
            timeout = 100
            if pending:
                timeout = max(0, math.ceil((pending[0][0] - now_tick()) * 1000 / CLOCK_HZ))
            if poller.poll(timeout):
                while sock.getsockopt(EVENTS) & POLLIN:  # drained without raising zmq.Again each time
                    who = sock.recv(NOBLOCK)
                    msg = sock.recv(NOBLOCK) if sock.getsockopt(rcvmore) else b""
                    extra = False
                    while sock.getsockopt(rcvmore):  # not ours: drain the rest of it
                        sock.recv(NOBLOCK)
                        extra = True
                    src = known.get(who)
                    tick = now_tick()
                    kind = msg[0] if msg and not extra and src is not None else -1
                    if kind == WANT and msg in (WANT_ON, WANT_OFF):
                        want(src, msg == WANT_ON, tick)  # type: ignore[arg-type]
                        continue
                    tx_msg = decode_tx(msg) if kind == TX else None
                    if tx_msg is None:
                        counters["bad_messages"] += 1
                        continue
                    cells, frame, still = tx_msg
                    tx = medium.start(src, frame, cells, tick)  # type: ignore[arg-type]
                    for c in cells:
                        old = busy.get(c)
                        busy[c] = (old[0], max(old[1], tx.end)) if old and old[1] > tick else (tick, tx.end)
                    for r, cell in tx.receivers:
                        if r in contending:
                            _send(sock, ident[r], encode_carrier(cell, tick, tx.end), counters, "carrier")
                    heapq.heappush(pending, (tx.end, tx.id, tx))
                    want(src, still, tick)  # type: ignore[arg-type]
            now = now_tick()
            while pending and pending[0][0] <= now:
                tx = heapq.heappop(pending)[2]
                for r, cell, data in medium.finish(tx):
                    if addressed_to(data, r):  # a bridge drops others' unicasts anyway: save the message
                        _send(sock, ident[r], encode_rx(cell, data), counters, "rx")
    finally:
        sock.close()


def run(args: argparse.Namespace) -> int:
    try:
        mesh = load_mesh(args.mesh)
    except MeshError as exc:
        print(f"cellbridge medium: {exc}", file=sys.stderr)
        return 2
    ep = endpoints(args)
    bind = f"tcp://{args.bind}:{args.base_port}" if args.bind else ep.medium
    stop = StopFlag()
    medium = Medium(mesh, args.seed)
    serve(medium, bind, stop)
    print(f"medium: {dict(medium.counters)}", file=sys.stderr)
    return 0
