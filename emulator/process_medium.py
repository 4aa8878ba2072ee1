"""``cellbridge medium``: relays transmissions between bridge processes over ZeroMQ.

A thin shell around :class:`~cellbridge.emulator.medium.Medium`: bridges connect a
DEALER socket (identity = bridge id) to this ROUTER. Messages, all multipart:

* bridge → medium: ``[b"tx", cells, frame]`` (cells: u32 big-endian each) and
  ``[b"want", b"1" or b"0"]`` (whether its transceiver is contending for the cell),
* medium → bridge: ``[b"cs", cell u32, start u64, end u64]`` (carrier on a cell) and
  ``[b"rx", cell u32, frame]`` (a delivery at the transmission's end).

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
import struct
import sys
from collections import Counter

import zmq

from cellbridge.emulator.medium import Medium, Transmission
from cellbridge.emulator.mesh import MeshError, load_mesh
from cellbridge.emulator.rawframe import addressed_to
from cellbridge.emulator.realtime import (
    CLOCK_HZ, StopFlag, add_endpoint_arguments, endpoints, now_tick,
)

_CS = struct.Struct(">IQQ")
_CELL = struct.Struct(">I")


def pack_cells(cells: tuple[int, ...]) -> bytes:
    return b"".join(_CELL.pack(c) for c in cells)


def unpack_cells(data: bytes) -> tuple[int, ...]:
    return tuple(_CELL.unpack_from(data, i)[0] for i in range(0, len(data) - len(data) % 4, 4))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Relay cell transmissions between bridge processes (collisions, loss and "
                          "bit errors as in the mesh file). Started by 'cellbridge mesh up'; run it "
                          "yourself to put bridges on other hosts.")
    parser.add_argument("--mesh", required=True, help="mesh file (TOML)")
    parser.add_argument("--seed", type=int, default=0, help="seed of loss and bit errors (default 0)")
    parser.add_argument("--bind", default=None,
                        help="address to bind (default: the --host address, 127.0.0.1)")
    add_endpoint_arguments(parser)


def _send(sock: zmq.Socket, parts: list[bytes], counters: Counter[str], what: str) -> None:
    """Send to one bridge without blocking; a bridge not connected (dead, not started, or
    not heard yet by a restarted medium) or not reading counts as ``<what>_unreachable``
    or ``<what>_backlog``."""
    try:
        sock.send_multipart(parts, zmq.NOBLOCK)
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
    known = {str(b).encode(): b for b in medium.mesh.ids}
    cells_of = {b.id: b.cells for b in medium.mesh.bridges}
    pending: list[tuple[int, int, Transmission]] = []
    busy: dict[int, tuple[int, int]] = {}  # cell -> (start, end) of its latest transmission
    contending: set[int] = set()
    try:
        while not stop.stopped:
            timeout = 100
            if pending:
                timeout = max(0, math.ceil((pending[0][0] - now_tick()) * 1000 / CLOCK_HZ))
            if sock.poll(timeout):
                while True:
                    try:
                        msg = sock.recv_multipart(zmq.NOBLOCK)
                    except zmq.Again:
                        break
                    src = known.get(msg[0])
                    tick = now_tick()
                    if src is not None and len(msg) == 3 and msg[1] == b"want":
                        if msg[2] == b"1":
                            contending.add(src)
                            for c in cells_of[src]:
                                if c in busy and busy[c][1] > tick:
                                    _send(sock, [msg[0], b"cs", _CS.pack(c, *busy[c])], medium.counters, "carrier")
                        else:
                            contending.discard(src)
                        continue
                    if src is None or len(msg) != 4 or msg[1] != b"tx":
                        medium.counters["bad_messages"] += 1
                        continue
                    tx = medium.start(src, msg[3], unpack_cells(msg[2]), tick)
                    for c in unpack_cells(msg[2]):
                        old = busy.get(c)
                        busy[c] = (old[0], max(old[1], tx.end)) if old and old[1] > tick else (tick, tx.end)
                    for r, cell in tx.receivers:
                        if r in contending:
                            _send(sock, [str(r).encode(), b"cs", _CS.pack(cell, tick, tx.end)],
                                  medium.counters, "carrier")
                    heapq.heappush(pending, (tx.end, tx.id, tx))
            now = now_tick()
            while pending and pending[0][0] <= now:
                tx = heapq.heappop(pending)[2]
                for r, cell, data in medium.finish(tx):
                    if addressed_to(data, r):  # a bridge drops others' unicasts anyway: save the message
                        _send(sock, [str(r).encode(), b"rx", _CELL.pack(cell), data], medium.counters, "rx")
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
