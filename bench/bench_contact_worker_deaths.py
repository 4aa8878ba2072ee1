"""Many contact estimates on the production worker process with its deaths sprinkled in:
what each costs (estimates lost, errors counted, restarts), whether a press keeps its
contact id across them, and whether anything is left behind (file descriptors, threads,
processes).

Run: ``.venv/bin/python bench/bench_contact_worker_deaths.py [--estimates N] [--seed S]``.

A press moves across a 4x4 skin and is lifted every 40 frames for 5. Before an estimate,
at seeded random points, the worker is killed as the request reaches it, stopped
(SIGSTOP: hung, the estimate times out after 2 s), or made to drop its estimators (its
next request without the spec is refused, SpecNeeded, and sent again with it). Each
death must cost exactly the estimate under way (one error, one restart); a forget costs
no estimate; the contact ids must follow the presses.
"""

from __future__ import annotations

import argparse
import asyncio
import concurrent.futures
import gc
import logging
import multiprocessing
import os
import random
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from cellbridge.daemon.core import contacts
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.contacts import ContactIdentity, ContactSnapshot, ContactSpec, EstimateRequest
from cellbridge.daemon.shell.contact_worker import ContactWorker, process_pool
from cellbridge.daemon.shell.worker_process import WorkerProcess
from cellbridge.tactile import grid_layout, skin_response

from timing import table

HUNG_S = 2.0  #: the estimate timeout of this run: a stopped worker is killed after it
PRESS = 40  #: frames of one press and its lift
LIFT = 5  #: frames of the lift

CONTACT = parse_config({"link": [{"name": "a", "url": "/dev/null"}]}).contact
LAYOUT = grid_layout(4, 4)


def _forget_estimators() -> None:
    """Run in the worker: it drops every estimator it built."""
    contacts._STAGES.clear()


class _Staged(concurrent.futures.Executor):
    """The worker process, with an action to take on it right after the next request is sent."""

    def __init__(self) -> None:
        pool = process_pool()
        assert isinstance(pool, WorkerProcess)
        self.pool = pool
        self.action: Callable[[WorkerProcess], None] | None = None
        self.retries = 0
        self._last: EstimateRequest | None = None

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        fut = self.pool.submit(fn, *args, **kwargs)
        req = next((a for a in args if isinstance(a, EstimateRequest)), None)
        if req is not None:
            if self._last is not None and self._last.spec is None and req.spec is not None:
                self.retries += 1  # (the request after one without a spec, with it: sent again)
            self._last = req
            if self.action is not None:
                act, self.action = self.action, None
                act(self.pool)
        return fut

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self.pool.shutdown(wait, cancel_futures=cancel_futures)

    def kill(self) -> None:
        self.pool.kill()


def _frame(k: int) -> ContactSnapshot:
    n = LAYOUT.n
    t = 1.0 + k * 0.01
    if k % PRESS >= PRESS - LIFT:
        dc = np.zeros((n, 2))
        return ContactSnapshot(dc, np.zeros(n, dtype=bool), t, np.ones(n), np.arange(n, dtype=np.uint64), LAYOUT.ids, t)
    x = 0.01 + 0.06 * (k % PRESS) / (PRESS - LIFT)
    dc1, dc2 = skin_response(LAYOUT, [(x, 0.035, 3.0, 0.012)])
    return ContactSnapshot(np.stack([dc1, dc2], axis=1), dc1 > 1e-13, t, np.ones(n), np.arange(n, dtype=np.uint64),
                           LAYOUT.ids, t)


def _live_children() -> list[int]:
    """This process's children that still run (not zombies), multiprocessing's resource tracker aside."""
    out = []
    for task in os.listdir("/proc/self/task"):
        with open(f"/proc/self/task/{task}/children") as f:
            out += [int(p) for p in f.read().split()]
    live = []
    for pid in out:
        try:
            with open(f"/proc/{pid}/stat") as f:
                state = f.read().split(")")[-1].split()[0]
            with open(f"/proc/{pid}/cmdline") as f:
                tracker = "resource_tracker" in f.read()
        except FileNotFoundError:
            continue
        if state != "Z" and not tracker:
            live.append(pid)
    return live


