"""Attacks on what crosses to the contact worker (:class:`EstimateRequest`, the spec by its
digest) and on the exchange around it (``ContactWorker._submit``): each failed before its
fix.

- An estimate queued behind a hung warm-up on an executor that cancels what it has not
  started (a thread pool's ``shutdown(cancel_futures=True)``, as a hung worker's kill does)
  left the estimate's future pending for ever: the callback that hands on the answer raised
  on the cancelled future, so the worker stayed ``working`` and a stop skipped its last
  estimate.
- Specs equal as values but with other digests (``-0.0`` and ``0.0`` in a band, as the
  worker compares what it keeps) cost every estimate two round trips and the spec shipped
  again: the worker kept the first spec's digest, refused each request by the second's
  (SpecNeeded), and on the spec shipped kept its estimator, and the old digest.
- Readings of the right count but another shape or dtype (``unknown`` as int64, a third
  column, ``touched`` as floats) were estimated as whatever they made: int64 ``unknown``
  was taken as indices, so the contacts were bounded by other elements than the frame's
  unknown ones.
- A request read the cached digest (``_key``) twice, around its own write of it: a retry's
  write from the results thread in between named the request by the other spec's digest
  (refused by the worker unless it kept that spec for the owner: a needless round trip)."""

from __future__ import annotations

import asyncio
import concurrent.futures
import dataclasses
import logging
import threading
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from cellbridge.daemon.core import contacts
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.contacts import (
    ContactIdentity,
    ContactJob,
    ContactSnapshot,
    ContactSpec,
    EstimateRequest,
    estimate,
)
from cellbridge.daemon.shell.contact_worker import ContactWorker, InlineExecutor
from cellbridge.tactile import grid_layout, skin_response
from cellbridge.tactile.skin_geometry import Band

CONTACT = parse_config({"link": [{"name": "a", "url": "/dev/null"}]}).contact
LAYOUT = grid_layout(4, 4)
SPEC = ContactSpec.of(LAYOUT, 2e-15, CONTACT)


def _snapshot(k: int = 0, unknown: np.ndarray | None = None) -> ContactSnapshot:
    """Frame ``k`` of one press on element 5 of a 4x4."""
    x, y = LAYOUT.centres[5, :2]
    dc1, dc2 = skin_response(LAYOUT, [(float(x), float(y), 3.0, 0.012)])
    n = LAYOUT.n
    return ContactSnapshot(np.stack([dc1, dc2], axis=1), dc1 > 1e-13, 1.0 + 0.01 * k, np.ones(n),
                           np.arange(n, dtype=np.uint64), LAYOUT.ids, 1.0 + 0.01 * k, unknown)


class _HungWarmUp(concurrent.futures.ThreadPoolExecutor):
    """One thread whose warm-up never ends until ``release`` is set: every estimate waits
    behind it, and a kill (``shutdown(cancel_futures=True)``) cancels them."""

    def __init__(self, release: threading.Event) -> None:
        super().__init__(1)
        self.release = release

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        if fn.__name__ == "warm_up":
            return super().submit(self.release.wait)
        return super().submit(fn, *args, **kwargs)


def test_an_estimate_cancelled_by_the_kill_of_its_hung_worker_is_not_left_pending() -> None:
    release = threading.Event()
    made: list[_HungWarmUp] = []

    def factory() -> concurrent.futures.Executor:
        made.append(_HungWarmUp(release))
        return made[-1]

    cw = ContactWorker(logging.getLogger("attack"), factory)
    cw.start()
    cw.stop()  # a stop's drain: its estimate has a bound, and the hung worker is not replaced
    try:
        job = ContactIdentity().job(SPEC, _snapshot())
        assert asyncio.run(cw.estimate(job, 0.05)) is None  # behind the hung warm-up: timed out
        assert cw.stats["errors"] == 1 and cw.stats["worker_restarts"] == 1
        assert not cw.working, "the cancelled estimate's future is pending for ever"
    finally:
        release.set()
        cw.close()
        for pool in made:
            pool.shutdown(wait=True)


class _Noting(InlineExecutor):
    """Inline, noting whether each request handed over carried its spec."""

    def __init__(self) -> None:
        self.shipped: list[bool] = []

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future[Any]:
        self.shipped.extend(a.spec is not None for a in args if isinstance(a, EstimateRequest))
        return super().submit(fn, *args, **kwargs)


