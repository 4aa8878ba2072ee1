"""READOUT_SAME on the readout schedule: a record in which nothing changed goes as three
payload bytes without an acknowledgement, and what is lost or cannot be rebuilt comes out
*missing*, never *unchanged* (docs/time.md, "Nothing changed: READOUT_SAME").

Sans-I/O (the link layer alone, a relay's :class:`FrameReadout` alone), then a whole
event-based mesh against the emulator's ground truth with loss and a leaf killed."""

from __future__ import annotations

import random
from collections import Counter
from collections.abc import Iterator

import pytest
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.linklayer import LinkLayer
from cellbridge.emulator.firmware.readout import FrameReadout, ReadoutConfig
from cellbridge.emulator.firmware.reporting import ReportingMode
from cellbridge.emulator.firmware.transceiver import Transceiver
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.mesh.virtual import VirtualMesh
from cellbridge.protocol import Flags, FrameType, Mode, Readout, ReadoutSame, ReadoutSample, decode, own

from support.readout_truth import Truth, check_known, log_readout_states, records

PARENT = 9


@pytest.fixture
def truth(monkeypatch: pytest.MonkeyPatch) -> Iterator[Truth]:
    """(bridge, index) -> (c1, c2, sent) of every state a bridge handed its readout."""
    yield log_readout_states(monkeypatch)


def _unchanged(index: int, ids: tuple[int, ...] = (5,)) -> Readout:
    return Readout(index, 100, Mode.COUNTER, 1, (), ids, (), 2840, 0, 1, 1)


def _run(link: LinkLayer, tick: int, until: int) -> tuple[int, list[bytes]]:
    """Drive ``link`` by its own ``next_tick`` up to ``until``: (tick, transmissions started)."""
    sent: list[bytes] = []
    for _ in range(200):
        out, _used = link.advance(tick, PARENT, 0, 1)
        if out is not None:
            sent.append(out[0])
        t = link.next_tick
        if t is None or t > until:
            break
        tick = max(tick + 1, t)
    return tick, sent


def _send(link: LinkLayer, record: Readout, seq: int, tick: int, ack: bool = True) -> tuple[int, bytes]:
    """Queue ``record`` (frame seq ``seq``) and run the link until it went; acknowledge it
    when asked and it asked for it: (tick, the frame put on the cell)."""
    link.enqueue_urgent(own(record, 5, seq), tick, until=10**12, of=(1, 100, record.index), record=record)
    tick, sent = _run(link, tick, tick + 60_000)
    assert len(sent) == 1
    if decode(sent[0]).flags & Flags.ACK_REQUEST:
        if ack:
            assert link.acked(5, seq, PARENT, tick)
        else:  # its acknowledgement lost: given up (its retries are not what is looked at here)
            del link.outstanding[(5, seq)]
    return tick, sent[0]


def test_an_all_unchanged_record_goes_as_a_readout_same_only_once_the_parent_acknowledged_the_record_it_repeats() -> None:
    link = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    tick, first = _send(link, _unchanged(100), 40, 0, ack=False)  # whole, and its acknowledgement lost
    assert decode(first).type is FrameType.READOUT
    tick, second = _send(link, _unchanged(101), 41, tick + 10**6)  # nothing to refer to yet: whole
    assert decode(second).type is FrameType.READOUT and decode(second).flags & Flags.ACK_REQUEST
    tick, third = _send(link, _unchanged(104), 42, tick + 10**6)
    f = decode(third)
    assert f.type is FrameType.READOUT_SAME and f.payload == ReadoutSame(3, 41) and len(third) == 19
    assert not f.flags & Flags.ACK_REQUEST and not link.outstanding  # never retried
    # a record that says more than its reference (a sample, a missing element, another
    # element set, span or root) goes whole, and leaves no reference until acknowledged
    for other in (Readout(105, 100, Mode.COUNTER, 1, (ReadoutSample(5, 1, 2, 0),), (), (), 2840, 0, 1, 1),
                  Readout(106, 100, Mode.COUNTER, 1, (), (5,), (8,), 2840, 0, 1, 1), _unchanged(107, (5, 8)),
                  Readout(108, 100, Mode.COUNTER, 1, (), (5,), (), 9999, 0, 1, 1),
                  Readout(109, 100, Mode.COUNTER, 1, (), (5,), (), 2840, 0, 1, 2)):
        tick, data = _send(link, other, 50 + other.index % 100, tick + 10**6, ack=False)
        assert decode(data).type is FrameType.READOUT
    tick, data = _send(link, _unchanged(110), 60, tick + 10**6)  # (whole: the last one was not acknowledged)
    assert decode(data).type is FrameType.READOUT
    # at most 127 frames after its reference
    tick, data = _send(link, _unchanged(237), 61, tick + 10**6)
    assert decode(data).payload == ReadoutSame(127, 60)
    tick, data = _send(link, _unchanged(238), 62, tick + 10**6)
    assert decode(data).type is FrameType.READOUT
    assert link.counters["urgent_same"] == 2