def _fds() -> int:
    return len(os.listdir("/proc/self/fd")) - 1  # (the listing's own)


async def _run(estimates: int, seed: int) -> list[list[object]]:
    rng = random.Random(seed)
    made: list[_Staged] = []

    def factory() -> concurrent.futures.Executor:
        made.append(_Staged())
        return made[-1]

    spec = ContactSpec.of(LAYOUT, 2e-15, CONTACT)
    cw = ContactWorker(logging.getLogger("deaths"), factory)
    logging.getLogger("deaths").setLevel(logging.CRITICAL)
    identity = ContactIdentity()
    cw.start()
    await cw.warm(300.0)
    job = identity.job(spec, _frame(0))
    identity.published(job, await cw.estimate(job, 300.0) or [], lambda t: t)
    before = (_fds(), threading.active_count(), len(_live_children()))
    kills = hangs = forgets = lost = 0
    ids: dict[int, set[int]] = {}  # press -> the ids it was published under
    newest, back = -1, False  # ids are handed out in order: a new one below one seen went back
    cpu0 = os.times()
    for k in range(1, estimates):
        r, cur = rng.random(), made[-1]
        if r < 0.004:
            cur.action, kills = WorkerProcess.kill, kills + 1
        elif r < 0.006:
            cur.action, hangs = (lambda p: os.kill(p.pid or 0, signal.SIGSTOP)), hangs + 1
        elif r < 0.012:
            cur.pool.submit(_forget_estimators).result(300.0)
            forgets += 1
        job = identity.job(spec, _frame(k))
        got = await cw.estimate(job, HUNG_S)
        if got is None:
            lost += 1
            await cw.warm(300.0)
            continue
        identity.published(job, got, lambda t: t)
        for c in got:
            ids.setdefault(k // PRESS, set()).add(c["id"])
            back = back or c["id"] < newest
            newest = max(newest, c["id"])
    cpu1 = os.times()
    retries = sum(s.retries for s in made)
    pids = [s.pool.pid for s in made]
    cw.close()
    for s in made:
        s.pool.shutdown(wait=True)
    del made[:]
    multiprocessing.active_children()  # (reaps the killed workers)
    gc.collect()
    after = (_fds(), threading.active_count(), len(_live_children()))
    split = sum(len(v) > 1 for v in ids.values())
    return [["estimates", estimates], ["kills / hangs / forgets", f"{kills} / {hangs} / {forgets}"],
            ["estimates lost", lost], ["errors counted", cw.stats["errors"]],
            ["worker restarts", cw.stats["worker_restarts"]], ["requests sent again (SpecNeeded)", retries],
            ["presses / with more than one id", f"{len(ids)} / {split}"],
            ["an id went back", back],
            ["workers started", len(pids)],
            ["fds / threads / live children before", "{} / {} / {}".format(*before)],
            ["fds / threads / live children after close", "{} / {} / {}".format(*after)],
            ["CPU user+sys s: daemon side / workers",
             f"{cpu1.user - cpu0.user + cpu1.system - cpu0.system:.1f} / "
             f"{cpu1.children_user - cpu0.children_user + cpu1.children_system - cpu0.children_system:.1f}"]]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--estimates", type=int, default=2000)
    ap.add_argument("--seed", type=int, default=43)
    args = ap.parse_args()
    t0 = time.perf_counter()
    rows = asyncio.run(_run(args.estimates, args.seed))
    table(f"contact worker deaths, seed {args.seed} ({time.perf_counter() - t0:.0f} s)", ["", "value"], rows)


if __name__ == "__main__":
    main()
