"""Readout records queued behind one another leave as fast as the cell allows: a bridge
that fell behind (its process held up by the host) catches up instead of sending one
record per frame for ever (each then late at its parent and dropped)."""

from __future__ import annotations

import random

from cellbridge.emulator.firmware.linklayer import LinkLayer
from cellbridge.emulator.firmware.transceiver import Transceiver
from cellbridge.protocol import Mode, Readout, ReadoutSample, own


def _record(index: int) -> Readout:
    return Readout(index, 100, Mode.COUNTER, 1, (ReadoutSample(5, index, index, 0),), (), ())


def test_a_backlog_of_records_goes_out_one_after_another_without_waiting_for_another_wake() -> None:
    """The real-time shells send records without a per-hop acknowledgement: after a record
    went, nothing told the bridge to wake for the next one queued, which waited for the
    bridge's next gate (one record per frame: a bridge 4 frames behind stayed 4 frames
    behind). Driven only by the link's own ``next_tick``, as the bridge process is, all
    four records of a backlog go within a few airtimes."""
    link = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    link.urgent_acks = False
    for k in range(4):
        link.enqueue_urgent(own(_record(k), 5, k), 0, rank=0)
    sent: list[int] = []
    tick = 0
    link.advance(tick, 9, 0, 1)  # the bridge's wake at its gate: the first record is handed over
    for _ in range(50):
        t = link.next_tick
        if t is None:
            break
        tick = max(tick, t)
        out, _used = link.advance(tick, 9, 0, 1)
        if out is not None:
            sent.append(tick)
    assert len(sent) == 4, f"{len(sent)} of 4 records went; the rest waited for another wake"
    assert link.next_tick is None  # nothing left: no busy wake
    assert sent[-1] - sent[0] < 50_000  # within a millisecond (four short records at 1 Mbit/s)


def test_records_without_a_parent_do_not_make_the_bridge_spin() -> None:
    link = LinkLayer(5, (1,), Transceiver(random.Random(0)))
    link.urgent_acks = False
    link.enqueue_urgent(own(_record(0), 5, 0), 0)
    link.advance(0, None, 0, 1)
    assert link.next_tick is None  # no parent: the record waits for one, no wake for it
