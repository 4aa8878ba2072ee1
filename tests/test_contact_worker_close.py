"""A stop ends the contact worker process in bounded time, whatever state it is in
(daemon/shell/contact_worker.py ContactWorker.close)."""

from __future__ import annotations

import asyncio
import logging
import os
import signal
import time

import pytest
from cellbridge.daemon.shell import contact_worker
from cellbridge.daemon.shell.contact_worker import ContactWorker
from cellbridge.daemon.shell.worker_process import WorkerProcess

from support.process_state import gone


def _worker_pid(worker: ContactWorker) -> int:
    pool = worker._executor()
    assert isinstance(pool, WorkerProcess) and pool.pid is not None
    return pool.pid


def test_an_idle_worker_that_does_not_exit_is_killed_within_the_close_wait(warm_kernels: None) -> None:
    """Warmed up and idle, then stopped (SIGSTOP: as a worker stuck between jobs): close()
    waited for its exit for ever, and the daemon with it, until systemd killed it."""
    worker = ContactWorker(logging.getLogger("test"))
    worker.start()
    assert asyncio.run(worker.warm(120.0)), "the worker did not warm up"
    pid = _worker_pid(worker)
    os.kill(pid, signal.SIGSTOP)
    try:
        t0 = time.monotonic()
        worker.close()
        took = time.monotonic() - t0
        end = time.monotonic() + 5.0
        while not gone(pid) and time.monotonic() < end:
            time.sleep(0.02)
        assert gone(pid), "the stopped worker was left running"
        assert took < contact_worker.CLOSE_WAIT + 2.0, f"close() took {took:.1f} s"
    finally:
        if not gone(pid):
            os.kill(pid, signal.SIGKILL)


def test_an_idle_worker_exits_by_itself_at_close(warm_kernels: None, monkeypatch: pytest.MonkeyPatch,
                                                 caplog: pytest.LogCaptureFixture) -> None:
    """Told to end, an idle worker exits by itself: it is not the close wait's kill that
    ends it. (Timed against ``CLOSE_WAIT`` this raced the machine: beside four CPU burners
    an interpreter's exit took 2.06 s of the 2 s, and close() rightly killed it. The wait
    is lengthened here, and what is checked is who ended it.)"""
    monkeypatch.setattr(contact_worker, "CLOSE_WAIT", 60.0)
    worker = ContactWorker(logging.getLogger("test"))
    worker.start()
    assert asyncio.run(worker.warm(120.0))
    pid = _worker_pid(worker)
    with caplog.at_level(logging.WARNING, logger="test"):
        worker.close()
    assert gone(pid)
    assert not [r for r in caplog.records if "did not exit" in r.getMessage()], caplog.text
