"""How long a contact job waits to start in the worker process, and for its result to reach
the event loop, while the loop is busy as the daemon's is around a press.

Run: ``.venv/bin/python bench/bench_worker_handoff.py [--jobs N]``.

The loop runs reads of 1-5 ms of small-array numpy work (what a serial read costs the
daemon around a press: docs/time.md) with 0-2 ms gaps; every 3-12 ms a job of 0.8 ms (an
estimate of a press) is submitted and awaited. Compared: the standard library's
``ProcessPoolExecutor`` (one spawned process; at Python's default GIL switch interval,
5 ms, and at the daemon's, 0.5 ms) and the daemon's ``WorkerProcess``. Same seed, same
loads: the table shows what the hand-offs cost, not the job.
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import multiprocessing
import random
import sys
import time

import numpy as np
from cellbridge.daemon.shell.service import GIL_SWITCH_INTERVAL
from cellbridge.daemon.shell.worker_process import WorkerProcess

from timing import table

JOB_S = 0.0008


def job(_: int) -> float:
    """A job of JOB_S s; returns when it began (the monotonic clock is the machine's)."""
    t = time.monotonic()
    while time.monotonic() - t < JOB_S:
        pass
    return t


def _read(rng: random.Random) -> None:
    a = np.arange(16.0)
    t = time.perf_counter()
    ms = rng.uniform(1.0, 5.0)
    while time.perf_counter() - t < ms / 1e3:
        (a * 2 + 1).sum()
        np.isnan(a).any()


async def _reads(rng: random.Random) -> None:
    while True:
        _read(rng)
        await asyncio.sleep(rng.uniform(0.0, 0.002))


async def _measure(ex: concurrent.futures.Executor, jobs: int, seed: int) -> tuple[list[float], list[float]]:
    ex.submit(job, 0).result()  # the process is up
    reads = asyncio.create_task(_reads(random.Random(seed)))
    rng = random.Random(seed + 1)
    began, total = [], []
    try:
        for i in range(jobs):
            await asyncio.sleep(rng.uniform(0.003, 0.012))
            t = time.monotonic()
            start = await asyncio.wrap_future(ex.submit(job, i))
            began.append((start - t) * 1e3)
            total.append((time.monotonic() - t) * 1e3)
    finally:
        reads.cancel()
    return began, total


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=400, help="jobs per executor (default 400)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()
    rows = []
    default = sys.getswitchinterval()
    cases = [("ProcessPoolExecutor", default), ("ProcessPoolExecutor", GIL_SWITCH_INTERVAL),
             ("WorkerProcess", GIL_SWITCH_INTERVAL)]
    for name, interval in cases:
        sys.setswitchinterval(interval)
        ex: concurrent.futures.Executor = (
            concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
            if name == "ProcessPoolExecutor" else WorkerProcess())
        try:
            began, total = asyncio.run(_measure(ex, args.jobs, args.seed))
        finally:
            ex.shutdown(wait=True)
        for what, ms in (("submitted -> began", began), ("submitted -> result in the loop", total)):
            a = np.asarray(ms)
            rows.append([name, f"{interval * 1e3:g}", what,
                         *(f"{np.percentile(a, q):.2f}" for q in (50, 90, 99)), f"{a.max():.2f}"])
    sys.setswitchinterval(default)
    table(f"a {JOB_S * 1e3:g} ms job, {args.jobs} of them, with the loop busy 1-5 ms per read",
          ["executor", "GIL switch ms", "what", "p50 ms", "p90 ms", "p99 ms", "max ms"], rows)


if __name__ == "__main__":
    main()
