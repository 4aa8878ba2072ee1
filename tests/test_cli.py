"""The installed ``cellbridge`` command, run as a real process."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

from cellbridge.protocol import Beacon, Frame, encode_stream

CLI = shutil.which("cellbridge", path=str(Path(sys.executable).parent)) or "cellbridge"


def run(*args: str, stdin: bytes = b"") -> subprocess.CompletedProcess[bytes]:
    return subprocess.run([CLI, *args], input=stdin, capture_output=True, timeout=60)


def test_help_lists_subcommands() -> None:
    out = run("--help")
    assert out.returncode == 0
    assert b"decode" in out.stdout


def test_internal_entry_points_run_but_stay_out_of_the_top_level_help() -> None:
    listed = run("--help").stdout.decode()
    for name in ("bridge", "medium", "world"):  # started by 'mesh up', not by people
        assert f"    {name} " not in listed
        out = run(name, "--help")
        assert out.returncode == 0 and f"cellbridge {name}" in out.stdout.decode()
    assert "    mesh " in listed and "    daemon " in listed


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


def test_decode_hex_from_stdin() -> None:
    frame = Frame(5, 0, 5, 1, Beacon(1, 20, 2))
    out = run("decode", "--hex", "-", stdin=encode_stream(frame).hex(" ").encode())
    assert out.returncode == 0 and json.loads(out.stdout)["seq"] == 1


def test_decode_bad_input_gives_clear_errors(tmp_path: Path) -> None:
    missing = run("decode", str(tmp_path / "nope.bin"))
    assert missing.returncode == 2 and b"cannot read" in missing.stderr and b"Traceback" not in missing.stderr
    bad_hex = run("decode", "--hex", "-", stdin=b"zz")
    assert bad_hex.returncode == 2 and b"not hexadecimal" in bad_hex.stderr
