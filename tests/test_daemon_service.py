"""The daemon as a real process: real ptys in, real ZeroMQ sockets on loopback out."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zmq
from cellbridge.protocol import Command, Frame, Op, StreamDecoder

from daemon_harness import Client, Pty, daemon, write_config
from daemon_traffic import GridFrames
from support.payloads import payload_as

CORNER = (0.020, 0.020, 3.0, 0.012)  # on the corner of four elements: x and y both observable


@pytest.fixture
def rig(tmp_path: Path, warm_kernels: None) -> Iterator[tuple[Pty, Client, Path]]:
    """A daemon on a pty with its kernels compiled: tests wait for its contacts."""
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link, "reconnect_min": 0.05, "reconnect_max": 0.2}],
                             calibration={"n_baseline": 10})
    client = Client(endpoints)
    log = tmp_path / "stderr.log"
    try:
        with daemon(cfg, log) as proc:
            client.ready()
            yield pty, client, log
            assert proc.poll() is None, "the daemon died during the test"
    finally:
        client.close()
        pty.close()


def feed(pty: Pty, sk: GridFrames, n: int, press=None, start: int = 0, pause: float = 0.002) -> None:
    for _, data in sk.stream(n, press, start):
        pty.write(data)
        time.sleep(pause)


def calibrated(health: dict, n: int) -> bool:
    """A health message that places ``n`` elements, every one with its baseline taken."""
    layout = health["layout"]
    return layout["elements"] == n and not layout["not_ready"]


def test_press_written_into_a_pty_comes_out_as_element_and_contact(rig) -> None:
    pty, client, _ = rig
    sk = GridFrames(rows=3, cols=3)  # pressing every element at once would read as a common-mode step
    pty.write(sk.hellos() + sk.beacons())
    feed(pty, sk, 40)
    # The calibrator steps on host time (at most calibration.max_step_rate a second), so a
    # loaded daemon that reads the quiet slots in a few large reads has not finished its
    # baselines after 40 of them; pressing then would go into the baselines and never read
    # as touched. Quiet slots go on until health says every element is calibrated.
    k = 40
    ready = False
    end = time.monotonic() + 20
    while not ready and time.monotonic() < end:
        pty.write(sk.slot(k))
        k += 1
        got = client.recv(0.005)
        while got is not None and not ready:
            ready = got[0] == "health" and calibrated(got[1], 9)
            got = client.recv(0)
    assert ready, "the elements' baselines were never all taken"

    def newest_slot(m: dict) -> list[int]:
        return [i for i, c in enumerate(m["cycle"]) if c == max(m["cycle"])]

    def pressed(m: dict) -> bool:
        return len(newest_slot(m)) == 9 and [m["bridge"][i] for i in newest_slot(m) if m["touched"][i]] == [1, 2, 4, 5]

    # Each sample's counts carry the counter's quantisation (a random phase a sample), so
    # one estimate's force scatters by about 0.3 % (1 sigma; the tails of a few hundred
    # frames reach 1.1 %): every estimate is held to 3 %, their median to 1 %.
    element: dict | None = None
    reports: list[dict] = []
    end = time.monotonic() + 20
    while (element is None or len(reports) < 10) and time.monotonic() < end:  # press until contacts come
        pty.write(sk.slot(k, CORNER))
        k += 1
        got = client.recv(0.005)
        while got is not None:
            if got[0] == "element" and pressed(got[1]):
                element = element or got[1]
            elif got[0] == "contact" and got[1]["contacts"]:
                reports.append(got[1])
            got = client.recv(0)
    assert element is not None and len(reports) >= 10, (element, len(reports))
    el = element
    assert el["v"] == 2 and isinstance(el["t_host"], float) and len(el["cycle"]) == len(el["bridge"])
    forces = [el["force"][i] for i in newest_slot(el) if el["valid"][i]]
    assert sum(forces) == pytest.approx(3.0, rel=0.05)  # each element's share of one press
    # A frame the daemon did not get whole (a loaded machine writes and reads the slots
    # late) is told as such: its contact lists the elements it did not know and its σ
    # covers the press; every frame it knew whole is exact.
    whole = [c for c in reports if not c["unknown"]]
    assert len(whole) >= len(reports) // 2
    for c in reports:
        (contact,) = c["contacts"]
        if c["unknown"]:
            assert abs(contact["x"] - CORNER[0]) <= max(1e-3, 3 * contact["sigma_x"]), c
            assert abs(contact["y"] - CORNER[1]) <= max(1e-3, 3 * contact["sigma_y"]), c
            continue
        assert contact["x"] == pytest.approx(CORNER[0], abs=1e-3)
        assert contact["y"] == pytest.approx(CORNER[1], abs=1e-3)
        assert contact["force"] == pytest.approx(3.0, rel=0.03)
        assert contact["diameter"] == pytest.approx(0.012, abs=2e-4)
        assert c["v"] == 2 and c["t_host"] > 0 and sorted(contact["elements"]) == [1, 2, 4, 5]
        assert contact["id"] == 0  # tracked: one stable id, from its first estimate (birth_frames 1)
    assert reports[-1]["contacts"][0]["age"] >= 1
    assert float(np.median([c["contacts"][0]["force"] for c in reports])) == pytest.approx(3.0, rel=0.01)


def announce(pty: Pty, client: Client, slots: int) -> GridFrames:
    """Bridges say HELLO and send a few quiet slots; returns once their data comes out."""
    sk = GridFrames()
    pty.write(sk.hellos())
    feed(pty, sk, slots)
    client.wait_for("element")
    return sk


def test_closing_and_reopening_the_pty_reconnects(rig) -> None:
    pty, client, _ = rig
    sk = announce(pty, client, 5)
    pty.close()
    client.wait_for("health", lambda m: not m["links"]["gw"]["connected"])
    time.sleep(0.3)  # a few failed reopen attempts (backoff), then the device is back
    pty.open()
    h = client.wait_for("health", lambda m: m["links"]["gw"]["connected"] and m["links"]["gw"]["reconnects"] >= 1)
    assert "device lost" in h["links"]["gw"]["last_error"] or "open failed" in h["links"]["gw"]["last_error"]
    feed(pty, sk, 5, start=5)
    el = client.wait_for("element")
    # every bridge's data flows again (a busy host may take several slots in one read)
    assert set(el["bridge"]) == {1, 2, 3, 4} and len(el["bridge"]) % 4 == 0


def test_garbage_and_truncated_frames_are_counted_not_fatal(rig) -> None:
    pty, client, _ = rig
    sk = GridFrames()
    pty.write(sk.hellos())
    one = sk.slot(0).split(b"\x00")[1]
    pty.write(b"\x00line noise\xff\xfe\x00" + one[:10] + b"\x00" + os.urandom(600) + b"\x00")
    feed(pty, sk, 5, start=1)
    client.wait_for("element")
    st = client.request({"v": 1, "cmd": "status"})
    assert st["ok"]
    link = st["links"]["gw"]
    assert link["framing_errors"] + link["crc_errors"] >= 3
    assert link["frames"] >= 24


def test_malformed_control_requests_get_error_replies(rig) -> None:
    _, client, _ = rig
    cases = {
        b"\xc1": "not valid msgpack",
        msgpack.packb([1, 2]): "must be a msgpack map",
        msgpack.packb({"cmd": "explode"}): "unknown cmd 'explode'",
        msgpack.packb({"cmd": "set", "param": "colour", "value": 1}): "param must be one of",
        msgpack.packb({"cmd": "set", "param": "rate", "value": -5, "bridge": 1}): "value for rate",
        msgpack.packb({"cmd": "set", "param": "rate", "value": 50, "bridge": 7}): "bridge 7 has not been heard",
        msgpack.packb({"cmd": "status", "v": 9}): "unsupported request version",
        msgpack.packb({"cmd": "tare", "bridges": "some"}): "bridges must be a list",
    }
    for body, needle in cases.items():
        rep = client.request(body)
        assert rep["ok"] is False and needle in rep["error"], (body, rep)
    assert client.request({"v": 1, "cmd": "status", "id": 7})["ok"] is True
    assert client.request({"v": 1, "cmd": "status", "id": 7})["id"] == 7


def test_set_goes_down_the_pty_as_a_cmd_frame_and_the_reply_comes_back(rig) -> None:
    pty, client, _ = rig
    sk = announce(pty, client, 3)
    req = client.ctx.socket(zmq.DEALER)
    req.connect(client.endpoints["control"])
    try:
        req.send(msgpack.packb({"v": 1, "cmd": "set", "param": "mode", "value": "adc", "bridge": 3}))
        frames: list[Frame] = []
        decoder = StreamDecoder()
        end = time.monotonic() + 5
        while not frames and time.monotonic() < end:
            frames = decoder.feed(pty.read(0.2))
        (cmd,) = frames
        sent = payload_as(cmd, Command)
        assert cmd.dst == 3 and sent.op == Op.SET_MODE and sent.value == 1
        pty.write(sk.reply(3, sent.token, Op.SET_MODE))
        assert req.poll(5000)
        rep = msgpack.unpackb(req.recv())
        assert rep["ok"] is True and rep["replies"]["3"]["status"] == "OK" and rep["sent_on"] == ["gw"]
        req.send(msgpack.packb({"v": 1, "cmd": "ping", "bridge": 2, "timeout": 0.3}))
        assert req.poll(5000)
        rep = msgpack.unpackb(req.recv())
        assert rep["ok"] is False and "no reply within the timeout from bridges [2]" in rep["error"]
    finally:
        req.close(0)


def test_topology_and_tare_over_control(rig) -> None:
    pty, client, _ = rig
    sk = GridFrames()
    pty.write(sk.hellos() + sk.beacons())
    feed(pty, sk, 12)
    topo = client.wait_for("topology", lambda m: len(m["bridges"]) == 4)
    assert topo["bridges"]["4"]["parent"] == 1 and topo["bridges"]["4"]["path_cost"] == 1.0
    rep = client.request({"v": 1, "cmd": "topology"})
    assert rep["ok"] and rep["layout"]["ids"] == [1, 2, 3, 4]
    assert client.request({"v": 1, "cmd": "tare", "bridges": [1, 2]})["tared_elements"] == 2


def test_subscriber_that_never_reads_does_not_slow_ingest(tmp_path: Path) -> None:
    """A subscriber that connects and never reads: its queue fills (hwm) and it loses
    messages; the daemon goes on ingesting and the subscriber that reads gets everything."""
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link}], pub={"hwm": 10}, contact={"enabled": False})
    reader = Client(endpoints, (b"element", b"health"))
    stuck = Client(endpoints, (b"",))
    stuck.sub.setsockopt(zmq.RCVHWM, 1)
    received = 0

    def drain(timeout: float) -> bool:
        nonlocal received
        got = reader.recv(timeout)
        if got is not None and got[0] == "element":
            received += len(got[1]["bridge"])
        return got is not None

    try:
        with daemon(cfg):
            reader.ready()
            sk = GridFrames(rate=1000.0)
            slots = 3000
            hellos = sk.hellos()  # numbered before the data, as a bridge does
            blob = b"".join(data for _, data in sk.stream(slots))
            pty.write(hellos)
            # Paced by the reader: each chunk's messages read before the next is written. With
            # hwm 10 a reader that falls more than 10 messages behind loses its own (libzmq, per
            # subscriber), and on a busy machine the reader's process, starved for a moment,
            # did (11 898 of 12 000 samples): the test is about the stuck subscriber, not that.
            for i in range(0, len(blob), 1024):
                pty.write(blob[i:i + 1024])
                while drain(0.02):
                    pass
            # until every sample came, or none came for 5 s: on a busy machine the daemon
            # may take far longer than its usual 2 s over these 12 000 samples, and the test
            # is about losing none, not about when
            end = time.monotonic() + 180
            while received < 4 * slots and time.monotonic() < end and drain(5.0):
                pass
            assert received == 4 * slots  # every sample reached the subscriber that reads
            st = reader.request({"v": 1, "cmd": "status"})
            assert sum(b["samples"] for b in st["bridges"].values()) == 4 * slots
            assert st["pub"]["sent"]["element"] >= 1
    finally:
        reader.close()
        stuck.close()
        pty.close()


def test_sigterm_drains_and_exits_zero_and_sighup_reloads(tmp_path: Path) -> None:
    """Also over ipc:// endpoints instead of loopback TCP."""
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link}], pub={"endpoint": f"ipc://{tmp_path}/pub"},
                             control={"endpoint": f"ipc://{tmp_path}/control"})
    client = Client(endpoints)
    log = tmp_path / "err.log"
    try:
        with daemon(cfg, log) as proc:
            client.ready()
            good = cfg.read_text()
            cfg.write_text(good.replace("[health]", "[health]\nbogus = 1"))
            proc.send_signal(signal.SIGHUP)
            time.sleep(0.5)
            assert proc.poll() is None
            cfg.write_text(good.replace("interval = 0.2", "interval = 0.3"))
            proc.send_signal(signal.SIGHUP)
            time.sleep(0.5)
            proc.send_signal(signal.SIGTERM)
            assert proc.wait(10) == 0
        lines = [json.loads(line) for line in log.read_text().splitlines()]
        msgs = [ln["msg"] for ln in lines]
        rejected = next(ln for ln in lines if ln["msg"].startswith("reload rejected"))
        assert "health.bogus" in rejected["error"]
        assert "config reloaded" in msgs and msgs[-1] == "stopped"
    finally:
        client.close()
        pty.close()


