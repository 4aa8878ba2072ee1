"""Skin frames from readout records (daemon/core/frames.py): complete by the records or by the
deadline, in order, each once, late records counted, memory bounded whatever arrives."""

from __future__ import annotations

import math

import numpy as np
import pytest
from cellbridge.daemon.core.frames import SkinFrame, SkinFrames
from cellbridge.protocol import Mode, Readout, ReadoutSample
from hypothesis import given, settings
from hypothesis import strategies as st

RATE = 100
SPAN_US = 4000
MARGIN = 0.01


def t_of(k: int, rate: int = RATE) -> float:
    """A host map: frame k's gate start at k / rate s."""
    return k / rate


def record(k: int, samples: dict[int, tuple[int, int]] | None = None, unchanged: tuple[int, ...] = (),
           missing: tuple[int, ...] = (), part: int = 0, parts: int = 1, rate: int = RATE) -> Readout:
    s = tuple(ReadoutSample(b, c1, c2, 0) for b, (c1, c2) in sorted((samples or {}).items()))
    return Readout(k, rate, Mode.COUNTER, 1, s, tuple(unchanged), tuple(missing), SPAN_US, part, parts)


def arrive(k: int, rate: int = RATE) -> float:
    """When a record of frame k comes, at the earliest: its readout's end, plus a little."""
    return t_of(k, rate) + SPAN_US * 1e-6 + 0.001


def states(f: SkinFrame) -> dict[int, object]:
    out: dict[int, object] = {int(b): (int(c1), int(c2)) for b, c1, c2 in zip(f.bridges, f.c1, f.c2)}
    out.update({int(b): "unchanged" for b in f.unchanged})
    out.update({int(b): "missing" for b in f.missing})
    return out


def test_one_gateways_record_makes_its_frame_complete_at_once() -> None:
    sf = SkinFrames(MARGIN)
    sf.add(1, record(10, {1: (100, 200), 3: (5, 6)}, unchanged=(2,), missing=(4,)), arrive(10), t_of(10))
    (f,) = sf.take(arrive(10))
    assert (f.index, f.rate, f.t, f.complete, f.by_deadline) == (10, RATE, t_of(10), True, False)
    assert states(f) == {1: (100, 200), 3: (5, 6), 2: "unchanged", 4: "missing"}
    assert sf.take(arrive(10) + 1.0) == []  # each frame once
    assert sf.counts["frames_complete"] == 1


def test_a_frame_waits_for_every_active_gateway_then_comes_whole() -> None:
    sf = SkinFrames(MARGIN)
    for k in (1, 2):  # both gateways active
        sf.add(1, record(k, {1: (1, 1)}), arrive(k), t_of(k))
        sf.add(9, record(k, {9: (9, 9)}), arrive(k), t_of(k))
    assert [f.index for f in sf.take(arrive(2))] == [1, 2]
    sf.add(1, record(3, {1: (2, 2)}), arrive(3), t_of(3))
    assert sf.take(arrive(3)) == []  # gateway 9's record of 3 may still come
    sf.add(9, record(3, {9: (3, 3)}), arrive(3) + 0.002, t_of(3))
    (f,) = sf.take(arrive(3) + 0.002)
    assert f.complete and states(f) == {1: (2, 2), 9: (3, 3)} and f.gateways == (1, 9)


def test_records_of_one_gateway_in_either_order_give_the_frames_in_order() -> None:
    """A gateway writes a record as soon as it is complete: the record of frame 4 may come
    before the one of 3. Frame 4 waits for 3 (until 3's deadline at most), then both go
    out, 3 first, each whole."""
    sf = SkinFrames(0.05)
    for k in (1, 2):
        sf.add(1, record(k, {1: (k, k)}), arrive(k), t_of(k))
    assert [f.index for f in sf.take(arrive(2))] == [1, 2]
    sf.add(1, record(4, {1: (4, 4)}), arrive(4), t_of(4))
    assert sf.take(arrive(4)) == []  # frame 3 may still come
    sf.add(1, record(3, {1: (3, 3)}), arrive(4) + 0.001, t_of(3))
    f3, f4 = sf.take(arrive(4) + 0.001)
    assert (f3.index, f4.index) == (3, 4) and f3.complete and f4.complete and not f4.after_gap
    assert sf.counts["late_records"] == 0 and sf.counts["frames_missed"] == 0


