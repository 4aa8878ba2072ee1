"""The skin frame contacts are estimated on (``daemon.moment``), fed readings directly.

What a subscriber feels: how far behind ``now`` the estimated frame is. A held reading
(event-based reporting) stands for the frames after it, so an idle element whose last
heartbeat is long past must not hold the frame back, while one whose change may still be
on its way must, for as long as its own readings take to arrive.
"""

from __future__ import annotations

import math

import numpy as np

from cellbridge.daemon.moment import DELAY_FORGET_S, DELAY_MARGIN, Moments

PERIOD = 0.01  # 100 Hz
DELAY = 0.03  # each reading arrives 30 ms after its sample time


def _record(m: Moments, row: int, t: float, held: bool = True, period: float = PERIOD, delay: float = DELAY) -> None:
    """One mesh-time reading of ``row`` taken at ``t``, arriving ``delay`` later."""
    rows = np.array([row])
    zero = np.zeros((2, 2))
    m.record(rows, np.array([t]), np.array([0], dtype=np.uint64), np.zeros((1, 2)), True, t + delay,
             zero + 1.0, zero + 0.5, np.array([held]), np.array([True]), np.array([period]))
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


def test_bridges_at_different_rates_are_known_at_every_frame_between_their_samples() -> None:
    """One bridge set to 250 Hz (control ``set rate`` with a ``bridge``), its neighbour at
    100 Hz. At a frame of one rate the other has no sample of that instant, and its last
    sample is its reading there, as a held reading is: it was taken, nothing is lost. Each
    element was unknown at a third of the frames (a contact on it ended and was born again).
    A sample that was due and did not come still makes its element unknown."""
    m = Moments(2, 128)
    unknown = np.zeros(2, dtype=int)
    taken = told = 0
    lost = 2.50  # the 100 Hz sample of this instant never arrives
    for k in range(3000):  # 1 ms steps
        t = round(k * 0.001, 6)
        if k % 10 == 0 and t != lost:
            _record(m, 0, t, held=False, period=0.01)
        if k % 4 == 0:
            _record(m, 1, t, held=False, period=0.004)
        got = m.take(t + DELAY, 2.0, 0.5)
        if got is None or got.t < 1.0:
            continue
        if lost <= got.t < lost + 0.01:
            assert got.unknown[0], got.t  # its sample of 2.50 was due: unknown until the next one
            told += 1
            continue
        taken += 1
        unknown += got.unknown
    assert taken > 250 and told and not unknown.any(), (taken, told, unknown)


def test_the_delay_mark_forgets_between_readings_too() -> None:
    """The delay a held element is waited for forgets with ``DELAY_FORGET_S`` whether it
    reports 100 times a second or a heartbeat in 10 s: the mark only decayed when a reading
    came, so after one late heartbeat the frame trailed by ``held_wait`` until the next."""
    m = Moments(2, 64)
    for k in range(1500):  # element 0 periodic at 100 Hz; element 1 held, a heartbeat every 10 s
        t = round(k * PERIOD, 6)
        _record(m, 0, t, held=False)
        if k == 0:
            _record(m, 1, t, delay=2.0)  # delivered 2 s late: the mark is 2 s
    now = 14.99 + DELAY  # 13 s after that reading arrived, before the next heartbeat
    lag = now - m.moment(now, timeout=30.0, max_lag=0.5, held_wait=0.5)
    expected = 2.0 * math.exp(-(now - 2.0) / DELAY_FORGET_S) + DELAY_MARGIN  # ~0.15 s
    assert lag <= expected + PERIOD + 1e-9, (lag, expected)


def test_one_late_delivery_does_not_hold_the_frames_back_but_two_do() -> None:
    """A held element is waited for by the second-highest delay it had lately: one frame
    of its late by an acknowledgement wait (a retry, here 60 ms) held every frame of the
    skin back by that much for seconds (press p99 in real processes), while two late
    ones say the route is slow now."""
    def lag(late: list[int]) -> float:
        m = Moments(2, 64)
        for k in range(100):  # element 0 pressed, reporting; element 1 held, its heartbeats
            t = round(9.0 + k * PERIOD, 6)
            _record(m, 0, t)
            if k % 10 == 0:
                _record(m, 1, t, delay=0.06 if k in late else DELAY)
        now = 9.0 + 99 * PERIOD + DELAY
        return now - m.moment(now, timeout=2.0, max_lag=0.5, held_wait=0.5)

    steady = lag([])
    assert steady <= DELAY + DELAY_MARGIN + PERIOD + 1e-9, steady
    assert lag([50]) == steady  # one retry: as if it had come on time
    assert lag([30, 60]) >= 0.06 * math.exp(-0.4 / DELAY_FORGET_S), lag([30, 60])  # two: waited for


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


