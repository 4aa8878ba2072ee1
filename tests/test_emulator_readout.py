"""The scheduled readout against the emulator's ground truth: what a record says of an
element is what its bridge sampled, and what it does not know it lists as missing.

Every bridge's own state of every frame is logged as the sampler hands it to the readout
(the ground truth); the gateways' READOUT records are then checked against it, element
by element, under random frame loss, a relay killed mid-run, and event-based reporting
under presses.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Iterator

import pytest
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.readout import FrameReadout, ReadoutConfig
from cellbridge.emulator.firmware.reporting import ReportingMode
from cellbridge.emulator.firmware.sampling import Sampler
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import VirtualMesh
from cellbridge.emulator.world.world import Contact, World
from cellbridge.protocol import FrameType, Mode, Readout, ReadoutSample

from support.payloads import payload_as
from support.readout_truth import Truth, log_readout_states, records


@pytest.fixture
def truth(monkeypatch: pytest.MonkeyPatch) -> Iterator[Truth]:
    """(bridge, index) -> (c1, c2, sent) of every state a bridge handed its readout."""
    yield log_readout_states(monkeypatch)


def test_periodic_records_under_loss_and_a_dead_relay_say_what_each_bridge_sampled(truth: Truth) -> None:
    mesh = meshgen.grid(4, 4, loss=0.01, gateways=(1,))
    vm = VirtualMesh(mesh, seed=7, readout=True)
    vm.kill(6, at=4.0)  # a relay in the middle: its subtree re-routes
    vm.run(7.0)
    got = records(vm)
    assert got
    samples = missing = 0
    for (b, k), (state, s) in got.items():
        assert state != "u", "periodic reporting sends samples"
        if state == "s":
            assert s is not None
            assert (s.c1, s.c2) == truth[(b, k)][:2], (b, k)  # never a wrong reading
            samples += 1
        else:
            missing += 1
    assert missing > 0  # the loss and the dead relay were real, and said so
    # frames of bridge 6 after its death are in no record as samples
    assert not any(b == 6 and st == "s" and k > 405 for (b, k), (st, _) in got.items())
    # after the skin re-formed, the share known is high
    late = [(b, k) for (b, k) in got if 600 <= k < 690 and b != 6]  # 6 is listed missing until forgotten
    known = sum(1 for key in late if got[key][0] == "s")
    assert known >= 0.99 * len(late), (known, len(late))


def test_event_based_records_keep_every_unchanged_element_within_its_threshold(truth: Truth) -> None:
    # The host reads an unchanged element as its last sample, and only when it knew the
    # element's frame before (a record lost on the way breaks the chain until the next
    # sample). Whatever it reads that way must lie within the reporting threshold of what
    # the bridge sampled at that frame.
    mesh = meshgen.grid(4, 4, loss=0.01, gateways=(1,))
    presses = [Contact(1.5 + 0.7 * i, 0.5, 0.02 + 0.04 * (i % 3), 0.03 + 0.03 * (i % 2), 3.0, 0.02)
               for i in range(6)]
    vm = VirtualMesh(mesh, seed=3, world=World(mesh, presses), readout=True,
                     settings=Settings(reporting=ReportingMode(40, 1000)))
    vm.run(6.0)
    got = records(vm)
    reading: dict[int, tuple[int, int]] = {}
    last_index: dict[int, int] = {}
    checked = unchanged = 0
    for (b, k) in sorted(got, key=lambda x: (x[1], x[0])):
        state, s = got[(b, k)]
        prev = last_index.get(b)
        if state == "s":
            assert s is not None
            reading[b] = (s.c1, s.c2)
        elif state == "u" and prev == k - 1 and b in reading:
            c1, c2, kept = truth[(b, k)]
            assert not kept
            assert abs(c1 - reading[b][0]) <= 40 and abs(c2 - reading[b][1]) <= 40, (b, k)
            unchanged += 1
        else:
            reading.pop(b, None)  # missing, or unchanged after a frame the host did not know
        last_index[b] = k if state != "m" else -1
        checked += 1
    assert unchanged > 1000 and checked > 5000


def test_a_relay_whose_record_failed_sends_its_subtree_as_samples_next() -> None:
    from collections import Counter

    c: Counter[str] = Counter()
    r = FrameReadout(5, ReadoutConfig(depths=4, window=1000), c)
    child = Readout(10, 100, Mode.COUNTER, 1, (ReadoutSample(7, 100, 200, 0),), (), ())
    r.child(7, child, 0)
    r.own(10, 100, Mode.COUNTER, 1, ReadoutSample(5, 1, 2, 0), 500, 5000)
    first = r.take(0)
    assert [s.bridge for s in first[0].samples] == [5, 7]
    r.sent(False)  # its hop was not acknowledged: the host may not have these samples
    r.child(7, Readout(11, 100, Mode.COUNTER, 1, (), (7,), ()), 100)
    r.own(11, 100, Mode.COUNTER, 1, "u", 600, 5000)
    second = r.take(100)
    assert second[0].unchanged == ()
    assert [(s.bridge, s.c1, s.c2) for s in second[0].samples] == [(5, 1, 2), (7, 100, 200)]
    assert c["readout_expanded"] == 2


def test_after_a_failed_record_a_frame_is_never_expanded_to_a_later_frames_sample() -> None:
    """A bridge whose process is late (real-time shells on a loaded host, 250 Hz: frames 4
    ms apart, wakes ~6 ms late) may build its record of frame 11 after its state of frame 12
    came, and a relay after its child's record of 12. The expansion after a failed record
    took the sample kept, frame 12's, as frame 11's: the host called the element known in
    frame 11 with a reading the bridge took a frame later (51 element-frames in 10 s of a
    4x4 with 1 % loss per hop). A state is expanded only to a sample not newer than its
    frame; else it stays unchanged (the host knows it only if it knew the frame before)."""
    from collections import Counter

    c: Counter[str] = Counter()
    r = FrameReadout(5, ReadoutConfig(depths=4, window=1000), c)
    r.child(7, Readout(10, 100, Mode.COUNTER, 1, (ReadoutSample(7, 100, 200, 0),), (), ()), 0)
    r.own(10, 100, Mode.COUNTER, 1, ReadoutSample(5, 1, 2, 0), 500, 5000)
    assert [s.bridge for s in r.take(0)[0].samples] == [5, 7]
    r.sent(False)  # its hop was not acknowledged
    r.own(11, 100, Mode.COUNTER, 1, "u", 600, 5000)
    r.child(7, Readout(12, 100, Mode.COUNTER, 1, (ReadoutSample(7, 101, 201, 0),), (), ()), 100)
    r.own(12, 100, Mode.COUNTER, 1, ReadoutSample(5, 3, 4, 0), 700, 5000)  # before 11's record went
    r.child(7, Readout(11, 100, Mode.COUNTER, 1, (), (7,), ()), 100)
    by_index = {rec.index: rec for rec in r.take(100)}
    eleven = by_index[11]
    assert {(s.bridge, s.c1, s.c2) for s in eleven.samples} <= {(5, 1, 2), (7, 100, 200)}  # never 12's
    assert {s.bridge for s in eleven.samples} | set(eleven.unchanged) | set(eleven.missing) == {5, 7}


def test_a_child_whose_record_does_not_come_is_listed_missing_at_the_slot() -> None:
    from collections import Counter

    c: Counter[str] = Counter()
    r = FrameReadout(5, ReadoutConfig(depths=4, window=1000), c)
    r.child(7, Readout(1, 100, Mode.COUNTER, 1, (ReadoutSample(7, 1, 1, 0),), (9,), ()), 0)
    r.own(2, 100, Mode.COUNTER, 1, "u", 2000, 5000)
    passed = r.take(1999)  # frame 1 (not sampled here) is passed on a window after it came
    assert [x.index for x in passed] == [1]  # frame 2 is not complete before its slot: 7 is expected
    out = r.take(2000)
    assert out[0].unchanged == (5,) and out[0].missing == (7, 9)


def test_a_record_of_a_frame_older_than_the_last_record_sent_is_dropped_however_old() -> None:
    """The gateway (or a relay) remembers the last 256 frames it sent; a child's record of an
    older one (a relay passing on a record seconds old) went on alone before, and the host got
    a second record of a frame it had given out. It is counted late instead."""
    from collections import Counter

    c: Counter[str] = Counter()
    r = FrameReadout(1, ReadoutConfig(depths=4, window=1000), c)
    for k in range(300):  # 300 frames at 100 Hz, each sent at its slot
        r.own(k, 100, Mode.COUNTER, 1, ReadoutSample(1, k, k, 0), k * 500_000, 5000)
        assert [x.index for x in r.take(k * 500_000)] == [k]
    r.child(7, Readout(5, 100, Mode.COUNTER, 1, (ReadoutSample(7, 1, 1, 0),), (), ()), 300 * 500_000)
    r.own(300, 100, Mode.COUNTER, 1, ReadoutSample(1, 0, 0, 0), 300 * 500_000 + 4000, 5000)
    assert [x.index for x in r.take(300 * 500_000 + 4000)] == [300]  # frame 5 does not go on again
    assert c["readout_late"] == 1
    # the skin's time going back (a new root numbering from 0) is followed, not taken for late
    r = FrameReadout(1, ReadoutConfig(depths=4, window=1000), c)
    r.own(100_000, 100, Mode.COUNTER, 1, ReadoutSample(1, 0, 0, 0), 0, 5000)
    assert [x.index for x in r.take(0)] == [100_000]
    r.child(7, Readout(2, 100, Mode.COUNTER, 1, (ReadoutSample(7, 1, 1, 0),), (), ()), 10)
    assert c["readout_time_back"] == 1 and c["readout_late"] == 1
    assert [x.index for x in r.take(1010)] == [2]


def test_a_record_too_large_for_a_frame_fills_each_part_before_the_next() -> None:
    """A relay near the gateway sends most of the skin's samples: a record of 40 samples
    goes in 3 frames (16, 16, 8), not halved into 4 of 10; every part fits a frame, and the
    parts hold every state once."""
    from cellbridge.emulator.firmware.readout import _fits, _split

    r = Readout(7, 250, Mode.COUNTER, 1, tuple(ReadoutSample(b, 1_000_000 + b, 2_000_000 + b, 0) for b in range(1, 41)),
                (50, 51), (60,), 100_000)
    parts = _split(r)
    assert all(_fits(p) for p in parts)
    assert len(parts) == 3, [len(p.samples) for p in parts]
    assert sorted(s.bridge for p in parts for s in p.samples) == list(range(1, 41))
    assert [b for p in parts for b in p.unchanged] == [50, 51] and [b for p in parts for b in p.missing] == [60]
    for a, b in zip(parts, parts[1:]):  # none could have taken the next one's first entry
        first = b.samples[:1]
        assert not first or not _fits(Readout(a.index, a.rate, a.mode, a.oversampling, a.samples + first, a.unchanged,
                                              a.missing, a.span_us))


def test_a_split_record_has_the_parts_that_filling_entry_by_entry_gives() -> None:
    """``_split`` finds each part by bisection: its parts are exactly those of adding the
    entries one by one until the next would not fit, for records of every size, with
    small and large values (a packed entry from 1 to 9 bytes a number), with the
    gateway's room kept or not."""
    import random

    from cellbridge.emulator.firmware.readout import _fits, _part, _split

    def one_by_one(r: Readout, room: int) -> list[Readout]:
        if _fits(r, room):
            return [r]
        items: list[tuple[str, object]] = [("s", s) for s in r.samples]
        items += [("u", b) for b in r.unchanged] + [("m", b) for b in r.missing]
        out: list[Readout] = []
        part: list[tuple[str, object]] = []
        for item in items:
            if part and not _fits(_part(r, [*part, item]), room):
                out.append(_part(r, part))
                part = []
            part.append(item)
        return [*out, _part(r, part)]

    rng = random.Random(5)
    split = 0
    for _ in range(400):
        ids = sorted(rng.sample(range(1, 70_000), rng.randint(2, 80)))
        kinds = [rng.choice("ssum") for _ in ids]
        big = rng.choice([10, 70_000, 2**31])
        r = Readout(rng.randrange(2**32), 100, Mode.COUNTER, 1,
                    tuple(ReadoutSample(b, rng.randrange(big), rng.randrange(big), rng.randrange(4))
                          for b, k in zip(ids, kinds) if k == "s"),
                    tuple(b for b, k in zip(ids, kinds) if k == "u"),
                    tuple(b for b, k in zip(ids, kinds) if k == "m"), rng.randrange(2**20), 0, 1, rng.randrange(3))
        room = rng.choice([0, 5])
        parts = _split(r, room)
        assert parts == one_by_one(r, room)
        split += len(parts) > 1
    assert split > 100  # the records did need splitting, most of them into several parts


