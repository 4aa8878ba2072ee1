"""Time domains (daemon/core/domains.py): parts of a skin that no cell joins keep their own
mesh time and their own frames; a frame of one never speaks for the other's elements."""

from __future__ import annotations

import math

import numpy as np
from cellbridge.daemon.core.domains import TimeDomains
from cellbridge.daemon.core.frames import SkinFrame
from cellbridge.daemon.core.readings import ElementReadings
from cellbridge.protocol import Mode, Readout, ReadoutSample

HZ = 50_000_000
RATE = 100
SPAN_US = 4000


def record(k: int, bridges: tuple[int, ...], root: int) -> Readout:
    return Readout(k, RATE, Mode.COUNTER, 1, tuple(ReadoutSample(b, 100 + b, 200, 0) for b in bridges), (), (),
                   SPAN_US, 0, 1, root)


def feed(td: TimeDomains, gateway: int, root: int, k0: int, frames: range, bridges: tuple[int, ...],
         t0: float = 100.0) -> None:
    """Records of frames ``k0 + i`` (i in ``frames``) of ``gateway`` on ``root``'s mesh time,
    each arriving its readout after its gate start (host time ``t0 + i / RATE``)."""
    for i in frames:
        k = k0 + i
        td.record(gateway, record(k, bridges, root), root, k * HZ // RATE, t0 + i / RATE + SPAN_US * 1e-6 + 0.001,
                  0.001)


def aged(k: int, gateway: int, span_us: int, age_us: int) -> Readout:
    """Gateway ``gateway``'s record of frame ``k`` on root 1: its one element sampled, its age said."""
    return Readout(k, RATE, Mode.COUNTER, 1, (ReadoutSample(gateway * 10, 1, 2, 0),), (), (), span_us, 0, 1, 1,
                   age_us)


