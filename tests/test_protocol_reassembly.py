"""Fragmentation and reassembly: any order, duplicates, conflicts, and bounded state."""

from __future__ import annotations

import collections
import random

import pytest
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
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from support.protocol_wire import sealed


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


@settings(max_examples=150, deadline=None)
@given(
    plan=st.lists(st.tuples(st.integers(1, 40), st.integers(0, 2), st.booleans()), min_size=1, max_size=10),
    max_frame=st.integers(40, 120),
    loss=st.sampled_from([0.0, 0.05, 0.3]),
    seed=st.integers(0, 2**32 - 1),
)
def test_loss_reordering_and_tag_reuse_never_deliver_an_unsent_datagram(plan, max_frame, loss, seed) -> None:
    """One bridge sends datagrams with tags from {0, 1, 2} and sometimes resets (seq and
    tag numbering start again, so (tag, head seq) repeats with other contents). Fragments
    are lost, repeated and reordered: whatever comes out was sent, and no more often."""
    rng = random.Random(seed)
    sent: list[Frame] = []
    arrivals: list[tuple[float, float, Frame]] = []
    seq, t = 0, 0.0
    for n, tag, reset in plan:
        if reset:
            seq = 0
        frame = Frame(9, 0, 9, seq, Data(Mode.COUNTER, tuple(Sample(0, rng.randrange(2**32), rng.randrange(2**16),
                                                                    15800, 0) for _ in range(n))))
        parts = fragment(frame, tag=tag, max_frame=max_frame)
        seq = (seq + len(parts)) & 0xFFFF
        sent.append(frame)
        for p in parts:
            # a whole frame passes straight through: repeating it is the DuplicateFilter's business
            copies = 0 if rng.random() < loss else 1 + (rng.random() < 0.2 and len(parts) > 1)
            arrivals += [(t + rng.uniform(0.0, 0.4), rng.random(), p) for _ in range(copies)]
        t += rng.uniform(0.0, 0.3)
    arrivals.sort(key=lambda a: a[:2])
    r = Reassembler()
    out = [x for x in (r.receive(decode(encode(p)), now) for now, _, p in arrivals) if x is not None]
    sent_count = collections.Counter(repr(f) for f in sent)
    out_count = collections.Counter(repr(f) for f in out)
    assert all(out_count[k] <= sent_count[k] for k in out_count), "delivered a datagram that was not sent"
    assert r.slot_count <= r.max_slots


def test_small_frames_pass_through_untouched() -> None:
    frame = big_frame(1)
    assert fragment(frame, tag=1) == [frame]
    assert Reassembler().receive(frame, 0.0) is frame


def _frag(index: int, data: bytes, total: int = 30, tag: int = 1, origin: int = 4,
          ftype: FrameType = FrameType.DATA, step: int = 10, head_seq: int = 0) -> Frame:
    """Fragment ``index`` of a datagram cut in ``step``-byte slices, numbered from ``head_seq``."""
    return Frame(origin, 0, origin, (head_seq + index) & 0xFFFF, Fragment(ftype, tag, index * step, total, data))


def test_non_first_fragment_without_state_is_dropped() -> None:
    r = Reassembler()
    assert r.receive(_frag(1, b"x" * 10), 0.0) is None
    assert r.drops == {"no_state": 1} and r.slot_count == 0


@pytest.mark.parametrize(
    "second,cause",
    [(_frag(0, b"B" * 10), "conflict"),  # same fragment, other bytes
     (_frag(1, b"A" * 10, total=40), "conflict"),  # another total
     (_frag(1, b"A" * 10, ftype=FrameType.STATUS), "conflict")],  # another type
)
def test_conflicting_fragments_drop_the_datagram(second: Frame, cause: str) -> None:
    r = Reassembler()
    assert r.receive(_frag(0, b"A" * 10), 0.0) is None
    assert r.receive(second, 0.1) is None
    assert r.drops == {cause: 1} and r.slot_count == 0
    # The datagram is gone: its remaining fragments find no state.
    assert r.receive(_frag(2, b"A" * 10), 0.2) is None
    assert r.drops["no_state"] == 1


@pytest.mark.parametrize(
    "stranger",
    [Frame(4, 0, 4, 1, Fragment(FrameType.DATA, 1, 5, 30, b"A" * 10)),  # not at a multiple of the step
     _frag(1, b"A" * 10, head_seq=7),  # not numbered consecutively from the head
     _frag(1, b"A" * 6),  # a short slice that is not the last
     _frag(2, b"A" * 12, total=32)],  # a last slice longer than the step
)
def test_fragments_that_do_not_belong_are_dropped_alone(stranger: Frame) -> None:
    r = Reassembler()
    r.receive(_frag(0, b"A" * 10), 0.0)
    assert r.receive(stranger, 0.0) is None
    assert r.drops == {"mismatch": 1} and r.slot_count == 1  # the datagram is still open


def test_spliced_datagrams_fail_the_checksum() -> None:
    # Two datagrams with one tag and one head seq (a bridge that reset twice):
    # only the datagram checksum tells their fragments apart.
    a = sealed(b"a" * 28)
    b = sealed(b"b" * 28)
    r = Reassembler()
    r.receive(_frag(0, a[:10], total=len(a)), 0.0)
    r.receive(_frag(1, a[10:20], total=len(a)), 0.0)
    assert r.receive(_frag(2, b[20:], total=len(b)), 0.0) is None
    assert r.drops == {"checksum": 1} and r.completed == 0