@pytest.mark.parametrize("n", [0, 1, 2, 3, 4, 6, 9, 14, 20])
def test_whether_a_record_fits_is_what_its_packed_size_says(n: int) -> None:
    """``_fits`` skips packing a record whose largest possible encoding fits: its answer
    is the packed size's for records of every number of entries around that bound, with
    the largest numbers each field can hold and the smallest, with room kept or not."""
    from cellbridge.emulator.firmware.readout import _fits
    from cellbridge.protocol import CRC_LEN, HEADER_LEN, MAX_FRAME
    from cellbridge.protocol.messages import pack_payload

    for big in (False, True):
        v = (lambda x: x) if not big else (lambda x: 0xFFFF_FFFF - x)
        samples = tuple(ReadoutSample(0xFFFF - b if big else b, v(b), v(2 * b), 3 if big else 0) for b in range(n))
        ids = tuple(range(1000, 1000 + n))
        for k in range(n + 1):
            r = Readout(2**64 - 1 if big else 1, 0xFFFF if big else 100, Mode.ADC if big else Mode.COUNTER,
                        0xFFFF if big else 1, samples[:k], ids[k:], ids[:n - k] if big else (),
                        0xFFFF_FFFF if big else 0, 0, 1, 0xFFFF if big else 0, 0xFFFF_FFFF if big else 0)
            for room in (0, 5, 40):
                truth = HEADER_LEN + CRC_LEN + len(pack_payload(r)) + room <= MAX_FRAME
                assert _fits(r, room) == truth, (n, k, big, room)


