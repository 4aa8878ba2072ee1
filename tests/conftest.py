"""Suite-wide settings.

Hypothesis's per-example deadline is a timed assertion: on a shared two-core machine (CI,
a laptop running the emulator) a slow example says nothing about the code, so the
deadline is off everywhere; speed is measured by the scripts in bench/.

Three guards run around every test: one fails a test that starts a process or a pty without
the ``process`` mark, one a test whose event loop closes with tasks still pending, and one
a test module that leaves a process of its own running after its last test.
"""

import asyncio
import contextlib
import functools
import os
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path
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
    "test_cli", "test_contact_warm_up_kernels", "test_daemon_kernels_apart", "test_daemon_kernels_apart_which", "test_contact_worker_close", "test_contact_worker_gc", "test_daemon_capture", "test_daemon_config", "test_daemon_keys_cli",
    "test_daemon_limits", "test_daemon_local_access", "test_daemon_notify", "test_daemon_ops_live",
    "test_daemon_replay", "test_daemon_replay_gate", "test_daemon_serial_link", "test_daemon_service", "test_daemon_shells", "test_daemon_startup", "test_daemon_sub_cli", "test_demo",
    "test_demo_children", "test_demo_gateway", "test_make_test_stop", "test_emulator_mesh", "test_emulator_readout_load", "test_emulator_processes",
    "test_emulator_pty_link", "test_emulator_realtime_attack", "test_emulator_realtime_priority",
    "test_emulator_robustness", "test_examples", "test_harness_pty", "test_humanoid", "test_packaging",
    "test_plot_cli", "test_process_guard", "test_proxy", "test_recording_core", "test_recording_live", "test_recording_robust", "test_robot",
    "test_ros2_bag", "test_ros2_hostile", "test_ros2_live", "test_skin_frames_live", "test_systemd_units", "test_tactile_kernel_cache", "test_tactile_kernel_cache_cut", "test_tactile_kernel_cache_sources",
    "test_tactile_lazy_kernels", "test_views_fuzz", "test_views_hostile", "test_views_live", "test_views_model",
    "test_views_robot", "test_worker_process", "test_worker_process_attacks",
})
#: Fixtures that start a process or open a pty for the test that asks for them.
PROCESS_FIXTURES = frozenset({"warm_kernels"})


