"""End to end, as a user starts it: an emulated 4×4 skin in real processes, the daemon on
its gateway's pty, a press across a seam, and the contact the daemon publishes."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import shutil
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
    proc = subprocess.Popen([CLI, "demo", "--check", "--json", "--x", str(x), "--y", str(y)],
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
    got = result["reported"]
    assert abs(got["x"] - x) <= 1e-3 and abs(got["y"] - y) <= 1e-3, result
    assert abs(got["force"] - 3.0) <= 0.05 * 3.0, result
    assert len(result["ids"]) == 1, result  # one press, one tracked contact
    assert r.returncode == 0, r.stderr
    left = _left_behind(tmp_path)
    assert left == [], f"processes left behind: {left}"


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
