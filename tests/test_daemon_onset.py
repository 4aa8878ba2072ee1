"""A press's onset frame: the untouched neighbours of a touch just begun are *unknown*
until they have reported past that frame (``daemon.moment.ONSET_WAIT``).

A press sets off the bridges under it at one instant and they contend for the same
cells; one retried after a collision reaches the host after its usual delivery delay.
Its held reading from before the press said "not touched", and a corner press seen on
three of its four elements was fitted as two contacts: an extra contact id.
"""

from __future__ import annotations

import numpy as np

from cellbridge.daemon.moment import DELAY_MARGIN, ONSET_WAIT, Moments
from cellbridge.tactile.layout import grid_layout

PERIOD = 0.01  # 100 Hz
DELAY = 0.005  # usual delivery delay of every element
T0 = 10.0  # the press's first frame


def _record(m: Moments, row: int, t: float, touched: bool, arrive: float) -> None:
    """One held (event-based) mesh-time reading of ``row`` taken at ``t``."""
    rows = np.array([row])
    thresholds = np.full((4, 2), 1.0)
    dc = np.full((1, 2), 2.0 if touched else 0.0)
    m.record(rows, np.array([t]), np.array([0], dtype=np.uint64), dc, True, arrive,
             thresholds, thresholds * 0.5, np.array([True]), np.array([True]), np.array([PERIOD]))
    flags = np.zeros(4, dtype=bool)
    flags[row] = touched
    m.settle(rows, flags)


def _skin() -> Moments:
    """A 2×2 skin whose four elements reported idle for a second (delays learnt)."""
    m = Moments(4, 256, grid_layout(2, 2).corner_edges)
    for k in range(100):
        t = T0 - 1.0 + k * PERIOD
        for row in range(4):
            _record(m, row, t, False, t + DELAY)
    return m


def _take(m: Moments, now: float) -> tuple[float, np.ndarray, np.ndarray]:
    got = m.take(now, timeout=2.0, max_lag=0.5)
    assert got is not None
    return got.t, got.touched, got.unknown


def test_a_neighbour_whose_onset_sample_is_late_is_unknown_not_untouched() -> None:
    m = _skin()
    for row in range(3):  # three of the four elements under a corner press report at once
        _record(m, row, T0, True, T0 + DELAY)
    t, touched, unknown = _take(m, T0 + DELAY + DELAY_MARGIN + 0.001)
    assert t == T0
    assert touched.tolist() == [True, True, True, False]
    # the fourth was retried: its held reading from before the press must not say "untouched"
    assert unknown.tolist() == [False, False, False, True]
    _record(m, 3, T0, True, T0 + 0.012)  # its sample of that frame arrives, late
    _record(m, 3, T0 + PERIOD, True, T0 + 0.013)
    for row in range(3):
        _record(m, row, T0 + PERIOD, True, T0 + PERIOD + DELAY)
    t, touched, unknown = _take(m, T0 + PERIOD + DELAY + DELAY_MARGIN + 0.001)
    assert t == T0 + PERIOD
    assert touched.all() and not unknown.any()


def test_a_neighbour_that_stays_untouched_is_known_in_the_frames_after_the_onset_wait() -> None:
    m = _skin()
    for row in range(3):
        _record(m, row, T0, True, T0 + DELAY)
    now = T0 + ONSET_WAIT + PERIOD + DELAY + DELAY_MARGIN + 0.001
    got = m.take(now, timeout=2.0, max_lag=0.5)
    assert got is not None and got.t >= T0 + ONSET_WAIT
    # nothing came from element 3: past the onset wait its held reading stands again
    assert not got.unknown[3] and not got.touched[3]
    assert got.touched[:3].all()


def test_a_frame_estimated_late_knows_the_neighbour_once_its_delay_and_the_onset_wait_passed() -> None:
    """The onset frame itself, estimated after the neighbour's delay plus the onset wait
    (the moment held back by a slower element): nothing can still be on its way."""
    m = _skin()
    for row in range(3):
        _record(m, row, T0, True, T0 + DELAY)
    dc, touched, _t, _cycle, unknown, _gap = m.at(T0, T0 + DELAY + DELAY_MARGIN + ONSET_WAIT + 0.001)
    assert not unknown.any() and touched.tolist() == [True, True, True, False]
    dc, touched, _t, _cycle, unknown, _gap = m.at(T0, T0 + DELAY + DELAY_MARGIN + ONSET_WAIT - 0.001)
    assert unknown.tolist() == [False, False, False, True]


def test_the_neighbours_of_a_steady_press_are_known() -> None:
    m = _skin()
    _record(m, 0, T0, True, T0 + DELAY)
    for k in range(1, 10):  # element 0 pressed for 90 ms; the others idle, silent
        _record(m, 0, T0 + k * PERIOD, True, T0 + k * PERIOD + DELAY)
    t, touched, unknown = _take(m, T0 + 9 * PERIOD + DELAY + DELAY_MARGIN + 0.001)
    assert t >= T0 + ONSET_WAIT + PERIOD
    assert touched.tolist() == [True, False, False, False]
    assert not unknown.any()


def test_the_onset_holds_no_frame_back() -> None:
    """Unknown instead of waited for: the onset frame comes as soon as it did before."""
    m = _skin()
    for row in range(3):
        _record(m, row, T0, True, T0 + DELAY)
    assert m.moment(T0 + DELAY + DELAY_MARGIN + 0.001, timeout=2.0, max_lag=0.5) == T0


def test_a_touch_whose_first_readings_arrive_in_one_batch_began_at_the_first() -> None:
    """A bridge retried under contention sends its queued samples together: the onset and
    the readings after it in one batch. Each touched reading of the batch counted as an
    onset (the hysteresis looked at the reading before the batch), so the touch 'began' at
    the batch's newest reading and its neighbours stayed unknown up to 30 ms past the
    documented window (40 ms after the press here)."""
    m = _skin()
    rows = np.zeros(5, dtype=np.int64)
    t = T0 + PERIOD * np.arange(5)
    thresholds = np.full((4, 2), 1.0)
    arrive = t[-1] + DELAY
    m.record(rows, t, np.zeros(5, dtype=np.uint64), np.full((5, 2), 2.0), False, arrive, thresholds,
             thresholds * 0.5, np.ones(5, dtype=bool), np.ones(5, dtype=bool), np.full(5, PERIOD))
    flags = np.array([True, False, False, False])
    m.settle(np.array([0]), flags)
    assert m.touch_began[0] == T0
    moment = T0 + 4 * PERIOD  # 40 ms into the touch: past the onset wait
    _dc, touched, _t, _cycle, unknown, _gap = m.at(moment, arrive + DELAY_MARGIN + 0.001)
    assert touched.tolist() == [True, False, False, False]
    assert not unknown.any()