def test_timeout_frees_the_slot() -> None:
    r = Reassembler(timeout=1.0)
    r.receive(_frag(0, b"A" * 10), 0.0)
    r.receive(_frag(1, b"A" * 10), 0.5)
    assert r.slot_count == 1
    r.expire(1.01)
    assert r.slot_count == 0 and r.drops == {"timeout": 1}


def test_invalid_reassembled_payload_is_counted() -> None:
    r = Reassembler()
    body = sealed(b"\xc1" * 28)
    r.receive(_frag(0, body[:15], step=15), 0.0)
    assert r.receive(_frag(1, body[15:], step=15), 0.0) is None
    assert r.drops == {"payload": 1}


def test_a_new_head_with_the_same_tag_replaces_an_incomplete_datagram() -> None:
    r = Reassembler()
    r.receive(_frag(0, b"A" * 10), 0.0)
    r.receive(_frag(0, b"B" * 10, head_seq=50), 0.1)
    assert r.drops == {"replaced": 1} and r.slot_count == 1
    assert r.receive(_frag(1, b"A" * 10), 0.2) is None  # a fragment of the abandoned one
    assert r.drops["mismatch"] == 1


def test_reset_forgets_an_origin() -> None:
    r = Reassembler()
    r.receive(_frag(0, b"A" * 10, origin=4), 0.0)
    r.receive(_frag(0, b"A" * 10, origin=5), 0.0)
    r.reset(4)
    assert r.slot_count == 1 and r.drops == {"reset": 1}


def test_slot_limits_evict_the_oldest() -> None:
    r = Reassembler(max_per_origin=2, max_slots=3)
    for tag in range(3):
        r.receive(_frag(0, b"A", tag=tag, origin=1, step=1), 0.0)
    assert r.slot_count == 2 and r.drops == {"evicted": 1}
    for origin in (2, 3):
        r.receive(_frag(0, b"A", origin=origin, step=1), 0.0)
    assert r.slot_count == 3 and r.drops == {"evicted": 2}
    # Oldest surviving slot of origin 1 was tag 1: evicted last, its next fragment has no state.
    assert r.receive(_frag(1, b"A", tag=1, origin=1, step=1), 0.0) is None
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
    assert r.completed == 0 and r.drops["checksum"] == 20  # b"A"*30 fails the checksum: counted anyway
    assert r.recent_count <= 5
    r.expire(100.0)
    assert r.recent_count == 0


def test_fragment_rejects_bad_sizes() -> None:
    with pytest.raises(ProtocolError):
        fragment(big_frame(400), tag=1)  # > MAX_DATAGRAM
    with pytest.raises(ProtocolError):
        fragment(big_frame(50), tag=1, max_frame=20)


def test_completions_are_forgotten_after_remember_for_whatever_the_order_of_origins() -> None:
    r = Reassembler(remember_for=10.0)
    body = sealed(b"\x94\x01\x14\x02\xc0")  # a BEACON [1, 20, 2, nil]
    beacon = lambda origin, tag: Frame(origin, 0, origin, 0, Fragment(FrameType.BEACON, tag, 0, len(body), body))
    assert r.receive(beacon(1, 0), 0.0) is not None
    assert r.receive(beacon(2, 0), 1.0) is not None
    assert r.receive(beacon(1, 1), 9.0) is not None  # origin 1 completed last: it is now behind origin 2
    assert r.receive(beacon(1, 0), 10.5) is not None  # 10.5 s after its completion: a new datagram
    assert r.receive(beacon(2, 0), 10.6) is None and r.drops["late_duplicate"] == 1


def test_a_jittery_clock_does_not_age_a_datagram_faster_than_real_time() -> None:
    """Times stamped by two readers and merged step back by a millisecond every other call.

    0.7 s of real time passes between the first and last fragment, well inside the 2 s
    timeout: the datagram completes. (Adding every backward jitter to every age made it
    time out after 0.7 s, and each step back rewrote every stored time.)
    """
    parts = fragment(big_frame(40), tag=1, max_frame=64)
    r = Reassembler(timeout=2.0)
    t, out = 1000.0, None
    for part in parts:
        for k in range(500):
            t += 0.0001
            r.expire(t - (0.001 if k % 2 else 0.0))
        out = r.receive(part, t)
    assert out is not None and out.payload == big_frame(40).payload
    assert r.drops == {} and r.clock_steps == 0


def test_a_clock_drifting_back_in_small_steps_is_a_clock_step() -> None:
    """Jitter is forgiven only up to clock_jitter: a clock that keeps going back still keeps ages."""
    parts = fragment(big_frame(40), tag=1, max_frame=64)
    r = Reassembler(timeout=2.0, clock_jitter=0.25)
    r.receive(parts[0], 1000.0)
    for i in range(1, 11):
        r.expire(1000.0 - 0.1 * i)  # back to 999.0 in steps of 0.1 s
    assert r.clock_steps >= 1 and r.slot_count == 1
    r.expire(999.0 + 2.3)  # timeout + clock_jitter after the last reading: too old whatever happened before
    assert r.slot_count == 0 and r.drops["timeout"] == 1
