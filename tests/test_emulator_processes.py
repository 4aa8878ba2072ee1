"""Real processes, real ptys, real ZeroMQ on loopback: ``cellbridge mesh up`` and friends."""

from __future__ import annotations

import argparse
import os
import signal
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import serial
from cellbridge.emulator.firmware.reporting import ReportingMode
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.mesh import mesh_to_toml
from cellbridge.emulator.realtime.realtime import reporting_arg, reporting_text
from cellbridge.protocol import Command, CommandReply, Flags, Frame, FrameType, Op, StreamDecoder, encode_stream

from support.emulator_procs import (
    PY,
    Skin,
    data_by_origin,
    free_base_port,
    posing_bridges,
    processes_mentioning,
    running_medium,
    running_skin,
    stop_and_sweep,
    terminate,
)
from support.payloads import payload_as


@pytest.fixture
def skin(tmp_path: Path) -> Iterator[Skin]:
    # (these tests read each bridge's own frames on the gateway's line: DATA, not readout records)
    with running_skin(tmp_path, "--readout", "off") as s:
        yield s


def test_mesh_up_pty_press_kill_and_clean_stop(skin: Skin) -> None:
    device, url = skin.gateways[1]
    with serial.Serial(device, 115200, timeout=0.1) as pty:
        skin.wait_for(pty, {1, 2, 3, 4})
        frames = skin.read(pty, 3.0)
        data = data_by_origin(frames)
        assert set(data) == {1, 2, 3, 4}, {f.origin for f in frames}
        assert {f.origin for f in frames if f.type is FrameType.HELLO} <= {1, 2, 3, 4}
        rest = {b: sum(s.c1 for s in v[-20:]) / len(v[-20:]) for b, v in data.items()}

        # press on bridge 4's element (0.04, 0.04): its C1 rises, so its counts fall
        r = subprocess.run([*PY, "press", "0.04", "0.04", "--force", "3", "--diameter", "0.02",
                            "--duration", "3", "--base-port", str(skin.base)], capture_output=True, timeout=20)
        assert r.returncode == 0, r.stderr
        skin.read(pty, 0.8)  # the world republishes; frames in flight drain
        pressed = data_by_origin(skin.read(pty, 1.5))
        assert set(pressed) == {1, 2, 3, 4}
        mean = {b: sum(s.c1 for s in v) / len(v) for b, v in pressed.items()}
        assert mean[4] < rest[4] - 200
        assert all(abs(mean[b] - rest[b]) < 20 for b in (1, 2, 3))

        # a command written to the pty reaches bridge 4 and its reply comes back
        pty.write(encode_stream(Frame(0, 4, 0, 500, Command(77, Op.PING), flags=int(Flags.ACK_REQUEST))))
        answers = [f for f in skin.read(pty, 2.0) if f.type is FrameType.CMD_REPLY]
        assert [(f.origin, payload_as(f, CommandReply).token) for f in answers] == [(4, 77)]

        # the same stream on the TCP port, as pyserial's socket:// URL
        with serial.serial_for_url(url, timeout=0.1) as tcp:
            dec = StreamDecoder()
            got: list[Frame] = []
            end = time.monotonic() + 2.0
            while time.monotonic() < end and not got:
                got += [f for f in dec.feed(tcp.read(4096)) if f.type is FrameType.DATA]
            assert got

        # kill one bridge process: the others keep delivering
        os.kill(_bridge_pid(skin, 2), signal.SIGKILL)
        skin.read(pty, 1.5)
        assert {1, 3, 4} <= skin.wait_for(pty, {1, 3, 4})
        assert {1, 3, 4} <= set(data_by_origin(skin.read(pty, 2.0))) <= {1, 3, 4}  # and 2 is gone

    skin.proc.send_signal(signal.SIGTERM)
    assert skin.proc.wait(15) == 0
    time.sleep(0.2)
    assert processes_mentioning(str(skin.mesh_path)) == []


def _bridge_pid(skin: Skin, bridge: int) -> int:
    for pid in processes_mentioning(str(skin.mesh_path)):
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").split()  # a forked bridge: its title
        if b"bridge" in cmd and b"--id" in cmd and cmd[cmd.index(b"--id") + 1] == str(bridge).encode():
            return pid
    raise AssertionError(f"no process for bridge {bridge}")