def test_every_part_of_a_gateways_record_still_fits_a_frame_once_its_age_and_root_are_on_it() -> None:
    """A gateway stamps each part's age as it writes it: parts filled to the last byte
    without room for it went out too long for a frame, and the host dropped them (on a
    humanoid, part 0 of a pressed patch's record, every frame)."""
    from cellbridge.emulator.firmware.readout import AGE_ROOM, _fits, record_parts

    samples = [ReadoutSample(b, 1_000_000 + b, 2_000_000 + b, 0) for b in range(1, 81)]
    for root in (1, 200, 0xFFFF):
        parts = record_parts(7, 250, {(Mode.COUNTER, 1): (samples, [90, 91], [95])}, 100_000, root, AGE_ROOM)
        assert len(parts) > 1 and all(p.root == root and p.parts == len(parts) for p in parts)
        assert sorted(s.bridge for p in parts for s in p.samples) == list(range(1, 81))
        assert all(_fits(dataclasses.replace(p, age_us=0xFFFF_FFFF)) for p in parts)
        plain = record_parts(7, 250, {(Mode.COUNTER, 1): (samples, [90, 91], [95])}, 100_000, root)
        assert all(_fits(p) for p in plain)  # (a relay's: no room kept, its root measured)


def test_records_of_a_parent_and_its_child_do_not_take_the_same_slot() -> None:
    """At 250 Hz a relay's record of frame k and its child's record of frame k + 1 wait for
    the same transmission's end; with equal ranks they started together and the child's
    was lost to the relay's half duplex (101 in 2 s of a 4x4). A depth's parity in the
    slots keeps them apart."""

    vm = VirtualMesh(meshgen.grid(4, 4, gateways=(1,)), seed=1, settings=Settings(rate_hz=250), readout=True)
    vm.run(4.0)  # every bridge on the schedule
    before = vm.medium.counters.get("half_duplex_at_addressee", 0)
    vm.run(2.0)
    lost = vm.medium.counters.get("half_duplex_at_addressee", 0) - before
    assert lost <= 10, lost


