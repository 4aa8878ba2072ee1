"""ROS 2 bags (``cellbridge record --profile ros2``), read back by rosbags: its own rosbag2
reader and CDR deserialiser, with the shipped tactile_msgs .msg text registered.

The live test records a daemon reading a 4×4 skin's gateway traffic through a press across
the seam of two elements, beside a ZeroMQ subscriber of the same daemon: every message in the bag decodes, and the press's contact in the bag is the
ZeroMQ contact of the same skin frame, exactly.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
from pathlib import Path
from typing import Any

import pytest

pytest.importorskip("cyclonedds", reason="the ros2 extra is not installed (make install installs it)")

from mcap.reader import make_reader
from rosbags.rosbag2 import Reader
from ruamel.yaml import YAML

from cellbridge.ros2 import msgdefs
from cellbridge.ros2 import types as T
from cellbridge.ros2.bag import BagExists, BagWriter
from cellbridge.ros2.qos import topics
from live_skin import Collector, cellbridge_cmd, group
from ros2_peer import typestore
from view_harness import Client, daemon, fed_skin, skin_config, wait_ready

PRESS = (0.040, 0.060)  # across the seam of two elements of the 4×4 skin


def read_bag(path: Path) -> list[tuple[str, str, int, Any]]:
    """Every message as rosbags reads and deserialises it: (topic, type, time, message)."""
    store = typestore()
    out = []
    with Reader(path) as reader:
        for conn, t, raw in reader.messages():
            out.append((conn.topic, conn.msgtype, t, store.deserialize_cdr(raw, conn.msgtype)))
    return out


def _stop(proc: subprocess.Popen[Any], sig: int = signal.SIGTERM, timeout: float = 20) -> int:
    os.killpg(proc.pid, sig)
    return proc.wait(timeout)


@pytest.fixture(scope="module")
def live_bag(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A 4×4 skin's gateway traffic on a pty (a feeder thread writes it in real time: an
    emulated 4×4 in real processes does not hold up on a loaded machine), its daemon, the
    recorder and a ZeroMQ subscriber; a held press across the seam of two elements."""
    work = tmp_path_factory.mktemp("ros2bag")
    bag = work / "skin"
    with fed_skin(work, rows=4, cols=4, rate=100.0) as (pty, feeder):
        cfg, ep = skin_config(work, pty)
        client = Client(ep, (b"contact", b"health"))
        live = Collector(ep["pub"], (b"contact",))
        try:
            with daemon(cfg, work / "daemon.log"):
                wait_ready(client, 120)
                with group(cellbridge_cmd("record", str(bag), "--profile", "ros2", "--endpoint", ep["pub"],
                                          "--control", ep["control"], "--chunk-seconds", "0.5"),
                           stderr=open(work / "record.log", "wb")) as rec:
                    live.pump(2.0)  # the recorder has joined and has the layout
                    assert rec.poll() is None
                    feeder.press(lambda k: (*PRESS, 2.0, 0.010))  # held (the contact worker may start slowly)
                    live.pump(120, until=lambda t, m: t == "contact" and any(_at_press(c) for c in m["contacts"]))
                    assert any(_at_press(c) for _, m in live.payloads("contact") for c in m["contacts"]), \
                        f"no contact at the press: {[m['contacts'] for _, m in live.payloads('contact')][-3:]}"
                    live.pump(1.0)
                    feeder.press(None)  # released
                    live.pump(60, until=lambda t, m: t == "contact" and not m["contacts"])
                    live.pump(1.0)
                    assert _stop(rec) == 0
        finally:
            live.close()
            client.close()
    stats = json.loads((work / "record.log").read_text().strip().splitlines()[-1])
    return {"bag": bag, "live": live, "stats": stats}


def _at_press(c: dict[str, Any]) -> bool:
    return abs(c["x"] - PRESS[0]) < 3e-3 and abs(c["y"] - PRESS[1]) < 6e-3


def test_rosbags_reads_the_live_bag_and_every_message_decodes(live_bag: dict[str, Any]) -> None:
    messages = read_bag(live_bag["bag"])
    counts: dict[str, int] = {}
    for topic, _, _, _ in messages:
        counts[topic] = counts.get(topic, 0) + 1
    assert counts == live_bag["stats"]["recorded"]
    assert {"/cellbridge/tactile_state", "/cellbridge/contacts", "/cellbridge/markers", "/diagnostics"} <= set(counts)
    types = {topic: msgtype for topic, msgtype, _, _ in messages}
    assert types["/cellbridge/contacts"] == "tactile_msgs/msg/TactileContacts"
    assert types["/cellbridge/tactile_state"] == "tactile_msgs/msg/TactileState"
    # the MCAP files: the ros2 profile, .msg schemas, CDR channels with their QoS
    (mcap_file,) = live_bag["bag"].glob("*.mcap")
    with open(mcap_file, "rb") as fh:
        reader = make_reader(fh)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        schema = {s.name: s.data.decode() for s in summary.schemas.values()}
        assert schema["tactile_msgs/msg/TactileContacts"] == msgdefs.schema("tactile_msgs/msg/TactileContacts")
        qos = {c.topic: c.metadata["offered_qos_profiles"] for c in summary.channels.values()}
        assert "reliability: 2" in qos["/cellbridge/tactile_state"] and "reliability: 1" in qos["/cellbridge/contacts"]
    # the readings: 16 elements in id order, the pressed ones carry force
    states = [m for topic, _, _, m in messages if topic == "/cellbridge/tactile_state"]
    channels = {ch.name: ch.values for ch in states[-1].sensors}
    assert list(channels["cellbridge_skin/element"]) == [float(b) for b in range(1, 17)]
    assert max(max(s.sensors[0].values) for s in states) > 1.0
    assert live_bag["stats"]["malformed"] == 0 and live_bag["stats"]["error"] == ""


