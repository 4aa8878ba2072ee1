"""Real processes, ptys and ZeroMQ sockets around a `cellbridge daemon` (tests and benchmarks)."""

from __future__ import annotations

import errno
import os
import random
import select
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import msgpack
import zmq

CLI = shutil.which("cellbridge", path=str(Path(sys.executable).parent)) or "cellbridge"


def free_port(count: int = 1) -> int:
    """A loopback TCP port (the first of ``count`` in a row) that a process this test or
    benchmark starts can bind: free now, outside the kernel's ephemeral range, and in a
    band of its own per pytest-xdist worker, and not among the last 512 this process handed out.

    A port the kernel picks (bind to 0) is an ephemeral one: until the daemon binds it, any
    outgoing connection of the machine (a subscriber, the other worker's tests) may take it
    as its source port, and the daemon then exits "cannot bind" while the test waits for
    its reply (seen once in a suite beside four CPU burners)."""
    lo, hi = _ephemeral_range()
    top = max(lo, 12_000)
    bands = 16
    width = (top - 10_000) // bands
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw")
    band = 10_000 + (int(worker) % bands if worker.isdigit() else 0) * width
    start = random.randrange(width)
    for i in range(width):
        port = band + (start + i) % width
        if port + count > band + width or any(p in _HANDED for p in range(port, port + count)):
            continue
        try:
            for p in range(port, port + count):
                with socket.socket() as s:
                    s.bind(("127.0.0.1", p))
        except OSError:
            continue
        _HANDED.extend(range(port, port + count))
        return port
    raise RuntimeError(f"no {count} free loopback ports in {band}..{band + width - 1}")


#: the ports this process handed out lately (a daemon may not have bound them yet)
_HANDED: deque[int] = deque(maxlen=512)


def _ephemeral_range() -> tuple[int, int]:
    """The kernel's ephemeral port range (Linux; elsewhere the IANA one)."""
    try:
        lo, hi = Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()
        return int(lo), int(hi)
    except (OSError, ValueError):
        return 49152, 65535


def idle_connects(endpoint: str, n: int) -> list[socket.socket]:
    """``n`` TCP connections to ``endpoint`` that never send a byte; non-blocking, so a
    full listen backlog does not stall the caller. The caller closes them."""
    host, port = endpoint.removeprefix("tcp://").rsplit(":", 1)
    out = []
    for _ in range(n):
        s = socket.socket()
        s.setblocking(False)
        err = s.connect_ex((host, int(port)))
        if err not in (0, errno.EINPROGRESS):
            s.close()
            raise OSError(err, f"connect to {endpoint}: {os.strerror(err)}")
        out.append(s)
    return out


def proc_status_kb(pid: int, key: str) -> int:
    """A ``/proc/PID/status`` figure in kB (``VmRSS``, ``VmHWM``: peak resident memory)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise KeyError(key)


def open_descriptors(pid: int) -> int:
    return len(os.listdir(f"/proc/{pid}/fd"))


class Pty:
    """A pseudo-terminal whose slave is reachable through a stable symlink, like a gateway's."""

    def __init__(self, link: Path) -> None:
        self.link = link
        self.master = -1
        self.open()

    def open(self) -> None:
        self.master, slave = os.openpty()
        os.set_blocking(self.master, False)  # writes wait in select (write), never in the kernel
        name = os.ttyname(slave)
        os.close(slave)  # the daemon opens it by path
        tmp = self.link.with_suffix(".tmp")
        if tmp.is_symlink():
            tmp.unlink()
        tmp.symlink_to(name)
        tmp.replace(self.link)

    def write(self, data: bytes, limit: float = 10.0) -> None:
        """All of ``data`` into the line, waiting at most ``limit`` s for room: a pty holds
        about 12 KB, and a daemon that stopped reading (died, or its link ended) would
        otherwise block the test for ever instead of failing it."""
        view = memoryview(data)
        end = time.monotonic() + limit
        while view:
            if not select.select([], [self.master], [], max(0.0, end - time.monotonic()))[1]:
                raise AssertionError(f"nobody read the pty for {limit:.0f} s ({len(view)} bytes left to write)")
            n = os.write(self.master, view)
            view = view[n:]

    def read(self, timeout: float = 2.0) -> bytes:
        ready, _, _ = select.select([self.master], [], [], timeout)
        return os.read(self.master, 4096) if ready else b""

    def close(self) -> None:
        if self.master >= 0:
            os.close(self.master)
            self.master = -1


