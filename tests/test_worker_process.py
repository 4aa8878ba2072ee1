"""The contact worker's executor, a real spawned process (daemon/shell/worker_process.py): jobs in
order, their exceptions, a process that dies or is killed under a job, shutdown, and a
daemon that dies without a word."""

from __future__ import annotations

import concurrent.futures
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest
from cellbridge.daemon.shell.worker_process import BrokenWorker, WorkerProcess

from support.process_state import gone, until_gone


@pytest.fixture
def worker() -> Iterator[WorkerProcess]:
    w = WorkerProcess()
    try:
        yield w
    finally:
        w.kill()
        w.shutdown(wait=True)


class Unpicklable(Exception):
    def __reduce__(self) -> tuple:
        raise TypeError("not this one")


def _raise_unpicklable() -> None:
    raise Unpicklable("inside")


def test_jobs_run_in_order_in_another_process_and_their_exceptions_come_back(worker: WorkerProcess) -> None:
    futs = [worker.submit(pow, 2, i) for i in range(50)] + [worker.submit(os.getpid)]
    assert [f.result(30) for f in futs[:-1]] == [2 ** i for i in range(50)]
    assert futs[-1].result(30) == worker.pid != os.getpid()
    with pytest.raises(ZeroDivisionError):
        worker.submit(divmod, 1, 0).result(30)
    with pytest.raises(RuntimeError, match="does not pickle"):  # the job failed, the process did not
        worker.submit(_raise_unpicklable).result(30)
    assert worker.submit(pow, 3, 2).result(30) == 9


def test_a_process_killed_under_a_job_fails_that_job_and_every_later_one(worker: WorkerProcess) -> None:
    assert worker.submit(pow, 2, 2).result(30) == 4
    slow = worker.submit(time.sleep, 30)
    time.sleep(0.2)
    assert worker.pid is not None
    os.kill(worker.pid, signal.SIGKILL)  # (dies by itself: an estimate that crashed the interpreter)
    with pytest.raises(BrokenWorker):
        slow.result(60)
    with pytest.raises(BrokenWorker):
        worker.submit(pow, 2, 2).result(60)


def test_kill_ends_a_hung_job_at_once(worker: WorkerProcess) -> None:
    hung = worker.submit(time.sleep, 60)
    time.sleep(0.2)
    t0 = time.monotonic()
    worker.kill()
    with pytest.raises(BrokenWorker):
        hung.result(5)
    assert time.monotonic() - t0 < 5 and worker.pid is not None and until_gone(worker.pid)


def test_shutdown_runs_the_jobs_sent_then_the_process_exits_by_itself() -> None:
    w = WorkerProcess()
    futs = [w.submit(pow, 2, i) for i in range(5)]
    w.shutdown(wait=True)
    assert [f.result(0) for f in futs] == [1, 2, 4, 8, 16]
    assert w.pid is not None and gone(w.pid)
    with pytest.raises(RuntimeError):
        w.submit(pow, 2, 2)


def test_end_kills_a_process_that_does_not_exit_in_its_wait() -> None:
    w = WorkerProcess()
    assert w.submit(pow, 2, 2).result(30) == 4
    assert w.pid is not None
    os.kill(w.pid, signal.SIGSTOP)  # stuck between jobs
    t0 = time.monotonic()
    try:
        assert w.end(0.5) is False
        assert time.monotonic() - t0 < 3 and until_gone(w.pid)
    finally:
        if not gone(w.pid):
            os.kill(w.pid, signal.SIGKILL)


def test_the_process_ignores_ctrl_c_and_ends_with_the_daemon_that_dies_without_a_word() -> None:
    """A Ctrl-C reaches the terminal's whole process group: the worker stays for the
    daemon's drain. A daemon killed outright (SIGKILL) closes its end of the pipe: the idle
    worker exits, as it must not be left running on the robot."""
    code = ("import os, sys, time\n"
            "from cellbridge.daemon.shell.worker_process import WorkerProcess\n"
            "w = WorkerProcess(); w.submit(pow, 2, 2).result(30)\n"
            "print(w.pid, flush=True); time.sleep(60)\n")
    parent = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, start_new_session=True)
    pid = 0
    try:
        line = parent.stdout.readline() if parent.stdout else b""  # bounded: the parent prints or dies
        pid = int(line)
        os.kill(pid, signal.SIGINT)
        time.sleep(0.3)
        assert not gone(pid), "Ctrl-C ended the worker"
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(10)
        assert until_gone(pid), "the worker outlived its daemon"
    finally:
        with_pids = [p for p in (pid, parent.pid) if p and not gone(p)]
        for p in with_pids:
            os.kill(p, signal.SIGKILL)
        parent.wait(10)
        if parent.stdout:
            parent.stdout.close()


def test_a_future_of_the_worker_cannot_be_cancelled_once_sent(worker: WorkerProcess) -> None:
    fut = worker.submit(time.sleep, 0.2)
    assert not fut.cancel()  # it runs in the process already: cancelling it would lie
    assert fut.result(60) is None
    assert isinstance(fut, concurrent.futures.Future)
