"""Frames as a relay handles them: header fields plus the payload bytes, never parsed.

A forwarding bridge needs the header (who, which sequence number, how many hops)
and a good CRC; the payload is the host's business. Keeping the payload as the
bytes that arrived saves a msgpack decode and re-encode per hop, which is most of
the cost of a mesh in virtual time. The layout is the one of docs/protocol.md §2 and
of :mod:`cellbridge.protocol.frame` (the same header ``struct``);
:func:`cellbridge.protocol.decode` remains the validating parser (the host's, and a
bridge's for the frames it acts on: beacons, commands, acknowledgements).
"""

from __future__ import annotations

import struct
from typing import NamedTuple

from cellbridge.protocol.crc import crc16
from cellbridge.protocol.frame import CRC_LEN, HEADER, HEADER_LEN, MAX_FRAME, MIN_FRAME, VERSION
from cellbridge.protocol.messages import FrameType, Message, pack_payload
from cobs import cobs

_CRC = struct.Struct(">H")
# Header bytes a radio's address filter reads (docs/protocol.md §2): type, link destination.
_TYPE_AT = 2
_DST_AT = 5


class Raw(NamedTuple):
    """A frame's header fields and its body bytes (fragment fields and payload), unparsed."""

    type: int
    flags: int  #: every flag bit, must-understand ones (FRAGMENT) included
    origin: int
    seq: int
    hops: int
    cost: int
    body: bytes  #: everything between header and CRC (fragment fields and payload)


_FOR_ALL = frozenset({int(FrameType.BEACON), int(FrameType.CMD)})  # every bridge that hears them reads them


def addressed_to(data: bytes, bridge: int) -> bool:
    """Whether ``bridge`` should read a frame it hears, from the header bytes alone (the
    address filter of a radio: the type and the link destination)."""
    return (len(data) <= _DST_AT + 1 or data[_TYPE_AT] in _FOR_ALL
            or (data[_DST_AT] << 8 | data[_DST_AT + 1]) == bridge)


def peek(data: bytes) -> tuple[int, int, Raw] | None:
    """(src, dst, frame) of wire bytes, or None when the CRC, length or version is wrong."""
    n = len(data)
    if n < MIN_FRAME or n > MAX_FRAME or crc16(data[:-CRC_LEN]) != (data[-2] << 8 | data[-1]):
        return None
    ver, flags, ftype, src, dst, origin, seq, hops, cost = HEADER.unpack_from(data)
    if ver != VERSION:
        return None
    return src, dst, Raw(ftype, flags, origin, seq, hops, cost, data[HEADER_LEN:-CRC_LEN])


def reframe(f: Raw, src: int, dst: int, extra_flags: int = 0) -> bytes:
    """Wire bytes of ``f`` sent on by ``src`` to ``dst`` (a new header and CRC, the same body)."""
    body = HEADER.pack(VERSION, f.flags | extra_flags, f.type, src, dst, f.origin, f.seq, f.hops, f.cost) + f.body
    return body + _CRC.pack(crc16(body))


def own(message: Message, origin: int, seq: int) -> Raw:
    """A new frame created by ``origin`` (not fragmented)."""
    return Raw(int(message.frame_type), 0, origin, seq, 0, 0, pack_payload(message))


def to_serial(data: bytes) -> bytes:
    """Serial-line bytes of one frame: 00 cobs(frame) 00 (docs/protocol.md §8)."""
    return b"\x00" + cobs.encode(data) + b"\x00"