def test_two_gateways_pty_and_socket_url_duplicates_removed(tmp_path: Path) -> None:
    """Two gateways hear the same bridges: a pty and a TCP serial server (socket:// URL).
    Every sample is published once; the second copy is counted as a duplicate; a dropped
    TCP connection is reopened."""
    import socket

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    server.settimeout(10)
    port = server.getsockname()[1]
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "tty", "url": pty.link},
                                   {"name": "tcp", "url": f"socket://127.0.0.1:{port}", "reconnect_min": 0.05,
                                    "reconnect_max": 0.2}])
    client = Client(endpoints, (b"element", b"health"))
    conns = []
    try:
        with daemon(cfg):
            client.ready()
            conn, _ = server.accept()
            conns.append(conn)
            sk = GridFrames()
            data = sk.hellos() + b"".join(d for _, d in sk.stream(10))
            pty.write(data)
            conn.sendall(data)
            total = 0
            while total < 40:
                total += len(client.wait_for("element")["bridge"])
            h = client.wait_for("health", lambda m: m["duplicates"] >= 44)
            assert total == 40 and h["duplicates"] == 44  # 4 HELLO + 40 DATA frames heard twice
            conn.close()  # the serial server goes away and comes back
            conn, _ = server.accept()
            conns.append(conn)
            # pyserial flushes what arrives while it opens a socket:// port: send once it is up
            client.wait_for("health", lambda m: m["links"]["tcp"]["connected"] and m["links"]["tcp"]["reconnects"])
            conn.sendall(b"".join(d for _, d in sk.stream(3, start=10)))
            el = client.wait_for("element")
            assert el["cycle"][0] == sk.cycle0 + 10 * 500_000  # the new samples, through the new connection
    finally:
        for c in conns:
            c.close()
        server.close()
        client.close()
        pty.close()