def test_a_frame_lost_whole_holds_the_next_until_its_deadline_and_is_told() -> None:
    """No record of frame 3 came at all: frame 4 (complete) waits until 3's deadline, then
    goes out after a gap: its "unchanged" may refer to a sample in frame 3, so those bridges
    are missing in it."""
    sf = SkinFrames(MARGIN)
    for k in (1, 2):
        sf.add(1, record(k, {1: (k, k)}, unchanged=(2,)), arrive(k), t_of(k))
    sf.take(arrive(2))
    sf.add(1, record(4, {1: (4, 4)}, unchanged=(2,)), arrive(4), t_of(4))
    deadline_3 = t_of(3) + SPAN_US * 1e-6 + MARGIN
    assert sf.take(deadline_3 - 1e-6) == []
    (f4,) = sf.take(deadline_3 + 1e-6)
    assert f4.index == 4 and f4.complete and f4.after_gap and states(f4) == {1: (4, 4), 2: "missing"}
    assert sf.counts["frames_missed"] == 1 and sf.counts["unchanged_after_gap"] == 1
    sf.add(1, record(5, {1: (5, 5)}, unchanged=(2,)), arrive(5), t_of(5))
    (f5,) = sf.take(arrive(5))
    assert not f5.after_gap and states(f5) == {1: (5, 5), 2: "unchanged"}


def test_a_frame_goes_out_at_its_deadline_and_not_before() -> None:
    sf = SkinFrames(MARGIN)
    serial = 0.0005
    for k in (1, 2):
        sf.add(1, record(k, {1: (1, 1)}), arrive(k), t_of(k), serial)
        sf.add(9, record(k, {9: (9, 9)}), arrive(k), t_of(k), serial)
    sf.take(arrive(2))
    sf.add(1, record(3, {1: (3, 3)}), arrive(3), t_of(3), serial)
    deadline = t_of(3) + SPAN_US * 1e-6 + serial + MARGIN
    assert sf.due() == pytest.approx(deadline)
    assert sf.take(deadline - 1e-6) == []
    (f,) = sf.take(deadline)
    assert f.by_deadline and not f.complete and states(f) == {1: (3, 3)}
    # gateway 9's record of 3 after all: late, counted, history not rewritten
    sf.add(9, record(3, {9: (3, 3)}), deadline + 0.001, t_of(3), serial)
    assert sf.take(deadline + 0.001) == [] and sf.counts["late_records"] == 1
    assert sf.counts["frames_by_deadline"] == 1 and sf.due() == math.inf


def test_a_gateway_silent_past_active_for_is_not_waited_for() -> None:
    sf = SkinFrames(MARGIN, active_for=2.0)
    sf.add(1, record(1, {1: (1, 1)}), arrive(1), t_of(1))
    sf.add(9, record(1, {9: (9, 9)}), arrive(1), t_of(1))
    sf.take(arrive(1))
    k = 1 + 3 * RATE  # 3 s later: gateway 9 no longer active
    sf.add(1, record(k, {1: (2, 2)}), arrive(k), t_of(k))
    (f,) = sf.take(arrive(k))
    assert f.complete and not f.by_deadline and f.gateways == (1,)


def test_a_record_in_parts_is_complete_once_every_part_came() -> None:
    sf = SkinFrames(MARGIN)
    sf.add(1, record(5, {1: (1, 1)}, part=0, parts=2), arrive(5), t_of(5))
    assert sf.take(arrive(5)) == []
    sf.add(1, record(5, {1: (1, 1)}, part=0, parts=2), arrive(5), t_of(5))  # the same part again
    sf.add(1, record(5, {2: (2, 2)}, unchanged=(3,), part=1, parts=2), arrive(5), t_of(5))
    (f,) = sf.take(arrive(5))
    assert f.complete and states(f) == {1: (1, 1), 2: (2, 2), 3: "unchanged"}
    assert sf.counts["duplicate_parts"] == 1


