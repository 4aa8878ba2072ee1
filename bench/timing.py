"""Timing helpers shared by the benchmark scripts (imported as ``timing`` when a
script in bench/ runs, since Python puts the script's folder first on sys.path)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
import tomllib
from collections.abc import Callable, Sequence
from pathlib import Path


def pin_to_one_core() -> None:
    """Run on one core, so figures read as "per core" and do not depend on idle siblings."""
    try:
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    except (AttributeError, OSError):
        pass


def fifo_every_thread(priority: int) -> None:
    """Put every thread of this process at real-time (FIFO) ``priority``.

    ``os.sched_setscheduler(0, ...)`` sets the calling thread only: threads started
    before it (ZeroMQ's I/O threads, made with the first socket) keep the priority they
    were born with, and a subscriber whose I/O thread waits behind the emulated skin's
    processes measures that wait as the daemon's latency."""
    for tid in os.listdir("/proc/self/task"):
        try:
            os.sched_setscheduler(int(tid), os.SCHED_FIFO, os.sched_param(priority))
        except ProcessLookupError:  # a thread that ended meanwhile
            pass


def warm_daemon_kernels() -> None:
    """The compiled READOUT reader and calibrator step loaded (compiled on a fresh
    installation), as the daemon has them once it runs: a pipeline measured in-process
    without them steps with numpy and parses records in Python, the daemon's path only in
    its first seconds."""
    from cellbridge.daemon.core import readout_columns
    from cellbridge.tactile import calibration_kernel

    readout_columns.warm_up()
    calibration_kernel.warm_up()


def best_rate(fn: Callable[[], object], n: int, repeats: int = 3) -> float:
    """Items per second of ``fn`` processing ``n`` items, best of ``repeats`` runs
    (the best run is the one least disturbed by the rest of the machine)."""
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return n / best


def row(cells: Sequence[object], widths: list[int]) -> str:
    """One table line: first column left-aligned, the others right-aligned."""
    return "  ".join(str(c).rjust(w) if i else str(c).ljust(w) for i, (c, w) in enumerate(zip(cells, widths)))


def table(title: str, head: Sequence[str], rows: Sequence[Sequence[object]]) -> None:
    """Print a titled table with a dashed rule under the header."""
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    print(f"\n{title}")
    print(row(head, widths))
    print(row(["-" * w for w in widths], widths))
    for r in rows:
        print(row(r, widths))


# ----------------------------------------------------------------- another git revision

#: Runs a script on a source tree given as argv[1] instead of the installed package: the
#: editable install's finder (consulted before the import path) is taken away.
_AT_REVISION = """
import os, runpy, sys
tree, script = sys.argv[1], os.path.abspath(sys.argv[2])
sys.meta_path[:] = [f for f in sys.meta_path if 'editable' not in repr(f).lower()]
sys.path[:0] = [tree, os.path.dirname(script)]  # first: the revision's package wins over any other
sys.argv = sys.argv[2:]
runpy.run_path(script, run_name='__main__')
"""

def revision_tree(rev: str, root: Path, into: Path) -> Path:
    """The package of git revision ``rev`` of the repository at ``root``, laid out under
    ``into`` as an install would (``[tool.setuptools.package-dir]``): a folder to put first
    on the import path. Raises CalledProcessError for an unknown revision."""
    src = into / "src"
    src.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(root), "archive", rev], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(src)], input=archive, check=True)
    dirs = tomllib.loads((src / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    tree = into / "tree"
    for package, folder in sorted(dirs.items()):
        target = tree.joinpath(*package.split("."))
        if "." in package:
            target.symlink_to(src / folder, target_is_directory=True)
        else:
            shutil.copytree(src / folder, target)
    return tree


def run_at_revision(tree: Path, script: str, args: list[str], data: bytes) -> bytes:
    """stdout of ``script args`` run on ``tree`` (see :func:`revision_tree`), ``data`` on its stdin."""
    out = subprocess.run([sys.executable, "-c", _AT_REVISION, str(tree), script, *args], input=data,
                         capture_output=True, check=False, timeout=3600)
    if out.returncode:
        raise RuntimeError(f"{script} at the revision failed:\n{out.stderr.decode(errors='replace')[-2000:]}")
    return out.stdout
