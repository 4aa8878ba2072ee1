"""The datagrams between bridge processes and the medium process.

Bridges and the medium exchange UDP datagrams (loopback by default; the medium's
address may be another host's). One datagram per message, its first byte says what
it is. UDP rather than a message library: at 100 Hz on dozens of bridges the cost
of a message is per wake-up and per system call, and a datagram is one ``send`` and
one ``recv`` with no I/O thread in between (a ZeroMQ message cost ~75 µs of CPU at
the receiver on the development VM, a datagram ~10 µs: ``bench/bench_processes.py``).

Bridge → medium messages carry the sender's id (the medium learns each bridge's
address from them, so a bridge or the medium may restart at any time):

* ``TX``: ``b"t"``, bridge u32, want (``b"1"`` the transceiver still contends after
  this transmission, ``b"0"`` not), start u64 (the tick at which the sender's transceiver
  started the transmission: its MAC-layer timestamp), u8 number of cells, u32 cells, frame;
* ``WANT``: ``b"w"``, bridge u32, ``b"1"`` or ``b"0"`` (contending or not); a bridge
  also sends it at least once a second, so a medium that restarted learns it is there.

Medium → bridge:

* ``CARRIER``: ``b"c"``, cell u32, start u64, end u64 (ticks);
* ``RX``: ``b"r"``, cell u32, start u64 (the sender's start tick, passed on), the frame as
  received.

A receiver takes the sender's start tick as the frame's start-of-frame instant (mesh time
pairs the sender's stamp with the receiver's clock at that instant): the message latency of
the datagrams, hundreds of microseconds and varying, never enters mesh time. Every process
reads the same host clock, so the sender's tick is the receiver's. 0 means "not known"
(the receiver then takes its own arrival tick minus the airtime).

All integers big-endian. A malformed message decodes to None, never an exception.
"""

from __future__ import annotations

import struct

TX, WANT, CARRIER, RX = b"t"[0], b"w"[0], b"c"[0], b"r"[0]
MAX_DATAGRAM = 2048  #: larger than any message (a frame is at most 255 bytes)
_CS = struct.Struct(">cIQQ")
_RX = struct.Struct(">cIQ")
_TX = struct.Struct(">cIcQB")
_WANT = struct.Struct(">cIc")
_CELL = struct.Struct(">I")


def pack_cells(cells: tuple[int, ...]) -> bytes:
    return b"".join(_CELL.pack(c) for c in cells)


def unpack_cells(data: bytes) -> tuple[int, ...]:
    return tuple(_CELL.unpack_from(data, i)[0] for i in range(0, len(data) - len(data) % 4, 4))


def encode_tx(bridge: int, cells: tuple[int, ...], frame: bytes, want: bool, start: int = 0) -> bytes:
    return _TX.pack(b"t", bridge, b"1" if want else b"0", start, len(cells)) + pack_cells(cells) + frame


def decode_tx(msg: bytes) -> tuple[int, tuple[int, ...], bytes, bool, int] | None:
    """(bridge, cells, frame, still contending, start tick), or None for a malformed message."""
    if len(msg) < _TX.size or msg[0] != TX:
        return None
    _, bridge, want, start, n = _TX.unpack_from(msg)
    end = _TX.size + 4 * n
    if n == 0 or len(msg) < end or want not in (b"0", b"1"):
        return None
    return bridge, unpack_cells(msg[_TX.size:end]), msg[end:], want == b"1", start


def encode_want(bridge: int, on: bool) -> bytes:
    return _WANT.pack(b"w", bridge, b"1" if on else b"0")


def decode_want(msg: bytes) -> tuple[int, bool] | None:
    """(bridge, contending), or None for a malformed message."""
    if len(msg) != _WANT.size or msg[0] != WANT:
        return None
    _, bridge, on = _WANT.unpack(msg)
    return (bridge, on == b"1") if on in (b"0", b"1") else None


def sender(msg: bytes) -> int | None:
    """The bridge id a bridge → medium message names, without decoding the rest."""
    return _CELL.unpack_from(msg, 1)[0] if len(msg) >= 5 else None


def encode_carrier(cell: int, start: int, end: int) -> bytes:
    return _CS.pack(b"c", cell, start, end)


def decode_carrier(msg: bytes) -> tuple[int, int, int] | None:
    if len(msg) != _CS.size or msg[0] != CARRIER:
        return None
    _, cell, start, end = _CS.unpack(msg)
    return cell, start, end


def encode_rx(cell: int, frame: bytes, start: int = 0) -> bytes:
    return _RX.pack(b"r", cell, start) + frame


def decode_rx(msg: bytes) -> tuple[int, bytes, int] | None:
    """(cell, frame, the sender's start tick or 0), or None for a malformed message."""
    if len(msg) < _RX.size or msg[0] != RX:
        return None
    _, cell, start = _RX.unpack_from(msg)
    return cell, msg[_RX.size:], start