def test_a_part_lost_leaves_its_bridges_unknown_from_its_deadline() -> None:
    sf = SkinFrames(0.05)
    sf.add(1, record(5, {1: (1, 1)}, part=0, parts=2), arrive(5), t_of(5))
    sf.add(1, record(6, {1: (1, 1), 2: (2, 2)}), arrive(6), t_of(6))
    assert sf.take(arrive(6)) == []  # (frame 6 waits for 5)
    f5, f6 = sf.take(t_of(5) + SPAN_US * 1e-6 + 0.05)
    assert states(f5) == {1: (1, 1)} and not f5.complete and f5.by_deadline
    assert f6.complete and not f6.after_gap


def test_a_bridge_in_two_gateways_records() -> None:
    """A bridge both gateways account for: a sample beats missing (its word came through one
    route), the same sample twice is one; two that disagree make it missing, counted."""
    sf = SkinFrames(MARGIN)
    sf.add(1, record(1, {1: (1, 1), 5: (50, 50), 6: (60, 60)}, unchanged=(7,)), arrive(1), t_of(1))
    sf.add(9, record(1, {9: (9, 9), 6: (61, 60)}, unchanged=(5,), missing=(1,)), arrive(1), t_of(1))
    (f,) = sf.take(arrive(1))
    assert states(f) == {1: (1, 1), 5: "missing", 6: "missing", 7: "unchanged", 9: (9, 9)}
    assert sf.counts["conflicts"] == 2


def test_a_gateway_that_restarts_and_counts_from_zero_starts_the_frames_again() -> None:
    """Its records behind the frames given out are late until they have agreed for 0.1 s
    (three or more, as far apart in mesh time as in arrival): then the frames start again."""
    sf = SkinFrames(MARGIN)
    base = 5000.0  # its new frames' host times: the host's map restarted too
    for k in range(1000, 1005):
        sf.add(1, record(k, {1: (k, k)}), arrive(k), t_of(k))
    assert len(sf.take(arrive(1004))) == 5
    out = []
    for k in range(15):
        sf.add(1, record(k, {1: (k, k)}), base + k / RATE + 0.005, base + k / RATE)
        out += sf.take(base + k / RATE + 0.005)
    assert [f.index for f in out] == list(range(10, 15)) and all(f.complete for f in out)
    assert sf.counts["restarts"] == 1 and sf.counts["late_records"] == 10
    assert out[0].after_gap  # (what the bridges said unchanged may refer to samples before the restart)


def test_a_single_record_behind_does_not_restart_the_frames() -> None:
    sf = SkinFrames(MARGIN)
    for k in range(1000, 1003):
        sf.add(1, record(k, {1: (k, k)}), arrive(k), t_of(k))
    sf.take(arrive(1002))
    sf.add(1, record(3, {1: (3, 3)}), arrive(1003), t_of(3))  # an index corrupted past the CRC
    sf.add(1, record(1003, {1: (1, 1)}), arrive(1003), t_of(1003))
    assert [f.index for f in sf.take(arrive(1003))] == [1003]
    assert sf.counts["restarts"] == 0 and sf.counts["late_records"] == 1


def test_a_gateway_going_back_while_another_is_ahead_is_late_not_a_restart() -> None:
    sf = SkinFrames(MARGIN)
    for k in range(1000, 1003):
        sf.add(1, record(k, {1: (k, k)}), arrive(k), t_of(k))
        sf.add(9, record(k, {9: (k, k)}), arrive(k), t_of(k))
    sf.take(arrive(1002))
    sf.add(9, record(0, {9: (0, 0)}), arrive(1003), t_of(0))
    sf.add(9, record(1, {9: (0, 0)}), arrive(1003), t_of(1))
    assert sf.counts["restarts"] == 0 and sf.counts["late_records"] == 2


def test_an_index_at_the_top_of_u64_then_zero() -> None:
    """Frame instants are exact integers: the last indices of a u64 order right, and an index
    back at 0 is the skin's time going back (a restart once confirmed), not a wrap forward."""
    top = (1 << 64) - 3
    sf = SkinFrames(MARGIN)
    for i, k in enumerate((top, top + 1, top + 2)):
        sf.add(1, record(k, {1: (i, i)}), 100.0 + i * 0.01 + 0.005, 100.0 + i * 0.01)
    assert [f.index for f in sf.take(101.0)] == [top, top + 1, top + 2]
    for k in range(12):
        sf.add(1, record(k, {1: (k, k)}), 200.005 + k * 0.01, 200.0 + k * 0.01)
    assert [f.index for f in sf.take(201.0)] == [10, 11] and sf.counts["restarts"] == 1


