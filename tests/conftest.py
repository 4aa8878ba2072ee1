"""Suite-wide settings.

Hypothesis's per-example deadline is a timed assertion: on a shared two-core machine (CI,
a laptop running the emulator) a slow example says nothing about the code, so the
deadline is off everywhere; speed is measured by the scripts in bench/.
"""

import functools
import os
from collections.abc import Callable, Iterator
from typing import Any

import pytest
from hypothesis import settings

settings.register_profile("cellbridge", deadline=None)
settings.load_profile("cellbridge")


@pytest.fixture
def warm_kernels() -> None:
    """The contact estimator's kernels in numba's cache before a test's contact worker
    needs them: on a fresh checkout its warm-up compiles them (half a minute, more on a
    loaded machine), and a test that waits for its contacts outlasts its own patience."""
    from cellbridge.demo import _warm_kernels

    _warm_kernels()


# -- the fast lane: tests that start processes or ptys are marked `process` --------------------
#
# `make test-fast` (pytest -m "not process") runs every test that stays in this process; `make
# test` runs all. A module below is marked whole (most of its tests start the daemon, the
# emulator's processes, a pty, a browser or a compiler); a test elsewhere that asks for one of
# PROCESS_FIXTURES is marked by that. The guard underneath keeps the mark honest: a test not
# marked `process` that forks, spawns or opens a pty fails, naming what it started.

#: Test modules whose tests (most or all) start processes or ptys.
PROCESS_MODULES = frozenset({
    "test_cli", "test_contact_worker_close", "test_daemon_capture", "test_daemon_config", "test_daemon_keys_cli",
    "test_daemon_limits", "test_daemon_local_access", "test_daemon_notify", "test_daemon_ops_live",
    "test_daemon_replay", "test_daemon_replay_gate", "test_daemon_service", "test_daemon_shells", "test_daemon_startup", "test_daemon_sub_cli", "test_demo",
    "test_demo_children", "test_demo_gateway", "test_emulator_mesh", "test_emulator_processes",
    "test_emulator_pty_link", "test_emulator_realtime_attack", "test_emulator_realtime_priority",
    "test_emulator_robustness", "test_examples", "test_harness_pty", "test_humanoid", "test_packaging",
    "test_plot_cli", "test_proxy", "test_recording_core", "test_recording_live", "test_recording_robust", "test_robot",
    "test_ros2_bag", "test_ros2_live", "test_skin_frames_live", "test_systemd_units", "test_tactile_kernel_cache",
    "test_tactile_lazy_kernels", "test_views_fuzz", "test_views_hostile", "test_views_live", "test_views_model",
    "test_views_robot", "test_worker_process", "test_worker_process_attacks",
})
#: Fixtures that start a process or open a pty for the test that asks for them.
PROCESS_FIXTURES = frozenset({"warm_kernels"})


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        module = getattr(item, "module", None)
        name = module.__name__.rpartition(".")[2] if module is not None else ""
        if name in PROCESS_MODULES or PROCESS_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.process)


_running: list[pytest.Item | None] = [None]  # the test whose setup, call or teardown runs now
_started: dict[str, list[str]] = {}  # test id -> what an unmarked test started


def _guarded(what: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    @functools.wraps(fn)
    def call(*args: Any, **kwargs: Any) -> Any:
        item = _running[0]
        if item is not None and item.get_closest_marker("process") is None:
            _started.setdefault(item.nodeid, []).append(what)
        return fn(*args, **kwargs)
    return call


def pytest_configure(config: pytest.Config) -> None:
    """Every way a test starts a process or a pty passes through one of these: subprocess
    and multiprocessing's spawn (fork_exec, posix_spawn), a fork (multiprocessing's fork,
    pty.fork), a pty (os.openpty, which pty.openpty calls)."""
    import _posixsubprocess
    import subprocess

    for name in ("fork", "forkpty", "openpty", "posix_spawn", "posix_spawnp"):
        if hasattr(os, name):
            setattr(os, name, _guarded(f"os.{name}", getattr(os, name)))
    _posixsubprocess.fork_exec = _guarded("fork_exec", _posixsubprocess.fork_exec)
    if getattr(subprocess, "_fork_exec", None) is not None:
        subprocess._fork_exec = _posixsubprocess.fork_exec  # type: ignore[attr-defined]


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Any:
    _running[0] = item
    try:
        return (yield)
    finally:
        _running[0] = None


@pytest.fixture(autouse=True)
def _process_mark_is_honest(request: pytest.FixtureRequest) -> Iterator[None]:
    yield
    started = _started.pop(request.node.nodeid, None)
    if started:
        pytest.fail(f"this test starts processes or ptys ({', '.join(sorted(set(started)))}) but is not marked "
                    "`process`: add its module to PROCESS_MODULES or its fixture to PROCESS_FIXTURES "
                    "(tests/conftest.py)", pytrace=False)
