"""The skin frame contacts are estimated on (``daemon.moment``), fed readings directly.

What a subscriber feels: how far behind ``now`` the estimated frame is. A held reading
(event-based reporting) stands for the frames after it, so an idle element whose last
heartbeat is long past must not hold the frame back, while one whose change may still be
on its way must, for as long as its own readings take to arrive.
"""

from __future__ import annotations

import numpy as np

from cellbridge.daemon.moment import Moments

PERIOD = 0.01  # 100 Hz
DELAY = 0.03  # each reading arrives 30 ms after its sample time


def _record(m: Moments, row: int, t: float, held: bool = True) -> None:
    rows = np.array([row])
    zero = np.zeros((2, 2))
    m.record(rows, np.array([t]), np.array([0], dtype=np.uint64), np.zeros((1, 2)), True, t + DELAY,
             zero + 1.0, zero + 0.5, np.array([held]), np.array([True]), np.array([PERIOD]))
    m.settle(rows, np.zeros(2, dtype=bool))


def test_an_idle_held_element_holds_the_frame_back_only_by_its_own_delivery_delay() -> None:
    m = Moments(2, 64)
    for k in range(50):  # both report for a while: their delivery delay is learnt
        _record(m, 0, 9.5 + k * PERIOD)
        _record(m, 1, 9.5 + k * PERIOD)
    for k in range(50, 81):  # element 0 is pressed and reports; element 1 is idle (held)
        _record(m, 0, 9.5 + k * PERIOD)
    now = 9.5 + 80 * PERIOD + DELAY
    t = m.moment(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
    # the frame trails now by element 1's delay (and a margin), not by its 0.3 s old reading
    assert now - t <= DELAY + 0.005 + PERIOD + 1e-9, now - t
    assert t <= now - DELAY  # never a frame a change of element 1 could not have reached us for


def test_a_held_element_never_heard_on_time_is_waited_for_up_to_held_wait() -> None:
    m = Moments(2, 64)
    for k in range(81):
        _record(m, 0, 9.5 + k * PERIOD)
    rows = np.array([1])
    zero = np.zeros((2, 2))
    m.record(rows, np.array([10.0]), np.array([0], dtype=np.uint64), np.zeros((1, 2)), True, 10.03,
             zero + 1.0, zero + 0.5, np.array([True]), np.array([False]), np.array([PERIOD]))
    m.settle(rows, np.zeros(2, dtype=bool))
    now = 10.3 + DELAY
    t = m.moment(now, timeout=2.0, max_lag=0.5, held_wait=0.2)
    assert abs(t - (now - 0.2)) <= PERIOD + 1e-9, t  # no delay known for it: held_wait behind now


def test_with_no_new_data_the_moment_moves_on_at_due_and_not_before() -> None:
    """An event-based skin sends a press's onset and then little: the frames after it come
    from the holds running out, with no data to wake a shell. ``due`` names when the next
    one is there; the shell estimates then (and a shell that waited for data took a press's
    next frames up to a heartbeat late)."""
    m = Moments(2, 64)
    for k in range(50):  # both report for a while: their delivery delay is learnt
        _record(m, 0, 9.5 + k * PERIOD)
        _record(m, 1, 9.5 + k * PERIOD)
    now = 9.5 + 49 * PERIOD + DELAY
    first = m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
    assert first is not None
    frames = [first.t]
    for _ in range(5):  # no data comes: each due brings the next frame, a moment earlier nothing
        due = m.due(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
        assert now < due < now + 2 * PERIOD, (now, due)
        assert m.take(due - 1e-4, timeout=2.0, max_lag=0.5, held_wait=0.5) is None
        got = m.take(due, timeout=2.0, max_lag=0.5, held_wait=0.5)
        assert got is not None and abs(got.t - (frames[-1] + PERIOD)) < 1e-9, (got, frames)
        frames.append(got.t)
        now = due


def test_due_is_never_while_a_periodic_element_is_waited_for() -> None:
    """A periodic element's frame comes only with its data: no time to wake for."""
    m = Moments(2, 64)
    for k in range(50):
        _record(m, 0, 9.5 + k * PERIOD)
        _record(m, 1, 9.5 + k * PERIOD, held=False)
    now = 9.5 + 49 * PERIOD + DELAY
    assert m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5) is not None
    assert m.due(now, timeout=2.0, max_lag=0.5, held_wait=0.5) == float("inf")
    assert m.due(now + 10.0, timeout=2.0, max_lag=0.5, held_wait=0.5) == float("inf")  # all silent