def test_a_burst_of_old_records_among_current_ones_is_late_not_a_restart() -> None:
    """A confused relay passed on records of frames seconds old, in bursts, between the
    gateway's current ones (seen on an emulated skin under load): late, and counted; the
    current frames go on (taken for the skin's time going back, the frames restarted ten
    times in a minute, and every frame after each was lost as "late")."""
    sf = SkinFrames(MARGIN)
    out = []
    for k in range(500, 540):
        now = arrive(k)
        sf.add(1, record(k, {1: (k, k)}), now, t_of(k))
        if k % 7 == 0:
            for old in range(k - 300, k - 296):  # four old frames in one read
                sf.add(1, record(old, {1: (old, old)}), now, t_of(old))
        out += sf.take(now)
    assert [f.index for f in out] == list(range(500, 540)) and all(f.complete for f in out)
    assert sf.counts["restarts"] == 0 and sf.counts["late_records"] == 4 * 6


def test_frames_of_two_rates_come_out_in_the_order_of_their_instants() -> None:
    sf = SkinFrames(MARGIN)
    sf.add(1, record(10, {1: (1, 1)}, rate=100), 0.11, 0.1)
    sf.add(1, record(26, {1: (2, 2)}, rate=250), 0.11, 0.104)
    sf.add(1, record(11, {1: (3, 3)}, rate=100), 0.12, 0.11)
    assert [(f.index, f.rate) for f in sf.take(0.2)] == [(10, 100), (26, 250), (11, 100)]


def test_a_record_whose_frame_lies_after_its_arrival_is_refused() -> None:
    sf = SkinFrames(MARGIN)
    huge = (1 << 60)
    sf.add(1, record(huge, {1: (1, 1)}), 10.0, t_of(huge))
    sf.add(1, record(5, {1: (1, 1)}), 10.0, math.nan)  # the host could not map it
    assert sf.take(1e30) == [] and sf.counts["rejected_records"] == 2 and sf.due() == math.inf


def test_frames_pending_are_bounded() -> None:
    """Gateway 9 active but its records never coming, and frames far apart (no deadline
    passed yet): at most max_pending wait; the oldest go out as they are, counted."""
    sf = SkinFrames(margin=100.0, max_pending=8)
    sf.add(9, record(0, {9: (9, 9)}), arrive(0), t_of(0))
    for k in range(1, 101):
        sf.add(1, record(k, {1: (k, k)}), arrive(0) + 0.001, t_of(0))
        assert len(sf._pending) <= 8
    out = sf.take(arrive(0) + 0.001)
    assert [f.index for f in out] == list(range(0, 101 - 8))  # in order, each once
    assert sf.counts["frames_pushed_out"] == 101 - 8 and all(f.by_deadline for f in out)


def test_gateways_followed_are_bounded() -> None:
    sf = SkinFrames(MARGIN, max_gateways=4)
    for gw in range(10):
        sf.add(gw, record(1, {gw: (1, 1)}), arrive(1), t_of(1))
    assert len(sf._gw) == 4 and sf.counts["rejected_records"] == 6


@settings(max_examples=150, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.booleans(), st.booleans()), min_size=1, max_size=40),
       st.integers(0, 3))
