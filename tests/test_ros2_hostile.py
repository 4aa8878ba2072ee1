"""The ROS 2 side under a daemon stream nobody planned for: values past a ROS 2 field's range,
several daemons on one endpoint (a proxy), payloads the views cannot read.

In-process tests use the views' real ZeroMQ shell on a real PUB socket on loopback; the
recorder tests run ``cellbridge record --profile ros2`` as a process (its own process group,
stopped on the way out) against a stand-in daemon on loopback, and read the bag back with
rosbags as ``tests/test_ros2_bag.py`` does.
"""

from __future__ import annotations

import json
import math
import os
import signal
import struct
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import msgpack
import pytest
import zmq

pytest.importorskip("cyclonedds", reason="the ros2 extra is not installed (make install installs it)")

from rosbags.rosbag2 import Reader

from cellbridge.ros2 import types as T
from cellbridge.ros2.convert import Converter
from cellbridge.ros2.daemon_feed import PayloadModel
from cellbridge.ros2.relay import Relay
from cellbridge.views.source import Source
from live_skin import cellbridge_cmd, free_port, group
from ros2_peer import typestore
from support.process_state import rss_mib

LAYOUT = {"ids": [1, 2], "x": [0.02, 0.06], "y": [0.02, 0.02], "side": 0.04}


def element(seq: int, source: str = "skin", **cols: Any) -> dict[str, Any]:
    base = {"v": 2, "seq": seq, "t_host": 1.7e9 + seq, "source": source, "bridge": [1, 2], "force": [1.0, 0.0],
            "area": [1e-4, 0.0], "dc1": [1e-13, 0.0], "dc2": [1e-13, 0.0], "valid": [True, False],
            "status": [0, 8], "touched": [True, False], "t_sample": [1.7e9 + seq] * 2}
    return {**base, **cols}


def contact(seq: int, source: str = "skin", x: float = 0.02, **fields: Any) -> dict[str, Any]:
    return {"v": 2, "seq": seq, "t_host": 1.7e9 + seq, "t_sample": 1.7e9 + seq, "source": source,
            "contacts": [{"id": 3, "x": x, "y": 0.02, "force": 2.0, "valid": True, "diameter": 0.01}], **fields}


def health(seq: int, source: str = "skin") -> dict[str, Any]:
    return {"v": 2, "seq": seq, "t_host": 1.7e9 + seq, "uptime": 1.0, "source": source,
            "links": {"gw": {"connected": True}}, "bridges": {"1": {"silent": False, "loss": 0.0}}}


# ---- the converter: whatever comes in, what goes out is a message ROS 2 can carry -----------

OUT_OF_RANGE = {
    "force past float32": ("element", element(0, force=[1e300, 0.0])),
    "area past float32": ("element", element(0, area=[-1e300, 0.0])),
    "dc1 past float32": ("element", element(0, dc1=[1e39, 0.0])),
    "dc2 past float32": ("element", element(0, dc2=[0.0, -4e38])),
    "bridge id past u16": ("element", element(0, bridge=[1, 2**200])),
    "negative bridge id": ("element", element(0, bridge=[1, -5])),
    "stamp at 2^31 s": ("contact", contact(0, t_sample=2.0**31)),
    "stamp rounding up to 2^31 s": ("contact", contact(0, t_sample=2147483647.9999999)),
}


@pytest.mark.parametrize("name", list(OUT_OF_RANGE))
def test_every_message_made_of_an_out_of_range_payload_serialises(name: str) -> None:
    """A value a ROS 2 field cannot hold (float32 past 3.4e38, an int32 second past 2038, an
    element id no bridge has) is unknown (NaN, zero stamp) or left out, and counted: it never
    stops the relay or the recorder with an encoder's exception."""
    topic, payload = OUT_OF_RANGE[name]
    conv = Converter()
    conv.set_layout({"layout": LAYOUT})
    out = conv.feed(topic, payload, 1.0)
    assert out, "nothing made"
    for _, message in out:
        T.cdr(message)  # raised "Failed to encode member sensors" before
    later = conv.feed("element", element(1), 2.0)  # and the next ordinary message still goes out
    for _, message in later:
        T.cdr(message)
    state = next(m for k, m in later if k == "state")
    assert [c.name for c in state.sensors][-1].endswith("/element")
    assert all(0 <= v <= 65535 for v in state.sensors[-1].values)
    if topic == "element":
        assert conv.malformed >= 1, "an out-of-range reading must be counted"


