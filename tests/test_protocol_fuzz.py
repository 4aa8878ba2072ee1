"""Fuzzing the decoders: 100 000+ random and mutated inputs, only ProtocolError ever escapes.

Mutations are resealed with a correct CRC half of the time, so they get past the
checksum into the header, fragment and msgpack parsers instead of dying at the CRC.
"""

from __future__ import annotations

import random
from typing import Any

import msgpack
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
    FrameType,
    Hello,
    LinkAck,
    MeshTime,
    Mode,
    Neighbour,
    Op,
    ProtocolError,
    Readout,
    ReadoutSample,
    Reassembler,
    Sample,
    SampleFlags,
    Status,
    StreamDecoder,
    crc16,
    decode,
    encode,
    fragment,
)
from cellbridge.protocol.frame import HEADER_LEN
from cobs import cobs

from support.protocol_v1 import encode_v1, encode_v2, encode_v3, same_header
from support.protocol_wire import mutate

#: READOUT records (version 4): a periodic one, an event-based one with all three states and
#: ids in every msgpack form, both parts of a record split by mode, and an 8x8 that travels
#: fragmented
READOUTS = [
    Readout(4521, 100, Mode.COUNTER, 1, tuple(ReadoutSample(b, 19600 + b, 15800 - b, b % 4) for b in range(1, 5)),
            span_us=2840),
    Readout(2**33, 250, Mode.COUNTER, 1, (ReadoutSample(6, 21000, 15800), ReadoutSample(300, 65535, 0, 3)),
            (1, 2, 127, 128, 255, 256), (7, 0xFFFE), 70_000),
    Readout(4600, 100, Mode.COUNTER, 1, (ReadoutSample(2, 19600, 15800),), (4,), (), 2840, 0, 2),
    Readout(4600, 100, Mode.ADC, 16, (ReadoutSample(9, 255 * 16, 1968, 1),), (), (10,), 2840, 1, 2),
]
BIG_READOUT = Readout(4601, 100, Mode.COUNTER, 1, tuple(ReadoutSample(b, 19600 + b, 15800) for b in range(1, 65)),
                      span_us=5200)

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
    *(Frame(1, 0, 1, 200 + i, r) for i, r in enumerate(READOUTS)),
    Frame(1, 0, 1, 210, Bundle((Frame(1, 0, 1, 211, READOUTS[2]), Frame(1, 0, 1, 212, READOUTS[3])))),
    *fragment(Frame(1, 0, 1, 220, BIG_READOUT), tag=6),
]
# Versions 1 to 3 are still read (docs/protocol.md §3): old senders' bytes are fuzzed too
# (a READOUT among them is a type their version did not have).
WHOLE = [f for f in SEEDS if not isinstance(f.payload, Fragment)]
WIRE = [encode(f) for f in SEEDS] + [encode_v1(f) for f in WHOLE] + [encode_v2(f) for f in WHOLE] + [encode_v3(f) for f in WHOLE]


def test_fuzz_decoders_raise_only_protocol_error() -> None:
    rng = random.Random(20261122)
    stream = StreamDecoder()
    reassembler = Reassembler(max_per_origin=2, max_slots=8)
    decoded = decoded_v1 = decoded_v2 = decoded_v3 = readouts = 0
    n = 100_000
    for i in range(n):
        if i % 4 == 0:
            data = rng.randbytes(rng.randint(0, 300))
        else:
            data = mutate(rng, rng.choice(WIRE), WIRE)
        try:
            frame = decode(data)
        except ProtocolError:
            pass
        else:
            decoded += 1
            readouts += isinstance(frame.payload, Readout)
            if isinstance(frame.payload, Readout) or getattr(frame.payload, "frame_type", None) is FrameType.READOUT:
                assert data[0] >= 4  # older versions had no READOUT: never decoded as one
            if data[0] == VERSION or isinstance(frame.payload, Fragment):
                assert encode(frame) == data  # only the canonical bytes of a frame are accepted
            else:  # a whole version 1, 2 or 3 frame: read into today's message, written back as version 4
                decoded_v1 += data[0] == 1
                decoded_v2 += data[0] == 2
                decoded_v3 += data[0] == 3
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
    assert decoded > n // 20 and decoded_v1 > n // 200 and decoded_v2 > n // 200 and decoded_v3 > n // 200
    assert readouts > n // 1000  # ~230: mutated READOUTs got through the CRC and all its checks
    assert stream.frames_dropped["type"] > 0  # among them READOUTs in older versions
    assert sum(stream.frames_dropped.values()) > 0 and stream.frames_ok > n // 40
    assert reassembler.completed + sum(reassembler.drops.values()) > 0


