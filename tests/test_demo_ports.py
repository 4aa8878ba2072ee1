"""The demo's listening ports come from below the kernel's ephemeral range.

A port in the ephemeral range, free when the demo chose it, was taken as the local end of
an outgoing connection before ``mesh up`` bound it: the demo stopped with "TCP
127.0.0.1:47074 already in use" (1 run in 20 with both cores busy).
"""

from __future__ import annotations

import socket

from cellbridge.demo import LISTEN_FLOOR, _free_port, _free_port_block, ephemeral_low


def test_a_port_block_is_free_and_below_the_ephemeral_range() -> None:
    low = ephemeral_low()
    for _ in range(20):
        base = _free_port_block(3)
        if low - LISTEN_FLOOR >= 1003:
            assert LISTEN_FLOOR <= base and base + 3 <= low, (base, low)
        socks = [socket.socket() for _ in range(3)]
        try:
            for k, s in enumerate(socks):
                s.bind(("127.0.0.1", base + k))  # raises if the block was not free
        finally:
            for s in socks:
                s.close()


def test_a_single_port_is_below_the_ephemeral_range_too() -> None:
    low = ephemeral_low()
    if low - LISTEN_FLOOR >= 1001:
        assert all(LISTEN_FLOOR <= p < low for p in (_free_port() for _ in range(20)))


def test_a_block_skips_a_port_in_use() -> None:
    """A block whose ports are taken is never returned (here: every base tried is checked)."""
    held = []
    try:
        for _ in range(30):
            base = _free_port_block(2)
            s = socket.socket()
            s.bind(("127.0.0.1", base + 1))
            s.listen()
            held.append((base, s))
        bases = {b for b, _ in held}
        assert len(bases) == len(held)  # a taken block was never handed out again
    finally:
        for _, s in held:
            s.close()
