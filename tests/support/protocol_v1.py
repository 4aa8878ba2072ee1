"""Test-only writers of protocol version 1, 2 and 3 frames (docs/protocol.md §3), to prove
that ``decode`` still reads them: today's ``encode`` writes version 4 only.

Version 3 differs from version 4 in one thing: it had no READOUT frame type. Every other
payload, and the header, is the same byte for byte (only the version byte and the CRC differ).

Version 2 differs from version 3 in DATA alone: no ``period``, and every sample written
absolute (version 3 packs the samples after a frame's first).

Version 1 differs from version 2 in three payloads: DATA had no ``rate`` and its samples
no ``index`` (``[element, cycle, c1, c2, flags]``), BEACON no ``time``, HELLO no
``boots``. Everything else, header included, is the same byte for byte.

These writers write any message in any version, READOUT included, so a test can also
show what a receiver does with a type the version did not have (drops it, cause ``type``).
"""

from __future__ import annotations

import dataclasses
import struct
from typing import Any

import msgpack
from cellbridge.protocol import Beacon, Bundle, Data, Frame, Hello, SampleFlags
from cellbridge.protocol.frame import HEADER_LEN

from support.protocol_wire import sealed

_HEADER = struct.Struct(">BBBHHHHBH")


def payload_old(message: Any, version: int) -> list[Any]:
    """The wire form of ``message`` in protocol ``version`` 1, 2 or 3 (the fields later versions
    added left out; DATA's samples all absolute before version 3)."""
    if isinstance(message, Data) and version < 3:
        if version == 1:
            return [int(message.mode), message.oversampling, [list(s[:5]) for s in message.samples]]
        return [int(message.mode), message.oversampling, [list(s) for s in message.samples], message.rate]
    if isinstance(message, Beacon) and version == 1:
        return message.to_wire()[:3]
    if isinstance(message, Hello) and version == 1:
        return message.to_wire()[:5]
    if isinstance(message, Bundle):
        return [encode_old(f, version) for f in message.frames]
    return message.to_wire()


def payload_v1(message: Any) -> list[Any]:
    """The version 1 wire form of ``message`` (fields version 2 added are left out)."""
    return payload_old(message, 1)


def encode_old(frame: Frame, version: int) -> bytes:
    """``frame`` as a version 1, 2 or 3 sender wrote it (whole frames only, not fragments)."""
    head = _HEADER.pack(version, frame.flags, frame.type, frame.src, frame.dst, frame.origin, frame.seq,
                        frame.hops, frame.cost)
    body = head + msgpack.packb(payload_old(frame.payload, version), use_bin_type=True)
    return sealed(body)


def encode_v1(frame: Frame) -> bytes:
    return encode_old(frame, 1)


def encode_v2(frame: Frame) -> bytes:
    return encode_old(frame, 2)


def encode_v3(frame: Frame) -> bytes:
    return encode_old(frame, 3)


def read_back(frame: Frame, wire: bytes, expected: Frame) -> bytes | None:
    """Check an older version's ``wire`` (of ``frame``) decodes into ``expected`` and is written
    back as the current version with the same header and content; that re-encoding, or None
    when the newer fields overflow a full old frame (``too_large``, the only reason allowed)."""
    from cellbridge.protocol import MAX_FRAME, VERSION, ProtocolError, decode, encode

    assert len(wire) <= MAX_FRAME
    got = decode(wire)
    assert got == expected
    try:
        again = encode(got)
    except ProtocolError as exc:
        assert exc.cause == "too_large"
        return None
    assert again[0] == VERSION and same_header(again, wire)
    assert decode(again) == got  # the canonical re-encoding is the current version, with the same content
    return again


def as_read_from_v2(frame: Frame) -> Frame:
    """What ``decode(encode_v2(frame))`` must give: DATA's period 0, everything else as sent."""
    p = frame.payload
    if isinstance(p, Data):
        p = dataclasses.replace(p, period=0)
    elif isinstance(p, Bundle):
        p = Bundle(tuple(as_read_from_v2(f) for f in p.frames))
    return Frame(frame.src, frame.dst, frame.origin, frame.seq, p, frame.hops, frame.cost, frame.flags)


def as_read_from_v1(frame: Frame) -> Frame:
    """What ``decode(encode_v1(frame))`` must give: the fields version 2 added at their
    defaults (samples flagged NO_MESH_TIME with index 0, rate 0, no time, boots 0)."""
    p = frame.payload
    if isinstance(p, Data):
        samples = tuple(s._replace(flags=s.flags | SampleFlags.NO_MESH_TIME, index=0) for s in p.samples)
        p = Data(p.mode, samples, p.oversampling, 0, 0)
    elif isinstance(p, Beacon):
        p = dataclasses.replace(p, time=None)
    elif isinstance(p, Hello):
        p = dataclasses.replace(p, boots=0)
    elif isinstance(p, Bundle):
        p = Bundle(tuple(as_read_from_v1(f) for f in p.frames))
    return Frame(frame.src, frame.dst, frame.origin, frame.seq, p, frame.hops, frame.cost, frame.flags)


def same_header(a: bytes, b: bytes) -> bool:
    """Whether two frames' headers agree on everything after the version byte."""
    return a[1:HEADER_LEN] == b[1:HEADER_LEN]

