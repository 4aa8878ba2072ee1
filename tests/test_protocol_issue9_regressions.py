"""Regressions for the protocol half of issue 9: each test failed on the code before the fix."""

from __future__ import annotations

import math
import tracemalloc
from typing import Any

import msgpack
import numpy as np
import pytest
from cellbridge.protocol import (
    VERSION,
    Beacon,
    Bundle,
    Data,
    DuplicateFilter,
    Fragment,
    Frame,
    FrameType,
    Hello,
    LinkAck,
    Mode,
    ProtocolError,
    Reassembler,
    Sample,
    StreamDecoder,
    decode,
    encode,
    encode_stream,
    fragment,
)
from cellbridge.protocol.frame import CRC_LEN, HEADER_LEN
from cellbridge.tactile import transfer
from hypothesis import HealthCheck, given, settings

from support.payloads import payload_as
from support.protocol_strategies import data as data_strategy
from support.protocol_wire import sealed

# -- 1. duplicate filter ------------------------------------------------------------------------

def test_one_stale_frame_does_not_reopen_the_window() -> None:
    f = DuplicateFilter()
    assert not any(f.is_duplicate(1, s) for s in range(1000))
    assert f.is_duplicate(1, 500)  # far behind: stale, dropped
    assert f.is_duplicate(1, 998) and f.is_duplicate(1, 999)
    c = f.counters()
    assert c["stale"] == 1 and c["restarts"] == 0 and c["duplicates"] == 2


def test_two_gateways_with_a_lagging_path_deliver_each_frame_once() -> None:
    f = DuplicateFilter()
    delivered = 0
    for s in range(2000 + 300):
        if s < 2000:
            delivered += not f.is_duplicate(1, s)
        if s >= 300:
            delivered += not f.is_duplicate(1, s - 300)
    assert delivered == 2000
    # the lagging copies are stale until the first path stops at 1999, then duplicates
    assert f.counters()["stale"] == 1744 and f.counters()["duplicates"] == 256
    assert f.counters()["restarts"] == 0


def test_reset_inside_the_window_is_recognised_from_hello() -> None:
    f = DuplicateFilter()
    assert not f.is_duplicate(1, 0, hello=True)
    assert not any(f.is_duplicate(1, s) for s in range(1, 100))
    # The bridge resets and numbers from 0 again, announcing itself first.
    assert not f.is_duplicate(1, 0, hello=True)
    assert not any(f.is_duplicate(1, s) for s in range(1, 100))
    assert f.counters()["restarts"] == 1


def test_explicit_reset_forgets_the_origin() -> None:
    f = DuplicateFilter()
    for s in range(50):
        f.is_duplicate(1, s)
        f.is_duplicate(2, s)
    f.reset(1)
    assert not f.is_duplicate(1, 10)
    assert f.is_duplicate(2, 10)


# -- 2. fragment tag reuse ----------------------------------------------------------------------

def _datagram(seq: int, first_c1: int, n: int = 20, origin: int = 9) -> Frame:
    return Frame(origin, 0, origin, seq, Data(Mode.COUNTER, tuple(Sample(0, 10**6 * i, first_c1 + i, 15800, 0)
                                                                  for i in range(n))))


def test_reused_tag_after_a_reset_is_a_new_datagram() -> None:
    r = Reassembler()
    first, second = _datagram(100, 19000), _datagram(5, 18000)  # the bridge reset: seq and tag restart
    out = [r.receive(p, 0.0) for p in fragment(first, tag=0, max_frame=64)]
    assert out[-1] == first
    out = [r.receive(p, 1.0) for p in fragment(second, tag=0, max_frame=64)]
    assert out[-1] == second
    assert r.completed == 2 and "late_duplicate" not in r.drops


def test_two_boots_reusing_tag_and_head_seq_are_two_datagrams() -> None:
    r = Reassembler()
    boot1, boot2 = _datagram(1, 19000), _datagram(1, 18000)  # same tag, same head seq, other readings
    p1, p2 = fragment(boot1, tag=0, max_frame=64), fragment(boot2, tag=0, max_frame=64)
    assert [r.receive(p, 0.0) for p in p1][-1] == boot1
    assert r.receive(p1[0], 0.5) is None and r.drops["late_duplicate"] == 1  # a copy is still a copy
    assert [r.receive(p, 1.0) for p in p2][-1] == boot2
    assert r.completed == 2


def test_completion_time_not_first_fragment_time_is_remembered() -> None:
    r = Reassembler(timeout=5.0, remember_for=2.0)
    parts = fragment(_datagram(100, 19000), tag=3, max_frame=64)
    r.receive(parts[0], 0.0)
    for p in parts[1:]:
        assert r.receive(p, 3.0) is None or p is parts[-1]
    # 1.5 s after completion (4.5 s after the first fragment) a copy is still recognised.
    assert r.receive(parts[1], 4.5) is None
    assert r.drops["late_duplicate"] == 1


