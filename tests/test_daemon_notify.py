"""sd_notify spoken from the service manager's side: a unix datagram socket as NOTIFY_SOCKET.

A real subprocess uses Notifier as the daemon does (READY once up, WATCHDOG every
watchdog_interval from its loop, STOPPING on SIGTERM); the test is systemd.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from cellbridge.daemon.ops.notify import Notifier

# The daemon's use of Notifier, reduced to its notify calls.
SERVICE = """
import signal, sys, time
from cellbridge.daemon.ops.notify import Notifier
n = Notifier()
stop = []
signal.signal(signal.SIGTERM, lambda *_: stop.append(1))
n.ready("links up: 1")
n.status("contacts: 0\\nelements: 16")
while not stop:
    time.sleep(n.watchdog_interval)
    n.watchdog()
n.stopping()
sys.exit(n.send_errors)
"""


@contextlib.contextmanager
def notify_socket(address: str | bytes) -> Iterator[socket.socket]:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        sock.bind(address)
        sock.settimeout(10)
        yield sock
    finally:
        sock.close()


def receive_until(sock: socket.socket, wanted: str, limit: int = 200) -> list[str]:
    """Datagrams received up to and including the first that holds the line ``wanted``."""
    got: list[str] = []
    while len(got) < limit:
        got.append(sock.recv(4096).decode())
        if wanted in got[-1].splitlines():
            return got
    raise AssertionError(f"{wanted} not among {got}")


def run_service(env_extra: dict[str, str], sock: socket.socket) -> list[str]:
    env = {**os.environ, "WATCHDOG_USEC": "100000", **env_extra}
    env.pop("WATCHDOG_PID", None)
    proc = subprocess.Popen([sys.executable, "-c", SERVICE], env=env, start_new_session=True)
    try:
        seen = receive_until(sock, "WATCHDOG=1")
        seen += receive_until(sock, "WATCHDOG=1")
        proc.send_signal(signal.SIGTERM)
        seen += receive_until(sock, "STOPPING=1")
        assert proc.wait(10) == 0  # no send error
        return seen
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def test_service_sends_ready_watchdog_stopping(tmp_path: Path) -> None:
    path = tmp_path / "notify.sock"
    with notify_socket(str(path)) as sock:
        seen = run_service({"NOTIFY_SOCKET": str(path)}, sock)
    assert seen[0] == "READY=1\nSTATUS=links up: 1"
    assert seen[1] == "STATUS=contacts: 0 elements: 16"  # a newline would have started a new assignment
    assert seen.count("WATCHDOG=1") >= 2
    assert seen[-1] == "STOPPING=1"


def test_abstract_socket() -> None:
    name = f"cellbridge-test-{uuid.uuid4().hex}"
    with notify_socket(b"\0" + name.encode()) as sock:
        seen = run_service({"NOTIFY_SOCKET": "@" + name}, sock)
    assert seen[0].startswith("READY=1") and seen[-1] == "STOPPING=1"


def test_watchdog_interval_is_half_of_watchdog_usec() -> None:
    assert Notifier({"NOTIFY_SOCKET": "/x", "WATCHDOG_USEC": "30000000"}).watchdog_interval == 15.0
    assert Notifier({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": str(os.getpid())}).watchdog_interval == 2.5
    assert Notifier({"WATCHDOG_USEC": "5000000", "WATCHDOG_PID": str(os.getpid() + 1)}).watchdog_interval is None
    assert Notifier({}).watchdog_interval is None
    assert Notifier({"WATCHDOG_USEC": "0"}).watchdog_interval is None
    assert Notifier({"WATCHDOG_USEC": "soon"}).watchdog_interval is None


def test_reloading_then_ready(tmp_path: Path) -> None:
    path = tmp_path / "notify.sock"
    with notify_socket(str(path)) as sock:
        n = Notifier({"NOTIFY_SOCKET": str(path)})
        before = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        n.reloading()
        n.ready()
        reloading, ready = sock.recv(4096).decode().splitlines(), sock.recv(4096).decode()
        n.close()
    assert reloading[0] == "RELOADING=1"
    key, _, usec = reloading[1].partition("=")
    assert key == "MONOTONIC_USEC" and before <= int(usec) <= before + 10_000_000
    assert ready == "READY=1"


def test_without_notify_socket_nothing_is_sent_and_nothing_fails() -> None:
    n = Notifier({})
    assert not n.enabled
    n.ready("x")
    n.watchdog()
    n.stopping()
    assert n.send_errors == 0


def test_a_vanished_manager_is_counted_not_raised(tmp_path: Path) -> None:
    n = Notifier({"NOTIFY_SOCKET": str(tmp_path / "gone.sock")})
    n.ready()
    n.watchdog()
    assert n.send_errors == 2


def test_a_manager_that_reads_nothing_costs_a_send_a_bounded_wait_not_the_daemon(tmp_path: Path) -> None:
    """The daemon's first act on SIGTERM is STOPPING=1; a service manager whose queue is full
    (busy, or stuck) left that send blocked for ever, and the daemon never drained. A send
    that finds the queue full waits at most SEND_TIMEOUT, is counted as an error, and the
    sends after it do not wait until one gets through."""
    import threading

    path = str(tmp_path / "notify")
    with notify_socket(path):  # bound, never read
        n = Notifier({"NOTIFY_SOCKET": path})
        sent = threading.Event()

        def flood() -> None:
            for i in range(2000):  # past any datagram queue's length (net.unix.max_dgram_qlen)
                n.status(f"line {i}")
            n.stopping()
            sent.set()

        threading.Thread(target=flood, daemon=True).start()
        assert sent.wait(30), "a send blocked on a full queue"
        assert n.send_errors > 0


@pytest.mark.parametrize("value", ["", "relative/path.sock", "vsock:2:1234"])
def test_unusable_notify_socket_values_disable_it(value: str) -> None:
    assert not Notifier({"NOTIFY_SOCKET": value}).enabled
