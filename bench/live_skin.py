"""A live emulated skin (``cellbridge mesh up``), daemons on its gateway, and processes around them.

As ``cellbridge demo`` starts them (its helpers are reused): every process in its own
process group, stopped on the way out (SIGTERM, then SIGKILL), also when a test fails.
The recording, replay and proxy tests and bench/bench_recording.py use it.
"""

from __future__ import annotations

import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import zmq
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import mesh_to_toml

from cellbridge.demo import _cellbridge, _free_port, _free_port_block, _group, _warm_kernels, gateway_line

__all__ = ["LiveSkin", "Collector", "live_skin", "group", "cellbridge_cmd", "free_port"]

group = _group
cellbridge_cmd = _cellbridge
free_port = _free_port


@dataclass
class LiveSkin:
    work: Path
    rows: int
    cols: int
    device: str
    base_port: int
    mesh: subprocess.Popen[Any]
    pub: str = field(default_factory=lambda: f"tcp://127.0.0.1:{_free_port()}")
    control: str = field(default_factory=lambda: f"tcp://127.0.0.1:{_free_port()}")

    @property
    def elements(self) -> int:
        return self.rows * self.cols

    @property
    def world_control(self) -> str:
        """The world process's control socket (REQ/REP, as ``cellbridge press`` talks to it)."""
        return f"tcp://127.0.0.1:{self.base_port + 2}"

    def daemon_config(self, name: str = "daemon", source: str = "", link: str = "gateway", extra: str = "",
                      hwm: int = 100_000) -> Path:
        """A daemon config; ``hwm``: room for a test's subscribers, which a loaded machine starves."""
        path = self.work / f"{name}.toml"
        src = f'source = "{source}"\n' if source else ""
        path.write_text(f'[pub]\nendpoint = "{self.pub}"\nhwm = {hwm}\n{src}\n[control]\nendpoint = "{self.control}"\n\n'
                        f'[health]\ninterval = 0.2\n\n[daemon]\nlog_format = "text"\n\n{extra}\n'
                        f'[[link]]\nname = "{link}"\nurl = "{self.device}"\n')
        return path

    @contextmanager
    def daemon(self, config: Path) -> Iterator[subprocess.Popen[Any]]:
        with _group(_cellbridge("daemon", "--config", str(config)),
                    stderr=open(self.work / f"{config.stem}.log", "wb")) as proc:
            yield proc

    def press(self, x: float, y: float, force: float = 3.0, diameter: float = 0.02, duration: float = 2.0) -> None:
        subprocess.run(_cellbridge("press", str(x), str(y), "--force", str(force), "--diameter", str(diameter),
                                   "--duration", str(duration), "--base-port", str(self.base_port)),
                       check=True, timeout=30, stdout=subprocess.DEVNULL)


@contextmanager
def live_skin(work: Path, rows: int = 4, cols: int = 4, name: str = "skin",
              reporting: str = "periodic") -> Iterator[LiveSkin]:
    """An emulated skin in real processes serving its gateway on a pty (no daemon yet);
    ``reporting`` as ``cellbridge mesh up --reporting``."""
    _warm_kernels()
    work.mkdir(parents=True, exist_ok=True)
    mesh_file = work / f"{name}.toml"
    mesh_file.write_text(mesh_to_toml(meshgen.grid(rows, cols)))
    base_port = _free_port_block(3)
    with _group(_cellbridge("mesh", "up", str(mesh_file), "--base-port", str(base_port),
                            "--reporting", reporting),
                stdout=subprocess.PIPE, stderr=open(work / f"{name}-mesh.log", "w"), text=True) as mesh:
        yield LiveSkin(work, rows, cols, gateway_line(mesh)[2], base_port, mesh)


class Collector:
    """A SUB socket that keeps every message it gets, raw payload bytes and receive time included."""

    def __init__(self, endpoint: str, topics: tuple[bytes, ...] = (b"",), ctx: zmq.Context | None = None) -> None:
        self.ctx = ctx or zmq.Context.instance()
        self.sock = self.ctx.socket(zmq.SUB)
        self.sock.linger = 0
        self.sock.rcvhwm = 0
        self.sock.reconnect_ivl = 10  # ms: joins a daemon started after it as soon as it binds
        for t in topics:
            self.sock.subscribe(t)
        self.sock.connect(endpoint)
        self.messages: list[tuple[str, bytes, float]] = []

    def pump(self, seconds: float, until: Any = None) -> None:
        """Receive for ``seconds`` or until ``until(topic, payload)`` is true."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            if not self.sock.poll(50):
                continue
            while True:
                try:
                    topic, payload = self.sock.recv_multipart(zmq.NOBLOCK)
                except zmq.Again:
                    break
                self.messages.append((topic.decode(), payload, time.time()))
                if until is not None and until(topic.decode(), msgpack.unpackb(payload, strict_map_key=False)):
                    return

    @contextmanager
    def in_background(self) -> Iterator[Collector]:
        """Receive in a thread of its own meanwhile, so every receive time is taken as the
        message comes (the caller may block, e.g. on a subprocess); the socket is the
        thread's until the block ends."""
        done = threading.Event()

        def run() -> None:
            while not done.is_set():
                self.pump(0.1)

        th = threading.Thread(target=run, daemon=True)
        th.start()
        try:
            yield self
        finally:
            done.set()
            th.join()

    def wait(self, until: Any, seconds: float) -> bool:
        """While receiving :meth:`in_background`: until a message received from now on makes
        ``until(topic, payload)`` true (True), or ``seconds`` pass (False)."""
        seen, end = len(self.messages), time.monotonic() + seconds
        while time.monotonic() < end:
            while seen < len(self.messages):
                topic, payload, _ = self.messages[seen]
                seen += 1
                if until(topic, msgpack.unpackb(payload, strict_map_key=False)):
                    return True
            time.sleep(0.02)
        return False

    def payloads(self, topic: str | None = None) -> list[tuple[str, dict[str, Any]]]:
        return [(t, msgpack.unpackb(p, strict_map_key=False)) for t, p, _ in self.messages
                if topic is None or t == topic]

    def close(self) -> None:
        self.sock.close()


def calibrated(n: int) -> Any:
    """``until`` for :meth:`Collector.pump`: a health message with ``n`` calibrated elements."""
    return lambda topic, m: topic == "health" and m.get("layout", {}).get("calibration", {}).get("ready", 0) >= n
