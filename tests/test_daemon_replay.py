"""Capture and replay: recorded traffic gives the golden output, in-process and through the real daemon."""

from __future__ import annotations

import struct
import time
from pathlib import Path

import pytest
from cellbridge.daemon.shell.capture import MAGIC, CaptureError, read_capture, write_capture

from daemon_harness import Client, Pty, daemon, write_config
from daemon_traffic import GridFrames
from support.golden_corpus import diff, offline_run, paths, published_diff, scenario

SCENARIO = scenario("daemon_press")  # the corpus's capture: its output is tests/data/golden/daemon_press.chk
CAPTURE, CHK = paths(SCENARIO)
CONFIG = CAPTURE.with_suffix(".toml")
# (the offline driver on the capture gives daemon_press.chk: tests/test_golden_corpus.py)


def test_golden_holds_what_the_capture_was_made_of() -> None:
    lines = CHK.read_text().splitlines()
    last = [ln for ln in lines if ln.startswith("contact")][-1]
    assert " n=1 " in last and " elements=2,5 valid=1" in last, last  # the second press, across the seam
    fields = dict(w.split("=", 1) for w in last.split(" | ")[1].split())
    assert abs(float(fields["x"].removesuffix("mm")) - 40.0) <= 1.0 and abs(float(fields["y"].removesuffix("mm")) - 22.0) <= 1.0
    assert abs(float(fields["F"].removesuffix("N")) - 2.0) <= 0.02
    pressed = [ln for ln in lines if ln.startswith("element") and "1" in ln.split("touched=")[1]][:6]
    touched = set()  # the first press, on four elements
    for ln in pressed:
        words = dict(w.split("=", 1) for w in ln.split()[1:])
        touched |= {int(b) for b, t in zip(words["b"].split(","), words["touched"]) if t == "1"}
    assert sorted(touched) == [1, 2, 4, 5]


def test_comparison_catches_a_moved_contact_and_a_changed_force() -> None:
    import copy

    messages, _ = offline_run(SCENARIO, CAPTURE)
    assert published_diff(SCENARIO, messages) == []  # the offline driver's own output passes
    moved = copy.deepcopy(messages)
    last = next(m for t, m in reversed(moved) if t == "contact")
    last["contacts"][0]["x"] += 1e-3
    d = published_diff(SCENARIO, moved)
    assert len(d) == 2 and all("x=41.0mm" in x and "x=40.0mm" in x for x in d), d  # the frame's line, the last
    changed = copy.deepcopy(messages)
    i, m = next((i, m) for i, (t, m) in enumerate(changed) if t == "element" and any(f == f for f in m["force"]))
    m["force"] = [f * 1.0001 for f in m["force"]]
    d = published_diff(SCENARIO, changed)
    assert len([x for x in d if ".force[" in x]) == sum(f == f for f in m["force"]), d  # each valid force is caught
    # and in the .chk: a contact moved by a millimetre is a changed line
    lines = [ln.replace("x=40.0mm", "x=41.0mm") if ln.startswith("contact") else ln for ln in CHK.read_text().splitlines()]
    assert sum(1 for ln in diff(SCENARIO, lines) if ln.startswith("+contact")) == sum(
        1 for ln in lines if ln.startswith("contact") and "x=41.0mm" in ln) > 0


def test_daemon_replaying_the_capture_publishes_the_golden_output(tmp_path: Path, warm_kernels: None) -> None:
    cfg = tmp_path / "replay.toml"
    text = CONFIG.read_text().replace("replay:daemon_press.cbcap", f"replay:{CAPTURE}")
    endpoints = write_config(tmp_path / "endpoints.toml", [])
    cfg.write_text(f'[pub]\nendpoint = "{endpoints["pub"]}"\n[control]\nendpoint = "{endpoints["control"]}"\n'
                   + text)
    client = Client(endpoints, (b"element", b"contact"))
    try:
        with daemon(cfg, tmp_path / "err.log") as proc:
            messages = client.until_exit(proc)
    finally:
        client.close()
    diffs = published_diff(SCENARIO, messages)
    assert not diffs, diffs[:10]