def test_with_records_lost_at_random_every_frame_comes_out_once_in_order_and_says_only_what_came(
        lost: list[tuple[bool, bool, bool]], gateways_lost_part: int) -> None:
    """Three gateways, each record lost or not (the last gateway's in two parts, one of them
    lost when asked); every record that came is read exactly as written (but "unchanged" after
    a frame of which no record came), every frame a record of which came goes out once, in
    order, by the records or at its deadline."""
    sf = SkinFrames(MARGIN)
    written: dict[int, dict[int, object]] = {}
    got: list[SkinFrame] = []
    now = 0.0
    for k, drop in enumerate([(False, False, False), *lost]):  # frame 0 whole: every gateway active
        now = arrive(k)
        for gw, gone in zip((1, 2, 3), drop):
            if gw == 3:
                parts = [record(k, {30: (k, 1)}, part=0, parts=2), record(k, {31: (k, 2)}, missing=(32,), part=1, parts=2)]
                if gone and gateways_lost_part:
                    parts = parts[:1] if k % 2 else parts[1:]  # (then its elements are unknown)
                elif gone:
                    parts = []
            else:
                parts = [] if gone else [record(k, {gw * 10: (k, gw)}, unchanged=(gw * 10 + 1,))]
            for r in parts:
                written.setdefault(k, {}).update(states(_as_frame(r)))
                sf.add(gw, r, now, t_of(k))
        got += sf.take(now)
    got += sf.take(1e9)
    assert [f.index for f in got] == sorted(written)  # each frame a record of which came, once, in order
    for f in got:
        said = written[f.index]
        assert f.after_gap == (f.index - 1 not in written and f.index > 0)
        for b, state in states(f).items():  # nothing said that was not written; unchanged only
            # where a record of the frame before came (else it may refer to a lost sample)
            assert state == said[b] or (state == "missing" and said[b] == "unchanged" and f.after_gap), (f.index, b)
        drop = (False, False, False) if f.index == 0 else lost[f.index - 1]
        assert f.complete == (not any(drop))  # every gateway's record came whole


def _as_frame(r: Readout) -> SkinFrame:
    """The states one record part says, read alone."""
    sf = SkinFrames(MARGIN)
    sf.add(0, r, 1e9, 0.0)
    (f,) = sf.take(1e10)
    return f


def test_the_frames_arrays_are_int64_columns() -> None:
    sf = SkinFrames(MARGIN)
    sf.add(1, record(1, {1: (1, 2)}), arrive(1), t_of(1))
    (f,) = sf.take(arrive(1))
    for a in (f.bridges, f.c1, f.c2, f.flags, f.mode, f.oversampling, f.unchanged, f.missing):
        assert a.dtype == np.int64


def test_each_sample_keeps_its_own_parts_mode_and_oversampling() -> None:
    """A record in two parts of two modes (samples of two modes never share a part), and a
    gateway's record of the frame beside it: every sample's mode and oversampling are its
    own part's, whatever the order the parts came in."""
    adc = Readout(1, RATE, Mode.ADC, 4, (ReadoutSample(2, 40, 50, 0), ReadoutSample(5, 41, 51, 0)), (), (),
                  SPAN_US, 1, 2)
    counter = Readout(1, RATE, Mode.COUNTER, 1, (ReadoutSample(1, 100, 200, 1), ReadoutSample(7, 101, 201, 0)),
                      (3,), (), SPAN_US, 0, 2)
    other = Readout(1, RATE, Mode.ADC, 8, (ReadoutSample(9, 60, 70, 2),), (8,), (6,), SPAN_US)
    sf = SkinFrames(MARGIN)
    sf.add(1, adc, arrive(1), t_of(1))
    sf.add(4, other, arrive(1), t_of(1))
    sf.add(1, counter, arrive(1), t_of(1))
    (f,) = sf.take(arrive(1))
    got = {int(b): (int(c1), int(c2), int(fl), int(mo), int(ov))
           for b, c1, c2, fl, mo, ov in zip(f.bridges, f.c1, f.c2, f.flags, f.mode, f.oversampling)}
    assert got == {2: (40, 50, 0, 1, 4), 5: (41, 51, 0, 1, 4), 1: (100, 200, 1, 0, 1), 7: (101, 201, 0, 0, 1),
                   9: (60, 70, 2, 1, 8)}
    assert (f.unchanged.tolist(), f.missing.tolist(), f.complete) == ([3, 8], [6], True)