def test_a_frame_complete_early_waits_for_the_older_frames_of_its_rate() -> None:
    """The host reads a record of a later frame on a gateway's line as the loss of the
    earlier ones (a line keeps its order): a frame whose records all came waits until
    every older frame's record went, at its slot at the latest."""
    from collections import Counter

    c: Counter[str] = Counter()
    r = FrameReadout(1, ReadoutConfig(depths=4, window=1000), c)
    r.child(7, Readout(0, 100, Mode.COUNTER, 1, (ReadoutSample(7, 1, 1, 0),), (), ()), 0)  # 7 is expected
    r.child(8, Readout(0, 100, Mode.COUNTER, 1, (ReadoutSample(8, 1, 1, 0),), (), ()), 0)  # so is 8
    assert [x.index for x in r.take(1000)] == [0]  # passed on a window later
    r.own(1, 100, Mode.COUNTER, 1, "u", 10_000, 5000)
    r.own(2, 100, Mode.COUNTER, 1, "u", 12_000, 5000)
    r.child(7, Readout(1, 100, Mode.COUNTER, 1, (ReadoutSample(7, 2, 2, 0),), (), ()), 8000)
    r.child(7, Readout(2, 100, Mode.COUNTER, 1, (ReadoutSample(7, 2, 2, 0),), (), ()), 9000)
    p2 = r._pending[(100, 2)]  # frame 2 as if complete: its own state and every child heard
    p2.heard = {7, 8}
    assert r.take(9000) == []  # not before frame 1, which waits for 8
    out = r.take(10_000)  # frame 1 at its slot (8 missing), then frame 2
    assert [x.index for x in out] == [1, 2]


def test_a_frame_whose_child_already_sent_a_later_record_goes_without_waiting_for_its_slot() -> None:
    """A child sends its records in frame order: once its record of frame 2 came, its record
    of frame 1 was lost, and frame 1 goes at once with the child missing (the frames behind
    it waited for frame 1's slot, 80 ms at a real-time gateway, otherwise)."""
    from collections import Counter

    c: Counter[str] = Counter()
    r = FrameReadout(1, ReadoutConfig(depths=4, window=1000), c)
    r.child(7, Readout(0, 100, Mode.COUNTER, 1, (ReadoutSample(7, 1, 1, 0),), (), ()), 0)  # 7 is expected
    assert [x.index for x in r.take(1000)] == [0]
    r.own(1, 100, Mode.COUNTER, 1, "u", 10_000, 5000)  # 7's record of frame 1 lost on its way
    r.own(2, 100, Mode.COUNTER, 1, "u", 12_000, 5000)
    r.child(7, Readout(2, 100, Mode.COUNTER, 1, (ReadoutSample(7, 2, 2, 0),), (), ()), 3000)
    out = r.take(3000)
    assert [(x.index, x.missing) for x in out] == [(1, (7,)), (2, ())]


