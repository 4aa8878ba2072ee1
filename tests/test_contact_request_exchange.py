"""The exchange of a request without its spec (``ContactWorker._submit``) attacked at each
point, on real worker processes: a worker that has no estimator under the request's
digest answers SpecNeeded, and the request goes again with its spec; here that worker is
killed, hung or made to forget between the two, the daemon stops meanwhile, or the layout
changes. What must hold: every estimate is answered or fails once (counted once, never a
future left pending), a stop starts no worker, a worker's answer after its replacement is
not used, and no contact is named by another layout's elements."""

from __future__ import annotations

import asyncio
import concurrent.futures
import logging
import os
import signal
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from cellbridge.daemon.core import contacts
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.contacts import ContactIdentity, ContactJob, ContactSnapshot, ContactSpec, EstimateRequest
from cellbridge.daemon.shell.contact_worker import ContactWorker, process_pool
from cellbridge.daemon.shell.worker_process import WorkerProcess
from cellbridge.tactile import SkinLayout, grid_layout, skin_response

from support.process_state import gone, until_gone

LIMIT = 300.0  #: s an answer may take (a cold warm-up compiles the kernels): a hang guard only
HUNG = 1.0  #: s the estimate of a stopped (SIGSTOP) worker is given: it never answers, so this bounds the test only
CONTACT = parse_config({"link": [{"name": "a", "url": "/dev/null"}]}).contact


def _forget_estimators() -> None:
    """Run in the worker: it drops every estimator it built (as when it keeps more owners')."""
    contacts._STAGES.clear()


Hook = Callable[["_Staged", EstimateRequest], None]


class _Staged(concurrent.futures.Executor):
    """A worker process whose requests pass ``hook`` first: before the worker gets each
    (``before``) and after (``after``), the test kills, stops or empties the worker."""

    def __init__(self, before: Hook | None = None, after: Hook | None = None) -> None:
        pool = process_pool()
        assert isinstance(pool, WorkerProcess)
        self.pool = pool
        self.before, self.after = before, after
        self.sent: list[EstimateRequest] = []

    @property
    def pid(self) -> int:
        assert self.pool.pid is not None
        return self.pool.pid

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        req = next((a for a in args if isinstance(a, EstimateRequest)), None)
        if req is not None:
            self.sent.append(req)
            if self.before is not None:
                self.before(self, req)
        fut = self.pool.submit(fn, *args, **kwargs)
        if req is not None and self.after is not None:
            self.after(self, req)
        return fut

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self.pool.shutdown(wait, cancel_futures=cancel_futures)

    def kill(self) -> None:
        self.pool.kill()


def _press(layout: SkinLayout, k: int, at: int) -> ContactSnapshot:
    x, y = layout.centres[at, :2]
    dc1, dc2 = skin_response(layout, [(float(x), float(y), 3.0, 0.012)])
    n = layout.n
    return ContactSnapshot(np.stack([dc1, dc2], axis=1), dc1 > 1e-13, 1.0 + 0.01 * k, np.ones(n),
                           np.arange(n, dtype=np.uint64), layout.ids, 1.0 + 0.01 * k)


class _Rig:
    """A contact worker on ``_Staged`` processes, and one press's jobs on a 4x4."""

    def __init__(self, before: Hook | None = None, after: Hook | None = None) -> None:
        self.made: list[_Staged] = []
        self.hooks = (before, after)
        self.cw = ContactWorker(logging.getLogger("exchange"), self._factory)
        self.layout = grid_layout(4, 4)
        self.spec = ContactSpec.of(self.layout, 2e-15, CONTACT)
        self.identity = ContactIdentity()
        self.k = 0

    def _factory(self) -> concurrent.futures.Executor:
        self.made.append(_Staged(*self.hooks))
        return self.made[-1]

    def job(self, spec: ContactSpec | None = None, layout: SkinLayout | None = None, at: int = 5) -> ContactJob:
        self.k += 1
        return self.identity.job(spec or self.spec, _press(layout or self.layout, self.k, at))

    def estimate(self, job: ContactJob, limit: float = LIMIT) -> list[dict[str, Any]] | None:
        got = asyncio.run(self.cw.estimate(job, limit))
        if got is not None:
            self.identity.published(job, got, lambda t: t)  # (a contact named by elements not of the job: KeyError)
        return got

    def close(self) -> None:
        pids = [s.pid for s in self.made]
        self.cw.close()
        for s in self.made:
            with_kill = not gone(s.pid)
            if with_kill:
                os.kill(s.pid, signal.SIGKILL)
            s.pool.shutdown(wait=False)
        for pid in pids:
            assert until_gone(pid), f"worker {pid} left running"