def test_other_origins_cannot_flush_an_origins_completions() -> None:
    r = Reassembler(remember=4)
    parts = fragment(_datagram(100, 19000), tag=3, max_frame=64)
    for p in parts:
        r.receive(p, 0.0)
    for origin in range(20, 40):  # many other origins complete datagrams
        for p in fragment(_datagram(100, 19000, origin=origin), tag=3, max_frame=64):
            r.receive(p, 0.0)
    assert r.receive(parts[0], 0.1) is None
    assert r.drops["late_duplicate"] == 1


# -- 3. splicing --------------------------------------------------------------------------------

def test_fragments_of_two_datagrams_with_one_tag_are_not_spliced() -> None:
    a, b = _datagram(100, 19000), _datagram(200, 17000)
    pa, pb = fragment(a, tag=7, max_frame=64), fragment(b, tag=7, max_frame=64)
    assert len(pa) == len(pb) and payload_as(pa[0], Fragment).total == payload_as(pb[0], Fragment).total
    r = Reassembler()
    out = [r.receive(p, 0.0) for p in [pa[0], *pb[1:]]]
    assert out == [None] * len(out)
    assert r.completed == 0 and r.drops["mismatch"] == len(pb) - 1


# -- 4. canonical msgpack -----------------------------------------------------------------------

LINK_ACK_HEAD = bytes.fromhex("02000700010005000100370000 00".replace(" ", ""))


@pytest.mark.parametrize("payload", [
    "92 05 cd 01 2c",  # the canonical form, accepted
])
def test_canonical_link_ack_is_accepted(payload: str) -> None:
    assert payload_as(decode(sealed(LINK_ACK_HEAD + bytes.fromhex(payload))), LinkAck).seq == 300


@pytest.mark.parametrize("payload", [
    "92 cc 05 cd 01 2c",  # uint8 for a fixint
    "92 05 ce 00 00 01 2c",  # uint32-widened
    "92 05 d3 00 00 00 00 00 00 01 2c",  # int64-widened
    "92 d0 05 cd 01 2c",  # int8 for a positive fixint
    "dc 00 02 05 cd 01 2c",  # array16 header for two items
])
def test_non_canonical_link_ack_is_refused(payload: str) -> None:
    with pytest.raises(ProtocolError) as err:
        decode(sealed(LINK_ACK_HEAD + bytes.fromhex(payload)))
    assert err.value.cause == "payload"


def _hello_wire(geometry: bytes, fw: bytes, boots: bytes = b"\x01") -> bytes:
    head = bytes.fromhex("0200030005000100050000000000")
    return sealed(head + b"\x96\x05" + fw + b"\x93" + geometry + b"\xce\x02\xfa\xf0\x80\x03" + boots)


def test_hello_refuses_float32_geometry_and_str8_strings() -> None:
    f32 = b"".join(msgpack.packb(v, use_single_float=True) for v in (0.5, 0.25, 0.04))
    assert payload_as(decode(_hello_wire(_F64, b"\xa50.1.0")), Hello).side == 0.04
    for bad in (_hello_wire(f32, b"\xa50.1.0"), _hello_wire(_F64, b"\xd9\x050.1.0")):
        with pytest.raises(ProtocolError) as err:
            decode(bad)
        assert err.value.cause == "payload"


_F64 = b"".join(b"\xcb" + msgpack.packb(v, use_single_float=False)[1:] for v in (0.5, 0.25, 0.04))


@pytest.mark.parametrize("boots,accepted", [
    (b"\x00", 0), (b"\xce\xff\xff\xff\xff", 2**32 - 1),  # u32, smallest form
    (b"\xcf\x00\x00\x00\x01\x00\x00\x00\x00", None),  # 2**32: more than a u32
    (b"\xff", None), (b"\xc3", None), (b"\xc0", None),  # negative, bool, nil
    (b"\xcc\x05", None),  # 5 in a wider form than needed
])
def test_hello_boots_is_a_canonical_u32(boots: bytes, accepted: int | None) -> None:
    wire = _hello_wire(_F64, b"\xa50.1.0", boots)
    if accepted is not None:
        assert payload_as(decode(wire), Hello).boots == accepted
        return
    with pytest.raises(ProtocolError) as err:
        decode(wire)
    assert err.value.cause == "payload"


# -- 5. DATA ranges and BUNDLE -----------------------------------------------------------------

def _data_wire(mode: int, over: int, c1: int) -> bytes:
    head = encode(Frame(7, 0, 7, 1, Beacon(0, 0, 0)))[:HEADER_LEN]
    head = head[:2] + bytes([FrameType.DATA]) + head[3:]
    assert head[0] == VERSION
    return sealed(head + msgpack.packb([mode, over, [[0, 1000, c1, 100, 0, 7]], 100, 500_000]))


@pytest.mark.parametrize("mode,over,c1", [(0, 500, 100), (0, 1, 70_000), (1, 4, 255 * 4 + 1)])
def test_data_ranges_depend_on_the_mode(mode: int, over: int, c1: int) -> None:
    with pytest.raises(ProtocolError) as err:
        decode(_data_wire(mode, over, c1))
    assert err.value.cause == "payload"