def test_a_reading_past_float32_is_unknown_not_a_wrong_number() -> None:
    conv = Converter()
    conv.set_layout({"layout": LAYOUT})
    out = dict(conv.feed("element", element(0, force=[1e300, 0.5], valid=[True, True], dc1=[1e39, 2e-13]), 1.0))
    force, dc1 = out["state"].sensors[0].values, out["state"].sensors[2].values
    assert math.isnan(force[0]) and force[1] == 0.5
    assert math.isnan(dc1[0]) and dc1[1] == 2e-13
    assert conv.malformed == 1


def test_a_stamp_past_int32_seconds_is_zero_not_an_overflow() -> None:
    assert T.stamp(2.0**31) == T.Time()
    assert T.stamp(2147483647.9999999) == T.Time()
    assert T.stamp(2147483646.5) == T.Time(sec=2147483646, nanosec=500_000_000)


# ---- the feed: one daemon per topic, each bad payload counted once ---------------------------

class Pub:
    """A PUB socket on loopback standing in for daemons behind a proxy, and a Source on it."""

    def __init__(self) -> None:
        self.ctx = zmq.Context()
        self.pub = self.ctx.socket(zmq.PUB)
        self.pub.linger = 0
        self.port = self.pub.bind_to_random_port("tcp://127.0.0.1")
        ctl = self.ctx.socket(zmq.ROUTER)  # a control endpoint that never answers
        ctl.linger = 0
        self.ctl_port = ctl.bind_to_random_port("tcp://127.0.0.1")
        self.ctl = ctl
        self.source = Source(f"tcp://127.0.0.1:{self.port}", f"tcp://127.0.0.1:{self.ctl_port}")

    def send(self, topic: str, payload: Any) -> None:
        self.pub.send_multipart([topic.encode(), msgpack.packb(payload)])

    def joined(self, model: PayloadModel, source: str = "skin") -> None:
        end = time.monotonic() + 30
        seq = 0
        while time.monotonic() < end:
            self.send("health", health(seq, source))
            seq += 1
            if self.source.poll(50):
                while self.source.poll(300):  # the rest of those sent meanwhile: none left to count later
                    self.source.drain(model)
                self.source.drain(model)
                model.take()
                return
        raise AssertionError("the subscriber never joined")

    def settle(self, model: PayloadModel, n: int) -> None:
        """Until ``n`` more messages were drained into ``model`` (counted off the socket: a
        model's own counters count some messages twice, a non-map as received and malformed)."""
        end = time.monotonic() + 30
        while n > 0 and time.monotonic() < end:
            if self.source.poll(100):
                n -= self.source.drain(model)

    def close(self) -> None:
        self.source.close()
        self.ctx.destroy(linger=0)


@pytest.fixture
def pub() -> Iterator[Pub]:
    p = Pub()
    try:
        yield p
    finally:
        p.close()


def test_two_daemons_behind_a_proxy_are_never_mixed_into_one_topic(pub: Pub) -> None:
    """As every view: the first daemon heard (or ``--source``'s) is the one published, the
    others are counted (docs/views.md, "One daemon per picture")."""
    conv = Converter(marker_period=math.inf)
    model = PayloadModel(conv)
    pub.joined(model, "left")
    pub.send("contact", contact(1, "left", x=0.02))
    pub.send("contact", contact(1, "right", x=0.06))
    pub.send("topology", {"v": 2, "seq": 0, "source": "right", "t_host": 1.7e9, "layout": LAYOUT})
    pub.settle(model, 3)
    out: list[tuple[str, Any]] = []
    Relay(pub.source, model, conv, lambda k, m: out.append((k, m))).step(0)
    xs = [c.position.x for k, m in out if k == "contacts" for c in m.contacts]
    assert xs == [0.02], xs  # the right daemon's contact was published as the left's before
    assert model.other_sources == {"right": 2}
    assert not conv.layout  # nor its layout taken for the left's


def test_source_picks_the_daemon_published(pub: Pub) -> None:
    conv = Converter(marker_period=math.inf)
    model = PayloadModel(conv, source="right")
    pub.joined(model, "right")
    pub.send("contact", contact(1, "left", x=0.02))
    pub.send("contact", contact(1, "right", x=0.06))
    pub.settle(model, 2)
    out: list[tuple[str, Any]] = []
    Relay(pub.source, model, conv, lambda k, m: out.append((k, m))).step(0)
    assert [c.position.x for k, m in out if k == "contacts" for c in m.contacts] == [0.06]


def test_a_payload_nobody_can_read_is_counted_once(pub: Pub) -> None:
    conv = Converter(marker_period=math.inf)
    model = PayloadModel(conv)
    pub.joined(model)
    pub.send("element", {"v": 2, "seq": 1, "source": "skin", "bridge": 5})  # no bridge column
    pub.send("element", [1, 2, 3])  # not a map
    pub.pub.send_multipart([b"contact", b"\xc1\xc1"])  # not msgpack
    pub.settle(model, 3)
    Relay(pub.source, model, conv, lambda k, m: None).step(0)
    assert model.malformed + conv.malformed == 3, (model.malformed, conv.malformed)  # 5: two counted twice