def _forget(staged: _Staged) -> None:
    staged.pool.submit(_forget_estimators).result(LIMIT)


def _is_retry(req: EstimateRequest, staged: _Staged) -> bool:
    """``req`` ships its spec right after the same owner's request without it: the retry."""
    return req.spec is not None and len(staged.sent) >= 2 and staged.sent[-2].spec is None


@pytest.mark.parametrize("point", ["killed before the retry", "killed after the retry", "hung on the retry"])
def test_a_worker_lost_during_the_retry_fails_that_estimate_once_and_the_next_goes_on(
        warm_kernels: None, point: str) -> None:
    def before(staged: _Staged, req: EstimateRequest) -> None:
        if point == "killed before the retry" and _is_retry(req, staged):
            staged.kill()

    def after(staged: _Staged, req: EstimateRequest) -> None:
        if _is_retry(req, staged):
            if point == "killed after the retry":
                staged.kill()
            elif point == "hung on the retry":
                os.kill(staged.pid, signal.SIGSTOP)

    rig = _Rig(before, after)
    try:
        rig.cw.start()
        first = rig.estimate(rig.job())
        assert first and len(first) == 1
        _forget(rig.made[0])
        lost = rig.estimate(rig.job(), HUNG if point == "hung on the retry" else LIMIT)
        assert lost is None  # the retry's worker was lost: this estimate failed ...
        assert [r.spec is not None for r in rig.made[0].sent] == [True, False, True]
        assert rig.cw.stats["errors"] == 1 and rig.cw.stats["worker_restarts"] == 1  # ... once
        assert not rig.cw.working
        assert until_gone(rig.made[0].pid)
        again = rig.estimate(rig.job())  # the new worker gets the spec with its first request
        assert again and len(again) == 1 and again[0]["id"] == first[0]["id"]  # the press's track continued
        assert len(rig.made) == 2 and rig.made[1].sent[0].spec is not None
        assert rig.cw.stats["errors"] == 1
    finally:
        rig.close()


def test_a_stop_during_a_hung_retry_starts_no_worker(warm_kernels: None) -> None:
    def after(staged: _Staged, req: EstimateRequest) -> None:
        if _is_retry(req, staged):
            os.kill(staged.pid, signal.SIGSTOP)

    rig = _Rig(after=after)
    try:
        rig.cw.start()
        assert rig.estimate(rig.job())
        _forget(rig.made[0])
        rig.cw.stop()  # the daemon's drain: its last estimate, whose retry hangs
        assert rig.estimate(rig.job(), HUNG) is None
        assert rig.cw.stats["errors"] == 1 and not rig.cw.working
        assert rig.estimate(rig.job(), HUNG) is None  # stopping, and no worker: none started
        assert len(rig.made) == 1 and until_gone(rig.made[0].pid)
        assert rig.cw.stats["errors"] == 1
    finally:
        rig.close()


def test_a_layout_change_between_spec_needed_and_the_retry_names_each_contact_by_its_own_layout(
        warm_kernels: None) -> None:
    """Two layouts of the same count of elements (a bridge replaced: other ids): the retry
    carries its own job's spec, and the next job, of the other layout, ships its own."""
    other = SkinLayout(grid_layout(4, 4).centres[:, :2].copy() + 0.5, side=grid_layout(4, 4).side,
                       ids=np.arange(100, 116, dtype=np.int64))
    rig = _Rig()
    other_spec = ContactSpec.of(other, 2e-15, CONTACT)
    try:
        rig.cw.start()
        assert rig.estimate(rig.job())
        ids = {"a": set(int(i) for i in rig.layout.ids), "b": set(int(i) for i in other.ids)}
        plan = ["a", "forget", "a", "b", "forget", "b", "a", "forget", "b", "a", "b"]
        for step in plan:
            if step == "forget":
                _forget(rig.made[0])
                continue
            job = rig.job(*((None, None) if step == "a" else (other_spec, other)))
            got = rig.estimate(job)
            assert got and len(got) == 1, step
            assert set(got[0]["elements"]) <= ids[step], (step, got[0]["elements"])
        assert rig.cw.stats["errors"] == 0 and len(rig.made) == 1
    finally:
        rig.close()
