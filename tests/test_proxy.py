"""`cellbridge proxy`: two daemons on two emulated skins read as one stream, told apart by `source`;
CURVE on the proxy's front as the daemon does it; subscriptions passed upstream."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from contextlib import ExitStack
from pathlib import Path

import msgpack
import pytest
import zmq
from cellbridge.daemon.ops.security import apply_client
from cellbridge.daemon.shell.keys import write_keypair

from live_skin import Collector, calibrated, cellbridge_cmd, free_port, group, live_skin
from support.example_subscribers import c_subscriber
from support.pub_helpers import json_lines, run_subscriber


def _proxy_cmd(front: str, backs: list[str], *extra: str) -> list[str]:
    return cellbridge_cmd("proxy", "--front", front, *[a for b in backs for a in ("--back", b)], *extra)


def _sources(sock: zmq.Socket, want: set[str], seconds: float) -> dict[str, int]:
    """Messages per source until every wanted source was seen (or the time is up)."""
    seen: dict[str, int] = {}
    end = time.monotonic() + seconds
    while time.monotonic() < end and not want <= set(seen):
        if sock.poll(100):
            _, payload = sock.recv_multipart()
            src = msgpack.unpackb(payload)["source"]
            seen[src] = seen.get(src, 0) + 1
    return seen


def test_two_skins_behind_one_curve_proxy_reach_the_c_subscriber_told_apart_by_source(tmp_path: Path) -> None:
    c_cmd = c_subscriber(tmp_path)
    keys = tmp_path / "keys"
    (keys / "allowed").mkdir(parents=True)
    proxy_pub, proxy_secret = write_keypair(keys, "proxy")
    _, arm_secret = write_keypair(keys / "allowed", "arm")
    _, stranger_secret = write_keypair(keys, "stranger")  # a key pair the proxy does not allow
    front = f"tcp://127.0.0.1:{free_port()}"
    ctx = zmq.Context()
    with ExitStack() as stack:
        skins, watches = [], []
        for name in ("skin-a", "skin-b"):  # both started, then waited for: their calibrations overlap
            skin = stack.enter_context(live_skin(tmp_path / name, 2, 2, name))
            watch = Collector(skin.pub, (b"health",), ctx)
            stack.callback(watch.close)
            stack.enter_context(skin.daemon(skin.daemon_config(source=name)))
            skins.append(skin)
            watches.append(watch)
        for watch in watches:
            watch.pump(120, until=calibrated(4))
        proxy = stack.enter_context(group(
            _proxy_cmd(front, [s.pub for s in skins], "--server-secret", str(proxy_secret),
                       "--allowed-clients", str(keys / "allowed")),
            stderr=open(tmp_path / "proxy.log", "wb")))

        def subscriber(secret: Path) -> zmq.Socket:
            sock = ctx.socket(zmq.SUB)
            sock.linger = 0
            apply_client(sock, proxy_pub, secret)
            sock.subscribe(b"health")
            sock.connect(front)
            stack.callback(sock.close)
            return sock

        allowed, stranger = subscriber(arm_secret), subscriber(stranger_secret)
        assert set(_sources(allowed, {"skin-a", "skin-b"}, 30)) == {"skin-a", "skin-b"}
        assert _sources(stranger, {"skin-a"}, 3) == {}  # a foreign key gets nothing
        out = run_subscriber([*c_cmd, "-e", front, "-n", "30", "-s", str(proxy_pub), "-k", str(arm_secret),
                              "health"], cwd=tmp_path, timeout=60)
        assert out.returncode == 0, out.stderr
        lines = json_lines(out.stdout)
        assert len(lines) == 30 and {ln["topic"] for ln in lines} == {"health"}
        assert {ln["payload"]["source"] for ln in lines} == {"skin-a", "skin-b"}
        os.killpg(proxy.pid, signal.SIGTERM)
        assert proxy.wait(15) == 0
    ctx.term()
    stopped = json.loads((tmp_path / "proxy.log").read_text().strip().splitlines()[-1])
    assert stopped["proxy"] == "stopped" and stopped["handshakes_denied"] >= 1 and stopped["handshakes_accepted"] >= 2


def test_subscriptions_reach_the_daemons_through_the_proxy(tmp_path: Path) -> None:
    """A daemon builds a topic only while someone subscribes to it: through the proxy too."""
    with live_skin(tmp_path, 2, 2) as skin, skin.daemon(skin.daemon_config(source="solo")):
        front = f"tcp://127.0.0.1:{free_port()}"
        with group(_proxy_cmd(front, [skin.pub]), stderr=subprocess.DEVNULL) as proxy:
            sub = Collector(front, (b"raw",))
            try:
                sub.pump(60, until=lambda t, m: t == "raw")
                assert sub.payloads("raw") and all(m["source"] == "solo" for _, m in sub.payloads())
            finally:
                sub.close()
            os.killpg(proxy.pid, signal.SIGTERM)
            assert proxy.wait(15) == 0


def test_proxy_refuses_a_front_beyond_loopback_without_curve(tmp_path: Path) -> None:
    r = subprocess.run(_proxy_cmd("tcp://0.0.0.0:5999", ["tcp://127.0.0.1:5560"]), capture_output=True, text=True,
                       timeout=30)
    assert r.returncode == 2 and "refusing to bind" in r.stderr and "CURVE" in r.stderr
    r = subprocess.run(_proxy_cmd("tcp://127.0.0.1:5999", ["tcp://127.0.0.1:5560=missing.key"]),
                       capture_output=True, text=True, timeout=30)
    assert r.returncode == 2 and "--client-key" in r.stderr


@pytest.mark.parametrize("bad", ["5560", "http://x", "inproc://daemon"])  # inproc: this process only, no daemon
def test_proxy_names_a_bad_backend(bad: str) -> None:
    r = subprocess.run(cellbridge_cmd("proxy", "--back", bad), capture_output=True, text=True, timeout=30)
    assert r.returncode == 2 and "ZeroMQ endpoint" in r.stderr


def test_a_curve_daemon_behind_the_proxy_is_reached_with_its_key_and_the_proxys_own(tmp_path: Path) -> None:
    """CURVE on the back side: a publisher that allows only the proxy's key, next to a plain one."""
    from cellbridge.daemon.ops.security import CurveKeys, CurveServer

    from support.pub_helpers import publisher

    (tmp_path / "allowed").mkdir()
    server_pub, server_secret = write_keypair(tmp_path, "daemon")
    _, proxy_secret = write_keypair(tmp_path / "allowed", "proxy")
    context = zmq.Context()
    curve = CurveServer(context, CurveKeys(server_secret, tmp_path / "allowed"))
    front = f"tcp://127.0.0.1:{free_port()}"
    try:
        with publisher(setup=curve.apply, context=context) as secured, publisher(period=0.05) as plain, \
                group(_proxy_cmd(front, [f"{secured}={server_pub}", plain], "--client-key", str(proxy_secret)),
                      stderr=subprocess.DEVNULL) as proxy:
            sub = Collector(front, (b"contact",))
            try:
                sub.pump(20, until=lambda t, m: len(sub.messages) >= 60)
            finally:
                sub.close()
            os.killpg(proxy.pid, signal.SIGTERM)
            assert proxy.wait(15) == 0
        counters = curve.counters()
    finally:
        curve.stop()
        context.term()
    assert len(sub.messages) >= 60 and counters["handshakes_accepted"] >= 1 and counters["handshakes_denied"] == 0
    # both publishers got through: the secured one every 20 ms, the plain one every 50 ms
    seqs = [msgpack.unpackb(p)["seq"] for _, p, _ in sub.messages]
    assert any(b < a for a, b in zip(seqs, seqs[1:]))  # two numberings interleaved: both came through