def _learnt_and_taken() -> tuple[Moments, float]:
    """Two held elements that reported 50 frames (their delivery delay learnt), and the
    host time at which their newest frame was taken."""
    m = Moments(2, 64)
    for k in range(50):
        _record(m, 0, 9.5 + k * PERIOD)
        _record(m, 1, 9.5 + k * PERIOD)
    now = 9.5 + 49 * PERIOD + DELAY
    assert m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5) is not None
    return m, now


def test_a_frame_whose_holds_ran_out_before_anyone_looked_is_due_at_once() -> None:
    """A shell wakes a little after ``due`` (timer slack, a read in between) and asks
    again before it looks: the frame it woke for is there now. ``due`` named the frame
    after it, so the shell slept a whole frame more and the press's first frame was
    skipped (+10 ms on about a tenth of presses, real processes, bench_press_latency --trace)."""
    m, now = _learnt_and_taken()
    due = m.due(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
    woke = due + 0.002  # 2 ms late
    assert m.due(woke, timeout=2.0, max_lag=0.5, held_wait=0.5) <= woke
    got = m.take(woke, timeout=2.0, max_lag=0.5, held_wait=0.5)
    assert got is not None
    assert m.due(woke, timeout=2.0, max_lag=0.5, held_wait=0.5) > woke  # taken: the next one is later


def test_a_frame_held_back_by_a_transition_is_not_due_until_the_frame_after_it() -> None:
    """An element touched in its newest reading, timed from its arrival (its bridge lost
    mesh time), and untouched in the one before: the press fell somewhere between them,
    so the frames between are held back (:meth:`Moments.take`). ``due`` must not call
    them due now (a shell would look, find nothing and rest a whole period)."""
    m, now = _learnt_and_taken()
    t = 9.5 + 60 * PERIOD  # element 0 pressed: its first touched reading, after ten quiet frames
    zero = np.zeros((2, 2))
    now = t + 0.005
    m.record(np.array([0]), np.array([t]), np.array([0], dtype=np.uint64), np.full((1, 2), 2.0), True, now,
             zero + 1.0, zero + 0.5, np.array([True]), np.array([False]), np.array([PERIOD]))
    assert m.moment(now, timeout=2.0, max_lag=0.5, held_wait=0.5) > m.t_moment  # a new frame, before t
    assert m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5) is None  # held back: in transition
    assert m.due(now, timeout=2.0, max_lag=0.5, held_wait=0.5) > now


