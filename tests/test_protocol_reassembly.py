"""Fragmentation and reassembly: any order, duplicates, conflicts, and bounded state."""

from __future__ import annotations

import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from cellbridge.protocol import (
    MAX_FRAME,
    Data,
    Fragment,
    Frame,
    FrameType,
    Mode,
    ProtocolError,
    Reassembler,
    Sample,
    decode,
    encode,
    fragment,
)


def big_frame(n: int, seq: int = 100, origin: int = 9) -> Frame:
    return Frame(origin, 0, origin, seq, Data(Mode.COUNTER, tuple(Sample(0, 10**9 + i, 19600 + i, 15800, 0)
                                                                  for i in range(n))))


@settings(max_examples=120)
@given(
    n=st.integers(1, 250),
    max_frame=st.integers(40, MAX_FRAME),
    order=st.randoms(use_true_random=False),
    dup_count=st.integers(0, 10),
)
def test_any_order_with_duplicates_gives_the_datagram_once(n, max_frame, order, dup_count) -> None:
    frame = big_frame(n)
    parts = fragment(frame, tag=7, max_frame=max_frame)
    assume(len(parts) > 1)  # a lone frame passes through; duplicates of it are the DuplicateFilter's job
    assert all(len(encode(p)) <= max_frame for p in parts)
    assert [p.seq for p in parts] == [(frame.seq + i) & 0xFFFF for i in range(len(parts))]
    # The first fragment opens the datagram; everything else (and copies of anything,
    # the first included) comes in any order, before or after completion.
    rest = parts[1:] + [order.choice(parts) for _ in range(dup_count)]
    order.shuffle(rest)
    arrivals = [parts[0], *rest]
    r = Reassembler()
    out = [x for x in (r.receive(decode(encode(p)), now=0.001 * i) for i, p in enumerate(arrivals)) if x]
    assert out == [frame]
    assert r.slot_count == 0 and r.completed == 1
    assert set(r.drops) <= {"duplicate_fragment", "late_duplicate"}
    assert sum(r.drops.values()) == dup_count


def test_small_frames_pass_through_untouched() -> None:
    frame = big_frame(1)
    assert fragment(frame, tag=1) == [frame]
    assert Reassembler().receive(frame, 0.0) is frame


def _frag(offset: int, data: bytes, total: int = 30, tag: int = 1, origin: int = 4,
          ftype: FrameType = FrameType.DATA) -> Frame:
    return Frame(origin, 0, origin, offset, Fragment(ftype, tag, offset, total, data))


def test_non_first_fragment_without_state_is_dropped() -> None:
    r = Reassembler()
    assert r.receive(_frag(10, b"x" * 10), 0.0) is None
    assert r.drops == {"no_state": 1} and r.slot_count == 0


@pytest.mark.parametrize(
    "second,cause",
    [(_frag(0, b"B" * 10), "conflict"),  # same offset, other bytes
     (_frag(5, b"A" * 10), "overlap"),  # partly overlapping slice
     (_frag(10, b"A" * 10, total=40), "conflict"),  # another total
     (_frag(10, b"A" * 10, ftype=FrameType.STATUS), "conflict")],  # another type
)
def test_conflicting_fragments_drop_the_datagram(second: Frame, cause: str) -> None:
    r = Reassembler()
    assert r.receive(_frag(0, b"A" * 10), 0.0) is None
    assert r.receive(second, 0.1) is None
    assert r.drops == {cause: 1} and r.slot_count == 0
    # The datagram is gone: its remaining fragments find no state.
    assert r.receive(_frag(20, b"A" * 10), 0.2) is None
    assert r.drops["no_state"] == 1


def test_overlap_with_following_slice() -> None:
    r = Reassembler()
    r.receive(_frag(0, b"A" * 5), 0.0)
    r.receive(_frag(10, b"A" * 10), 0.0)
    assert r.receive(_frag(5, b"A" * 6), 0.0) is None
    assert r.drops == {"overlap": 1}


def test_timeout_frees_the_slot() -> None:
    r = Reassembler(timeout=1.0)
    r.receive(_frag(0, b"A" * 10), 0.0)
    r.receive(_frag(10, b"A" * 10), 0.5)
    assert r.slot_count == 1
    r.expire(1.01)
    assert r.slot_count == 0 and r.drops == {"timeout": 1}


def test_invalid_reassembled_payload_is_counted() -> None:
    r = Reassembler()
    r.receive(_frag(0, b"\xc1" * 15), 0.0)
    assert r.receive(_frag(15, b"\xc1" * 15), 0.0) is None
    assert r.drops == {"payload": 1}


def test_slot_limits_evict_the_oldest() -> None:
    r = Reassembler(max_per_origin=2, max_slots=3)
    for tag in range(3):
        r.receive(_frag(0, b"A", tag=tag, origin=1), 0.0)
    assert r.slot_count == 2 and r.drops == {"evicted": 1}
    for origin in (2, 3):
        r.receive(_frag(0, b"A", origin=origin), 0.0)
    assert r.slot_count == 3 and r.drops == {"evicted": 2}
    # Oldest surviving slot of origin 1 was tag 1: evicted last, its next fragment has no state.
    assert r.receive(_frag(1, b"A", tag=1, origin=1), 0.0) is None
    assert r.drops["no_state"] == 1


def test_flood_of_first_fragments_keeps_memory_bounded() -> None:
    r = Reassembler(max_per_origin=4, max_slots=64, remember=256)
    data = b"A" * 8
    for i in range(1_000_000):
        origin, tag = i % 97, (i // 97) & 0xFFFF
        r.receive(Frame(origin, 0, origin, i & 0xFFFF, Fragment(FrameType.DATA, tag, 0, 4096, data)), 0.0)
        if i % 100_000 == 0:
            assert r.slot_count <= 64
    assert r.slot_count == 64
    assert max(r._per_origin.values()) <= 4
    assert r.recent_count == 0
    assert r.drops["evicted"] == 1_000_000 - 64


def test_recent_memory_is_bounded_and_ages_out() -> None:
    r = Reassembler(remember=5, remember_for=10.0)
    for tag in range(20):
        r.receive(_frag(0, b"A" * 30, tag=tag), float(tag))
    assert r.completed == 0 and r.drops["payload"] == 20  # b"A"*30 is not msgpack: counted anyway
    assert r.recent_count <= 5
    r.expire(100.0)
    assert r.recent_count == 0


def test_fragment_rejects_bad_sizes() -> None:
    with pytest.raises(ProtocolError):
        fragment(big_frame(400), tag=1)  # > MAX_DATAGRAM
    with pytest.raises(ProtocolError):
        fragment(big_frame(50), tag=1, max_frame=20)
