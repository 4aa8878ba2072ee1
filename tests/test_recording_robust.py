"""Recordings under hostile input: impossible times while recording, clock steps, damaged and
hostile files for ``info`` and ``replay`` (bounded memory, one-line errors, what can be read is read)."""

from __future__ import annotations

import base64
import json
import math
import os
import signal
import struct
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path
from typing import Any

import msgpack
import pytest
import zmq
from cellbridge.daemon.shell.capture import CaptureError
from cellbridge.daemon.shell.replay_source import read_records
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import recording_mutations as rm
from cellbridge.recording import codec
from cellbridge.recording.mcapfile import ReadResult, RecordingWriter, read_messages, read_payloads
from cellbridge.recording.recorder import Recorder
from cellbridge.recording.replay import Pacer
from daemon_harness import free_port
from support.process_state import first_stderr_line, rss_mib

CLI = [sys.executable, "-m", "cellbridge"]


def _element(seq: int, t_host: Any) -> dict[str, Any]:
    return {"v": 1, "seq": seq, "t_host": t_host, "t_bridge": [1e-6], "bridge": [1], "element": [0],
            "cycle": [seq], "c1": [1e-11], "c2": [2e-11], "force": [math.nan], "area": [math.nan],
            "valid": [False], "source": "skin-a"}


# -- item 5: an impossible t_host while recording ------------------------------------------------

BAD_TIMES: list[Any] = [1e20, math.inf, -math.inf, math.nan, -1.0, 0, 2**63, "soon", None, True, [1.0]]


def test_a_message_with_an_impossible_t_host_is_recorded_counted_and_the_recording_goes_on(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "t.mcap", lambda p: RecordingWriter(p, fsync=False))
    seq = 0
    for bad in BAD_TIMES:
        for t in (bad, 100.0 + seq * 0.01):
            rec.feed("element", codec.to_msgpack(_element(seq, t)), 200.0 + seq * 0.01)
            seq += 1
    no_time = _element(seq, 0.0)
    del no_time["t_host"]
    rec.feed("element", codec.to_msgpack(no_time), 200.0 + seq * 0.01)
    rec.close()
    s = rec.stats()
    assert s["bad_time"] == len(BAD_TIMES) + 1 and s["messages"] == seq + 1 and not s["error"]
    result = ReadResult()
    got = list(read_payloads(tmp_path / "t.mcap", result))
    assert result.complete and result.ok
    assert [p["seq"] for _, p in got] == list(range(seq + 1))  # every one, the odd ones too, as they were
    for m, p in got:
        if p["seq"] % 2 == 0 or p["seq"] == seq:  # the bad ones: logged at their receive time
            assert m.log_ns == m.publish_ns == int((200.0 + p["seq"] * 0.01) * 1e9)
        else:
            assert m.log_ns == int(p["t_host"] * 1e9)
    assert got[0][1]["t_host"] == 1e20 and got[2][1]["t_host"] == math.inf and math.isnan(got[6][1]["t_host"])


def _xpub(port: int) -> tuple[zmq.Context, zmq.Socket]:
    ctx = zmq.Context()
    pub = ctx.socket(zmq.XPUB)
    pub.linger = 0
    pub.bind(f"tcp://127.0.0.1:{port}")
    return ctx, pub


def _wait_subscribed(pub: zmq.Socket, proc: subprocess.Popen[Any], topic: bytes = b"element",
                     seconds: float = 60) -> None:
    """Until the recorder subscribed to ``topic``: its first subscription may be another
    socket's (the recorder also listens for the daemon's health, to say when none comes)."""
    end = time.monotonic() + seconds
    while True:
        left = end - time.monotonic()
        assert left > 0 and pub.poll(int(left * 1000)), f"no subscription to {topic!r} (recorder status {proc.poll()})"
        if pub.recv() == b"\x01" + topic:
            return


def test_record_keeps_going_after_t_host_1e20_and_inf_and_says_how_many(tmp_path: Path) -> None:
    port = free_port()
    ctx, pub = _xpub(port)
    out = tmp_path / "r.mcap"
    try:
        proc = subprocess.Popen([*CLI, "record", str(out), "--endpoint", f"tcp://127.0.0.1:{port}",
                                 "--topics", "element", "--count", "6"],
                                stderr=subprocess.PIPE, text=True, start_new_session=True)
        try:
            _wait_subscribed(pub, proc)
            for i, t in enumerate([1.0, 1e20, math.inf, 2.0, -math.inf, 3.0]):
                pub.send_multipart([b"element", codec.to_msgpack(_element(i, t))])
            _, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    finally:
        pub.close()
        ctx.term()
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    stats = json.loads(err.strip().splitlines()[-1])
    assert stats["bad_time"] == 3 and stats["messages"] == 6
    assert [p["seq"] for _, p in read_payloads(out)] == list(range(6))