#: `slow`: seconds of CPU each (long virtual-time runs of a whole mesh, hours of simulated
#: drift, large property sweeps). `make test` runs them; `make test-fast` leaves them out, so
#: the in-process lane is the one to run after every edit. Modules whose tests are mostly such:
SLOW_MODULES = frozenset({
    "test_daemon_skin_frames", "test_emulator_meshtime", "test_emulator_topology", "test_daemon_frames_truth",
    "test_daemon_held_press", "test_emulator_readout", "test_skin_daemon", "test_daemon_service_offline",
    "test_emulator_lazy_attacks", "test_daemon_skin_file",
})
#: ... and single tests elsewhere ("module::test", every parametrisation), each about a second or more.
SLOW_TESTS = frozenset({
    "test_daemon_fuzz::test_any_data_frames_and_noise_never_raise",
    "test_daemon_pipeline::test_frames_of_one_press_arriving_staggered_give_one_steady_contact",
    "test_daemon_security::test_allowed_key_gets_replies_foreign_key_and_plain_clients_get_none",
    "test_daemon_security::test_reload_admits_a_newly_allowed_key",
    "test_emulator_carrier_arbiter::test_a_4x4_skin_under_real_time_latency_delivers_every_sample",
    "test_emulator_firmware::test_a_broadcast_reset_is_answered_by_every_bridge",
    "test_emulator_firmware::test_event_reporting_sends_far_fewer_frames_when_idle_and_reports_every_press",
    "test_emulator_heartbeat_slots::test_an_idle_event_based_skin_spreads_its_heartbeats_over_the_frames",
    "test_emulator_medium::test_a_skin_whose_relays_hear_frames_together_needs_few_retransmissions",
    "test_golden_corpus::test_the_corpus_exercises_what_it_is_made_of",
    "test_lanes::test_no_test_file_or_bench_script_imports_a_test_file",
    "test_mesh_time_attacks::test_bridges_reset_under_a_press_are_read_out_again_within_a_second",
    "test_mesh_time_attacks::test_bridges_reset_under_a_press_deliver_again_within_a_second",
    "test_protocol_canonical::test_only_the_canonical_encoding_is_accepted",
    "test_protocol_fuzz::test_fuzz_decoders_raise_only_protocol_error",
    "test_protocol_readout::test_the_column_check_of_a_readout_agrees_with_the_element_by_element_one",
    "test_protocol_reassembly::test_flood_of_first_fragments_keeps_memory_bounded",
    "test_protocol_stream::test_feed_iter_yields_what_feed_returns_without_holding_it",
    "test_protocol_stream::test_stream_yields_exactly_the_intact_frames",
    "test_protocol_version3::test_a_version_3_frame_reads_as_today_and_is_written_back_as_version_4",
    "test_protocol_version3::test_fragmented_packed_data_reassembles",
    "test_protocol_version3::test_packed_data_round_trips_every_sample_a_chip_can_send",
    "test_replay_link_attacks::test_stamps_never_go_back_or_run_ahead_when_paced",
    "test_ros2_messages::test_no_payload_makes_the_converter_raise_or_a_message_that_does_not_serialise",
    "test_tactile_calibration::test_a_common_step_is_drift_not_touch",
    "test_tactile_calibration::test_a_held_press_does_not_carry_a_ratchet_of_the_common_offset",
    "test_tactile_calibration::test_a_tracker_without_touch_detection_would_erase_the_press",
    "test_tactile_calibration::test_an_untouched_skin_stays_untouched_for_an_hour_of_drift_steps_and_outages",
    "test_tactile_calibration::test_bounded_drift_alone_keeps_an_undetected_press",
    "test_tactile_calibration::test_common_drift_of_5_fF_per_second_is_not_touch",
    "test_tactile_calibration::test_exponential_tracker_uses_timestamps_not_sample_count",
    "test_tactile_calibration::test_max_touch_has_a_default_and_rebaselines_are_counted",
    "test_tactile_calibration::test_ten_minute_press_is_kept_while_neighbour_drift_is_removed",
    "test_tactile_calibration::test_ten_minute_press_under_5_fF_per_second_common_drift",
    "test_tactile_calibration::test_ten_minute_slow_press_is_reported_and_kept",
    "test_tactile_calibration::test_without_common_mode_the_press_is_still_not_erased",
    "test_views_robot_skin::test_any_skin_map_is_read_without_raising",
    "test_skin_geometry::test_a_deep_parent_chain_and_many_patches_are_read_in_linear_time",
    "test_skin_geometry::test_more_patches_than_the_limit_are_refused_at_once",
})


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        module = getattr(item, "module", None)
        name = module.__name__.rpartition(".")[2] if module is not None else ""
        if name in PROCESS_MODULES or PROCESS_FIXTURES & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.process)
        if name in SLOW_MODULES or f"{name}::{getattr(item, 'originalname', item.name)}" in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)


_running: list[pytest.Item | None] = [None]  # the test whose setup, call or teardown runs now
_started: dict[str, list[str]] = {}  # test id -> what an unmarked test started


_spawned: set[int] = set()  # every process a test started (its pid: its session or group, if it made one)


