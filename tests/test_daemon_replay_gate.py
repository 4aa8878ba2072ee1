"""A replay waits for the contact worker's warm-up (Service._replay_gate,
Service._finish_replay, ContactWorker.warm): under a stop, and with a warm-up that never ends."""

from __future__ import annotations

import asyncio
import concurrent.futures
import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zmq
import zmq.asyncio
from cellbridge.daemon.core.config import load_config
from cellbridge.daemon.shell.service import Service

from support.golden_corpus import DATA
from support.shell_fakes import RecordingHooks, until

CAPTURE, CONFIG = DATA / "daemon_press.cbcap", DATA / "daemon_press.toml"  # the golden corpus's capture scenario


class HungWarmUp(concurrent.futures.ThreadPoolExecutor):
    """One worker thread whose warm-up does not end until ``release`` is set (a worker
    process compiling the kernels on a loaded machine, or hung in it)."""

    release = threading.Event()

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        if fn.__name__ == "warm_up":
            return super().submit(self.release.wait, 60.0)
        return super().submit(fn, *args, **kwargs)


def _service(tmp_path: Path, worker_timeout: float = 30.0, exit_when_done: bool = True, **kw: Any) -> tuple[Service, zmq.asyncio.Context]:
    path = tmp_path / "replay.toml"
    path.write_text('[pub]\nendpoint = "inproc://gate-pub"\n[control]\nendpoint = "inproc://gate-ctl"\n'
                    + CONFIG.read_text().replace("replay:daemon_press.cbcap", f"replay:{CAPTURE}")
                    .replace("wait_for_subscriber = true", "wait_for_subscriber = false")
                    .replace("exit_when_done = true", f"exit_when_done = {str(exit_when_done).lower()}")
                    .replace("birth_frames = 1", f"birth_frames = 1\nworker_timeout = {worker_timeout}"))
    cfg = load_config(path)
    ctx = zmq.asyncio.Context()
    return Service(cfg, config_path=path, hooks=RecordingHooks(cfg), ctx=ctx, **kw), ctx


def test_sigterm_while_a_replay_waits_for_the_warm_up_stops_within_the_drain_limit(tmp_path: Path) -> None:
    """SIGTERM while the replay waits at its gate for a warm-up still going (on a fresh
    installation: the kernels compiling, 20-30 s): the daemon must stop within
    ``drain_limit`` (systemd kills at TimeoutStopSec), not when the warm-up ends."""
    HungWarmUp.release.clear()
    threading.Timer(6.0, HungWarmUp.release.set).start()  # the warm-up ends 6 s in (a slow compile)

    async def scenario() -> float:
        svc, ctx = _service(tmp_path, exit_when_done=False, contact_executor=lambda: HungWarmUp(1), drain_limit=0.5)
        task = asyncio.create_task(svc.run())
        try:
            await until(lambda: any(w == "ready" for w, _ in svc.hooks.said) or task.done())  # type: ignore[attr-defined]
            await asyncio.sleep(0.3)  # the replay at its gate
            assert not task.done(), "the service ended before its signal handlers were in place"
            t0 = time.monotonic()
            os.kill(os.getpid(), signal.SIGTERM)
            await asyncio.wait_for(asyncio.shield(task), 20.0)
            return time.monotonic() - t0
        finally:
            HungWarmUp.release.set()
            await asyncio.wait_for(task, 70.0)
            ctx.destroy(linger=0)

    took = asyncio.run(scenario())
    assert took < 0.5 + 1.0, f"SIGTERM took {took:.1f} s with drain_limit 0.5 s"


def test_a_hung_warm_up_delays_a_finished_replay_by_the_warm_limit_once(tmp_path: Path) -> None:
    """A warm-up that never ends: the gate gives up after REPLAY_WARM_LIMIT and the replay
    goes on; the finished replay must not wait out the same hung warm-up a second time
    (300 s + 300 s in production) before it stops."""
    HungWarmUp.release.clear()
    limit = 3.0
    threading.Timer(4 * limit, HungWarmUp.release.set).start()  # (only so that the test ends)

    async def scenario() -> tuple[float, float]:
        svc, ctx = _service(tmp_path, worker_timeout=0.5, contact_executor=lambda: HungWarmUp(1), drain_limit=0.5)
        svc.REPLAY_WARM_LIMIT = limit
        stopping: list[float] = []
        said = svc.hooks.stopping
        def stopping_noted() -> None:
            stopping.append(time.monotonic())
            said()

        svc.hooks.stopping = stopping_noted  # type: ignore[method-assign]
        gate = svc._replay_gate
        gate_over: list[float] = []

        async def gate_noted(subscriber: bool) -> None:
            t = time.monotonic()
            await gate(subscriber)
            gate_over.append(time.monotonic())
            assert gate_over[-1] - t >= limit - 0.1  # (the gate did wait for the hung warm-up)

        svc._replay_gate = gate_noted  # type: ignore[method-assign]
        task = asyncio.create_task(svc.run())
        try:
            await until(lambda: bool(stopping), 60.0)
            assert gate_over, "the daemon stopped before its replay's gate gave up"
            return stopping[0] - gate_over[0], limit
        finally:
            HungWarmUp.release.set()
            await asyncio.wait_for(task, 70.0)
            ctx.destroy(linger=0)

    # From the gate's end, not the start (imports, the calibrator's warm-up: seconds on a busy
    # machine): the replay of 61 reads as fast as it can and its stop, well under a second
    # wait of REPLAY_WARM_LIMIT
    after_gate, limit = asyncio.run(scenario())
    assert after_gate < limit - 0.5, (f"the replay daemon began to stop {after_gate:.1f} s after its gate gave up "
                                      f"(REPLAY_WARM_LIMIT {limit} s): it waited for the warm-up again")
