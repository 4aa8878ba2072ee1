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

The process is spawned (a fork would copy the daemon's sockets). It ignores SIGINT (a
Ctrl-C in a terminal reaches the whole process group; the daemon decides when its worker
ends) and exits when its pipe closes: at :meth:`WorkerProcess.shutdown`, and when the
daemon dies, however it dies.
"""

from __future__ import annotations

import collections
import concurrent.futures
import concurrent.futures.process
import multiprocessing
import multiprocessing.connection
import signal
import threading
from collections.abc import Callable
from typing import Any

BrokenWorker = concurrent.futures.process.BrokenProcessPool  #: what a job's future holds when the process died


class WorkerProcess(concurrent.futures.Executor):
    """An executor of one spawned process. :meth:`submit` sends the job at once, from the
    caller's thread (jobs are small: a contact job pickles to about 2.5 KB, well inside a
    pipe's buffer); a result thread completes the futures in order. A process that dies
    fails every pending future, and every later one, with ``BrokenProcessPool``."""

    def __init__(self) -> None:
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=True)
        self._proc = ctx.Process(target=_serve, args=(child,), name="cellbridge-contact-worker", daemon=True)
        self._proc.start()
        child.close()  # the child's end lives in the child only: its exit is our EOF
        self._pending: collections.deque[concurrent.futures.Future[Any]] = collections.deque()
        self._lock = threading.Lock()
        self._broken = ""  # why the process can take no more jobs ("" while it can)
        self._shut = False
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
        with self._lock:
            if self._shut:
                raise RuntimeError("cannot submit to a worker process after shutdown")
            if self._broken:
                fut.set_exception(BrokenWorker(self._broken))
                return fut
            self._pending.append(fut)
            try:
                self._conn.send((fn, args, kwargs))
            except (OSError, ValueError) as exc:  # the process's end is gone
                self._pending.pop()
                fut.set_exception(BrokenWorker(f"the contact worker process is gone: {exc}"))
        return fut

    def _read(self) -> None:
        while True:
            try:
                ok, value = self._conn.recv()
            except (EOFError, OSError):
                break
            with self._lock:
                if not self._pending:  # a result that came in as the process was killed
                    continue
                fut = self._pending.popleft()
            if ok:
                fut.set_result(value)
            else:
                fut.set_exception(value)
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
        self._fail("the contact worker process was killed")

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """No more jobs: the process ends once it has run those sent (at once with
        ``cancel_futures``: killed). ``wait``: until it has ended."""
        with self._lock:
            first, self._shut = not self._shut, True
        if cancel_futures:
            self.kill()
        elif first:
            with self._lock:
                try:
                    self._conn.send(None)  # (the process reads it after the jobs before it)
                except (OSError, ValueError):
                    pass  # gone already
        if wait:
            self._proc.join()
            self._reader.join()

    def end(self, wait: float) -> bool:
        """Shut down and give the process ``wait`` s to exit, then kill it; whether it exited
        by itself (a stopped or stuck process kept the daemon from exiting)."""
        self.shutdown(wait=False)
        self._proc.join(wait)
        if self._proc.is_alive():
            self.kill()
            self._proc.join(1.0)
            return False
        return True


def _serve(conn: multiprocessing.connection.Connection) -> None:
    """The process: run each job as it comes, send back ``(True, result)`` or ``(False,
    exception)``; end at ``None`` or when the pipe closes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
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