def test_a_record_held_up_tens_of_ms_in_the_real_time_shells_still_makes_its_frame() -> None:
    """A bridge process held up by a loaded host (tens of ms before it computes its sample
    and sends its record) is late for its own slot. With the real-time shells' levels
    spread evenly its parent gave it up 10 ms after that slot and dropped the record as
    late, and every record it sent while behind went the same way: its element unknown for
    as long as the host stayed loaded. With the slots packed at the span's end the parent
    waits until just before its own parent's slot, and passes the record on as soon as it
    comes. (A 4x4 with a corner gateway: the leaf is 6 hops deep, its parent 5, of 8 levels.)"""
    from collections import Counter

    from cellbridge.emulator.realtime.process_bridge import READOUT_HOP, READOUT_WINDOW

    ms = 50_000
    config = ReadoutConfig(depths=8, window=READOUT_WINDOW, hop=READOUT_HOP)
    c: Counter[str] = Counter()
    parent = FrameReadout(5, config, c)
    leaf = FrameReadout(7, config, Counter())
    period = 10 * ms  # 100 Hz
    gates = 4 * ms
    sent: dict[int, tuple[int, Readout]] = {}
    arrivals: list[tuple[int, Readout]] = []  # (tick, the leaf's record) at the parent
    # (frame 0: the parent learns of its child before its own state comes)
    for k, held_up in ((0, -ms), (1, 0), (2, 40 * ms), (3, 40 * ms), (4, 0)):
        gate_end = k * period + gates
        # the leaf's process wakes ``held_up`` late: its sample and record come then, and
        # reach the parent a millisecond later (airtime, the medium)
        leaf.own(k, 100, Mode.COUNTER, 1, ReadoutSample(7, k, k, 0), gate_end + leaf.slot(6), leaf.slot(0))
        arrivals += [(gate_end + held_up + ms, r) for r in leaf.take(gate_end + held_up)]
    for t in range(0, 5 * period + 100 * ms, ms // 2):
        while arrivals and arrivals[0][0] <= t:
            parent.child(7, arrivals.pop(0)[1], t)
        if t % period == gates and t // period < 5:  # the parent's own sample, on time
            k = t // period
            parent.own(k, 100, Mode.COUNTER, 1, ReadoutSample(5, k, k, 0), t + parent.slot(5), parent.slot(0))
        for r in parent.take(t):
            sent[r.index] = (t, r)
    assert c["readout_late"] == 0
    for k in range(5):
        t, r = sent[k]
        assert [s.bridge for s in r.samples] == [5, 7] and r.missing == ()
    t2, _ = sent[2]
    assert t2 - (2 * period + gates) <= 42 * ms  # it went when the record came, not at its slot
    # the parent's own record still has a hop's time before the grandparent's slot
    assert parent.slot(4) - parent.slot(5) >= 4 * ms


def test_a_bridge_a_child_lists_missing_stays_with_the_branch_its_state_comes_through() -> None:
    """After the root gateway died, bridge 3 (and 4 behind it) moved from relay 2's subtree
    to relay 7 directly, while 2, now behind 6, still listed them missing until it forgot
    them (2 s). At 7, 6's stale claim and 3's own record took 3 and 4 from each other at
    every frame; whenever 6's record came first, child 3 was no longer expected, the frame
    went at once with 3 and 4 missing and 3's record came late: unknown in two frames of
    three for 2 s. A bridge listed missing stays with the branch its state comes through."""
    from collections import Counter

    c: Counter[str] = Counter()
    r = FrameReadout(7, ReadoutConfig(depths=4, window=1000), c)
    sample = ReadoutSample(0, 1, 1, 0)
    for k, t in ((1, 0), (2, 10_000), (3, 20_000)):
        r.own(k, 100, Mode.COUNTER, 1, sample._replace(bridge=7), t + 5000, 5000)
        stale = Readout(k, 100, Mode.COUNTER, 1, (sample._replace(bridge=2), sample._replace(bridge=6)), (), (3, 4))
        r.child(6, stale, t + 1000)  # 6's record first: it still lists 3 and 4, missing
        if k > 1:  # 3 is expected from its first record on: the frame waits for it
            assert r.take(t + 1000) == [], k
        r.child(3, Readout(k, 100, Mode.COUNTER, 1, (sample._replace(bridge=3), sample._replace(bridge=4)), (), ()),
                t + 2000)
        out = r.take(t + 2000) if k > 1 else r.take(t + 5000)
        assert [(x.index, [s.bridge for s in x.samples], x.missing) for x in out] == [(k, [2, 3, 4, 6, 7], ())], k
    assert c["readout_late"] == 0


def test_a_later_frame_whose_slot_passed_does_not_wake_the_bridge_before_the_older_frame_can_go() -> None:
    """A later frame's slot can come before an older one's (a frame a child's record began,
    or one planned at another depth); it goes only after the older one. Its slot taken for
    the next wake, the firmware woke at every tick (20 ns) until the older frame's slot: a
    boot of a 4x4 with two gateways took minutes of CPU instead of seconds."""
    from collections import Counter

    r = FrameReadout(5, ReadoutConfig(depths=4, window=1000), Counter())
    for b in (7, 8):  # 7 and 8 are expected
        r.child(b, Readout(1, 100, Mode.COUNTER, 1, (ReadoutSample(b, 1, 1, 0),), (), ()), 0)
    assert [x.index for x in r.take(1000)] == [1]
    r.own(2, 100, Mode.COUNTER, 1, "u", 9000, 5000)  # waits for 7 (and 8) until its slot
    r.child(8, Readout(3, 100, Mode.COUNTER, 1, (ReadoutSample(8, 1, 1, 0),), (), ()), 2000)  # frame 3 begun
    assert r.take(2000) == [] and r.next_tick == 9000  # frame 3's slot, 3000, cannot go before frame 2
    assert [x.index for x in r.take(3000)] == [] and r.next_tick == 9000
    assert [x.index for x in r.take(9000)] == [2, 3]


def test_a_record_names_the_root_its_index_counts_not_the_one_the_bridge_follows_when_it_goes() -> None:
    """At boot gateway 16 was its own root while its children were on root 1's time: it
    stamped its own root on their records (their indices count root 1; ~100 refused by the
    host). A record names the root of its frame: the bridge's own when it sampled, or the
    child's for a frame it passes on, and frames of two roots wait for each other only
    within their own root."""
    from collections import Counter

    r = FrameReadout(16, ReadoutConfig(depths=4, window=1000), Counter())
    r.own(723_687, 100, Mode.COUNTER, 1, ReadoutSample(16, 1, 1, 0), 9000, 5000, root=16)
    r.child(12, Readout(1_330_216, 100, Mode.COUNTER, 1, (ReadoutSample(12, 1, 1, 0),), (), (), root=1), 0)
    out = r.take(1000) + r.take(9000)  # (the child's frame of root 1 goes a window after it came)
    assert sorted((x.index, x.root) for x in out) == [(723_687, 16), (1_330_216, 1)]


@pytest.mark.parametrize("seed", [4, 5, 6])
def test_at_boot_a_gateway_that_is_its_own_root_names_no_childs_frame_with_its_root(
        monkeypatch: pytest.MonkeyPatch, seed: int) -> None:
    """Two gateways, 1 and 16: 16 is its own root for its first second (its own epoch) while
    its children already sample on root 1's time. It stamped its own root on the records it
    passed on (110 records refused by the host in the two-gateway truth run; with the root
    taken with the sample but frames of both roots passed on, its line switched roots at
    every record, 198 root moves at the host). Every record on 16's line names the root its
    samples were taken on, and the line switches root once (16, then 1): also when its clock
    follows root 1 while its next gate is still planned on root 16 (seeds 4 and 6: a frame
    of its children alone on root 1 went before that gate's own frame, 16, 1, 16, 1)."""
    roots: dict[tuple[int, int], int] = {}  # (bridge, index) -> the root whose time gave the index
    plan = Sampler._plan

    def logged(self: Sampler, earliest: int, free: int, restart: bool = False) -> None:
        plan(self, earliest, free, restart)
        if self.on_time:  # the index as the clock gave it, and the root that clock followed then
            roots[(self.timebase.clock.me, self.index)] = self.timebase.clock.root or 0

    monkeypatch.setattr(Sampler, "_plan", logged)
    vm = VirtualMesh(meshgen.grid(4, 4, gateways=(1, 16), loss=0.01), seed=seed, random_epochs=True,
                     settings=Settings(rate_hz=100), readout=True)
    vm.run(4.0)
    named = [payload_as(f, Readout).root for f in vm.frames[16] if f.type is FrameType.READOUT]
    wrong = [(s.bridge, payload_as(f, Readout).index, payload_as(f, Readout).root, roots.get((s.bridge, payload_as(f, Readout).index)))
             for f in vm.frames[16] if f.type is FrameType.READOUT
             for s in payload_as(f, Readout).samples
             if roots.get((s.bridge, payload_as(f, Readout).index), 0) not in (0, payload_as(f, Readout).root)]
    assert not wrong, wrong[:10]
    switches = [(a, b) for a, b in zip(named, named[1:]) if a != b]
    assert switches == [(16, 1)], switches[:10]
    assert vm.nodes[16].counters["readout_other_root"] > 0  # its children's frames of root 1, dropped while it was root 16


def test_frames_sampled_before_a_root_switch_go_before_the_new_roots_frames() -> None:
    """Gateway 16's own frame of its own root, sampled before it followed root 1, waited for
    its slot while its first frame of root 1 went: the line named 16, 1, 16, 1 (seed 6 of
    bench_root_failover). The frames of the root followed now wait until those went."""
    from collections import Counter

    r = FrameReadout(16, ReadoutConfig(depths=4, window=1000), Counter())
    r.child(12, Readout(1, 100, Mode.COUNTER, 1, (ReadoutSample(12, 1, 1, 0),), (), (), root=16), 0)
    assert [x.index for x in r.take(1000, 16)] == [1]  # 12 is expected
    r.own(191_562, 100, Mode.COUNTER, 1, ReadoutSample(16, 1, 1, 0), 9000, 5000, root=16)  # waits for 12
    r.own(892_925, 100, Mode.COUNTER, 1, ReadoutSample(16, 1, 1, 0), 5000, 5000, root=1)  # a slot before it
    assert r.take(5000, 1) == [] and r.next_tick == 9000
    assert [(x.index, x.root) for x in r.take(9000, 1)] == [(191_562, 16), (892_925, 1)]


def test_a_multi_hop_skin_at_one_percent_loss_per_hop_keeps_its_element_frames_known(truth: Truth) -> None:
    """A 4x4 at 250 Hz read out through one corner gateway (up to six hops), 1 % of frames
    lost on every hop. A relay's record of frame k + 1 went while its record of k still
    waited for its acknowledgement; when that acknowledgement did not come, the parent had
    taken the record of k + 1 for the loss of k's, listed the relay's whole subtree missing,
    and the retry of k, come through, was dropped as late (98.0 % of element-frames known).
    With the later frame's record waiting for the earlier one's outcome, and retries while
    they can still reach the parent by its slot, the skin keeps its element-frames known,
    and every one it calls known is what its bridge sampled."""
    mesh = meshgen.grid(4, 4, loss=0.01, gateways=(1,))
    vm = VirtualMesh(mesh, seed=7, settings=Settings(rate_hz=250), readout=True)
    vm.run(7.0)
    got = records(vm)
    window = [(b, k) for b in mesh.ids for k in range(1000, 1700)]  # 4 s on: every bridge on mesh time
    known = [key for key in window if got.get(key, ("m", None))[0] == "s"]
    assert len(known) >= 0.999 * len(window), (len(known), len(window))
    for key, (state, s) in got.items():
        assert state != "u"  # periodic reporting
        if s is not None:
            assert (s.c1, s.c2) == truth[key][:2], key
    assert vm.result().total("retries") > 0  # the loss was real


def _relay_that_failed_once() -> tuple[FrameReadout, Counter[str]]:
    """Relay 5 with child 7 (event-based): frames 1 and 2 passed on, 7's sample in each."""
    c: Counter[str] = Counter()
    r = FrameReadout(5, ReadoutConfig(depths=4, window=1000), c)
    for k, (t, v) in enumerate(((0, 100), (10_000, 200)), start=1):
        r.child(7, Readout(k, 100, Mode.COUNTER, 1, (ReadoutSample(7, v, v, 0),), (), ()), t)
        r.own(k, 100, Mode.COUNTER, 1, ReadoutSample(5, 1, 1, 0) if k == 1 else "u", t + 900, 5000)
        assert [x.index for x in r.take(t + 100)] == [k]
    return r, c


def test_a_late_retry_of_an_older_record_does_not_become_the_sample_an_expansion_sends() -> None:
    """A child's record of frame 1 got through but its acknowledgement was lost; its retries
    go on, and once past the first the record of frame 2 no longer waits for them: the last
    retry of 1 comes after 2. It is late (dropped), but its sample replaced 2's as the one
    the relay kept for 7; when the relay's own record then failed, its next record expanded
    7's *unchanged* to frame 1's reading, a sample 7 no longer held: a wrong reading the
    host took as known."""
    r, c = _relay_that_failed_once()
    r.child(7, Readout(1, 100, Mode.COUNTER, 1, (ReadoutSample(7, 100, 100, 0),), (), ()), 10_200)  # the retry
    assert c["readout_late"] == 1
    r.sent(False)  # the relay's record of frame 2 was not acknowledged
    r.child(7, Readout(3, 100, Mode.COUNTER, 1, (), (7,), ()), 20_000)  # 7: within its threshold of 200
    r.own(3, 100, Mode.COUNTER, 1, "u", 20_900, 5000)
    (out,) = r.take(20_100)
    assert [(s.bridge, s.c1) for s in out.samples] == [(5, 1), (7, 200)]


def test_an_expansion_does_not_send_a_sample_of_a_bridge_whose_last_frame_came_another_way() -> None:
    """Bridge 7's record of frame 3 (a new sample) went up another route (relay 5's parent
    changed, or 7 moved for a frame), and 7 said *unchanged* against it in frame 4, back
    through relay 5. The sample relay 5 kept for 7 is frame 2's: expanded after a failed
    record, it was a wrong reading. A relay expands only what it knows is the reference;
    else the state stays *unchanged* (the host knows it only if it knew frame 3)."""
    r, c = _relay_that_failed_once()
    r.own(3, 100, Mode.COUNTER, 1, "u", 20_900, 5000)  # 7's record of frame 3 does not come here
    r.take(20_900)
    r.sent(False)
    r.child(7, Readout(4, 100, Mode.COUNTER, 1, (), (7,), ()), 30_000)
    r.own(4, 100, Mode.COUNTER, 1, "u", 30_900, 5000)
    (out,) = r.take(30_100)
    assert [(s.bridge, s.c1) for s in out.samples] == [(5, 1)] and out.unchanged == (7,)


def test_a_relay_that_dies_at_250_hz_has_its_subtree_rerouted_in_tens_of_ms_not_by_the_beacon_timeout() -> None:
    """At 250 Hz records are nearly all a bridge sends, and a record waits for the one before
    it: the frames whose failed transmissions evict a dead parent did not get the cell, and a
    record that failed all its retries was not told to the routing. Relay 6's subtree (seed 7)
    stayed unknown until its beacons timed out, 2.4 s: 4 806 element-frames. A record whose
    every retry went unacknowledged now counts as a lost link."""
    mesh = meshgen.grid(4, 4, loss=0.01, gateways=(1,))
    vm = VirtualMesh(mesh, seed=7, settings=Settings(rate_hz=250), readout=True)
    vm.kill(6, at=4.0)
    vm.run(5.0)
    got = records(vm)
    after = [(b, k) for (b, k) in got if k >= 1000 and b != 6]
    unknown = sum(1 for key in after if got[key][0] != "s")
    assert len(after) >= 15 * 200 and unknown <= 100, (unknown, len(after))
    assert all(p != 6 for p in vm.result().parents.values())


def test_a_child_silent_for_quiet_is_not_waited_for_until_it_is_heard_again() -> None:
    """Children 2 and 3; 3 falls silent. Until ``quiet`` has passed the frame waits for it
    (a slow child's record still makes its frame); after, the frame goes as soon as 2's
    record is in, with 3's subtree listed missing; once 3 is heard again it is waited for."""
    quiet = 5_000_000  # (above two frame periods at 100 Hz, and the span and a period, which count too)
    r = FrameReadout(1, ReadoutConfig(depths=4, window=1000, forget=10**9, quiet=quiet), Counter())
    slot = 10**8  # far: nothing here goes at its slot

    def rec(src: int, index: int) -> Readout:
        return Readout(index, 100, Mode.COUNTER, 1, (ReadoutSample(src, 1, 1, 0),))

    r.child(2, rec(2, 1), 0)
    r.child(3, rec(3, 1), 0)
    r.at(10)
    r.own(1, 100, Mode.COUNTER, 1, ReadoutSample(1, 1, 1, 0), slot, slot)
    assert [x.index for x in r.take(10)] == [1]
    # frame 2: 2's record comes, 3 is silent but heard 1 000 000 cycles ago: waited for
    r.own(2, 100, Mode.COUNTER, 1, ReadoutSample(1, 1, 1, 0), slot, slot)
    r.child(2, rec(2, 2), 1_000_000)
    assert r.take(1_000_000) == [] and r.expects_children(100)
    assert r.next_tick == quiet + 1  # it wakes when 3 stops being waited for, not at the slot
    got = r.take(quiet + 1)
    assert [(x.index, [s.bridge for s in x.samples], list(x.missing)) for x in got] == [(2, [1, 2], [3])]
    # 3 is heard again (its record of frame 2, late): waited for in frame 3
    r.child(3, rec(3, 2), quiet + 2)
    assert r.counters["readout_late"] == 1
    r.own(3, 100, Mode.COUNTER, 1, ReadoutSample(1, 1, 1, 0), slot, slot)
    r.child(2, rec(2, 3), quiet + 3)
    assert r.take(quiet + 3) == []
    r.child(3, rec(3, 3), quiet + 4)
    assert [(x.index, list(x.missing)) for x in r.take(quiet + 4)] == [(3, [])]


@pytest.mark.parametrize("held_ms", [90, 110, 150])
def test_a_child_held_up_as_long_as_the_schedule_absorbs_is_still_waited_for(held_ms: int) -> None:
    """The real-time shells' schedule (8 levels of 30 ms, slots packed 15 ms apart) lets a
    4x4's leaf (6 hops deep) be held up for up to ~150 ms and still make its parent's
    frame (its parent, 5 deep, waits until 165 ms after the gate). Silent for ``quiet``
    (100 ms), the leaf was no longer waited for: every frame of the hold from then on went
    without it, and each record it sent once running again came late (in a virtual real-time
    4x4 with the leaf held 110 ms every 500 ms, 255 element-frames of 4 144 unknown where
    the slots alone had none). A child is waited for as long as its record could still make
    the frame: ``quiet`` is not shorter than the schedule's span and a frame period."""
    from cellbridge.emulator.realtime.process_bridge import READOUT_HOP, READOUT_WINDOW

    ms = 50_000
    config = ReadoutConfig(depths=8, window=READOUT_WINDOW, hop=READOUT_HOP)  # quiet: its default, 100 ms
    c: Counter[str] = Counter()
    parent = FrameReadout(5, config, c)
    leaf = FrameReadout(7, config, Counter())
    period, gates, frames = 10 * ms, 4 * ms, 40
    hold = (10 * period + gates + ms, 10 * period + gates + ms + held_ms * ms)  # after frame 10's record left
    sent: dict[int, Readout] = {}
    arrivals: list[tuple[int, Readout]] = []  # (tick, the leaf's record) at the parent
    sampled = 0  # the leaf's frames sampled so far
    for t in range(0, frames * period + 300 * ms, ms // 2):
        if not hold[0] <= t < hold[1]:  # running: every frame whose gate ended (the hold's at once after it)
            while sampled < frames and sampled * period + gates <= t:
                k, sampled = sampled, sampled + 1
                leaf.own(k, 100, Mode.COUNTER, 1, ReadoutSample(7, k, k, 0), k * period + gates + leaf.slot(6),
                         leaf.slot(0))
            arrivals += [(t + ms, r) for r in leaf.take(t)]
        while arrivals and arrivals[0][0] <= t:
            parent.child(7, arrivals.pop(0)[1], t)
        # the parent's own sample, on time (frame 0's 2 ms late: it learns of its child first)
        if t % period == gates + (2 * ms if t < period else 0) and t // period < frames:
            k = t // period
            parent.own(k, 100, Mode.COUNTER, 1, ReadoutSample(5, k, k, 0), k * period + gates + parent.slot(5),
                       parent.slot(0))
        for r in parent.take(t):
            sent[r.index] = r
    assert sorted(sent) == list(range(frames))
    lost = [k for k, r in sent.items() if [s.bridge for s in r.samples] != [5, 7]]
    assert lost == [] and c["readout_late"] == 0, (lost, c)


def test_a_leaf_held_up_110_ms_every_half_second_keeps_its_frames_on_a_real_time_skin(truth: Truth) -> None:
    """The same in a virtual real-time 4x4 (bench/bench_readout_hold.py): its deepest leaf's
    process held up 110 ms every 500 ms. With children not waited for after 100 ms of
    silence, 255 element-frames of 4 144 were unknown (the leaf's 61 of 259 among them);
    the slots alone lose none. Every sample the host gets is what its bridge sampled."""
    from cellbridge.emulator.mesh.virtual import Latency
    from cellbridge.emulator.realtime.process_bridge import ACK_SLACK, READOUT_HOP, READOUT_WINDOW

    mesh = meshgen.grid(4, 4, gateways=(1,))
    vm = VirtualMesh(mesh, seed=5, latency=Latency(up=0.002, down=0.002, wake_late=0.001), readout=True,
                     readout_acks=False, readout_window=READOUT_WINDOW, readout_hop=READOUT_HOP,
                     ack_slack=ACK_SLACK, readout_depths=mesh.readout_depths())
    vm.run(6.0)
    leaf = 16  # (the corner opposite the gateway: 6 hops deep)
    assert vm.nodes[leaf].router.hops == 6 and not any(vm.nodes[b].router.parent == leaf for b in mesh.ids)
    for k in range(5):
        vm.hold(leaf, 6.2 + 0.5 * k, 0.110)
    vm.run(3.0)
    got = {key: v for key, v in records(vm).items() if 610 <= key[1] < 870}
    for (b, k), (state, s) in got.items():
        if state == "s":
            assert s is not None and (s.c1, s.c2) == truth[(b, k)][:2], (b, k)
    unknown = 16 * 260 - sum(1 for state, _ in got.values() if state != "m")
    assert unknown <= 10, unknown
    assert sum(1 for (b, _), (state, _) in got.items() if b == leaf and state == "s") >= 255
