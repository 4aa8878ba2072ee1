"""What one client, and all of them, can make the daemon hold: descriptors and memory.

Idle TCP connects that never speak ZMTP used to take every descriptor the daemon had
(control went silent, the gateway line could not be reopened); one 500 MB control
request took gigabytes and came back echoed in the reply. These tests run the daemon
as a real process with systemd's default descriptor limit and attack it over loopback.
"""

from __future__ import annotations

import resource
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgpack
import pytest
import zmq
from cellbridge.daemon.core.control import MAX_ID_BYTES, RequestError, parse_request
from cellbridge.daemon.ops.peers import PeerLimits

from daemon_harness import Client, Pty, daemon, idle_connects, open_descriptors, proc_status_kb, write_config

SERVICE_NOFILE = 1024  # what systemd gives a service unless LimitNOFILE= says otherwise


def _service_nofile() -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (SERVICE_NOFILE, SERVICE_NOFILE))


@pytest.fixture
def limited(tmp_path: Path) -> Iterator[tuple[Pty, Client, dict[str, str], int]]:
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link, "reconnect_min": 0.05, "reconnect_max": 0.2}],
                             contact={"enabled": False})
    client = Client(endpoints, (b"health",))
    try:
        with daemon(cfg, tmp_path / "stderr.log", preexec_fn=_service_nofile) as proc:
            client.ready()
            yield pty, client, endpoints, proc.pid
            assert proc.poll() is None, "the daemon died during the test"
    finally:
        client.close()
        pty.close()


# -- descriptors ------------------------------------------------------------------------

def test_idle_connections_cannot_take_the_descriptors_of_control_or_the_gateway(limited) -> None:
    """2 000 idle connects to control and 1 000 to PUB under a 1 024 descriptor limit: the
    daemon holds a bounded number of them, still answers control and reopens its line."""
    pty, client, endpoints, pid = limited
    held: list[socket.socket] = []
    try:
        held = idle_connects(endpoints["control"], 2000) + idle_connects(endpoints["pub"], 1000)
        time.sleep(1.0)  # let the daemon accept (and refuse) what it will
        assert client.request({"v": 1, "cmd": "ping"}, timeout=10.0)["ok"]
        pty.close()  # a blip on the gateway line: the daemon must be able to open it again
        time.sleep(0.3)
        pty.open()
        h = client.wait_for("health", lambda m: m["links"]["gw"]["connected"] and m["links"]["gw"]["reconnects"] >= 1,
                            timeout=15.0)
        peers = h["security"]["peers"]
        for role in ("control", "pub"):  # silent connects were dropped for newer ones, or refused
            assert peers[role]["evicted"] + peers[role]["refused"] > 0
        assert peers["control"]["connected"] <= 64 and peers["pub"]["connected"] <= 256
        assert open_descriptors(pid) < 64 + 256 + 100
    finally:
        for s in held:
            s.close()


def test_peers_that_never_handshake_are_dropped(tmp_path: Path) -> None:
    """A connection that sends nothing is closed by the daemon after handshake_timeout."""
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link}], contact={"enabled": False},
                             peers={"handshake_timeout": 0.5})
    client = Client(endpoints, (b"health",))
    try:
        with daemon(cfg, tmp_path / "stderr.log"):
            client.ready()
            s = idle_connects(endpoints["control"], 1)[0]
            s.setblocking(True)
            s.settimeout(20.0)
            try:
                assert s.recv(1 << 16) is not None  # the greeting, then EOF when the daemon closes
                while s.recv(1 << 16):
                    pass
            finally:
                s.close()
    finally:
        client.close()
        pty.close()


def test_peer_limits_bound_all_peers_and_each_address() -> None:
    lim = PeerLimits(max_peers=4, max_per_address=2)
    assert lim.accepted(10, "127.0.0.1") == [] and lim.accepted(11, "127.0.0.1") == []
    assert lim.accepted(12, "127.0.0.1") == [12]  # a third from one address
    assert lim.accepted(13, "10.0.0.2") == [] and lim.accepted(14, "10.0.0.3") == []
    assert lim.accepted(15, "10.0.0.4") == [15]  # a fifth in all
    lim.closed(10)
    assert lim.accepted(16, "127.0.0.1") == []  # room again
    lim.closed(99)  # an unknown descriptor (refused, or closed twice) changes nothing
    assert lim.stats() == {"connected": 4, "accepted": 5, "refused": 2, "evicted": 0, "max": 4,
                           "max_per_address": 2}


def test_a_new_connection_takes_the_place_of_the_oldest_silent_one() -> None:
    """Idle connects must not lock out a client that speaks: at the bound, the oldest
    connection whose peer sent nothing goes; one that spoke is never evicted."""
    lim = PeerLimits(max_peers=3, max_per_address=3)
    spoke = {2}
    for fd in (1, 2, 3):
        assert lim.accepted(fd, "a", lambda f: f not in spoke) == []
    assert lim.accepted(4, "a", lambda f: f not in spoke) == [1]  # 1 was silent and oldest
    assert lim.accepted(5, "a", lambda f: f not in spoke) == [3]  # 2 spoke: skipped
    spoke |= {4, 5}
    assert lim.accepted(6, "a", lambda f: f not in spoke) == [6]  # all spoke: the new one is refused
    assert lim.stats()["evicted"] == 2 and lim.stats()["refused"] == 1 and lim.stats()["connected"] == 3


