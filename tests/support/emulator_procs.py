"""The emulator's real processes for the tests: ``cellbridge mesh up`` and its medium, started,
watched and stopped (every process a test starts is stopped, also on failure)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import termios
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import serial
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import mesh_to_toml
from cellbridge.protocol import Frame, FrameType, StreamDecoder

from cellbridge.demo import gateway_line
from daemon_harness import free_port

PY = [sys.executable, "-m", "cellbridge"]


def free_base_port() -> int:
    """A base port whose three ZeroMQ ports (base..base+2) are free right now
    (:func:`daemon_harness.free_port`: outside the ephemeral range, a band per worker)."""
    return free_port(3)


def processes_mentioning(text: str) -> list[int]:
    pids = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if text in cmd and int(pid) != os.getpid():
            pids.append(int(pid))
    return pids


class Skin:
    def __init__(self, mesh_path: Path, base: int, proc: subprocess.Popen[bytes], gateways: dict[int, list[str]]):
        self.mesh_path, self.base, self.proc, self.gateways = mesh_path, base, proc, gateways
        self.decoder = StreamDecoder()

    def wait_for(self, port: serial.SerialBase, origins: set[int], seconds: float = 15.0) -> set[int]:
        """Origins of DATA seen until all of ``origins`` were (or ``seconds`` passed): a
        loaded machine may take seconds to start the processes."""
        seen: set[int] = set()
        end = time.monotonic() + seconds
        while not origins <= seen and time.monotonic() < end:
            seen |= set(data_by_origin(self.read(port, 0.5)))
        return seen

    def read(self, port: serial.SerialBase, seconds: float) -> list[Frame]:
        """The frames read off ``port`` for ``seconds``. The gateway flushes what no host
        read for a second (a test that ran ``press`` meanwhile): pyserial then finds the
        line readable and empty, and raises, which is not the line going away."""
        frames: list[Frame] = []
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                data = port.read(4096)
            except serial.SerialException:
                termios.tcgetattr(port.fileno())  # raises if the line is really gone
                continue
            frames += self.decoder.feed(data)
        return frames


@contextmanager
def running_skin(tmp_path: Path, *extra: str) -> Iterator[Skin]:
    """``mesh up`` of a 2x2 grid (gateway 1) with ``extra`` options; every process is
    stopped afterwards, also when the test fails."""
    mesh_path = tmp_path / "skin-2x2.toml"
    mesh_path.write_text(mesh_to_toml(meshgen.grid(2, 2)))
    base = free_base_port()
    proc = subprocess.Popen([*PY, "mesh", "up", str(mesh_path), "--base-port", str(base), "--tcp", *extra],
                            stdout=subprocess.PIPE, start_new_session=True)
    try:
        line = gateway_line(proc)
        assert line[:2] == ["gateway", "1"] and line[2].startswith("/dev/pts/"), line
        yield Skin(mesh_path, base, proc, {1: line[2:]})
    finally:
        stop_and_sweep(proc, mesh_path)


def terminate(proc: subprocess.Popen[bytes], seconds: float = 15.0) -> None:
    """SIGTERM, and SIGKILL to its whole session when it has not stopped after ``seconds``."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(seconds)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


def stop_and_sweep(proc: subprocess.Popen[bytes], mesh_path: Path) -> None:
    """``terminate`` ``mesh up``, then SIGKILL to anything still naming the mesh file:
    a failed test still leaves nothing running."""
    terminate(proc)
    for pid in processes_mentioning(str(mesh_path)):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def data_by_origin(frames: list[Frame]) -> dict[int, list]:
    out: dict[int, list] = {}
    for f in frames:
        if f.type is FrameType.DATA:
            out.setdefault(f.origin, []).extend(f.payload.samples)  # type: ignore[union-attr]  # a DATA frame's payload is a Data
    return out


def udp_port_taken(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return True
    return False


def medium_counters(err: bytes) -> dict[str, int]:
    import json

    line = [x for x in err.decode().splitlines() if x.startswith("medium: ")][-1]
    return json.loads(line.removeprefix("medium: ").replace("'", '"'))


@contextmanager
def running_medium(tmp_path: Path, mesh_name: str = "line-2") -> Iterator[tuple[int, dict[str, int]]]:
    """A ``cellbridge medium`` on a line of 2; yields (base port, its counters after stop)."""
    mesh_path = tmp_path / f"{mesh_name}.toml"
    mesh_path.write_text(mesh_to_toml(meshgen.line(2)))
    base = free_base_port()
    proc = subprocess.Popen([*PY, "medium", "--mesh", str(mesh_path), "--base-port", str(base)],
                            stderr=subprocess.PIPE, start_new_session=True)
    counters: dict[str, int] = {}
    try:
        end = time.monotonic() + 30  # a loaded machine takes a while to start a process
        while not udp_port_taken(base):  # bound: the medium is serving
            assert time.monotonic() < end and proc.poll() is None, "medium did not start"
            time.sleep(0.1)
        yield base, counters
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            _, err = proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            _, err = proc.communicate()
        counters.update(medium_counters(err))


@contextmanager
def posing_bridges(base: int) -> Iterator[tuple[socket.socket, socket.socket]]:
    """Two sockets talking to the medium at ``base`` as bridges 1 and 2 of a line of 2;
    bridge 2 has said it is there (WANT), so deliveries for it are sent."""
    from cellbridge.emulator.medium.medium_wire import encode_want

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as b1, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as b2:
        for s in (b1, b2):
            s.connect(("127.0.0.1", base))
            s.settimeout(5)
        b2.send(encode_want(2, False))
        yield b1, b2
