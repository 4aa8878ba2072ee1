"""The real-time emulator under a hostile network and a careless operator: real processes,
ptys and sockets on loopback. Every process a test starts is stopped, also when it fails
(its own session, SIGKILL of the group after a timeout, then anything naming its mesh)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import Mesh, mesh_to_toml

from cellbridge.demo import gateway_line
from support.emulator_procs import (
    PY,
    free_base_port,
    posing_bridges,
    processes_mentioning,
    running_medium,
    stop_and_sweep,
    terminate,
)


def _roles(mesh_path: Path) -> dict[str, int]:
    """pid of each process naming ``mesh_path``, by role ('up', 'medium', 'world', 'bridge N')."""
    out: dict[str, int] = {}
    for pid in processes_mentioning(str(mesh_path)):
        try:
            if Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
                continue  # exited, not yet reaped
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode().split()
        except OSError:
            continue
        if "up" in cmd:
            out["up"] = pid
        elif "bridge" in cmd:
            out[f"bridge {cmd[cmd.index('--id') + 1]}"] = pid
        elif "medium" in cmd or "world" in cmd:
            out["medium" if "medium" in cmd else "world"] = pid
    return out


@contextmanager
def mesh_up(tmp_path: Path, mesh: Mesh, *extra: str, stderr: int | None = None) -> Iterator[tuple[Path, subprocess.Popen[bytes]]]:
    """``cellbridge mesh up`` of ``mesh`` in its own session; everything stopped afterwards."""
    mesh_path = tmp_path / "attack.toml"
    mesh_path.write_text(mesh_to_toml(mesh))
    proc = subprocess.Popen([*PY, "mesh", "up", str(mesh_path), "--base-port", str(free_base_port()), *extra],
                            stdout=subprocess.PIPE, stderr=stderr, start_new_session=True)
    try:
        yield mesh_path, proc
    finally:
        stop_and_sweep(proc, mesh_path)


def _wait_roles(mesh_path: Path, want: set[str], seconds: float = 20.0) -> dict[str, int]:
    end = time.monotonic() + seconds
    while True:
        roles = _roles(mesh_path)
        if want <= set(roles) or time.monotonic() > end:
            return roles
        time.sleep(0.1)


# -- a forked bridge and a broken stderr ---------------------------------------------------

_ESCAPE = """
import os, sys
from cellbridge.emulator.realtime import process_up
r, w = os.pipe()
os.close(r)
os.dup2(w, 2)  # whoever read stderr went away: every write to it fails (EPIPE)
me = os.getpid()
try:
    b = process_up.ForkedBridge(["bridge", "--mesh", sys.argv[1], "--id", "1"], None)
except BaseException:
    os._exit(3 if os.getpid() != me else 4)
if os.getpid() != me:
    os._exit(5)
