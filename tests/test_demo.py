"""End to end, as a user starts it: an emulated 4×4 skin in real processes, the daemon on
its gateway's pty, a press across a seam, and the contact the daemon publishes."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

CLI = shutil.which("cellbridge", path=str(Path(sys.executable).parent)) or "cellbridge"


@pytest.mark.parametrize("x, y", [(0.057, 0.040), (0.0585, 0.0625)])  # across a seam; across a corner
def test_a_press_across_a_seam_comes_back_at_that_point_with_that_force(x: float, y: float, tmp_path: Path) -> None:
    # The demo's work folder goes under this test's own tmp_path (TMPDIR): the check for
    # processes left behind looks for this run's alone, not for another demo running on
    # the machine (the other case on a second pytest-xdist worker)
    r = subprocess.run([CLI, "demo", "--check", "--json", "--x", str(x), "--y", str(y)],
                       capture_output=True, text=True, timeout=280, env={**os.environ, "TMPDIR": str(tmp_path)})
    assert r.stdout.strip(), r.stderr
    result = json.loads(r.stdout)
    got = result["reported"]
    assert abs(got["x"] - x) <= 1e-3 and abs(got["y"] - y) <= 1e-3, result
    assert abs(got["force"] - 3.0) <= 0.05 * 3.0, result
    assert len(result["ids"]) == 1, result  # one press, one tracked contact
    assert r.returncode == 0, r.stderr
    left = subprocess.run(["pgrep", "-af", f"{tmp_path}/cellbridge-demo-"], capture_output=True, text=True)  # its work folder
    assert left.stdout == "", f"processes left behind: {left.stdout}"
