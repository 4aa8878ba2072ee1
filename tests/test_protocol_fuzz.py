"""Fuzzing the decoders: 100 000+ random and mutated inputs, only ProtocolError ever escapes.

Mutations are resealed with a correct CRC half of the time, so they get past the
checksum into the header, fragment and msgpack parsers instead of dying at the CRC.
"""

from __future__ import annotations

import random

from cobs import cobs
from protocol_v1 import encode_v1, encode_v2, same_header
from protocol_wire import sealed

from cellbridge.protocol import (
    VERSION,
    Beacon,
    BridgeStatus,
    Bundle,
    Command,
    CommandReply,
    Data,
    Fragment,
    Frame,
    Hello,
    LinkAck,
    MeshTime,
    Mode,
    Neighbour,
    Op,
    ProtocolError,
    Reassembler,
    Sample,
    SampleFlags,
    Status,
    StreamDecoder,
    decode,
    encode,
    fragment,
)

SEEDS = [
    Frame(1, 0, 1, 1, Data(Mode.COUNTER, (Sample(0, 123456, 19600, 15800, SampleFlags.HELD, 70_000),
                                          Sample(0, 223456, 19590, 15790, 2 | SampleFlags.NO_MESH_TIME, 12)), 1, 100)),
    # version 3 packs the samples after the first: a periodic bridge past 2^32 cycles, a gap,
    # mesh time lost (the index back to 0) and cycles at the u64 edge
    Frame(1, 0, 1, 2, Data(Mode.COUNTER, (Sample(0, 9_000_000_123, 19600, 15800, 0, 18_000),
                                          Sample(0, 9_000_500_126, 19599, 15801, 0, 18_001),
                                          Sample(0, 9_001_500_120, 19598, 15800, 0, 18_003),
                                          Sample(0, 9_002_000_120, 19597, 15800, 4, 0),
                                          Sample(0, 2**64 - 1, 19597, 15800, 4, 1),
                                          Sample(0, 499_999, 19597, 15800, 4, 2)), 1, 100, 500_000)),
    Frame(2, 0xFFFF, 2, 2, Beacon(1, 35, 2), flags=1),
    Frame(2, 0xFFFF, 2, 3, Beacon(1, 35, 2, MeshTime(1, 513, 2**40 + 12345))),
    Frame(3, 0, 3, 3, Hello(3, "0.1.0", 0.04, 0.08, 0.04, 50_000_000, 3, 7)),
    Frame(4, 0, 4, 4, BridgeStatus(1, 20, (Neighbour(1, 10), Neighbour(5, 14)), 0, 3, 1, 10**9)),
    Frame(0, 5, 0, 5, Command(77, Op.SET_RATE, 100)),
    Frame(5, 0, 5, 6, CommandReply(77, Op.SET_RATE, Status.OK, 100)),
    Frame(6, 5, 6, 7, LinkAck(5, 6)),
    Frame(7, 0, 7, 8, Bundle((Frame(8, 7, 8, 1, Beacon(7, 20, 2, MeshTime(1, 4, 99))),
                              Frame(9, 7, 9, 1, LinkAck(7, 8))))),
    *fragment(Frame(9, 0, 9, 100, Data(Mode.ADC, tuple(Sample(0, 10**6 * i, 142 * 16, 123 * 16, 0, 500 + i)
                                                       for i in range(30)), 16, 200)), tag=5, max_frame=64),
]
# Versions 1 and 2 are still read (docs/protocol.md §3): old senders' bytes are fuzzed too.
WIRE = ([encode(f) for f in SEEDS] + [encode_v1(f) for f in SEEDS if not isinstance(f.payload, Fragment)]
        + [encode_v2(f) for f in SEEDS if not isinstance(f.payload, Fragment)])


def mutate(rng: random.Random, data: bytes) -> bytes:
    b = bytearray(data)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(6)
        if op == 0 and b:
            b[rng.randrange(len(b))] = rng.randrange(256)
        elif op == 1 and b:
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        elif op == 2:
            del b[rng.randrange(len(b) + 1):]
        elif op == 3:
            pos = rng.randrange(len(b) + 1)
            b[pos:pos] = rng.randbytes(rng.randint(1, 8))
        elif op == 4:
            other = rng.choice(WIRE)
            cut = rng.randrange(len(other) + 1)
            b = b[:rng.randrange(len(b) + 1)] + bytearray(other[cut:])
        elif op == 5 and len(b) > 16:  # rewrite a header field with an extreme value
            pos = rng.randrange(14)
            b[pos] = rng.choice([0, 1, 0x0F, 0x10, 0x7F, 0x80, 0xFF])
    if rng.random() < 0.5 and len(b) >= 2:
        b = bytearray(sealed(bytes(b[:-2])))
    return bytes(b)


def test_fuzz_decoders_raise_only_protocol_error() -> None:
    rng = random.Random(20261122)
    stream = StreamDecoder()
    reassembler = Reassembler(max_per_origin=2, max_slots=8)
    decoded = decoded_v1 = decoded_v2 = 0
    n = 100_000
    for i in range(n):
        if i % 4 == 0:
            data = rng.randbytes(rng.randint(0, 300))
        else:
            data = mutate(rng, rng.choice(WIRE))
        try:
            frame = decode(data)
        except ProtocolError:
            pass
        else:
            decoded += 1
            if data[0] == VERSION or isinstance(frame.payload, Fragment):
                assert encode(frame) == data  # only the canonical bytes of a frame are accepted
            else:  # a whole version 1 or 2 frame: read into today's message, written back as version 3
                decoded_v1 += data[0] == 1
                decoded_v2 += data[0] == 2
                try:
                    again = encode(frame)
                except ProtocolError as exc:  # later versions' extra fields overflow a full old frame
                    assert exc.cause == "too_large"
                else:
                    assert again[0] == VERSION and same_header(again, data) and decode(again) == frame
            reassembler.receive(frame, now=i * 1e-4)
        # The serial path: the same bytes, raw or COBS-framed, in two pieces.
        serial = data if i % 2 else b"\x00" + cobs.encode(data) + b"\x00"
        for f in stream.feed(serial[: len(serial) // 3]) + stream.feed(serial[len(serial) // 3:]):
            reassembler.receive(f, now=i * 1e-4)
        assert stream.buffered <= stream.max_buffer
        assert reassembler.slot_count <= 8
    # The fuzzer must have reached past the CRC into the parsers, or it proved little.
    assert decoded > n // 20 and decoded_v1 > n // 200 and decoded_v2 > n // 200
    assert sum(stream.frames_dropped.values()) > 0 and stream.frames_ok > n // 40
    assert reassembler.completed + sum(reassembler.drops.values()) > 0
