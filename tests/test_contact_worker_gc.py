"""The contact worker's process keeps its long-lived objects (modules, compiled kernels, the
estimators it built) out of the cyclic collector's full passes: over the humanoid's
estimator one such pass took about 60 ms of the worker's CPU and came every several
seconds, stalling whichever frame's estimate it fell in. An estimate run inline (tests,
tools, the offline driver) leaves its caller's collector as it is."""

from __future__ import annotations

import gc

import numpy as np
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.contacts import ContactJob, ContactSnapshot, ContactSpec, estimate, warm_up
from cellbridge.daemon.shell.contact_worker import process_pool
from cellbridge.daemon.shell.worker_process import WorkerProcess
from cellbridge.tactile import grid_layout, skin_response

LIMIT = 300.0  #: s a job may take: a cold warm-up compiles the kernels


def _job(owner: str) -> ContactJob:
    """One press on a 4x4 skin, to be estimated by ``owner``'s estimator (built for it)."""
    layout = grid_layout(4, 4)
    dc1, dc2 = skin_response(layout, [(0.02, 0.02, 3.0, 0.012)])
    spec = ContactSpec.of(layout, 2e-15, parse_config({"link": [{"name": "a", "url": "/dev/null"}]}).contact)
    n = layout.n
    snap = ContactSnapshot(np.stack([dc1, dc2], axis=1), dc1 > 1e-13, 1.0, np.ones(n), np.zeros(n, np.uint64),
                           layout.ids, 1.0)
    return ContactJob(owner, spec, snap)


def test_the_worker_process_freezes_its_warm_up_and_each_estimator_it_builds(warm_kernels: None) -> None:
    pool = process_pool()
    assert isinstance(pool, WorkerProcess)  # the production executor: a process
    try:
        pool.submit(warm_up).result(LIMIT)
        after_warm_up = pool.submit(gc.get_freeze_count).result(LIMIT)
        assert after_warm_up > 10_000  # the modules and kernels at least
        assert pool.submit(estimate, _job("a").request(b"", True)).result(LIMIT)  # the press: a contact
        after_build = pool.submit(gc.get_freeze_count).result(LIMIT)
        assert after_build > after_warm_up  # the new estimator's objects too
        assert pool.submit(estimate, _job("a").request(b"", True)).result(LIMIT)  # the same spec: nothing built, nothing more
        assert pool.submit(gc.get_freeze_count).result(LIMIT) == after_build
    finally:
        pool.kill()
        pool.shutdown(wait=True)


def test_an_inline_estimate_leaves_its_callers_collector_alone() -> None:
    frozen = gc.get_freeze_count()
    warm_up()
    assert estimate(_job(f"inline {id(object())}").request(b"", True))
    assert gc.get_freeze_count() == frozen
