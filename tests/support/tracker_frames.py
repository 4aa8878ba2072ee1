"""Noisy frames of a 3x3 skin and a tracker on it: what the contact tracker's tests share."""

from __future__ import annotations

from cellbridge.tactile.contacts import ContactEstimator
from cellbridge.tactile.layout import grid_layout
from cellbridge.tactile.response import skin_response
from cellbridge.tactile.tracker import ContactTracker

MM = 1e-3
NOISE = 1e-15
LAY = grid_layout(3, 3)
CORNER_PRESS = [0.0185, 0.0225, 3.0, 0.020]  # across the corner of elements 0, 1, 3 and 4


def frame(contacts, rng, lay=LAY):
    dc1, dc2 = skin_response(lay, contacts)
    return dc1 + rng.normal(0, NOISE, lay.n), dc2 + rng.normal(0, NOISE, lay.n)


def tracker(**kw):
    return ContactTracker(ContactEstimator(LAY, noise=NOISE), **kw)


def _reads(at, fresh, stale_at=-0.5):
    """``read_at`` of a 3x3 frame: the elements in ``fresh`` read at ``at``, the others last
    read at ``stale_at`` (an event-based skin's held readings: a heartbeat before)."""
    return {e: (at if e in fresh else stale_at) for e in range(LAY.n)}
