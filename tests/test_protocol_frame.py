"""Frame codec: round trips for every type, and every way a frame can be wrong."""

from __future__ import annotations

from typing import Any

import pytest
from cellbridge.protocol import (
    CRC_CHECK,
    MAX_FRAME,
    VERSION,
    Beacon,
    Bundle,
    Data,
    Fragment,
    Frame,
    FrameType,
    MeshTime,
    Mode,
    ProtocolError,
    Readout,
    Sample,
    crc16,
    decode,
    encode,
)
from cellbridge.protocol.frame import CRC_LEN, HEADER_LEN
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from support.payloads import payload_as
from support.protocol_strategies import frames_of, messages_by_type
from support.protocol_wire import sealed


def test_crc_parameters() -> None:
    assert crc16(b"123456789") == CRC_CHECK == 0x29B1
    # Independent bitwise CRC-16/CCITT-FALSE.
    def ref(data: bytes) -> int:
        crc = 0xFFFF
        for byte in data:
            crc ^= byte << 8
            for _ in range(8):
                crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
                crc &= 0xFFFF
        return crc
    for data in (b"", b"\x00", b"cellbridge", bytes(range(256))):
        assert crc16(data) == ref(data)


def test_every_frame_type_has_a_strategy() -> None:
    assert set(messages_by_type) == set(FrameType)