def test_the_frame_before_a_held_elements_onset_is_taken_with_its_held_reading() -> None:
    """Event-based, on mesh time: the bridge sampled every frame since its held reading and
    sends a change at once, so a frame before its onset sample is known from the held
    reading; it is no transition. Holding it back skipped a press's first frame whenever a
    neighbour's touch began one frame later and its reading came first (+10 ms on about a
    tenth of presses, real processes, bench_press_latency --trace)."""
    m, now = _learnt_and_taken()
    t = 9.5 + 60 * PERIOD  # element 0's onset, after ten frames its held reading stood for
    zero = np.zeros((2, 2))
    now = t + 0.005
    m.record(np.array([0]), np.array([t]), np.array([0], dtype=np.uint64), np.full((1, 2), 2.0), True, now,
             zero + 1.0, zero + 0.5, np.array([True]), np.array([True]), np.array([PERIOD]))
    m.settle(np.array([0]), np.array([True, False]))
    frame = m.moment(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
    assert m.t_moment < frame < t
    got = m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
    assert got is not None and got.t == frame
    assert not got.touched[0] and not got.unknown[0]  # its held reading: untouched, known


def test_an_idle_event_based_skin_off_mesh_time_is_looked_at_once_a_frame_not_back_to_back() -> None:
    """Every bridge without mesh time (``NO_MESH_TIME``: booting, cut off, or firmware that
    has none), event-based and idle: its readings are timed from their arrival, so the
    moment is off the frame grid and moves on with ``now``. ``due`` said "now" after every
    look, and a look that finds nothing touched costs the pacer nothing (it ships no
    estimate): the contact loop looked again at once, back to back, a core at 100 %
    (6000 looks a second at 0.1 ms each, here). A moment less than a period past the
    last one taken is no new frame."""
    from cellbridge.daemon.pacing import Pacer

    m = Moments(2, 64)
    zero = np.zeros((2, 2))
    for k in range(50):
        for row in (0, 1):
            t = 9.5 + k * PERIOD
            m.record(np.array([row]), np.array([t]), np.array([0], dtype=np.uint64), np.zeros((1, 2)), True,
                     t + DELAY, zero + 1.0, zero + 0.5, np.array([True]), np.array([False]), np.array([PERIOD]))
            m.settle(np.array([row]), np.zeros(2, dtype=bool))
    pacer, now, looks, taken, cost = Pacer(1.0 / PERIOD), 10.1, 0, 0, 1e-4
    while now < 12.1:  # the service's contact loop (daemon/service.py _contacts), a look costing 0.1 ms
        now = max(now, min(m.due(now, 2.0, 0.5, 0.5), now + 0.1))  # woken at due (or by the tick)
        began = now
        got = m.take(now, 2.0, 0.5, held_wait=0.5)
        if began >= 11.1:  # the second second (in the first, no delay known: held_wait behind)
            looks += 1
            taken += got is not None
        now += cost
        # nothing touched, no track: not shipped to the worker, not counted as an estimate
        now = max(now, pacer.after_look(began, False, m.due(now, 2.0, 0.5, 0.5)))
    assert looks <= 2.0 / PERIOD, looks
    assert taken >= 0.8 / PERIOD, taken  # and the moment still moves on, about a frame a period


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


def test_adopt_keeps_the_newest_readings_that_fit_in_either_depth() -> None:
    """A layout that grew (or a SIGHUP that changed ``max_lag``, so the depth) keeps each
    carried element's newest readings, newest last, as many as both rings hold."""
    for old_depth, new_depth in ((8, 5), (5, 8), (6, 6)):
        for count in (0, 3, 5, 6, 13):
            old = Moments(2, old_depth)
            for k in range(count):
                _record(old, 1, float(k))
            new = Moments(3, new_depth)
            new.adopt(old, np.array([2]), np.array([1]))
            n = int(new.count[2])
            kept = [float(new.t[2, (n - 1 - i) % new_depth]) for i in range(min(n, new_depth))]
            assert kept == [float(count - 1 - i) for i in range(min(count, old_depth, new_depth))]
            assert new.t_moment == old.t_moment and np.isnan(new.t[0]).all()


def test_an_element_without_a_baseline_is_unknown_not_untouched() -> None:
    """After a tare (or at start) an element has no baseline until ``n_baseline`` quiet
    readings came: the calibrator gives no ΔC (NaN), and on an event-based skin an idle
    element sends one reading a heartbeat, so that is ~50 s. Its readings, and the ones
    the tare told to forget, said nothing, yet the contact message listed no element as
    unknown: a press there was simply not seen (virtual 4x4, event:40, a 3 N corner press
    6 s after a tare: no contact, ``unknown`` empty)."""
    m = Moments(2, 64)
    for k in range(50):
        _record(m, 0, 9.5 + k * PERIOD)
        _record(m, 1, 9.5 + k * PERIOD)
    m.forget(np.array([1]))  # a tare of element 1: its readings so far no longer count
    now = 9.5 + 49 * PERIOD + DELAY + 0.006
    got = m.take(now, timeout=2.0, max_lag=0.5)
    assert got is not None and got.unknown.tolist() == [False, True]
    rows = np.array([1])  # a reading after the tare, while the baseline is still collected
    zero = np.zeros((2, 2))
    m.record(rows, np.array([10.0]), np.array([0], dtype=np.uint64), np.full((1, 2), np.nan), True, 10.0 + DELAY,
             zero + 1.0, zero + 0.5, np.array([True]), np.array([True]), np.array([PERIOD]))
    m.settle(rows, np.zeros(2, dtype=bool))
    _record(m, 0, 10.0)
    got = m.take(10.0 + DELAY + 0.006, timeout=2.0, max_lag=0.5)
    assert got is not None and got.t == 10.0 and got.unknown.tolist() == [False, True]


def test_an_idle_skin_has_nothing_unseen_until_a_reading_newer_than_its_last_frame_comes() -> None:
    """The contact loop's idle rule (``Pipeline.contact_due(now, idle=True)``): after a frame
    with nothing to track, the frames after it repeat its held readings, so they are looked
    at only once a newer reading came. An idle event-based skin was otherwise looked at
    once a period whatever ``[contact] rate`` (rate 1: 1.2 % of a core idle became 11.6 %),
    while the onset of a press must still be taken when its frame is due, not at the tick."""
    m, now = _learnt_and_taken()
    assert not m.unseen()  # every reading is in the frame taken: nothing to look at
    for _ in range(30):  # frames of held readings come due; taken, they change nothing
        due = m.due(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
        assert math.isfinite(due)  # (without the idle rule a shell would wake for each)
        now = max(now, due)
        assert m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5) is not None
        assert not m.unseen()
    t = m.t_moment + 3 * PERIOD  # a press's onset on element 0, on mesh time
    zero = np.zeros((2, 2))
    m.record(np.array([0]), np.array([t]), np.array([0], dtype=np.uint64), np.full((1, 2), 2.0), True, t + DELAY,
             zero + 1.0, zero + 0.5, np.array([True]), np.array([True]), np.array([PERIOD]))
    m.settle(np.array([0]), np.array([True, False]))
    assert m.unseen()  # a reading past the last frame: its frame is worth a look when due
    now, taken = t + DELAY, []
    while m.unseen() and len(taken) < 10:  # the frames up to the onset's, each when due
        now = max(now, m.due(now, timeout=2.0, max_lag=0.5, held_wait=0.5))
        got = m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
        assert got is not None
        taken.append(got)
    assert taken[-1].t == t and taken[-1].touched[0]  # the onset's frame, then nothing unseen
    assert now <= t + DELAY + 2 * DELAY_MARGIN + 1e-9, now - t  # when due: not at a tick 0.1 s on


def _onset(m: Moments, row: int, t: float, now: float, held: bool = True) -> None:
    """Element ``row``'s reading of frame ``t`` says touched (a press's onset), arriving at ``now``."""
    zero = np.zeros((2, 2))
    m.record(np.array([row]), np.array([t]), np.array([0], dtype=np.uint64), np.full((1, 2), 2.0), True, now,
             zero + 1.0, zero + 0.5, np.array([held]), np.array([True]), np.array([PERIOD]))
    touched = np.zeros(2, dtype=bool)
    touched[row] = True
    m.settle(np.array([row]), touched)


def _idle_frames_taken(k: int) -> tuple[Moments, float]:
    """:func:`_learnt_and_taken`, then ``k`` more frames taken when due, on the two
    elements' held readings (no new data), and the host time of the last look."""
    m, now = _learnt_and_taken()
    for _ in range(k):
        now = max(now, m.due(now, timeout=2.0, max_lag=0.5, held_wait=0.5))
        assert m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5) is not None
    return m, now


