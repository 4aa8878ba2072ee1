"""The test harness's loopback ports: a daemon a test starts can bind the ports it was given.

A port the kernel picked (bind to port 0) is an ephemeral one: between the pick and the
daemon's bind, any outgoing connection of the machine may take it as its source port, and
the daemon then exits "cannot bind" while the test waits 30 s for its reply (seen once in a
suite beside four CPU burners)."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from daemon_harness import free_port


def _ephemeral() -> range:
    lo, hi = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
    return range(int(lo), int(hi) + 1)


def test_ports_lie_outside_the_ephemeral_range_and_are_bindable() -> None:
    eph = _ephemeral()
    for count in (1, 3):
        for _ in range(200):
            base = free_port(count)
            assert all(p not in eph for p in range(base, base + count)), base
            for p in range(base, base + count):
                with socket.socket() as s:
                    s.bind(("127.0.0.1", p))


def test_no_port_is_handed_out_twice_in_a_row_of_calls() -> None:
    got = [free_port() for _ in range(300)]
    assert len(set(got)) == len(got)


def test_each_xdist_worker_has_a_band_of_its_own(monkeypatch: pytest.MonkeyPatch) -> None:
    seen = {}
    for w in ("gw0", "gw1", "gw5"):
        monkeypatch.setenv("PYTEST_XDIST_WORKER", w)
        seen[w] = {free_port() for _ in range(100)}
    assert not seen["gw0"] & seen["gw1"] and not seen["gw1"] & seen["gw5"] and not seen["gw0"] & seen["gw5"]
    assert os.environ["PYTEST_XDIST_WORKER"] == "gw5"
