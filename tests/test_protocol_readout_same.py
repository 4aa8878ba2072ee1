"""READOUT_SAME (docs/protocol.md §4): a bridge's all-unchanged READOUT told relative to a
record its parent acknowledged. Its codec (round trip, ranges, canonical bytes, versions)
and the record it stands for (:meth:`ReadoutSame.rebuild`)."""

from __future__ import annotations

import msgpack
import pytest
from cellbridge.protocol import (
    Frame,
    FrameType,
    Mode,
    ProtocolError,
    Readout,
    ReadoutSame,
    ReadoutSample,
    decode,
    encode,
    unpack_payload,
)
from cellbridge.protocol.frame import HEADER_LEN
from hypothesis import given
from hypothesis import strategies as st

from support.protocol_strategies import frames_of, readout_same, readouts
from support.protocol_v1 import encode_v3
from support.protocol_wire import sealed


@given(frames_of(readout_same))
def test_a_readout_same_round_trips_in_a_19_byte_frame(frame: Frame) -> None:
    data = encode(frame)
    assert len(data) == 19  # header, [step, ref] as two positive fixints, CRC
    assert decode(data) == frame
    assert data[HEADER_LEN:-2] == bytes([0x92, frame.payload.step, frame.payload.ref])  # type: ignore[union-attr]


@pytest.mark.parametrize("wire", [
    [0, 5], [128, 5], [-1, 5], [3, 128], [3, -1], [3], [3, 5, 0], [True, 5], [3, False], [3.0, 5], [None, 5],
    [3, "a"], {"step": 3, "ref": 5},
])
def test_a_readout_same_out_of_its_ranges_or_shape_is_refused(wire: object) -> None:
    with pytest.raises(ProtocolError) as exc:
        unpack_payload(FrameType.READOUT_SAME, msgpack.packb(wire))
    assert exc.value.cause == "payload"


@given(st.integers(0, 0xFF), st.integers(0, 0xFF))
def test_any_payload_of_a_readout_same_decodes_to_its_ranges_or_raises_protocol_error(a: int, b: int) -> None:
    head = encode(Frame(6, 2, 6, 815, ReadoutSame(3, 44)))[:HEADER_LEN]
    for body in (bytes([0x92, a, b]), bytes([0x92, 0xCC, a, b]), bytes([a, b]), bytes([0x93, a, b, 0])):
        try:
            f = decode(sealed(head + body))
        except ProtocolError:
            continue
        assert isinstance(f.payload, ReadoutSame)
        assert 1 <= f.payload.step <= 127 and 0 <= f.payload.ref <= 127
        assert encode(f) == sealed(head + body)  # only the canonical form is accepted


def test_a_readout_same_in_a_frame_of_an_older_version_is_dropped_as_a_type_it_did_not_have() -> None:
    frame = Frame(6, 2, 6, 815, ReadoutSame(3, 44))
    with pytest.raises(ProtocolError) as exc:
        decode(encode_v3(frame))
    assert exc.value.cause == "type"


@given(readouts(), st.integers(1, 127))
def test_the_record_a_readout_same_stands_for_lists_every_element_of_its_reference_unchanged(
        ref: Readout, step: int) -> None:
    if ref.index + step >= 2**64:
        return
    r = ReadoutSame(step, 0).rebuild(ref)
    ids = sorted((*(s.bridge for s in ref.samples), *ref.unchanged, *ref.missing))
    assert r == Readout(ref.index + step, ref.rate, ref.mode, ref.oversampling, (), tuple(ids), (), ref.span_us, 0,
                        1, ref.root)
    assert Readout.from_wire(r.to_wire()) == r  # a valid record: what the parent passes on


def test_a_missing_element_of_the_reference_is_unchanged_in_the_record_rebuilt() -> None:
    # the sender sends a READOUT_SAME only when the rebuilt record is its own record (the
    # link layer compares them): an element missing in the reference but unchanged now is
    # one; an element missing now makes the record go whole
    ref = Readout(4521, 100, Mode.COUNTER, 1, (ReadoutSample(6, 19600, 15800),), (9,), (12,), 2840, 0, 1, 1)
    assert ReadoutSame(3, 44).rebuild(ref) == Readout(4524, 100, Mode.COUNTER, 1, (), (6, 9, 12), (), 2840, 0, 1, 1)


def test_fuzzed_readout_same_frames_raise_only_protocol_error_and_decode_only_within_their_ranges() -> None:
    """Mutated READOUT_SAME frames (resealed half of the time, so they reach the payload
    parser), on their own and as older versions' bytes: only ProtocolError escapes, and
    what decodes is a canonical frame of a READOUT_SAME in its ranges, or another type."""
    import random

    from support.protocol_v1 import encode_v1, encode_v2
    from support.protocol_wire import mutate

    seeds = [Frame(6, 2, 6, 815, ReadoutSame(3, 44)), Frame(300, 0xFFFE, 300, 0xFFFF, ReadoutSame(127, 127)),
             Frame(1, 2, 1, 0, ReadoutSame(1, 0))]
    wire = [encode(f) for f in seeds] + [g(f) for f in seeds for g in (encode_v1, encode_v2, encode_v3)]
    rng = random.Random(20261201)
    decoded = sames = 0
    for _ in range(20_000):
        data = mutate(rng, rng.choice(wire), wire)
        try:
            f = decode(data)
        except ProtocolError:
            continue
        decoded += 1
        assert encode(f) == data or data[0] != 4
        if isinstance(f.payload, ReadoutSame):
            sames += 1
            assert data[0] == 4 and len(data) == 19
            assert 1 <= f.payload.step <= 127 and 0 <= f.payload.ref <= 127
    assert sames > 200 and decoded > sames  # the mutations got through the CRC into the parser (475)