def test_a_frame_estimated_before_its_late_onset_came_is_taken_again_at_once() -> None:
    """An onset later than the frame's holds: the bridges under a press send at one instant
    and contend for the cells, so the first touched reading can reach the host after its
    frame was taken with the element's held, untouched reading. That frame is taken again
    as soon as the onset comes, not left to the next frame (+10 ms on 10 of 120 presses of
    a traced run on real processes, bench_press_latency --trace, the tenth that made p99)."""
    m, now = _idle_frames_taken(3)
    frame = m.t_moment
    now += 0.004
    _onset(m, 0, frame, now)  # its reading of the frame already taken: touched
    assert m.unseen()  # (an idle skin's loop looks again)
    assert m.due(now, timeout=2.0, max_lag=0.5, held_wait=0.5) <= now
    got = m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5)
    assert got is not None and got.t == frame and got.touched[0] and not got.touched[1]
    assert m.retaken == 1
    assert m.take(now, timeout=2.0, max_lag=0.5, held_wait=0.5) is None  # once
    assert not m.unseen()


def test_an_onset_older_than_the_frame_taken_retakes_that_frame_with_its_held_reading() -> None:
    m, now = _idle_frames_taken(3)
    frame = m.t_moment
    _onset(m, 1, frame - 2 * PERIOD, now + 0.003)  # a retried frame two back: it stands for the frames after it
    got = m.take(now + 0.003, timeout=2.0, max_lag=0.5, held_wait=0.5)
    assert got is not None and got.t == frame and got.touched[1]


def test_readings_that_begin_no_touch_or_are_not_held_take_no_frame_again() -> None:
    """A late untouched heartbeat changes no contact; a periodic reading of a frame taken
    without it was late past ``max_lag`` and is unknown there anyway."""
    m, now = _idle_frames_taken(3)
    frame = m.t_moment
    _record(m, 0, frame, delay=now + 0.004 - frame)  # an untouched reading of the frame taken
    assert m.take(now + 0.004, timeout=2.0, max_lag=0.5, held_wait=0.5) is None
    _onset(m, 1, frame, now + 0.005, held=False)
    assert m.take(now + 0.005, timeout=2.0, max_lag=0.5, held_wait=0.5) is None
    assert m.retaken == 0