def test_bridges_survive_the_medium_dying_and_reconnect(skin: Skin) -> None:
    device, _ = skin.gateways[1]
    with serial.Serial(device, timeout=0.1) as pty:
        assert {2, 3, 4} <= skin.wait_for(pty, {2, 3, 4})
        medium = [p for p in processes_mentioning(str(skin.mesh_path))
                  if b"medium" in Path(f"/proc/{p}/cmdline").read_bytes().replace(b"\0", b" ").split()]
        assert len(medium) == 1
        os.kill(medium[0], signal.SIGKILL)
        # what was on its way when the medium died; read on meanwhile: a pty queue nobody
        # reads for a second is flushed by the gateway (stale), and a read racing that
        # flush finds the device readable but empty (pyserial raises)
        skin.read(pty, 1.0)
        quiet = data_by_origin(skin.read(pty, 1.0))
        assert set(quiet) <= {1}  # only the gateway's own element, no cell traffic
        again = subprocess.Popen([*PY, "medium", "--mesh", str(skin.mesh_path), "--base-port", str(skin.base)],
                                 start_new_session=True)
        try:
            assert {2, 3, 4} <= skin.wait_for(pty, {2, 3, 4})
        finally:
            again.send_signal(signal.SIGTERM)
            again.wait(10)


