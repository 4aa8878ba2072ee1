"""Protocol version 3 (docs/protocol.md §3, §4): DATA packs the samples after a frame's first.

Each later sample travels as its index step and its cycle's residual from the bridge's
nominal schedule (``period`` cycles per index), both signed 64-bit modulo 2⁶⁴; the
decoder rebuilds the absolute samples, so nothing above the protocol layer changes.
Versions 1 and 2 are still read. Version 4 kept every version 3 payload (it only added
READOUT): a version 3 frame reads as today's and is written back as version 4.
"""

from __future__ import annotations

import random
from typing import Any

import msgpack
import pytest
from cellbridge.protocol import (
    MAX_FRAME,
    VERSION,
    Data,
    Fragment,
    Frame,
    FrameType,
    Mode,
    ProtocolError,
    Reassembler,
    Sample,
    SampleFlags,
    StreamDecoder,
    decode,
    encode,
    fragment,
)
from cellbridge.protocol.frame import CRC_LEN, HEADER_LEN
from cellbridge.protocol.messages import packed_sample, packed_samples
from cellbridge.protocol.relay import peek
from cobs import cobs
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from support.payloads import payload_as
from support.protocol_strategies import frames_v3
from support.protocol_v1 import as_read_from_v2, encode_v2, encode_v3, read_back

U64 = 2**64 - 1
NO_MESH_TIME = int(SampleFlags.NO_MESH_TIME)
CLOCK_HZ = 50_000_000


