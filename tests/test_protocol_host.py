"""The host's receive path: two gateways, loss on one, lag on the other: every datagram once."""

from __future__ import annotations

import random

import pytest

from cellbridge.protocol import (
    Beacon,
    Bundle,
    Data,
    DuplicateFilter,
    Frame,
    Hello,
    HostReceiver,
    Mode,
    Reassembler,
    Sample,
    fragment,
)


def _traffic(n: int, start_seq: int) -> tuple[list[Frame], list[Frame]]:
    """``n`` datagrams of one bridge, fragmented (seqs wrap when start_seq is high), and their fragments."""
    sent, wire, seq = [], [], start_seq
    for d in range(n):
        frame = Frame(9, 0, 9, seq, Data(Mode.COUNTER, tuple(Sample(0, 10**6 * d + i, 19000 + i, 15000, 0)
                                                             for i in range(30))))
        parts = fragment(frame, tag=d, max_frame=100)  # 5 fragments each, as version 2 cut them at 128
        sent.append(frame)
        wire += parts
        seq = (seq + len(parts)) & 0xFFFF
    return sent, wire


def _two_gateways(wire: list[Frame], loss_a: float, lag: int, seed: int) -> list[Frame]:
    """Gateway A loses ``loss_a`` of the frames; gateway B loses none and runs ``lag`` frames late."""
    rng = random.Random(seed)
    events = [(i, 0, f) for i, f in enumerate(wire) if rng.random() >= loss_a]
    events += [(i + lag, 1, f) for i, f in enumerate(wire)]
    events.sort(key=lambda e: (e[0], e[1]))
    return [f for _, _, f in events]


@pytest.mark.parametrize("lag", [1, 50, 255])
@pytest.mark.parametrize("start_seq", [1000, 65000])
def test_a_datagram_whose_head_one_gateway_lost_is_completed_from_the_other(lag: int, start_seq: int) -> None:
    """Filtering fragments before reassembly (the old pipeline) lost a quarter of these
    datagrams: A's later fragments came first, found no open datagram, and were marked
    seen, so B's copies were dropped as duplicates."""
    sent, wire = _traffic(300, start_seq)
    rx = HostReceiver()
    got = [f for k, frame in enumerate(_two_gateways(wire, 0.1, lag, seed=lag)) for f in rx.receive(frame, k * 0.0005)]
    assert sorted(got, key=lambda f: f.payload.samples[0].cycle) == sent

    # The same traffic through the filter first, then the reassembler: datagrams lost.
    dedupe, reassembler, old = DuplicateFilter(), Reassembler(), []
    for k, frame in enumerate(_two_gateways(wire, 0.1, lag, seed=lag)):
        if not dedupe.is_duplicate(frame.origin, frame.seq):
            whole = reassembler.receive(frame, k * 0.0005)
            old += [whole] if whole is not None else []
    assert len(old) < len(sent)


def test_frames_bundled_on_one_path_and_not_on_the_other_are_delivered_once() -> None:
    frames = [Frame(8, 1, 8, s, Beacon(1, 20, 2)) for s in range(1, 5)]
    hello = Frame(8, 1, 8, 0, Hello(8, "0.1.0", 0.0, 0.0, 0.01, 50_000_000, 3))
    rx = HostReceiver()
    got = rx.receive(hello, 0.0)
    got += rx.receive(Frame(1, 0, 1, 70, Bundle(tuple(frames[:2]))), 0.1)  # gateway A bundles two
    got += [f for frame in frames for f in rx.receive(frame, 0.2)]  # gateway B forwards each alone
    got += rx.receive(Frame(1, 0, 1, 71, Bundle(tuple(frames[2:]))), 0.3)
    assert got == [hello, *frames]
    assert rx.counters()["dedupe"]["duplicates"] == 4