def test_an_acknowledgement_of_an_older_record_that_comes_after_a_newer_one_went_is_no_reference() -> None:
    """The reference is the newest whole record sent to the parent: an older one whose
    acknowledgement comes after a newer one was sent (its retry got through late) is a
    record the parent has replaced since (it keeps each child's last)."""
    link = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    link.enqueue_urgent(own(_unchanged(100, (5, 8)), 5, 40), 0, until=10**12, of=None, record=_unchanged(100, (5, 8)))
    link.enqueue_urgent(own(_unchanged(101), 5, 41), 0, until=10**12, of=None, record=_unchanged(101))
    tick, sent = _run(link, 0, 60_000)
    assert len(sent) == 2 and set(link.outstanding) == {(5, 40), (5, 41)}  # (not frame-ordered here: of=None)
    assert link.acked(5, 41, PARENT, tick) and link.acked(5, 40, PARENT, tick)  # 40's comes last
    tick, data = _send(link, _unchanged(102), 42, tick + 10**6)
    assert decode(data).payload == ReadoutSame(1, 41)  # the newest one, not the last acknowledged


def _relay() -> tuple[FrameReadout, Counter[str]]:
    c: Counter[str] = Counter()
    return FrameReadout(5, ReadoutConfig(depths=4, window=1000), c), c


def _frame(r: FrameReadout, k: int, tick: int, state: object = "u") -> Readout:
    r.own(k, 100, Mode.COUNTER, 1, state, tick, 5000, 1)  # type: ignore[arg-type]  # a State
    out = r.take(tick)
    assert [x.index for x in out] == [k]
    return out[0]


def test_a_lost_or_unmatched_readout_same_leaves_the_childs_elements_missing_never_unchanged() -> None:
    r, c = _relay()
    ref = Readout(10, 100, Mode.COUNTER, 1, (ReadoutSample(7, 100, 200, 0),), (9,), (), 2840, 0, 1, 1)
    r.child(7, ref, 0, seq=300)
    first = _frame(r, 10, 1000, ReadoutSample(5, 1, 2, 0))
    assert {s.bridge for s in first.samples} == {5, 7} and first.unchanged == (9,)
    # frame 11: child 7's READOUT_SAME was lost on the cell: silence at the slot
    eleven = _frame(r, 11, 2000)
    assert eleven.missing == (7, 9) and eleven.unchanged == (5,)
    # frame 12: one that refers to another record (seq 301, not 300) is not rebuilt
    assert not r.child_same(7, ReadoutSame(2, 301 & 0x7F), 2500)
    twelve = _frame(r, 12, 3000)
    assert twelve.missing == (7, 9) and c["readout_same_unknown"] == 1
    # frame 13: a matching one is the child's record of 13, every element unchanged; the
    # elements this relay listed missing go as the samples it keeps of them (the host does
    # not take an unchanged after a frame it did not know)
    assert r.child_same(7, ReadoutSame(3, 300 & 0x7F), 3500)
    thirteen = _frame(r, 13, 4000)
    assert [(s.bridge, s.c1, s.c2) for s in thirteen.samples] == [(7, 100, 200)]
    assert thirteen.unchanged == (5, 9) and thirteen.missing == ()  # (9: no sample of it kept here)
    # frame 14: the debt is paid, unchanged again
    assert r.child_same(7, ReadoutSame(4, 300 & 0x7F), 4500)
    fourteen = _frame(r, 14, 5000)
    assert fourteen.unchanged == (5, 7, 9) and not fourteen.samples
    assert c["readout_same"] == 2


def test_a_bridge_that_restarted_keeps_no_record_to_rebuild_from() -> None:
    r, c = _relay()  # (a parent that restarted: it holds none of its children's records)
    assert not r.child_same(7, ReadoutSame(1, 44), 0)
    out = _frame(r, 10, 1000)
    assert out.unchanged == (5,) and 7 not in out.unchanged
    assert c["readout_same_unknown"] == 1