def test_record_refuses_a_chunk_size_its_readers_would_not_read(tmp_path: Path) -> None:
    r = subprocess.run([*CLI, "record", str(tmp_path / "x.mcap"), "--chunk-size", "50"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "at most 8 MB" in r.stderr and not (tmp_path / "x.mcap").exists()


@pytest.mark.parametrize("profile", ["mcap", "ros2"])
@pytest.mark.parametrize(("option", "value"), [("--count", "0"), ("--count", "-3"), ("--duration", "0")])
def test_record_refuses_a_limit_of_nothing_as_sub_does(tmp_path: Path, profile: str, option: str, value: str) -> None:
    # --count 0 (and --duration 0) meant "no limit": a recording until Ctrl-C, without a
    # word, where `cellbridge sub --count 0` is refused. One way to say "until Ctrl-C": leave it out.
    port = free_port()  # nobody publishes there: a recorder that started would wait until the timeout
    out = tmp_path / "x.mcap"
    r = subprocess.run([*CLI, "record", str(out), "--profile", profile, "--endpoint", f"tcp://127.0.0.1:{port}",
                        option, value], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert f"{option} must be" in r.stderr and "leave it out" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not out.exists()


def test_record_help_says_how_to_record_until_ctrl_c() -> None:
    r = subprocess.run([*CLI, "record", "--help"], capture_output=True, text=True, timeout=60)
    text = " ".join(r.stdout.split())
    assert "--count N stop after N messages (default: until Ctrl-C)" in text, text
    assert "--duration S stop after S seconds (default: until Ctrl-C)" in text, text


@pytest.mark.parametrize("rotate", [False, True])
def test_record_refuses_to_replace_an_earlier_recording_unless_force(tmp_path: Path, rotate: bool) -> None:
    # `cellbridge record skin.mcap` run twice replaced the first recording without a word,
    # where `record skin --profile ros2` refuses an existing bag.
    from support.pub_helpers import publisher

    out = tmp_path / "skin.mcap"
    earlier = tmp_path / "skin-0000.mcap" if rotate else out
    earlier.write_bytes(b"an earlier recording")
    extra = ["--rotate-minutes", "60"] if rotate else []
    with publisher() as endpoint:
        r = subprocess.run([*CLI, "record", str(out), "--endpoint", endpoint, "--count", "3", *extra],
                           capture_output=True, text=True, timeout=60)
        assert r.returncode == 2 and str(earlier) in r.stderr and "--force" in r.stderr, r.stderr
        assert earlier.read_bytes() == b"an earlier recording" and "Traceback" not in r.stderr
        r = subprocess.run([*CLI, "record", str(out), "--endpoint", endpoint, "--count", "3", "--force", *extra],
                           capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert len(list(read_payloads(earlier))) == 3


def test_record_refuses_force_for_a_ros2_bag(tmp_path: Path) -> None:
    # a bag is always a new directory: --force would be ignored, so it is refused
    r = subprocess.run([*CLI, "record", str(tmp_path / "bag"), "--profile", "ros2", "--force", "--endpoint",
                        f"tcp://127.0.0.1:{free_port()}"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--force" in r.stderr and "new directory" in r.stderr, r.stderr


def test_record_of_a_daemon_that_is_not_there_says_so_and_that_no_file_was_written(tmp_path: Path) -> None:
    # With no daemon on the endpoint the recorder waited without a word and, stopped, exited
    # 0 with its counters: no skin.mcap, and nothing said about it.
    out = tmp_path / "skin.mcap"
    endpoint = f"tcp://127.0.0.1:{free_port()}"  # nobody publishes there
    proc = subprocess.Popen([*CLI, "record", str(out), "--endpoint", endpoint], stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        said = first_stderr_line(proc)
        assert b"is the daemon running" in said and endpoint.encode() in said, said
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    text = (said + err).decode()
    assert proc.returncode == 1, text
    assert f"nothing received from {endpoint}: {out} not written" in text and "Traceback" not in text, text
    assert not out.exists()


def test_replay_refuses_a_topic_the_daemon_has_not() -> None:
    # `cellbridge replay skin.mcap --topics contacts` (a typo) sent nothing and exited 0
    from support.golden_corpus import DATA

    r = subprocess.run([*CLI, "replay", str(DATA / "fragments.mcap"), "--fast", "--endpoint",
                        f"tcp://127.0.0.1:{free_port()}", "--topics", "serial,contacts"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "'contacts'" in r.stderr and "contact, element" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


def test_record_of_a_quiet_topic_of_a_running_daemon_does_not_ask_whether_it_runs(tmp_path: Path) -> None:
    # an idle skin publishes no contact: `record --topics contact` must not ask "is the daemon
    # running?" of a daemon whose health comes every second
    from support.pub_helpers import publisher

    out = tmp_path / "skin.mcap"
    with publisher() as endpoint:  # contact, health and raw; never topology
        r = subprocess.run([*CLI, "record", str(out), "--endpoint", endpoint, "--topics", "topology",
                            "--duration", "7"], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and f"nothing received from {endpoint}: {out} not written" in r.stderr, r.stderr
    assert "is the daemon running" not in r.stderr, r.stderr


def test_the_recorder_counts_what_it_cannot_write_and_writes_the_rest(tmp_path: Path) -> None:
    rec = Recorder(tmp_path / "o.mcap", lambda p: RecordingWriter(p, fsync=False), topics={"element"})
    rec.feed("element", codec.to_msgpack(_element(0, 1.0)), 1.0)
    rec.feed("element", codec.to_msgpack({**_element(1, 1.0), "pad": "x" * (codec.MAX_MESSAGE_BYTES + 1)}), 1.0)
    rec.feed("element", codec.to_msgpack({**_element(2, 1.0), "pad": [0] * (codec.MAX_MESSAGE_VALUES + 1)}), 1.0)
    rec.feed("elementary", codec.to_msgpack(_element(3, 1.0)), 1.0)  # a subscription is a prefix
    nested: Any = 0
    for _ in range(1000):  # msgpack holds it, the JSON encoder does not
        nested = [nested]
    rec.feed("element", msgpack.packb({"v": 1, "seq": 4, "t_host": 1.0, "deep": nested}), 1.0)
    rec.feed("element", codec.to_msgpack(_element(5, 1.0)), 1.0)
    rec.close()
    s = rec.stats()
    assert s["oversized"] == 2 and s["malformed"] == 2 and s["messages"] == 2
    assert [p["seq"] for _, p in read_payloads(tmp_path / "o.mcap")] == [0, 5]


# -- item 6: a wall-clock step while recording ---------------------------------------------------

STEPPED = """
import os, sys, time
real = time.time
flag = sys.argv[1]
stepped = []
def stepping():
    if not stepped and os.path.exists(flag):
        stepped.append(3600.0)
    return real() + (stepped[0] if stepped else 0.0)
time.time = stepping
from cellbridge.cli import main
sys.exit(main(sys.argv[2:]))
"""


def test_a_wall_clock_step_while_recording_is_not_a_pause_in_the_recording(tmp_path: Path) -> None:
    """The recorder's wall clock jumps an hour ahead halfway (as NTP or an operator would step it):
    its publish times, which a replay paces by, go on as the messages came."""
    port = free_port()
    ctx, pub = _xpub(port)
    out, flag = tmp_path / "step.mcap", tmp_path / "step-now"
    try:
        proc = subprocess.Popen([sys.executable, "-c", STEPPED, str(flag), "record", str(out), "--endpoint",
                                 f"tcp://127.0.0.1:{port}", "--topics", "element", "--count", "60"],
                                stderr=subprocess.PIPE, text=True, start_new_session=True)
        try:
            _wait_subscribed(pub, proc)
            for i in range(60):
                if i == 30:
                    flag.touch()
                pub.send_multipart([b"element", codec.to_msgpack(_element(i, 1000.0 + i * 0.02))])
                time.sleep(0.02)
            _, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    finally:
        pub.close()
        ctx.term()
    assert proc.returncode == 0, err
    published = [m.publish_ns * 1e-9 for m in read_messages(out)]
    assert len(published) == 60
    steps = [b - a for a, b in zip(published, published[1:])]
    assert min(steps) >= 0 and max(steps) < 60, f"publish times jump {max(steps):.1f} s"


def _paused_recording(path: Path) -> None:
    """Ten messages 10 ms apart, two hours without one, ten more, a step back of three hours, ten more."""
    w = RecordingWriter(path, fsync=False)
    t = 100_000.0
    for i in range(30):
        if i == 10:
            t += 7200.0
        elif i == 20:
            t -= 10800.0
        t += 0.01
        w.add("element", codec.encode("element", _element(i, t)), int(t * 1e9), int(t * 1e9), i)
    w.finish()


def test_a_long_pause_in_a_recording_is_shortened_and_said_and_a_step_back_too(tmp_path: Path) -> None:
    path = tmp_path / "pause.mcap"
    _paused_recording(path)
    r = subprocess.run([*CLI, "replay", str(path), "--rate", "20", "--endpoint", f"tcp://127.0.0.1:{free_port()}"],
                       capture_output=True, text=True, timeout=90)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 0, r.stderr
    assert any(f"{path}: no message for 7200.0 s" in line and "waiting 0.5 s" in line for line in lines), lines
    assert any(f"{path}: publish times go back 10800.0 s" in line for line in lines), lines
    stats = json.loads(lines[-1])
    assert stats["sent"] == 30 and stats["gaps"] == 2


def test_pacer_shortens_pauses_to_max_gap_and_goes_on_at_once_after_a_step_back() -> None:
    p = Pacer(2.0, max_gap=10.0)
    assert p.due(100.0, 5.0) == 5.0 and p.notice is None
    assert p.due(101.0, 5.2) == 5.5 and p.notice is None
    assert p.due(3701.0, 5.6) == 10.5 and p.notice == (3600.0, 5.0)  # 3600 s of recording: 10 s at rate 2
    assert p.due(3702.0, 10.6) == 11.0 and p.notice is None  # the schedule goes on from there
    assert p.due(2.0, 11.1) == 11.0 and p.notice == (-3700.0, 0.0)  # a step back: at once
    assert p.due(4.0, 11.2) == 12.0
    assert p.due(3.5, 11.3) == 11.75 and p.notice is None  # jitter back (under BACK_STEP) keeps the schedule
    keep = Pacer(1.0, max_gap=math.inf)
    keep.due(0.0, 0.0)
    assert keep.due(3600.0, 0.1) == 3600.0
    with pytest.raises(ValueError):
        Pacer(1.0, max_gap=0)


# -- item 7: a small file that declares or expands to a huge chunk ------------------------------

@pytest.mark.parametrize("kind", [0, 1, 3, 6])
def test_a_small_file_declaring_or_expanding_to_a_huge_chunk_is_refused_before_memory_grows(
        tmp_path: Path, kind: int) -> None:
    """0: an 8 kB file whose zstd chunk declares a 256 MB message; 1: a chunk that declares ~70 bytes and
    expands to 1 GB (zstd, no content size); 3: the same in lz4; 6: a chunk declaring 2**64 - 1 bytes."""
    path = tmp_path / f"bomb{kind}.mcap"
    path.write_bytes(rm.bomb(kind))
    assert path.stat().st_size < 5_000_000
    for tool in ("info", "replay"):
        code, _, rss_mb, stderr, _ = rm.run_one(rm.command(tool, path), tmp_path, timeout=120, exec_cli=True)
        run = rm.Run(str(path), tool, code, 0.0, rss_mb, stderr, 0)
        assert rm.verdict(run) == "" and code == 1, (tool, code, stderr)
        assert rss_mb < 200, f"{tool}: {rss_mb:.0f} MB"
        assert "bytes uncompressed" in stderr or "expands to more than" in stderr


def test_reading_a_decompression_bomb_takes_no_more_memory_than_the_bounds(tmp_path: Path) -> None:
    path = tmp_path / "b.mcap"
    for kind in (0, 1, 2, 3, 4, 5, 6):
        path.write_bytes(rm.bomb(kind))
        tracemalloc.start()
        try:
            result = ReadResult()
            got = list(read_payloads(path, result))
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert not got and result.damaged == 1 and not result.ok, kind
        # the file read (once or twice over) and a few MB: never what it declares or expands to
        assert peak < 3 * path.stat().st_size + (8 << 20), f"bomb {kind}: {peak / 1e6:.0f} MB"


def test_the_daemons_replay_link_refuses_every_bomb_by_name_within_bounded_memory(tmp_path: Path) -> None:
    """``replay:FILE.mcap`` read recordings with the MCAP library's own reader, which
    decompresses what a chunk declares: 256 MB for an 8 kB file. Every bomb, on the serial
    channel the link reads, is a ValueError naming the file, and memory stays bounded."""
    path = tmp_path / "b.mcap"
    for kind in range(rm.BOMB_KINDS):
        path.write_bytes(rm.bomb(kind, topic="serial"))
        tracemalloc.start()
        try:
            with pytest.raises(CaptureError, match=str(path)):
                list(read_records(path, "gw"))
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 3 * path.stat().st_size + (24 << 20), f"bomb {kind}: {peak / 1e6:.0f} MB"


def test_the_daemons_replay_link_reads_a_recording_cut_short_to_its_last_whole_chunk(tmp_path: Path) -> None:
    path = tmp_path / "s.mcap"
    w = RecordingWriter(path, chunk_size=200)
    for i in range(50):
        m = {"link": "gw", "t_host": 100.0 + i, "t_read": 10.0 + i, "data": base64.b64encode(bytes([i])).decode()}
        w.add("serial", json.dumps(m).encode(), int((100 + i) * 1e9), int((100 + i) * 1e9), i)
    w.finish()
    whole = [t for t, _ in read_records(path, "gw")]
    assert whole == [10.0 + i for i in range(50)]
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:len(data) // 2])
    got = [t for t, _ in read_records(cut, "gw")]
    assert 0 < len(got) < 50 and got == whole[:len(got)]
    damaged = bytearray(data)
    pos = data.index(b"\x28\xb5\x2f\xfd", len(data) // 3)  # a zstd frame's magic, a third in
    damaged[pos:pos + 8] = b"\xff" * 8
    bad = tmp_path / "damaged.mcap"
    bad.write_bytes(bytes(damaged))
    with pytest.raises(CaptureError, match="damaged chunk"):
        list(read_records(bad, "gw"))


# -- item 8: damaged recordings ------------------------------------------------------------------

def _chunks(data: bytes) -> list[tuple[int, int]]:
    return [(pos, length) for pos, op, length in rm.records(data) if op == 0x06]


def _chunk_seqs(path: Path, pos: int) -> list[tuple[str, int]]:
    """(topic, seq) of the messages of the chunk at ``pos`` of an intact file, read by the mcap
    package's own reader."""
    from mcap.reader import make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
        assert summary is not None
        fh.seek(pos)
        chunk = next(StreamReader(fh, skip_magic=True, emit_chunks=True).records)
    assert isinstance(chunk, Chunk)
    return [(summary.channels[r.channel_id].topic, json.loads(r.data)["seq"])
            for r in breakup_chunk(chunk) if isinstance(r, Message)]


def test_a_chunk_damaged_in_place_is_skipped_named_and_the_rest_is_info_and_replay(tmp_path: Path) -> None:
    seed_path = rm.write_seed(tmp_path / "seed.mcap")
    seed = seed_path.read_bytes()
    every = [(m.topic, json.loads(m.data)["seq"]) for m in read_messages(seed_path)]
    chunks = _chunks(seed)
    assert len(chunks) > 10
    pos, _ = chunks[len(chunks) // 2]
    lost = _chunk_seqs(seed_path, pos)
    assert lost
    damaged = bytearray(seed)
    (name_len,) = struct.unpack_from("<I", damaged, pos + 9 + 28)
    frame = pos + 9 + 32 + name_len + 8
    damaged[frame:frame + 4] = b"\x00\x00\x00\x00"  # the zstd frame's magic number overwritten
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(damaged))

    r = subprocess.run([*CLI, "info", "--json", str(path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "Traceback" not in r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith(f"cellbridge info: {path}: damaged: 1 damaged part skipped (chunk at byte {pos}: zstd")
    info = json.loads(r.stdout)
    assert info["messages"] == len(every) - len(lost) and info["complete"]

    port = free_port()
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.linger = 0
    sub.subscribe(b"")
    sub.connect(f"tcp://127.0.0.1:{port}")
    try:
        proc = subprocess.Popen([*CLI, "replay", str(path), "--fast", "--wait-subscriber", "--endpoint",
                                 f"tcp://127.0.0.1:{port}"], stderr=subprocess.PIPE, text=True,
                                start_new_session=True)
        got: list[tuple[str, int]] = []
        try:
            while len(got) < len(every) - len(lost) and sub.poll(30_000):
                topic, payload = sub.recv_multipart()
                got.append((topic.decode(), msgpack.unpackb(payload)["seq"]))
            _, err = proc.communicate(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    finally:
        sub.close()
        ctx.term()
    assert proc.returncode == 1 and "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith(f"cellbridge replay: {path}: damaged: 1 damaged part")
    assert got == [m for m in every if m not in lost]  # every other message, in order


def test_odd_json_payloads_are_skipped_counted_and_named_and_the_rest_is_read(tmp_path: Path) -> None:
    topics = ["element", "contact", "health", "serial", "topology"]
    chans = b"".join(rm.channel_record(i + 1, t) for i, t in enumerate(topics))
    odd = {  # not a map, not JSON, too deep: skipped
        "element": [b"[1, 2, 3]", b"[" * 100_000 + b"]" * 100_000, b"\xff not utf-8", b'{"seq": ' + b"9" * 5000 + b"}"],
        # maps with fields of other types than the API's: read, summarised where they make sense
        "contact": [b'{"seq": "x", "contacts": [1, "x", null, {"id": "3", "force": "NaN"}]}', b'{"contacts": {"id": 3}}'],
        "health": [b'{"bridges": 5, "source": 7}', b'{"bridges": {"x": 1, "99999999": 2, "12": 3}}'],
        "serial": [b'{"link": ["gw"], "data": 12}', b'{"link": "gw", "data": "!!!"}'],
        "topology": [b'{"a":' * 50_000 + b"1" + b"}" * 50_000],
    }
    good = [rm.message_record(1 + topics.index(t), codec.encode(t, p), p["seq"])
            for t, p, _ in rm._payloads(20) if t in topics]
    bad = [rm.message_record(1 + topics.index(t), d) for t in topics for d in odd[t]]
    path = tmp_path / "odd.mcap"
    path.write_bytes(rm.file_of(rm.chunk_record(chans + b"".join(good[:5] + bad[:6] + good[5:])),
                                rm.chunk_record(b"".join(bad[6:] + good), compression="lz4")))
    skipped = 4 + 1 + 1  # the four of element, the serial data that is not base64, the deep topology
    r = subprocess.run([*CLI, "info", "--json", str(path)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    (line,) = r.stderr.strip().splitlines()
    assert line.startswith(f"cellbridge info: {path}: damaged: {skipped} unreadable messages skipped")
    info = json.loads(r.stdout)
    assert info["messages"] == 2 * len(good) + len(bad) - skipped
    assert info["bridges"] == [1, 2, 12] and info["sources"] == ["skin-a"]
    assert info["contacts"]["most_at_once"] == 4 and info["serial"]["links"] == {"gw": 2 * 2, "?": 1}

    r = subprocess.run([*CLI, "replay", "--fast", str(path), "--endpoint", f"tcp://127.0.0.1:{free_port()}"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 2 and lines[0].startswith(f"cellbridge replay: {path}: damaged: {skipped} unreadable")
    assert json.loads(lines[1])["sent"] == info["messages"]


def test_a_file_that_is_not_mcap_is_one_line_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(b"not mcap at all")
    for tool in ("info", "replay"):
        code, _, _, stderr, _ = rm.run_one(rm.command(tool, path), tmp_path, exec_cli=True)
        assert rm.verdict(rm.Run(str(path), tool, code, 0.0, 0.0, stderr, 0)) == "" and code == 1, stderr
        assert f"{path}: not an MCAP file (bad magic)" in stderr


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=300) | st.text(max_size=300).map(str.encode) | st.sampled_from(rm.ODD_JSON),
       st.sampled_from(rm.TOPICS))
def test_decode_gives_a_map_or_a_payload_error(data: bytes, topic: str) -> None:
    try:
        p = codec.decode(topic, data)
    except codec.PayloadError:
        return
    assert isinstance(p, dict)
    try:
        codec.to_msgpack_checked(p)
    except codec.PayloadError:
        pass


SEED: dict[str, bytes] = {}  # the seed file (and its messages) for the property test


def _seed() -> bytes:
    if not SEED:
        import tempfile

        with tempfile.TemporaryDirectory() as d:
            SEED["zstd"] = rm.write_seed(Path(d) / "s.mcap", messages=120).read_bytes()
    return SEED["zstd"]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), min_size=1, max_size=12),
       st.integers(0, 10**6))
def test_the_reader_of_a_damaged_file_raises_nothing_and_yields_only_messages_as_written(
        tmp_path_factory: pytest.TempPathFactory, edits: list[tuple[int, int]], cut: int) -> None:
    seed = bytearray(_seed())
    written = {(m.topic, m.data) for m in _seed_messages()}
    for at, value in edits:
        seed[8 + at % (len(seed) - 8)] = value
    data = bytes(seed[:max(8, len(seed) - cut % len(seed))])
    path = tmp_path_factory.mktemp("h") / "f.mcap"
    path.write_bytes(data)
    result = ReadResult()
    got = list(read_payloads(path, result))  # raises nothing
    assert result.messages == len(got) + result.bad_messages
    assert all((m.topic, m.data) in written for m, _ in got)  # every chunk is checked (CRC) before it is read
    assert result.complete or result.error


def _seed_messages() -> list[Any]:
    if "messages" not in SEED:
        import tempfile

        with tempfile.TemporaryDirectory() as d:
            (Path(d) / "s.mcap").write_bytes(_seed())
            SEED["messages"] = list(read_messages(Path(d) / "s.mcap"))  # type: ignore[assignment]
    return SEED["messages"]  # type: ignore[return-value]


def test_a_chunk_whose_length_is_damaged_is_skipped_and_reading_goes_on_at_the_next(tmp_path: Path) -> None:
    path = rm.write_seed(tmp_path / "seed.mcap")
    seed = path.read_bytes()
    every = [(m.topic, json.loads(m.data)["seq"]) for m in read_messages(path)]
    chunks = _chunks(seed)
    # past the end of the file; short (the rest of the chunk read as records); a little long (into the
    # message index after it: the chunk itself is whole and read, the bytes after it are not records)
    for i, length in ((3, 2**64 - 1), (5, 17), (7, chunks[7][1] + 40)):
        pos = chunks[i][0]
        lost = _chunk_seqs(path, pos) if i != 7 else []
        data = bytearray(seed)
        struct.pack_into("<Q", data, pos + 1, length)
        bad = tmp_path / f"len{i}.mcap"
        bad.write_bytes(bytes(data))
        result = ReadResult()
        got = [(m.topic, p["seq"]) for m, p in read_payloads(bad, result)]
        assert got == [m for m in every if m not in lost], i
        assert result.damaged >= 1 and result.complete
        assert f"byte {pos if i != 7 else pos + 9 + length}" in result.problem(bad)


def test_a_chunk_twice_in_a_finished_file_is_read_twice_and_said(tmp_path: Path) -> None:
    path = rm.write_seed(tmp_path / "seed.mcap")
    seed = path.read_bytes()
    every = [(m.topic, json.loads(m.data)["seq"]) for m in read_messages(path)]
    pos, length = _chunks(seed)[4]
    twice = _chunk_seqs(path, pos)
    spliced = tmp_path / "twice.mcap"
    spliced.write_bytes(seed[:pos] + seed[pos:pos + 9 + length] + seed[pos:])
    result = ReadResult()
    got = [(m.topic, p["seq"]) for m, p in read_payloads(spliced, result)]
    i = every.index(twice[0])
    assert got == every[:i] + twice + every[i:]  # every message, none lost to the index's offsets, now wrong
    assert not result.ok  # and said: the summary is not where the footer says


# -- the must-show: info and replay on many mutated recordings ------------------------------------

def test_info_and_replay_end_cleanly_on_120_mutated_recordings(tmp_path: Path) -> None:
    """Each of 120 mutated recordings (every kind, every bomb) through ``cellbridge info`` and
    ``cellbridge replay --fast``, each run in a process of its own: exit 0, or 1 with one line
    naming the file; never a traceback; peak RSS under 200 MB. (Times: bench/bench_recording_fuzz.py.)"""
    files = rm.corpus(tmp_path / "corpus", 120)
    assert {k for _, k in files} == set(rm.KINDS)
    proc = subprocess.Popen([sys.executable, str(Path(rm.__file__)), str(tmp_path / "corpus")], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=Path(rm.__file__).parent, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=400)
    finally:
        if proc.poll() is None:  # the runner and the run it forked
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 0, err[-3000:]
    runs = [rm.Run(**json.loads(line)) for line in out.splitlines()]
    assert len(runs) == 2 * len(files)
    bad = [(Path(x.file).name, x.tool, v) for x in runs if (v := rm.verdict(x))]
    assert not bad, bad[:10]
    fat = [(Path(x.file).name, x.tool, round(x.rss_mb)) for x in runs if x.rss_mb >= 200]
    assert not fat, fat
    assert {x.code for x in runs} == {0, 1}  # some read whole, some damaged


def test_reading_some_topics_skips_chunks_by_the_index_and_loses_none(tmp_path: Path) -> None:
    path = rm.write_seed(tmp_path / "seed.mcap", chunk_size=1500)
    every = [(m.topic, m.data) for m in read_messages(path)]
    for topics in ({"health"}, {"contact", "topology"}, {"none"}):
        result = ReadResult()
        got = [(m.topic, m.data) for m in read_messages(path, result, topics)]
        assert got == [m for m in every if m[0] in topics] and result.ok and result.complete


@pytest.mark.parametrize("profile", ["mcap", "ros2"])
@pytest.mark.parametrize("option", ["--rotate-size", "--chunk-size", "--chunk-seconds", "--duration",
                                    "--rotate-minutes"])
def test_record_refuses_an_option_that_is_not_a_number_it_can_keep_to(tmp_path: Path, profile: str,
                                                                     option: str) -> None:
    """``nan`` (or ``inf``) passed every check: ``--rotate-size nan`` ended in a traceback, and
    ``--chunk-seconds nan`` or ``--duration nan`` recorded on without finishing a chunk on time
    or stopping when told: a kill then lost far more than the second the help promises."""
    out = tmp_path / "x"
    r = subprocess.run([*CLI, "record", str(out), "--profile", profile, "--endpoint", "tcp://127.0.0.1:1",
                        option, "nan"], capture_output=True, text=True, timeout=30)
    assert r.returncode == 2, r.stderr
    assert option in r.stderr and "Traceback" not in r.stderr
    assert not out.exists()


def test_record_profile_ros2_refuses_a_chunk_size_its_readers_would_not_read(tmp_path: Path) -> None:
    r = subprocess.run([*CLI, "record", str(tmp_path / "bag"), "--profile", "ros2", "--chunk-size", "50"],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "at most 8 MB" in r.stderr and not (tmp_path / "bag").exists()


@pytest.mark.parametrize("hwm", ["0", "-1"])
def test_replay_refuses_a_queue_bound_that_is_no_bound(tmp_path: Path, hwm: str) -> None:
    """``--hwm -1`` was a ZeroMQ traceback; ``--hwm 0`` is libzmq's "no limit": a subscriber
    that stops reading then grows the replay's memory without end."""
    w = RecordingWriter(tmp_path / "a.mcap", fsync=False)
    w.add("element", codec.encode("element", _element(0, 1.7e9)), 1, 1, 0)
    w.finish()
    r = subprocess.run([*CLI, "replay", str(tmp_path / "a.mcap"), "--fast", "--endpoint",
                        f"tcp://127.0.0.1:{free_port()}", "--hwm", hwm], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--hwm" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_a_burst_of_large_messages_faster_than_the_disk_keeps_the_recorders_memory_bounded_and_counts_the_rest(
        tmp_path: Path) -> None:
    """The receiver held up to 100 000 messages whatever their size, and ZeroMQ's queue as many
    again: a publisher of 450 kB messages faster than the writer grew the recorder by ~150 MB
    a second (GBs, until the kernel killed it; a replay --fast of a large skin into a recorder). Now it keeps at most 256 MB behind, and what
    it could not keep is counted (``missed``, ``behind``), never silently lost."""
    port = free_port()
    out = tmp_path / "big.mcap"
    n, per_second = 6000, 600  # 270 MB/s for 10 s: more than the writer encodes, steadily (not one burst)
    rec = subprocess.Popen([*CLI, "record", str(out), "--endpoint", f"tcp://127.0.0.1:{port}", "--no-fsync",
                            "--topics", "element"], stderr=subprocess.PIPE, text=True, start_new_session=True)
    ctx = zmq.Context()
    pub = ctx.socket(zmq.PUB)
    pub.sndhwm = 0
    pub.linger = 0
    peak = 0
    try:
        pub.bind(f"tcp://127.0.0.1:{port}")
        time.sleep(2.0)  # the recorder connects and subscribes
        rest = b"".join(msgpack.packb(x) for x in ("v", 1, "t_host", 1.7e9, "source", "x",
                                                    "force", [0.123456789012345] * 50_000))
        t0 = time.monotonic()
        for i in range(n):
            pub.send_multipart([b"element", b"\x85" + msgpack.packb("seq") + msgpack.packb(i) + rest])
            if i % 20 == 0:
                peak = max(peak, rss_mib(rec.pid))
                time.sleep(max(0.0, t0 + i / per_second - time.monotonic()))
        for _ in range(20):
            peak = max(peak, rss_mib(rec.pid))
            time.sleep(0.1)
        os.killpg(rec.pid, signal.SIGINT)
        _, err = rec.communicate(timeout=120)
    finally:
        if rec.poll() is None:
            os.killpg(rec.pid, signal.SIGKILL)
            rec.wait()
        pub.close()
        ctx.term()
    assert rec.returncode == 0, err
    stats = json.loads(err.strip().splitlines()[-1])
    assert peak < 1000, f"recorder grew to {peak} MB"
    assert stats["behind"] > 0
    kept = sum(1 for _ in read_payloads(out))
    assert kept == stats["recorded"]["element"]
    # every message is written, or counted: a gap in seq before a kept one, or not kept at the end
    assert kept + stats["missed"].get("element", 0) <= n <= kept + stats["missed"].get("element", 0) + stats["behind"]


def test_a_recording_of_messages_that_compress_past_the_readers_ratio_reads_back(tmp_path: Path) -> None:
    """Messages that repeat themselves (a large skin's identical readings, a synthetic stream)
    compressed into chunks of more than 1000:1, which every reader, ``info`` and ``replay``
    of this very recorder among them, refused as decompression bombs: a whole recording
    read back as "damaged: N damaged parts skipped; 0 messages read". The recorder writes
    only what its readers read."""
    from mcap.stream_reader import StreamReader

    out = tmp_path / "same.mcap"
    w = RecordingWriter(out, fsync=False)
    for i in range(12):
        p = {"v": 1, "seq": i, "t_host": 1.7e9 + i, "force": [0.123456789012345] * 50_000, "source": "x"}
        w.add("element", codec.encode("element", p), int((1.7e9 + i) * 1e9), int((1.7e9 + i) * 1e9), i)
    w.finish()
    result = ReadResult()
    assert [p["seq"] for _, p in read_payloads(out, result)] == list(range(12))
    assert result.ok and result.damaged == 0, result.damage
    with open(out, "rb") as fh:  # and the mcap package reads it as it stands
        n = sum(1 for r in StreamReader(fh).records if type(r).__name__ == "Message")
    assert n == 12
    r = subprocess.run([*CLI, "info", str(out)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0 and "damaged" not in r.stderr, r.stderr


def test_info_and_replay_of_a_fifo_say_what_it_is_and_wait_for_nothing(tmp_path: Path) -> None:
    """``cellbridge info`` of a FIFO (a name given by mistake, a pipe left in a directory of
    recordings) waited for ever for a writer; ``replay`` said it was no such file."""
    fifo = tmp_path / "skin.mcap"
    os.mkfifo(fifo)
    for cmd in (["info", str(fifo)], ["replay", str(fifo), "--fast", "--endpoint", f"tcp://127.0.0.1:{free_port()}"]):
        r = subprocess.run([*CLI, *cmd], capture_output=True, text=True, timeout=30)
        assert r.returncode in (1, 2) and "not a regular file" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_a_paced_replay_of_a_long_recording_does_not_grow_with_its_length(tmp_path: Path) -> None:
    """The replay kept how late every paced message went out, a float per message, for its
    closing line: a 3-day recording (50 million messages) grew it by ~1.6 GB. A million
    messages paced now take no more memory than a million sent as fast as possible."""
    src = tmp_path / "a.mcap"
    w = RecordingWriter(src, fsync=False)
    data = codec.encode("health", {"v": 1, "seq": 0, "t_host": 1.7e9})
    for i in range(20_000):
        w.add("health", data, 1_700_000_000_000_000_000 + i, 1_700_000_000_000_000_000 + i * 1000, i)
    w.finish()

    def peak_kb(*mode: str) -> int:
        p = subprocess.Popen([*CLI, "replay", *[str(src)] * 50, *mode, "--endpoint", f"tcp://127.0.0.1:{free_port()}"],
                             stderr=subprocess.PIPE, text=True)
        assert p.stderr is not None
        err = p.stderr.read()
        _, status, usage = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        assert p.returncode == 0 and json.loads(err.strip().splitlines()[-1])["sent"] == 1_000_000, err
        return usage.ru_maxrss

    fast, paced = peak_kb("--fast"), peak_kb("--rate", "1e9")
    assert paced < fast + 12_000, f"paced {paced} kB, fast {fast} kB"


def test_messages_a_restarted_daemon_published_before_the_recorder_reconnected_are_counted_missed(
        tmp_path: Path) -> None:
    """A restarted daemon numbers its messages from 0 again; the recorder took a seq going back
    as the restart and counted nothing, though the new process's first messages, published
    before the recorder had reconnected, never reached it: a recording short of them with
    ``missed`` 0. They are counted now (the new numbering starts at 0), and so is the restart."""
    port = free_port()
    out = tmp_path / "r.mcap"
    rec = subprocess.Popen([*CLI, "record", str(out), "--endpoint", f"tcp://127.0.0.1:{port}", "--no-fsync",
                            "--topics", "health"], stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        for life, lost in ((0, 0), (1, 5)):
            ctx = zmq.Context()  # a daemon process each: its own context, ended (the port free) before the next
            pub = ctx.socket(zmq.PUB)
            pub.linger = 0
            try:
                pub.bind(f"tcp://127.0.0.1:{port}")
                for seq in range(10):
                    if seq == lost:
                        time.sleep(2.0)  # the recorder (re)connects and subscribes: the ones before never reach it
                    pub.send_multipart([b"health", msgpack.packb({"v": 1, "seq": seq, "t_host": 1.7e9 + life,
                                                                  "source": "arm:5560"})])
                time.sleep(0.5)
            finally:
                pub.close()
                ctx.term()
        time.sleep(0.5)
        os.killpg(rec.pid, signal.SIGINT)
        _, err = rec.communicate(timeout=60)
    finally:
        if rec.poll() is None:
            os.killpg(rec.pid, signal.SIGKILL)
            rec.wait()
    stats = json.loads(err.strip().splitlines()[-1])
    assert stats["recorded"] == {"health": 15}, stats
    assert stats["missed"] == {"health": 5} and stats["restarts"] == 1, stats