def arrive(td: TimeDomains, events: list[tuple[float, int, Readout]]) -> tuple[list[SkinFrame], int]:
    """Each (arrival, gateway, record) in order of arrival, the frames taken after each:
    (the frames given out, how many records were refused)."""
    frames: list[SkinFrame] = []
    refused = 0
    for now, gw, rec in sorted(events, key=lambda e: e[0]):
        t, _ = td.record(gw, rec, 1, rec.index * HZ // RATE, now, 0.001)
        refused += math.isnan(t)
        frames += td.take(now)
    return frames, refused


def test_two_roots_with_unrelated_indices_give_both_their_frames() -> None:
    """Two limbs: root 1 counts from frame 5 000, root 22 from frame 9 000 000 (their roots
    powered on at unrelated moments). One map for both refused the second's records."""
    td = TimeDomains(HZ, margin=0.01)
    got = []
    for i in range(50):
        feed(td, 1, 1, 5_000, range(i, i + 1), (1, 2, 3))
        feed(td, 22, 22, 9_000_000, range(i, i + 1), (22, 23))
        got += td.take(100.0 + i / RATE + 0.006)
    c = td.counters(101.0)
    assert c["rejected_records"] == 0 and c["late_records"] == 0, c
    assert c["time_roots"] == [1, 22] and c["gateways_active"] == 2
    by_root = {r: [f for f in got if f.root == r] for r in (1, 22)}
    assert [f.index for f in by_root[1]] == list(range(5_000, 5_050))
    assert [f.index for f in by_root[22]] == list(range(9_000_000, 9_000_050))
    assert all(f.complete and not f.by_deadline for f in got)  # neither waits for the other's gateway
    # one host time base: frame i of both limbs is at 100 + i / RATE, within the map's error
    assert abs(by_root[1][-1].t - by_root[22][-1].t) < 0.002
    assert [f.t for f in got] == sorted(f.t for f in got)


def test_a_gateway_that_moves_to_another_root_no_longer_holds_the_old_ones_frames() -> None:
    """Gateway 16 followed root 1 with gateway 1, then (a failover) root 16. Frames of root 1
    stop waiting for it: gateway 1's record makes them complete at once, not at the deadline."""
    td = TimeDomains(HZ, margin=0.05)
    feed(td, 1, 1, 1_000, range(0, 20), (1, 2))
    feed(td, 16, 1, 1_000, range(0, 20), (15, 16))
    td.take(101.0)
    feed(td, 16, 16, 777_000, range(20, 21), (15, 16))
    feed(td, 1, 1, 1_000, range(20, 21), (1, 2))
    (f1, f16) = sorted(td.take(100.0 + 20 / RATE + 0.006), key=lambda f: f.root)
    assert (f1.root, f1.index, f1.complete) == (1, 1_020, True)
    assert f16.root == 16 and f16.complete
    assert td.counters(101.0)["root_moves"] == 1 and td.root_of(16) == 16


def test_roots_beyond_the_bound_are_refused_and_counted_and_unfollowed_ones_make_room() -> None:
    td = TimeDomains(HZ, max_domains=2)
    feed(td, 1, 1, 1_000, range(0, 5), (1,))
    feed(td, 2, 2, 2_000, range(0, 5), (2,))
    feed(td, 3, 3, 3_000, range(0, 5), (3,))  # a third root: no room (both followed, active)
    c = td.counters(100.1)
    assert c["time_roots"] == [1, 2] and c["rejected_records"] == 5
    feed(td, 2, 1, 1_000, range(5, 6), (2,))  # gateway 2 moves to root 1: root 2 is followed by nobody
    feed(td, 3, 3, 3_000, range(400, 401), (3,), t0=100.0)  # 4 s later: root 2 inactive, pruned
    assert td.counters(104.1)["time_roots"] == [1, 3]


def test_a_frame_of_one_root_leaves_the_other_roots_elements_as_their_frame_said() -> None:
    """Elements 0-1 on root 1, 2-3 on root 22. Root 22's frame (2 sampled, 3 missing) must not
    make 0 and 1 unknown, nor erase their readings; root 1's next frame leaves 2 and 3 as
    root 22's frame said (2 known, 3 unknown)."""
    r = ElementReadings(4, 8)
    dc = lambda *v: np.array([[x, x] for x in v], dtype=np.float64)
    caps = dc(1.0, 1.0)
    r.scheduled(10.0, 1, np.array([0, 1]), caps, np.array([0, 1]), dc(0.5, 0.7), np.array([True, False]), 1,
                np.array([0, 1]))
    unknown = r.scheduled(10.001, 2, np.array([2]), caps[:1], np.array([2]), dc(0.9), np.array([True]), 22,
                          np.array([2, 3]))
    assert unknown == 1  # element 3, of root 22's two
    f = r.take(10.002, 2.0, 0.1, True)
    assert f is not None
    assert f.unknown.tolist() == [False, False, False, True]
    assert f.dc[:, 0].tolist()[:3] == [0.5, 0.7, 0.9] and math.isnan(f.dc[3, 0])
    assert f.touched.tolist() == [True, False, True, False]
    r.scheduled(10.01, 3, np.array([0]), caps[:1], np.array([0]), dc(0.6), np.array([True]), 1, np.array([0, 1]))
    f = r.take(10.011, 2.0, 0.1, True)
    assert f is not None
    assert f.unknown.tolist() == [False, True, False, True]  # 1: missing in root 1's frame; 2, 3 as root 22 said
    assert f.dc[2, 0] == 0.9 and f.t_sample[2] == 10.001


def test_every_part_of_a_record_held_back_is_refused_whatever_each_parts_age() -> None:
    """A gateway stamps each part of a record with its own age (when it began writing that
    part: part 1 after part 0's time on the line). Frame 1199's record came again, its index
    corrupted one frame ahead (1201): its part 0 is held back and refused, but part 1, whose
    point differs by its age, was taken as frame 1201's, and the samples of frame 1199 went
    out as those of frame 1201 when the true record's part 1 came as a duplicate."""
    serial = 0.0025  # s a full part takes on the line

    def parts(k: int, i: int, age0: int = 8000) -> list[float]:
        out = []
        for p in range(2):
            age = age0 + int(p * serial * 1e6)
            rec = Readout(k, RATE, Mode.COUNTER, 1, tuple(ReadoutSample(b, 100 + b + i, 200, 0) for b in (1 + p, 3 + p)),
                          (), (), 20_000, p, 2, 1, age)
            now = 100.0 + i / RATE + age * 1e-6 + serial
            out.append(td.record(1, rec, 1, k * HZ // RATE, now, 2 * serial)[0])
        return out

    td = TimeDomains(HZ, margin=0.01)
    for i in range(200):
        assert all(math.isfinite(t) for t in parts(1000 + i, i))
    copy = parts(1201, 199)  # frame 1199's record under index 1201
    assert all(math.isnan(t) for t in copy), copy
    assert all(math.isnan(t) for t in parts(1200, 199)), "one frame ahead (10 ms, within its age) is refused too"
    assert all(math.isfinite(t) for t in parts(1200, 200) + parts(1201, 201))
    frames = {f.index: f for f in td.take(100.0 + 201 / RATE + 0.015)}
    f = frames[1201]
    assert f.complete and sorted(f.bridges.tolist()) == [1, 2, 3, 4]
    assert f.c1.tolist() == [100 + b + 201 for b in f.bridges.tolist()], f.c1  # its own samples, none of 1199's


def test_records_that_begin_to_say_their_age_move_no_frame_before_its_gate_start() -> None:
    """A gateway's records said no age for 3 s (it had no mesh time of this root yet, or an
    older gateway's alone), then said it. The map had learned from their frames' gate
    starts, as late as the readout (6-8 ms); the ages lowered its envelope by that step, and
    the skew fit, its line through the old blocks' minima and the new, ran down at its bound
    below the newest: frames were put up to 4 ms before their gate start for a minute, and
    the first aged record of each gateway was refused (its frame lost)."""
    line = 0.0013  # s from a record's writing to its arrival
    td = TimeDomains(HZ, margin=0.02)
    events = []
    for k in range(3000):  # 30 s
        for gw, age in ((1, 0.006), (2, 0.008)):
            said = int(age * 1e6) if k >= 300 else 0
            events.append((100.0 + k / RATE + age + line, gw, aged(k, gw, 20_000, said)))
    frames, refused = arrive(td, events)
    err = [f.t - (100.0 + f.index / RATE) for f in frames if f.index >= 300]
    assert refused == 0 and len(frames) == 3000 and all(f.complete for f in frames)
    assert -1e-4 <= min(err) and max(err) <= line + 1e-4, (min(err), max(err))


def test_a_record_whose_age_alone_is_wrong_is_taken_by_its_frame() -> None:
    """One record of gateway 2 said an age 6 ms too long (a glitch of its clock, or a bit
    past the CRC): its point, that far after its arrival, is held back as an index
    corrupted ahead would be. But its frame's gate start lies before its arrival as every
    other's: the record was refused and its elements unknown in that frame, where without
    the age they were known. The point stays held (it teaches nothing), the record is taken."""
    line = 0.0013
    td = TimeDomains(HZ, margin=0.02)
    events = []
    for k in range(500):
        for gw, age in ((1, 0.006), (2, 0.008)):
            said = age + (0.006 if (gw, k) == (2, 400) else 0.0)
            events.append((100.0 + k / RATE + age + line, gw, aged(k, gw, 20_000, int(said * 1e6))))
    frames, refused = arrive(td, events)
    err = [f.t - (100.0 + f.index / RATE) for f in frames if f.index >= 300]
    assert refused == 0 and len(frames) == 500 and all(f.complete for f in frames), refused
    assert -1e-4 <= min(err) and max(err) <= line + 1e-4, (min(err), max(err))


def test_a_record_beyond_its_span_on_a_deep_schedule_is_taken() -> None:
    """A deep schedule (span 0.48 s): records go 0.31-0.32 s after their gates. One was
    written later than its span (0.5 s): its age is not believed and it teaches its frame's
    gate start, as a record that says none. The gateway's newest point was counted by its
    age (when it was written), so this frame looked more than 0.25 s behind it, the skin's
    time gone back: the record was refused, its elements unknown, where without ages it
    was taken."""
    line = 0.0013
    td = TimeDomains(HZ, margin=0.02)
    events = []
    for k in range(1500):
        for gw in (1, 2):
            age = 0.5 if (gw, k) == (1, 1000) else 0.30 + 0.01 * gw
            said = int(age * 1e6) if age <= 0.48 else 0  # (said beyond the span or not: not believed)
            events.append((100.0 + k / RATE + age + line, gw, aged(k, gw, 480_000, said)))
    frames, refused = arrive(td, events)
    frames += td.take(math.inf)
    assert refused == 0 and len(frames) == 1500, refused
    assert all(len(f.bridges) == 2 for f in frames if f.index >= 100)
    err = [f.t - (100.0 + f.index / RATE) for f in frames if f.index >= 100]
    assert -1e-4 <= min(err) and max(err) <= line + 1e-4, (min(err), max(err))
