"""`make test` stopped with Ctrl-C stops the kernels' warm-up it started beside lint.

The recipe runs the warm-up as a background job of its shell. A non-interactive shell starts
a background job with SIGINT ignored (POSIX), so the terminal's Ctrl-C, sent to the whole
foreground group, stopped make and lint but not the warm-up: it went on compiling the
kernels for its half minute or more, a core taken after the user had stopped the suite.

The recipe is run here as make runs it (its shell, its job), in a makefile of its own with
a stand-in for the Python that only records its pid and waits, and a lint that waits: a
test of the recipe's signals, not of the warm-up or lint themselves.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

STANDIN = """#!/bin/sh
# the warm-up records its pid and waits; the suite records that it ran
case "$1" in
  tests/support/warm_kernels.py) echo $$ > warm.pid; exec sleep 300 ;;
  -m) touch suite.ran ;;
esac
"""


def _recipe() -> str:
    """The `test` target's recipe lines, as the Makefile has them."""
    lines = (ROOT / "Makefile").read_text().splitlines()
    start = next(i for i, ln in enumerate(lines) if re.match(r"test:", ln))
    recipe = []
    for ln in lines[start + 1:]:
        if not ln.startswith("\t"):
            break
        recipe.append(ln)
    return "\n".join(recipe)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # (a zombie is gone for our purpose: it runs nothing)
    stat = Path(f"/proc/{pid}/stat")
    return not (stat.exists() and stat.read_text().rsplit(")", 1)[1].split()[0] == "Z")


def _default_signals() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGQUIT, signal.SIG_DFL)


@pytest.mark.skipif(shutil.which("make") is None or shutil.which("pgrep") is None, reason="no make or pgrep")
def test_ctrl_c_during_lint_stops_the_warm_up_and_the_suite_does_not_start(tmp_path: Path) -> None:
    standin = tmp_path / "python"
    standin.write_text(STANDIN)
    standin.chmod(0o755)
    (tmp_path / "Makefile").write_text(f"PY := {standin}\nTEST_JOBS := 2\n\nlint:\n\t@exec sleep 300\n\n"
                                       f"test:\n{_recipe()}\n")
    make = subprocess.Popen(["make", "--no-print-directory", "test"], cwd=tmp_path, start_new_session=True,
                            preexec_fn=_default_signals, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    warm = None
    try:
        pid_file = tmp_path / "warm.pid"
        for _ in range(600):  # (until the warm-up and lint run: a hang guard, not a timing)
            if pid_file.exists() and pid_file.read_text().strip() and \
                    subprocess.run(["pgrep", "-g", str(make.pid), "-x", "sleep"], capture_output=True,
                                   text=True).stdout.count("\n") >= 2:
                break
            time.sleep(0.05)
        warm = int(pid_file.read_text())
        os.killpg(make.pid, signal.SIGINT)  # the terminal's Ctrl-C: the whole foreground group
        assert make.wait(timeout=60) != 0
        for _ in range(200):  # (the shell's kill on its way: a hang guard)
            if not _alive(warm):
                break
            time.sleep(0.05)
        assert not _alive(warm), "the warm-up went on after make test was stopped"
        assert not (tmp_path / "suite.ran").exists()
    finally:
        with_pids = [make.pid] + ([warm] if warm else [])
        for pid in with_pids:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        try:
            os.killpg(make.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        make.wait()


@pytest.mark.skipif(shutil.which("make") is None, reason="no make")
@pytest.mark.parametrize("lint, suite_runs", [("true", True), ("false", False)])
def test_the_suite_runs_after_lint_and_the_warm_up_and_not_after_a_lint_finding(
        tmp_path: Path, lint: str, suite_runs: bool) -> None:
    standin = tmp_path / "python"
    standin.write_text(STANDIN.replace("exec sleep 300", "true"))
    standin.chmod(0o755)
    (tmp_path / "Makefile").write_text(f"PY := {standin}\nTEST_JOBS := 2\n\nlint:\n\t@{lint}\n\n"
                                       f"test:\n{_recipe()}\n")
    r = subprocess.run(["make", "--no-print-directory", "test"], cwd=tmp_path, capture_output=True, timeout=60)
    assert (r.returncode == 0) is suite_runs
    assert (tmp_path / "warm.pid").exists()
    assert (tmp_path / "suite.ran").exists() is suite_runs
