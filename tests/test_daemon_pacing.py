"""The contact loop's schedule (``daemon.pacing``): estimates bounded by ``[contact] rate``
without a late one making every later one late, and looks that find nothing kept rare."""

from __future__ import annotations

import pytest
from cellbridge.daemon.core.pacing import BURST, EMPTY_LOOK_GAP, Pacer
from hypothesis import given, settings
from hypothesis import strategies as st

RATE = 100.0
PERIOD = 1.0 / RATE


def test_a_late_estimate_does_not_make_the_next_frame_late() -> None:
    """Frames come due every period. One estimate ran 6 ms after its frame was due (a
    read in the way): the next frame is estimated when it is due, not a whole period
    after the late one. A rest of a period after each estimate kept that 6 ms on every
    later frame (and on the next press's first contact)."""
    pacer = Pacer(RATE)
    t = 10.0
    for k in range(20):  # on time: each frame estimated at its due
        assert pacer.after_look(t + k * PERIOD, True, t + (k + 1) * PERIOD) <= t + (k + 1) * PERIOD
    late = t + 20 * PERIOD + 0.006
    nxt = pacer.after_look(late, True, t + 21 * PERIOD)
    assert nxt <= t + 21 * PERIOD + 1e-9, nxt - (t + 21 * PERIOD)
    for k in range(21, 40):  # and it stays on the frames' schedule
        assert pacer.after_look(t + k * PERIOD, True, t + (k + 1) * PERIOD) <= t + (k + 1) * PERIOD + 1e-9


def test_estimates_as_fast_as_they_are_allowed_settle_at_the_rate() -> None:
    pacer = Pacer(RATE)
    t, times = 5.0, []
    for _ in range(200):  # a frame always due: the loop looks as soon as it may
        times.append(t)
        t = pacer.after_look(t, True, t)
    assert times[1] == times[0]  # the bucket's second estimate at once
    span = times[-1] - times[0]
    assert len(times) - 1 <= span * RATE + BURST
    assert times[-1] - times[-2] == pytest.approx(PERIOD)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(0.0, 0.03), st.booleans(), st.floats(-0.02, 0.05)), min_size=1, max_size=200))
def test_no_window_holds_more_estimates_than_the_rate_allows(looks: list[tuple[float, bool, float]]) -> None:
    """Whatever data and dues do, a loop that looks only when allowed estimates at most
    ``BURST + rate * T`` times in any window of ``T`` s."""
    pacer = Pacer(RATE)
    t, allowed, done = 0.0, 0.0, []
    for wait, estimated, due in looks:
        t = max(t + wait, allowed)  # data or a due wakes the loop; never before it is allowed
        if estimated:
            done.append(t)
        allowed = pacer.after_look(t, estimated, t + due)
    for i, a in enumerate(done):
        for j in range(i, len(done)):
            assert j - i + 1 <= BURST + (done[j] - a) * RATE + 1e-9


def test_a_look_that_finds_nothing_waits_a_gap_or_until_due_and_a_due_that_brings_nothing_a_period() -> None:
    pacer = Pacer(RATE)
    assert pacer.after_look(1.0, False, 1.0005) == pytest.approx(1.0005)  # due sooner than the gap
    assert pacer.after_look(1.0, False, 1.5) == pytest.approx(1.0 + EMPTY_LOOK_GAP * PERIOD)
    assert pacer.after_look(1.0, False, 0.99) == pytest.approx(1.0 + PERIOD)  # due, none came: no spinning
    assert pacer.after_look(1.0, False, float("inf")) == pytest.approx(1.0 + EMPTY_LOOK_GAP * PERIOD)


def test_a_rate_that_is_no_rate_is_refused() -> None:
    with pytest.raises(ValueError):
        Pacer(0.0)
    with pytest.raises(ValueError):
        Pacer(RATE).set_rate(-1.0)


def test_a_frame_that_came_due_while_the_look_ran_is_looked_at_again_at_once() -> None:
    """The look began 0.3 ms before the frame was due and ended 0.5 ms after: nothing was
    found, yet the frame is there. Judged by the look's end (as the service did), "due and
    none came" rested a whole period (+10 ms on a press's first contact, real processes)."""
    pacer = Pacer(RATE)
    began, due, ended = 2.0, 2.0003, 2.0008
    assert pacer.after_look(began, False, due) <= ended
