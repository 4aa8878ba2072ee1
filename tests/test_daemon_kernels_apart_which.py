"""The daemon's warm-ups compile apart the kernels they load, and only where those are missing.

:mod:`cellbridge.daemon.shell.kernels` starts a child to compile a warm-up's kernels when the
cache lacks them. The daemon's process makes the contact estimator's kernels at import (they
are its worker's to compile and load), the READOUT reader's only at its warm-up, and the
calibrator's at its import in the warm-up thread. Each case runs the daemon's own warm-up
(``Service._warm_calibration``) in a fresh Python on one cache folder, first filled with the
reader and the calibrator's step alone, as a daemon with contacts disabled leaves it.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from support.numba_cache import run_with_cache

SCRIPT = r"""
import logging, sys, threading, types
from cellbridge.daemon.shell import kernels, service
from cellbridge.daemon.core import readout_columns
from cellbridge.tactile import _jit

if sys.argv[1] == "fill":  # the reader and the calibrator's step compiled in place, nothing else
    from cellbridge.tactile import calibration_kernel
    readout_columns.warm_up()
    calibration_kernel.warm_up()
    sys.exit(0)
if sys.argv[1] == "worker_cached":  # as if the kernels made so far (the worker's) were in the cache
    _jit._CACHED.clear()
run = kernels.subprocess.run
children = []
def counted(args, **kw):
    children.append(args[-1].rsplit("import_module(", 1)[1].split(")")[0])
    return run(args, **kw)
kernels.subprocess.run = counted
service.Service._warm_calibration(types.SimpleNamespace(log=logging.getLogger("t")), threading.Event())
from cellbridge.tactile import calibration_kernel
print("children", ",".join(children) or "-")
print("compiled_here", sum(len(d.stats.cache_misses) for d in _jit._CACHED))  # (any kernel of the process)
print("loaded", sum(len(d.stats.cache_hits) for d in (*readout_columns._PARSE, calibration_kernel.step)))
"""


def _run(mode: str, cache: Path) -> dict[str, str]:
    return run_with_cache(SCRIPT, mode, cache)


@pytest.fixture(scope="module")
def cache(tmp_path_factory: pytest.TempPathFactory) -> Path:
    folder = tmp_path_factory.mktemp("cache")
    _run("fill", folder)
    return folder


def test_a_warm_cache_starts_no_child_though_the_contact_kernels_are_not_in_it(cache: Path) -> None:
    # the estimator's kernels, made by the daemon's imports, are not the daemon's to load: a
    # daemon without contacts (no worker ever compiles them) started two children at every start
    got = _run("daemon", cache)
    assert got["children"] == "-"
    assert got["compiled_here"] == "0" and got["loaded"] == "2"


def test_the_reader_missing_alone_is_compiled_apart_and_loaded(cache: Path) -> None:
    # the reader's kernels are made at its warm-up: asked before, the cache seemed full, and
    # the daemon compiled the reader in its own process
    for f in list(cache.rglob("readout_columns.*")):
        f.unlink()
    got = _run("worker_cached", cache)
    assert got["children"] == "'cellbridge.daemon.core.readout_columns'"
    assert got["compiled_here"] == "0" and got["loaded"] == "2"


READ_WHILE_APART = r"""
import logging, sys, threading, types
from cellbridge.daemon.shell import kernels, service
from cellbridge.daemon.core import readout_columns
from cellbridge.daemon.core.readout_columns import Readout, ReadoutSample, Mode
from cellbridge.protocol.messages import pack_payload

RECORD = pack_payload(Readout(1, 100, Mode.COUNTER, 1, (ReadoutSample(1, 2, 3, 0),), (2,), (3,), 10, 0, 1, 1, 1))

def apart(target, limit=0.0, modules=()):
    if "readout_columns" in target:  # a record comes while the child compiles the reader
        print("read_meanwhile", readout_columns.readout_columns(RECORD) is not None)
        print("compiled_meanwhile", sum(len(d.stats.cache_misses) for d in readout_columns._PARSE))
        return False  # (no child here: the warm-up compiles in place)
    print("read_after", readout_columns.readout_columns(RECORD) is not None)
    sys.exit(0)  # (not the calibrator's)
kernels.compile_apart = apart
service.Service._warm_calibration(types.SimpleNamespace(log=logging.getLogger("t")), threading.Event())
"""


def test_a_record_while_the_reader_compiles_apart_is_read_plainly_not_compiled_in_the_daemon(tmp_path: Path) -> None:
    # the daemon waits for its warm-ups a few seconds at most (CALIBRATION_WARM_LIMIT), and a child
    # compiling the reader took longer (a Python's start, then 4 s of compiling; 11 s with two
    # daemons starting): the first READOUT record after the links started compiled the reader on
    # the event loop, in the daemon's process
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    env.pop("NUMBA_CACHE_LOCATOR_CLASSES", None)
    r = subprocess.run([sys.executable, "-c", READ_WHILE_APART], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    got = dict(line.split(" ", 1) for line in r.stdout.splitlines())
    assert got == {"read_meanwhile": "False", "compiled_meanwhile": "0", "read_after": "True"}