def _guarded(what: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    @functools.wraps(fn)
    def call(*args: Any, **kwargs: Any) -> Any:
        item = _running[0]
        if item is not None and item.get_closest_marker("process") is None:
            _started.setdefault(item.nodeid, []).append(what)
        result = fn(*args, **kwargs)
        pid = result[0] if isinstance(result, tuple) else result  # forkpty: (pid, fd); openpty: (fd, fd)
        if what != "os.openpty" and isinstance(pid, int) and pid > 0:
            _spawned.add(pid)
        return result
    return call


#: s the kernels' warm-up before a distributed run may take (a cold cache on a busy machine: ~1-2 min)
WARM_UP_LIMIT = 600
#: Set (to 1) by ``make test`` on the suite it starts: its recipe ran the same warm-up beside
#: lint and waited for it, so the controller's own would only load the kernels again (~2 s
#: before any worker starts).
WARMED_ENV = "CELLBRIDGE_KERNELS_WARMED"


def _warm_kernel_cache(config: pytest.Config) -> None:
    """Compile the numba kernels (the contact estimator's, the calibrator's step, the readout
    reader) into their cache once, before pytest-xdist's workers start.

    On a fresh checkout every worker that reaches a kernel first compiles it (about 30 s of
    CPU), and so does every daemon a live test starts meanwhile: the workers are handed
    alternate tests of the same modules, so they get there together and both cores spent the
    suite's first half minute compiling the same kernels, two to four times over. Once the
    cache holds them a worker or daemon loads them in a second. Only the controller of a
    distributed run does this (in one process a kernel is compiled once, where it is first
    used); a warm-up that fails changes nothing: the test that needs the kernel fails and
    says why. Not done again when ``make test`` says (``WARMED_ENV``) it has just done it."""
    if os.environ.get(WARMED_ENV) == "1" or hasattr(config, "workerinput") or not config.getoption("numprocesses", None) \
            or config.getoption("dist", "no") == "no" or config.getoption("collectonly", False) \
            or config.getoption("help", False):  # (nothing runs: --co, --help)
        return
    import subprocess
    import sys

    try:  # (a warm-up that hangs must not hold the suite: its tests would say what hangs)
        subprocess.run([sys.executable, str(Path(__file__).with_name("support") / "warm_kernels.py")],
                       stdout=subprocess.DEVNULL, check=False, timeout=WARM_UP_LIMIT)
    except subprocess.TimeoutExpired:
        pass


def pytest_configure(config: pytest.Config) -> None:
    """Every way a test starts a process or a pty passes through one of these: subprocess
    and multiprocessing's spawn (fork_exec, posix_spawn), a fork (multiprocessing's fork,
    pty.fork), a pty (os.openpty, which pty.openpty calls)."""
    import _posixsubprocess
    import subprocess

    _warm_kernel_cache(config)

    for name in ("fork", "forkpty", "openpty", "posix_spawn", "posix_spawnp"):
        if hasattr(os, name):
            setattr(os, name, _guarded(f"os.{name}", getattr(os, name)))
    _posixsubprocess.fork_exec = _guarded("fork_exec", _posixsubprocess.fork_exec)
    if getattr(subprocess, "_fork_exec", None) is not None:
        subprocess._fork_exec = _posixsubprocess.fork_exec  # type: ignore[attr-defined]
    _watch_loops_close()
    _become_subreaper()


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


# -- no asyncio task outlives its test -----------------------------------------------------------
#
# ``asyncio.run`` (and ``asyncio.Runner``) cancels every task still pending when its coroutine
# returns, and a loop closed by hand drops them: either way a task that the code under test
# started and forgot (a reader never awaited, a timer never cancelled) vanishes without a word,
# and in the daemon it would go on running. Every loop a test closes, through a runner or by
# hand, in the test's thread or another, is looked at as it closes: a task still pending there
# fails the test, named with where it waits.

_leaked: dict[str, list[str]] = {}  # test id -> the tasks its loops closed on


def _note_pending(loop: asyncio.AbstractEventLoop) -> None:
    item = _running[0]
    if item is None:
        return
    pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
    if pending:
        seen = _leaked.setdefault(item.nodeid, [])
        seen += [d for d in map(_describe, pending) if d not in seen]


def _describe(task: asyncio.Task[Any]) -> str:
    frames = task.get_stack(limit=1)
    where = f" at {frames[0].f_code.co_filename}:{frames[0].f_lineno}" if frames else ""
    return f"{task.get_name()} ({getattr(task.get_coro(), '__qualname__', task.get_coro())}{where})"


def _watch_loops_close() -> None:
    """Look at a loop's tasks before a runner cancels them (``Runner.close``, which
    ``asyncio.run`` calls) and before a loop closed by hand (``BaseEventLoop.close``) drops them."""
    runner_close = asyncio.Runner.close
    loop_close = asyncio.BaseEventLoop.close

    @functools.wraps(runner_close)
    def close_runner(self: asyncio.Runner) -> None:
        loop = getattr(self, "_loop", None)  # None until the runner made one
        if loop is not None and not loop.is_closed():
            _note_pending(loop)
        runner_close(self)

    @functools.wraps(loop_close)
    def close_loop(self: asyncio.BaseEventLoop) -> None:
        if not self.is_closed():
            _note_pending(self)
        loop_close(self)

    asyncio.Runner.close = close_runner  # type: ignore[method-assign]
    asyncio.BaseEventLoop.close = close_loop  # type: ignore[method-assign]


@pytest.fixture(autouse=True)
def _no_task_outlives_its_test(request: pytest.FixtureRequest) -> Iterator[None]:
    yield
    leaked = _leaked.pop(request.node.nodeid, None)
    if leaked:
        pytest.fail(f"the event loop closed with {len(leaked)} task(s) still pending (cancelled or dropped "
                    f"unawaited): {'; '.join(leaked)}. Cancel and await every task the test or the code under "
                    "test starts before its loop ends.", pytrace=False)


# -- no process outlives its test module -----------------------------------------------------------
#
# Every test stops what it starts, also on failure; a view stuck in its shutdown or a stop
# path that sends SIGTERM and never SIGKILL leaves a process running after the suite, on a
# user's machine. After a module's last test (and its fixtures) every process the tests
# started, every descendant of this worker (a grandchild under a child still running; a
# daemon that double-forked and called setsid, re-parented here as its orphan: the worker
# is its descendants' subreaper), and every process in a session or group one of them led,
# must be gone. One that is not is killed and the module fails, named with the process's
# command line. Under xdist each worker guards its own. Not seen: a process handed to
# another parent on purpose (started through systemd-run or a session manager), and, where
# PR_SET_CHILD_SUBREAPER is missing (not Linux), an orphan that left its session. The scan
# reads /proc once a module (about 1 ms with 70 processes on the machine).


#: Processes multiprocessing starts once per interpreter and keeps for its lifetime (a
#: process pool's resource tracker, the fork server): not a test's to stop.
_INTERPRETER_HELPERS = ("multiprocessing.resource_tracker", "multiprocessing.forkserver")


def _become_subreaper() -> None:
    """Orphans of this worker's descendants (a daemon that double-forked and called setsid
    itself, e.g. tmux's server) are re-parented to this worker instead of init: the guard
    sees them, as children. Linux only (PR_SET_CHILD_SUBREAPER); elsewhere they go unseen."""
    import ctypes

    try:
        ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER
    except (OSError, AttributeError):
        pass


def _alive_descendants() -> dict[int, str]:
    """Live processes (not zombies) this worker started, their descendants (grandchildren
    under a child still running; orphans re-parented here, :func:`_become_subreaper`), or
    in a session or process group that one of them leads: pid -> command line. Orphans
    that ended here are reaped."""
    me = os.getpid()
    table: dict[int, tuple[bytes, int, int, int]] = {}  # pid -> state, ppid, group, session
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as f:
                fields = f.read().rsplit(b")", 1)[1].split()
            table[int(entry)] = (fields[0], int(fields[1]), int(fields[2]), int(fields[3]))
        except (OSError, IndexError, ValueError):  # it ended meanwhile
            continue
    children: dict[int, list[int]] = {}
    for pid, (_, ppid, _, _) in table.items():
        children.setdefault(ppid, []).append(pid)
    mine, todo = set(), list(children.get(me, ()))
    while todo:
        pid = todo.pop()
        if pid not in mine:
            mine.add(pid)
            todo += children.get(pid, ())
    found = {}
    for pid, (state, ppid, pgrp, session) in table.items():
        if pid == me:
            continue
        if state in (b"Z", b"X"):
            if ppid == me and pid not in _spawned:  # an orphan adopted here ended: reap it
                with contextlib.suppress(ChildProcessError):
                    os.waitpid(pid, os.WNOHANG)
            continue
        if pid in mine or pgrp in _spawned or session in _spawned:
            try:
                with open(f"/proc/{pid}/cmdline", "rb") as f:
                    cmd = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
            except OSError:
                continue
            if not any(helper in cmd for helper in _INTERPRETER_HELPERS):
                found[pid] = cmd
    return found


#: s the guard gives processes that are ending to end: a test that stopped its child leaves
#: the child's own children (a daemon's contact worker, a skin's bridges) to notice and
#: exit by themselves, and on a busy machine one was caught mid-exit (its command line
#: already gone) and reported as left running.
EXIT_GRACE = 3.0


def _left_after(grace: float) -> dict[int, str]:
    """:func:`_alive_descendants` once those ending within ``grace`` s have ended: what a
    module really left running."""
    left = _alive_descendants()
    end = time.monotonic() + grace
    while left and time.monotonic() < end:
        time.sleep(0.05)
        left = _alive_descendants()
    return left


@pytest.fixture(autouse=True, scope="module")
def _no_process_outlives_its_module(request: pytest.FixtureRequest) -> Iterator[None]:
    yield
    left = _left_after(EXIT_GRACE)
    _spawned.clear()
    if not left:
        return
    for pid in left:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    pytest.fail(f"{request.module.__name__} left {len(left)} process(es) running after its tests (now killed): "
                + "; ".join(f"{pid}: {cmd[:200]}" for pid, cmd in sorted(left.items()))
                + ". Stop every process a test starts, with SIGKILL after a bounded wait, also on failure.",
                pytrace=False)
