"""The daemon's frame path attacked as a robot's lines attack it: a serial path steadily
late, a failover that moves a gateway to another root, an index corrupted past the CRC,
phantom roots filling the table. Each frame must say the truth or say it does not know,
and every record refused stays counted in health."""

from __future__ import annotations

import random

import numpy as np
from cellbridge.daemon.core.clock import SkinClock
from cellbridge.daemon.core.domains import TimeDomains
from cellbridge.daemon.core.frames import SkinFrames
from cellbridge.daemon.core.readings import ElementReadings
from cellbridge.protocol import Mode, Readout, ReadoutSample

HZ = 50_000_000
RATE = 100
SPAN_US = 4000


def record(k: int, bridges: tuple[int, ...], root: int, unchanged: tuple[int, ...] = ()) -> Readout:
    return Readout(k, RATE, Mode.COUNTER, 1, tuple(ReadoutSample(b, 100 + b, 200, 0) for b in bridges),
                   unchanged, (), SPAN_US, 0, 1, root)


def at(i: int, lag: float = 0.0) -> float:
    """When frame ``1000 + i``'s record comes: its readout's end, a little, and ``lag``."""
    return 100.0 + i / RATE + SPAN_US * 1e-6 + 0.001 + lag


def test_a_gateway_whose_serial_path_is_late_has_its_frames_complete_not_its_elements_unknown_for_good() -> None:
    """Two gateways, one behind a path 50-500 ms slower. Every record of the slow one came
    after its frame's deadline: its elements were unknown in every frame, for as long as it
    ran (each record counted late). The deadline learns each gateway's lag."""
    for lag in (0.05, 0.2, 0.5):
        td = TimeDomains(HZ, margin=0.02)
        events = sorted([(at(i), 1, i) for i in range(600)] + [(at(i, lag), 2, i) for i in range(600)])
        out = []
        for t, gw, i in events:
            td.record(gw, record(1000 + i, (gw,), 1), 1, (1000 + i) * HZ // RATE, t, 0.001)
            out += td.take(t)
        settled = [f for f in out if f.index >= 1200]  # after the first 2 s
        assert [f.index for f in settled] == list(range(1200, 1600))
        assert all(f.complete and 2 in f.bridges for f in settled), lag
        late = td.counters(200.0)["late_records"]
        assert late <= (1.0 + lag) * RATE, (lag, late)  # only until its lag is learnt


def test_unchanged_in_a_gateways_first_record_after_a_root_move_is_not_believed() -> None:
    """Bridge 15 sampled, then said unchanged; its next sample was in a record lost on the
    line just as root 1 died. Gateway 16 took over as root 16 and carried the time on: its
    next record says 15 unchanged, against the sample the host never got. No index can
    show that loss across two roots' frames: 15 is missing in that frame (and counted)."""
    td = TimeDomains(HZ)
    out = []
    for i in range(50):
        td.record(16, record(1000 + i, (15, 16) if i == 0 else (16,), 1, () if i == 0 else (15,)), 1,
                  (1000 + i) * HZ // RATE, at(i), 0.001)
        out += td.take(at(i))
    for i in range(51, 60):  # frame 1050 lost on the line
        td.record(16, record(1000 + i, (16,), 16, (15,)), 16, (1000 + i) * HZ // RATE, at(i), 0.001)
        out += td.take(at(i))
    moved = [f for f in out if f.root == 16]
    assert moved and 15 not in moved[0].unchanged.tolist() and 15 in moved[0].missing.tolist()
    assert all(15 in f.unchanged.tolist() for f in moved[1:])  # from then on it speaks for itself again
    assert td.counters(101.0)["unchanged_after_gap"] >= 1
    assert all(15 in f.unchanged.tolist() for f in out if f.root == 1 and f.index > 1000)  # (the old root's)


def test_an_index_corrupted_a_few_frames_ahead_does_not_move_the_skins_time() -> None:
    """One record whose index passed the CRC 20 frames ahead (0.2 s, within the map's slack)
    lowered the map's envelope at once: every frame after it was timed 0.2 s early for a
    minute, and its deadline passed before its records could come."""
    c = SkinClock(HZ)
    for i in range(300):
        c.teach(1, (1000 + i) * HZ // RATE, at(i))
    c.teach(1, (1000 + 320) * HZ // RATE, at(300))  # frame 1300's record, its index 20 frames ahead
    for i in range(301, 600):
        c.teach(1, (1000 + i) * HZ // RATE, at(i))
    assert abs(c.frame_time((1000 + 600) * HZ // RATE, 200.0) - at(600)) < 0.002
    # a line whose delay truly drops (a gateway's first points came 50 ms late) is followed
    c = SkinClock(HZ)
    for i in range(100):
        c.teach(1, (1000 + i) * HZ // RATE, at(i, 0.05))
    for i in range(100, 110):
        c.teach(1, (1000 + i) * HZ // RATE, at(i))
    assert abs(c.frame_time((1000 + 110) * HZ // RATE, 200.0) - at(110)) < 0.002


def test_phantom_roots_do_not_lock_out_the_root_a_failover_moves_to_and_counts_survive() -> None:
    """A noisy line: 63 records passed the CRC corrupted, each naming a root (and a gateway)
    of its own. Their gateways are remembered for ``forget_after`` (10 min), so the table of
    roots stayed full of them: when the root gateway died and gateway 16 took over as root
    16, every record of it was refused for those 10 minutes (the whole skin unknown). And a
    root forgotten took its counts out of health (counts went down)."""
    td = TimeDomains(HZ)
    rng = random.Random(3)
    for i in range(300):
        for gw in (1, 16):
            td.record(gw, record(1000 + i, (gw - 1, gw), 1), 1, (1000 + i) * HZ // RATE, at(i), 0.001)
        if i < 63:
            phantom, root, k = rng.randrange(100, 60000), rng.randrange(100, 60000), rng.randrange(1 << 40)
            td.record(phantom, record(k, (phantom,), root), root, k * HZ // RATE, at(i), 0.001)
        td.take(at(i))
    before = td.counters(at(300))
    assert len(before["time_roots"]) == 64
    out = []
    for i in range(1300, 1400):  # 10 s later: root 1 died, gateway 16 is root 16
        td.record(16, record(1000 + i, (15, 16), 16), 16, (1000 + i) * HZ // RATE, at(i), 0.001)
        out += td.take(at(i))
    after = td.counters(at(1400))
    assert sum(f.root == 16 for f in out) >= 95
    assert after["rejected_records"] == before["rejected_records"]
    for key in ("records", "frames_complete", "frames_by_deadline"):
        assert after[key] >= before[key], key  # health counts never go back


def test_a_failover_to_a_root_last_mapped_at_boot_is_a_restart_not_hundreds_of_thousands_of_frames_missed() -> None:
    """Gateway 16 was its own root for its first second (its counter's epoch), then followed
    root 1; when root 1 died it became root 16 again, carrying root 1's time on. Root 16's
    map jumped (confirmed), and its frame sequence counted every frame between its boot
    time and root 1's time as missed (606 743 in a 4x4 virtual skin)."""
    td = TimeDomains(HZ)
    for i in range(100):  # at boot: root 16, on its own epoch
        td.record(16, record(5_000 + i, (16,), 16), 16, (5_000 + i) * HZ // RATE, at(i), 0.001)
        td.take(at(i))
    for i in range(100, 300):  # following root 1
        for gw in (1, 16):
            td.record(gw, record(700_000 + i, (gw,), 1), 1, (700_000 + i) * HZ // RATE, at(i), 0.001)
        td.take(at(i))
    out = []
    for i in range(300, 400):  # root 1 died: gateway 16 is root 16 on root 1's time
        td.record(16, record(700_000 + i, (16,), 16), 16, (700_000 + i) * HZ // RATE, at(i), 0.001)
        out += td.take(at(i))
    c = td.counters(at(400))
    assert c["frames_missed"] < 20, c["frames_missed"]
    assert c["restarts"] == 1 and c["rejected_records"] <= 20
    moved = [f for f in out if f.root == 16]
    assert moved[0].after_gap and [f.index for f in moved] == list(range(moved[0].index, 700_400))


def test_bridges_at_two_rates_a_lost_record_of_one_is_seen_and_frames_at_one_instant_are_not_late() -> None:
    """Bridge 5 at 100 Hz, bridge 7 at 40 Hz, one gateway. Frame 10 at 100 Hz (a new sample of
    5) was lost on the line: with 40 Hz frames given out between, the gap was looked for only
    against the newest frame given out, of the other rate, so frame 11 vouched for 5's sample
    of frame 0 ("unchanged"): a stale reading called known, and nothing counted missed. And
    every 2nd 40 Hz frame, at the instant of a 100 Hz frame already given out, was late."""
    sf = SkinFrames(0.01)
    events = [(k / 100, rec(k, 100, (5,) if k in (0, 10) else (), () if k in (0, 10) else (5,)))
              for k in range(30) if k != 10]
    events += [(j / 40, rec(j, 40, (7,) if j == 0 else (), () if j == 0 else (7,))) for j in range(12)]
    out = []
    for t, r in sorted(events, key=lambda e: e[0]):
        sf.add(1, r, t + 0.005, t)
        out += sf.take(t + 0.005)
    out += sf.take(10.0)
    (f11,) = [f for f in out if (f.index, f.rate) == (11, 100)]
    assert 5 not in f11.unchanged.tolist() and 5 in f11.missing.tolist() and f11.after_gap
    assert sf.counts["frames_missed"] == 1 and sf.counts["late_records"] == 0
    assert sorted(f.index for f in out if f.rate == 40) == list(range(12))
    assert all(7 in f.unchanged.tolist() for f in out if f.rate == 40 and f.index > 0)


def rec(k: int, rate: int, samples: tuple[int, ...] = (), unchanged: tuple[int, ...] = ()) -> Readout:
    return Readout(k, rate, Mode.COUNTER, 1, tuple(ReadoutSample(b, 1, 2, 0) for b in samples), unchanged, (),
                   SPAN_US, 0, 1)


def test_an_older_frame_of_another_root_given_out_later_never_vouches_with_a_newer_reference() -> None:
    """At a failover a gateway's records flap between the old root and the new one for a
    few frames, both counting the same mesh time: root 16's frame at 7.278 s came before
    root 1's frame at 7.275 s. Root 1's frame said element 0 unchanged, and the host gave
    it the sample of root 16's later frame; and a sample of the older frame overwrote the
    newer reference, so the next frame's "unchanged" vouched for the older sample."""
    r = ElementReadings(2, 8)
    one = np.array([0])
    dc = np.array([[0.5, 0.5]])
    caps = lambda v: np.array([[v, v]])
    r.scheduled(7.235, 1, one, caps(1.0), one, dc, np.array([False]), 1, one)  # root 1: a sample
    r.scheduled(7.278, 3, one, caps(2.0), one, dc, np.array([True]), 16, one)  # root 16, later: a new sample
    kept, kept_caps = r.references(one, 7.275)  # root 1's frame of 7.275 s, given out after, says unchanged
    assert kept.size == 0  # its bridge's sample then was the one of 7.235 s, not 7.278 s
    r.scheduled(7.265, 2, one, caps(3.0), one, dc, np.array([False]), 1, one)  # root 1's older sample, late
    kept, kept_caps = r.references(one, 7.285)  # root 16's next frame: unchanged since 7.278 s
    assert kept.tolist() == [0] and kept_caps.tolist() == [[2.0, 2.0]]


def test_a_record_copied_under_an_index_corrupted_ahead_is_refused_not_given_out_as_that_frame() -> None:
    """Frame 1200's record came a second time, its index corrupted to 1220 (0.2 s ahead,
    within the map's slack). It waited as frame 1220 and, whole, went out as soon as 1219
    did: frame 1220 carried bridge 5's sample of frame 1200 (a stale reading called known),
    and 1220's own record was late. The map holds that point back; its record is refused."""
    td = TimeDomains(HZ)
    out = []
    for i in range(300):
        k = 1000 + i
        r = Readout(k, RATE, Mode.COUNTER, 1, (ReadoutSample(5, 100 + i, 100 + i, 0),), (), (), SPAN_US, 0, 1, 1)
        td.record(1, r, 1, k * HZ // RATE, at(i), 0.001)
        if i == 200:
            bad = Readout(k + 20, RATE, Mode.COUNTER, 1, r.samples, (), (), SPAN_US, 0, 1, 1)
            td.record(1, bad, 1, (k + 20) * HZ // RATE, at(i), 0.001)
        out += td.take(at(i))
    (f,) = [f for f in out if f.index == 1220]
    assert f.c1.tolist() == [320] and f.complete
    c = td.counters(at(300))
    assert c["rejected_records"] == 1 and c["late_records"] == 0


def test_mesh_time_drifting_100_ppm_from_the_host_for_an_hour_stays_mapped_within_a_millisecond() -> None:
    """The root's crystal ±100 ppm off the host's monotonic clock for an hour, serial delays
    of 3 ms and a random wait: the map follows the skew (no point held back for long, no
    reset), every frame's host time within 1 ms of when its gates opened (plus the 3 ms)."""
    for ppm in (100.0, -100.0):
        rng = random.Random(1)
        c = SkinClock(HZ)
        worst = 0.0
        g0 = 123_456_789_000
        for i in range(3600 * 5):
            host = 1000.0 + i / 5
            g = g0 + int(i / 5 * (1 + ppm * 1e-6) * HZ)
            arrival = host + 0.003 + rng.expovariate(1 / 0.002)
            c.teach(1, g, arrival)
            if i > 5 * 120 and i % 97 == 0:
                ahead = g0 + int((i + 1) / 5 * (1 + ppm * 1e-6) * HZ)
                worst = max(worst, abs(c.frame_time(ahead, arrival + 1.0) - (1000.0 + (i + 1) / 5 + 0.003)))
        assert worst < 0.001 and c.resets == 0, (ppm, worst)