# -- message sizes ----------------------------------------------------------------------

def test_a_huge_id_is_refused_not_echoed() -> None:
    with pytest.raises(RequestError, match="id"):
        parse_request(msgpack.packb({"cmd": "ping", "id": "x" * (MAX_ID_BYTES + 1)}))
    with pytest.raises(RequestError, match="id"):
        parse_request(msgpack.packb({"cmd": "ping", "id": {"a": [1, 2, 3]}}))
    assert parse_request(msgpack.packb({"cmd": "ping", "id": "x" * MAX_ID_BYTES})).id == "x" * MAX_ID_BYTES
    assert parse_request(msgpack.packb({"cmd": "ping", "id": 7})).id == 7


def test_oversize_requests_get_an_error_and_huge_ones_cost_no_memory(limited) -> None:
    _, client, endpoints, pid = limited
    rep = client.request({"v": 1, "cmd": "ping", "id": "x" * 200_000})  # over max_request_bytes (64 KiB)
    assert not rep["ok"] and "max_request_bytes" in rep["error"] and "id" not in rep
    peak = proc_status_kb(pid, "VmHWM") / 1024
    ctx = zmq.Context()
    try:
        req = ctx.socket(zmq.REQ)
        req.setsockopt(zmq.LINGER, 0)
        req.connect(endpoints["control"])
        req.send(b"\x00" * 200_000_000)  # beyond what the transport accepts: the connection is dropped
        assert not req.poll(3000)
    finally:
        ctx.destroy(linger=0)
    assert client.request({"v": 1, "cmd": "ping"})["ok"]
    assert proc_status_kb(pid, "VmHWM") / 1024 - peak < 50, "a 200 MB request was read into memory"
    client.wait_for("health", lambda m: m["control"]["oversize"] == 1)


#: A subscriber that sends one huge subscription, in a process of its own: libzmq on the
#: sending side crashes when it closes a socket whose peer refused such a message.
HUGE_SUBSCRIPTION = """
import sys, time, zmq
ctx = zmq.Context()
s = ctx.socket(zmq.XSUB)
s.connect(sys.argv[1])
s.send(b"\\x01" + b"h" * 50_000_000)
time.sleep(2.0)
"""


def test_subscriptions_are_bounded_in_size_and_kind(limited) -> None:
    """A 50 MB subscription is dropped by the transport (it used to be read whole, kept in
    the socket's subscription tree and handed up); prefixes that can match no topic are
    counted, never kept by the daemon itself."""
    _, client, endpoints, pid = limited
    peak = proc_status_kb(pid, "VmHWM") / 1024
    subprocess.run([sys.executable, "-c", HUGE_SUBSCRIPTION, endpoints["pub"]], timeout=60, capture_output=True)
    ctx = zmq.Context()
    try:
        junk = ctx.socket(zmq.XSUB)
        junk.setsockopt(zmq.LINGER, 0)
        junk.setsockopt(zmq.SNDHWM, 0)  # all 2 000 are sent when it connects
        junk.connect(endpoints["pub"])
        for i in range(2000):
            junk.send(b"\x01nonsense-%d" % i)
        h = client.wait_for("health", lambda m: m["pub"]["subscriptions_unmatched"] >= 2000, timeout=15.0)
        assert "health" in h["pub"]["subscribed_topics"]
    finally:
        ctx.destroy(linger=0)
    assert client.request({"v": 1, "cmd": "ping"})["ok"]
    assert proc_status_kb(pid, "VmHWM") / 1024 - peak < 20, "a 50 MB subscription was read into memory"


def test_requests_beyond_max_pending_are_answered_busy(tmp_path: Path) -> None:
    """Commands wait for bridges; a client pipelining thousands of them over DEALER must
    not make the daemon hold thousands of waiting tasks."""
    from daemon_traffic import GridFrames

    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link}], contact={"enabled": False},
                             control={"max_pending": 2})
    client = Client(endpoints)
    try:
        with daemon(cfg, tmp_path / "stderr.log"):
            client.ready()
            sk = GridFrames()
            pty.write(sk.hellos())
            for _, data in sk.stream(3):
                pty.write(data)
            client.wait_for("element")
            dealer = client.ctx.socket(zmq.DEALER)
            dealer.setsockopt(zmq.LINGER, 0)
            dealer.connect(endpoints["control"])
            for i in range(5):  # nobody answers the pings: each waits its timeout
                dealer.send(msgpack.packb({"v": 1, "cmd": "ping", "bridge": 2, "timeout": 3.0, "id": i}))
            replies: list[dict[str, Any]] = []
            while len(replies) < 5 and dealer.poll(10_000):
                replies.append(msgpack.unpackb(dealer.recv()))
            busy = [r for r in replies if "busy" in r.get("error", "")]
            waited = [r for r in replies if "no reply within the timeout" in r.get("error", "")]
            assert len(busy) == 3 and len(waited) == 2, replies
            assert sorted(r["id"] for r in busy) == [2, 3, 4]  # which ones to send again
            assert client.request({"v": 1, "cmd": "status"})["control"]["busy"] == 3
            dealer.close(0)
    finally:
        client.close()
        pty.close()
