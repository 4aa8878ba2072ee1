"""Where an element the host lost comes back from, on an event-based skin whose cells carry
no refresh to speak of: the gateway's refresh of its serial line, a whole record's step back
to the record its READOUT_SAMEs referred to, and a bridge's first record after a new route
(emulator/firmware/readout.py, docs/time.md).

Sans-I/O: a gateway's or relay's :class:`FrameReadout` fed its children's records, and a
bridge's :class:`LinkLayer` handing its records to the cell."""

from __future__ import annotations

import random
from collections import Counter

from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.linklayer import LinkLayer
from cellbridge.emulator.firmware.readout import AGE_ROOM, FrameReadout, ReadoutConfig, stagger
from cellbridge.emulator.firmware.reporting import ReportingMode
from cellbridge.emulator.firmware.transceiver import Transceiver
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import VirtualMesh
from cellbridge.protocol import (
    ADDR_BROADCAST,
    Command,
    Flags,
    Frame,
    FrameType,
    Mode,
    Op,
    Readout,
    ReadoutSame,
    ReadoutSample,
    decode,
    own,
)

PARENT = 9


def _record(index: int, samples: tuple[ReadoutSample, ...] = (), unchanged: tuple[int, ...] = (),
            ref_step: int = 0) -> Readout:
    return Readout(index, 100, Mode.COUNTER, 1, samples, unchanged, (), 2840, 0, 1, 1, 0, ref_step)


def _bridge(me: int, refresh: int = 0) -> tuple[FrameReadout, Counter[str]]:
    c: Counter[str] = Counter()
    return FrameReadout(me, ReadoutConfig(depths=4, window=1000), c, AGE_ROOM if refresh else 0, refresh), c


def _frame(r: FrameReadout, k: int, state: object = "u") -> Readout:
    """Frame ``k`` with this bridge's own ``state``, taken at its slot."""
    r.own(k, 100, Mode.COUNTER, 1, state, 1000 * k, 5000, 1)  # type: ignore[arg-type]  # a State
    out = r.take(1000 * k)
    assert [x.index for x in out] == [k]
    return out[0]


def _samples(r: Readout) -> dict[int, tuple[int, int]]:
    return {s.bridge: (s.c1, s.c2) for s in r.samples}


def test_a_gateway_writes_each_unchanged_element_it_keeps_as_its_sample_once_every_refresh_frames() -> None:
    """A record lost on the serial line (no bridge sees it) leaves the host without an
    element until its next sample: the gateway sends the sample it keeps, in the element's
    own phase, every ``refresh`` frames. It refreshes only what it keeps as the reference of
    the *unchanged* (an element it never had a sample of stays unchanged), and a relay
    (refresh 0) never does."""
    gw, c = _bridge(1, refresh=10)
    relay, rc = _bridge(5)
    first = _record(10, (ReadoutSample(7, 100, 200, 0),), (9,))
    gw.child(7, first, 0, seq=300)
    relay.child(7, first, 0, seq=300)
    _frame(gw, 10, ReadoutSample(1, 1, 2, 0))
    _frame(relay, 10, ReadoutSample(5, 1, 2, 0))
    kept = {1: (1, 2), 7: (100, 200)}  # (its own element too)
    for k in range(11, 41):
        gw.child(7, _record(k, (), (7, 9)), 1000 * k - 500, seq=300 + k - 10)
        relay.child(7, _record(k, (), (7, 9)), 1000 * k - 500, seq=300 + k - 10)
        out = _frame(gw, k)
        assert _frame(relay, k).samples == ()
        assert _samples(out) == {b: v for b, v in kept.items() if k % 10 == stagger(b, 10)}, (k, out)
        assert 9 in out.unchanged
    assert c["readout_serial_refreshed"] == 6 and rc["readout_serial_refreshed"] == 0


def test_a_gateway_does_not_refresh_an_element_from_a_sample_a_lost_frame_may_have_replaced() -> None:
    """Frame 12 of child 7 did not come (it may have held a new sample of 7): from then on
    the sample kept is no reference, and the gateway refreshes nothing of 7 (the host then
    waits for 7's next sample; a wrong reading is worse than an unknown one)."""
    gw, c = _bridge(1, refresh=4)
    gw.child(7, _record(10, (ReadoutSample(7, 100, 200, 0),)), 0, seq=300)
    _frame(gw, 10, ReadoutSample(1, 1, 2, 0))
    for k in range(11, 31):
        if k != 12:
            gw.child(7, _record(k, (), (7,)), 1000 * k - 500, seq=300 + k - 10)
        out = _frame(gw, k)
        if k > 12:
            assert 7 not in _samples(out), (k, out)
    assert c["readout_serial_refreshed"] == sum(1 for k in range(11, 31) if k % 4 == stagger(1, 4))  # its own only