def test_an_event_based_skin_sends_readout_sames_and_every_element_frame_it_knows_is_right(truth: Truth) -> None:
    """An idle event-based 4x4 with 1 % loss per hop and a leaf killed mid-run: most records
    go as READOUT_SAME, and the gateway's records say of each element-frame what its bridge
    sampled: a sample is the reading of the frame or of the last sample sent (an expansion),
    an unchanged element after a frame the host knew lies within the threshold of the host's
    reading, and the dead leaf is never unchanged after its death."""
    mesh = meshgen.grid(4, 4, loss=0.01, gateways=(1,))
    vm = VirtualMesh(mesh, seed=11, readout=True, settings=Settings(reporting=ReportingMode(40, 1000)))
    vm.kill(16, at=4.0)  # a leaf in the far corner
    vm.run(6.0)
    same = sum(fw.link.counters.get("urgent_same", 0) for fw in vm.nodes.values())
    whole = sum(fw.counters.get("readout_records", 0) for b, fw in vm.nodes.items() if b != 1)
    assert same > 0.5 * whole, (same, whole)
    got = records(vm)
    assert all(state == "m" for (b, k), (state, _) in got.items() if b == 16 and k > 405)  # dead: never unchanged
    unchanged = check_known(got, truth)
    assert unchanged > 3000


def _send_to(link: LinkLayer, parent: int, record: Readout, seq: int, tick: int,
             neighbours: tuple[int, ...] = ()) -> tuple[int, bytes]:
    """``record`` (frame seq ``seq``) sent to ``parent`` and acknowledged if it asked: (tick, frame)."""
    link.enqueue_urgent(own(record, 5, seq), tick, until=10**12, of=(1, 100, record.index), record=record)
    sent: list[bytes] = []
    for _ in range(200):
        out, _used = link.advance(tick, parent, 0, 1, neighbours)
        if out is not None:
            sent.append(out[0])
            break
        t = link.next_tick
        if t is None:
            break
        tick = max(tick + 1, t)
    assert len(sent) == 1
    if decode(sent[0]).flags & Flags.ACK_REQUEST:
        assert link.acked(5, seq, parent, tick)
    return tick, sent[0]


def test_a_record_sent_to_another_parent_ends_the_reference_the_old_parent_holds() -> None:
    """A child that moved to another parent and back must not refer to the record its old
    parent kept: its records meanwhile (samples among them) went elsewhere, and the old
    parent, reading the READOUT_SAME as "nothing but READOUT_SAMEs since", kept its stale
    sample as the element's reference and sent it as the element's reading when it owed it."""
    link = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    tick, data = _send_to(link, PARENT, _unchanged(100), 40, 0)
    assert decode(data).type is FrameType.READOUT
    sampled = Readout(101, 100, Mode.COUNTER, 1, (ReadoutSample(5, 7, 8, 0),), (), (), 2840, 0, 1, 1)
    tick, data = _send_to(link, 8, sampled, 41, tick + 10**6)  # (the route changed: parent 8 now)
    assert decode(data).type is FrameType.READOUT
    tick, data = _send_to(link, PARENT, _unchanged(102), 42, tick + 10**6)  # back to the old parent
    assert decode(data).type is FrameType.READOUT, "a READOUT_SAME to a parent that missed a record"
    tick, data = _send_to(link, PARENT, _unchanged(103), 43, tick + 10**6)
    assert decode(data).payload == ReadoutSame(1, 42)  # (the new reference, once acknowledged)



def test_a_late_acknowledgement_from_the_old_parent_is_no_reference_after_a_record_went_to_another() -> None:
    """The old parent's acknowledgement of a whole record coming after a newer whole record
    went to the new parent (a route change while it was on its way) makes no reference:
    the old parent missed the newer record."""
    link = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    link.enqueue_urgent(own(_unchanged(100), 5, 40), 0, until=10**12, of=None, record=_unchanged(100))
    out, _used = link.advance(0, PARENT, 0, 1)
    tick = 0
    while out is None:
        tick = max(tick + 1, link.next_tick or tick + 1)
        out, _used = link.advance(tick, PARENT, 0, 1)
    sampled = Readout(101, 100, Mode.COUNTER, 1, (ReadoutSample(5, 7, 8, 0),), (), (), 2840, 0, 1, 1)
    tick, data = _send_to(link, 8, sampled, 41, tick, (PARENT, 8))  # to the new parent 8, acknowledged
    assert link.acked(5, 40, PARENT, tick)  # the old parent's acknowledgement, late
    tick, data = _send_to(link, PARENT, _unchanged(102), 42, tick + 10**6)  # back to the old parent
    assert decode(data).type is FrameType.READOUT, "a READOUT_SAME to a parent that missed a record"


