"""Contact estimation off the event loop: one spawned worker process, on the newest snapshot only.

A thread would not do: the estimator's Python code holds the interpreter lock for
milliseconds at a time, and every one of them would stall ingest. The worker builds
its own estimator from a small :class:`~cellbridge.daemon.physics.ContactSpec` and keeps
it while the layout stays the same; a worker that dies is replaced at the next estimate.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import concurrent.futures.process
import logging
import multiprocessing
import time
from typing import Any

from cellbridge.daemon.logs import event
from cellbridge.daemon.physics import ContactSnapshot, ContactSpec, estimate_in_worker, warm_up


class ContactWorker:
    def __init__(self, log: logging.Logger) -> None:
        self.log = log
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self.busy = False
        self._quiet = 0  # estimates in a row with nothing touched
        self.stats: dict[str, Any] = {"runs": 0, "errors": 0, "last_ms": 0.0, "max_ms": 0.0, "feeds_skipped": 0,
                                      "worker_restarts": 0}
        self._answered = False  # the current worker has finished an estimate (its warm-up is behind it)

    def _executor(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            self._pool = concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
        return self._pool

    def start(self) -> None:
        """Start the worker now, so its imports are done before the first touch."""
        self._executor().submit(warm_up)

    async def estimate(self, spec: ContactSpec, snap: ContactSnapshot,
                       timeout: float = 30.0) -> list[dict[str, Any]] | None:
        """Contacts of one snapshot; None when the estimate failed (logged and counted).
        An estimate past ``timeout`` (once the worker has answered before: its first one
        waits for the warm-up) means a hung worker: it is killed and a new one started."""
        t0 = time.perf_counter()
        touched = bool(snap.touched.any())
        self._quiet = 0 if touched else self._quiet + 1
        if self._quiet > spec.max_missed + 1:
            contacts: list[dict[str, Any]] = []  # nothing touched and every track has ended: no need to ask
        else:
            self.busy = True
            try:
                loop = asyncio.get_running_loop()
                job = loop.run_in_executor(self._executor(), estimate_in_worker, spec, snap)
                contacts = await asyncio.wait_for(job, timeout if self._answered else None)
                self._answered = True
            except Exception as exc:  # a bad estimate (or a dead worker) must not end contact publishing
                self.stats["errors"] += 1
                if isinstance(exc, asyncio.TimeoutError):
                    event(self.log, "error", "contact worker hung: killed, a new one starts", timeout=timeout)
                    self._replace()
                else:
                    event(self.log, "error", "contact estimation failed", error=f"{type(exc).__name__}: {exc}")
                    if isinstance(exc, concurrent.futures.process.BrokenProcessPool):
                        self._replace()
                return None
            finally:
                self.busy = False
        ms = (time.perf_counter() - t0) * 1e3
        st = self.stats
        st["runs"] += 1
        st["last_ms"], st["max_ms"] = ms, max(st["max_ms"], ms)
        return contacts

    def _replace(self) -> None:
        """Kill the worker (hung, or dead already) and warm up a new one."""
        pool, self._pool = self._pool, None
        self._answered = False
        self.stats["worker_restarts"] += 1
        if pool is not None:
            for proc in list(getattr(pool, "_processes", {}).values()):  # the executor offers no kill
                proc.kill()
            pool.shutdown(wait=False, cancel_futures=True)
        self.start()

    async def idle(self, limit: float = 5.0) -> None:
        """Until a running estimate has finished (at most ``limit`` s)."""
        end = time.monotonic() + limit
        while self.busy and time.monotonic() < end:
            await asyncio.sleep(0.01)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