def test_count_drops_counts_what_a_full_subscriber_queue_refused(tmp_path: Path) -> None:
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link}], pub={"hwm": 5, "count_drops": True},
                             contact={"enabled": False})
    control = Client(endpoints, (b"health",))
    stuck = control.ctx.socket(zmq.SUB)  # tiny queues: it fills after a few messages
    stuck.setsockopt(zmq.RCVHWM, 1)
    stuck.setsockopt(zmq.RCVBUF, 1024)
    stuck.setsockopt(zmq.SUBSCRIBE, b"")  # everything, raw columns included: its queues fill at once
    stuck.connect(endpoints["pub"])
    slots = 6000
    try:
        with daemon(cfg):
            control.ready()
            sk = GridFrames(rate=1000.0)
            pty.write(sk.hellos())
            for _, data in sk.stream(slots):
                pty.write(data)
            end = time.monotonic() + 60
            st = control.request({"v": 1, "cmd": "status"})
            while sum(b["samples"] for b in st["bridges"].values()) < 4 * slots and time.monotonic() < end:
                time.sleep(0.2)
                st = control.request({"v": 1, "cmd": "status"})
            assert sum(b["samples"] for b in st["bridges"].values()) == 4 * slots  # ingest went on
            assert sum(st["pub"]["dropped"].values()) > 0  # and the refusals were counted
    finally:
        stuck.close(0)
        control.close()
        pty.close()