def test_the_press_in_the_bag_is_the_zeromq_contact_of_the_same_frame(live_bag: dict[str, Any]) -> None:
    zmq_contacts = {round(m["t_sample"] * 1e9): m for t, m in live_bag["live"].payloads("contact")}
    bag_contacts = [m for topic, _, _, m in read_bag(live_bag["bag"]) if topic == "/cellbridge/contacts"]
    matched = 0
    for msg in bag_contacts:
        for c in msg.contacts:
            z = zmq_contacts.get(c.header.stamp.sec * 1_000_000_000 + c.header.stamp.nanosec)
            if z is None:
                continue
            (zc,) = [k for k in z["contacts"] if f"contact_{k['id']}" == c.name]
            assert (c.position.x, c.position.y) == (zc["x"], zc["y"])  # exactly: the same float64
            assert -c.wrench.force.z == zc["force"]
            assert c.header.frame_id == "cellbridge_skin"
            matched += _at_press(zc)
    assert matched >= 5, f"only {matched} contacts at the press matched a ZeroMQ contact of the same frame"
    # and the contact's end: the last contacts message is empty, as on ZeroMQ
    assert bag_contacts[-1].contacts == [] and not live_bag["live"].payloads("contact")[-1][1]["contacts"]


def _spec_messages() -> list[tuple[str, Any]]:
    return [
        ("state", T.TactileState(header=T.Header(stamp=T.stamp(1.7e9), frame_id="f"),
                                 sensors=[T.ChannelFloat32("f", [1.5, math.nan, 0.0])])),
        ("contacts", T.TactileContacts(contacts=[T.TactileContact(name="contact_3", position=T.Point(0.1, 0.2, 0.0),
                                                                  wrench=T.Wrench(force=T.Vector3(0, 0, -2.5)))])),
        ("diagnostics", T.DiagnosticArray(status=[T.DiagnosticStatus(level=2, name="x", values=[T.KeyValue("a", "b")])])),
        ("markers", T.MarkerArray(markers=[T.Marker(type=9, text="#3 2.50 N")])),
    ]


def test_a_bag_rotates_into_files_rosbags_reads_in_order(tmp_path: Path) -> None:
    bag = BagWriter(tmp_path / "b", topics(), rotate_bytes=2000, chunk_size=500)
    written = []
    for i in range(300):
        key, msg = _spec_messages()[i % 4]
        bag.add(key, msg, 1_700_000_000_000_000_000 + i * 1_000_000)
        written.append(key)
        if i % 50 == 0:
            bag.flush()
    bag.finish()
    assert len(bag.files) > 2
    meta = YAML(typ="safe").load((tmp_path / "b" / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["message_count"] == 300 and len(meta["relative_file_paths"]) == len(bag.files)
    got = read_bag(tmp_path / "b")
    assert [t for _, _, t, _ in got] == sorted(t for _, _, t, _ in got)
    assert len(got) == 300
    state = next(m for topic, _, _, m in got if topic.endswith("tactile_state"))
    values = list(state.sensors[0].values)
    assert values[0] == 1.5 and math.isnan(values[1]) and values[2] == 0.0  # NaN says "not known"
    with pytest.raises(BagExists):
        BagWriter(tmp_path / "b", topics())


def test_info_and_decode_say_a_bags_file_is_a_ros_2_bag(tmp_path: Path, capsys: Any) -> None:
    """`cellbridge info skin/skin_0.mcap` (a bag of record --profile ros2) called the file
    damaged, every message 'not JSON' (replay too: the same reader): they now say it is a
    ROS 2 bag's file and what reads it."""
    import argparse

    from cellbridge import decode
    from cellbridge.recording import info
    from cellbridge.recording.mcapfile import NotARecording, read_messages

    bag = BagWriter(tmp_path / "skin", topics())
    for key, msg in _spec_messages():
        bag.add(key, msg, 1_700_000_000_000_000_000)
    bag.finish()
    file = tmp_path / "skin" / "skin_0.mcap"
    with pytest.raises(NotARecording, match="a ROS 2 bag's file"):
        next(read_messages(file))
    assert info.run(argparse.Namespace(files=[file], json=False)) == 1
    assert decode.run(_decode_args(str(file))) == 1
    err = capsys.readouterr().err
    assert err.count(f"{file}: a ROS 2 bag's file (cellbridge record --profile ros2") == 2, err
    assert "damaged" not in err and "not JSON" not in err


def _decode_args(path: str) -> Any:
    import argparse

    from cellbridge import decode

    parser = argparse.ArgumentParser()
    decode.add_arguments(parser)
    return parser.parse_args([path])


def test_every_shipped_type_serialises_as_rosbags_reads_it() -> None:
    """Each DDS class's CDR decodes with rosbags' definitions (ROS 2 Humble's for the standard
    messages, the shipped .msg text for tactile_msgs), and its fields are those of the .msg."""
    store = typestore()
    for name, cls in T.ALL.items():
        fields = [f for f, _ in store.fielddefs[name][1]]
        assert list(cls.__dataclass_fields__) == fields, name  # type: ignore[attr-defined]
        store.deserialize_cdr(T.cdr(cls()), name)
    assert sorted(T.ALL) == msgdefs.shipped()
