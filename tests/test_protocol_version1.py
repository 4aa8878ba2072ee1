"""Version 1 is still read (docs/protocol.md §3): old captures replay, old bridges are heard.

A version 1 frame decodes into today's message with the fields versions 2 and 3 added at
their defaults, and ``encode`` writes it back as version 4 (what a forwarder relays). A
fragment keeps its datagram's version, since its slice holds that version's bytes.
"""

from __future__ import annotations

import msgpack
import pytest
from cellbridge.protocol import (
    MAX_FRAME,
    VERSION,
    Beacon,
    Data,
    Fragment,
    Frame,
    FrameType,
    Hello,
    MeshTime,
    Mode,
    ProtocolError,
    Reassembler,
    Sample,
    SampleFlags,
    StreamDecoder,
    decode,
    encode,
    encode_stream,
)
from cellbridge.protocol.frame import CRC_LEN
from cobs import cobs
from hypothesis import HealthCheck, assume, given, settings

from support.protocol_strategies import frames_v3
from support.protocol_v1 import as_read_from_v1, encode_v1, payload_v1, read_back
from support.protocol_wire import sealed

NO_MESH_TIME = SampleFlags.NO_MESH_TIME


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(frame=frames_v3)
def test_a_version_1_frame_decodes_with_the_new_fields_at_their_defaults(frame: Frame) -> None:
    wire = encode_v1(frame)
    assume(len(wire) <= MAX_FRAME)
    assert wire[0] == 1
    again = read_back(frame, wire, as_read_from_v1(frame))  # None: later fields overflow a full frame
    if again is not None and frame.type not in (FrameType.DATA, FrameType.BEACON, FrameType.HELLO, FrameType.BUNDLE):
        # payloads versions 2 and 3 did not change are the same bytes: only the version byte differs
        assert again[1:-CRC_LEN] == wire[1:-CRC_LEN]


def test_version_1_data_is_flagged_without_mesh_time() -> None:
    frame = Frame(7, 0, 7, 42, Data(Mode.COUNTER, (Sample(0, 10**6, 19600, 15800, 0, 555),
                                                  Sample(0, 11 * 10**5, 19598, 15801, 1, 556)), 1, 100))
    got = decode(encode_v1(frame)).payload
    assert isinstance(got, Data)
    assert got.rate == 0
    assert [(s.flags, s.index) for s in got.samples] == [(NO_MESH_TIME, 0), (NO_MESH_TIME | 1, 0)]
    assert [s[:4] for s in got.samples] == [s[:4] for s in frame.payload.samples]  # type: ignore[union-attr]  # a DATA frame's payload is a Data


def test_version_1_beacon_and_hello_have_no_time_and_boot_count_0() -> None:
    beacon = decode(encode_v1(Frame(3, 0xFFFF, 3, 9, Beacon(1, 35, 2, MeshTime(1, 7, 123)))))
    assert beacon.payload == Beacon(1, 35, 2, None)
    hello = decode(encode_v1(Frame(5, 0, 5, 0, Hello(5, "0.1.0", 0.04, 0.08, 0.04, 50_000_000, 3, 17))))
    assert hello.payload == Hello(5, "0.1.0", 0.04, 0.08, 0.04, 50_000_000, 3, 0)


@pytest.mark.parametrize("message", [
    Data(Mode.COUNTER, (Sample(0, 1000, 19600, 15800, 0, 9),), 1, 100),
    Beacon(1, 20, 2, None),
    Hello(5, "0.1.0", 0.04, 0.08, 0.04, 50_000_000, 3, 1),
])
def test_version_2_payloads_in_a_version_1_frame_are_refused(message: Data | Beacon | Hello) -> None:
    """Each version checks its own array lengths exactly: the header's version says which."""
    good = encode(Frame(5, 0, 5, 0, message))
    body = bytearray(good[:-CRC_LEN])
    body[0] = 1
    with pytest.raises(ProtocolError) as err:
        decode(sealed(bytes(body)))
    assert err.value.cause == "payload"
    v1 = encode_v1(Frame(5, 0, 5, 0, message))
    body = bytearray(v1[:-CRC_LEN])
    body[0] = VERSION
    with pytest.raises(ProtocolError) as err:
        decode(sealed(bytes(body)))
    assert err.value.cause == "payload"