@pytest.mark.parametrize("hwm", ["0", "-1"])
def test_proxy_refuses_a_queue_bound_that_is_no_bound(hwm: str) -> None:
    """libzmq reads a high-water mark of 0 as "no limit": one slow subscriber then grows the
    proxy's memory without end, while --help promises a bound per subscriber."""
    with group(_proxy_cmd(f"tcp://127.0.0.1:{free_port()}", ["tcp://127.0.0.1:1"], "--hwm", hwm),
               stderr=subprocess.PIPE, text=True) as proxy:
        try:
            rc = proxy.wait(15)
        except subprocess.TimeoutExpired:
            rc = None  # (it ran, unbounded)
        assert rc == 2, f"status {rc}"
        assert proxy.stderr is not None and "--hwm" in proxy.stderr.read()


def test_a_proxy_whose_thread_dies_ends_with_a_failure_instead_of_staying_up_deaf() -> None:
    """The proxy runs libzmq's loop in a thread; when that loop failed (an error from
    libzmq), the thread ended and the process stayed up for ever forwarding nothing, so
    systemd never restarted it. The failure is injected (libzmq's loop cannot be made to
    fail from outside): the process must end with status 1, saying why."""
    front, back = free_port(), free_port()
    code = ("import sys, zmq\n"
            "def broken(*args):\n"
            "    raise zmq.ZMQError(14)\n"
            "zmq.proxy_steerable = broken\n"
            "from cellbridge.cli import main\n"
            f"sys.exit(main(['proxy', '--front', 'tcp://127.0.0.1:{front}', '--back', 'tcp://127.0.0.1:{back}']))\n")
    with group([sys.executable, "-c", code], stderr=subprocess.PIPE, text=True) as proc:
        try:
            rc = proc.wait(20)
        except subprocess.TimeoutExpired:
            pytest.fail("the proxy stayed up with its proxy thread dead")
        err = proc.stderr.read() if proc.stderr is not None else ""
    assert rc == 1, err
    last = json.loads(err.strip().splitlines()[-1])
    assert last["proxy"] == "failed" and "ZMQError" in last["error"], err
