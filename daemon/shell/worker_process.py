"""One spawned process that runs the jobs handed to it, in order, one at a time: the contact
worker's executor.

Why not :class:`concurrent.futures.ProcessPoolExecutor`: a job reached the pool's process
through two of the pool's threads (its manager and its call queue's feeder), and each had
to win the interpreter lock from the event loop, busy 1-5 ms with every serial read around
a press. On a 4x4 skin at 100 Hz a contact job waited 0.9 / 3.1 / 5.2 ms (p50/p90/p99)
from its submission to its start in the worker, longer than the estimate itself (1.6 ms).
Here the caller writes the job down the process's pipe itself, and one thread reads the
results: ``bench/bench_worker_handoff.py`` measures both under a loop busy like the
daemon's.

The process is spawned (a fork would copy the daemon's sockets). It ignores SIGINT and
SIGTERM, from its first instruction on (a Ctrl-C in a terminal reaches the whole process
group, and ``systemctl stop`` the whole unit: the worker must outlive the daemon's drain,
whose last estimate it runs), and the daemon ends it: it exits when its pipe closes (at
:meth:`WorkerProcess.shutdown`, or when the daemon dies: an idle worker reads the end, a
busy one fails to send), it is killed (a hung job; the daemon's exit, see
:func:`_kill_left_over`), and the kernel kills it when the daemon dies outright
(``PR_SET_PDEATHSIG``: a job that never ends must not outlive it).
"""

from __future__ import annotations

import atexit
import collections
import concurrent.futures
import concurrent.futures.process
import ctypes
import multiprocessing
import multiprocessing.connection
import os
import signal
import threading
import weakref
from collections.abc import Callable
from multiprocessing.reduction import ForkingPickler
from typing import Any

BrokenWorker = concurrent.futures.process.BrokenProcessPool  #: what a job's future holds when the process died
_ENDED_BY_DAEMON = {signal.SIGINT, signal.SIGTERM}  #: signals the worker leaves to the daemon
_LIVE: weakref.WeakSet[WorkerProcess] = weakref.WeakSet()  # workers started and not yet ended


