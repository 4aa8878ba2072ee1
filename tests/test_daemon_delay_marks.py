"""Which delay mark a held neighbour of a touch is waited by (daemon/moment.py, ``Moments._hold``).
The rule: past the onset window (``ONSET_WAIT``) of a touch, the touched element and its
neighbours are waited for by their highest delay mark; within it, an untouched neighbour
is unknown until it reported (``_onset_pending``). Here element 1 had one delivery 60 ms late half a second
before (its highest mark), and its touched reading of the press's spread onto it comes
25 ms late. No frame taken after that reading's sample may call element 1 untouched."""

from __future__ import annotations

import numpy as np
import pytest

from cellbridge.daemon.moment import Moments
from cellbridge.tactile.layout import grid_layout

PERIOD, DELAY, T0 = 0.01, 0.005, 10.0


def _record(m: Moments, row: int, t: float, touched: bool, arrive: float) -> None:
    rows = np.array([row])
    th = np.full((4, 2), 1.0)
    m.record(rows, np.array([t]), np.array([0], dtype=np.uint64), np.full((1, 2), 2.0 if touched else 0.0), True,
             arrive, th, th * 0.5, np.array([True]), np.array([True]), np.array([PERIOD]))
    flags = m.touched[m._all, (m.count - 1) % m.depth].copy()
    flags[row] = touched
    m.settle(rows, flags)


def _frames_calling_the_neighbour_untouched(b_at: float, late: float, look: float) -> list[tuple[float, float]]:
    """Element 0 pressed from T0; element 1 (its neighbour) touched from T0 + b_at, that
    reading ``late`` s in delivery; the skin looked at every ``look`` s (a contact loop
    whose estimates take that long). (frame, look) of each frame with element 1 known
    and untouched at or after its touched sample."""
    m = Moments(4, 256, grid_layout(2, 2).corner_edges)
    for k in range(100):  # a second idle: delays learnt; one frame of element 1 retried (60 ms)
        t = round(T0 - 1.0 + k * PERIOD, 6)
        for row in range(4):
            _record(m, row, t, False, t + (0.060 if row == 1 and k == 50 else DELAY))
    events = [(round(T0 + k * PERIOD, 6) + DELAY, 0, round(T0 + k * PERIOD, 6)) for k in range(20)]
    tb = round(T0 + b_at, 6)
    events += [(max(tb + k * PERIOD + DELAY, tb + late), 1, round(tb + k * PERIOD, 6)) for k in range(10)]
    events.sort()
    bad, now, i = [], T0 - 0.01, 0
    while now < T0 + 0.2:
        now = round(now + look, 6)
        while i < len(events) and events[i][0] <= now:
            _record(m, events[i][1], events[i][2], True, events[i][0])
            i += 1
        got = m.take(now, timeout=2.0, max_lag=0.5)
        if got is not None and got.t >= tb - 1e-9 and not got.unknown[1] and not got.touched[1]:
            bad.append((round(got.t - T0, 3), round(now - T0, 3)))
    return bad


@pytest.mark.parametrize("b_at", [0.03, 0.04])
def test_the_first_frame_past_the_onset_wait_waits_for_a_neighbour_by_its_highest_mark(b_at: float) -> None:
    """Looked at every 5 ms: at the first frame past ONSET_WAIT the touch is no longer
    'just begun' (no onset wait); the mark was chosen by the *last taken* moment, still
    inside ONSET_WAIT, and the neighbour was waited for by its second mark only."""
    assert _frames_calling_the_neighbour_untouched(b_at, 0.025, 0.005) == []


def test_a_look_after_a_slow_estimate_waits_for_a_neighbour_by_its_highest_mark() -> None:
    """Looked at every 40 ms (the loop awaits each estimate): the moment jumped from a frame
    within ONSET_WAIT of the touch to one 50 ms into it, with the neighbour waited for by
    its second mark."""
    assert _frames_calling_the_neighbour_untouched(0.05, 0.025, 0.04) == []
