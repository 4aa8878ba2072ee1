"""``cellbridge ros2`` against a live daemon, read by a second DDS participant with its own types.

The daemon reads synthesized gateway traffic of a 3×3 skin from a pty (view_harness): a
2 N press across the seam of bridges 2 and 5. ``cellbridge ros2`` runs as a real process;
the test is a second DDS participant (bench/ros2_peer.py: types generated from the .msg
text by another parser) on loopback, on a domain and namespace of its own so parallel
tests never see each other.
"""

from __future__ import annotations

import json
import math
import os
import random
import signal
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from ros2_peer import Peer
from view_harness import PRESSED, Client, daemon, fed_skin, skin_config, stop_session, view_process, wait_ready

pytest.importorskip("cyclonedds", reason="the ros2 extra is not installed (make install installs it)")


def _domain() -> int:
    return random.Random(os.getpid() * 1000 + time.time_ns()).randrange(100, 230)


def _namespace() -> str:
    return f"/t{os.getpid()}_{random.randrange(1 << 30)}"


def start_ros2(ep: dict[str, str], domain: int, ns: str, *extra: str) -> Any:
    return view_process(["ros2", "--endpoint", ep["pub"], "--control", ep["control"], "--domain", str(domain),
                         "--namespace", ns, "--diagnostics-topic", f"{ns}/diagnostics", *extra],
                        stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def ready_line(proc: subprocess.Popen[bytes]) -> str:
    line = proc.stdout.readline().decode()  # type: ignore[union-attr]  # started with stdout=PIPE
    assert line.startswith("cellbridge ros2: domain"), line
    return line


def subscribe_all(peer: Peer, ns: str) -> None:
    peer.subscribe(f"{ns}/contacts", "tactile_msgs/msg/TactileContacts", reliable=True)
    peer.subscribe(f"{ns}/tactile_state", "tactile_msgs/msg/TactileState", reliable=False)
    peer.subscribe(f"{ns}/markers", "visualization_msgs/msg/MarkerArray", reliable=True)
    peer.subscribe(f"{ns}/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", reliable=True)


def stamp(t: Any) -> int:
    return int(t.sec) * 1_000_000_000 + int(t.nanosec)


def ns_of(t: float) -> int:
    return int(round(t * 1e9))


@pytest.fixture
def pressed(tmp_path: Path) -> Iterator[tuple[dict[str, str], Any, Client]]:
    """A daemon on a pty fed by a held press (not yet pressed), ready."""
    with fed_skin(tmp_path) as (pty, feeder):
        cfg, ep = skin_config(tmp_path, pty)
        client = Client(ep, (b"contact", b"health"))
        try:
            with daemon(cfg, tmp_path / "daemon.log"):
                wait_ready(client)
                yield ep, feeder, client
        finally:
            client.close()


def test_a_second_participant_receives_the_press_in_tactile_msgs_as_the_daemon_published_it(pressed: Any) -> None:
    ep, feeder, client = pressed
    domain, ns = _domain(), _namespace()
    peer = Peer(domain)
    try:
        subscribe_all(peer, ns)
        with start_ros2(ep, domain, ns) as proc:
            ready_line(proc)
            assert peer.pump(30, until=lambda t, s: t.endswith("tactile_state")), "no TactileState arrived"
            feeder.press()
            contacts = f"{ns}/contacts"
            assert peer.pump(60, until=lambda t, s: t == contacts and len(s.contacts) == 1), "no contact arrived"
            peer.pump(1.0)
            zmq_contacts: dict[int, dict[str, Any]] = {}
            # a held press publishes contacts without pause: drain what is queued, bounded
            drain_until = time.monotonic() + 5.0
            while time.monotonic() < drain_until and (got := client.recv(0.2)) is not None:
                if got[0] == "contact":
                    zmq_contacts[ns_of(got[1]["t_sample"])] = got[1]
            matched = 0
            for _, msg in peer.got[contacts]:
                for c in msg.contacts:
                    z = zmq_contacts.get(stamp(c.header.stamp))
                    if z is None:
                        continue
                    (zc,) = [k for k in z["contacts"] if f"contact_{k['id']}" == c.name]
                    # the same frame's contact, exactly: position and force
                    assert (c.position.x, c.position.y, c.position.z) == (zc["x"], zc["y"], 0.0)
                    assert -c.wrench.force.z == zc["force"] and (c.normal.x, c.normal.y, c.normal.z) == (0, 0, 1)
                    assert c.wrench.torque.x == pytest.approx(zc["y"] * -zc["force"], rel=1e-12)
                    assert c.header.frame_id == "cellbridge_skin"
                    matched += 1
            assert matched >= 1, f"no bag contact had a ZeroMQ contact of the same frame ({len(zmq_contacts)} seen)"
            # readings: the pressed elements carry force, the others 0 N, in element id order
            _, state = peer.got[f"{ns}/tactile_state"][-1]
            channels = {ch.name: list(ch.values) for ch in state.sensors}
            assert channels["cellbridge_skin/element"] == [float(b) for b in range(1, 10)]
            force = dict(zip(range(1, 10), channels["cellbridge_skin"]))
            assert all(force[b] > 0.2 for b in PRESSED), force
            assert all(force[b] == 0.0 for b in force if b not in PRESSED), force
            assert set(channels) == {"cellbridge_skin", "cellbridge_skin/area", "cellbridge_skin/dc1",
                                     "cellbridge_skin/dc2", "cellbridge_skin/element"}
            # the picture: a box per element, a disk, an arrow and a label for the contact
            peer.pump(1.0)
            _, markers = peer.got[f"{ns}/markers"][-1]
            kinds = {(m.ns, m.type) for m in markers.markers}
            assert {("elements", 6), ("contacts", 3), ("forces", 0), ("labels", 9)} <= kinds, kinds
            (cubes,) = [m for m in markers.markers if m.ns == "elements"]
            assert len(cubes.points) == len(cubes.colors) == 9
            # the health, as diagnostics
            diag = peer.got[f"{ns}/diagnostics"]
            assert diag, "no diagnostics arrived"
            names = {s.name: s for s in diag[-1][1].status}
            assert names["cellbridge: daemon"].level == 0, names["cellbridge: daemon"]
            assert {f"cellbridge: bridge {b}" for b in range(1, 10)} <= set(names)
            assert names["cellbridge: link gw"].message == "connected"
            stop_session(proc)
            assert proc.returncode == 0
            stats = json.loads(proc.stderr.read().decode().strip().splitlines()[-1])
            assert stats["published"]["contacts"] >= matched and stats["malformed"] == 0
    finally:
        peer.close()


def test_another_domain_receives_nothing(pressed: Any) -> None:
    """--domain elsewhere: a participant there gets the topics, one on our domain nothing."""
    ep, feeder, _ = pressed
    mine, ns = _domain(), _namespace()
    other = mine + 1 if mine < 229 else mine - 1
    here, there = Peer(mine), Peer(other)
    try:
        subscribe_all(here, ns)
        subscribe_all(there, ns)
        feeder.press()
        with start_ros2(ep, other, ns) as proc:
            ready_line(proc)
            assert there.pump(30, until=lambda t, s: t.endswith("contacts") and len(s.contacts) == 1)
            here.pump(3.0)
            there.pump(0.5)
            assert all(not v for v in here.got.values()), {k: len(v) for k, v in here.got.items()}
            assert all(here.writers(t) == 0 for t in here.readers)
            assert there.got[f"{ns}/tactile_state"] and there.writers(f"{ns}/contacts") == 1
    finally:
        here.close()
        there.close()


def _session_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
        return True
    except ProcessLookupError:
        return False


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL])
def test_a_restarted_daemon_is_picked_up_again_and_a_killed_bridge_leaves_nothing(tmp_path: Path, sig: int) -> None:
    domain, ns = _domain(), _namespace()
    peer = Peer(domain)
    try:
        subscribe_all(peer, ns)
        with fed_skin(tmp_path) as (pty, feeder):
            cfg, ep = skin_config(tmp_path, pty)
            client = Client(ep, (b"contact", b"health"))
            try:
                with start_ros2(ep, domain, ns) as proc:
                    ready_line(proc)
                    for run in (1, 2):
                        with daemon(cfg, tmp_path / f"daemon{run}.log") as d:
                            wait_ready(client)
                            feeder.press()
                            since = time.time()
                            assert peer.pump(60, until=lambda t, s, since=since: t.endswith("contacts")
                                             and len(s.contacts) == 1 and stamp(s.contacts[0].header.stamp) > since * 1e9
                                             ), f"no contact from daemon run {run}"
                            feeder.press(None)  # the next daemon takes its baseline on a quiet skin
                            if run == 1:
                                os.killpg(d.pid, signal.SIGKILL)  # the daemon dies outright
                                d.wait(10)
                    assert proc.poll() is None, "cellbridge ros2 exited with the daemon"
                    assert peer.writers(f"{ns}/contacts") == 1
                    os.killpg(proc.pid, sig)
                    proc.wait(15)
                    if sig == signal.SIGTERM:
                        assert proc.returncode == 0
                        stats = json.loads(proc.stderr.read().decode().strip().splitlines()[-1])
                        assert stats["daemon_restarts"] >= 1
                    assert not _session_alive(proc.pid), "a process of cellbridge ros2 outlived it"
                    # its DDS writers go: at once after SIGTERM (deleted), after their lease after SIGKILL
                    end = time.monotonic() + 30
                    while time.monotonic() < end and any(peer.writers(t) for t in peer.readers):
                        time.sleep(0.1)
                    assert not any(peer.writers(t) for t in peer.readers)
            finally:
                client.close()
    finally:
        peer.close()


def test_bad_options_say_what_is_wrong() -> None:
    from view_harness import CLI

    for argv, text in ((["--domain", "300"], "--domain must be within 0..232"),
                       (["--namespace", "no/slash"], "is not an absolute ROS 2 name"),
                       (["--interface", "a b"], "is not a network interface name")):
        r = subprocess.run([CLI, "ros2", "--endpoint", "tcp://127.0.0.1:1", *argv], capture_output=True, text=True,
                           timeout=60)
        assert r.returncode == 2 and text in r.stderr, (argv, r.stderr)
    assert math.isfinite(1.0)
