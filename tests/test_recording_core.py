"""The recording cores without processes: codec, schemas, MCAP files, the recorder, the pacer, info."""

from __future__ import annotations

import math
import os
import struct
from pathlib import Path
from typing import Any

import jsonschema
import msgpack
import pytest
from cellbridge.daemon.shell.capture import CaptureError
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from cellbridge.recording import codec
from cellbridge.recording.info import summarise
from cellbridge.recording.mcapfile import ReadResult, RecordingWriter, read_messages
from cellbridge.recording.recorder import Recorder, rotated_path
from cellbridge.recording.replay import Pacer
from cellbridge.recording.schemas import schema_for
from recording_helpers import same_payload

floats = st.floats(allow_nan=True, allow_infinity=True)
scalars = st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), floats,
                    st.text().filter(lambda s: s not in codec.NONFINITE))
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=5),
                                                       st.dictionaries(st.text(max_size=8), inner, max_size=5)),
                      max_leaves=30)


def _same(a: Any, b: Any) -> bool:
    """Equal as a subscriber sees it: same types (1 is not 1.0), same key order, any NaN equals any NaN
    (the sign and payload bits of a NaN are not kept; they mean nothing in the API)."""
    return same_payload(a, b)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(["element", "health", "contact", "topology", "raw"]),
       st.dictionaries(st.text(max_size=8), values, max_size=6))
def test_every_payload_comes_back_as_it_went_in(topic: str, payload: dict[str, Any]) -> None:
    if topic in codec.COLUMNAR:  # those topics carry no free text: a string there is a link or host name
        payload = {k: v for k, v in payload.items() if not _has_text(v)}
    data = codec.encode(topic, payload)
    data.decode("utf-8")
    assert b"NaN" not in data.replace(b'"NaN"', b"") and b"Infinity" not in data.replace(b'Infinity"', b"")
    assert _same(codec.decode(topic, data), payload)


def _has_text(v: Any) -> bool:
    if isinstance(v, str):
        return True
    if isinstance(v, dict):
        return any(_has_text(x) for x in v.values())
    if isinstance(v, list):
        return any(_has_text(x) for x in v)
    return False


def element(seq: int, t: float, force: float = math.nan) -> dict[str, Any]:
    return {"v": 1, "seq": seq, "t_host": t, "bridge": [1, 2], "element": [0, 0], "cycle": [10, 11],
            "t_bridge": [1e-6, 2e-6], "t_sample": [t, t], "c1": [1.5e-11, 1.6e-11], "c2": [1.9e-11, math.inf],
            "dc1": [math.nan, 1e-14], "dc2": [math.nan, 2e-14], "force": [force, 1.0], "area": [math.nan, 1e-4],
            "valid": [False, True], "status": [1, 0], "touched": [False, True], "source": "skin-a"}


def test_schemas_validate_what_the_codec_writes_and_reject_a_wrong_field() -> None:
    contact = {"v": 1, "seq": 0, "t_host": 1.0, "t_bridge": None, "t_sample": 1.0, "source": "a",
               "contacts": [{"id": 3, "x": 0.01, "y": 0.02, "force": math.nan, "elements": [1, 2], "valid": False}]}
    serial = {"v": 1, "seq": 0, "t_host": 1.0, "t_bridge": None, "link": "gw", "data": b"\x00\x01", "source": "a"}
    for topic, p in (("element", element(0, 1.0)), ("contact", contact), ("serial", serial)):
        jsonschema.validate(__import__("json").loads(codec.encode(topic, p)), schema_for(topic))
    bad = element(0, 1.0)
    bad["valid"] = [1, 0]  # ints where the schema says booleans
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(__import__("json").loads(codec.encode("element", bad)), schema_for("element"))


def _writer(path: Path, **kw: Any) -> RecordingWriter:
    return RecordingWriter(path, **kw)