def test_a_whole_record_after_lost_readout_sames_keeps_the_reference_of_the_elements_it_names() -> None:
    """Child 7's READOUT_SAME of frame 11 was lost (its elements missing here, owed to the
    host); its record of frame 12 is whole (8 changed) and says its reference is 2 frames
    back. A READOUT_SAME carries no sample, so 7's unchanged refers to the sample of frame
    10 this relay keeps: the relay pays its debt with it at once. Without the step it could
    not know that, and 7 stayed unknown to the host until its next sample."""
    for step, paid in ((2, True), (0, False), (1, False)):  # (1: a record this relay does not hold)
        r, c = _bridge(5)
        r.child(7, _record(10, (ReadoutSample(7, 100, 200, 0), ReadoutSample(8, 300, 400, 0))), 0, seq=300)
        _frame(r, 10, ReadoutSample(5, 1, 2, 0))
        assert _frame(r, 11).missing == (7, 8)  # the READOUT_SAME of 11: lost on the cell
        r.child(7, _record(12, (ReadoutSample(8, 310, 410, 0),), (7,), ref_step=step), 11_500, seq=302)
        twelve = _frame(r, 12)
        assert _samples(twelve) == ({7: (100, 200), 8: (310, 410)} if paid else {8: (310, 410)}), (step, twelve)
        assert (7 in twelve.unchanged) != paid and c["readout_ref_step"] == int(paid)


def test_a_step_back_holds_only_for_the_elements_of_the_record_it_names() -> None:
    """Element 11 came through child 6 until frame 10, 6's record of frame 11 was lost, and
    from frame 12 it comes through child 7 (re-routed), whose record names a reference that
    did not hold 11 (7 sent a READOUT_SAME of it for frame 11). Frame 11 of 11 may have held a new sample, gone with 6's record: the
    sample kept from 6 is no reference for 7's *unchanged* of it."""
    r, _ = _bridge(5)
    r.child(6, _record(10, (ReadoutSample(11, 500, 600, 0),)), 0, seq=40)
    r.child(7, _record(10, (ReadoutSample(7, 100, 200, 0),)), 0, seq=300)
    _frame(r, 10, ReadoutSample(5, 1, 2, 0))
    assert r.child_same(7, ReadoutSame(1, 300 & 0x7F), 10_500)
    assert _frame(r, 11).missing == (11,)  # 6's record lost
    r.child(7, _record(12, (), (7, 11), ref_step=2), 11_500, seq=302)
    twelve = _frame(r, 12)
    assert 11 in twelve.unchanged and 11 not in _samples(twelve), twelve


def _link_send(link: LinkLayer, record: Readout, seq: int, tick: int, ack: bool = True) -> tuple[int, Readout | None]:
    """Queue ``record`` and run the link until it went (acknowledged if asked and ``ack``):
    (tick, the READOUT put on the cell, or None for a READOUT_SAME)."""
    link.enqueue_urgent(own(record, 5, seq), tick, until=10**12, of=(1, 100, record.index), record=record)
    for _ in range(200):
        out, _used = link.advance(tick, PARENT, 0, 1)
        if out is not None:
            f = decode(out[0])
            if f.flags & Flags.ACK_REQUEST and ack:
                assert link.acked(5, seq, PARENT, tick)
            return tick, f.payload if f.type is FrameType.READOUT else None  # type: ignore[return-value]
        t = link.next_tick
        assert t is not None
        tick = max(tick + 1, t)
    raise AssertionError("not sent")


def test_a_whole_record_after_readout_sames_names_the_record_they_referred_to() -> None:
    """The step is said only when it holds: everything sent to the parent since the record
    it names, which the parent acknowledged, was a READOUT_SAME."""
    link = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    changed = (ReadoutSample(8, 300, 400, 0),)
    tick, first = _link_send(link, _record(100, changed, (5,)), 40, 0)
    assert first is not None and first.ref_step == 0  # (no reference yet)
    tick, same = _link_send(link, _record(101, (), (5, 8)), 41, tick + 10**6)
    assert same is None  # a READOUT_SAME
    tick, whole = _link_send(link, _record(103, changed, (5,)), 43, tick + 10**6, ack=False)
    assert whole is not None and whole.ref_step == 3 and link.counters["urgent_ref_step"] == 1
    # its acknowledgement lost: no reference now (the parent may hold 103 or 100)
    del link.outstanding[(5, 43)]
    link._no_ref()
    tick, after = _link_send(link, _record(104, changed, (5,)), 44, tick + 10**6)
    assert after is not None and after.ref_step == 0


