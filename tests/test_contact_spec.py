"""A contact job's spec (``ContactSpec``: the layout's ids and centres as int64 and float64
array bytes) and its snapshot, as the worker takes them: what does not make one layout of
the snapshot's elements is refused with an error that says which, never estimated.

Bytes that are not whole int64 ids or (x, y) float64 pairs, counts of ids and centres that
differ, and a snapshot of other elements than the spec's were read as whatever the bytes
made (an error about buffer sizes or reshapes, or contacts named by elements the frame
does not have: the host's contact loop then failed on them)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.contacts import ContactJob, ContactSnapshot, ContactSpec, EstimateRequest, estimate
from cellbridge.tactile import grid_layout, skin_response

LAYOUT = grid_layout(4, 4)
SPEC = ContactSpec.of(LAYOUT, 2e-15, parse_config({"link": [{"name": "a", "url": "/dev/null"}]}).contact)


def _snapshot(ids: np.ndarray = LAYOUT.ids) -> ContactSnapshot:
    dc1, dc2 = skin_response(LAYOUT, [(0.02, 0.02, 3.0, 0.012)])
    n = LAYOUT.n
    return ContactSnapshot(np.stack([dc1, dc2], axis=1), dc1 > 1e-13, 1.0, np.ones(n), np.zeros(n, np.uint64),
                           ids, 1.0)


def _shipped(spec: ContactSpec, snap: ContactSnapshot, owner: str) -> EstimateRequest:
    """A request with ``spec`` as the worker may get it: past the host's own checks
    (:meth:`ContactJob.request`), so the worker's are what stands."""
    return EstimateRequest(owner, b"", spec, snap.dc, snap.touched, snap.t_host, snap.t_frame, snap.unknown, 0, ())


@pytest.mark.parametrize(("ids", "centres", "says"), [
    (SPEC.ids[:-1], SPEC.centres, "ids are 127 bytes"),
    (SPEC.ids, SPEC.centres[:-8], "centres are 248 bytes"),
    (SPEC.ids + SPEC.ids[:8], SPEC.centres, "17 ids and 16 centres"),
    (np.asarray(LAYOUT.ids, dtype=np.int32).tobytes(), SPEC.centres, "8 ids and 16 centres"),
])
def test_a_spec_whose_bytes_make_no_layout_is_refused_saying_why(ids: bytes, centres: bytes, says: str) -> None:
    spec = dataclasses.replace(SPEC, ids=ids, centres=centres)
    with pytest.raises(ValueError, match=f"contact spec: {says}"):
        spec.build()
    with pytest.raises(ValueError, match=f"contact spec: {says}"):
        ContactJob(f"spec {says}", spec, _snapshot()).request(b"", True)
    with pytest.raises(ValueError, match=f"contact spec: {says}"):
        estimate(_shipped(spec, _snapshot(), f"spec {says}"))


def test_a_snapshot_of_other_elements_than_its_spec_is_refused() -> None:
    """The same count of elements, other ids: the estimate named its contacts by the spec's
    ids, which the host then looked up in the snapshot's."""
    assert estimate(ContactJob("spec same ids", SPEC, _snapshot()).request(SPEC.digest(), True))  # (a contact)
    other = np.asarray(LAYOUT.ids, dtype=np.int64) + 1000
    with pytest.raises(ValueError, match="contact job: the snapshot's 16 elements are not its spec's 16"):
        ContactJob("spec same ids", SPEC, _snapshot(other)).request(SPEC.digest(), False)
    fewer = _snapshot()
    fewer = dataclasses.replace(fewer, dc=fewer.dc[:-1], touched=fewer.touched[:-1])
    with pytest.raises(ValueError, match="contact job: the snapshot's 15 elements are not its spec's 16"):
        estimate(_shipped(SPEC, fewer, "spec same ids"))  # (past the host's check: the worker's own)
    assert estimate(ContactJob("spec same ids", SPEC, _snapshot()).request(SPEC.digest(), False))  # kept, goes on


def test_the_worker_process_refuses_a_hostile_spec_and_goes_on(warm_kernels: None) -> None:
    """In the production executor (a real process): each malformed job fails alone with the
    error that says why, and the same process estimates the next good job."""
    from cellbridge.daemon.shell.contact_worker import process_pool
    from cellbridge.daemon.shell.worker_process import WorkerProcess

    pool = process_pool()
    assert isinstance(pool, WorkerProcess)
    try:
        pid = pool.pid
        bad = [dataclasses.replace(SPEC, ids=SPEC.ids[:-3]),
               dataclasses.replace(SPEC, ids=np.asarray(LAYOUT.ids, dtype=np.int32).tobytes()),
               dataclasses.replace(SPEC, centres=SPEC.centres[:-8])]
        for spec in bad:
            with pytest.raises(ValueError, match="contact spec: "):
                pool.submit(estimate, _shipped(spec, _snapshot(), "hostile")).result(300)
        snap = _snapshot()
        fewer = dataclasses.replace(snap, dc=snap.dc[:-1], touched=snap.touched[:-1])
        with pytest.raises(ValueError, match="contact job: "):
            pool.submit(estimate, _shipped(SPEC, fewer, "hostile")).result(300)
        assert pool.submit(estimate, _shipped(SPEC, snap, "hostile")).result(300)
        assert pool.pid == pid and pool._proc.is_alive()
    finally:
        pool.kill()
        pool.shutdown(wait=True)
