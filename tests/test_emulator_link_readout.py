"""A readout record's hop: its acknowledgement, its retries within its frame's slots, and
the order of records of successive frames at the parent (sans-I/O, the link layer alone)."""

from __future__ import annotations

import random

from cellbridge.emulator.firmware.linklayer import LinkLayer
from cellbridge.emulator.firmware.transceiver import Transceiver
from cellbridge.protocol import Hello, Mode, Readout, ReadoutSample, own

PARENT = 9


def _record(index: int) -> Readout:
    return Readout(index, 250, Mode.COUNTER, 1, (ReadoutSample(5, index, index, 0),), (), ())


def _run(link: LinkLayer, tick: int, until: int) -> tuple[int, list[tuple[int, bytes]]]:
    """Drive ``link`` by its own ``next_tick`` up to ``until``: (tick, transmissions started)."""
    sent: list[tuple[int, bytes]] = []
    for _ in range(200):
        out, _used = link.advance(tick, PARENT, 0, 1)
        if out is not None:
            sent.append((tick, out[0]))
        t = link.next_tick
        if t is None or t > until:
            break
        tick = max(tick + 1, t)
    return tick, sent


def test_a_later_frames_record_waits_until_the_earlier_ones_is_acknowledged() -> None:
    """The parent reads a child's record of frame k + 1 as the loss of its record of k: it
    lists the child's subtree missing in k and sends k on. Sent while k's record still
    waited for its acknowledgement, the record of k + 1 made a retry of k that got through
    come too late, and the subtree unknown in k."""
    link = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    link.enqueue_urgent(own(_record(0), 5, 0), 0, until=10**9, of=(0, 250, 0))
    link.enqueue_urgent(own(_record(1), 5, 1), 0, until=10**9, of=(0, 250, 1))
    tick, sent = _run(link, 0, 60_000)  # well short of the acknowledgement's deadline
    assert len(sent) == 1 and link.outstanding  # k + 1 waits for k's outcome
    (origin, seq), = link.outstanding
    assert link.acked(origin, seq, PARENT, tick)
    _tick, sent = _run(link, tick, tick + 60_000)
    assert len(sent) == 1  # now it goes


def test_a_record_is_retried_while_a_retry_can_still_reach_the_parent_by_its_slot() -> None:
    """No acknowledgement comes: with room before the parent's slot the record goes
    ``urgent_retries`` + 1 times; with the slot too close for a retransmission to end by it,
    it is given up at its first deadline, and the next frame's record goes."""
    far = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    far.enqueue_urgent(own(_record(0), 5, 0), 0, until=10**9, of=(0, 250, 0))
    _tick, sent = _run(far, 0, 10**8)
    assert len(sent) == far.urgent_retries + 1 >= 3
    assert far.urgent_results == [False] and not far.outstanding

    near = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    near.enqueue_urgent(own(_record(0), 5, 0), 0, until=20_000, of=(0, 250, 0))  # 0.4 ms: one record's airtime
    near.enqueue_urgent(own(_record(1), 5, 1), 0, until=10**9, of=(0, 250, 1))
    _tick, sent = _run(near, 0, 10**6)
    first = [data for _, data in sent if data == sent[0][1]]
    assert len(first) == 1  # no retransmission of frame 0: it could not make the parent's slot
    assert near.urgent_results[0] is False and len(sent) >= 2  # given up; frame 1 went


def test_a_frame_queued_behind_a_held_record_does_not_wake_the_bridge_before_the_acknowledgement() -> None:
    """A record of frame k + 1 held behind frame k's record (waiting for its acknowledgement)
    holds the bridge's other frames too; the link still named the end of the last
    transmission, long past, as its next wake for them: the bridge woke at every cycle
    until the acknowledgement's deadline. After relay 6 of a 4x4 at 250 Hz died, bridge 7
    held a record behind each one sent to it for a whole acknowledgement wait, 135 297
    wakes in 5 ms, and the virtual mesh took minutes per simulated second."""
    link = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    link.enqueue_urgent(own(_record(0), 5, 0), 0, until=10**9, of=(0, 250, 0))
    link.enqueue_urgent(own(_record(1), 5, 1), 0, until=10**9, of=(0, 250, 1))
    link.enqueue(own(Hello(5, "t", 0.0, 0.0, 0.04, 50_000_000, 3, 1), 5, 2))
    tick, sent = _run(link, 0, 60_000)
    assert len(sent) == 1 and link._held()  # frame 0's record is on its way, the rest wait
    (u,) = link.outstanding.values()
    assert tick < u.deadline
    wakes = 0
    while tick < u.deadline:
        out, _used = link.advance(tick, PARENT, 0, 1)
        assert out is None
        t = link.next_tick
        assert t is not None and t > tick, (t, tick)  # not a wake that finds nothing to do
        tick, wakes = t, wakes + 1
    assert tick == u.deadline and wakes <= 2  # the record's acknowledgement deadline: its retry goes then


def test_a_record_whose_every_retry_went_unacknowledged_is_a_lost_link_for_the_routing() -> None:
    """A parent that died acknowledges nothing: a record that spent all its retries is told
    to the routing as a failed transmission (as a normal frame's last retry is), so that
    the parent is evicted by its failures and not only by its beacons' timeout. One given
    up for its parent's slot is not: its retries were cut short."""
    far = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    far.enqueue_urgent(own(_record(0), 5, 0), 0, until=10**9, of=(0, 250, 0))
    _run(far, 0, 10**8)
    assert far.results == [(PARENT, far.urgent_retries + 1, False)]

    near = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    near.enqueue_urgent(own(_record(0), 5, 0), 0, until=20_000, of=(0, 250, 0))
    _run(near, 0, 10**6)
    assert near.urgent_results == [False] and near.results == []
