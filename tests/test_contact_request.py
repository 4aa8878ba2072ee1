"""What crosses to the contact worker (:class:`EstimateRequest`): the spec goes along until
the worker has answered a request of it, and after that its digest alone; a worker without
the estimator a digest names (replaced, or one that dropped it) is sent the spec again, at
once, and the estimate is not lost.

A humanoid's job pickled to about 80 kB, its unchanging spec 28 kB of it and the sample
times, cycle counts and ids the host keeps (to publish the contacts) most of the rest:
more than a pipe holds, so each job's write waited for the worker to read."""

from __future__ import annotations

import concurrent.futures
import logging
import pickle
from collections.abc import Callable
from typing import Any

import numpy as np
from cellbridge.daemon.core import contacts
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.contacts import ContactIdentity, ContactJob, ContactSnapshot, ContactSpec, EstimateRequest
from cellbridge.daemon.shell.contact_worker import ContactWorker, process_pool
from cellbridge.daemon.shell.worker_process import WorkerProcess
from cellbridge.tactile import SkinLayout, grid_layout, skin_response

LIMIT = 300.0  #: s a job may take: a cold warm-up compiles the kernels
CONTACT = parse_config({"link": [{"name": "a", "url": "/dev/null"}]}).contact


def _jobs(layout: SkinLayout, count: int) -> list[ContactJob]:
    """``count`` jobs of one press on ``layout``, from one owner, on one spec."""
    spec = ContactSpec.of(layout, 2e-15, CONTACT)
    identity = ContactIdentity()
    x, y = layout.centres[layout.n // 2, :2]
    dc1, dc2 = skin_response(layout, [(float(x) + 0.01, float(y), 3.0, 0.012)])
    n = layout.n
    out = []
    for k in range(count):
        snap = ContactSnapshot(np.stack([dc1, dc2], axis=1), dc1 > 1e-13, 1.0 + k * 0.01, np.ones(n),
                               np.arange(n, dtype=np.uint64), layout.ids, 1.0 + k * 0.01)
        out.append(identity.job(spec, snap))
    return out


class _Noting(concurrent.futures.Executor):
    """The production executor (a worker process), noting every request handed to it."""

    def __init__(self) -> None:
        pool = process_pool()
        assert isinstance(pool, WorkerProcess)
        self.pool = pool
        self.sent: list[EstimateRequest] = []

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        self.sent.extend(a for a in args if isinstance(a, EstimateRequest))
        return self.pool.submit(fn, *args, **kwargs)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self.pool.shutdown(wait, cancel_futures=cancel_futures)

    def kill(self) -> None:
        self.pool.kill()


def _worker() -> tuple[ContactWorker, list[_Noting]]:
    """A contact worker on production worker processes, and the executors it made (each
    noting the requests it was handed)."""
    made: list[_Noting] = []

    def factory() -> concurrent.futures.Executor:
        made.append(_Noting())
        return made[-1]

    return ContactWorker(logging.getLogger("request"), factory), made


def _forget_estimators() -> None:
    """Run in the worker: it drops every estimator it built (as it drops an owner's when it
    keeps more than a few owners')."""
    contacts._STAGES.clear()


def test_a_spec_goes_to_the_worker_once_and_then_its_digest_alone(warm_kernels: None) -> None:
    layout = grid_layout(32, 36)  # a humanoid's count of elements
    jobs = _jobs(layout, 3)
    cw, made = _worker()
    try:
        got = [cw.estimate_now(j) for j in jobs]
        sent = made[0].sent
        assert [r.spec is not None for r in sent] == [True, False, False]
        assert {r.key for r in sent} == {jobs[0].spec.digest()}
        assert all(len(c) == 1 for c in got) and got[1][0]["id"] == got[2][0]["id"]  # one press, one track
        whole, slim = len(pickle.dumps(jobs[1])), len(pickle.dumps(sent[1]))
        assert slim < 0.35 * whole and slim < 64 * 1024, (whole, slim)  # (within a pipe's buffer)
    finally:
        cw.close()


def test_a_worker_without_the_estimator_is_sent_the_spec_again_and_the_estimate_is_not_lost(
        warm_kernels: None) -> None:
    layout = grid_layout(4, 4)
    jobs = _jobs(layout, 4)
    cw, made = _worker()
    try:
        first = cw.estimate_now(jobs[0])
        made[0].pool.submit(_forget_estimators).result(LIMIT)
        again = cw.estimate_now(jobs[1])  # the digest alone, refused (SpecNeeded), then the spec
        assert [r.spec is not None for r in made[0].sent] == [True, False, True]
        assert len(again) == 1 and again[0]["id"] == first[0]["id"]  # the rebuilt tracker continued it
        assert cw.stats["errors"] == 0
        cw.estimate_now(jobs[2])
        assert made[0].sent[-1].spec is None  # answered: the digest alone again
    finally:
        cw.close()


def test_a_replaced_worker_gets_the_spec_with_its_first_request(warm_kernels: None) -> None:
    import asyncio

    layout = grid_layout(4, 4)
    jobs = _jobs(layout, 3)
    cw, made = _worker()
    try:
        cw.start()
        assert asyncio.run(cw.estimate(jobs[0], LIMIT))
        made[0].kill()  # the worker dies: the next estimate fails and a new worker starts
        assert asyncio.run(cw.estimate(jobs[1], LIMIT)) is None and len(made) == 2
        got = asyncio.run(cw.estimate(jobs[2], LIMIT))
        assert got and len(got) == 1
        assert made[1].sent[0].spec is not None and cw.stats["errors"] == 1
    finally:
        cw.close()


def test_a_replaced_worker_builds_the_estimator_on_an_untouched_frame_not_on_the_first_touch(
        warm_kernels: None) -> None:
    """A new worker has no estimator: the first job after the replacement runs even on an
    idle skin, so that the build is paid before a press, not by the press's first estimate
    (the same rule as a layout that changed on an idle skin)."""
    import asyncio

    layout = grid_layout(4, 4)
    spec = ContactSpec.of(layout, 2e-15, CONTACT)
    identity = ContactIdentity()
    n = layout.n

    def untouched(k: int) -> ContactJob:
        t = 1.0 + k * 0.01
        return identity.job(spec, ContactSnapshot(np.zeros((n, 2)), np.zeros(n, dtype=bool), t, np.ones(n),
                                                  np.arange(n, dtype=np.uint64), layout.ids, t))

    cw, made = _worker()
    try:
        cw.start()
        quiet = CONTACT.max_missed + 3
        for k in range(quiet):  # the estimator is built, then an idle skin asks nothing more
            assert asyncio.run(cw.estimate(untouched(k), LIMIT)) == []
        asked = len(made[0].sent)
        assert asked < quiet
        made[0].kill()
        cw._replace()  # as a hung or dead worker is replaced
        assert len(made) == 2
        assert asyncio.run(cw.estimate(untouched(quiet), LIMIT)) == []
        assert len(made[1].sent) == 1 and made[1].sent[0].spec is not None  # built now, on the idle skin
        assert asyncio.run(cw.estimate(untouched(quiet + 1), LIMIT)) == []
        assert len(made[1].sent) == 1  # and then idle again
    finally:
        cw.close()
