"""The messages between bridge processes and the medium process (one ZeroMQ frame each).

Every message is a single ZeroMQ frame whose first byte says what it is (the medium's
ROUTER adds the bridge's identity frame in front). One frame rather than a multipart
message, and the contention state carried inside the transmission that changes it,
because at 100 Hz on dozens of bridges the cost of a message is mostly per frame and
per wake-up of the ZeroMQ I/O threads, not per byte:

* bridge → medium ``TX``: ``b"t"``, want (``b"1"`` the transceiver still contends
  after this transmission, ``b"0"`` not), u8 number of cells, u32 big-endian cells, frame;
* bridge → medium ``WANT``: ``b"w"`` then ``b"1"`` or ``b"0"`` (contending or not);
* medium → bridge ``CARRIER``: ``b"c"``, cell u32, start u64, end u64 (ticks);
* medium → bridge ``RX``: ``b"r"``, cell u32, the frame as received.
"""

from __future__ import annotations

import struct

import zmq

TX, WANT, CARRIER, RX = b"t"[0], b"w"[0], b"c"[0], b"r"[0]
_CS = struct.Struct(">cIQQ")
_RX = struct.Struct(">cI")
_TX = struct.Struct(">ccB")
_CELL = struct.Struct(">I")
WANT_ON, WANT_OFF = b"w1", b"w0"

#: pyzmq flags as plain ints: or-ing its enum flags per message costs microseconds
NOBLOCK = int(zmq.NOBLOCK)
MORE_NOBLOCK = int(zmq.SNDMORE | zmq.NOBLOCK)
EVENTS, POLLIN = int(zmq.EVENTS), int(zmq.POLLIN)


def pack_cells(cells: tuple[int, ...]) -> bytes:
    return b"".join(_CELL.pack(c) for c in cells)


def unpack_cells(data: bytes) -> tuple[int, ...]:
    return tuple(_CELL.unpack_from(data, i)[0] for i in range(0, len(data) - len(data) % 4, 4))


def encode_tx(cells: tuple[int, ...], frame: bytes, want: bool) -> bytes:
    return _TX.pack(b"t", b"1" if want else b"0", len(cells)) + pack_cells(cells) + frame


def decode_tx(msg: bytes) -> tuple[tuple[int, ...], bytes, bool] | None:
    """(cells, frame, still contending), or None for a malformed message."""
    if len(msg) < _TX.size:
        return None
    _, want, n = _TX.unpack_from(msg)
    end = _TX.size + 4 * n
    if n == 0 or len(msg) < end or want not in (b"0", b"1"):
        return None
    return unpack_cells(msg[_TX.size:end]), msg[end:], want == b"1"


def encode_carrier(cell: int, start: int, end: int) -> bytes:
    return _CS.pack(b"c", cell, start, end)


def decode_carrier(msg: bytes) -> tuple[int, int, int] | None:
    if len(msg) != _CS.size:
        return None
    _, cell, start, end = _CS.unpack(msg)
    return cell, start, end


def encode_rx(cell: int, frame: bytes) -> bytes:
    return _RX.pack(b"r", cell) + frame


def decode_rx(msg: bytes) -> tuple[int, bytes] | None:
    if len(msg) < _RX.size:
        return None
    return _RX.unpack_from(msg)[1], msg[_RX.size:]
