"""The contact worker's executor with the daemon's event loop reading its results
(daemon/shell/worker_process.py, ``WorkerProcess(loop)``): results in order and in the loop's
thread, a result in pieces, a process that dies or is killed, shutdown, no descriptor or
registration left behind; and the framing the loop parses (a property test)."""

from __future__ import annotations

import asyncio
import concurrent.futures
import os
import signal
import struct
import threading
import time

import pytest
from cellbridge.daemon.shell import contact_worker
from cellbridge.daemon.shell.worker_process import BrokenWorker, WorkerProcess, _messages
from hypothesis import given
from hypothesis import strategies as st

from support.process_state import until_gone


def _big(n: int) -> bytes:
    return b"r" * n


async def _result(fut: concurrent.futures.Future[object], limit: float = 30.0) -> object:
    async with asyncio.timeout(limit):
        return await asyncio.wrap_future(fut)


def test_results_come_in_order_and_complete_in_the_loops_thread() -> None:
    async def main() -> None:
        w = WorkerProcess(asyncio.get_running_loop())
        try:
            seen: list[str] = []
            futs = [w.submit(pow, 2, i) for i in range(200)]
            futs[0].add_done_callback(lambda _: seen.append(threading.current_thread().name))
            assert [await _result(f) for f in futs] == [2 ** i for i in range(200)]
            assert seen == [threading.current_thread().name]  # no result thread in between
            assert not any(t.name == "contact-worker-results" for t in threading.enumerate())
            with pytest.raises(ZeroDivisionError):
                await _result(w.submit(divmod, 1, 0))
            assert await _result(w.submit(pow, 3, 2)) == 9
        finally:
            w.kill()
            w.shutdown(wait=True)

    asyncio.run(main())


def test_a_result_larger_than_one_read_comes_whole_after_its_pieces() -> None:
    async def main() -> None:
        w = WorkerProcess(asyncio.get_running_loop())
        try:
            futs = [w.submit(_big, n) for n in (5 * 1024 * 1024, 1, 70_000, 0)]
            got = [await _result(f) for f in futs]
            assert [len(g) for g in got] == [5 * 1024 * 1024, 1, 70_000, 0]  # type: ignore[arg-type]
        finally:
            w.kill()
            w.shutdown(wait=True)

    asyncio.run(main())


def test_a_process_that_dies_fails_the_pending_and_every_later_future_and_leaves_the_loop() -> None:
    async def main() -> None:
        loop = asyncio.get_running_loop()
        watched0 = len(loop._selector.get_map())  # type: ignore[attr-defined]
        w = WorkerProcess(loop)
        assert await _result(w.submit(pow, 2, 2)) == 4
        slow = w.submit(time.sleep, 30)
        await asyncio.sleep(0.2)
        assert w.pid is not None
        os.kill(w.pid, signal.SIGKILL)  # (dies by itself: an estimate that crashed the interpreter)
        with pytest.raises(BrokenWorker):
            await _result(slow, 10)
        with pytest.raises(BrokenWorker):
            await _result(w.submit(pow, 2, 2), 10)
        watched = len(loop._selector.get_map())  # type: ignore[attr-defined]
        assert watched == watched0, "the loop still watches the dead worker's pipe"  # (its number is soon another's)

    asyncio.run(main())


def test_kill_ends_a_hung_job_at_once_and_replacements_leave_nothing_behind() -> None:
    async def main() -> None:
        loop = asyncio.get_running_loop()
        w = WorkerProcess(loop)
        hung = w.submit(time.sleep, 60)
        await asyncio.sleep(0.2)
        t = time.monotonic()
        w.kill()
        with pytest.raises(BrokenWorker):
            await _result(hung, 5)
        assert time.monotonic() - t < 5
        await asyncio.sleep(0.3)
        fds0 = len(os.listdir("/proc/self/fd"))
        watched0 = len(loop._selector.get_map())  # type: ignore[attr-defined]
        pids = []
        for _ in range(30):  # as ContactWorker._replace does
            w = WorkerProcess(loop)
            pids.append(w.pid)
            w.submit(pow, 2, 2)
            contact_worker._kill(w)
        del w
        assert all(until_gone(p) for p in pids if p)
        await asyncio.sleep(0.3)
        assert len(loop._selector.get_map()) == watched0  # type: ignore[attr-defined]
        assert len(os.listdir("/proc/self/fd")) - fds0 <= 6  # (a leak per worker would be 30 or more)

    asyncio.run(main())


def test_end_takes_the_last_results_and_the_process_exits() -> None:
    async def main() -> None:
        w = WorkerProcess(asyncio.get_running_loop())
        futs = [w.submit(pow, 2, i) for i in range(20)]
        assert w.end(10.0) is True  # (the loop's thread waits: the results are read at the end)
        assert [f.result(0) for f in futs] == [2 ** i for i in range(20)]
        with pytest.raises(RuntimeError):
            w.submit(pow, 2, 2)

    asyncio.run(main())


def test_the_daemons_executor_is_read_by_the_running_loop() -> None:
    async def main() -> str:
        pool = contact_worker.process_pool()
        assert isinstance(pool, WorkerProcess)
        try:
            done: list[str] = []
            fut = pool.submit(pow, 2, 3)
            fut.add_done_callback(lambda _: done.append(threading.current_thread().name))
            assert await _result(fut) == 8
            return done[0]
        finally:
            pool.end(5.0)

    assert asyncio.run(main()) == threading.current_thread().name
    pool = contact_worker.process_pool()  # outside a loop: a result thread
    try:
        names: list[str] = []
        fut = pool.submit(pow, 2, 2)
        fut.add_done_callback(lambda _: names.append(threading.current_thread().name))
        fut.result(30)
        time.sleep(0.05)
        assert names == ["contact-worker-results"]
    finally:
        assert isinstance(pool, WorkerProcess)
        pool.end(5.0)


def _frame(msg: bytes) -> bytes:
    return struct.pack("!i", len(msg)) + msg


@given(st.lists(st.binary(max_size=300), max_size=12), st.lists(st.integers(1, 400), max_size=40))
def test_the_framing_gives_every_message_whole_and_in_order_however_the_bytes_come(
        msgs: list[bytes], cuts: list[int]) -> None:
    wire = b"".join(_frame(m) for m in msgs)
    inbox = bytearray()
    got: list[bytes] = []
    at = 0
    for c in [*cuts, len(wire)]:
        inbox += wire[at:at + c]
        at += c
        got += _messages(inbox)
        assert len(inbox) < 4 or len(inbox) < 4 + struct.unpack_from("!i", inbox)[0]  # nothing whole left
    assert got == msgs and not inbox


def test_the_framing_reads_a_length_over_2_gib_as_multiprocessing_writes_it() -> None:
    inbox = bytearray(struct.pack("!i", -1) + struct.pack("!Q", 3) + b"abc" + _frame(b"z"))
    assert _messages(inbox) == [b"abc", b"z"] and not inbox
    part = bytearray(struct.pack("!i", -1) + b"\0\0")
    assert _messages(part) == [] and len(part) == 6
