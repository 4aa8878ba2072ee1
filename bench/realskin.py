"""A real-time emulated skin for the benchmarks: ``cellbridge mesh up`` read off its gateway
ptys, each sample stamped with the host monotonic time its bytes arrived.

Imported as ``realskin`` by scripts in bench/ (Python puts the script's folder first on
sys.path). What it measures is what a host on the pty sees: no daemon in between.

Each sample's C1 gate start in host time is exact: a bridge's tick is the host's monotonic
clock at 50 MHz and its ``cycle`` is its crystal's counter at the gate's tick
(``Crystal.tick_at`` inverts it, the crystal drawn from the mesh seed as the bridge does).
So "gate start → on the pty" is the whole delay of the skin for that sample, and the
arrival spread of one ``index`` across bridges is direct.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Self

import msgpack
import serial
import zmq
from cellbridge.emulator.firmware.meshtime import Crystal
from cellbridge.emulator.mesh.mesh import Mesh, mesh_to_toml
from cellbridge.emulator.mesh.virtual import default_chip
from cellbridge.emulator.realtime.realtime import CLOCK_HZ
from cellbridge.protocol import Data, HostReceiver, SampleFlags, StreamDecoder

from daemon_harness import free_port

_NO_MESH_TIME = int(SampleFlags.NO_MESH_TIME)


def free_base_port() -> int:
    """A base port with the next two free too (:func:`daemon_harness.free_port`)."""
    return free_port(3)


def rt_permitted() -> bool:
    """Whether this user may run a process at real-time priority (``chrt -f``)."""
    chrt = shutil.which("chrt")
    return chrt is not None and subprocess.run([chrt, "-f", "10", "true"], capture_output=True).returncode == 0


def read_now(port: serial.Serial) -> bytes:
    """What the port holds now, as soon as a byte is there (b"" after the port's timeout).
    ``port.read(n)`` with a timeout waits for all ``n`` bytes or the whole timeout: every
    arrival would be stamped up to that timeout late, and batches of frames that came
    tens of milliseconds apart would share one stamp."""
    first = port.read(1)
    return first + port.read(port.in_waiting) if first and port.in_waiting else first


def percentile(xs: list[float], q: float) -> float:
    if not xs:
        return float("nan")
    ys = sorted(xs)
    return ys[min(len(ys) - 1, int(q * len(ys)))]


def world_press(base_port: int, x: float, y: float, duration: float = 0.5, force: float = 3.0,
                diameter: float = 0.02) -> float:
    """Ask the world of the ``mesh up`` on ``base_port`` for a press now; the host monotonic
    second the press starts (as the world set it). RuntimeError when it refuses or is silent."""
    ctx: zmq.Context = zmq.Context.instance()
    s = ctx.socket(zmq.REQ)
    s.setsockopt(zmq.LINGER, 0)
    s.connect(f"tcp://127.0.0.1:{base_port + 2}")
    try:
        s.send(msgpack.packb({"duration": duration, "position": [x, y], "force": force, "diameter": diameter}))
        if not s.poll(3000):
            raise RuntimeError("the world did not answer")
        answer = msgpack.unpackb(s.recv())
    finally:
        s.close()
    if not answer.get("ok"):
        raise RuntimeError(answer.get("error"))
    return float(answer["start"])


@dataclass
class Arrival:
    bridge: int
    index: int
    cycle: int
    c1: int
    synced: bool
    gate: float  #: host monotonic seconds of the C1 gate start
    arrived: float  #: host monotonic seconds the bytes were read off the pty


@dataclass
class RealSkin:
    """``with RealSkin(mesh, seconds...) as skin:`` runs the skin and reads every gateway."""

    mesh: Mesh
    rate: int = 100
    reporting: str = "periodic"
    seed: int = 0
    extra_args: tuple[str, ...] = ()
    arrivals: list[Arrival] = field(default_factory=list)
    counters: dict[int, dict[str, int]] = field(default_factory=dict)
    gates: dict[int, dict[int, int]] = field(default_factory=dict)  #: bridge -> planned gate ticks by index
    stderr_lines: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._tmp = tempfile.TemporaryDirectory()
        self.path = os.path.join(self._tmp.name, "mesh.toml")
        Path(self.path).write_text(mesh_to_toml(self.mesh))
        self.base_port = free_base_port()
        self._crystals = {b.id: Crystal(default_chip(b.id, self.seed).config.crystal_ppm)
                          for b in self.mesh.bridges}
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()

    def gate_time(self, bridge: int, cycle: int) -> float:
        return self._crystals[bridge].tick_at(cycle) / CLOCK_HZ

    def __enter__(self) -> Self:
        self._err = open(self.path + ".err", "w+")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "cellbridge", "mesh", "up", self.path, "--base-port", str(self.base_port),
             "--rate", str(self.rate), "--reporting", self.reporting, "--seed", str(self.seed), *self.extra_args],
            stdout=subprocess.PIPE, stderr=self._err, start_new_session=True, text=True)
        try:
            for _ in self.mesh.gateways:
                line = self.proc.stdout.readline().split()  # type: ignore[union-attr]
                if len(line) < 3 or line[0] != "gateway":
                    raise RuntimeError(f"mesh up printed {line!r}")
                t = threading.Thread(target=self._read, args=(line[2],), daemon=True)
                t.start()
                self._threads.append(t)
        except BaseException:
            self._kill()
            raise
        self.started = time.monotonic()
        return self

    def _read(self, device: str) -> None:
        port = serial.Serial(device, timeout=0.05)
        dec = StreamDecoder()
        host = HostReceiver()
        try:
            while not self._stop.is_set():
                chunk = read_now(port)
                now = time.monotonic()
                if not chunk:
                    continue
                got: list[Arrival] = []
                for frame in dec.feed(chunk):
                    for f in host.receive(frame, now):
                        if isinstance(f.payload, Data):
                            for s in f.payload.samples:
                                got.append(Arrival(f.origin, s.index, s.cycle, s.c1,
                                                   not s.flags & _NO_MESH_TIME,
                                                   self.gate_time(f.origin, s.cycle), now))
                with self._lock:
                    self.arrivals.extend(got)
        finally:
            port.close()

    def press(self, x: float, y: float, duration: float = 0.5, force: float = 3.0,
              diameter: float = 0.02) -> float:
        """Press now; the host monotonic second the press starts (as the world set it)."""
        return world_press(self.base_port, x, y, duration, force, diameter)

    def pids(self, role: bytes = b"bridge") -> list[int]:
        out = []
        for pid in os.listdir("/proc"):
            if pid.isdigit():
                try:
                    cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").split()
                except OSError:
                    continue
                if self.path.encode() in cmd and role in cmd:
                    out.append(int(pid))
        return out

    def _kill(self) -> None:
        self.proc.send_signal(signal.SIGTERM)
        try:
            self.proc.wait(60)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(2)
        self._kill()
        self._err.seek(0)
        for line in self._err:
            if line.startswith("{"):
                try:
                    d = json.loads(line)
                    self.counters[d["bridge"]] = d["counters"]
                    self.gates[d["bridge"]] = {int(k): v for k, v in d.get("gates", {}).items()}
                except (ValueError, KeyError):
                    pass
            else:
                self.stderr_lines.append(line.rstrip())
        self._err.close()
        self._tmp.cleanup()

    def gate_spread_us(self) -> tuple[int, int, float]:
        """(index, bridges reporting it, max - min of their planned gate starts in µs) for
        the index most bridges reported at exit (see ``process_bridge.planned_gates``)."""
        by: dict[int, list[int]] = {}
        for g in self.gates.values():
            for k, t in g.items():
                by.setdefault(k, []).append(t)
        if not by:
            return -1, 0, float("nan")
        k = max(by, key=lambda i: len(by[i]))
        ts = by[k]
        return k, len(ts), (max(ts) - min(ts)) / (CLOCK_HZ / 1e6)

    def snapshot(self) -> list[Arrival]:
        with self._lock:
            return list(self.arrivals)