def test_a_record_of_samples_only_or_right_after_its_reference_says_no_step() -> None:
    """A periodic skin's records (every element a sample) keep their size, as does a record
    right after its reference: the step would tell the parent nothing it does not know."""
    for k, record in ((101, _record(101, (ReadoutSample(5, 1, 2, 0), ReadoutSample(8, 300, 400, 0)))),
                      (101, _record(101, (ReadoutSample(8, 310, 410, 0),), (5,))),
                      (105, _record(105, (ReadoutSample(5, 1, 2, 0), ReadoutSample(8, 300, 400, 0))))):
        link = LinkLayer(5, (1,), Transceiver(random.Random(0)))
        tick, _ = _link_send(link, _record(100, (ReadoutSample(8, 300, 400, 0),), (5,)), 40, 0)
        tick, sent = _link_send(link, record, 41, tick + 10**6)
        assert sent is not None and sent.ref_step == 0, (k, sent)


def test_a_gateways_own_element_is_a_fresh_sample_every_serial_refresh_frames_after_a_rate_change() -> None:
    """A gateway's own element goes straight onto its line, so it carries no refresh on the
    cells; its line's refresh wrote the sample its readout kept, and only while that sample
    was the reference of the frame's time root and rate. After a rate change (the reporter
    keeps its reference: the first frames at the new rate are *unchanged*) nothing was kept
    at the new rate, and the gateway's own element stayed unknown to the host until its
    heartbeat (here a minute; 2 s of 200 Hz frames without one sample). It samples afresh
    at its line's refresh phase instead, as every other bridge does at its cells' one."""
    vm = VirtualMesh(meshgen.grid(2, 2, gateways=(1,)), seed=3, readout=True,
                     settings=Settings(reporting=ReportingMode(40, 60_000)))
    vm.host_write(1, Frame(0, ADDR_BROADCAST, 0, 500, Command(1, Op.SET_RATE, 200)), at=2.0)
    vm.run(3.0)
    every = vm.nodes[1].config.serial_refresh
    records = [f.payload for f in vm.frames[1] if isinstance(f.payload, Readout)]
    fast = sorted((r.index, r) for r in records if r.rate == 200)
    assert len(fast) > 150
    own = [k for k, r in fast if 1 in _samples(r)]
    assert own and own[0] - fast[0][0] <= every, (own[:3], fast[0][0])
    assert all(b - a <= every for a, b in zip(own, own[1:])), own


def test_a_bridge_back_on_the_schedule_expands_its_own_element_only_from_a_sample_taken_since() -> None:
    """A bridge off mesh time (cut off for 5 s) sends its samples in DATA frames: its
    reporter's reference is then one of them, and its first frames back on the schedule are
    *unchanged* from it. Its readout still kept the last sample it had put in a record, and
    after a failed record expanded its own element to that older reading (pressed while off
    the schedule: read as released). Its own sample is a reference only through frames
    handed to the readout one after another, as a child's element is through the child's."""
    r, c = _bridge(5)
    _frame(r, 10, ReadoutSample(5, 100, 200, 0))
    _frame(r, 11)
    r.sent(False)  # a failed record: the next one expands its unchanged elements
    assert _samples(_frame(r, 12)) == {5: (100, 200)}  # (frames 10-12 in a row: the reference)
    _frame(r, 13)
    r.sent(False)  # frames 14-600 off the schedule (DATA frames), and a record failed
    back = _frame(r, 601)
    assert 5 not in _samples(back) and 5 in back.unchanged, back
    assert c["readout_expanded"] == 1


def test_a_gateway_refreshes_a_frame_built_after_a_later_frames_record_came() -> None:
    """A gateway (or relay) builds a frame's record once every child's record of it is in,
    and a leaf's record of the next frame may come before a relay's of this one (retried, or
    held up). The sample kept was then the reference through a later frame than the one
    written, and was taken for no reference of it: neither refreshed nor sent for an element
    owed, which the host then waited for until its next sample (under heavy loss a tenth of
    the element-frames). It is the reference of every frame from its own to the last one it
    is kept through; a sample of a later frame is not."""
    k = 20 + stagger(7, 10)  # a frame at 7's phase
    for later, written in (((), (100, 200)), ((ReadoutSample(7, 300, 400, 0),), None)):
        gw, _ = _bridge(1, refresh=10)
        gw.child(7, _record(k - 2, (ReadoutSample(7, 100, 200, 0),)), 0, seq=300)
        for j in range(k - 2, k):
            _frame(gw, j, ReadoutSample(1, 1, 2, 0))
            gw.child(7, _record(j + 1, (), (7,)), 1000 * j + 500, seq=300 + j - k + 3)
        # frame k + 1's record comes before frame k's record is built: 7 unchanged, or sampled
        gw.child(7, _record(k + 1, later, () if later else (7,)), 1000 * k - 200, seq=304)
        out = _frame(gw, k, ReadoutSample(1, 1, 2, 0))
        assert _samples(out).get(7) == written, out
