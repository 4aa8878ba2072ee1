"""What a hostile review of the emulator's process shells found (issue 17, points
15, 17-19): real processes, real ptys and sockets on loopback."""

from __future__ import annotations

import os
import socket
import subprocess
import time
from pathlib import Path

import pytest
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import mesh_to_toml

from cellbridge.demo import gateway_line
from daemon_harness import free_port
from support.emulator_procs import PY, free_base_port, running_skin, stop_and_sweep, terminate


def _grid(tmp_path: Path, name: str = "skin.toml") -> Path:
    path = tmp_path / name
    path.write_text(mesh_to_toml(meshgen.grid(2, 2)))
    return path


def test_a_second_mesh_up_on_a_base_port_in_use_exits_naming_the_port_and_starts_no_bridge(tmp_path):
    """The second mesh's medium and world failed to bind, it took 'address in use' for
    'my medium is up' and forked its bridges onto the first mesh's medium: one origin
    then carried two bridges' samples."""
    with running_skin(tmp_path) as skin:
        second = _grid(tmp_path, "second.toml")
        proc = subprocess.Popen([*PY, "mesh", "up", str(second), "--base-port", str(skin.base)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
        try:
            out, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            stop_and_sweep(proc, second)
            pytest.fail("the second mesh up kept running on a base port in use")
        finally:
            stop_and_sweep(proc, second)
        assert proc.returncode != 0
        assert str(skin.base) in err.decode(), err
        assert b"gateway" not in out  # no line of a skin that does not run
        assert not [p for p in _processes(str(second)) if b"bridge" in _cmdline(p)]


def test_two_mesh_ups_started_at_once_on_one_base_port_one_runs_and_the_other_starts_nothing(tmp_path):
    """Both found the base port free, both started a medium and a world, and each took the
    other's bound port for its own failure: the loser's medium or world failed only after
    it had been started, and as often as not (2 runs in 5) both exited, the first skin
    taken down by the second start. The base port is claimed before anything starts: one
    runs, the other refuses naming the port and starts no process."""
    base = free_base_port()
    paths = [_grid(tmp_path, f"skin-{i}.toml") for i in range(2)]
    procs = [subprocess.Popen([*PY, "mesh", "up", str(path), "--base-port", str(base)], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, start_new_session=True) for path in paths]
    try:
        deadline = time.monotonic() + 60
        while all(p.poll() is None for p in procs):
            assert time.monotonic() < deadline, "neither mesh up refused the shared base port"
            time.sleep(0.05)
        loser = next(i for i, p in enumerate(procs) if p.poll() is not None)
        winner = procs[1 - loser]
        _, err = procs[loser].communicate(timeout=30)
        assert procs[loser].returncode == 1
        assert f"base port {base}" in err.decode(), err
        # it started neither a medium nor a world (each says why it could not bind)
        assert b"cellbridge medium" not in err and b"cellbridge world" not in err, err
        assert gateway_line(winner)[:2] == ["gateway", "1"]  # the other skin runs, undisturbed
        time.sleep(1.0)
        assert winner.poll() is None, winner.stderr.read() if winner.stderr else b""
    finally:
        for p, path in zip(procs, paths):
            stop_and_sweep(p, path)


def test_mesh_up_on_a_base_port_another_program_holds_names_the_port_and_starts_nothing(tmp_path):
    base = free_base_port()
    path = _grid(tmp_path)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as other:
        other.bind(("127.0.0.1", base))
        proc = subprocess.Popen([*PY, "mesh", "up", str(path), "--base-port", str(base)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, start_new_session=True)
        try:
            out, err = proc.communicate(timeout=60)
        finally:
            stop_and_sweep(proc, path)
    assert proc.returncode == 1 and f"UDP 127.0.0.1:{base}" in err.decode() and b"Nothing started" in err, err
    assert b"gateway" not in out


def test_a_second_process_for_a_running_bridge_id_is_refused(tmp_path):
    with running_skin(tmp_path) as skin:
        # Bridge 4 runs under mesh up; a second one with the same id and ports must not.
        deadline = time.monotonic() + 30
        while not [p for p in _processes(str(skin.mesh_path)) if b"--id 4" in _cmdline(p)]:
            assert time.monotonic() < deadline, "bridge 4 never started"
            time.sleep(0.1)
        proc = subprocess.Popen([*PY, "bridge", "--mesh", str(skin.mesh_path), "--id", "4",
                                 "--base-port", str(skin.base)],
                                stderr=subprocess.PIPE, start_new_session=True)
        try:
            _, err = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            terminate(proc)
            pytest.fail("a second bridge 4 ran beside the first")
        assert proc.returncode != 0
        assert b"bridge 4" in err and b"already" in err, err


def _processes(text: str) -> list[int]:
    from support.emulator_procs import processes_mentioning

    return processes_mentioning(text)


def _cmdline(pid: int) -> bytes:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
    except OSError:
        return b""


def test_a_host_opening_the_gateway_pty_late_reads_no_seconds_old_frames(tmp_path):
    """The pty is held open while no host has it, so frames queued there: a host opening
    it 15 s late read 14 s old frames first. What no host took for STALE_S (1 s) is
    flushed: the oldest sample waiting at the open is about that old, not 6 s."""
    import serial
    from cellbridge.protocol import StreamDecoder

    from support.emulator_procs import data_by_origin

    with running_skin(tmp_path, "--readout", "off") as skin:  # (each sample's own cycle: DATA frames)
        device = skin.gateways[1][0]
        with serial.serial_for_url(device, timeout=0) as port:
            skin.wait_for(port, {1, 2, 3, 4})
        time.sleep(6.0)  # nobody reads the line
        fd = os.open(device, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            waiting = b""
            while True:
                try:
                    chunk = os.read(fd, 65536)
                except BlockingIOError:
                    break
                if not chunk:
                    break
                waiting += chunk
            dec = StreamDecoder()
            old = data_by_origin(dec.feed(waiting)).get(1, [])
            live: list = []
            end = time.monotonic() + 5.0
            while not live and time.monotonic() < end:
                time.sleep(0.05)
                try:
                    live = data_by_origin(dec.feed(os.read(fd, 65536))).get(1, [])
                except BlockingIOError:
                    pass
        finally:
            os.close(fd)
        assert live, "the gateway sent nothing after the open"
        if old:  # nothing waiting at all is fine too
            age = (max(s.cycle for s in live) - min(s.cycle for s in old)) / 50e6
            assert age < 3.0, age  # STALE_S, a check period, the reads above: not the 6 s unread


def test_the_daemon_flushes_what_a_line_held_before_it_opened_it():
    """Point 17, the host's side: frames queued on a pty before the daemon opens it would
    be read as new (stamped with the arrival time of now). pyserial's open() flushes the
    input (tcflush TCIFLUSH; a socket:// line is drained), and the daemon opens every line
    through it: this pins that down."""
    import tty

    from cellbridge.daemon.core.config import LinkConfig
    from cellbridge.daemon.shell.links import SerialLink

    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        os.write(master, b"\x00stale frame bytes\x00" * 10)
        link = SerialLink(LinkConfig("gw", os.ttyname(slave)), lambda *a: None, lambda *a: None)
        ser = link._open()
        try:
            time.sleep(0.2)
            assert ser.read(4096) == b""
            os.write(master, b"\x00new\x00")
            deadline = time.monotonic() + 5
            got = b""
            while got != b"\x00new\x00" and time.monotonic() < deadline:
                got += ser.read(4096)
            assert got == b"\x00new\x00"
        finally:
            ser.close()
    finally:
        os.close(master)
        os.close(slave)


def _port_free() -> int:
    return free_port()


def _serves(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=2):
            return True
    except OSError:
        return False


def test_the_mesh_files_tcp_port_is_served_only_with_tcp(tmp_path):
    """Point 18: the docs say --tcp serves a TCP port; gateways served the file's 'tcp'
    without it too (a port nobody asked to open)."""
    from cellbridge.emulator.mesh.mesh import parse_mesh

    tcp = _port_free()
    mesh_path = tmp_path / "tcp.toml"
    mesh_path.write_text(mesh_to_toml(meshgen.grid(2, 2)).replace("gateway = true", f"gateway = true\ntcp = {tcp}"))
    assert parse_mesh(mesh_path.read_text()).bridge(1).tcp == tcp
    for extra, served in (([], False), (["--tcp"], True)):
        proc = subprocess.Popen([*PY, "mesh", "up", str(mesh_path), "--base-port", str(free_base_port()), *extra],
                                stdout=subprocess.PIPE, start_new_session=True)
        try:
            line = gateway_line(proc)
            assert line[:2] == ["gateway", "1"], line
            assert (f"socket://127.0.0.1:{tcp}" in line) == served, line
            time.sleep(1.0)  # the gateway bridge has started (its line is printed once it runs)
            assert _serves(tcp) == served
        finally:
            stop_and_sweep(proc, mesh_path)


def test_idle_tcp_clients_are_bounded_and_the_gateway_keeps_serving(tmp_path):
    """~1 010 idle clients exhausted the gateway's descriptors (and cost it a third of a
    core); beyond MAX_CLIENTS a client is closed at once, the first ones keep the stream."""
    from cellbridge.emulator.realtime import gateway_port

    MAX_CLIENTS = getattr(gateway_port, "MAX_CLIENTS", 8)
    with running_skin(tmp_path) as skin:
        url = skin.gateways[1][1]
        port = int(url.rsplit(":", 1)[1])
        deadline = time.monotonic() + 30  # the gateway's process binds its port once it runs
        while not _serves(port):
            assert time.monotonic() < deadline, "the gateway never served its TCP port"
            time.sleep(0.1)
        first = socket.create_connection(("127.0.0.1", port), timeout=10)
        idle = [socket.create_connection(("127.0.0.1", port), timeout=10) for _ in range(MAX_CLIENTS - 1 + 50)]
        try:
            refused = 0
            for s in idle[MAX_CLIENTS - 1:]:
                s.settimeout(10)
                try:
                    refused += s.recv(1) == b""  # closed by the gateway, not fed
                except ConnectionResetError:
                    refused += 1
            assert refused == 50
            got = b""
            first.settimeout(10)
            while len(got) < 1000:
                got += first.recv(4096)
            assert skin.proc.poll() is None
        finally:
            first.close()
            for s in idle:
                s.close()


EMFILE_SCRIPT = """
import os, resource, select, socket
resource.setrlimit(resource.RLIMIT_NOFILE, (64, 64))
from cellbridge.emulator.realtime.gateway_port import GatewayPort
p = GatewayPort(None, 0)
client = socket.create_connection(("127.0.0.1", p.tcp_port))
fill = []
try:
    while True:
        fill.append(os.open(os.devnull, os.O_RDONLY))
except OSError:
    pass
for _ in range(3):
    ready = select.select(p.fds(), [], [], 0.2)[0]
    p.read(set(ready))
    p.write(b"x")
print(dict(p.counters), p.listener.fileno() in p.fds())
"""


def test_no_descriptor_left_to_accept_a_tcp_client_does_not_end_the_gateway():
    """Point 18: an uncaught EMFILE from accept() ended the gateway process."""
    import sys

    out = subprocess.run([sys.executable, "-c", EMFILE_SCRIPT], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "'tcp_accept_failed': 1" in out.stdout and out.stdout.strip().endswith("False"), out.stdout


@pytest.mark.parametrize("value", ["nan", "inf", "1e20", "-1", "0"])
def test_press_timeout_must_be_a_finite_positive_number_of_seconds(value):
    """nan, inf and 1e20 raised a traceback; -1 waited for ever (zmq's 'no timeout')."""
    out = subprocess.run([*PY, "press", "0", "0", "--timeout", value, "--base-port", str(free_base_port())],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out
    assert "--timeout" in out.stderr and "Traceback" not in out.stderr


@pytest.mark.parametrize("value", ["70000", "65535", "65534", "0", "-5", "x"])
def test_base_port_leaves_room_for_the_worlds_two_ports(tmp_path, value):
    """70000 raised a traceback; 65535 ran without a world (base+1 and base+2 do not exist)."""
    mesh_path = _grid(tmp_path)
    proc = subprocess.Popen([*PY, "mesh", "up", str(mesh_path), "--base-port", value],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    try:
        _, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail(f"mesh up ran with --base-port {value}")
    finally:
        stop_and_sweep(proc, mesh_path)
    assert proc.returncode == 2, err
    assert b"--base-port" in err and b"Traceback" not in err


def test_the_medium_is_described_as_udp_not_zeromq():
    # (the top-level --help no longer lists the internal entry points: medium's own help says it)
    for args in (["medium", "--help"],):
        out = subprocess.run([*PY, *args], capture_output=True, text=True, timeout=60).stdout
        line = [ln for ln in out.splitlines() if "relay cell transmissions" in ln.lower()] or [out]
        assert "ZeroMQ" not in " ".join(line) and "UDP" in out, out