@pytest.mark.parametrize("mode,over,c1", [(0, 1, 65535), (1, 4, 255 * 4), (1, 65535, 255 * 65535)])
def test_data_ranges_at_their_limits_are_accepted(mode: int, over: int, c1: int) -> None:
    assert payload_as(decode(_data_wire(mode, over, c1)), Data).samples[0].c1 == c1


def test_bundle_refuses_fragments() -> None:
    parts = fragment(_datagram(100, 19000), tag=1, max_frame=64)
    head = encode(Frame(1, 0, 1, 2, Bundle((Frame(3, 1, 3, 1, Beacon(1, 10, 1)),))))[:HEADER_LEN]
    forged = sealed(head + msgpack.packb([encode(parts[1])]))
    with pytest.raises(ProtocolError) as err:
        decode(forged)
    assert err.value.cause == "bundle"
    with pytest.raises(ProtocolError):
        encode(Frame(1, 0, 1, 2, Bundle((parts[1],))))


def test_bundle_is_never_fragmented() -> None:
    inner = tuple(Frame(3, 1, 3, i, Beacon(1, 10, 1)) for i in range(8))
    with pytest.raises(ProtocolError):
        fragment(Frame(1, 0, 1, 2, Bundle(inner)), tag=1, max_frame=64)
    body = encode(Frame(1, 0, 1, 2, Bundle(inner[:1])))[HEADER_LEN:-CRC_LEN]
    frag = Frame(1, 0, 1, 2, Fragment(FrameType.BUNDLE, 1, 0, len(body), body))
    with pytest.raises(ProtocolError):
        encode(frag)
    head = bytes.fromhex("02 10 08 00 01 00 00 00 01 00 02 00 00 00")
    forged = sealed(head + (1).to_bytes(2, "big") + bytes(2) + len(body).to_bytes(2, "big") + body)
    with pytest.raises(ProtocolError) as err:
        decode(forged)
    assert err.value.cause == "fragment"


def test_inner_frame_bad_crc_is_the_inner_frames_problem() -> None:
    inner = bytearray(encode(Frame(3, 1, 3, 1, Beacon(1, 10, 1))))
    inner[-1] ^= 0xFF
    head = encode(Frame(1, 0, 1, 2, Bundle((Frame(3, 1, 3, 1, Beacon(1, 10, 1)),))))[:HEADER_LEN]
    with pytest.raises(ProtocolError) as err:
        decode(sealed(head + msgpack.packb([bytes(inner)])))
    assert err.value.cause == "inner_crc"


# -- 6. reassembler clock, stream memory and delimiter count ----------------------------------

@pytest.mark.parametrize("now", [math.nan, math.inf, -math.inf])
def test_reassembler_refuses_a_non_finite_clock(now: float) -> None:
    parts = fragment(_datagram(100, 19000), tag=1, max_frame=64)
    with pytest.raises(ValueError):
        Reassembler().receive(parts[0], now)


def test_reassembler_times_out_after_the_clock_steps_back() -> None:
    r = Reassembler(timeout=2.0)
    parts = fragment(_datagram(100, 19000), tag=1, max_frame=64)
    r.receive(parts[0], 1000.0)
    r.expire(5.0)  # the clock stepped back by ~995 s: the slot's age is kept, not made negative
    assert r.slot_count == 1
    r.expire(7.5)
    assert r.slot_count == 0 and r.drops["timeout"] == 1


def test_stream_feed_does_not_split_a_large_chunk_in_memory() -> None:
    d = StreamDecoder()
    chunk = (b"\x41" * 199 + b"\x00") * 50_000  # 10 MB of line noise between delimiters
    tracemalloc.start()
    try:
        d.feed(chunk)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < len(chunk) // 10  # the old decoder split the whole chunk: more than its size again
    c: dict[str, Any] = d.counters()  # nested counts, read as the test knows them
    assert c["delimiters"] == 50_000 and c["frames_dropped"] == {"cobs": 50_000}
    assert c["bytes_in"] == c["bytes_ok"] + sum(c["bytes_dropped"].values()) + c["delimiters"] + d.buffered


def test_delimiters_are_counted() -> None:
    d = StreamDecoder()
    frame = Frame(5, 0, 5, 9, Beacon(0, 10, 1))
    d.feed(encode_stream(frame) * 3 + b"\x00\x00")
    assert d.counters()["delimiters"] == 8 and d.delimiters == 8


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(payload=data_strategy)
def test_every_decodable_data_payload_is_accepted_by_tactile(payload: Data) -> None:
    """What decode lets through, the counts-to-capacitance functions take without raising."""
    try:
        wire = encode(Frame(7, 0, 7, 1, payload))
    except ProtocolError:
        return  # too many samples for one frame
    decoded = payload_as(decode(wire), Data)
    if not decoded.samples:
        return
    c = np.array([[s.c1, s.c2] for s in decoded.samples], dtype=np.int64)
    if decoded.mode is Mode.COUNTER:
        transfer.unwrap_counts(c, transfer.expected_counts(20e-12))
    else:
        transfer.code_to_capacitance(c // decoded.oversampling)