def test_bad_mesh_file_is_refused_by_every_process(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[[cell]]\nid = 1\n[[bridge]]\nid = 1\ncells = [1]\nposition = [0, 0]\n")
    for cmd in (["mesh", "up", str(bad)], ["bridge", "--mesh", str(bad), "--id", "1"],
                ["medium", "--mesh", str(bad)]):
        r = subprocess.run([*PY, *cmd], capture_output=True, timeout=30)
        assert r.returncode == 2 and b"gateway" in r.stderr and b"Traceback" not in r.stderr, (cmd, r.stderr)


def test_press_without_a_world_says_so() -> None:
    r = subprocess.run([*PY, "press", "0", "0", "--timeout", "0.5", "--base-port", str(free_base_port())],
                       capture_output=True, timeout=30)
    assert r.returncode == 1 and b"no world process answered" in r.stderr


def test_medium_counts_deliveries_to_bridges_it_cannot_reach(tmp_path: Path) -> None:
    # A delivery for a bridge process that is not there (dead, not yet started, or not
    # yet heard by a medium that restarted) is lost: the medium must count it, not drop
    # it silently.
    from cellbridge.emulator.medium.medium_wire import encode_tx
    from cellbridge.protocol import ADDR_BROADCAST, Beacon, encode

    beacon = encode(Frame(1, ADDR_BROADCAST, 1, 0, Beacon(0, 0, 0)))
    with running_medium(tmp_path) as (base, counters):
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as bridge1:
            bridge1.connect(("127.0.0.1", base))
            for _ in range(20):  # bridge 2 shares cell 1 and never says it is there
                bridge1.send(encode_tx(1, (1,), beacon, False))
                time.sleep(0.05)
            time.sleep(0.3)
    assert counters["delivered"] >= 1
    assert counters["rx_unreachable"] == counters["delivered"]


def test_medium_relays_between_two_bridge_sockets_and_refuses_strangers(tmp_path: Path) -> None:
    # The medium learns where each bridge is from its own messages: bridge 2 says it is
    # there (WANT), bridge 1 transmits on their cell, bridge 2 receives the frame. A
    # datagram naming a bridge the mesh does not have, or garbage, is counted, never relayed.
    from cellbridge.emulator.medium.medium_wire import decode_rx, encode_tx
    from cellbridge.protocol import ADDR_BROADCAST, Beacon, encode

    beacon = encode(Frame(1, ADDR_BROADCAST, 1, 0, Beacon(0, 0, 0)))
    with running_medium(tmp_path) as (base, counters):
        with posing_bridges(base) as (b1, b2):
            b1.send(encode_tx(99, (1,), beacon, False))  # no bridge 99 in the mesh
            b1.send(b"\xff" * 9)
            time.sleep(0.2)
            b1.send(encode_tx(1, (1,), beacon, False, 1234567))
            got = decode_rx(b2.recv(4096))
    assert got == (1, beacon, 1234567)  # the sender's start tick passed on (mesh time's stamp)
    assert counters["bad_messages"] == 2 and counters["delivered"] == 1
    assert counters.get("rx_unreachable", 0) == 0 and counters["udp_drops"] == 0


def test_press_beside_the_skin_is_refused(tmp_path: Path) -> None:
    # A press that touches no element (a typo, metres for millimetres) did nothing and
    # said "pressed"; the world knows the mesh and says where the skin is.
    mesh_path = tmp_path / "grid-2x2.toml"
    mesh_path.write_text(mesh_to_toml(meshgen.grid(2, 2)))
    base = free_base_port()
    world = subprocess.Popen([*PY, "world", "--mesh", str(mesh_path), "--base-port", str(base)],
                             stderr=subprocess.PIPE, start_new_session=True)
    try:
        def press(*args: str) -> subprocess.CompletedProcess[bytes]:
            return subprocess.run([*PY, "press", *args, "--timeout", "10", "--base-port", str(base)],
                                  capture_output=True, timeout=30)

        r = press("1e308", "1e308")
        assert r.returncode == 2 and b"touches no element" in r.stderr and b"skin spans" in r.stderr, r.stderr
        r = press("40", "40")  # millimetres for metres
        assert r.returncode == 2 and b"touches no element" in r.stderr, r.stderr
        r = press("0.5", "0.0", "--velocity", "-0.5", "0", "--duration", "2")  # slides onto the skin
        assert r.returncode == 0, r.stderr
        r = press("0.04", "0.04")
        assert r.returncode == 0 and b"pressed" in r.stdout, r.stderr
    finally:
        terminate(world)
    assert processes_mentioning(str(mesh_path)) == []


def test_mesh_up_event_reporting_sends_heartbeats_when_idle_and_reports_a_press(tmp_path: Path) -> None:
    # Booted event-based (threshold 40 counts, heartbeat 500 ms): an untouched skin sends
    # a heartbeat per bridge twice a second instead of 100 samples; a press is reported.
    with running_skin(tmp_path, "--reporting", "event:40:500", "--readout", "off") as skin, \
            serial.Serial(skin.gateways[1][0], 115200, timeout=0.1) as pty:
        skin.wait_for(pty, {1, 2, 3, 4}, seconds=20.0)
        skin.read(pty, 1.0)  # start-up traffic drains
        idle = data_by_origin(skin.read(pty, 3.0))
        assert set(idle) == {1, 2, 3, 4}, idle.keys()
        cycles = {b: sorted({s.cycle for s in v}) for b, v in idle.items()}  # a retried frame may repeat
        assert all(len(c) >= 3 for c in cycles.values()), cycles  # periodic: ~300 each
        # heartbeats only, never more than one heartbeat apart, and a heartbeat apart unless a
        # change came before: a sample that moved by more than the threshold, or whose flags
        # changed (a bridge that gets mesh time meanwhile: the host learns it is on the skin's
        # clock), goes at once, the sample after it too, and the next heartbeat comes in the
        # bridge's slot of the heartbeat period, sooner than a heartbeat after them.
        for b, v in idle.items():
            got = sorted({s.cycle: s for s in v}.values(), key=lambda s: s.cycle)  # a retried frame may repeat
            early = 3  # samples before this may come sooner than a heartbeat (the window may open on a change)
            for i, (a, s) in enumerate(zip(got, got[1:]), start=1):
                gap = s.cycle - a.cycle
                assert gap <= 520 * 50_000, (b, i, gap)
                if s.flags != a.flags or abs(s.c1 - a.c1) > 40 or abs(s.c2 - a.c2) > 40:
                    early = i + 3  # the change, the sample after it, the heartbeat in the slot
                assert gap >= 400 * 50_000 or i < early, (b, i, gap, [x.cycle for x in got])
        rest = idle[4][-1].c1

        r = subprocess.run([*PY, "press", "0.04", "0.04", "--force", "3", "--diameter", "0.02",
                            "--duration", "2", "--base-port", str(skin.base)], capture_output=True, timeout=20)
        assert r.returncode == 0, r.stderr
        pressed = data_by_origin(skin.read(pty, 1.5))
        assert any(s.c1 < rest - 200 for s in pressed.get(4, [])), pressed.get(4)
        # the untouched bridges still send only heartbeats (periodic: a sample each 10 ms): one
        # per 400 ms of the span they cover (the read also drains what queued while `press`
        # ran), and 3 more for each change (a bridge losing or regaining mesh time on a busy
        # machine changes its flags: the change, the sample after it, an early slot heartbeat)
        for b in (1, 2, 3):
            got = sorted({s.cycle: s for s in pressed.get(b, [])}.values(), key=lambda s: s.cycle)
            changes = sum(s.flags != a.flags or abs(s.c1 - a.c1) > 40 or abs(s.c2 - a.c2) > 40
                          for a, s in zip(got, got[1:]))
            span = got[-1].cycle - got[0].cycle if got else 0
            assert len(got) <= 1 + span // (400 * 50_000) + 3 * changes, (b, changes, [(s.cycle, s.flags) for s in got])


@pytest.mark.parametrize("text, mode", [
    ("periodic", ReportingMode()),
    ("event", ReportingMode(0, 1000)),
    ("event:40", ReportingMode(40, 1000)),
    ("event:40:250", ReportingMode(40, 250)),
    ("Event:7:0", ReportingMode(7, 1000)),  # heartbeat 0 = the default, as in SET_REPORTING
])
def test_reporting_option_means_what_set_reporting_means(text: str, mode: ReportingMode) -> None:
    got = reporting_arg(text)
    assert got == mode
    assert reporting_arg(reporting_text(got)) == got


@pytest.mark.parametrize("text, says", [
    ("events", "periodic"), ("event:x", "integers"), ("event:-1", "THRESHOLD"),
    ("event:1:600001", "HEARTBEAT_MS"), ("event:1:2:3", "periodic"), ("", "periodic"),
])
def test_reporting_option_refuses_bad_values_naming_them(text: str, says: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError, match=says):
        reporting_arg(text)


def test_bad_reporting_option_is_refused_by_mesh_up_and_bridge(tmp_path: Path) -> None:
    mesh_path = tmp_path / "g.toml"
    mesh_path.write_text(mesh_to_toml(meshgen.grid(2, 2)))
    for cmd in (["mesh", "up", str(mesh_path)], ["bridge", "--mesh", str(mesh_path), "--id", "1"],
                ["mesh", "run", str(mesh_path)]):
        r = subprocess.run([*PY, *cmd, "--reporting", "event:fast"], capture_output=True, timeout=30)
        assert r.returncode == 2 and b"--reporting" in r.stderr and b"Traceback" not in r.stderr, (cmd, r.stderr)
    assert processes_mentioning(str(mesh_path)) == []


def test_mesh_up_starts_gateways_first_then_outwards() -> None:
    # Bridges boot beside neighbours that already route: the gateway, then by hops.
    from cellbridge.emulator.realtime.process_up import start_order

    assert [b.id for b in start_order(meshgen.line(5, gateways=(3,)))] == [3, 2, 4, 1, 5]
    order = [b.id for b in start_order(meshgen.grid(3, 3, gateways=(1,)))]
    hops = {1: 0, 2: 1, 4: 1, 3: 2, 5: 2, 7: 2, 6: 3, 8: 3, 9: 4}
    assert sorted(order) == list(range(1, 10))
    assert [hops[b] for b in order] == sorted(hops[b] for b in order)


def test_mesh_up_refuses_a_bad_start_interval(tmp_path: Path) -> None:
    mesh_path = tmp_path / "line-2.toml"
    mesh_path.write_text(mesh_to_toml(meshgen.line(2)))
    r = subprocess.run([*PY, "mesh", "up", str(mesh_path), "--start-interval", "-1"], capture_output=True, timeout=30)
    assert r.returncode == 2 and b"--start-interval" in r.stderr and b"Traceback" not in r.stderr


def test_ctrl_c_to_mesh_up_stops_everything_without_a_word_of_failure(tmp_path: Path) -> None:
    # Ctrl-C in a terminal sends SIGINT to the whole foreground process group: the
    # supervisor and every process it started at once. The children then exit while the
    # supervisor still watches them, and it said "bridge 3 exited ...; the rest keep
    # running" about each: a normal stop looked like failures. Three stops: the children's
    # exits fall at another moment of the supervisor's watch each time.
    mesh_path = tmp_path / "line-2.toml"
    mesh_path.write_text(mesh_to_toml(meshgen.line(2)))
    from cellbridge.demo import gateway_line

    for _ in range(3):
        proc = subprocess.Popen([*PY, "mesh", "up", str(mesh_path), "--base-port", str(free_base_port()),
                                 "--start-interval", "0"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
        try:
            gateway_line(proc)
            end = time.monotonic() + 30
            while len(processes_mentioning(str(mesh_path))) < 5 and time.monotonic() < end:  # up, medium, world, 2
                time.sleep(0.1)
            time.sleep(0.5)
            os.killpg(proc.pid, signal.SIGINT)  # as the terminal does
            _, err = proc.communicate(timeout=30)
        finally:
            stop_and_sweep(proc, mesh_path)
        assert proc.returncode == 0, err
        assert b"exited" not in err and b"keep running" not in err, err.decode()
        assert b"Traceback" not in err, err.decode()
    assert processes_mentioning(str(mesh_path)) == []


def test_mesh_up_refuses_a_bad_scenario_before_starting_anything(tmp_path: Path) -> None:
    # The scenario was read by the world process only: the medium started (and printed its
    # counters), the world failed, then 'the world did not start on base port ...'
    mesh_path = tmp_path / "line-2.toml"
    mesh_path.write_text(mesh_to_toml(meshgen.line(2)))
    bad = tmp_path / "presses.toml"
    bad.write_text("[[contact]]\nstart = 1\nduration = 1\nposition = [0.04]\nforce = 2\ndiameter = 0.02\n")
    off = tmp_path / "beside.toml"
    off.write_text("[[contact]]\nstart = 1\nduration = 1\nposition = [4.0, 4.0]\nforce = 2\ndiameter = 0.02\n")
    for scenario, says in ((bad, "must be [x, y]"), (off, "touches no element"), (tmp_path / "none.toml", "cannot read")):
        r = subprocess.run([*PY, "mesh", "up", str(mesh_path), "--scenario", str(scenario), "--base-port",
                            str(free_base_port())], capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and str(scenario) in r.stderr and says in r.stderr, r.stderr
        assert "medium:" not in r.stderr and "did not start" not in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert processes_mentioning(str(mesh_path)) == []
