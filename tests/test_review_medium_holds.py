"""Hostile review of the ack hold (carrier_arbiter.py, process_medium.py).

The shell is driven as it runs: ``serve`` on a real UDP socket on loopback, in a thread,
with sockets posing as bridges (no processes)."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

from cellbridge.emulator import meshgen, udp
from cellbridge.emulator.carrier_arbiter import HOLD, CarrierArbiter
from cellbridge.emulator.medium import Medium
from cellbridge.emulator.medium_wire import decode_rx, encode_tx, encode_want
from cellbridge.emulator.process_medium import serve
from cellbridge.protocol import ADDR_BROADCAST, Beacon, Frame, encode

BIT = 50
DIFS = 40 * BIT
GUARD = 200_000


class _Stop:
    stopped = False


@contextmanager
def serving(n: int = 2) -> Iterator[tuple[int, Medium, threading.Thread, list[BaseException]]]:
    medium = Medium(meshgen.line(n), 0)
    sock = udp.bind("127.0.0.1", 0)
    port = sock.getsockname()[1]
    stop = _Stop()
    errors: list[BaseException] = []

    def run() -> None:
        try:
            serve(medium, sock, stop)  # type: ignore[arg-type]  # duck-typed StopFlag
        except BaseException as exc:  # noqa: BLE001  # what killed the medium
            errors.append(exc)

    t = threading.Thread(target=run, daemon=True)
    t.start()
    try:
        yield port, medium, t, errors
    finally:
        stop.stopped = True
        t.join(5)
        sock.close()


def test_a_transmission_with_a_frame_shorter_than_3_bytes_does_not_kill_the_medium() -> None:
    # decode_tx takes an empty frame (test_emulator_medium_wire encodes one); the new
    # parsing in serve's admit() reads frame[2] unguarded: IndexError, serve() returns
    # by exception, and the medium process exits. Before 7800b1e it was relayed.
    beacon = encode(Frame(1, ADDR_BROADCAST, 1, 0, Beacon(0, 0, 0)))
    with serving() as (port, medium, t, errors):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as b1, \
                socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as b2:
            for s in (b1, b2):
                s.connect(("127.0.0.1", port))
                s.settimeout(3)
            b2.send(encode_want(2, False))
            for short in (b"", b"\x01", b"\x01\x02"):
                b1.send(encode_tx(1, (1,), short, False))
            time.sleep(0.2)
            b1.send(encode_tx(1, (1,), beacon, False, 4242))
            got = None
            try:
                while got is None or got[1] != beacon:
                    got = decode_rx(b2.recv(4096))
            except socket.timeout:
                pass
            assert not errors, errors
            assert t.is_alive()
            assert got is not None and got[1] == beacon