def test_a_sample_that_went_nowhere_for_want_of_a_route_is_no_reference() -> None:
    """A bridge without a route drops its frame's state (``readout_no_route``). A change
    dropped so was a sample its reporter counted as sent: the frames after it were
    *unchanged* from a reading no one got, and went as READOUT_SAMEs to the parent back,
    which kept its older sample as the reference through them and sent that stale reading
    as the element's sample when it owed it. The next sample after one lost so is sent."""
    vm = VirtualMesh(meshgen.grid(2, 2, gateways=(1,)), seed=3, readout=True,
                     settings=Settings(reporting=ReportingMode(40, 1000)))
    vm.run(2.0)
    fw = vm.nodes[4]
    rep = fw.sampler.reporter
    last = rep._last
    assert last is not None and fw.router.has_route
    moved = [last._replace(index=last.index + i, cycle=last.cycle + i * 500_000, c1=last.c1 + 500)
             for i in (1, 2, 3)]
    parent, fw.router.parent = fw.router.parent, None  # the route lost for two frames
    for s in moved[:2]:
        assert rep.wants(s)  # (a change, and the sample after it)
        fw._readout_sample(s, True, s.cycle)
    fw.router.parent = parent
    assert fw.counters["readout_no_route"] >= 2
    assert rep.wants(moved[2]), "unchanged from a sample that went nowhere"


def test_an_older_whole_record_coming_late_does_not_replace_the_newer_one_a_readout_same_refers_to() -> None:
    """A whole record's last retry comes after the child's next whole record (its earlier
    attempts got through, their acknowledgements lost; the next record went once it was
    past its first retry). The child refers to the newer one, acknowledged: kept in its
    place, the older record made every READOUT_SAME after it unmatched, the child's
    elements missing for up to 127 frames."""
    r, c = _relay()
    old = Readout(10, 100, Mode.COUNTER, 1, (ReadoutSample(7, 100, 200, 0),), (), (), 2840, 0, 1, 1)
    new = Readout(11, 100, Mode.COUNTER, 1, (), (7,), (), 2840, 0, 1, 1)
    r.child(7, old, 0, seq=300)
    r.child(7, new, 100, seq=301)
    r.child(7, old, 200, seq=300)  # (the retry, late)
    assert r.child_same(7, ReadoutSame(1, 301 & 0x7F), 300), "the newer record's READOUT_SAME unmatched"
    assert c["readout_same_unknown"] == 0


@pytest.mark.parametrize("readout", [True, False])
def test_a_readout_same_the_bridge_cannot_read_as_its_childs_is_counted_and_dropped_not_relayed(readout: bool) -> None:
    """A READOUT_SAME is a bridge-to-parent frame: one fragmented, bundled, or sent to a
    bridge not on the readout schedule was relayed up as a frame of its origin's, marking
    its (origin, seq) seen at every relay (a real frame of that number then a duplicate)
    and reaching the host, which has no use for it. It is counted (``rx_readout_same``)
    and dropped."""
    from cellbridge.protocol import Bundle, Frame, Raw, encode, reframe
    from cellbridge.protocol.messages import pack_payload

    vm = VirtualMesh(meshgen.grid(2, 2, gateways=(1,)), seed=3, readout=readout,
                     settings=Settings(reporting=ReportingMode(40, 1000)))
    vm.run(1.0)
    fw = vm.nodes[2]
    tick = vm.tick
    same = Frame(4, 2, 4, 77, ReadoutSame(1, 3))
    frames = [reframe(Raw(int(FrameType.READOUT_SAME), 0, 4, 76, 0, 0, pack_payload(ReadoutSame(1, 3))), 4, 2,
                      int(Flags.FRAGMENT)),  # (a fragment's header or not: the flag is what the firmware reads)
              encode(Frame(4, 2, 4, 78, Bundle((Frame(4, 2, 4, 79, ReadoutSame(1, 3)),))))]
    if not readout:
        frames.append(encode(same))
    before = fw.counters["forwarded"]
    for data in frames:
        fw.receive(data, tick, fw.config.cells[0])
    assert fw.counters["forwarded"] == before
    assert fw.counters["rx_readout_same"] == len(frames)