def _readout_ok(r: Readout) -> bool:
    """The invariants every decoded READOUT holds (docs/protocol.md §4)."""
    limit = 0xFFFF if r.mode is Mode.COUNTER else 255 * r.oversampling
    ids = [s.bridge for s in r.samples]
    lists_ok = all(list(x) == sorted(set(x)) for x in (ids, r.unchanged, r.missing))
    every = ids + list(r.unchanged) + list(r.missing)
    return (lists_ok and len(every) == len(set(every)) and all(0 <= b <= 0xFFFF for b in every)
            and all(0 <= s.c1 <= limit and 0 <= s.c2 <= limit and 0 <= s.flags <= 3 for s in r.samples)
            and 0 <= r.part < r.parts <= 255 and 1 <= r.rate <= 0xFFFF and 0 <= r.span_us < 2**32
            and 0 <= r.index < 2**64 and (r.oversampling == 1 if r.mode is Mode.COUNTER else 1 <= r.oversampling <= 0xFFFF))


def test_fuzzed_readouts_raise_only_protocol_error() -> None:
    """Mutated READOUT payloads (edge integers, other types, ids moved between lists, fields
    removed or added) either decode into a record whose invariants hold and that encodes back
    to the same bytes, or are dropped with ProtocolError: nothing else escapes."""
    rng = random.Random(20261128)
    edges: list[Any] = [0, 1, 2, 3, 4, 127, 128, 255, 256, 65535, 65536, 2**32 - 1, 2**32, 2**64 - 1, -1, -32,
             None, True, 1.5, "x", [], [1], {}]
    bases = [r.to_wire() for r in [*READOUTS, BIG_READOUT]]
    head = encode(Frame(1, 0, 1, 7, READOUTS[0]))[:HEADER_LEN]
    decoded = refused = 0
    for _ in range(30_000):
        obj = msgpack.unpackb(msgpack.packb(rng.choice(bases)))
        for _ in range(rng.randint(1, 3)):
            where = rng.random()
            value = rng.choice(edges) if rng.random() < 0.7 else rng.randint(-(2**63), 2**64 - 1)
            lists = [k for k in (4, 5, 6) if type(obj[k]) is list and obj[k]] if type(obj) is list and len(obj) in (10, 11) else []
            if where < 0.3 and lists:  # an element: one of its fields, in any list
                k = rng.choice(lists)
                i = rng.randrange(len(obj[k]))
                if k == 4 and type(obj[k][i]) is list and obj[k][i]:
                    obj[k][i][rng.randrange(len(obj[k][i]))] = value
                else:
                    obj[k][i] = value
            elif where < 0.5 and lists:  # an id moved or copied, within a list or to another
                k, j = rng.choice(lists), rng.choice([x for x in (4, 5, 6) if type(obj[x]) is list])
                item = obj[k][rng.randrange(len(obj[k]))]
                b = item[0] if type(item) is list and item else item
                entry = [b, 100, 100, 0] if j == 4 else b
                obj[j].insert(rng.randrange(len(obj[j]) + 1), entry)
                if rng.random() < 0.5:
                    obj[k].remove(item)
            elif where < 0.85 and type(obj) is list and obj:  # a header field of the record
                obj[rng.randrange(len(obj))] = value
            elif type(obj) is list:  # a field removed or added
                if rng.random() < 0.5 and obj:
                    del obj[rng.randrange(len(obj))]
                else:
                    obj.insert(rng.randrange(len(obj) + 1), value)
        try:
            body = head + msgpack.packb(obj)
        except (TypeError, ValueError, OverflowError):
            continue
        if len(body) + 2 > 255:
            continue
        wire = body + crc16(body).to_bytes(2, "big")
        try:
            frame = decode(wire)
        except ProtocolError:
            refused += 1
            continue
        decoded += 1
        assert isinstance(frame.payload, Readout) and _readout_ok(frame.payload)
        if type(obj) is list and len(obj) == 10:  # the form without a root: read as root 0, written with it
            assert frame.payload.root == 0 and Readout.from_wire(frame.payload.to_wire()[:10]) == frame.payload
            continue
        assert encode(frame) == wire
    assert decoded > 1000 and refused > 10_000  # both sides of every check were reached