def test_capture_records_what_the_link_read(tmp_path: Path) -> None:
    pty = Pty(tmp_path / "gw")
    cap = tmp_path / "gw.cbcap"
    cfg = tmp_path / "daemon.toml"
    endpoints = write_config(cfg, [{"name": "gw", "url": pty.link, "capture": cap}])
    client = Client(endpoints)
    sk = GridFrames()
    sent = sk.hellos() + b"\x00junk\x00" + b"".join(d for _, d in sk.stream(20))
    try:
        with daemon(cfg) as proc:
            client.ready()
            for i in range(0, len(sent), 300):
                pty.write(sent[i:i + 300])
                time.sleep(0.005)
            client.wait_for("health", lambda m: m["links"]["gw"]["bytes"] == len(sent))
            proc.terminate()
            assert proc.wait(10) == 0
    finally:
        client.close()
        pty.close()
    records = list(read_capture(cap))
    assert b"".join(d for _, d in records) == sent
    times = [t for t, _ in records]
    assert times == sorted(times) and abs(times[0] - time.time()) < 60


def test_truncated_capture_reads_to_its_last_whole_record(tmp_path: Path) -> None:
    f = tmp_path / "c.cbcap"
    write_capture(f, [(1.0, b"abc"), (2.0, b"defg")])
    f.write_bytes(f.read_bytes()[:-2])
    assert list(read_capture(f)) == [(1.0, b"abc")]
    (tmp_path / "bad").write_bytes(b"nope" + MAGIC)
    with pytest.raises(CaptureError, match="not a cellbridge capture"):
        list(read_capture(tmp_path / "bad"))


def test_the_last_health_of_a_replay_says_it_finished(tmp_path: Path) -> None:
    """The final health (published while stopping) carries the links' own counters as
    they are then: it used to carry the ones taken at the health before, so a replay that
    exited when done reported replay_finished false and too few replayed_records."""
    cfg = tmp_path / "replay.toml"
    text = CONFIG.read_text().replace("replay:daemon_press.cbcap", f"replay:{CAPTURE}")
    endpoints = write_config(tmp_path / "endpoints.toml", [])
    cfg.write_text(f'[pub]\nendpoint = "{endpoints["pub"]}"\n[control]\nendpoint = "{endpoints["control"]}"\n'
                   f"[health]\ninterval = 30.0\n" + text)
    client = Client(endpoints, (b"health",))
    last = None
    try:
        with daemon(cfg, tmp_path / "err.log") as proc:
            end = time.monotonic() + 30
            while time.monotonic() < end:
                got = client.recv(0.5)
                if got is not None:
                    last = got[1]
                elif proc.poll() is not None:
                    break
            assert proc.wait(10) == 0
    finally:
        client.close()
    assert last is not None
    gw = last["links"]["gw"]
    assert gw["replay_finished"] is True and gw["replayed_records"] == sum(1 for _ in read_capture(CAPTURE))


def test_a_capture_corrupt_midway_ends_the_replay_with_its_error(tmp_path: Path) -> None:
    """A record header past the first one that is garbage (a length beyond MAX_RECORD)
    raised inside the replay task, which died unseen: the link stayed 'connected', the
    error was never named, and with exit_when_done the daemon never exited. Now the
    replay ends there, says why, and a daemon told to exit when done does."""
    records = list(read_capture(CAPTURE))[:5]
    bad = tmp_path / "bad.cbcap"
    write_capture(bad, records)
    bad.write_bytes(bad.read_bytes() + struct.pack("<dI", 9.0, 0xFFFFFFFF) + b"x" * 16)
    cfg = tmp_path / "replay.toml"
    text = CONFIG.read_text().replace("replay:daemon_press.cbcap", f"replay:{bad}")
    endpoints = write_config(tmp_path / "endpoints.toml", [])
    cfg.write_text(f'[pub]\nendpoint = "{endpoints["pub"]}"\n[control]\nendpoint = "{endpoints["control"]}"\n'
                   + text)
    client = Client(endpoints, (b"health",))
    last = None
    try:
        with daemon(cfg, tmp_path / "err.log") as proc:
            end = time.monotonic() + 30
            while time.monotonic() < end and proc.poll() is None:
                got = client.recv(0.5)
                if got is not None:
                    last = got[1]
            assert proc.wait(10) == 0
    finally:
        client.close()
    assert last is not None
    gw = last["links"]["gw"]
    assert gw["replayed_records"] == 5 and gw["replay_finished"] is True
    assert "corrupt record" in gw["last_error"] and gw["connected"] is False