def test_a_version_1_hello_naming_another_bridge_is_refused() -> None:
    v1 = bytearray(encode_v1(Frame(5, 0, 5, 0, Hello(5, "0.1.0", 0.04, 0.08, 0.04, 50_000_000, 3)))[:-CRC_LEN])
    v1[7:9] = (6).to_bytes(2, "big")  # origin 6, payload says bridge 5
    with pytest.raises(ProtocolError) as err:
        decode(sealed(bytes(v1)))
    assert err.value.cause == "payload"


def test_the_stream_decoder_reads_version_1_and_2_alike() -> None:
    frame = Frame(7, 0, 7, 42, Data(Mode.COUNTER, (Sample(0, 10**6, 19600, 15800, 0, 3),), 1, 100))
    v1 = encode_v1(frame)
    serial = encode_stream(decode(v1))  # what a forwarder writes: the current version
    out = StreamDecoder().feed(b"\x00" + cobs.encode(v1) + b"\x00" + serial)
    assert out == [as_read_from_v1(frame)] * 2


def _fragments_v1(frame: Frame, tag: int, step: int) -> list[Frame]:
    """A version 1 sender's fragments of ``frame``: version 1 payload bytes, sliced."""
    body = sealed(msgpack.packb(payload_v1(frame.payload)))
    return [Frame(frame.src, frame.dst, frame.origin, (frame.seq + i) & 0xFFFF,
                  Fragment(frame.type, tag, off, len(body), body[off:off + step], 1))
            for i, off in enumerate(range(0, len(body), step))]


BIG = Frame(9, 0, 9, 100, Data(Mode.COUNTER, tuple(Sample(0, 10**6 + 2 * 10**5 * i, 19600 - i, 15800, 0, i)
                                                   for i in range(30))))


def test_a_version_1_fragment_is_relayed_as_version_1() -> None:
    for piece in _fragments_v1(BIG, tag=5, step=40):
        wire = encode(piece)
        assert wire[0] == 1  # its slice is version 1 bytes: relabelling it would corrupt the datagram
        got = decode(wire)
        assert got == piece and encode(got) == wire


def test_a_version_1_datagram_reassembles_as_version_1() -> None:
    r = Reassembler()
    out = [r.receive(decode(encode(p)), 0.0) for p in _fragments_v1(BIG, tag=5, step=40)]
    assert out[:-1] == [None] * (len(out) - 1)
    assert out[-1] == as_read_from_v1(BIG) and r.completed == 1 and not r.drops


def test_fragments_of_one_datagram_in_two_versions_conflict() -> None:
    pieces = _fragments_v1(BIG, tag=5, step=40)
    relabelled = Frame(9, 0, 9, pieces[1].seq, Fragment(FrameType.DATA, 5, 40, pieces[1].payload.total,  # type: ignore[union-attr]  # a fragment's payload is a Fragment
                                                        pieces[1].payload.data, VERSION))  # type: ignore[union-attr]  # a fragment's payload is a Fragment
    r = Reassembler()
    assert r.receive(pieces[0], 0.0) is None
    assert r.receive(relabelled, 0.0) is None
    assert r.drops["conflict"] == 1 and r.slot_count == 0


def test_a_fragment_of_an_unknown_version_cannot_be_encoded() -> None:
    with pytest.raises(ProtocolError) as err:
        encode(Frame(9, 0, 9, 1, Fragment(FrameType.DATA, 5, 0, 10, b"abc", VERSION + 1)))
    assert err.value.cause == "version"