def test_a_leaf_moved_between_its_parents_while_pressed_is_never_unchanged_from_a_reading_it_left(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A corner leaf's cell to its parent is cut every 0.3 s (the one cut before restored):
    it moves between its two parents and back, a while without a route each time, while
    presses come and go on it. A release sampled without a route went nowhere, and the host,
    its parent sending the pressed sample it kept when it owed the element, then read the
    leaf as pressed, *unchanged*, for as long as it stayed released."""
    from cellbridge.emulator.world.world import Contact, World

    log = log_readout_states(monkeypatch)  # (bridge, index) -> (c1, c2, sent)
    mesh = meshgen.grid(4, 4, loss=0.01, gateways=(1,))
    presses = [Contact(2.6 + 0.45 * i, 0.12, 0.12, 0.12, 2.0 + i % 3, 0.03) for i in range(12)]
    vm = VirtualMesh(mesh, seed=3, readout=True, settings=Settings(reporting=ReportingMode(40, 1000)),
                     world=World(mesh, presses))
    cut: list[int] = []

    def move() -> None:
        fw = vm.nodes[16]
        if fw.router.parent is None:
            return
        if cut:
            vm.medium.restore_cell(cut.pop())
        cell = next(iter(set(mesh.bridge(16).cells) & set(mesh.bridge(fw.router.parent).cells)))
        vm.medium.cut_cell(cell)
        cut.append(cell)

    for i in range(20):
        vm.at(2.5 + 0.3 * i, move)
    vm.run(8.5)
    unchanged = check_known(records(vm), log)
    assert unchanged > 3000 and vm.nodes[16].counters["readout_no_route"] > 0


def test_a_record_given_up_unsent_ends_the_reference_the_records_queued_behind_it_would_use() -> None:
    """A whole record (a sample in it) that expired in the queue without a parent was never
    sent, so the reference stayed: the record queued behind it, built before the loss was
    known (unchanged from that sample), went as a READOUT_SAME over it, and the parent took
    its older sample as the reference through the lost one."""
    link = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    tick, _data = _send(link, _unchanged(100), 40, 0)  # the reference, acknowledged
    sampled = Readout(101, 100, Mode.COUNTER, 1, (ReadoutSample(5, 7, 8, 0),), (), (), 2840, 0, 1, 1)
    link.enqueue_urgent(own(sampled, 5, 41), tick, until=10**12, of=(1, 100, 101), record=sampled)
    later = tick + 500_000
    link.enqueue_urgent(own(_unchanged(102), 5, 42), later, until=10**12, of=(1, 100, 102), record=_unchanged(102))
    link.advance(tick + link.urgent_ttl + 1, None, 0, 1)  # no parent meanwhile: the first expires
    assert link.counters["urgent_expired"] == 1 and len(link.urgent) == 1
    _tick, sent = _run(link, tick + link.urgent_ttl + 2, tick + link.urgent_ttl + 60_000)
    assert len(sent) == 1 and decode(sent[0]).type is FrameType.READOUT, "a READOUT_SAME over a lost sample"


def _from_4(message: object, seq: int) -> bytes:
    """``message`` as bridge 4's frame to bridge 2, on the wire."""
    from cellbridge.protocol import Frame, encode

    return encode(Frame(4, 2, 4, seq, message))  # type: ignore[arg-type]


def test_a_whole_record_acknowledged_but_unreadable_leaves_no_older_copy_to_rebuild_from() -> None:
    """The acknowledgement goes before the payload is read: a child's whole record that the
    parent acknowledged but could not read (``rx_bad_readout``) is the child's reference
    from then on, and the parent's older copy (its seq's low bits the same, 128 on) rebuilt
    the child's READOUT_SAME from the wrong record: another element set, another frame."""
    from cellbridge.protocol import Raw, reframe

    vm = VirtualMesh(meshgen.grid(2, 2, gateways=(1,)), seed=3, readout=True,
                     settings=Settings(reporting=ReportingMode(40, 1000)))
    vm.run(1.0)
    fw = vm.nodes[2]
    tick = vm.tick
    fw.receive(_from_4(Readout(10, 100, Mode.COUNTER, 1, (), (4, 8), (), 2840, 0, 1, 1), 300), tick,
               fw.config.cells[0])
    bad = reframe(Raw(int(FrameType.READOUT), 0, 4, 300 + 128, 0, 0, b"\x93\x01\x02\x03"), 4, 2,
                  int(Flags.ACK_REQUEST))
    fw.receive(bad, tick + 1000, fw.config.cells[0])
    assert fw.counters["rx_bad_readout"] == 1
    same = fw.counters["readout_same"]
    fw.receive(_from_4(ReadoutSame(1, 300 & 0x7F), 429), tick + 2000, fw.config.cells[0])
    assert fw.counters["readout_same"] == same, "rebuilt from a record the child does not refer to"
