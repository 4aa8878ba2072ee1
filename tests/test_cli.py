"""The installed ``cellbridge`` command, run as a real process."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from cellbridge.protocol import (
    Beacon,
    Data,
    Frame,
    Hello,
    MeshTime,
    Mode,
    Readout,
    ReadoutSample,
    Sample,
    SampleFlags,
    encode_stream,
    fragment,
)
from cobs import cobs

from support.protocol_v1 import encode_v1, encode_v3

CLI = shutil.which("cellbridge", path=str(Path(sys.executable).parent)) or "cellbridge"


def run(*args: str, stdin: bytes = b"") -> subprocess.CompletedProcess[bytes]:
    return subprocess.run([CLI, *args], input=stdin, capture_output=True, timeout=60)


def test_help_lists_subcommands() -> None:
    out = run("--help")
    assert out.returncode == 0
    assert b"decode" in out.stdout


def test_ros2_help_says_a_robots_contacts_are_in_their_links_frames() -> None:
    """`cellbridge ros2 --help` said 'Everything is in one frame (--frame-id)', while a
    contact on a robot's skin is in its link's frame (README, docs/ros2.md)."""
    text = " ".join(run("ros2", "--help").stdout.decode().split())
    assert "Everything is in one frame" not in text
    assert "a contact on a robot's skin is in the frame of the link it is on" in text


def test_internal_entry_points_run_but_stay_out_of_the_top_level_help() -> None:
    listed = run("--help").stdout.decode()
    for name in ("bridge", "medium", "world"):  # started by 'mesh up', not by people
        assert f"    {name} " not in listed
        out = run(name, "--help")
        assert out.returncode == 0 and f"cellbridge {name}" in out.stdout.decode()
    assert "    mesh " in listed and "    daemon " in listed


def test_every_command_and_action_says_what_it_does_in_its_help() -> None:
    # `cellbridge mesh up --help` and `robot run --help` listed options under no sentence of
    # what the command does (that it prints the gateways' lines, that Ctrl-C stops it all),
    # and `demo --help` began with the source's markup (``cellbridge demo``).
    import argparse

    from cellbridge.cli import INTERNAL, build_parser

    def commands(parser: argparse.ArgumentParser, path: str) -> list[tuple[str, argparse.ArgumentParser]]:
        found = [(path, parser)]
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    if name not in INTERNAL:
                        found += commands(sub, f"{path} {name}")
        return found

    bare, marked = [], []
    for path, parser in commands(build_parser(), "cellbridge"):
        text = parser.format_help()
        if not (parser.description or "").strip():
            bare.append(path)
        if "``" in text:
            marked.append(path)
    assert bare == [] and marked == [], (bare, marked)


@pytest.mark.parametrize("command", [
    ["daemon", "--print-config"], ["mesh", "gen", "grid", "8", "8"], ["mesh", "check", "{mesh}"],
    ["mesh", "run", "{mesh}", "--seconds", "0.5"],
])
def test_output_whose_reader_went_away_ends_quietly(command: list[str], tmp_path: Path) -> None:
    # `cellbridge daemon --print-config | head` (or mesh gen, check, run) ended in a
    # BrokenPipeError traceback and status 1: the reader leaving is the end of the output

    from cellbridge.emulator.mesh import meshgen
    from cellbridge.emulator.mesh.mesh import mesh_to_toml

    mesh = tmp_path / "skin.toml"
    mesh.write_text(mesh_to_toml(meshgen.grid(2, 2)))
    proc = subprocess.Popen([CLI, *(a.format(mesh=mesh) for a in command)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)
    assert proc.stdout is not None
    proc.stdout.close()  # the reader is gone before the first line
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 0 and err == b"", err.decode()


@pytest.mark.parametrize("command", [
    ["sub", "--endpoint", "127.0.0.1:5560"],
    ["record", "{tmp}/x.mcap", "--endpoint", "127.0.0.1:5560"],
    ["replay", "{golden}", "--endpoint", "127.0.0.1:5560"],
    ["proxy", "--back", "tcp://127.0.0.1:5560", "--front", "127.0.0.1:5570"],
])
def test_an_endpoint_without_its_scheme_is_named_as_such(command: list[str], tmp_path: Path) -> None:
    # `--endpoint 127.0.0.1:5560` (tcp:// left out) said libzmq's "Invalid argument
    # (addr='127.0.0.1:5560')", and `proxy --front 127.0.0.1:5570` that the loopback address
    # was "not a loopback endpoint"; the views and the daemon's config say what an endpoint is
    from support.golden_corpus import DATA

    argv = [a.format(tmp=tmp_path, golden=DATA / "fragments.mcap") for a in command]
    r = subprocess.run([CLI, *argv], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2, r.stderr
    assert "tcp://HOST:PORT" in r.stderr and "not a loopback" not in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_version() -> None:
    from cellbridge import __version__
    assert run("--version").stdout.decode().strip() == f"cellbridge {__version__}"


def test_decode_prints_frames_and_counts_garbage(tmp_path: Path) -> None:
    frames = [Frame(5, 0, 5, i, Beacon(1, 20 + i, 2)) for i in range(3)]
    capture = tmp_path / "capture.bin"
    capture.write_bytes(b"junk" + b"".join(encode_stream(f) for f in frames) + b"\x05zz\x00")
    out = run("decode", str(capture))
    assert out.returncode == 0
    lines = [json.loads(line) for line in out.stdout.decode().splitlines()]
    assert [ln["payload"]["path_etx"] for ln in lines] == [20, 21, 22]
    assert all(ln["type"] == "BEACON" for ln in lines)
    counters = json.loads(out.stderr.decode().strip().splitlines()[-1])
    assert counters["stream"]["frames_ok"] == 3
    assert sum(counters["stream"]["frames_dropped"].values()) == 2  # leading junk and the bad COBS tail


def test_decode_read_by_head_ends_quietly(tmp_path: Path) -> None:
    """`cellbridge decode capture.bin | head` (the README's) and the same of a recording
    ended in a BrokenPipeError traceback, or '[Errno 32] Broken pipe' and status 1: a reader
    that goes away is the end of the output, status 0, nothing on stderr about it."""
    frames = [Frame(5, 0, 5, i % 65536, Beacon(1, 20, 2)) for i in range(3000)]  # more than a pipe holds
    capture = tmp_path / "capture.bin"
    capture.write_bytes(b"".join(encode_stream(f) for f in frames))
    golden = Path(__file__).parent / "data" / "golden" / "bridge_reset.mcap"
    for source in (capture, golden):
        proc = subprocess.Popen([CLI, "decode", str(source), "--topics", "all"] if source == golden
                                else [CLI, "decode", str(source)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
        try:
            assert proc.stdout is not None and proc.stdout.readline().startswith(b"{")
            proc.stdout.close()  # as head does after its lines
            _, err = proc.communicate(timeout=60)
        finally:
            proc.kill()
            proc.wait()
        assert proc.returncode == 0 and b"Traceback" not in err and b"Broken pipe" not in err, (source, err)


def test_decode_hex_from_stdin() -> None:
    frame = Frame(5, 0, 5, 1, Beacon(1, 20, 2))
    out = run("decode", "--hex", "-", stdin=encode_stream(frame).hex(" ").encode())
    assert out.returncode == 0 and json.loads(out.stdout)["seq"] == 1


def test_decode_shows_version_2_fields_and_reads_version_1(tmp_path: Path) -> None:
    data = Frame(7, 0, 7, 3, Data(Mode.COUNTER, (Sample(0, 10**6, 19600, 15800, SampleFlags.NO_MESH_TIME, 17),), 1, 100))
    beacon = Frame(3, 0xFFFF, 3, 4, Beacon(1, 35, 2, MeshTime(1, 812, 2_250_000_000)))
    hello = Frame(5, 0, 5, 0, Hello(5, "0.1.0", 0.04, 0.08, 0.04, 50_000_000, 3, 12))
    old = Frame(7, 0, 7, 5, Data(Mode.COUNTER, (Sample(0, 2 * 10**6, 19601, 15801, 0, 99),), 1, 100))
    capture = tmp_path / "capture.bin"
    capture.write_bytes(b"".join(encode_stream(f) for f in (data, beacon, hello)) + b"\x00"
                        + cobs.encode(encode_v1(old)) + b"\x00")
    out = run("decode", str(capture))
    assert out.returncode == 0, out.stderr
    d, b, h, v1 = (json.loads(line)["payload"] for line in out.stdout.decode().splitlines())
    assert d["rate"] == 100 and d["samples"] == [[0, 10**6, 19600, 15800, 4, 17]]
    assert b["time"] == {"root": 1, "seq": 812, "time": 2_250_000_000}
    assert h["boots"] == 12
    assert v1["rate"] == 0 and v1["samples"] == [[0, 2 * 10**6, 19601, 15801, 4, 0]]  # version 1: defaults
    assert b"index" in run("decode", "--help").stdout


def test_decode_prints_readout_records_parts_and_fragments(tmp_path: Path) -> None:
    """A READOUT prints as one JSON line per frame (each part of a record its own line), a
    fragmented record once reassembled, and a READOUT in a version 3 frame is dropped as an
    unknown type, counted."""
    part0 = Frame(2, 0, 2, 90, Readout(4600, 100, Mode.COUNTER, 1, (ReadoutSample(2, 19600, 15800),), (5,), (),
                                       2840, 0, 2))
    part1 = Frame(2, 0, 2, 91, Readout(4600, 100, Mode.ADC, 16, (ReadoutSample(9, 2272, 1968, 1),), (), (10,),
                                       2840, 1, 2))
    big = Frame(1, 0, 1, 7, Readout(4601, 100, Mode.COUNTER, 1,
                                    tuple(ReadoutSample(b, 19600 + b, 15800) for b in range(1, 65)), span_us=5200))
    pieces = fragment(big, tag=3)
    assert len(pieces) == 3
    capture = tmp_path / "readout.bin"
    capture.write_bytes(b"".join(encode_stream(f) for f in (part0, part1, *pieces))
                        + b"\x00" + cobs.encode(encode_v3(part0)) + b"\x00")
    out = run("decode", str(capture))
    assert out.returncode == 0, out.stderr
    lines = [json.loads(line) for line in out.stdout.decode().splitlines()]
    assert [ln["type"] for ln in lines] == ["READOUT"] * 3
    assert lines[0]["payload"] == {"index": 4600, "rate": 100, "mode": 0, "oversampling": 1,
                                   "samples": [[2, 19600, 15800, 0]], "unchanged": [5], "missing": [],
                                   "span_us": 2840, "part": 0, "parts": 2, "root": 0, "age_us": 0, "ref_step": 0}
    assert lines[1]["payload"]["samples"] == [[9, 2272, 1968, 1]] and lines[1]["payload"]["missing"] == [10]
    assert lines[2]["seq"] == 7 and len(lines[2]["payload"]["samples"]) == 64  # reassembled from 3 fragments
    counters = json.loads(out.stderr.decode().strip().splitlines()[-1])
    assert counters["stream"]["frames_dropped"] == {"type": 1}  # the version 3 READOUT
    assert counters["reassembly"]["completed"] == 1
    assert b"READOUT" in run("decode", "--help").stdout


@pytest.mark.parametrize("topics", ["bogus", "contacts", "contact,helth"])
def test_decode_refuses_a_topic_the_daemon_has_not(topics: str) -> None:
    # `decode rec.mcap --topics contacts` (a typo) printed the frames and never a contact,
    # without a word: `cellbridge sub` and `record` refuse a topic no topic is
    from support.golden_corpus import DATA

    r = run("decode", str(DATA / "fragments.mcap"), "--topics", topics)
    assert r.returncode == 2 and r.stdout == b"", r.stderr
    assert b"--topics" in r.stderr and b"contact, element" in r.stderr and b"Traceback" not in r.stderr, r.stderr


def test_decode_topics_all_prints_every_topic_recorded() -> None:
    # `--topics all` (as `record --topics all`) was taken for a topic named 'all': no message printed
    from support.golden_corpus import DATA

    r = run("decode", str(DATA / "fragments.mcap"), "--run", "--topics", "all")
    assert r.returncode == 0, r.stderr
    outs = {json.loads(line)["out"] for line in r.stdout.splitlines() if b'"out"' in line}
    assert outs == {"contact", "element", "raw", "health", "topology"}, outs


def test_decode_bad_input_gives_clear_errors(tmp_path: Path) -> None:
    missing = run("decode", str(tmp_path / "nope.bin"))
    assert missing.returncode == 2 and b"cannot read" in missing.stderr and b"Traceback" not in missing.stderr
    bad_hex = run("decode", "--hex", "-", stdin=b"zz")
    assert bad_hex.returncode == 2 and b"not hexadecimal" in bad_hex.stderr


@pytest.mark.parametrize("command", [["info"], ["info", "--json"], ["decode"], ["replay", "--fast"],
                                     ["robot", "score"]])
def test_a_missing_file_is_a_usage_error_of_every_command_that_reads_one(tmp_path: Path, command: list[str]) -> None:
    # `info` exited 1 for a file that is not there, where decode, replay and robot score exit 2
    # (1 is a file that is there but damaged)
    missing = tmp_path / "nope.mcap"
    r = run(*command, str(missing))
    assert r.returncode == 2, (command, r.returncode, r.stderr)
    said = r.stderr.decode()
    assert str(missing) in said and "Traceback" not in said and r.stdout == b"", said


def test_info_of_a_missing_file_among_good_ones_still_summarises_the_good_ones(tmp_path: Path) -> None:
    from support.golden_corpus import DATA

    r = run("info", str(tmp_path / "nope.mcap"), str(DATA / "fragments.mcap"))
    assert r.returncode == 2 and b"fragments.mcap" in r.stdout, r.stderr