sys.exit(0 if b.wait(20) not in (3, 5) else 6)
"""


def test_a_forked_bridge_never_returns_into_the_supervisor(tmp_path: Path) -> None:
    # A forked bridge whose last words (an error, its counters) cannot be written must
    # still end in os._exit: an exception out of the child unwound into the supervisor's
    # code, which then ran in the child as a second supervisor (its `finally` stopping
    # the processes it knew of).
    r = subprocess.run([sys.executable, "-c", _ESCAPE, str(tmp_path / "no-such-mesh.toml")],
                       capture_output=True, timeout=30)
    assert r.returncode == 0, (r.returncode, r.stderr)


def test_mesh_up_keeps_running_when_its_stderr_reader_is_gone(tmp_path: Path) -> None:
    # `mesh up ... 2>&1 | grep gateway` and the grep ends: a bridge that dies then (its
    # counters go to stderr) took the whole skin down: the child escaped into the
    # supervisor's code, and the supervisor died writing "bridge N exited" to stderr.
    with mesh_up(tmp_path, meshgen.line(3), "--start-interval", "0", stderr=subprocess.PIPE) as (mesh_path, proc):
        assert proc.stdout is not None and proc.stderr is not None
        assert gateway_line(proc)[:2] == ["gateway", "1"]
        roles = _wait_roles(mesh_path, {"medium", "world", "bridge 1", "bridge 2", "bridge 3"})
        proc.stderr.close()
        os.kill(roles["bridge 3"], signal.SIGTERM)
        time.sleep(1.5)
        after = _roles(mesh_path)
        assert proc.poll() is None, "mesh up died"
        assert {k: after.get(k) for k in ("medium", "world", "bridge 1", "bridge 2")} == \
            {k: roles[k] for k in ("medium", "world", "bridge 1", "bridge 2")}
        assert "bridge 3" not in after
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(15) == 0


# -- stopping mesh up while it starts ------------------------------------------------------

@pytest.mark.parametrize("interval", ["1000", "1e300"])
def test_sigterm_during_a_long_start_interval_stops_at_once(tmp_path: Path, interval: str) -> None:
    # time.sleep() resumes after a signal handler (PEP 475): a SIGTERM while mesh up waited
    # between two bridges' starts was seen only when the pause ended (1000 s). A pause
    # beyond time_t (1e300, a finite number --start-interval accepts) was a traceback.
    with mesh_up(tmp_path, meshgen.line(2), "--start-interval", interval,
                 stderr=subprocess.PIPE) as (mesh_path, proc):
        assert proc.stdout is not None and proc.stderr is not None
        assert gateway_line(proc)[:2] == ["gateway", "1"]
        _wait_roles(mesh_path, {"medium", "world", "bridge 1"})
        time.sleep(0.5)
        assert proc.poll() is None, proc.stderr.read().decode()
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(10) == 0
        assert time.monotonic() - t0 < 6.0  # the bridges' grace is 5 s; they stop in far less
        assert b"Traceback" not in proc.stderr.read()
        time.sleep(0.3)
        assert processes_mentioning(str(mesh_path)) == []


# -- what mesh up prints ---------------------------------------------------------------------

def _lines(proc: subprocess.Popen[bytes], seconds: float) -> list[str]:
    """What ``proc`` printed on stdout within ``seconds``."""
    import select

    assert proc.stdout is not None
    fd, buf, end = proc.stdout.fileno(), b"", time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        if select.select([fd], [], [], left)[0]:
            chunk = os.read(fd, 4096)
            if not chunk:
                break
            buf += chunk
    return buf.decode().splitlines()


def test_mesh_up_prints_one_line_per_gateway_device_first(tmp_path: Path) -> None:
    # Documented: one 'gateway <id> <device> [socket://...]' per gateway. A forked gateway
    # bridge also printed its own 'gateway <id> socket://...' within milliseconds, before
    # the supervisor's lines (it waits --start-interval for the next gateway): a script
    # taking the first line's third word as the device got a socket URL.
    with mesh_up(tmp_path, meshgen.line(3, gateways=(1, 3)), "--tcp") as (mesh_path, proc):
        # every bridge started (a loaded machine takes seconds), then what was printed by then
        _wait_roles(mesh_path, {"bridge 1", "bridge 2", "bridge 3"})
        lines = _lines(proc, 1.0)
        while len(lines) < 2 and (more := _lines(proc, 5.0)):
            lines += more
    words = [line.split() for line in lines]
    assert [w[:2] for w in words] == [["gateway", "1"], ["gateway", "3"]], lines
    assert all(w[2].startswith("/dev/pts/") and w[3].startswith("socket://127.0.0.1:") for w in words), lines


# -- hostile datagrams at the medium ---------------------------------------------------------

def test_medium_refuses_transmissions_a_bridge_cannot_make(tmp_path: Path) -> None:
    # The medium took any TX naming a bridge of the mesh: on cells that bridge is not on
    # (each remembered in its carrier table for ever: 4 000 datagrams of 255 random cells
    # grew it by 140 MB), a frame longer than a frame can be (256 bytes), and a datagram
    # beyond its receive size, silently cut to 2 048 bytes. All counted as transmissions;
    # now refused and counted as bad_messages, and the real transmission still goes through.
    import random

    from cellbridge.emulator.medium.medium_wire import decode_rx, encode_tx
    from cellbridge.protocol import ADDR_BROADCAST, Beacon, Frame, encode

    beacon = encode(Frame(1, ADDR_BROADCAST, 1, 0, Beacon(0, 0, 0)))
    rnd = random.Random(7)
    with running_medium(tmp_path) as (base, counters):
        with posing_bridges(base) as (b1, b2):
            b1.send(encode_tx(1, (2,), beacon, False))  # line of 2: bridge 1 is on cell 1 only
            b1.send(encode_tx(1, (1, 77), beacon, False))  # one of them not its own
            b1.send(encode_tx(1, tuple(rnd.randrange(2**32) for _ in range(255)), beacon, False))
            b1.send(encode_tx(1, (1,), beacon + bytes(256 - len(beacon)), False))  # 256-byte frame
            b1.send(encode_tx(1, (1,), bytes(5000), False))  # cut to 2 048 bytes on receipt
            time.sleep(0.2)
            b1.send(encode_tx(1, (1,), beacon, False, 4242))
            got = decode_rx(b2.recv(4096))
            b2.settimeout(0.3)
            with pytest.raises(socket.timeout):
                b2.recv(4096)  # nothing else reached bridge 2
    assert got == (1, beacon, 4242)
    assert counters["bad_messages"] == 5, counters
    assert counters["transmissions"] == 1 and counters["delivered"] == 1, counters


# -- stimuli the world cannot have sent ------------------------------------------------------

def test_a_bridge_survives_stimuli_no_world_would_publish(tmp_path: Path) -> None:
    # Whatever publishes on the world's port (another mesh's world on the same base port, a
    # stale or foreign process that took the port while the world restarted) reaches every
    # bridge at once. A contact with a NaN position, an infinite force or a negative
    # diameter decoded as valid and the next sample raised ValueError ('contacts must be
    # finite'): every bridge of the skin died of one message. Such a message is malformed
    # (stimuli_malformed), as decode_contacts promises.
    import json

    import msgpack
    import zmq

    mesh_path = tmp_path / "line-2.toml"
    mesh_path.write_text(mesh_to_toml(meshgen.line(2)))
    base = free_base_port()
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    pub.bind(f"tcp://127.0.0.1:{base + 1}")
    bridge = subprocess.Popen([*PY, "bridge", "--mesh", str(mesh_path), "--id", "2", "--base-port", str(base)],
                              stderr=subprocess.PIPE, start_new_session=True)
    try:
        nan = float("nan")
        bad = [[0.0, 1e9, nan, 0.0, 3.0, 0.02, 0.0, 0.0], [0.0, 1e9, 0.04, 0.0, float("inf"), 0.02, 0.0, 0.0],
               [0.0, 1e9, 0.04, 0.0, 3.0, -0.02, 0.0, 0.0], [0.0, 1e9, 0.04, 0.0, -3.0, 0.02, 0.0, 0.0],
               [0.0, nan, 0.04, 0.0, 3.0, 0.02, 0.0, 0.0], [0.0, 1e9, 0.04, 0.0, 3.0, 0.02, float("inf"), 0.0]]
        end = time.monotonic() + 4.0  # the subscription takes a while: publish until it must have been heard
        while time.monotonic() < end and bridge.poll() is None:
            for row in bad:
                pub.send(msgpack.packb([row]))
            time.sleep(0.1)
        assert bridge.poll() is None, bridge.communicate(timeout=10)[1].decode()[-2000:]
        bridge.send_signal(signal.SIGTERM)
        _, err = bridge.communicate(timeout=15)
    finally:
        if bridge.poll() is None:
            os.killpg(bridge.pid, signal.SIGKILL)
            bridge.wait()
        pub.close()
        ctx.term()
    counters = json.loads(err.decode().strip().splitlines()[-1])["counters"]
    assert counters["stimuli_malformed"] >= len(bad), counters


def test_world_refuses_a_press_whose_track_leaves_the_numbers(tmp_path: Path) -> None:
    # `cellbridge press 0.04 0.04 --velocity 1e308 0 --duration 2` was accepted ("pressed"):
    # 1.8 s in, the contact's position overflowed to inf, and every bridge of a running
    # 2x2 skin died at its next sample ('contacts must be finite'). A start the world
    # cannot place in time (a raw request: "inf", NaN) was taken as well.
    import msgpack
    import zmq
    from cellbridge.emulator.world.world import ScenarioError, parse_scenario

    with pytest.raises(ScenarioError, match="velocity"):
        parse_scenario("[[contact]]\nstart = 0\nduration = 2\nposition = [0.04, 0.04]\nforce = 1\n"
                       "diameter = 0.02\nvelocity = [1e308, 0]\n")
    mesh_path = tmp_path / "grid-2x2.toml"
    mesh_path.write_text(mesh_to_toml(meshgen.grid(2, 2)))
    base = free_base_port()
    world = subprocess.Popen([*PY, "world", "--mesh", str(mesh_path), "--base-port", str(base)],
                             stderr=subprocess.PIPE, start_new_session=True)
    ctx = zmq.Context()
    try:
        r = subprocess.run([*PY, "press", "0.04", "0.04", "--velocity", "1e308", "0", "--duration", "2",
                            "--timeout", "10", "--base-port", str(base)], capture_output=True, timeout=30)
        assert r.returncode == 2 and b"velocity" in r.stderr, (r.returncode, r.stdout, r.stderr)
        req = ctx.socket(zmq.REQ)
        req.setsockopt(zmq.LINGER, 0)
        req.connect(f"tcp://127.0.0.1:{base + 2}")
        for start in ("inf", float("nan"), float("inf"), -1.0, [1]):
            req.send(msgpack.packb({"duration": 1.0, "position": [0.04, 0.04], "force": 1.0,
                                    "diameter": 0.02, "start": start}))
            assert req.poll(10_000), "the world did not answer"
            answer = msgpack.unpackb(req.recv())
            assert answer["ok"] is False and "start" in answer["error"], (start, answer)
        req.send(msgpack.packb({"duration": 1.0, "position": [0.04, 0.04], "force": 1.0,
                                "diameter": 0.02, "start": 0.5}))
        assert req.poll(10_000) and msgpack.unpackb(req.recv())["ok"] is True
    finally:
        ctx.destroy(linger=0)  # (term() waited for ever on the REQ socket a failed assertion left open)
        terminate(world)


# -- what a forked bridge holds ----------------------------------------------------------

def test_forked_bridges_hold_no_descriptor_they_were_not_given(tmp_path: Path) -> None:
    # A forked bridge inherits every descriptor of the supervisor; the medium and the world
    # (subprocess, close_fds) do not. Whatever the launcher of mesh up left open (a pipe
    # it waits on for EOF, a log file) stayed open in every bridge, and each bridge kept
    # an extra /dev/null. A bridge holds its stdio, its own pty (a gateway) and what it opens.
    r, w = os.pipe()
    try:
        mesh_path = tmp_path / "attack.toml"
        mesh_path.write_text(mesh_to_toml(meshgen.line(3, gateways=(1, 3))))
        proc = subprocess.Popen([*PY, "mesh", "up", str(mesh_path), "--base-port", str(free_base_port()),
                                 "--start-interval", "0"], stdout=subprocess.PIPE, pass_fds=(w,),
                                start_new_session=True)
        try:
            roles = _wait_roles(mesh_path, {"bridge 1", "bridge 2", "bridge 3"})
            time.sleep(0.5)
            pipe = f"pipe:[{os.fstat(w).st_ino}]"
            held = {}
            for role in ("bridge 1", "bridge 2", "bridge 3"):
                fd_dir = Path(f"/proc/{roles[role]}/fd")
                held[role] = sorted(os.readlink(fd_dir / fd) for fd in os.listdir(fd_dir))
            assert all(pipe not in links for links in held.values()), held
            assert all(links.count("/dev/null") == 1 for links in held.values()), held  # stdin only
            assert [links.count("/dev/ptmx") for links in held.values()] == [1, 0, 1], held
        finally:
            stop_and_sweep(proc, mesh_path)
    finally:
        os.close(r)
        os.close(w)