def write_config(path: Path, links: list[dict[str, Any]], **sections: dict[str, Any]) -> dict[str, str]:
    endpoints = {"pub": f"tcp://127.0.0.1:{free_port()}", "control": f"tcp://127.0.0.1:{free_port()}"}
    lines = []
    base: dict[str, dict[str, Any]] = {"pub": {"endpoint": endpoints["pub"]},
                                       "control": {"endpoint": endpoints["control"]},
                                       "health": {"interval": 0.2}, "daemon": {"log_format": "json"}}
    for name, values in sections.items():
        base.setdefault(name, {}).update(values)
    endpoints = {"pub": base["pub"]["endpoint"], "control": base["control"]["endpoint"]}
    for name, values in base.items():
        lines.append(f"[{name}]")
        lines += [f"{k} = {_toml(v)}" for k, v in values.items()]
    for link in links:
        lines.append("[[link]]")
        lines += [f"{k} = {_toml(v)}" for k, v in link.items()]
    path.write_text("\n".join(lines) + "\n")
    return endpoints


def _toml(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (str, Path)):
        return '"' + str(v) + '"'
    return repr(v)


def stop_session(proc: subprocess.Popen[bytes]) -> None:
    """SIGTERM to the process group of ``proc`` (started with ``start_new_session``), SIGKILL after 10 s."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5)


@contextmanager
def daemon(config: Path, stderr: Path | None = None, env: dict[str, str] | None = None,
           preexec_fn: Callable[[], None] | None = None,
           argv: list[str] | None = None) -> Iterator[subprocess.Popen[bytes]]:
    """The daemon as a real process in its own process group; always stopped on exit.

    ``preexec_fn`` runs in the child before the command (resource limits, umask); ``argv``
    is the command (default ``cellbridge daemon --config CONFIG``; a traced daemon,
    ``bench/press_trace.py``, takes the same config)."""
    err = open(stderr, "wb") if stderr else subprocess.DEVNULL
    proc = subprocess.Popen(argv or [CLI, "daemon", "--config", str(config)], stderr=err, stdout=subprocess.DEVNULL,
                            start_new_session=True, env=env, preexec_fn=preexec_fn)
    try:
        yield proc
    finally:
        stop_session(proc)
        if stderr:
            err.close()  # type: ignore[union-attr]  # opened when stderr was asked for


class Client:
    """Subscriber and control client on loopback."""

    def __init__(self, endpoints: dict[str, str], topics: tuple[bytes, ...] = (b"",)) -> None:
        self.ctx = zmq.Context()
        self.endpoints = endpoints
        self.sub = self.ctx.socket(zmq.SUB)
        self.sub.setsockopt(zmq.LINGER, 0)
        self.sub.setsockopt(zmq.RCVHWM, 0)
        for t in topics:
            self.sub.setsockopt(zmq.SUBSCRIBE, t)
        self.sub.connect(endpoints["pub"])

    def recv(self, timeout: float = 5.0) -> tuple[str, dict[str, Any]] | None:
        if not self.sub.poll(int(timeout * 1000)):
            return None
        topic, payload = self.sub.recv_multipart()
        return topic.decode(), msgpack.unpackb(payload, raw=False)

    def wait_for(self, topic: str, pred: Any = lambda m: True, timeout: float = 10.0) -> dict[str, Any]:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            got = self.recv(max(0.01, end - time.monotonic()))
            if got is not None and got[0] == topic and pred(got[1]):
                return got[1]
        raise AssertionError(f"no matching {topic!r} message within {timeout} s")

    def request(self, body: bytes | dict[str, Any], timeout: float = 5.0) -> dict[str, Any]:
        req = self.ctx.socket(zmq.REQ)
        req.setsockopt(zmq.LINGER, 0)
        req.connect(self.endpoints["control"])
        try:
            req.send(body if isinstance(body, bytes) else msgpack.packb(body))
            if not req.poll(int(timeout * 1000)):
                raise AssertionError(f"no control reply within {timeout} s")
            return msgpack.unpackb(req.recv(), raw=False)
        finally:
            req.close()

    def ready(self, timeout: float = 15.0) -> None:
        """Until the daemon answers ping and this subscriber gets messages (joined)."""
        self.request({"v": 1, "cmd": "ping"}, timeout)
        self.wait_for("health", timeout=timeout)

    def until_exit(self, proc: subprocess.Popen[bytes], timeout: float = 30.0) -> list[tuple[str, dict[str, Any]]]:
        """Every message until ``proc`` (a daemon with ``exit_when_done``) exits by itself, cleanly."""
        messages = []
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            got = self.recv(0.5)
            if got is not None:
                messages.append(got)
            elif proc.poll() is not None:
                break
        assert proc.wait(10) == 0  # exit_when_done: it stops by itself, cleanly
        return messages

    def close(self) -> None:
        self.ctx.destroy(linger=0)