def test_a_capture_on_a_full_disk_costs_the_capture_not_health_or_ingest(tmp_path: Path) -> None:
    """/dev/full answers every write with ENOSPC, as a full disk does. The capture's
    first flush used to raise in the ticker task, which died: no health ever again, and
    every read raised before reaching the pipeline. Now the capture stops (counted and
    named in health) and the link keeps being read."""
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link, "capture": "/dev/full"}],
                             contact={"enabled": False})
    client = Client(endpoints)
    try:
        with daemon(cfg, tmp_path / "stderr.log") as proc:
            client.ready()
            sk = announce(pty, client, 5)
            feed(pty, sk, 5, start=5)
            el = client.wait_for("element", lambda m: max(m["cycle"]) == sk.cycle0 + 9 * 500_000)
            # (one read may hold more than one frame of samples when the machine is busy)
            assert sorted(set(el["bridge"])) == [1, 2, 3, 4]
            h = client.wait_for("health", lambda m: m["links"]["gw"].get("capture_dropped", 0) >= 1)
            assert "No space left" in h["links"]["gw"]["capture_error"]
            assert proc.poll() is None
    finally:
        client.close()
        pty.close()


def _worker_pids(daemon_pid: int) -> list[int]:
    """The contact worker processes among the daemon's children (not the resource tracker)."""
    out = []
    for pid in subprocess.run(["pgrep", "-P", str(daemon_pid)], capture_output=True, text=True).stdout.split():
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            continue
        if b"spawn_main" in cmd:
            out.append(int(pid))
    return out