@pytest.mark.parametrize("ftype", list(FrameType), ids=lambda t: t.name)
@settings(max_examples=60, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_round_trip_every_type(ftype: FrameType, data: st.DataObject) -> None:
    frame = data.draw(frames_of(messages_by_type[ftype]))
    assert frame.type is ftype
    try:
        wire = encode(frame)
    except ProtocolError as exc:
        assert exc.cause == "too_large"  # the only reason a well-formed frame cannot be sent
        assert too_large(frame)
        return
    assert len(wire) <= MAX_FRAME
    assert decode(wire) == frame
    assert encode(decode(wire)) == wire


def too_large(frame: Frame) -> bool:
    """Whether ``frame`` is larger than one frame may be: by its bytes, or (a bundle) by a
    frame it carries that is itself too large (its encoding refuses it first)."""
    try:
        return len(frame_bytes_estimate(frame)) > MAX_FRAME
    except ProtocolError as exc:
        inner = getattr(frame.payload, "frames", ())
        return exc.cause == "too_large" and any(too_large(f) for f in inner)


def frame_bytes_estimate(frame: Frame) -> bytes:
    from cellbridge.protocol.messages import pack_payload
    assert not isinstance(frame.payload, Fragment)
    return b"h" * (HEADER_LEN + CRC_LEN) + pack_payload(frame.payload)


SAMPLE = Frame(7, 0, 7, 42, Data(Mode.COUNTER, (Sample(0, 123456, 19600, 15800, 0),)), hops=2, cost=25)


def test_a_bundle_of_a_frame_too_large_is_refused_as_too_large() -> None:
    """The round trip's check of a refusal: a bundle whose frame is itself too large (drawn
    once in a CI run) is refused by that frame's encoding, before the bundle's size is known."""
    big = Frame(1, 0, 1, 1, Data(Mode.COUNTER, tuple(Sample(0, 10**6 + i, 2**31, 2**31, 0) for i in range(40))))
    bundle = Frame(1, 0, 1, 2, Bundle((big,)))
    with pytest.raises(ProtocolError) as exc:
        encode(bundle)
    assert exc.value.cause == "too_large"
    assert too_large(bundle) and too_large(big)
    assert not too_large(SAMPLE)


@given(st.integers(0, len(encode(SAMPLE)) - 1), st.integers(1, 255))
def test_any_byte_error_is_detected(pos: int, xor: int) -> None:
    wire = bytearray(encode(SAMPLE))
    wire[pos] ^= xor
    with pytest.raises(ProtocolError) as err:
        decode(bytes(wire))
    assert err.value.cause == "crc"


def test_header_writes_version_4() -> None:
    assert encode(SAMPLE)[0] == VERSION == 4


@pytest.mark.parametrize(
    "offset,value,cause",
    [(0, 0, "version"), (0, 5, "version"), (0, 0xFF, "version"), (1, 0x20, "must_understand"),
     (1, 0x80, "must_understand"), (2, 0, "type"), (2, 11, "type"), (2, 99, "type")],
)
def test_header_policy(offset: int, value: int, cause: str) -> None:
    body = bytearray(encode(SAMPLE)[:-CRC_LEN])
    body[offset] = value
    with pytest.raises(ProtocolError) as err:
        decode(sealed(bytes(body)))
    assert err.value.cause == cause


def test_unknown_optional_flags_are_kept() -> None:
    body = bytearray(encode(SAMPLE)[:-CRC_LEN])
    body[1] = 0x0E  # optional bits the receiver does not know
    frame = decode(sealed(bytes(body)))
    assert frame.flags == 0x0E and frame.payload == SAMPLE.payload
    assert encode(frame) == sealed(bytes(body))  # a forwarder passes them on unchanged


@pytest.mark.parametrize("data,cause", [(b"", "short"), (b"\x01" * 15, "short"), (b"\x01" * 256, "too_large")])
def test_size_limits(data: bytes, cause: str) -> None:
    with pytest.raises(ProtocolError) as err:
        decode(data)
    assert err.value.cause == cause


@pytest.mark.parametrize(
    "payload",
    [
        b"\xc1",  # never-used msgpack byte
        b"\x94\x00\x01\x90",  # truncated array
        b"\x94\x05\x01\x90\x64",  # unknown mode
        b"\x94\x00\x00\x90\x64",  # oversampling 0
        b"\x94\x00\x01\x91\x95\x00\x00\x00\x00\x00\x64",  # sample with 5 fields (version 1's)
        b"\x94\x00\x01\x91\x97\x00\x00\x00\x00\x00\x00\x00\x64",  # sample with 7 fields
        b"\x94\x00\x01\x91\x96\xff\x00\x00\x00\x00\x00\x64",  # negative element
        b"\x94\x00\x01\x91\x96\xc3\x00\x00\x00\x00\x00\x64",  # bool element
        b"\x94\x00\x01\x91\x96\x00\x00\x00\x00\x00\xff\x64",  # negative index
        b"\x94\x00\x01\x91\x96\x00\x00\x00\x00\x00\xc3\x64",  # bool index
        b"\x94\x00\x01\x91\x96\x00\x00\x00\x00\x00\xc0\x64",  # nil index
        b"\x94\x00\x01\x90\xce\x00\x01\x00\x00",  # rate 65536: more than a u16
        b"\x94\x00\x01\x90\xff",  # negative rate
        b"\x94\x00\x01\x90\xc0",  # nil rate
        b"\x93\x00\x01\x90",  # version 1's DATA (no rate) in a version 2 frame
        b"\x95\x00\x01\x90\x64\x00",  # version 3's DATA (with a period) in a version 2 frame
        b"\x92\x00\x01",  # wrong arity
        b"\xd4\x01\x00",  # ext type
        b"\x94\x00\x01\x90\x64\x00",  # trailing data
    ],
)
def test_bad_payloads(payload: bytes) -> None:
    """Version 2's DATA layout (still read, docs/protocol.md §3), in a version 2 frame."""
    head = _V2_HEAD
    assert head[0] == 2
    with pytest.raises(ProtocolError) as err:
        decode(sealed(head + payload))
    assert err.value.cause == "payload"


def test_the_bad_payloads_are_bad_only_where_they_say() -> None:
    """The well-formed neighbour of the cases above decodes, so each is refused for its defect."""
    frame = decode(sealed(_V2_HEAD + b"\x94\x00\x01\x91\x96\x00\x00\x00\x00\x00\x00\x64"))
    assert frame.payload == Data(Mode.COUNTER, (Sample(0, 0, 0, 0, 0, 0),), 1, 100)
    assert decode(sealed(_V3_HEAD + _packb(V3_GOOD))).payload == V3_GOOD_DATA  # version 3's neighbour
    assert decode(sealed(_V4_HEAD + _packb(V3_GOOD))).payload == V3_GOOD_DATA  # version 4 kept its DATA


_V4_HEAD = encode(SAMPLE)[:HEADER_LEN]
_V3_HEAD = bytes([3]) + _V4_HEAD[1:]
_V2_HEAD = bytes([2]) + _V4_HEAD[1:]
#: A version 3 DATA payload (version 4's too), two samples, period 10: the second packed (residual -1, step 1).
V3_GOOD = [0, 1, [[0, 5, 0, 0, 0, 0], [0, -1, 0, 0, 0, 1]], 100, 10]
V3_GOOD_DATA = Data(Mode.COUNTER, (Sample(0, 5, 0, 0, 0, 0), Sample(0, 14, 0, 0, 0, 1)), 1, 100, 10)


def _v3_with(path: tuple[int, ...], value: object) -> list:
    """V3_GOOD with the field at ``path`` replaced by ``value`` (``...``: removed)."""
    import copy
    out = copy.deepcopy(V3_GOOD)
    parent: Any = out
    for i in path[:-1]:
        parent = parent[i]
    if value is ...:
        del parent[path[-1]]
    else:
        parent[path[-1]] = value
    return out


def _packb(obj: object) -> bytes:
    import msgpack
    return msgpack.packb(obj)


#: Version 3 DATA payloads, each wrong in one field (its comment) and otherwise V3_GOOD.
V3_BAD_PAYLOADS = [
    _packb(V3_GOOD[:4]),  # no period (version 2's DATA in a version 3 frame)
    _packb(_v3_with((4,), -1)),  # negative period
    _packb(_v3_with((4,), None)),  # nil period
    _packb(_v3_with((4,), True)),  # bool period
    _packb(_v3_with((4,), 2**32)),  # period more than a u32
    _packb(_v3_with((2, 0, 1), -1)),  # first sample's cycle negative (it is absolute)
    _packb(_v3_with((2, 0, 5), -1)),  # first sample's index negative
    _packb(_v3_with((2, 1, 5), ...)),  # packed sample of 5 fields
    _packb(_v3_with((2, 1), [0, -1, 0, 0, 0, 1, 0])),  # packed sample of 7 fields
    _packb(_v3_with((2, 1), None)),  # packed sample not an array
    _packb(_v3_with((2, 1, 0), -1)),  # negative element
    _packb(_v3_with((2, 1, 0), 0x10000)),  # element more than a u16
    _packb(_v3_with((2, 1, 1), True)),  # bool residual
    _packb(_v3_with((2, 1, 1), None)),  # nil residual
    _packb(_v3_with((2, 1, 1), 2**63)),  # residual beyond a signed 64-bit field
    _packb(_v3_with((2, 1, 5), 2**63)),  # step beyond a signed 64-bit field
    _packb(_v3_with((2, 1, 5), False)),  # bool step
    _packb(_v3_with((2, 1, 2), -1)),  # negative c1
    _packb(_v3_with((2, 1, 3), 0x10000)),  # c2 more than the 16-bit counter holds
    _packb(_v3_with((2, 1, 4), 0x100)),  # flags more than a u8
    _packb(_v3_with((2, 1, 4), 1.0)),  # float flags
    _packb(_v3_with((1,), 2)),  # oversampling 2 in counter mode
    _packb(V3_GOOD) + b"\x00",  # trailing data
]


@pytest.mark.parametrize("head", [_V3_HEAD, _V4_HEAD], ids=["v3", "v4"])
@pytest.mark.parametrize("payload", V3_BAD_PAYLOADS)
def test_bad_version_3_data(payload: bytes, head: bytes) -> None:
    with pytest.raises(ProtocolError) as err:
        decode(sealed(head + payload))
    assert err.value.cause == "payload"


@pytest.mark.parametrize(
    "payload",
    [
        b"\x93\x01\x14\x02",  # version 1's BEACON (no time) in a version 2 frame
        b"\x94\x01\x14\x02\x92\x01\x02",  # time of 2 fields
        b"\x94\x01\x14\x02\x93\xce\x00\x01\x00\x00\x02\x03",  # root > u16
        b"\x94\x01\x14\x02\x93\x01\xce\x00\x01\x00\x00\x03",  # round seq > u16
        b"\x94\x01\x14\x02\x93\x01\x02\xff",  # negative time
        b"\x94\x01\x14\x02\x93\x01\x02\xc2",  # bool time
        b"\x94\x01\x14\x02\x05",  # time neither nil nor an array
    ],
)
def test_bad_beacon_time(payload: bytes) -> None:
    head = bytearray(encode(SAMPLE)[:HEADER_LEN])
    head[2] = FrameType.BEACON
    with pytest.raises(ProtocolError) as err:
        decode(sealed(bytes(head) + payload))
    assert err.value.cause == "payload"
    ok = decode(sealed(bytes(head) + b"\x94\x01\x14\x02\x93\x01\x02\x03"))
    assert ok.payload == Beacon(1, 20, 2, MeshTime(1, 2, 3))


def test_bundle_cannot_nest() -> None:
    inner = Frame(3, 1, 3, 1, Beacon(1, 10, 1))
    outer = Frame(1, 0, 1, 2, Bundle((inner,)))
    assert payload_as(decode(encode(outer)), Bundle).frames == (inner,)
    with pytest.raises(ProtocolError) as err:
        encode(Frame(1, 0, 1, 3, Bundle((outer,))))
    assert err.value.cause == "nested_bundle"
    # Forged on the wire: a bundle whose inner frame is a bundle.
    import msgpack
    head = encode(outer)[:HEADER_LEN]
    with pytest.raises(ProtocolError) as err:
        decode(sealed(head + msgpack.packb([encode(outer)])))
    assert err.value.cause == "nested_bundle"


@pytest.mark.parametrize("outer,inner", [(4, 3), (4, 2), (4, 1), (3, 4), (3, 2), (2, 3), (1, 2)])
def test_a_bundle_carries_frames_of_its_own_version_only(outer: int, inner: int) -> None:
    """A forwarder bundles frames of the version it writes (it relays no other), so a bundle
    holding another version is refused (cause ``bundle``). Before this check a version 4
    bundle of a version 3 frame decoded, and encode wrote it back as other bytes (its inner
    frame relabelled): two byte strings for one frame. And a version 3 bundle delivered a
    version 4 READOUT, a type version 3 did not have."""
    import msgpack

    from support.protocol_v1 import encode_old


    def bundle_of(version: int, frames: list[bytes]) -> bytes:
        head = bytes([version]) + encode(Frame(1, 0, 1, 2, Bundle((Frame(3, 1, 3, 1, Beacon(1, 10, 1)),))))[1:HEADER_LEN]
        return sealed(head + msgpack.packb(frames))

    beacon = Frame(3, 1, 3, 1, Beacon(1, 10, 1))
    same = bundle_of(outer, [encode_old(beacon, outer) if outer < VERSION else encode(beacon)])
    assert payload_as(decode(same), Bundle).frames == (beacon,)  # the bundle's own version reads
    for inner_frame in (beacon, Frame(1, 0, 1, 1, Readout(5, 100, Mode.COUNTER, 1, (), (1,)))):
        if inner_frame.type is FrameType.READOUT and inner < 4:
            continue  # a READOUT of an older version is refused as an unknown type already
        raw = encode_old(inner_frame, inner) if inner < VERSION else encode(inner_frame)
        with pytest.raises(ProtocolError) as err:
            decode(bundle_of(outer, [raw]))
        assert err.value.cause == "bundle"


@pytest.mark.parametrize("field,value", [("src", -1), ("seq", 0x10000), ("hops", 256), ("flags", 0x10),
                                         ("cost", 1.5)])
def test_encode_rejects_out_of_range_fields(field: str, value) -> None:
    kwargs: dict[str, Any] = dict(src=1, dst=0, origin=1, seq=1, payload=Beacon(0, 0, 0))
    kwargs[field] = value
    with pytest.raises(ProtocolError):
        encode(Frame(**kwargs))


def test_encode_refuses_oversized_frames() -> None:
    big = Frame(1, 0, 1, 1, Data(Mode.COUNTER, tuple(Sample(0, 2**40 + 2**35 * i, 1, 1, 0) for i in range(30))))
    with pytest.raises(ProtocolError) as err:
        encode(big)
    assert err.value.cause == "too_large"


@settings(max_examples=50, derandomize=True)
@given(st.binary(min_size=0, max_size=300))
def test_arbitrary_bytes_only_protocol_error(data: bytes) -> None:
    with pytest.raises(ProtocolError):  # 300 random bytes are never a frame with a valid CRC here
        decode(data)


def test_a_hello_that_names_another_bridge_than_its_origin_is_dropped() -> None:
    """``[bridge, ...]`` of a HELLO is the bridge announcing itself: a HELLO whose bridge is not
    the frame's origin contradicts itself (geometry would be filed under one id and the
    restart under another), so it never passes decode, reassembly or encode."""
    from cellbridge.protocol import Hello, Reassembler, fragment
    from cellbridge.protocol.frame import _HEADER

    good = Frame(5, 0, 5, 0, Hello(5, "0.1.0", 0.04, 0.08, 0.04, 50_000_000, 3))
    wire = encode(good)
    assert decode(wire) == good
    body = bytearray(wire[:-CRC_LEN])
    _HEADER.pack_into(body, 0, VERSION, 0, 3, 5, 0, 6, 0, 0, 0)  # origin 6, payload still says bridge 5
    with pytest.raises(ProtocolError) as err:
        decode(sealed(bytes(body)))
    assert err.value.cause == "payload"
    bad = Frame(5, 0, 6, 0, good.payload)
    with pytest.raises(ProtocolError):
        encode(bad)
    r = Reassembler()
    pieces = fragment(Frame(5, 0, 5, 0, Hello(5, "x" * 32, 0.04, 0.08, 0.04, 50_000_000, 3)), tag=1, max_frame=40)
    assert len(pieces) > 1
    for p in pieces:
        p.origin = 6
        assert r.receive(decode(encode(p)), 0.0) is None
    assert r.drops["payload"] == 1
