"""The host's receive path: two gateways, loss on one, lag on the other: every datagram once."""

from __future__ import annotations

import random
from typing import Any

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
    Readout,
    ReadoutSample,
    Reassembler,
    Sample,
    fragment,
)


def _data(d: int) -> Data:
    return Data(Mode.COUNTER, tuple(Sample(0, 10**6 * d + i, 19000 + i, 15000, 0) for i in range(30)))


def _readout(d: int) -> Readout:
    """Skin frame ``d`` of a gateway with 30 elements: a record larger than one fragment."""
    return Readout(4000 + d, 100, Mode.COUNTER, 1, tuple(ReadoutSample(b, 19000 + d, 15000) for b in range(1, 25)),
                   (25, 26, 27), (28, 29, 30), 3000)


def _key(frame: Frame) -> int:
    p = frame.payload
    return p.index if isinstance(p, Readout) else p.samples[0].cycle  # type: ignore[union-attr]  # whole DATA frames here


def _traffic(n: int, start_seq: int, payload=_data) -> tuple[list[Frame], list[Frame]]:
    """``n`` datagrams of one bridge, fragmented (seqs wrap when start_seq is high), and their fragments."""
    sent, wire, seq = [], [], start_seq
    for d in range(n):
        frame = Frame(9, 0, 9, seq, payload(d))
        parts = fragment(frame, tag=d, max_frame=100)  # 3-5 fragments each, as version 2 cut them at 128
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
    assert sorted(got, key=_key) == sent

    # The same traffic through the filter first, then the reassembler: datagrams lost.
    dedupe, reassembler, old = DuplicateFilter(), Reassembler(), []
    for k, frame in enumerate(_two_gateways(wire, 0.1, lag, seed=lag)):
        if not dedupe.is_duplicate(frame.origin, frame.seq):
            whole = reassembler.receive(frame, k * 0.0005)
            old += [whole] if whole is not None else []
    assert len(old) < len(sent)


@pytest.mark.parametrize("lag", [1, 50, 255])
@pytest.mark.parametrize("start_seq", [1000, 65000])
def test_fragmented_readout_records_from_two_gateways_are_each_delivered_once(lag: int, start_seq: int) -> None:
    """A READOUT record larger than a frame, sent fragmented, passes the host like DATA: each
    record once, whole, from whichever copies complete it. With the default 4 open datagrams
    per origin a record that gateway A left incomplete can be given up (``evicted``) before B's
    copies arrive 50 frames later (docs/protocol.md §7a: 1 of these 300 at lag 50, its later
    fragments counted ``no_state``); with room for the lag, every record arrives."""
    sent, wire = _traffic(300, start_seq, _readout)
    assert len(wire) == 4 * len(sent)
    events = _two_gateways(wire, 0.1, lag, seed=lag)
    rx = HostReceiver(reassembler=Reassembler(max_per_origin=16))
    got = [f for k, frame in enumerate(events) for f in rx.receive(frame, k * 0.0005)]
    assert sorted(got, key=_key) == sent
    default = HostReceiver()
    got = [f for k, frame in enumerate(events) for f in default.receive(frame, k * 0.0005)]
    keys = [_key(f) for f in got]
    assert len(keys) == len(set(keys)) and all(f in sent for f in got)  # never twice, never altered
    drops = default.reassembler.drops
    assert len(got) == len(sent) or (drops["evicted"] and drops["no_state"])  # a loss is counted


def test_frames_bundled_on_one_path_and_not_on_the_other_are_delivered_once() -> None:
    frames = [Frame(8, 1, 8, s, Beacon(1, 20, 2)) for s in range(1, 5)]
    hello = Frame(8, 1, 8, 0, Hello(8, "0.1.0", 0.0, 0.0, 0.01, 50_000_000, 3))
    rx = HostReceiver()
    got = rx.receive(hello, 0.0)
    got += rx.receive(Frame(1, 0, 1, 70, Bundle(tuple(frames[:2]))), 0.1)  # gateway A bundles two
    got += [f for frame in frames for f in rx.receive(frame, 0.2)]  # gateway B forwards each alone
    got += rx.receive(Frame(1, 0, 1, 71, Bundle(tuple(frames[2:]))), 0.3)
    assert got == [hello, *frames]
    dedupe: Any = rx.counters()["dedupe"]
    assert dedupe["duplicates"] == 4