@st.composite
def chip_samples(draw: st.DrawFn) -> tuple[int, tuple[Sample, ...], Mode, int]:
    """(period, samples, mode, oversampling) a chip can send in one DATA frame: a periodic
    schedule whose cycles drift and step (mesh-time corrections), indices with gaps (frames
    skipped, samples an event-based reporter kept), a bridge that loses or takes mesh time
    (its index restarts at 0, or jumps to the skin's), counters and indices at the u64 edge."""
    rate = draw(st.sampled_from([1, 40, 100, 250, 1000, 65535]))
    period = draw(st.sampled_from([CLOCK_HZ // rate, 0, 1, 2**32 - 1]))
    mode = draw(st.sampled_from(Mode))
    over = 1 if mode is Mode.COUNTER else draw(st.integers(1, 0xFFFF))
    limit = 0xFFFF if mode is Mode.COUNTER else 255 * over
    cycle = draw(st.sampled_from([0, 2**32 - 1, 2**32, U64 - 3 * period, U64]) | st.integers(0, U64))
    index = draw(st.sampled_from([0, 2**16, U64 - 2, U64]) | st.integers(0, U64))
    on_time = draw(st.booleans())
    samples = []
    for _ in range(draw(st.integers(1, 20))):
        flags = draw(st.integers(0, 0x0B)) | (0 if on_time else NO_MESH_TIME)
        code = st.integers(0, limit)
        samples.append(Sample(draw(st.integers(0, 3) | st.just(0xFFFF)), cycle, draw(code), draw(code), flags, index))
        event = draw(st.sampled_from(["next", "next", "next", "gap", "drift", "step", "lose", "take", "edge"]))
        step = draw(st.integers(2, 600)) if event == "gap" else 1
        drift = draw(st.integers(-10**6, 10**6)) if event in ("drift", "step") else draw(st.integers(-25, 25))
        cycle = (cycle + step * period + drift) & U64
        index = (index + step) & U64
        if event == "lose":  # mesh time lost: the bridge counts its own samples from 0
            on_time, index = False, 0
        elif event == "take":  # mesh time taken: the index jumps to the skin's
            on_time, index = True, draw(st.integers(0, U64))
        elif event == "edge":
            cycle, index = draw(st.sampled_from([(U64, U64), (0, 0), (U64, 0), (0, U64)]))
    return period, tuple(samples), mode, over


@settings(max_examples=400, suppress_health_check=[HealthCheck.too_slow])
@given(chip_samples(), st.integers(0, 0xFFFF))
def test_packed_data_round_trips_every_sample_a_chip_can_send(drawn: tuple, rate: int) -> None:
    period, samples, mode, over = drawn
    data = Data(mode, samples, over, rate, period)
    assert Data.from_wire(msgpack.unpackb(msgpack.packb(data.to_wire()))) == data
    frame = Frame(4, 0, 4, 9, data, 2, 25)
    try:
        wire = encode(frame)
    except ProtocolError as exc:
        assert exc.cause == "too_large"  # a full frame's worth: it travels fragmented
        r = Reassembler()
        assert [w for w in (r.receive(decode(encode(p)), 0.0) for p in fragment(frame, tag=3)) if w] == [frame]
        return
    assert wire[0] == VERSION == 4
    assert decode(wire) == frame and encode(decode(wire)) == wire
    # every rebuilt cycle and index is in its u64 range (the decoder wraps, never overflows)
    assert all(0 <= s.cycle <= U64 and 0 <= s.index <= U64 for s in payload_as(decode(wire), Data).samples)


@settings(max_examples=200, suppress_health_check=[HealthCheck.too_slow])
@given(chip_samples())
def test_fragmented_packed_data_reassembles(drawn: tuple) -> None:
    period, samples, mode, over = drawn
    frame = Frame(4, 0, 4, 9, Data(mode, samples, over, 100, period))
    r = Reassembler()
    out = [w for w in (r.receive(decode(encode(p)), 0.0) for p in fragment(frame, tag=1, max_frame=48)) if w]
    assert out == [frame]


def _periodic(n: int, cycle: int, index: int, period: int = 500_000) -> tuple[Sample, ...]:
    drift = [0, 3, -2, 25, -25, 1]
    out, c = [], cycle
    for i in range(n):
        out.append(Sample(0, c, 19_600 - i, 15_800, 0, index + i))
        c += period + drift[i % len(drift)]
    return tuple(out)


@pytest.mark.parametrize("cycle,index", [(40_000_000, 4_000), (9_000_000_123, 18_000), (2**40, 2**33)])
def test_a_periodic_sample_after_the_first_costs_11_bytes(cycle: int, index: int) -> None:
    """The point of version 3: a later sample's index step and cycle residual are one byte each
    (the first sample keeps its 17-23 bytes; version 2 wrote every sample so)."""
    samples = _periodic(12, cycle, index)
    packed = packed_samples(samples, 500_000)
    assert packed[0] == list(samples[0])
    assert [len(msgpack.packb(p)) for p in packed[1:]] == [11] * 11
    assert [p[5] for p in packed[1:]] == [1] * 11 and all(-32 <= p[1] <= 127 for p in packed[1:])
    v2 = sum(len(msgpack.packb(list(s))) for s in samples)
    assert len(msgpack.packb(packed)) < 0.7 * v2


def test_a_full_frame_holds_19_periodic_samples_with_64_bit_cycles() -> None:
    data = Data(Mode.COUNTER, _periodic(19, 9_000_000_123, 80_000), 1, 100, 500_000)
    assert len(encode(Frame(7, 0, 7, 1, data))) <= MAX_FRAME
    data.samples = _periodic(20, 9_000_000_123, 80_000)
    with pytest.raises(ProtocolError):
        encode(Frame(7, 0, 7, 1, data))


def test_packed_fields_wrap_modulo_2_64_as_signed_64_bit() -> None:
    top = Sample(0, U64, 1, 2, 0, U64)
    # index U64 -> 0 is one step forward; the cycle U64 -> 0 is one cycle forward, 499 999 short
    assert packed_sample(top, Sample(0, 0, 1, 2, 0, 0), 500_000) == [0, 1 - 500_000, 1, 2, 0, 1]
    # an index back to 0 (mesh time lost) is a negative step; the residual is what is left
    back = packed_sample(Sample(0, 10**9, 1, 2, 0, 4_522), Sample(0, 10**9 + 500_000, 1, 2, 4, 0), 500_000)
    assert back[5] == -4_522 and back[1] == 500_000 + 4_522 * 500_000
    # half the u64 range apart: the step is -2^63, the smallest signed 64-bit value
    far = packed_sample(Sample(0, 0, 0, 0, 0, 0), Sample(0, 0, 0, 0, 0, 2**63), 0)
    assert far[5] == -(2**63)
    for prev, s, period in ((top, Sample(0, 0, 1, 2, 0, 0), 500_000), (Sample(0, 0, 0, 0, 0, 0), Sample(0, 0, 0, 0, 0, 2**63), 0),
                            (Sample(0, 5, 0, 0, 0, 7), Sample(0, U64, 0, 0, 0, 3), 2**32 - 1)):
        data = Data(Mode.COUNTER, (prev, s), 1, 100, period)
        assert decode(encode(Frame(1, 0, 1, 1, data))).payload == data


def test_a_residual_or_step_outside_signed_64_bit_is_refused_not_wrapped() -> None:
    """2⁶³ and -2⁶³ wrap to the same value: the decoder accepts only the signed form, so a
    frame has one encoding and ``encode(decode(x)) == x`` holds."""
    head = encode(Frame(7, 0, 7, 1, Data(Mode.COUNTER, (), 1, 100, 10)))[:HEADER_LEN]
    for residual, step in ((2**63, 1), (1, 2**63), (U64, 1), (1, U64)):
        body = head + msgpack.packb([0, 1, [[0, 5, 0, 0, 0, 0], [0, residual, 0, 0, 0, step]], 100, 10])
        with pytest.raises(ProtocolError) as err:
            decode(body + _crc(body))
        assert err.value.cause == "payload"
    body = head + msgpack.packb([0, 1, [[0, 5, 0, 0, 0, 0], [0, -(2**63), 0, 0, 0, -(2**63)]], 100, 10])
    got = decode(body + _crc(body))
    assert payload_as(got, Data).samples[1] == Sample(0, (5 - 2**63 * 10 - 2**63) & U64, 0, 0, 0, 2**63)
    assert encode(got) == body + _crc(body)


def _crc(body: bytes) -> bytes:
    from cellbridge.protocol import crc16
    return crc16(body).to_bytes(2, "big")


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(frame=frames_v3)
def test_a_version_2_frame_decodes_with_period_0_and_is_written_back_as_the_current_version(frame: Frame) -> None:
    wire = encode_v2(frame)
    assume(len(wire) <= MAX_FRAME)
    assert wire[0] == 2
    assert StreamDecoder().feed(b"\x00" + cobs.encode(wire) + b"\x00") == [as_read_from_v2(frame)]
    again = read_back(frame, wire, as_read_from_v2(frame))  # None: the period overflows a full frame
    if again is not None and frame.type is not FrameType.DATA and frame.type is not FrameType.BUNDLE:
        assert again[1:-CRC_LEN] == wire[1:-CRC_LEN]  # only DATA changed in version 3


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(frame=frames_v3)
def test_a_version_3_frame_reads_as_today_and_is_written_back_as_version_4(frame: Frame) -> None:
    """Version 4 only added READOUT: a version 3 frame of any other type is today's frame, and
    its version 4 form differs only in the version byte and the CRC (a bundle's inner frames too)."""
    wire = encode_v3(frame)
    assume(len(wire) <= MAX_FRAME)
    assert wire[0] == 3
    assert StreamDecoder().feed(b"\x00" + cobs.encode(wire) + b"\x00") == [frame]
    again = read_back(frame, wire, frame)
    assert again is not None  # nothing grew: it fits as it did
    if frame.type is not FrameType.BUNDLE:
        assert again[1:-CRC_LEN] == wire[1:-CRC_LEN]
    assert again == encode(frame)


def test_version_2_data_in_a_version_3_or_4_frame_and_the_other_way_round_are_refused() -> None:
    frame = Frame(7, 0, 7, 1, Data(Mode.COUNTER, _periodic(3, 10**6, 50), 1, 100, 500_000))
    v4, v2 = encode(frame), encode_v2(frame)
    for version, wire in ((2, v4), (3, v2), (4, v2)):
        body = bytes([version]) + wire[1:-CRC_LEN]
        with pytest.raises(ProtocolError) as err:
            decode(body + _crc(body))
        assert err.value.cause == "payload"


def test_a_fragmented_version_2_datagram_is_parsed_as_version_2() -> None:
    frame = Frame(9, 0, 9, 100, Data(Mode.COUNTER, _periodic(12, 10**6, 4000), 1, 250, 200_000))
    payload = encode_v2(frame)[HEADER_LEN:-CRC_LEN]
    datagram = payload + _crc(payload)
    step, r, out = 30, Reassembler(), []
    for k, off in enumerate(range(0, len(datagram), step)):
        part = Frame(9, 0, 9, 100 + k, Fragment(Data.frame_type, 5, off, len(datagram), datagram[off:off + step], 2))
        wire = encode(part)
        assert wire[0] == 2  # a fragment keeps its datagram's version
        got = r.receive(decode(wire), 0.0)
        out += [got] if got else []
    assert out == [as_read_from_v2(frame)]


def test_a_relay_forwards_frames_of_the_current_version_only() -> None:
    frame = Frame(7, 3, 7, 1, Data(Mode.COUNTER, _periodic(3, 10**6, 50), 1, 100, 500_000))
    assert peek(encode(frame)) is not None
    assert peek(encode_v2(frame)) is None  # it cannot turn a version 2 payload into version 4
    assert peek(encode_v3(frame)) is None  # nor relabel a version 3 frame (docs/protocol.md §3, mixed skins)


def test_fuzzed_packed_data_raises_only_protocol_error() -> None:
    """Mutated packed samples (any int, including the signed and unsigned edges, in any field,
    or other types) either decode into samples in range that encode back to the same bytes,
    or are dropped with ProtocolError: nothing else escapes."""
    rng = random.Random(20261124)
    edges: list[Any] = [0, 1, -1, 127, 128, -32, -33, 2**16, 2**32, 2**63 - 1, 2**63, -(2**63), U64, None, True, 1.5, "x", []]
    base = Data(Mode.COUNTER, _periodic(6, 9_000_000_123, 18_000), 1, 100, 500_000).to_wire()
    head = encode(Frame(7, 0, 7, 1, Data(Mode.COUNTER, (), 1, 100, 10)))[:HEADER_LEN]
    decoded = 0
    for _ in range(20_000):
        obj = msgpack.unpackb(msgpack.packb(base))
        for _ in range(rng.randint(1, 3)):
            where = rng.random()
            value = rng.choice(edges) if rng.random() < 0.7 else rng.randint(-(2**63), U64)
            if where < 0.8:
                sample = rng.choice(obj[2])
                if sample:
                    sample[rng.randrange(len(sample))] = value
            elif where < 0.9:
                obj[rng.choice([0, 1, 3, 4])] = value
            else:
                sample = rng.choice(obj[2])
                if sample:
                    del sample[rng.randrange(len(sample))]
        try:
            body = head + msgpack.packb(obj)
        except (TypeError, ValueError):
            continue
        wire = body + _crc(body)
        try:
            frame = decode(wire)
        except ProtocolError:
            continue
        decoded += 1
        assert all(0 <= s.cycle <= U64 and 0 <= s.index <= U64 for s in payload_as(frame, Data).samples)
        assert encode(frame) == wire
    assert decoded > 1000  # the fuzzer reached the packed samples' arithmetic, not only the checks