def test_an_equal_spec_of_another_digest_is_shipped_once_not_with_every_estimate() -> None:
    banded = dataclasses.replace(SPEC, bands=(Band(0.0, 0.08, 0.0, 0.07),))
    same = dataclasses.replace(SPEC, bands=(Band(-0.0, 0.08, 0.0, 0.07),))
    assert banded == same and banded.digest() != same.digest()  # (the premise)
    made: list[_Noting] = []

    def factory() -> concurrent.futures.Executor:
        made.append(_Noting())
        return made[-1]

    contacts._STAGES.clear()
    cw = ContactWorker(logging.getLogger("attack"), factory)
    identity = ContactIdentity()
    got = [cw.estimate_now(identity.job(banded if k < 2 else same, _snapshot(k))) for k in range(6)]
    assert all(len(c) == 1 and c[0]["id"] == got[0][0]["id"] for c in got)  # one press, one track throughout
    # the new digest refused once and its spec shipped, then the digest alone again (each
    # later estimate was refused and shipped: [..., False, True, False, True, False, True])
    assert made[0].shipped == [True, False, False, True, False, False, False], made[0].shipped


def _request(**change: Any) -> EstimateRequest:
    return dataclasses.replace(ContactJob("attack", SPEC, _snapshot()).request(SPEC.digest(), True), **change)


_N = LAYOUT.n
_DC = _snapshot().dc


@pytest.mark.parametrize(("change", "says"), [
    ({"unknown": np.ones(_N, dtype=np.int64)}, "unknown"),
    ({"unknown": np.zeros(_N - 1, dtype=bool)}, "unknown"),
    ({"touched": _snapshot().touched.astype(np.float64)}, "touched"),
    ({"touched": _snapshot().touched[:-1]}, "touched"),
    ({"dc": np.concatenate([_DC, _DC[:, :1]], axis=1)}, "dc"),
    ({"dc": _DC[:, 0].copy()}, "dc"),
    ({"dc": _DC.astype(object)}, "dc"),
    ({"dc": _DC.tolist()}, "dc"),
])
def test_readings_of_another_shape_or_dtype_are_refused_saying_which(change: dict[str, Any], says: str) -> None:
    contacts._STAGES.clear()
    with pytest.raises(ValueError, match=says):
        estimate(_request(**change))
    assert len(estimate(_request())) == 1  # the next request is estimated as ever


def test_nan_readings_of_unknown_elements_are_still_estimated() -> None:
    """What the host sends for an element without a reading (NaN ΔC, flagged unknown) is no
    hostile request: the checks above leave it to the estimator."""
    contacts._STAGES.clear()
    unknown = np.zeros(_N, dtype=bool)
    unknown[0] = True
    dc = _DC.copy()
    dc[0] = np.nan
    got = estimate(_request(dc=dc, unknown=unknown))
    assert len(got) == 1 and got[0]["unknown_near"] == [int(LAYOUT.ids[0])]


class _Interleaved(ContactWorker):
    """A contact worker whose ``_key`` runs ``between`` at the first read after a write: the
    results thread sending a request again (its spec's digest written to ``_key``) between
    the caller's write and its read."""

    def __init__(self) -> None:
        self._key_now: tuple[ContactSpec, bytes] | None = None
        self._wrote = False
        self.between: Callable[[], object] | None = None
        super().__init__(logging.getLogger("attack"), InlineExecutor)

    @property
    def _key(self) -> tuple[ContactSpec, bytes] | None:
        if self._wrote and self.between is not None:
            between, self.between = self.between, None
            between()
        self._wrote = False
        return self._key_now

    @_key.setter
    def _key(self, value: tuple[ContactSpec, bytes] | None) -> None:
        self._key_now, self._wrote = value, True


def test_a_request_is_named_by_its_own_specs_digest_whatever_the_results_thread_wrote_meanwhile() -> None:
    other = dataclasses.replace(SPEC, noise=3e-15)  # (the layout's noise reloaded: another spec)
    identity = ContactIdentity()
    cw = _Interleaved()
    old, new = identity.job(SPEC, _snapshot(0)), identity.job(other, _snapshot(1))
    cw.estimate_now(old)
    cw.between = lambda: cw._request(old, ship=True)  # a retry of the spec before, from the results thread
    req = cw._request(new)
    assert req.key == other.digest(), "the request names the other spec's estimator"