class WorkerProcess(concurrent.futures.Executor):
    """An executor of one spawned process. :meth:`submit` sends the job at once, from the
    caller's thread (jobs are small: a contact request without its spec stays inside a
    pipe's buffer even on a humanoid's skin); a result thread completes the futures in order. A process that dies
    fails every pending future, and every later one, with ``BrokenProcessPool``."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=True)
        self._proc = ctx.Process(target=_serve, args=(child, os.getpid()), name="cellbridge-contact-worker",
                                 daemon=True)
        # blocked across the spawn, inherited: a Ctrl-C while the new interpreter boots
        # (at the daemon's start, at every replacement) would kill it before _serve ran
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, _ENDED_BY_DAEMON)
        try:
            self._proc.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        child.close()  # the child's end lives in the child only: its exit is our EOF
        self._pending: collections.deque[concurrent.futures.Future[Any]] = collections.deque()
        self._lock = threading.Lock()  # the pending futures and the state below
        self._send_lock = threading.Lock()  # the pipe's order of jobs (the reader never takes it)
        self._broken = ""  # why the process can take no more jobs ("" while it can)
        self._shut = False
        _LIVE.add(self)
        self._reader = threading.Thread(target=self._read, name="contact-worker-results", daemon=True)
        self._reader.start()

    @property
    def pid(self) -> int | None:
        """The worker process's pid."""
        return self._proc.pid

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        """Run ``fn(*args, **kwargs)`` in the process after the jobs before it. ``fn`` and
        its arguments must pickle (``fn`` by its module and name). Raises RuntimeError after
        :meth:`shutdown`; a dead process gives a future failed with ``BrokenProcessPool``."""
        fut: concurrent.futures.Future[Any] = concurrent.futures.Future()
        fut.set_running_or_notify_cancel()  # sent at once: cancelling cannot take it back
        try:  # before it is queued: a job that does not pickle fails alone, later results stay theirs
            data = bytes(ForkingPickler.dumps((fn, args, kwargs)))
        except Exception as exc:
            fut.set_exception(exc)
            return fut
        with self._send_lock:
            with self._lock:
                if self._shut:
                    raise RuntimeError("cannot submit to a worker process after shutdown")
                if self._broken:
                    fut.set_exception(BrokenWorker(self._broken))
                    return fut
                self._pending.append(fut)
            try:  # (without the futures' lock: the reader takes the results meanwhile)
                self._conn.send_bytes(data)
            except (OSError, ValueError) as exc:  # the process's end is gone
                with self._lock:
                    if fut in self._pending:
                        self._pending.remove(fut)
                if not fut.done():
                    fut.set_exception(BrokenWorker(f"the contact worker process is gone: {exc}"))
        return fut

    def _read(self) -> None:
        try:
            while True:
                try:
                    data = self._conn.recv_bytes()
                except (EOFError, OSError):
                    break
                try:
                    ok, value = ForkingPickler.loads(data)
                except Exception as exc:  # pickled in the worker, does not unpickle here
                    ok, value = False, RuntimeError(f"the job's reply does not unpickle: {type(exc).__name__}: {exc}")
                with self._lock:
                    if not self._pending:  # a result that came in as the process was killed
                        continue
                    fut = self._pending.popleft()
                if ok:
                    fut.set_result(value)
                else:
                    fut.set_exception(value)
        finally:
            self._fail("the contact worker process ended")
            self._conn.close()

    def _fail(self, why: str) -> None:
        with self._lock:
            self._broken = self._broken or why
            pending, self._pending = list(self._pending), collections.deque()
        for fut in pending:
            fut.set_exception(BrokenWorker(why))

    def kill(self) -> None:
        """End the process now, whatever it runs; its pending futures fail."""
        self._proc.kill()
        _LIVE.discard(self)
        self._fail("the contact worker process was killed")

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """No more jobs: the process ends once it has run those sent (at once with
        ``cancel_futures``: killed). ``wait``: until it has ended."""
        with self._lock:
            first, self._shut = not self._shut, True
        if cancel_futures:
            self.kill()
        elif first:
            with self._send_lock:
                try:
                    self._conn.send_bytes(_END)  # (the process reads it after the jobs before it)
                except (OSError, ValueError):
                    pass  # gone already
        if wait:
            self._proc.join()
            self._reader.join()
            _LIVE.discard(self)

    def end(self, wait: float) -> bool:
        """Shut down and give the process ``wait`` s to exit, then kill it; whether it exited
        by itself (a stopped or stuck process kept the daemon from exiting)."""
        self.shutdown(wait=False)
        self._proc.join(wait)
        if self._proc.is_alive():
            self.kill()
            self._proc.join(1.0)
            return False
        _LIVE.discard(self)
        return True


_END = bytes(ForkingPickler.dumps(None))  #: the last message a worker reads


@atexit.register
def _kill_left_over() -> None:
    """At the daemon's exit, kill the workers still running (an exit past the service's own
    stop: an exception in its teardown). Registered after multiprocessing's exit hook, so it
    runs first: that hook sends a daemonic child SIGTERM, which a worker ignores, and then
    waits for it without a bound."""
    for worker in list(_LIVE):
        worker.kill()
        worker._proc.join(1.0)


_PR_SET_PDEATHSIG = 1


def _die_with(parent: int) -> None:
    """Have the kernel kill this process when ``parent`` dies (Linux; elsewhere the pipe's
    end does it once a job ends)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # it died before the request was made
        os._exit(0)


def _serve(conn: multiprocessing.connection.Connection, parent: int) -> None:
    """The process: run each job as it comes, send back ``(True, result)`` or ``(False,
    exception)``; end at ``None`` or when the pipe closes."""
    for sig in _ENDED_BY_DAEMON:
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _ENDED_BY_DAEMON)
    _die_with(parent)
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        fn, args, kwargs = job
        try:
            reply: tuple[bool, Any] = (True, fn(*args, **kwargs))
        except Exception as exc:  # handed to whoever reads the future, as an executor does
            reply = (False, exc)
        try:
            try:
                conn.send(reply)
            except (OSError, ValueError):
                raise
            except Exception as exc:  # a result or an exception that does not pickle (nothing was sent)
                what = "result" if reply[0] else f"exception ({type(reply[1]).__name__}: {reply[1]})"
                conn.send((False, RuntimeError(f"the job's {what} does not pickle: {exc}")))
        except (OSError, ValueError):  # the daemon is gone
            return