# ---- the recorder, a process -----------------------------------------------------------------

class Daemon:
    """A stand-in daemon on loopback: PUB, and a control socket that answers ``topology``."""

    def __init__(self) -> None:
        self.ctx = zmq.Context()
        self.pub = self.ctx.socket(zmq.PUB)
        self.pub.linger = 0
        self.pub_ep = f"tcp://127.0.0.1:{self.pub.bind_to_random_port('tcp://127.0.0.1')}"
        self.ctl = self.ctx.socket(zmq.ROUTER)
        self.ctl.linger = 0
        self.ctl_ep = f"tcp://127.0.0.1:{self.ctl.bind_to_random_port('tcp://127.0.0.1')}"
        self.seq: dict[str, int] = {}
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._answer, daemon=True)
        self._thread.start()

    def _answer(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                try:
                    frames = self.ctl.recv_multipart(zmq.NOBLOCK)
                except zmq.Again:
                    frames = None
                except zmq.ZMQError:
                    return
                if frames:
                    req = msgpack.unpackb(frames[-1])
                    reply = {"ok": True, "id": req.get("id"), "v": 2, "layout": LAYOUT, "source": "skin"}
                    self.ctl.send_multipart([frames[0], msgpack.packb(reply)])
            time.sleep(0.01)

    def send(self, topic: str, make: Any, **kw: Any) -> None:
        seq = self.seq[topic] = self.seq.get(topic, -1) + 1
        with self._lock:
            self.pub.send_multipart([topic.encode(), msgpack.packb(make(seq, **kw))])

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.ctx.destroy(linger=0)


def bag_counts(bag: Path) -> int:
    meta = (bag / "metadata.yaml").read_text() if (bag / "metadata.yaml").exists() else ""
    for line in meta.splitlines():
        if line.strip().startswith("message_count:"):
            return int(line.split(":")[1])
    return 0


@contextmanager
def recorder(daemon: Daemon, bag: Path, log: Path, *extra: str, preexec: Any = None) -> Iterator[subprocess.Popen[Any]]:
    cmd = cellbridge_cmd("record", str(bag), "--profile", "ros2", "--endpoint", daemon.pub_ep,
                         "--control", daemon.ctl_ep, "--chunk-seconds", "0.2", "--no-fsync", *extra)
    with open(log, "wb") as err, group(cmd, stderr=err) as proc:
        yield proc


def joined(daemon: Daemon, bag: Path, proc: subprocess.Popen[Any], topic: str = "health") -> None:
    """Until the recorder's bag holds a message (its subscription reached the PUB)."""
    end = time.monotonic() + 60
    while time.monotonic() < end and proc.poll() is None:
        daemon.send(topic, {"health": health, "element": element}[topic])
        if bag_counts(bag) > 0:
            return
        time.sleep(0.1)
    raise AssertionError(f"the recorder never recorded (status {proc.poll()})")


def stopped(proc: subprocess.Popen[Any], log: Path, sig: int = signal.SIGTERM) -> tuple[int, dict[str, Any]]:
    os.killpg(proc.pid, sig)
    rc = proc.wait(30)
    lines = [ln for ln in log.read_text().splitlines() if ln.startswith("{")]
    return rc, json.loads(lines[-1]) if lines else {}


def read_bag(bag: Path) -> dict[str, int]:
    store = typestore()
    counts: dict[str, int] = {}
    with Reader(bag) as reader:
        for conn, _, raw in reader.messages():
            store.deserialize_cdr(raw, conn.msgtype)
            counts[conn.topic] = counts.get(conn.topic, 0) + 1
    return counts


@pytest.fixture
def daemon() -> Iterator[Daemon]:
    d = Daemon()
    try:
        yield d
    finally:
        d.close()


def test_the_recorder_outlives_a_reading_past_float32_and_its_bag_reads(daemon: Daemon, tmp_path: Path) -> None:
    bag, log = tmp_path / "bag", tmp_path / "record.log"
    with recorder(daemon, bag, log) as proc:
        joined(daemon, bag, proc)
        daemon.send("element", element, force=[1e300, 0.0])
        daemon.send("contact", contact)
        time.sleep(0.5)
        assert proc.poll() is None, log.read_text()[-2000:]  # it died with a traceback before
        rc, stats = stopped(proc, log)
    assert rc == 0, log.read_text()[-2000:]
    assert stats["malformed"] >= 1
    got = read_bag(bag)
    assert got.get("/cellbridge/contacts") == 1
    assert got == {k: v for k, v in stats["recorded"].items() if v}


def stream_counts(bag: Path) -> dict[str, int]:
    """Messages per topic as a reader that goes through each MCAP file in order finds them
    (up to a file's last whole record: the last file of a stopped bag has no summary)."""
    from mcap.exceptions import McapError
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    counts: dict[str, int] = {}
    for f in sorted(bag.glob("*.mcap")):
        topics: dict[int, str] = {}
        with open(f, "rb") as fh:
            try:
                for r in StreamReader(fh, skip_magic=False).records:
                    if isinstance(r, Channel):
                        topics[r.id] = r.topic
                    elif isinstance(r, Message):
                        counts[topics[r.channel_id]] = counts.get(topics[r.channel_id], 0) + 1
            except (McapError, EOFError, struct.error):  # the cut-short end
                pass
    return counts


def metadata_counts(bag: Path) -> dict[str, int]:
    from ruamel.yaml import YAML

    info = YAML(typ="safe").load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    return {t["topic_metadata"]["name"]: t["message_count"] for t in info["topics_with_message_count"]
            if t["message_count"]}


def test_a_full_disk_stops_the_recorder_and_its_counts_are_what_the_bag_holds(daemon: Daemon, tmp_path: Path) -> None:
    """The file-size limit (RLIMIT_FSIZE, 100 KiB) stands for a full disk: the recorder stops with
    status 1, and what it says it recorded, what metadata.yaml says and what the files hold agree."""
    bag, log = tmp_path / "bag", tmp_path / "record.log"
    cmd = cellbridge_cmd("record", str(bag), "--profile", "ros2", "--endpoint", daemon.pub_ep, "--control",
                         daemon.ctl_ep, "--chunk-seconds", "0.2", "--chunk-size", "0.01", "--no-fsync")
    rng = __import__("random").Random(5)
    with open(log, "wb") as err, group(["bash", "-c", 'ulimit -f 100; exec "$@"', "bash", *cmd], stderr=err) as proc:
        joined(daemon, bag, proc)
        end = time.monotonic() + 60
        while proc.poll() is None and time.monotonic() < end:  # incompressible readings until the limit
            for _ in range(20):
                daemon.send("element", element, force=[rng.random(), rng.random()],
                            dc1=[rng.random() * 1e-12, rng.random() * 1e-12])
            time.sleep(0.02)
        rc = proc.wait(30)
    lines = [ln for ln in log.read_text().splitlines() if ln.startswith("{")]
    assert rc == 1 and lines, log.read_text()[-2000:]
    stats = json.loads(lines[-1])
    assert "File too large" in stats["error"]
    recorded = {k: v for k, v in stats["recorded"].items() if v}
    assert recorded == stream_counts(bag), (recorded, stream_counts(bag))
    assert metadata_counts(bag) == recorded
    assert stats["messages"] == sum(recorded.values())


def test_sigterm_while_the_recorder_starts_still_finishes_its_bag(daemon: Daemon, tmp_path: Path) -> None:
    """The bag exists from the recorder's first moments: a SIGTERM from then on finishes it. The
    recorder is held just after the bag is made, reading its key file (a FIFO nobody writes yet)."""
    bag, log, key = tmp_path / "bag", tmp_path / "record.log", tmp_path / "server.key"
    os.mkfifo(key)
    cmd = cellbridge_cmd("record", str(bag), "--profile", "ros2", "--endpoint", daemon.pub_ep, "--control",
                         daemon.ctl_ep, "--server-key", str(key), "--client-key", str(tmp_path / "c.key_secret"))
    with open(log, "wb") as err, group(cmd, stderr=err) as proc:
        end = time.monotonic() + 60
        while not (bag / "metadata.yaml").exists() and time.monotonic() < end:
            time.sleep(0.01)
        time.sleep(0.5)  # at the key file's open() by now
        os.killpg(proc.pid, signal.SIGTERM)
        time.sleep(0.2)
        fd = os.open(key, os.O_WRONLY | os.O_NONBLOCK) if proc.poll() is None else -1  # let the open() return
        if fd >= 0:
            os.close(fd)
        rc = proc.wait(30)
    assert rc != -signal.SIGTERM, "killed by the SIGTERM: its bag was left unfinished"
    assert read_bag(bag) == {}  # finished: rosbags reads it (it needs the summary)


def test_a_payload_of_a_schema_version_it_does_not_know_is_counted_not_converted(pub: Pub) -> None:
    """docs/zmq-api.md: a change that removes or redefines a field raises ``v``: a version-3
    contact's fields may not mean what version 2's do, so nothing is published as if they did."""
    from cellbridge.daemon.core.messages import SCHEMA_VERSION

    from cellbridge.ros2.convert import SCHEMA_VERSION as KNOWN

    assert KNOWN == SCHEMA_VERSION  # the converter knows the daemon's own version
    conv = Converter(marker_period=math.inf)
    model = PayloadModel(conv)
    pub.joined(model)
    pub.send("contact", contact(0))
    pub.send("contact", contact(1, v=KNOWN + 1))
    pub.send("topology", {"v": KNOWN + 1, "seq": 0, "source": "skin", "t_host": 1.7e9, "layout": LAYOUT})
    pub.send("contact", contact(2, v=1))  # an older version is read (fields are only added within one)
    pub.settle(model, 4)
    out: list[tuple[str, Any]] = []
    Relay(pub.source, model, conv, lambda k, m: out.append((k, m))).step(0)
    assert [len(m.contacts) for k, m in out if k == "contacts"] == [1, 1]
    assert conv.newer_schema == 2
    assert model.lost == {}  # the one left out was received: its seq is no gap
    assert not conv.layout
    assert Converter().feed("contact", contact(1, v=KNOWN + 1), 1.0) == []


def test_an_element_a_new_layout_drops_leaves_the_readings() -> None:
    """A topology that changes mid-stream (a daemon restarted on a smaller skin, a layout
    rebuilt): an element the new layout no longer has is no longer reported, with the last
    force the old one gave it, as if it were still there."""
    conv = Converter()
    conv.set_layout({"layout": {"ids": [1, 2, 3], "x": [0.02, 0.06, 0.10], "y": [0.02] * 3, "side": 0.04}})
    conv.feed("element", element(0, bridge=[1, 2, 3], force=[1.0, 2.0, 3.0], valid=[True] * 3), 1.0)
    conv.set_layout({"layout": LAYOUT})  # elements 1 and 2
    out = dict(conv.feed("element", element(1, bridge=[1], force=[1.5], valid=[True]), 2.0))
    ids = out["state"].sensors[-1].values
    assert ids == [1.0, 2.0], ids
    assert out["state"].sensors[0].values == [1.5, 2.0]
    cubes = next(m for m in out["markers"].markers if m.ns == "elements")
    assert len(cubes.points) == 2


def test_a_wall_clock_step_while_recording_neither_reorders_the_bag_nor_shows_in_it(
        daemon: Daemon, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``cellbridge record --help``: publish times follow the monotonic clock from the wall
    clock's time at the start, so a clock step while recording does not show in a replay. The
    recorder runs in this process (the wall clock cannot be stepped on this machine: it is
    replaced by one that steps back an hour a few messages into the recording); the bag's message times
    must still grow and span the recording's real length, not minus an hour."""
    from cellbridge.cli import build_parser

    real_time = time.time
    reads = [0]

    def stepped() -> float:  # back an hour once the recorder read the clock for 10 messages
        reads[0] += 1
        return real_time() - (3600.0 if reads[0] > 12 else 0.0)

    monkeypatch.setattr(time, "time", stepped)
    monkeypatch.setattr(time, "time_ns", lambda: int(stepped() * 1e9))
    stop = threading.Event()

    def traffic() -> None:
        while not stop.is_set():
            daemon.send("contact", contact)
            time.sleep(0.02)

    feeder = threading.Thread(target=traffic, daemon=True)
    feeder.start()
    bag = tmp_path / "bag"
    args = build_parser().parse_args(["record", str(bag), "--profile", "ros2", "--endpoint", daemon.pub_ep,
                                      "--control", daemon.ctl_ep, "--duration", "2", "--no-fsync", "--topics", "contact"])
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        assert args._module.endswith("record_cli")
        from cellbridge.ros2 import record

        assert record.run(args) == 0
    finally:
        stop.set()
        feeder.join(5)
        for s, h in handlers.items():
            signal.signal(s, h)
    with Reader(bag) as reader:
        times = [t for _, t, _ in reader.messages()]
    assert len(times) > 20
    assert times == sorted(times), "the step reordered the bag"
    span = (times[-1] - times[0]) / 1e9
    assert 1.0 < span < 3.0, span  # about the 2 s recorded (an hour off, or negative, before)


def test_the_bag_keeps_drawing_the_skin_when_the_daemons_clock_steps_back(daemon: Daemon, tmp_path: Path) -> None:
    """The markers' rate (10 a second) was measured on the daemon's ``t_host``: when the
    daemon's wall clock stepped back an hour, the bag held no picture for an hour."""
    bag, log = tmp_path / "bag", tmp_path / "record.log"
    with recorder(daemon, bag, log, "--topics", "element") as proc:
        joined(daemon, bag, proc, "element")
        for i in range(40):  # 2 s of readings, the daemon's clock an hour back after the first
            daemon.send("element", element, t_host=1.7e9 - (3600.0 if i else 0.0) + 0.05 * i)
            time.sleep(0.05)
        time.sleep(0.5)
        rc, stats = stopped(proc, log)
    assert rc == 0, log.read_text()[-2000:]
    markers = read_bag(bag).get("/cellbridge/markers", 0)
    assert markers >= 10, (markers, stats)  # about 20 in 2 s; 1 before


def test_a_contact_message_of_thousands_of_contacts_is_bounded() -> None:
    """A contact message of 20 000 contacts (a skin has at most one per element; the views keep
    64 per message) took seconds to convert, its picture megabytes: the relay, which sends
    contacts first, stalled on each. As the views: the picture draws at most 64 contacts, the
    message lists at most 4096 (a 64×64 skin's elements); the rest are counted. (The bounds are
    checked, not the time: speed is bench/'s to show.)"""
    from cellbridge.views.model import MAX_CONTACTS, MAX_ELEMENTS

    conv = Converter()
    conv.set_layout({"layout": LAYOUT})
    payload = contact(0)
    payload["contacts"] = [{"id": i, "x": 0.001 * (i % 100), "y": 0.02, "force": 1.0, "diameter": 0.01}
                           for i in range(20_000)]
    out = dict(conv.feed("contact", payload, 1.0))
    sizes = {k: len(T.cdr(m)) for k, m in out.items()}
    assert len(out["contacts"].contacts) == MAX_ELEMENTS
    assert len([m for m in out["markers"].markers if m.ns == "contacts"]) == MAX_CONTACTS
    assert conv.malformed == 1  # the message, once
    assert sizes["markers"] < 100_000, sizes


@pytest.mark.parametrize("link", ["fore\x00arm", "fore\u202earm", "f" * 65, "f" * 64 + "2"])
def test_a_link_that_cannot_name_a_frame_is_no_frame_id_and_its_contact_has_no_place(link: str) -> None:
    """A NUL in a contact's link went into the ROS 2 frame id as it was (a C++ subscriber
    reads the string up to the NUL: another frame, or none), and a long one cut to fit could
    read as another link. Such a link names no frame: the contact stays in the skin's frame
    with its place and force unknown (NaN), counted, and its label escapes nothing raw."""
    conv = Converter()
    conv.set_layout({"layout": LAYOUT})
    payload = contact(0)
    payload["contacts"][0].update(link=link, patch="p\x00", position=[0.01, 0.02, 0.03], normal=[0.0, 0.0, 1.0],
                                  force_vector=[0.0, 0.0, -2.0])
    out = dict(conv.feed("contact", payload, 1.0))
    (c,) = out["contacts"].contacts
    assert c.header.frame_id == conv.frame_id and "\x00" not in c.header.frame_id
    assert math.isnan(c.position.x) and math.isnan(c.wrench.force.z)
    assert conv.malformed == 1
    for m in out["markers"].markers:
        assert "\x00" not in m.header.frame_id and "\x00" not in m.text and "\u202e" not in m.text


def test_a_layout_of_a_hundred_thousand_elements_is_bounded_as_the_views_bound_it() -> None:
    from cellbridge.views.model import MAX_ELEMENTS

    conv = Converter()
    n = 100_000
    conv.set_layout({"layout": {"ids": list(range(n)), "x": [0.001 * i for i in range(n)], "y": [0.0] * n}})
    out = dict(conv.feed("element", element(0), 1.0))
    cubes = next(m for m in out["markers"].markers if m.ns == "elements")
    assert len(cubes.points) == MAX_ELEMENTS
    assert len(out["state"].sensors[-1].values) == MAX_ELEMENTS
    assert conv.malformed == 1


def test_messages_the_recorder_cannot_place_are_counted_in_its_closing_line(daemon: Daemon, tmp_path: Path) -> None:
    """A topic that only starts like a subscribed one (ZeroMQ subscribes by prefix:
    ``contact_v3`` reaches a ``contact`` subscriber) and a multipart of the wrong shape: each
    is counted where the closing line shows it, none is lost silently."""
    bag, log = tmp_path / "bag", tmp_path / "record.log"
    with recorder(daemon, bag, log) as proc:
        joined(daemon, bag, proc)
        daemon.pub.send_multipart([b"contact_v3", msgpack.packb(contact(0))])
        daemon.pub.send_multipart([b"contact", msgpack.packb(contact(1)), b"extra"])
        daemon.pub.send_multipart([b"contact", b"\xc1"])
        time.sleep(0.5)
        rc, stats = stopped(proc, log)
    assert rc == 0
    assert stats.get("unknown_topics") == 1, stats
    assert stats["malformed"] == 2, stats


def test_a_health_message_of_fifty_thousand_bridges_is_read_for_a_bounded_number() -> None:
    from cellbridge.ros2.convert import MAX_HEALTH_BRIDGES

    n = 50_000
    p = {**health(0), "bridges": {str(b): {"silent": b % 2 == 0, "loss": 0.0} for b in range(n)}}
    conv = Converter()
    out = dict(conv.feed("health", p, 1.0))
    T.cdr(out["diagnostics"])
    bridges = [s for s in out["diagnostics"].status if s.name.startswith("cellbridge: bridge ")]
    assert len(bridges) == MAX_HEALTH_BRIDGES
    assert conv.malformed == 1


def test_a_daemon_restarted_under_a_press_ends_its_contacts_on_ros_2(pub: Pub) -> None:
    """The daemon publishes contacts while there are any and once ``[]`` when they end; a
    daemon that dies under a press never sends that ``[]``, and a restarted one starts with
    no contact to end. The last TactileContacts said the skin was pressed, for ever (and the
    picture drew it): a restart (health's seq starting again) ends the old daemon's contacts."""
    conv = Converter(marker_period=math.inf)
    model = PayloadModel(conv)
    pub.joined(model)  # health seq 0, 1, ...
    out: list[tuple[str, Any]] = []
    relay = Relay(pub.source, model, conv, lambda k, m: out.append((k, m)))
    pub.send("health", health(100))
    pub.send("contact", contact(0))
    pub.settle(model, 2)
    relay.step(0)
    assert [len(m.contacts) for k, m in out if k == "contacts"] == [1]
    out.clear()
    pub.send("health", health(0))  # a new daemon process: its numbering starts again
    pub.settle(model, 1)
    relay.step(0)
    assert model.daemon_restarts == 1
    assert [len(m.contacts) for k, m in out if k == "contacts"] == [0], out
    assert not conv.contacts


def test_one_hiccup_is_not_a_warning_for_the_rest_of_the_week() -> None:
    """Diagnostics WARN when this subscriber lost daemon messages: lost since the diagnostics
    before, not ever (one loss on Monday read WARN until the relay was restarted)."""
    conv = Converter(diagnostics_period=0.0)
    conv.lost = {"element": 3}
    first = dict(conv.feed("health", health(0), 1.0))["diagnostics"].status[0]
    assert first.level == T.DiagnosticStatus.WARN and "lost 3" in first.message
    later = dict(conv.feed("health", health(1), 2.0))["diagnostics"].status[0]
    assert later.level == T.DiagnosticStatus.OK, later.message
    assert ("lost_by_this_subscriber", "3") in [(kv.key, kv.value) for kv in later.values]  # the total stays shown
    conv.lost = {"element": 4}
    again = dict(conv.feed("health", health(2), 3.0))["diagnostics"].status[0]
    assert again.level == T.DiagnosticStatus.WARN and "lost 1" in again.message


def test_a_bag_of_contacts_alone_still_ends_the_contacts_of_a_daemon_restarted_under_a_press(
        daemon: Daemon, tmp_path: Path) -> None:
    """``--topics contact``: the bag holds no health, yet a restarted daemon is known by its
    health numbering starting again. Without health the recorder never noticed: the old
    process's contact stayed the bag's last word (pressed for ever) and no restart was told."""
    bag, log = tmp_path / "bag", tmp_path / "record.log"
    with recorder(daemon, bag, log, "--topics", "contact") as proc:
        end = time.monotonic() + 60
        while bag_counts(bag) == 0 and time.monotonic() < end and proc.poll() is None:
            daemon.send("contact", contact)  # until its subscription reached the PUB
            time.sleep(0.1)
        for _ in range(3):
            daemon.send("health", health)
            time.sleep(0.05)
        daemon.send("contact", contact)
        time.sleep(0.3)
        daemon.seq["health"] = -1  # a new daemon process: its numbering starts again
        daemon.send("health", health)
        time.sleep(0.5)
        rc, stats = stopped(proc, log)
    assert rc == 0, log.read_text()[-2000:]
    assert stats["daemon_restarts"] == 1, stats
    assert stats["recorded"].get("/diagnostics", 0) == 0, stats  # health heard, not recorded: not asked for
    store = typestore()
    last = None
    with Reader(bag) as reader:
        for conn, _, raw in reader.messages():
            assert conn.topic != "/diagnostics"
            if conn.topic == "/cellbridge/contacts":
                last = store.deserialize_cdr(raw, conn.msgtype)
    assert last is not None and len(last.contacts) == 0, last


def test_an_interface_this_machine_has_not_is_named_as_such() -> None:
    # `cellbridge ros2 --interface eht0` (a typo) printed Cyclone DDS's "does not match an
    # available interface" and "cannot join ROS 2 domain 0: [DDS_RETCODE_ERROR] Non specific error"
    import socket

    from cellbridge.ros2.graph import BadInterface, dds_config

    with pytest.raises(BadInterface, match="no such network interface here"):
        dds_config("nosuchif0")
    names = [name for _, name in socket.if_nameindex()]
    assert all(dds_config(n) for n in names)  # every interface this machine has is taken
    r = subprocess.run(cellbridge_cmd("ros2", "--interface", "nosuchif0", "--endpoint", "tcp://127.0.0.1:1"),
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert "'nosuchif0': no such network interface here (interfaces: lo" in r.stderr, r.stderr
    assert "DDS_RETCODE" not in r.stderr and "Traceback" not in r.stderr, r.stderr


@pytest.mark.parametrize("frame", ["", " ", "skin\tleft", "skin\x7f", "x" * 65])
def test_a_frame_id_that_cannot_name_a_frame_is_refused_live_and_for_a_bag(tmp_path: Path, frame: str) -> None:
    """``--frame-id`` is every flat-skin message's frame: ``cellbridge ros2`` took one with a
    control character (a link named so is refused as a frame id), and ``record --profile
    ros2`` took any, an empty one too: a bag whose every message is in no frame rviz shows."""
    for cmd in (["ros2", "--frame-id", frame],
                ["record", str(tmp_path / "bag"), "--profile", "ros2", "--frame-id", frame]):
        r = subprocess.run([*cellbridge_cmd(), *cmd], capture_output=True, text=True, timeout=30)
        assert r.returncode == 2 and "--frame-id" in r.stderr and "Traceback" not in r.stderr, (cmd, r.stderr)
    assert not (tmp_path / "bag").exists()


def test_a_bag_recorder_behind_on_large_messages_keeps_its_memory_bounded_and_counts_the_rest(
        tmp_path: Path) -> None:
    """The bag recorder decoded up to 100 000 waiting messages at once, and ZeroMQ held as many
    again: a stream of a 64x64 skin's element messages (300 kB) faster than it converts them
    (a replay --fast into a bag) grew it by ~200 MB a second, 2.3 GB in 10 s. Now what waits
    is at most 256 MB of the daemon's bytes; messages past that are counted (behind, lost),
    and what was received before the SIGINT goes into the bag."""
    port = free_port()
    bag = tmp_path / "bag"
    n, per_second, e = 3000, 300, 4096
    rec = subprocess.Popen([*cellbridge_cmd(), "record", str(bag), "--profile", "ros2", "--endpoint",
                            f"tcp://127.0.0.1:{port}", "--control", f"tcp://127.0.0.1:{free_port()}", "--no-fsync",
                            "--topics", "element"], stderr=subprocess.PIPE, text=True, start_new_session=True)
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.sndhwm = 0
    pub.linger = 0
    peak = 0
    try:
        pub.bind(f"tcp://127.0.0.1:{port}")
        time.sleep(2.0)  # the recorder connects and subscribes
        t0 = time.monotonic()
        for i in range(n):
            p = {"v": 1, "seq": i, "t_host": 1.7e9 + i * 0.01, "t_sample": 1.7e9 + i * 0.01, "source": "x",
                 "t_bridge": [1e-6] * e, "bridge": list(range(e)), "element": list(range(e)), "cycle": [i] * e,
                 "c1": [1e-11] * e, "c2": [2e-11] * e, "dc1": [1e-13] * e, "dc2": [1e-13] * e, "force": [0.5] * e,
                 "area": [1e-4] * e, "valid": [True] * e}
            pub.send_multipart([b"element", msgpack.packb(p)])
            if i % 20 == 0:
                peak = max(peak, rss_mib(rec.pid))
            time.sleep(max(0.0, t0 + i / per_second - time.monotonic()))
        os.killpg(rec.pid, signal.SIGINT)
        _, err = rec.communicate(timeout=180)
    finally:
        if rec.poll() is None:
            os.killpg(rec.pid, signal.SIGKILL)
            rec.wait()
        pub.close()
        ctx.term()
    assert rec.returncode == 0, err
    stats = json.loads(err.strip().splitlines()[-1])
    assert peak < 1000, f"recorder grew to {peak} MB"
    got, lost = stats["recorded"]["/cellbridge/tactile_state"], stats["lost"].get("element", 0)
    assert got + lost <= n <= got + lost + stats["behind"], stats  # every message in the bag, or counted
