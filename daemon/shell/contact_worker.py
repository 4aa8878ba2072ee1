"""Contact estimation off the event loop: one worker, on the newest snapshot only.

Production runs the worker in one spawned *process*: a thread would not do, as the
estimator's Python code holds the interpreter lock for milliseconds at a time and every
one of them would stall ingest. The worker takes its executor from a factory, so tests,
tools and the golden files run the very same path on an :class:`InlineExecutor`. The
worker builds its own estimator from a :class:`~cellbridge.daemon.core.contacts.ContactSpec`
and keeps it while the layout stays the same: the spec goes along with a request until the
worker has answered one of it, and after that its digest alone. A worker that dies is
replaced at the next estimate.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import concurrent.futures.process
import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

from cellbridge.daemon.core.contacts import (
    ContactJob,
    ContactSpec,
    EstimateRequest,
    SpecNeeded,
    estimate,
    in_worker,
)
from cellbridge.daemon.shell.kernels import warm_up
from cellbridge.daemon.shell.logs import event
from cellbridge.daemon.shell.worker_process import WorkerProcess

Contacts = list[dict[str, Any]]
#: Makes the worker's executor (again after a hung or dead one was killed).
ExecutorFactory = Callable[[], concurrent.futures.Executor]
#: Seconds an idle worker has to exit when the daemon stops, before it is killed.
CLOSE_WAIT = 2.0


def process_pool() -> concurrent.futures.Executor:
    """The production executor: one spawned process (:class:`~cellbridge.daemon.shell.worker_process.WorkerProcess`),
    told first that it is the contact worker (its estimators' objects are kept out of the
    cyclic collector's full passes: :func:`~cellbridge.daemon.core.contacts.in_worker`)."""
    pool = WorkerProcess()
    pool.submit(in_worker)  # (jobs run in order: before the warm-up and every estimate)
    return pool


class InlineExecutor(concurrent.futures.Executor):
    """Runs each job in the caller at once: the production contact path without a process."""

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as exc:  # handed to whoever reads the future, as a pool does
            fut.set_exception(exc)
        return fut


class ContactWorker:
    """Runs contact jobs (:class:`~cellbridge.daemon.core.contacts.ContactJob`) on an executor from
    ``executor`` (default: one spawned process).

    :meth:`estimate` (async, with a hung-worker timeout) is the service's entry point,
    :meth:`estimate_now` the synchronous one for tests and tools; both skip asking once
    nothing has been touched for longer than every track can live."""

    def __init__(self, log: logging.Logger,
                 executor: ExecutorFactory = process_pool) -> None:
        self.log = log
        self._make_executor = executor
        self._pool: concurrent.futures.Executor | None = None
        self.busy = False
        self._quiet = 0  # estimates in a row with nothing touched
        self.stats: dict[str, Any] = {"runs": 0, "errors": 0, "last_ms": 0.0, "max_ms": 0.0, "feeds_skipped": 0,
                                      "worker_restarts": 0}
        self._answered = False  # the current worker has finished an estimate (its warm-up is behind it)
        self._job: concurrent.futures.Future[Contacts] | None = None  # the last estimate handed to the worker
        self._stopping = False
        self._ran = False  # the last estimate asked for ran the job (not skipped: nothing to track)
        self._built: tuple[str, Any] | None = None  # (owner, spec) of the last job that ran: the worker's estimator
        self._warm: concurrent.futures.Future[None] | None = None  # the current worker's warm-up
        self._shipped: tuple[str, ContactSpec] | None = None  # (owner, spec) the current worker answered on
        self._key: tuple[ContactSpec, bytes] | None = None  # the last spec's digest

    def _executor(self) -> concurrent.futures.Executor:
        if self._pool is None:
            self._pool = self._make_executor()
        return self._pool

    def start(self) -> None:
        """Start the worker now, so its imports are done before the first touch."""
        self._warm = self._executor().submit(warm_up)

    async def warm(self, limit: float) -> bool:
        """Until the worker's warm-up has finished (at most ``limit`` s); whether it has. On a
        fresh installation the warm-up compiles the estimator's kernels (about 20 s)."""
        if self._warm is None:
            return True
        with contextlib.suppress(Exception):  # a failed warm-up is the first estimate's to report
            async with asyncio.timeout(limit):  # (not wait_for: see estimate)
                await asyncio.shield(asyncio.wrap_future(self._warm))
        return self._warm.done()

    def warmed(self) -> bool:
        """Whether the worker's warm-up has finished (True when none was started)."""
        return self._warm is None or self._warm.done()

    def stop(self) -> None:
        """The daemon is stopping: from now on every estimate has its timeout (even the
        first), and a hung or dead worker is killed but not replaced."""
        self._stopping = True

    @property
    def working(self) -> bool:
        """The worker is still on an estimate (perhaps one nobody waits for any more: hung)."""
        return self._job is not None and not self._job.done()

    def _needed(self, job: ContactJob) -> bool:
        """False once nothing is touched and every track has ended: no need to ask; unless
        the job's layout or settings are new to the worker. It builds its estimator at the
        first job of a spec (and settles the collector): a layout that grew on an idle skin
        (a bridge booting late) cost the first touch after it that build, 39-47 ms on a
        4x4, where now an untouched frame pays it."""
        self._quiet = 0 if bool(job.snapshot.touched.any()) else self._quiet + 1
        built = (job.owner, job.spec)
        self._ran = self._quiet <= job.spec.max_missed + 1 or built != self._built  # (the pipeline's one spec
        # object per layout: compared by identity first)
        if self._ran:
            self._built = built
        return self._ran

    def _request(self, job: ContactJob, ship: bool = False) -> EstimateRequest:
        """``job`` as the worker takes it: with its spec while the current worker has not
        answered a request of it (or ``ship``), else by the spec's digest alone."""
        spec = job.spec
        key = self._key  # (read once: the results thread writes it too, sending a request again)
        if key is None or key[0] is not spec:
            key = self._key = (spec, spec.digest())
        shipped = self._shipped
        ship = ship or shipped is None or shipped[0] != job.owner or (shipped[1] is not spec and shipped[1] != spec)
        return job.request(key[1], ship)

    def _submit(self, job: ContactJob) -> concurrent.futures.Future[Contacts]:
        """Hand ``job`` to the worker; a worker that has not the spec (:class:`SpecNeeded`:
        it was replaced, or dropped the owner's estimator) gets it sent along again, at
        once, before the answer is handed on."""
        pool = self._executor()  # (the retry goes to the same worker: never a new one from the results thread)
        first = pool.submit(estimate, self._request(job))
        out: concurrent.futures.Future[Contacts] = concurrent.futures.Future()
        out.set_running_or_notify_cancel()

        def settle(fut: concurrent.futures.Future[Contacts], again: bool) -> None:
            if fut.cancelled():  # (an executor that cancels what it had not started: a thread
                # pool's kill; its exception() raises, and ``out`` was left pending for ever)
                self._shipped = None
                out.set_exception(concurrent.futures.process.BrokenProcessPool(
                    "the contact estimate was cancelled: its worker was killed before it ran"))
                return
            exc = fut.exception()
            if exc is None:
                self._shipped = (job.owner, job.spec)
                out.set_result(fut.result())
            elif isinstance(exc, SpecNeeded) and again:
                self._shipped = None
                try:
                    retry = pool.submit(estimate, self._request(job, ship=True))
                except Exception as err:  # (a worker shut down meanwhile)
                    out.set_exception(err)
                    return
                retry.add_done_callback(lambda f: settle(f, False))
            else:
                self._shipped = None
                out.set_exception(exc)

        first.add_done_callback(lambda f: settle(f, True))
        return out

    def last_ran(self) -> bool:
        """Whether the last estimate asked for ran its job (False: skipped, as nothing was
        touched and every track had ended; its answer was no contacts at no cost). The
        contact loop's pacer counts only those that ran against ``[contact] rate``."""
        return self._ran

    def estimate_now(self, job: ContactJob) -> Contacts:
        """The contacts of ``job``, waiting for them (an inline executor: at once). Raises
        what the estimate raised."""
        t0 = time.perf_counter()
        contacts = self._submit(job).result() if self._needed(job) else []
        self._count(t0)
        return contacts

    async def estimate(self, job: ContactJob, timeout: float = 30.0) -> Contacts | None:
        """The contacts of ``job``; None when the estimate failed (logged and counted), or
        when the daemon is stopping and its worker is gone (a stop never starts a new one).
        An estimate past ``timeout`` means a hung worker: it is killed and a new one
        started. The worker's warm-up (about 20 s on a fresh installation, compiling the
        kernels) is waited for first, without a bound; a worker started without one has
        no bound on its first estimate."""
        t0 = time.perf_counter()
        if self._stopping and self._pool is None:
            return None
        if not self._needed(job):
            contacts: Contacts = []
        else:
            self.busy = True
            try:
                if self._warm is not None and not self._warm.done() and not self._stopping:
                    with contextlib.suppress(Exception):  # a failed warm-up is the estimate's to report
                        await asyncio.shield(asyncio.wrap_future(self._warm))
                    t0 = time.perf_counter()  # last_ms/max_ms time the estimate, not the warm-up before it
                self._job = self._submit(job)
                limit = timeout if self._answered or self._stopping or self._warm is not None else None
                # asyncio.timeout, not wait_for: Python 3.11's wait_for returns a result that
                # came in the step before its task was cancelled, and the cancel is lost (the
                # service's contact loop then went on, and a stop waited for it for ever)
                async with asyncio.timeout(limit):
                    contacts = await asyncio.wrap_future(self._job)
                self._answered = True
            except Exception as exc:  # a bad estimate (or a dead worker) must not end contact publishing
                self.stats["errors"] += 1
                if isinstance(exc, asyncio.TimeoutError):
                    event(self.log, "error", "contact worker hung: killed" + ("" if self._stopping else ", a new one starts"),
                          timeout=timeout)
                    self._replace()
                else:
                    event(self.log, "error", "contact estimation failed", error=f"{type(exc).__name__}: {exc}")
                    if isinstance(exc, concurrent.futures.process.BrokenProcessPool):
                        self._replace()
                return None
            finally:
                self.busy = False
        self._count(t0)
        return contacts

    def _count(self, t0: float) -> None:
        ms = (time.perf_counter() - t0) * 1e3
        st = self.stats
        st["runs"] += 1
        st["last_ms"], st["max_ms"] = ms, max(st["max_ms"], ms)

    def _replace(self) -> None:
        """Kill the worker (hung, or dead already) and warm up a new one."""
        pool, self._pool = self._pool, None
        self._answered = False
        self._shipped = None
        self._built = None  # the new worker has no estimator: its first job runs, touched or not
        self.stats["worker_restarts"] += 1
        if pool is not None:
            _kill(pool)
        if not self._stopping:
            self.start()

    async def idle(self, limit: float = 5.0) -> None:
        """Until a running estimate has finished (at most ``limit`` s)."""
        end = time.monotonic() + limit
        while self.busy and time.monotonic() < end:
            await asyncio.sleep(0.01)

    def close(self) -> None:
        """End the worker: at once if it is still on an estimate (hung, or abandoned by a
        stop) or on its warm-up, else once it exits, killed if that takes ``CLOSE_WAIT``
        (an idle worker that does not answer: stopped, or stuck between jobs, kept the
        daemon from exiting until systemd killed it)."""
        pool, self._pool = self._pool, None
        if pool is None:
            return
        if self.working or not self.warmed():  # (a warm-up compiling the kernels takes half a minute)
            _kill(pool)
            return
        if not isinstance(pool, WorkerProcess):  # an executor of threads, or inline: nothing to kill
            pool.shutdown(wait=True)
            return
        if not pool.end(CLOSE_WAIT):
            event(self.log, "warning", "contact worker did not exit: killed", waited=CLOSE_WAIT)


def _kill(pool: concurrent.futures.Executor) -> None:
    """End ``pool`` now, whatever it is running: its ``kill()`` where it has one (the worker
    process, a test's fake), then shut it down without waiting."""
    kill = getattr(pool, "kill", None)
    if kill is not None:
        kill()
    pool.shutdown(wait=False, cancel_futures=True)
