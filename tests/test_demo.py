"""End to end, as a user starts it: an emulated 4×4 skin in real processes, the daemon on
its gateway's pty, a press across a seam, and the contact the daemon publishes."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

CLI = shutil.which("cellbridge", path=str(Path(sys.executable).parent)) or "cellbridge"


@pytest.mark.parametrize("x, y", [(0.057, 0.040), (0.0585, 0.0625)])  # across a seam; across a corner
def test_a_press_across_a_seam_comes_back_at_that_point_with_that_force(x: float, y: float, tmp_path: Path) -> None:
    # its work folder under this test's own folder: see _left_behind
    # its own session, killed whole however the test ends: killed alone at a timeout, the
    # demo left its skin (16 bridges, medium, world) and its daemon running
    # --keep: its logs stay in this test's folder, for the failure message below
    proc = subprocess.Popen([CLI, "demo", "--check", "--json", "--keep", "--x", str(x), "--y", str(y)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            env={**os.environ, "TMPDIR": str(tmp_path)})
    try:
        out, err = proc.communicate(timeout=360)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    r = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    assert r.stdout.strip(), r.stderr
    result = json.loads(r.stdout)
    left = _left_behind(tmp_path)
    assert left == [], f"processes left behind: {left}"
    try:
        check_press_result(result, x, y, 3.0)
        if result["skin_whole"]:
            assert r.returncode == 0, r.stderr
    except AssertionError as exc:
        raise AssertionError(f"{exc}\n{_logs(tmp_path)}") from None


def _logs(root: Path) -> str:
    """The demo's daemon log (its last lines) and its skin's counters, to read a failure by."""
    out = []
    for log in sorted(root.glob("cellbridge-demo-*/daemon.log")):
        out.append("daemon.log: ..." + "".join(log.read_text(errors="replace").splitlines(True)[-40:]))
    for log in sorted(root.glob("cellbridge-demo-*/mesh.log")):
        out.append("mesh.log: ..." + log.read_text(errors="replace")[-6000:])
    return "\n".join(out)


def check_press_result(result: dict, x: float, y: float, force: float) -> None:
    """What a demo's press must show, whatever the machine's load.

    Never a confident untruth: no report states a position off the press by more than
    1 mm and 3 of its σ without listing the unknown elements that leave it open. When the
    skin delivered every frame of the press whole, the press comes back within 1 mm and
    5 % as one contact id. The emulated skin is 18 processes at normal priority: on a busy
    machine (a laptop compiling, four CPU burners on two cores) they fall behind real time
    and records of some frames never reach the gateway, which the contact messages say
    (``unknown``). Then the reports that knew every element near them are held to 1 mm and
    5 %, and the others must only be honest; ``bench/bench_demo.py`` measures how often a
    loaded machine keeps the skin whole."""
    if result["messages"] == 0:  # no touch seen: only when the skin's readings went missing
        assert result["skin_frames"].get("unknown_element_frames", 0) > 0, result
    assert result["untrue"] == 0 and result.get("untrue_force", 0) == 0, result
    if result["skin_whole"]:
        got = result["reported"]
        assert abs(got["x"] - x) <= 1e-3 and abs(got["y"] - y) <= 1e-3, result
        assert abs(got["force"] - force) <= 0.05 * force, result
        assert len(result["ids"]) == 1, result  # one press, one tracked contact
    elif "known" in result:
        known = result["known"]
        assert abs(known["x"] - x) <= 1e-3 and abs(known["y"] - y) <= 1e-3, result
        assert abs(known["force"] - force) <= 0.05 * force, result


@pytest.mark.parametrize("result, ok", [
    ({"messages": 10, "untrue": 0, "skin_whole": True, "ids": [0],
      "reported": {"x": 0.057, "y": 0.04, "force": 3.0}}, True),
    ({"messages": 10, "untrue": 0, "skin_whole": True, "ids": [0, 1],  # a press split in two ids
      "reported": {"x": 0.057, "y": 0.04, "force": 3.0}}, False),
    ({"messages": 10, "untrue": 0, "skin_whole": True, "ids": [0],  # 2 mm off with the skin whole
      "reported": {"x": 0.059, "y": 0.04, "force": 3.0}}, False),
    ({"messages": 10, "untrue": 1, "skin_whole": False, "ids": [0],  # a precise wrong report
      "reported": {"x": 0.07, "y": 0.04, "force": 2.0}}, False),
    ({"messages": 10, "untrue": 0, "untrue_force": 2, "skin_whole": False, "ids": [0],  # a precise wrong force
      "reported": {"x": 0.057, "y": 0.04, "force": 2.0}}, False),
    ({"messages": 10, "untrue": 0, "skin_whole": False, "ids": [0],  # honest, known reports right
      "reported": {"x": 0.07, "y": 0.04, "force": 2.0}, "known": {"x": 0.057, "y": 0.04, "force": 3.05}}, True),
    ({"messages": 10, "untrue": 0, "skin_whole": False, "ids": [0],  # known reports wrong
      "reported": {"x": 0.057, "y": 0.04, "force": 3.0}, "known": {"x": 0.057, "y": 0.04, "force": 2.5}}, False),
    ({"messages": 0, "untrue": 0, "skin_whole": False,  # nothing published, the skin whole
      "skin_frames": {"frames_complete": 300, "unknown_element_frames": 0}}, False),
    ({"messages": 0, "untrue": 0, "skin_whole": False,  # nothing published, the skin starved
      "skin_frames": {"frames_complete": 100, "unknown_element_frames": 900}}, True),
])
def test_the_press_check_holds_the_known_reports_to_the_press_and_the_rest_to_honesty(result: dict, ok: bool) -> None:
    try:
        check_press_result(result, 0.057, 0.040, 3.0)
    except AssertionError:
        assert not ok
    else:
        assert ok


def _left_behind(root: Path) -> list[str]:
    """Command lines of processes naming a demo's work folder made under ``root`` (the
    demo's TMPDIR). ``make test`` runs two pytest-xdist workers: any demo's work folder
    (``pgrep -af cellbridge-demo-``) also found the one the other worker's demo was running
    in, and this test failed on processes that were not its own."""
    mark = f"{root}{os.sep}cellbridge-demo-"
    found = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit() or int(pid) == os.getpid():
            continue
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if mark in cmd:
            found.append(f"{pid} {cmd}")
    return found


def test_a_demo_running_beside_this_one_is_not_left_behind_by_it(tmp_path: Path) -> None:
    """The other xdist worker runs the other demo at the same time: its processes, in a work
    folder of its own, are not this test's leftovers; one naming this test's are."""
    beside = tmp_path / "other-worker" / "cellbridge-demo-x1" / "skin.toml"  # another demo's work folder
    mine = tmp_path / "mine"
    sleeper = [sys.executable, "-c", "import time; time.sleep(30)"]
    procs = [subprocess.Popen([*sleeper, str(beside)]), subprocess.Popen([*sleeper, str(mine / "cellbridge-demo-y2")])]
    try:
        for p in procs:  # until each shows its own command line (a loaded machine: not at once)
            end = time.monotonic() + 10.0
            while b"time.sleep" not in Path(f"/proc/{p.pid}/cmdline").read_bytes() and time.monotonic() < end:
                time.sleep(0.01)
        assert _left_behind(tmp_path / "other") == []
        left = _left_behind(mine)
        assert len(left) == 1 and str(procs[1].pid) == left[0].split()[0], left
    finally:
        for p in procs:
            p.kill()
            p.wait()


def test_the_demo_starts_its_daemon_again_on_other_ports_when_one_was_taken(
        warm_kernels: None, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
        tmp_path: Path) -> None:
    """The demo chooses free ports and its daemon binds them seconds later: on a busy machine
    (a test suite beside it) another program took one meanwhile, and the demo ended with
    'daemon ended with status 1 during start-up'. It starts the daemon again on other ports."""
    import argparse
    import socket
    import tempfile

    from cellbridge import demo

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))  # its work folder, kept, in this test's

    taken = socket.socket()
    taken.bind(("127.0.0.1", demo._free_port()))
    taken.listen()
    ports = iter([taken.getsockname()[1]])
    real = demo._free_port
    monkeypatch.setattr(demo, "_free_port", lambda: next(ports, None) or real())
    parser = argparse.ArgumentParser()
    demo.add_arguments(parser)
    args = parser.parse_args(["--check", "--json", "--keep", "--x", "0.057", "--y", "0.040"])
    try:
        code = demo.run(args)
    finally:
        taken.close()
    out = capsys.readouterr().out
    assert out.strip(), "no result"
    result = json.loads(out)
    check_press_result(result, 0.057, 0.040, 3.0)
    # 1 only when the check failed, which a loaded machine may cause only by keeping the
    # skin's frames from arriving whole (said in the messages; check_press_result holds
    # such a press to honesty, not to 1 mm): the retry on other ports is this test's point
    assert code in (0, 1), (code, result)
    if result["skin_whole"]:
        assert code == 0, result
    (log,) = tmp_path.glob("cellbridge-demo-*/daemon.log")
    assert result["kept"] == str(log.parent)  # --keep with --json: where the folder is, in the result
    text = log.read_text()
    assert text.count("cannot bind") == 1 and "Address already in use" in text  # the first daemon's
    assert _left_behind(tmp_path) == []


@pytest.mark.parametrize(("args", "says"), [
    (["--x", "5"], "press: a 0.02 m contact at (5.0, 0.04) touches no element"),
    (["--force", "-1"], "press.force: must be a number > 0.0, got -1.0"),
    (["--duration", "0"], "press.duration: must be a number > 0.0, got 0.0"),
    (["--rows", "0"], "grid: rows and cols must be >= 1"),
])
def test_a_press_or_skin_the_demo_cannot_make_is_refused_before_anything_starts(args: list[str], says: str) -> None:
    """`cellbridge demo --x 5` (millimetres for metres) or `--force -1` booted the skin and the
    daemon, waited for calibration, and only then had the press refused; `--rows 0` was a
    traceback. Each is said at once, exit 2, and nothing was started."""
    r = subprocess.run([CLI, "demo", *args], capture_output=True, text=True, timeout=60, start_new_session=True)
    assert r.returncode == 2 and r.stderr.startswith(f"cellbridge demo: {says}"), r.stderr
    assert "starting" not in r.stderr and "Traceback" not in r.stderr and r.stdout == ""