def test_a_take_at_the_same_time_again_sees_what_came_since() -> None:
    """The pipeline takes after every read and again for every contact job, at one time; the
    second walk is skipped only while nothing take reads changed: a record, a gateway
    forgotten, a reload or a restart in between is seen by a take at that very time."""
    sf = SkinFrames(MARGIN)
    now = arrive(3)
    for k in (1, 2):
        sf.add(1, record(k, {1: (1, 1)}), arrive(k), t_of(k))
        sf.add(9, record(k, {9: (9, 9)}), arrive(k), t_of(k))
    sf.add(1, record(3, {1: (2, 2)}), now, t_of(3))
    assert [f.index for f in sf.take(now)] == [1, 2]
    assert sf.take(now) == []  # gateway 9's record of 3 may still come
    sf.add(9, record(3, {9: (3, 3)}), now, t_of(3))  # it comes, at the same host time
    assert [(f.index, f.complete) for f in sf.take(now)] == [(3, True)]

    sf.add(1, record(4, {1: (4, 4)}), now + 0.01, t_of(4))
    assert sf.take(now + 0.01) == []  # waits for gateway 9
    sf.forget(9)  # gone for good: frame 4 waits for gateway 1 alone, whole
    assert [(f.index, f.complete) for f in sf.take(now + 0.01)] == [(4, True)]

    sf.add(2, record(5, {2: (5, 5)}, part=0, parts=2), now + 0.015, t_of(5))
    sf.add(1, record(5, {1: (5, 5)}), now + 0.02, t_of(5))
    assert sf.take(now + 0.02) == []  # gateway 2's record has a part to come
    sf.configure(MARGIN, 0.001, 64)  # a reload: gateway 2, 5 ms silent, is no longer active
    assert [(f.index, f.complete) for f in sf.take(now + 0.02)] == [(5, True)]


def test_a_record_that_went_long_before_its_schedules_end_is_taken() -> None:
    """A record goes as soon as it is complete, long before its schedule's end on a deep
    skin whose levels are wide (the real-time shells: 30 ms levels, an 8x8 grid's 16 of
    them make a 480 ms span). The check against a frame from the future compared the
    frame's *span end* with the arrival, so every record of such a skin that came within
    the span's first half-second was refused, and the skin gave no frame at all. A record
    is from the future when its frame's gates start after it arrived."""
    span_us = 480_000
    sf = SkinFrames(MARGIN)
    k = 500
    rec = Readout(k, RATE, Mode.COUNTER, 1, (ReadoutSample(1, 100, 200, 0),), (), (), span_us, 0, 1)
    sf.add(1, rec, t_of(k) + 0.02, t_of(k))  # 20 ms after its gates started: complete early
    (f,) = sf.take(t_of(k) + 0.02)
    assert (f.index, f.complete) == (k, True) and sf.counts["rejected_records"] == 0
    # its frame's gates half a second after its arrival: a wrong index, refused
    sf.add(1, Readout(k + 100, RATE, Mode.COUNTER, 1, (), (), (), span_us, 0, 1), t_of(k) + 0.5, t_of(k + 100))
    assert sf.counts["rejected_records"] == 1


def test_a_record_claiming_an_absurd_span_does_not_hold_the_frames_for_a_minute() -> None:
    """A record's span sets its frame's deadline. Since the future check compares the gate
    start with the arrival (not the span's end), a record whose span is corrupt past the
    CRC (0xFFFFFFFF us: 71 minutes) is taken, and a frame that lost another gateway's
    record waited until 64 newer frames pushed it out, holding every frame after it: 6.4 s
    without output at 10 Hz, 64 s at 1 Hz. A span counts for at most ``MAX_SPAN``."""
    from cellbridge.daemon.core.frames import MAX_SPAN

    rate = 10

    def rec(k: int, b: int, span_us: int = 240_000) -> Readout:
        return Readout(k, rate, Mode.COUNTER, 1, (ReadoutSample(b, 100, 200, 0),), (), (), span_us, 0, 1)

    sf = SkinFrames(MARGIN)
    for k in range(1, 20):  # two gateways, steady
        for gw in (1, 2):
            sf.add(gw, rec(k, gw), t_of(k, rate) + 0.03, t_of(k, rate))
        sf.take(t_of(k, rate) + 0.03)
    sf.add(1, rec(20, 1, 0xFFFF_FFFF), t_of(20, rate) + 0.03, t_of(20, rate))  # gateway 2's record of 20 lost
    out: list[SkinFrame] = []
    k = 21
    while not any(f.index == 20 for f in out) and k < 200:
        for gw in (1, 2):
            sf.add(gw, rec(k, gw), t_of(k, rate) + 0.03, t_of(k, rate))
        out += sf.take(t_of(k, rate) + 0.03)
        k += 1
    assert out and out[0].index == 20 and not out[0].complete
    assert t_of(k - 1, rate) + 0.03 - t_of(20, rate) <= MAX_SPAN + 0.1 + MARGIN + 0.03  # (not 6.4 s)
    assert [f.index for f in out] == list(range(20, 20 + len(out)))  # then the frames held, in order