def test_a_hung_contact_worker_is_killed_and_replaced_and_contacts_resume(tmp_path: Path, warm_kernels: None) -> None:
    """The worker stops answering (SIGSTOP: as a worker stuck in a loop). The daemon used
    to wait for it forever: no contact was ever published again, nothing said why, and
    SIGTERM hung in the drain. Now an estimate past contact.worker_timeout kills it
    (counted), a new worker takes over, contacts come back, and SIGTERM exits cleanly."""
    pty = Pty(tmp_path / "gw")
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link}], calibration={"n_baseline": 10},
                             contact={"worker_timeout": 2.0})
    client = Client(endpoints)
    stopped: list[int] = []
    try:
        with daemon(cfg, tmp_path / "stderr.log") as proc:
            client.ready()
            sk = GridFrames(rows=3, cols=3)
            pty.write(sk.hellos() + sk.beacons())
            k = 0

            def press_until(pred, limit: float = 30.0) -> dict:
                nonlocal k
                end = time.monotonic() + limit
                while time.monotonic() < end:
                    pty.write(sk.slot(k, CORNER if k >= 200 else None))
                    k += 1
                    got = client.recv(0.005)
                    while got is not None:
                        if pred(got):
                            return got[1]
                        got = client.recv(0)
                raise AssertionError("not seen while pressing")

            while k < 200:  # quiet slots for the baselines, then the press
                pty.write(sk.slot(k))
                k += 1
                time.sleep(0.002)
            press_until(lambda g: g[0] == "contact" and g[1]["contacts"])
            (worker,) = _worker_pids(proc.pid)
            os.kill(worker, signal.SIGSTOP)
            stopped.append(worker)
            h = press_until(lambda g: g[0] == "health" and g[1]["contact_estimation"].get("worker_restarts", 0) >= 1)
            assert h["contact_estimation"]["errors"] >= 1
            press_until(lambda g: g[0] == "contact" and g[1]["contacts"])  # from the new worker
            assert worker not in _worker_pids(proc.pid)
            os.killpg(proc.pid, signal.SIGTERM)
            assert proc.wait(30) == 0
    finally:
        for pid in stopped:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        client.close()
        pty.close()
