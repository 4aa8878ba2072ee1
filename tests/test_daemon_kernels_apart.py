"""Kernels missing from numba's cache are compiled in a child, and the process only loads them.

A long-running process that compiles keeps LLVM's memory for its life (the humanoid's daemon
and contact worker each about 100 MiB larger after a first start on a fresh installation), so
the daemon's warm-ups compile apart (:mod:`cellbridge.daemon.shell.kernels`). Each case runs
in a fresh Python with its own empty cache folder: the calibrator's step (the smallest of the
daemon's kernel sets, about 10 s to compile) compiled in place, and apart.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from support.numba_cache import run_with_cache

SCRIPT = r"""
import sys
from cellbridge.daemon.shell import kernels
from cellbridge.tactile import _jit, calibration_kernel

def mine():
    return [n for n in _jit.missing_from_cache() if n.startswith("cellbridge.tactile.calibration_kernel.")]

def status(key):
    for line in open("/proc/self/status"):
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024

print("missing_before", len(mine()))
if sys.argv[1] == "apart":
    try:
        kernels.compile_apart("no colon")
    except ValueError:
        print("refused True")
    print("failed_child", kernels.compile_apart("cellbridge.no_such_module:warm_up"))
    print("apart", kernels.compile_apart("cellbridge.tactile.calibration_kernel:warm_up"))
    print("missing_after_child", len(mine()))
rss = status("VmRSS")
calibration_kernel.warm_up()
print("grew", status("VmHWM") - rss)
print("missing_end", len(mine()))
"""


def _run(mode: str, cache: Path) -> dict[str, str]:
    return run_with_cache(SCRIPT, mode, cache)


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, str]]:
    in_place, apart = tmp_path_factory.mktemp("in_place"), tmp_path_factory.mktemp("apart")
    return {"in place": _run("in", in_place), "apart": _run("apart", apart), "again": _run("apart", apart)}


def test_missing_kernels_are_compiled_in_a_child_and_loaded_from_the_cache(runs: dict[str, dict[str, str]]) -> None:
    a = runs["apart"]
    assert int(a["missing_before"]) > 0  # an empty cache: the kernels are named missing
    assert a["apart"] == "True" and a["missing_after_child"] == "0"  # the child filled the cache
    assert a["missing_end"] == "0"


def test_the_process_that_loads_grows_far_less_than_the_one_that_compiles(runs: dict[str, dict[str, str]]) -> None:
    in_place, apart = float(runs["in place"]["grew"]), float(runs["apart"]["grew"])
    assert in_place - apart > 50, (in_place, apart)  # MiB (about 150 against 50 here)


def test_a_full_cache_starts_no_child(runs: dict[str, dict[str, str]]) -> None:
    again = runs["again"]
    assert again["missing_before"] == "0"
    assert again["apart"] == "False" and again["failed_child"] == "False"  # nothing missing: nothing run


def test_a_bad_target_is_refused_and_a_failing_child_leaves_the_compile_to_the_caller(
        runs: dict[str, dict[str, str]]) -> None:
    a = runs["apart"]
    assert a["refused"] == "True"
    assert a["failed_child"] == "False"
    assert int(runs["in place"]["missing_before"]) > 0 and runs["in place"]["missing_end"] == "0"


ORPHAN = r"""
import sys
from cellbridge.daemon.shell import kernels
from cellbridge.tactile import calibration_kernel  # (its kernels missing: the child is started)
print("started", flush=True)
kernels.compile_apart("slow_warm_up:warm")
"""

SLOW = """
import os, time
def warm():
    open(os.environ["CHILD_PID_FILE"], "w").write(str(os.getpid()))
    time.sleep(120)
"""


def test_a_child_whose_caller_is_killed_ends_itself(tmp_path: Path) -> None:
    (tmp_path / "slow_warm_up.py").write_text(SLOW)
    pid_file = tmp_path / "child.pid"
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), CHILD_PID_FILE=str(pid_file),
               PYTHONPATH=os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    env.pop("NUMBA_CACHE_LOCATOR_CLASSES", None)
    caller = subprocess.Popen([sys.executable, "-c", ORPHAN], env=env, stdout=subprocess.PIPE, start_new_session=True)
    child = 0
    try:
        deadline = time.monotonic() + 60
        while not pid_file.exists() or not pid_file.read_text():
            assert time.monotonic() < deadline and caller.poll() is None, "the child never started"
            time.sleep(0.05)
        child = int(pid_file.read_text())
        caller.kill()  # alone: its child is not signalled
        caller.wait(10)
        deadline = time.monotonic() + 5
        while _alive(child):
            assert time.monotonic() < deadline, "the child compiled on after its caller was killed"
            time.sleep(0.05)
    finally:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(caller.pid, signal.SIGKILL)
        caller.wait(10)
        if caller.stdout is not None:
            caller.stdout.close()


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, reaped by init soon, counts as ended)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


WHERE_FROM = """
import os
def warm():
    import cellbridge
    open(os.environ["WHERE_FILE"], "w").write(cellbridge.__file__)
"""

CALLER = r"""
import cellbridge
from cellbridge.daemon.shell import kernels
from cellbridge.tactile import calibration_kernel  # (its kernels missing: the child is started)
print("apart", kernels.compile_apart("where_from:warm"))
print("caller", cellbridge.__file__)
"""


def test_the_child_imports_the_package_its_caller_runs(tmp_path: Path) -> None:
    # the daemon's command (a console script) started where a folder holds another
    # `cellbridge` package (a checkout's, another version's): the child, a `python -c`, put
    # the working folder first on its path and imported that one, not the caller's
    (tmp_path / "tools").mkdir()
    (tmp_path / "tools" / "where_from.py").write_text(WHERE_FROM)
    (tmp_path / "tools" / "caller.py").write_text(CALLER)
    (tmp_path / "checkout" / "cellbridge").mkdir(parents=True)
    (tmp_path / "checkout" / "cellbridge" / "__init__.py").write_text("raise ImportError('another cellbridge')\n")
    where = tmp_path / "where"
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), WHERE_FILE=str(where),
               PYTHONPATH=os.pathsep.join(p for p in [str(tmp_path / "tools"), os.environ.get("PYTHONPATH")] if p))
    env.pop("NUMBA_CACHE_LOCATOR_CLASSES", None)
    r = subprocess.run([sys.executable, str(tmp_path / "tools" / "caller.py")], cwd=tmp_path / "checkout", env=env,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr[-2000:]
    got = dict(line.split(" ", 1) for line in r.stdout.splitlines())
    assert got["apart"] == "True" and where.read_text() == got["caller"]


NO_JIT = r"""
from cellbridge.daemon.shell import kernels
from cellbridge.tactile import _jit, calibration_kernel
print("missing", ",".join(_jit.missing_from_cache()) or "-")
print("apart", kernels.compile_apart("cellbridge.tactile.calibration_kernel:warm_up"))
kernels.warm_up()
print("warm True")
"""


def test_with_numba_s_jit_disabled_nothing_is_missing_and_the_worker_warms_up(tmp_path: Path) -> None:
    # NUMBA_DISABLE_JIT (numba's switch to step through the kernels as Python) makes the
    # decorator return the function itself: missing_from_cache raised on it (no py_func),
    # and the contact worker's warm-up with it
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), NUMBA_DISABLE_JIT="1")
    env.pop("NUMBA_CACHE_LOCATOR_CLASSES", None)
    r = subprocess.run([sys.executable, "-c", NO_JIT], env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    got = dict(line.split(" ", 1) for line in r.stdout.splitlines())
    assert got == {"missing": "-", "apart": "False", "warm": "True"}