def test_a_finished_file_opens_with_the_mcap_reader_indexed(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "a.mcap", _writer)
    for i in range(50):
        rec.feed("element", codec.to_msgpack(element(i, 100.0 + i * 0.01)), 100.0 + i * 0.01 + 0.001)
    rec.close()
    with open(tmp_path / "a.mcap", "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None and summary.statistics.message_count == 50
        assert {c.topic for c in summary.channels.values()} == {"element"}
        (schema,) = summary.schemas.values()
        assert schema.encoding == "jsonschema" and schema.name == "cellbridge.element"
        msgs = [(c.message_encoding, m.log_time, m.sequence) for _, c, m in reader.iter_messages()]
    assert msgs == [("json", int((100.0 + i * 0.01) * 1e9), i) for i in range(50)]


def test_a_file_cut_anywhere_reads_to_its_last_whole_chunk(tmp_path: Path) -> None:
    path = tmp_path / "cut.mcap"
    w = RecordingWriter(path, fsync=False)
    ends = []
    for i in range(40):
        w.add("element", codec.encode("element", element(i, float(i + 1))), (i + 1) * 10**9, (i + 1) * 10**9, i)
        if i % 10 == 9:
            w.flush()  # a chunk of ten messages
            ends.append(w.size)
    whole = path.read_bytes()
    w.abandon()
    for cut in range(ends[0], len(whole), 97):
        path.write_bytes(whole[:cut])
        result = ReadResult()
        seqs = [m.sequence for m in read_messages(path, result)]
        assert not result.complete and "cut short" in result.error
        whole_chunks = sum(1 for e in ends if e <= cut)  # ends: after each chunk's message index
        # every whole chunk (a chunk is whole before its index is), never part of one
        assert seqs == list(range(len(seqs))) and len(seqs) in (10 * whole_chunks, 10 * whole_chunks + 10)
    path.write_bytes(b"not mcap at all")
    with pytest.raises(ValueError, match="not an MCAP file"):
        list(read_messages(path))


def test_rotation_by_size_names_files_in_order_and_loses_nothing(tmp_path: Path) -> None:
    out = tmp_path / "skin.mcap"
    rec = Recorder(out, lambda p: RecordingWriter(p, chunk_size=4096, fsync=False), rotate_bytes=20_000)
    for i in range(400):
        rec.feed("element", codec.to_msgpack(element(i, 1.0 + i)), 1.0 + i)
    rec.close()
    assert rec.files[:2] == [rotated_path(out, 0), rotated_path(out, 1)] and len(rec.files) > 2
    seqs = [m.sequence for f in rec.files for m in read_messages(f)]
    assert seqs == list(range(400)) and rec.stats()["messages"] == 400


def test_rotation_by_time(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "t.mcap", _writer, rotate_seconds=10.0)
    for i in range(30):
        rec.feed("element", codec.to_msgpack(element(i, 1.0 + i)), 1.0 + i)
    rec.close()
    assert len(rec.files) == 3  # 0-9, 10-19, 20-29 s


def test_a_failed_write_stops_the_recording_names_it_and_counts_the_rest(tmp_path: Path) -> None:
    import resource
    import signal

    old_handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    old = resource.getrlimit(resource.RLIMIT_FSIZE)
    pid = os.fork()
    if pid == 0:  # the size limit is per process: try it in a child
        code = 1
        try:
            resource.setrlimit(resource.RLIMIT_FSIZE, (30_000, old[1]))
            rec = Recorder(tmp_path / "full.mcap", lambda p: RecordingWriter(p, chunk_size=2000))
            for i in range(400):
                rec.feed("element", codec.to_msgpack(element(i, 1.0 + i)), 1.0 + i)
            rec.close()
            s = rec.stats()
            ok = ("File too large" in s["error"] and "recording stopped" in s["error"]
                  and s["messages"] + s["dropped"] == 400 and 0 < s["messages"] < 400 and s["unconfirmed"] > 0)
            code = 0 if ok else 3
        finally:
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    signal.signal(signal.SIGXFSZ, old_handler)
    assert os.waitstatus_to_exitcode(status) == 0
    result = ReadResult()
    seqs = [m.sequence for m in read_messages(tmp_path / "full.mcap", result)]
    assert not result.complete and seqs == list(range(len(seqs))) and len(seqs) > 0


def test_a_message_that_is_not_msgpack_or_never_arrived_is_counted(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "m.mcap", _writer)
    rec.feed("element", b"\xc1junk", 1.0)
    rec.feed("element", msgpack.packb([1, 2]), 1.0)
    rec.feed("element", codec.to_msgpack(element(0, 1.0)), 1.0)
    rec.feed("element", codec.to_msgpack(element(4, 1.1)), 1.1)  # 1, 2 and 3 never arrived
    rec.feed("element", codec.to_msgpack(element(0, 1.2)), 1.2)  # the daemon restarted: no loss
    rec.close()
    s = rec.stats()
    assert s["malformed"] == 2 and s["messages"] == 3 and s["missed"] == {"element": 3}


def test_pacer_keeps_recorded_offsets_scaled_by_the_rate() -> None:
    p = Pacer(2.0)
    assert p.due(100.0, 5.0) == 5.0 and p.due(101.0, 5.3) == 5.5 and p.due(104.0, 6.0) == 7.0
    fast = Pacer(0.0)
    assert fast.due(100.0, 5.0) == 5.0 and fast.due(200.0, 5.1) == 5.1
    with pytest.raises(ValueError):
        Pacer(-1.0)


def test_info_counts_topics_bridges_contacts_and_sources(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "i.mcap", _writer)
    for i in range(10):
        rec.feed("element", codec.to_msgpack(element(i, 10.0 + i)), 10.0 + i)
    c = {"v": 1, "seq": 0, "t_host": 12.0, "t_bridge": None, "t_sample": 12.0, "source": "skin-b",
         "contacts": [{"id": 4, "x": 0.0, "y": 0.0, "force": 2.5, "elements": [1], "valid": True},
                      {"id": 5, "x": 0.1, "y": 0.0, "force": math.nan, "elements": [2], "valid": False}]}
    rec.feed("contact", codec.to_msgpack(c), 12.0)
    rec.feed("serial", codec.to_msgpack({"v": 1, "seq": 0, "t_host": 12.5, "t_bridge": None, "link": "gw",
                                         "data": b"\x00abc\x00", "source": "skin-a"}), 12.5)
    rec.close()
    info = summarise(tmp_path / "i.mcap")
    assert info["topics"] == {"contact": 1, "element": 10, "serial": 1} and info["messages"] == 12
    assert info["duration"] == pytest.approx(9.0) and info["complete"]
    assert info["sources"] == ["skin-a", "skin-b"] and info["bridges"] == [1, 2]
    assert info["contacts"] == {"distinct": 2, "most_at_once": 2, "max_force": 2.5}
    assert info["serial"] == {"links": {"gw": 1}, "bytes": 5}


def test_the_daemon_reads_a_recordings_serial_channel_and_old_captures(tmp_path: Path) -> None:
    from cellbridge.daemon.shell.capture import write_capture
    from cellbridge.daemon.shell.replay_source import read_records

    rec = Recorder(tmp_path / "s.mcap", _writer)
    reads = {"gw0": [(1.0, b"\x00ab"), (1.5, b"c\x00")], "gw1": [(1.2, b"\x00xyz\x00")]}
    for link, items in reads.items():
        for i, (t, data) in enumerate(items):
            rec.feed("serial", codec.to_msgpack({"v": 1, "seq": i, "t_host": t, "t_bridge": None, "link": link,
                                                 "data": data}), t)
    rec.close()
    assert list(read_records(tmp_path / "s.mcap", "gw0")) == reads["gw0"]
    assert list(read_records(tmp_path / "s.mcap", "gw1")) == reads["gw1"]
    with pytest.raises(CaptureError, match="recorded links: gw0, gw1"):
        list(read_records(tmp_path / "s.mcap", "other"))
    write_capture(tmp_path / "old.cbcap", reads["gw0"])
    assert list(read_records(tmp_path / "old.cbcap", "any")) == reads["gw0"]
    (tmp_path / "x").write_bytes(struct.pack("<Q", 7))
    with pytest.raises(CaptureError, match="bad magic"):
        read_records(tmp_path / "x", "gw")
