"""``cellbridge decode`` on a recording: each read's frames, then what it caused.

The golden corpus keeps the lines' bytes (``.mcap``) and the daemon's output (``.chk``)
apart; reading a regression needs them side by side, each input followed by the output it
caused. ``decode`` prints that: what a recording kept, or (``--run``) what the daemon run
offline makes of its reads now.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from cellbridge.cli import main
from cellbridge.recording import codec
from cellbridge.recording.mcapfile import RecordingWriter

CORPUS = Path(__file__).parent / "data" / "golden"


def _lines(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, list[dict[str, Any]], str]:
    rc = main(["decode", *argv])
    out, err = capsys.readouterr()
    return rc, [json.loads(line) for line in out.splitlines()], err


def test_run_follows_each_read_by_the_messages_it_caused_and_matches_the_golden_output(
        capsys: pytest.CaptureFixture[str]) -> None:
    rc, lines, err = _lines(capsys, str(CORPUS / "fragments.mcap"), "--run", "--topics", "contact,element")
    assert rc == 0, err
    outs = [d for d in lines if "out" in d]
    # exactly what the offline daemon (the service's own schedule) publishes on these reads
    from cellbridge.daemon.core.config import parse_config
    from cellbridge.daemon.shell.offline import OfflineDaemon

    from cellbridge.recording.mcapfile import read_payloads

    reads = sorted((p["t_host"], p["link"], p["data"]) for _, p in read_payloads(CORPUS / "fragments.mcap",
                                                                                 topics={"serial"}))
    config = parse_config({"link": [{"name": "gw1", "url": "/dev/null-gw1"}]}, "test")
    want = [(o.topic, o.payload["seq"]) for o in OfflineDaemon(config, topics={"contact", "element"}).run(reads)
            if o.topic in ("contact", "element")]
    assert [(d["out"], d["message"]["seq"]) for d in outs] == want
    assert sum(d["out"] == "contact" for d in outs) > 0 and len(outs) > 100
    # every message comes after the reads up to its time and before any later read
    last_in = -1.0
    for d in lines:
        if "in" in d:
            assert d["t"] >= last_in
            last_in = d["t"]
        else:
            assert d["t"] >= last_in, d["out"]
    # an element message follows the read whose samples it carries, at that read's time
    first_element = next(i for i, d in enumerate(lines) if d.get("out") == "element")
    read = lines[first_element - 1]
    assert "in" in read and read["t"] == lines[first_element]["t"]
    assert read["frame"]["type"] in ("DATA", "READOUT")


def test_a_recording_prints_its_reads_and_messages_in_the_order_kept(tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    from cellbridge.protocol import StreamDecoder

    from cellbridge.recording.mcapfile import read_payloads

    data = next(p["data"] for _, p in read_payloads(CORPUS / "fragments.mcap", topics={"serial"}))
    frames = list(StreamDecoder().feed_iter(data))
    assert frames  # a read of whole frames (HELLOs at start-up)
    path = tmp_path / "rec.mcap"
    w = RecordingWriter(path, fsync=False)
    t0 = 1_750_000_000.0
    w.add("serial", codec.encode("serial", {"v": 2, "seq": 0, "t_host": t0, "t_read": 10.0, "t_bridge": None,
                                            "link": "gw", "data": data}), int(t0 * 1e9), int(t0 * 1e9))
    w.add("contact", codec.encode("contact", {"v": 2, "seq": 0, "t_host": t0 + 0.01, "contacts": [],
                                              "force": float("nan")}), int((t0 + 0.01) * 1e9), int(t0 * 1e9))
    w.add("health", codec.encode("health", {"v": 2, "seq": 0, "t_host": t0 + 0.02}), int((t0 + 0.02) * 1e9),
          int(t0 * 1e9))
    w.finish()
    rc, lines, err = _lines(capsys, str(path))  # default topics: contact only
    assert rc == 0, err
    assert [("in" if "in" in d else d["out"]) for d in lines] == ["in"] * len(frames) + ["contact"]
    contact = lines[-1]
    assert contact["t"] == pytest.approx(t0 + 0.01) and contact["message"]["force"] == "NaN"  # strict JSON
    rc, lines, _ = _lines(capsys, str(path), "--topics", "none")
    assert rc == 0 and all("in" in d for d in lines)


def test_run_and_config_want_a_recording(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    capture = tmp_path / "capture.bin"
    capture.write_bytes(b"\x00\x01\x00")
    assert main(["decode", str(capture), "--run"]) == 2
    assert "take a recording" in capsys.readouterr().err


def test_a_config_whose_links_are_not_the_recordings_is_a_one_line_error(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "daemon.toml"
    bad.write_text("[contact]\nrate = -3\n")
    assert main(["decode", str(CORPUS / "fragments.mcap"), "--run", "--config", str(bad)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("cellbridge decode:") and "config" in err[0]
