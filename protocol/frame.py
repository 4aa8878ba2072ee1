"""The frame: one format on the cell and on the serial line.

Layout (big-endian; docs/protocol.md is the normative text)::

    0  version   u8    = 4 (1 to 3 are still read: docs/protocol.md §3)
    1  flags     u8    bits 0-3 optional, bits 4-7 must-understand
    2  type      u8    FrameType
    3  src       u16   link source (bridge id that transmitted this hop)
    5  dst       u16   link destination (0x0000 host/sink, 0xFFFF broadcast)
    7  origin    u16   bridge that created the datagram
    9  seq       u16   per-origin sequence number, one per frame sent
    11 hops      u8    hops travelled so far
    12 cost      u16   accumulated path cost, tenths of an expected transmission
    [14 tag u16, offset u16, total u16]   only when flags has FRAGMENT
    .. payload   msgpack (or a slice of one when fragmented)
    -2 crc       u16   CRC-16/CCITT-FALSE over everything before it

A frame is at most :data:`MAX_FRAME` bytes so that a cell transmission stays short
(255 bytes = 2 ms at 1 Mbit/s) and a receiver's buffers are fixed; larger
datagrams are fragmented (:mod:`cellbridge.protocol.fragment`).
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass
from enum import IntFlag
from typing import Any

from cellbridge.protocol.crc import crc16
from cellbridge.protocol.errors import ProtocolError
from cellbridge.protocol.messages import (
    MESSAGE_CLASSES,
    U16,
    VERSION,
    FrameType,
    Message,
    pack_payload,
    unpack_payload,
)

#: Versions :func:`decode` reads: frames of versions 1 to 3 decode into today's messages,
#: with the fields later versions added at their defaults (old captures replay);
#: :func:`encode` writes :data:`VERSION` (4).
READ_VERSIONS = frozenset({1, 2, 3, 4})
#: The first version that has each frame type; older versions did not know it (a frame of
#: that type and an older version is dropped as an unknown type).
_SINCE = {int(FrameType.READOUT): 4, int(FrameType.READOUT_SAME): 4}
#: The frame types each version has: one lookup per decoded frame checks version and type.
_TYPES_OF = {v: frozenset(t for t in MESSAGE_CLASSES if _SINCE.get(t, 0) <= v) for v in READ_VERSIONS}
MAX_FRAME = 255  #: whole frame, header to CRC, before COBS
MAX_DATAGRAM = 4096  #: largest fragmented datagram (payload and its 2-byte checksum)
DATAGRAM_CRC_LEN = 2  #: CRC-16 of the payload, ending every fragmented datagram
ADDR_HOST = 0x0000  #: the host (sink) behind every gateway
ADDR_BROADCAST = 0xFFFF

_HEADER = struct.Struct(">BBBHHHHBH")
HEADER = _HEADER  #: the header's layout (version, flags, type, src, dst, origin, seq, hops, cost)
_FRAG = struct.Struct(">HHH")
_CRC = struct.Struct(">H")
HEADER_LEN = _HEADER.size  # 14
FRAG_LEN = _FRAG.size  # 6
CRC_LEN = _CRC.size  # 2
MIN_FRAME = HEADER_LEN + CRC_LEN


class Flags(IntFlag):
    """Header flags. Bits 0-3 may be ignored by a receiver that does not know them;
    bits 4-7 are must-understand: a receiver that does not know one set drops the frame."""

    ACK_REQUEST = 0x01  #: the sender wants a LINK_ACK for this hop
    FRAGMENT = 0x10  #: fragment fields follow the header; the payload is a slice


OPTIONAL_MASK = 0x0F
MUST_UNDERSTAND_MASK = 0xF0
_FRAGMENT = int(Flags.FRAGMENT)  # plain int: IntFlag arithmetic is slow on the decode path
_UNKNOWN_MUST_UNDERSTAND = MUST_UNDERSTAND_MASK & ~_FRAGMENT
_BUNDLE = int(FrameType.BUNDLE)
_HELLO = int(FrameType.HELLO)
_READOUT = int(FrameType.READOUT)


@dataclass(frozen=True, slots=True)
class Fragment:
    """The payload of a fragment frame: a slice of the msgpack bytes of one datagram."""

    frame_type: FrameType  #: type of the whole datagram
    tag: int  #: datagram tag, unique per origin among datagrams in flight (u16)
    offset: int  #: byte offset of ``data`` in the datagram
    total: int  #: length of the whole datagram's payload
    data: bytes
    #: Protocol version of the datagram the slice belongs to (header byte 0): a slice of a
    #: version 1 datagram holds version 1 payload bytes, so it is relayed as version 1 and
    #: its datagram is parsed as one (docs/protocol.md §3).
    version: int = VERSION


@dataclass(slots=True)
class Frame:
    """One frame: link header fields plus a typed payload (or a :class:`Fragment`).

    Not frozen, because a frozen dataclass costs twice as much to build and the
    host decodes hundreds of thousands of frames a second; treat it as a value
    all the same (forwarders build a new frame with the next hop's fields).
    """

    src: int
    dst: int
    origin: int
    seq: int
    payload: Message | Fragment
    hops: int = 0
    cost: int = 0
    flags: int = 0  #: optional flags (FRAGMENT is implied by the payload, never set here)

    @property
    def type(self) -> FrameType:
        return self.payload.frame_type


def check_origin(origin: int, payload: Message) -> None:
    """A HELLO is its origin announcing itself: a HELLO naming another bridge contradicts its
    header (geometry filed under one id, the restart under another), so it is refused."""
    if payload.frame_type == _HELLO and payload.bridge != origin:  # type: ignore[union-attr]  # frame_type HELLO: the payload is a Hello
        raise ProtocolError("payload", f"HELLO: bridge {payload.bridge} is not the frame's origin {origin}")  # type: ignore[union-attr]  # frame_type HELLO: the payload is a Hello


def _check_u(value: int, limit: int, name: str) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= limit:
        raise ProtocolError("field", f"{name} must be an integer in 0..{limit}, got {value!r}")


def encode(frame: Frame) -> bytes:
    """Frame to wire bytes (no COBS), version :data:`VERSION`; a fragment keeps its own
    datagram's version (its slice is that version's bytes). Raises :class:`ProtocolError`
    for a frame that cannot be sent: a field out of range or a payload too large for one
    frame."""
    for name, limit in (("src", U16), ("dst", U16), ("origin", U16), ("seq", U16), ("hops", 0xFF),
                        ("cost", U16)):
        _check_u(getattr(frame, name), limit, name)
    _check_u(frame.flags, OPTIONAL_MASK, "flags (optional bits only)")
    p = frame.payload
    if isinstance(p, Fragment):
        _check_u(p.tag, U16, "tag")
        if not (0 <= p.offset and p.offset + len(p.data) <= p.total <= MAX_DATAGRAM and p.data):
            raise ProtocolError("fragment", "fragment must be a non-empty slice within total <= MAX_DATAGRAM")
        if p.frame_type == _BUNDLE:
            raise ProtocolError("fragment", "a bundle is never fragmented")
        if p.version not in READ_VERSIONS:
            raise ProtocolError("version", f"fragment of version {p.version}; versions are {sorted(READ_VERSIONS)}")
        if p.version < _SINCE.get(p.frame_type, 0):  # what decode would drop: never written
            raise ProtocolError("type", f"frame type {p.frame_type} did not exist in version {p.version}")
        head = _HEADER.pack(p.version, frame.flags | _FRAGMENT, p.frame_type, frame.src, frame.dst,
                            frame.origin, frame.seq, frame.hops, frame.cost)
        body = head + _FRAG.pack(p.tag, p.offset, p.total) + p.data
    else:
        if type(p) not in MESSAGE_CLASSES.values():
            raise ProtocolError("payload", f"not a message: {type(p).__name__}")
        check_origin(frame.origin, p)
        head = _HEADER.pack(VERSION, frame.flags, p.frame_type, frame.src, frame.dst, frame.origin,
                            frame.seq, frame.hops, frame.cost)
        body = head + pack_payload(p)
    if len(body) + CRC_LEN > MAX_FRAME:
        raise ProtocolError("too_large", f"frame of {len(body) + CRC_LEN} bytes exceeds {MAX_FRAME}; fragment it")
    return body + _CRC.pack(crc16(body))


def decode(data: bytes | bytearray | memoryview, readout: Callable[[bytes], Any] | None = None) -> Frame:
    """Wire bytes (no COBS) to a validated :class:`Frame`.

    Raises only :class:`ProtocolError`; its ``cause`` names what was wrong
    (``short``, ``too_large``, ``crc``, ``version``, ``must_understand``, ``type``,
    ``fragment``, ``payload``, ``nested_bundle``, ``bundle``, and ``inner_<cause>``
    for a bundled frame that fails). Reads every version in :data:`READ_VERSIONS`.
    Only the canonical encoding of a frame is accepted: ``encode(decode(x)) == x`` for a
    version 4 frame and for a fragment of any version; a whole frame of versions 1 to 3
    decodes into today's message (the fields later versions added at their defaults),
    which ``encode`` writes as version 4: ``decode(encode(decode(x))) == decode(x)``. A
    frame type newer than the frame's version (READOUT before version 4) is ``type``.

    ``readout``: a reader of a whole current-version READOUT payload that gives its own
    form of the record, or None to leave the payload to :func:`unpack_payload` (a reader
    that gives a value for a payload must give it only where ``unpack_payload`` decodes
    that payload, and be the same record: the daemon reads its records into columns).
    """
    n = len(data)
    if n < MIN_FRAME:
        raise ProtocolError("short", f"{n} bytes, a frame has at least {MIN_FRAME}")
    if n > MAX_FRAME:
        raise ProtocolError("too_large", f"{n} bytes, a frame has at most {MAX_FRAME}")
    if type(data) is not bytes:
        data = bytes(data)
    if crc16(data):  # a frame followed by its big-endian CRC-16/CCITT-FALSE leaves a residue of 0
        raise ProtocolError("crc", "CRC mismatch")
    ver, flags, ftype, src, dst, origin, seq, hops, cost = _HEADER.unpack_from(data)
    types = _TYPES_OF.get(ver)
    if types is None:
        raise ProtocolError("version", f"version {ver} not supported (this reads {sorted(READ_VERSIONS)})")
    if flags & _UNKNOWN_MUST_UNDERSTAND:
        raise ProtocolError("must_understand", f"unknown must-understand flags 0x{flags:02x}")
    if ftype not in types:
        raise ProtocolError("type", f"unknown frame type {ftype} in version {ver}")
    payload: Message | Fragment
    if flags & _FRAGMENT:
        if n < MIN_FRAME + FRAG_LEN + 1:
            raise ProtocolError("fragment", "fragment frame too short")
        tag, offset, total = _FRAG.unpack_from(data, HEADER_LEN)
        chunk = data[HEADER_LEN + FRAG_LEN:-CRC_LEN]
        if offset + len(chunk) > total or total > MAX_DATAGRAM:
            raise ProtocolError("fragment", f"slice {offset}+{len(chunk)} outside datagram of {total} bytes")
        if ftype == _BUNDLE:
            raise ProtocolError("fragment", "a bundle is never fragmented")
        payload = Fragment(FrameType(ftype), tag, offset, total, chunk, ver)
    else:
        body = data[HEADER_LEN:-CRC_LEN]
        fast = readout(body) if readout is not None and ftype == _READOUT and ver == VERSION else None
        payload = fast if fast is not None else unpack_payload(ftype, body, ver)
        if ftype == _HELLO:
            check_origin(origin, payload)
    return Frame(src, dst, origin, seq, payload, hops, cost, flags & OPTIONAL_MASK)
