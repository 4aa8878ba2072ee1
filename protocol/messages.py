"""Typed payloads of every frame type and their msgpack schema.

Payloads travel as msgpack *arrays* (positional fields), not maps: field names
would cost more bytes than the values on a 1 Mbit/s cell. Every ``from_wire``
checks shape, types and ranges, so a frame that passes :func:`decode` carries a
payload the rest of the system can trust without re-checking.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum
from itertools import repeat
from operator import itemgetter
from typing import TYPE_CHECKING, Any, ClassVar, NamedTuple

import msgpack
from cellbridge.protocol.errors import ProtocolError

if TYPE_CHECKING:
    from cellbridge.protocol.frame import Frame

U8, U16, U32, U64 = 0xFF, 0xFFFF, 0xFFFF_FFFF, 0xFFFF_FFFF_FFFF_FFFF
_I64_MIN, _I64_MAX = -(1 << 63), (1 << 63) - 1  #: a packed sample's signed fields (version 3)
_I64_MIN_NEG = 1 << 63
MAX_FW_VERSION_LEN = 32
MAX_NEIGHBOURS = 32
#: The protocol version :func:`unpack_payload` reads by default and the frame layer writes
#: (``cellbridge.protocol.frame.VERSION``, header byte 0).
VERSION = 4
_FRAGMENT_FLAG = 0x10  # header flag FRAGMENT (frame.Flags imports this module, so not from there)
_NO_MESH_TIME = 0x04  # SampleFlags.NO_MESH_TIME, as a plain int for the hot path
_OVERFLOWS = 0x03  # SampleFlags.OVERFLOW_C1 | OVERFLOW_C2: the flags a readout sample may carry


class FrameType(IntEnum):
    """Frame type codes (header byte 2). Unknown codes are rejected: a type is must-understand."""

    DATA = 1
    BEACON = 2
    HELLO = 3
    STATUS = 4
    CMD = 5
    CMD_REPLY = 6
    LINK_ACK = 7
    BUNDLE = 8
    READOUT = 9  #: version 4: one skin frame of a subtree, every element accounted for
    #: version 4, between bridges only: a READOUT whose every element is unchanged, told as
    #: "the elements of my record ``ref``, unchanged, ``step`` frames later"
    READOUT_SAME = 10


class Mode(IntEnum):
    """How a bridge measured C1 and C2."""

    COUNTER = 0  #: RC self-oscillation edges counted over a gate
    ADC = 1  #: sum of ``oversampling`` 8-bit charge-time conversions


_MODES = tuple(Mode)  # index -> member, cheaper than calling Mode(value)
_new_tuple = tuple.__new__
_first = itemgetter(0)
_LIST, _INT = {list}, {int}  # the one type of every sample, and of every id and code, in a READOUT


class SampleFlags(IntEnum):
    OVERFLOW_C1 = 0x01  #: the 16-bit counter of C1 wrapped during the gate
    OVERFLOW_C2 = 0x02
    #: The bridge had no mesh time at this gate (booting, or cut off from the time root
    #: for too long): ``index`` counts the bridge's own samples, not the skin's frames,
    #: and the host falls back to timing the sample from its arrival.
    NO_MESH_TIME = 0x04
    #: Event-based reporting: until this bridge's next sample, its readings stay within the
    #: reporting threshold of this one; a skin frame it does not send is this reading.
    #: Without the flag (periodic reporting) a frame not sent is a sample lost.
    HELD = 0x08


class Op(IntEnum):
    """Downlink command operations."""

    SET_RATE = 1  #: value: sampling rate in Hz
    SET_MODE = 2  #: value: a :class:`Mode`
    SET_GATE = 3  #: value: counter gate length in clock cycles
    SET_OVERSAMPLING = 4  #: value: ADC conversions per reported sample
    PING = 5  #: value: ignored; the reply carries the bridge's cycle counter
    RESET = 6  #: value: ignored
    SET_REPORTING = 7  #: value: 0 periodic; else threshold (bits 0-31) | heartbeat ms (bits 32-63)


class Status(IntEnum):
    """Result of a command, in :class:`CommandReply`."""

    OK = 0
    BAD_VALUE = 1
    UNSUPPORTED = 2


def _bad(kind: str, detail: str) -> ProtocolError:
    return ProtocolError("payload", f"{kind}: {detail}")


def _uint(value: Any, limit: int, kind: str, name: str) -> int:
    if type(value) is not int or not 0 <= value <= limit:
        raise _bad(kind, f"{name} must be an integer in 0..{limit}, got {value!r}")
    return value


def _array(value: Any, length: int, kind: str) -> list[Any]:
    if type(value) is not list or len(value) != length:
        raise _bad(kind, f"expected an array of {length} fields")
    return value


class Sample(NamedTuple):
    """One measurement of one element: both capacitances from one sampling slot."""

    element: int  #: element index on the reporting bridge (u16)
    cycle: int  #: bridge cycle counter at the start of the C1 gate (u64)
    c1: int  #: counter value (u16) or sum of ADC codes (u32) for C1
    c2: int  #: the same for C2
    flags: int = 0  #: :class:`SampleFlags` bits (u8)
    #: Sample index (u64): the C1 gate started at mesh time ``index / rate`` seconds, so one
    #: index is one instant of the whole skin (a *skin frame*); with ``NO_MESH_TIME`` set,
    #: the bridge's own sample count instead.
    index: int = 0  # type: ignore[assignment]  # the wire's name; it shadows tuple.index, unused here


@dataclass(slots=True)
class Data:
    """A batch of samples from one origin (several per frame to amortise the header).

    Not frozen, like :class:`~cellbridge.protocol.frame.Frame`: it is built once per
    frame on the host's hot path.

    On the wire (version 3, docs/protocol.md §4) the first sample is written as it is and
    every later one *relative to the one before it*: its index step and its cycle's
    residual from the bridge's nominal schedule (``period`` cycles per index step), which
    are one byte each on a periodic bridge instead of 5 and 9. ``samples`` always holds
    the absolute samples: nothing above the protocol layer sees the packing.
    """

    frame_type: ClassVar[FrameType] = FrameType.DATA
    mode: Mode
    samples: tuple[Sample, ...]
    oversampling: int = 1  #: ADC conversions summed into c1/c2 (1 in counter mode)
    #: Sampling rate in Hz (u16) the samples' ``index`` counts in; 0: none (frames of
    #: protocol version 1, which had no index, decode with 0), and the host then times
    #: the samples from their arrival as if each were flagged ``NO_MESH_TIME``.
    rate: int = 0
    #: The bridge's nominal sampling period in its own cycles (u32: ``clock_hz // rate``),
    #: the step the packed cycles are predicted with; any value encodes any samples (it
    #: only changes how many bytes they take), and 0 (frames of versions 1 and 2, which
    #: had none) packs each cycle as its difference from the one before.
    period: int = 0

    def to_wire(self) -> list[Any]:
        return [int(self.mode), self.oversampling, packed_samples(self.samples, self.period), self.rate,
                self.period]

    @classmethod
    def from_wire(cls, obj: Any) -> Data:
        if type(obj) is not list or len(obj) != 5:
            raise _bad("DATA", "expected an array of 5 fields")
        rate, period = obj[3], obj[4]
        if type(rate) is not int or not 0 <= rate <= U16:
            raise _bad("DATA", f"rate must be an integer in 0..{U16}, got {rate!r}")
        if type(period) is not int or not 0 <= period <= U32:
            raise _bad("DATA", f"period must be an integer in 0..{U32}, got {period!r}")
        return cls._parse(obj[0], obj[1], obj[2], 6, rate, period)

    @classmethod
    def from_wire_v2(cls, obj: Any) -> Data:
        """Protocol version 2 (every sample absolute, no period): read as sent, ``period`` 0."""
        if type(obj) is not list or len(obj) != 4:
            raise _bad("DATA", "expected an array of 4 fields")
        rate = obj[3]
        if type(rate) is not int or not 0 <= rate <= U16:
            raise _bad("DATA", f"rate must be an integer in 0..{U16}, got {rate!r}")
        return cls._parse(obj[0], obj[1], obj[2], 6, rate, None)

    @classmethod
    def from_wire_v1(cls, obj: Any) -> Data:
        """Protocol version 1 (no rate, samples without index): samples flagged
        ``NO_MESH_TIME`` with index 0, so old captures still replay."""
        if type(obj) is not list or len(obj) != 3:
            raise _bad("DATA", "expected an array of 3 fields")
        return cls._parse(obj[0], obj[1], obj[2], 5, 0, None)

    @classmethod
    def _parse(cls, mode: Any, over: Any, raw: Any, width: int, rate: int, period: int | None) -> Data:
        """The samples of every version: all absolute (versions 1 and 2, ``period`` None), or
        the first absolute and the later ones packed (version 3, :func:`packed_sample`)."""
        # The host's hottest path: checks are inlined and samples built with
        # tuple.__new__ (a NamedTuple's own constructor costs twice as much).
        # The ranges depend on the mode, so a decoded sample is one the chip could produce.
        if mode == 0 and type(mode) is int:
            if over != 1 or type(over) is not int:
                raise _bad("DATA", f"oversampling must be 1 in counter mode, got {over!r}")
            limit = U16  # 16-bit counter register
        elif mode == 1 and type(mode) is int:
            if type(over) is not int or not 1 <= over <= U16:
                raise _bad("DATA", f"oversampling must be an integer in 1..{U16}, got {over!r}")
            limit = U8 * over  # sum of `over` 8-bit codes
        else:
            raise _bad("DATA", f"unknown mode {mode!r}")
        if type(raw) is not list:
            raise _bad("DATA", "samples must be an array")
        samples: list[Sample] = []
        append = samples.append
        rest = iter(raw)
        for s in rest:  # every sample of versions 1 and 2; the first of version 3
            if type(s) is not list or len(s) != width:
                raise _bad("DATA", "a sample is [element, cycle, c1, c2, flags, index]" if width == 6
                           else "a version 1 sample is [element, cycle, c1, c2, flags]")
            e, cyc, c1, c2, fl = s[0], s[1], s[2], s[3], s[4]
            if not (
                type(e) is int and type(cyc) is int and type(c1) is int and type(c2) is int and type(fl) is int
                and 0 <= e <= U16 and 0 <= cyc <= U64 and 0 <= c1 <= limit and 0 <= c2 <= limit and 0 <= fl <= U8
            ):
                raise _bad("DATA", f"sample field out of range for {_MODES[mode].name} mode "
                                   f"(c1, c2 at most {limit}): {s!r}")
            if width == 6:
                k = s[5]
                if type(k) is not int or not 0 <= k <= U64:
                    raise _bad("DATA", f"sample index must be an integer in 0..{U64}, got {k!r}")
                append(_new_tuple(Sample, s))
            else:
                append(_new_tuple(Sample, (e, cyc, c1, c2, fl | _NO_MESH_TIME, 0)))
            if period is not None:
                break
        if period is None:
            return cls(_MODES[mode], tuple(samples), over, rate)
        for s in rest:  # version 3's packed samples, from the first's cyc and k: the periodic
            # case (step 1) and the wrap modulo 2^64 (rare) taken apart, for fewer big-integer
            # operations per sample
            if type(s) is not list or len(s) != 6:
                raise _bad("DATA", "a packed sample is [element, residual, c1, c2, flags, step]")
            e, r, c1, c2, fl, dk = s
            if not (
                type(e) is int and type(r) is int and type(c1) is int and type(c2) is int and type(fl) is int
                and type(dk) is int and 0 <= e <= U16 and 0 <= c1 <= limit and 0 <= c2 <= limit and 0 <= fl <= U8
                and _I64_MIN <= r <= _I64_MAX and _I64_MIN <= dk <= _I64_MAX
            ):
                raise _bad("DATA", f"packed sample field out of range for {_MODES[mode].name} mode "
                                   f"(c1, c2 at most {limit}; residual, step signed 64-bit): {s!r}")
            if dk == 1:
                k += 1
                cyc += period + r
            else:
                k += dk
                cyc += dk * period + r
            if not 0 <= cyc <= U64:
                cyc &= U64
            if not 0 <= k <= U64:
                k &= U64
            append(_new_tuple(Sample, (e, cyc, c1, c2, fl, k)))
        return cls(_MODES[mode], tuple(samples), over, rate, period)


def _wrap64(x: int) -> int:
    """``x`` modulo 2⁶⁴ as a signed 64-bit integer (two's complement), -2⁶³..2⁶³-1."""
    return ((x + _I64_MIN_NEG) & U64) - _I64_MIN_NEG


def packed_sample(prev: Sample | None, s: Sample, period: int) -> list[int]:
    """The version 3 wire form of ``s`` in a DATA frame after ``prev`` (None: the first).

    The first sample is ``[element, cycle, c1, c2, flags, index]`` as it is; a later one
    ``[element, residual, c1, c2, flags, step]`` with ``step = index - prev.index`` and
    ``residual = cycle - (prev.cycle + step * period)``, both modulo 2⁶⁴ as signed 64-bit
    integers (what a chip's u64 arithmetic gives for free): a periodic bridge's step is 1
    and its residual its crystal's drift over one period plus mesh-time corrections, each
    a one-byte msgpack fixint. Wrapping makes every sequence of samples encodable (an
    index that restarts at 0, a cycle counter at its limit) in exactly one way; the
    decoder adds modulo 2⁶⁴, so a rebuilt cycle and index are always in their u64 range.
    """
    if prev is None:
        return list(s)
    step = _wrap64(s[5] - prev[5])
    return [s[0], _wrap64(s[1] - prev[1] - step * period), s[2], s[3], s[4], step]


def packed_samples(samples: tuple[Sample, ...] | list[Sample], period: int) -> list[list[int]]:
    """The version 3 wire form of a DATA frame's samples (:func:`packed_sample` of each)."""
    out = []
    prev = None
    for s in samples:
        out.append(packed_sample(prev, s, period))
        prev = s
    return out


@dataclass(frozen=True, slots=True)
class MeshTime:
    """The time part of a BEACON (docs/time.md): the sender's estimate of the mesh's
    global time, taken at the cycle its transmission started (the transceiver stamps it
    then, not when the beacon was queued), and which flood of the root it descends from."""

    root: int  #: the time root's bridge id (u16): the lowest-id gateway that is alive
    seq: int  #: the root's round number this estimate descends from (u16, wraps)
    time: int  #: global time in cycles of the root's clock at the start of the frame (u64)

    def to_wire(self) -> list[int]:
        return [self.root, self.seq, self.time]

    @classmethod
    def from_wire(cls, obj: Any) -> MeshTime:
        r, q, t = _array(obj, 3, "BEACON")
        return cls(_uint(r, U16, "BEACON", "root"), _uint(q, U16, "BEACON", "time seq"),
                   _uint(t, U64, "BEACON", "time"))


@dataclass(frozen=True, slots=True)
class Beacon:
    """Collection-routing advertisement: "my parent is X, my path cost to the sink is Y"."""

    frame_type: ClassVar[FrameType] = FrameType.BEACON
    parent: int  #: the sender's parent bridge id (0 = the sender is a gateway)
    path_etx: int  #: path cost to the sink in tenths of an expected transmission (u16)
    hops: int  #: hops to the sink (u8)
    time: MeshTime | None = None  #: the sender's mesh time (None: it has none to pass on)

    def to_wire(self) -> list[Any]:
        return [self.parent, self.path_etx, self.hops, None if self.time is None else self.time.to_wire()]

    @classmethod
    def from_wire(cls, obj: Any) -> Beacon:
        p, etx, hops, t = _array(obj, 4, "BEACON")
        return cls(_uint(p, U16, "BEACON", "parent"), _uint(etx, U16, "BEACON", "path_etx"),
                   _uint(hops, U8, "BEACON", "hops"), None if t is None else MeshTime.from_wire(t))

    @classmethod
    def from_wire_v1(cls, obj: Any) -> Beacon:
        p, etx, hops = _array(obj, 3, "BEACON")
        return cls.from_wire([p, etx, hops, None])


@dataclass(frozen=True, slots=True)
class Hello:
    """A bridge announcing itself after reset and on request."""

    frame_type: ClassVar[FrameType] = FrameType.HELLO
    bridge: int  #: bridge id (u16)
    firmware: str  #: firmware version, at most 32 UTF-8 bytes
    x: float  #: element centre, metres, in the skin's frame
    y: float
    side: float  #: element side length, metres
    clock_hz: int  #: nominal clock frequency (u32)
    capabilities: int = 0  #: bit mask (u32); bit 0: ADC mode, bit 1: counter mode
    #: Boot counter (u32), kept in the chip's non-volatile memory and raised at every
    #: power-on or reset: a restart is known from evidence, not guessed from numbering.
    #: 0 in version 1 frames (which had none).
    boots: int = 0

    def to_wire(self) -> list[Any]:
        return [self.bridge, self.firmware, [float(self.x), float(self.y), float(self.side)],
                self.clock_hz, self.capabilities, self.boots]

    @classmethod
    def from_wire(cls, obj: Any) -> Hello:
        fields = _array(obj, 6, "HELLO")
        hello = cls.from_wire_v1(fields[:5])
        return cls(hello.bridge, hello.firmware, hello.x, hello.y, hello.side, hello.clock_hz,
                   hello.capabilities, _uint(fields[5], U32, "HELLO", "boots"))

    @classmethod
    def from_wire_v1(cls, obj: Any) -> Hello:
        b, fw, geo, clk, caps = _array(obj, 5, "HELLO")
        if type(fw) is not str or len(fw.encode()) > MAX_FW_VERSION_LEN:
            raise _bad("HELLO", f"firmware must be a string of at most {MAX_FW_VERSION_LEN} bytes")
        geo = _array(geo, 3, "HELLO")
        if not all(type(g) is float and math.isfinite(g) for g in geo) or geo[2] <= 0.0:
            raise _bad("HELLO", "geometry must be [x, y, side] finite floats with side > 0")
        return cls(_uint(b, U16, "HELLO", "bridge"), fw, geo[0], geo[1], geo[2],
                   _uint(clk, U32, "HELLO", "clock_hz"), _uint(caps, U32, "HELLO", "capabilities"))


@dataclass(frozen=True, slots=True)
class Neighbour:
    bridge: int  #: neighbour id (u16)
    link_etx: int  #: link cost in tenths of an expected transmission (u16)


@dataclass(frozen=True, slots=True)
class BridgeStatus:
    """A bridge's routing state and health counters, sent periodically to the host."""

    frame_type: ClassVar[FrameType] = FrameType.STATUS
    parent: int
    path_etx: int
    neighbours: tuple[Neighbour, ...]
    queue_drops: int  #: frames dropped because a queue was full (u32)
    retries: int  #: link retransmissions (u32)
    resets: int  #: resets since power-on (u32)
    uptime_cycles: int  #: cycles since the last reset (u64)

    def to_wire(self) -> list[Any]:
        return [self.parent, self.path_etx, [[n.bridge, n.link_etx] for n in self.neighbours],
                self.queue_drops, self.retries, self.resets, self.uptime_cycles]

    @classmethod
    def from_wire(cls, obj: Any) -> BridgeStatus:
        p, etx, nb, qd, rt, rs, up = _array(obj, 7, "STATUS")
        if type(nb) is not list or len(nb) > MAX_NEIGHBOURS:
            raise _bad("STATUS", f"neighbours must be an array of at most {MAX_NEIGHBOURS}")
        neighbours = tuple(
            Neighbour(_uint(n[0], U16, "STATUS", "neighbour"), _uint(n[1], U16, "STATUS", "link_etx"))
            for n in (_array(n, 2, "STATUS") for n in nb)
        )
        return cls(_uint(p, U16, "STATUS", "parent"), _uint(etx, U16, "STATUS", "path_etx"), neighbours,
                   _uint(qd, U32, "STATUS", "queue_drops"), _uint(rt, U32, "STATUS", "retries"),
                   _uint(rs, U32, "STATUS", "resets"), _uint(up, U64, "STATUS", "uptime_cycles"))


def _optional_value(value: Any, kind: str) -> int | None:
    if value is None:
        return None
    return _uint(value, U64, kind, "value")


@dataclass(frozen=True, slots=True)
class Command:
    """A downlink command from the host to one bridge (or all, with the broadcast address)."""

    frame_type: ClassVar[FrameType] = FrameType.CMD
    token: int  #: chosen by the host, echoed in the reply (u16)
    op: Op
    value: int | None = None

    def to_wire(self) -> list[Any]:
        return [self.token, int(self.op), self.value]

    @classmethod
    def from_wire(cls, obj: Any) -> Command:
        tok, op, val = _array(obj, 3, "CMD")
        if type(op) is not int or op not in Op._value2member_map_:
            raise _bad("CMD", f"unknown op {op!r}")
        return cls(_uint(tok, U16, "CMD", "token"), Op(op), _optional_value(val, "CMD"))


@dataclass(frozen=True, slots=True)
class CommandReply:
    """A bridge's answer to a :class:`Command`."""

    frame_type: ClassVar[FrameType] = FrameType.CMD_REPLY
    token: int
    op: Op
    status: Status
    value: int | None = None

    def to_wire(self) -> list[Any]:
        return [self.token, int(self.op), int(self.status), self.value]

    @classmethod
    def from_wire(cls, obj: Any) -> CommandReply:
        tok, op, st, val = _array(obj, 4, "CMD_REPLY")
        if type(op) is not int or op not in Op._value2member_map_:
            raise _bad("CMD_REPLY", f"unknown op {op!r}")
        if type(st) is not int or st not in Status._value2member_map_:
            raise _bad("CMD_REPLY", f"unknown status {st!r}")
        return cls(_uint(tok, U16, "CMD_REPLY", "token"), Op(op), Status(st), _optional_value(val, "CMD_REPLY"))


@dataclass(frozen=True, slots=True)
class LinkAck:
    """Per-hop acknowledgement of the link transmission (origin, seq) from the acked frame."""

    frame_type: ClassVar[FrameType] = FrameType.LINK_ACK
    origin: int
    seq: int

    def to_wire(self) -> list[Any]:
        return [self.origin, self.seq]

    @classmethod
    def from_wire(cls, obj: Any) -> LinkAck:
        o, s = _array(obj, 2, "LINK_ACK")
        return cls(_uint(o, U16, "LINK_ACK", "origin"), _uint(s, U16, "LINK_ACK", "seq"))


@dataclass(frozen=True, slots=True)
class Bundle:
    """Several frames for the same next hop in one link transmission (forwarder aggregation).

    Inner frames are complete frames (own header and CRC) of the bundle's own protocol
    version (a forwarder bundles what it relays, and relays only its own version); a
    bundle never holds a bundle.
    """

    frame_type: ClassVar[FrameType] = FrameType.BUNDLE
    frames: tuple[Frame, ...]

    def to_wire(self) -> list[Any]:
        from cellbridge.protocol.frame import Fragment, encode

        for f in self.frames:
            if isinstance(f.payload, Fragment):
                raise ProtocolError("bundle", "a bundle carries whole frames, not fragments")
            if f.type is FrameType.BUNDLE:
                raise ProtocolError("nested_bundle", "a bundle cannot contain a bundle")
        return [encode(f) for f in self.frames]

    @classmethod
    def from_wire(cls, obj: Any, version: int = VERSION) -> Bundle:
        """The bundle of a frame of protocol ``version``: its inner frames must be of that
        version too (cause ``bundle``), or a bundle would have two encodings (``encode``
        writes every inner frame in today's version) and an older version's bundle could
        carry a type that version did not have."""
        from cellbridge.protocol.frame import decode

        if type(obj) is not list or not obj:
            raise _bad("BUNDLE", "expected a non-empty array of frames")
        frames = []
        for i, raw in enumerate(obj):
            if type(raw) is not bytes:
                raise _bad("BUNDLE", "each bundled frame is a bin")
            if len(raw) > 2 and raw[2] == FrameType.BUNDLE:
                raise ProtocolError("nested_bundle", "a bundle cannot contain a bundle")
            if len(raw) > 1 and raw[1] & _FRAGMENT_FLAG:
                raise ProtocolError("bundle", f"bundled frame {i} is a fragment; a bundle carries whole frames")
            try:
                frames.append(decode(raw))
            except ProtocolError as exc:  # the inner frame's fault, not the bundle's: say so
                raise ProtocolError(f"inner_{exc.cause}", f"bundled frame {i}: {exc.detail}") from None
            if raw[0] != version:  # a sound frame, but not one a forwarder of this version bundles
                raise ProtocolError("bundle", f"bundled frame {i} is version {raw[0]} in a version {version} bundle")
        return cls(tuple(frames))


def _readout_lists(raw: list[Any], unchanged: list[Any], missing: list[Any],
                   limit: int) -> tuple[tuple[ReadoutSample, ...], tuple[int, ...], tuple[int, ...]] | None:
    """A READOUT's samples, unchanged and missing lists when every check of
    :meth:`Readout.from_wire` passes, in a few C-level passes over the columns rather than
    a Python step per element (a thousand elements a frame, a hundred frames a second);
    None when any check fails, and the element-by-element validation then names what.
    Every id of the three lists is an int once (one set of them all as long as the lists
    together), so each list is strictly increasing when it is in order. A record of
    at most :data:`_FEW` samples (every record on a cell) is checked in one Python pass
    instead, the same checks: the column passes' fixed cost is larger there."""
    if len(raw) <= _FEW:
        return _few_readout_lists(raw, unchanged, missing, limit)
    return _column_readout_lists(raw, unchanged, missing, limit)


def _column_readout_lists(raw: list[Any], unchanged: list[Any], missing: list[Any],
                          limit: int) -> tuple[tuple[ReadoutSample, ...], tuple[int, ...], tuple[int, ...]] | None:
    """:func:`_readout_lists` in C-level passes over the columns."""
    if raw:
        if set(map(type, raw)) != _LIST:
            return None
        try:  # lists of four each: rows of unequal lengths, or of another length, raise
            b, c1, c2, fl = zip(*raw, strict=True)
        except ValueError:
            return None
        ids = [*b, *unchanged, *missing]
        if {*map(type, ids), *map(type, c1), *map(type, c2), *map(type, fl)} != _INT:
            return None
        if not (min(c1) >= 0 and max(c1) <= limit and min(c2) >= 0 and max(c2) <= limit
                and min(fl) >= 0 and max(fl) <= _OVERFLOWS):
            return None
    else:
        ids = [*unchanged, *missing]
        if ids and set(map(type, ids)) != _INT:
            return None
    if len(set(ids)) != len(ids):
        return None  # a bridge twice: in two states, or twice in one list
    for ordered in (ids[:len(raw)], unchanged, missing):
        if ordered and (ordered[0] < 0 or ordered[-1] > U16 or ordered != sorted(ordered)):
            return None
    return tuple(map(_new_tuple, repeat(ReadoutSample, len(raw)), raw)), tuple(unchanged), tuple(missing)


#: Samples up to which a READOUT's lists are checked in one Python pass rather than in
#: column passes: measured faster at every size up to 40 (1 sample: 0.5 µs against 3.7;
#: 16: 7.7 against 9.3), and a bridge reads records of one sample (a leaf's) most.
_FEW = 16


def _few_readout_lists(raw: list[Any], unchanged: list[Any], missing: list[Any],
                       limit: int) -> tuple[tuple[ReadoutSample, ...], tuple[int, ...], tuple[int, ...]] | None:
    """:func:`_readout_lists` (the same checks, the same answer) in one pass over the
    entries: each list strictly increasing within 0..U16 and no bridge in two."""
    samples = []
    last = -1
    for s in raw:
        if type(s) is not list or len(s) != 4:
            return None
        b, c1, c2, fl = s
        if not (type(b) is int and type(c1) is int and type(c2) is int and type(fl) is int
                and last < b and 0 <= c1 <= limit and 0 <= c2 <= limit and 0 <= fl <= _OVERFLOWS):
            return None
        last = b
        samples.append(_new_tuple(ReadoutSample, s))
    if last > U16:
        return None
    if unchanged or missing:
        for ids in (unchanged, missing):
            last = -1
            for b in ids:
                if type(b) is not int or not last < b:
                    return None
                last = b
            if last > U16:
                return None
        # each list is strictly increasing (no id twice in one): a bridge in two is in two
        # lists, found by C-level set tests (a list of them all, and a set of it, took twice
        # as long: an event-based record holds some fifty unchanged ids)
        sampled = set(map(_first, raw))
        if not sampled.isdisjoint(unchanged):
            return None
        if missing and not (sampled.isdisjoint(missing) and set(missing).isdisjoint(unchanged)):
            return None
    return tuple(samples), tuple(unchanged), tuple(missing)


def _readout_lists_checked(raw: list[Any], unchanged: list[Any], missing: list[Any],
                           limit: int) -> tuple[tuple[ReadoutSample, ...], tuple[int, ...], tuple[int, ...]]:
    """What :func:`_readout_lists` gives, element by element: the first element that fails
    a check is named in the :class:`ProtocolError`."""
    samples = []
    last = -1
    for s in raw:
        if type(s) is not list or len(s) != 4:
            raise _bad("READOUT", "a sample is [bridge, c1, c2, flags]")
        b, c1, c2, fl = s
        if not (type(b) is int and type(c1) is int and type(c2) is int and type(fl) is int
                and last < b <= U16 and 0 <= c1 <= limit and 0 <= c2 <= limit and 0 <= fl <= _OVERFLOWS):
            raise _bad("READOUT", f"sample out of range or out of order (bridges increasing, c1, c2 at most "
                                  f"{limit}, flags overflow bits only): {s!r}")
        last = b
        samples.append(_new_tuple(ReadoutSample, s))
    seen = {s[0] for s in samples}
    lists = []
    for name, ids in (("unchanged", unchanged), ("missing", missing)):
        last = -1
        for b in ids:
            if type(b) is not int or not last < b <= U16:
                raise _bad("READOUT", f"{name} must be strictly increasing bridge ids, got {b!r}")
            if b in seen:
                raise _bad("READOUT", f"bridge {b} is in two states of one frame")
            last = b
        seen.update(ids)
        lists.append(tuple(ids))
    return tuple(samples), lists[0], lists[1]


class ReadoutSample(NamedTuple):
    """One element's sample of a skin frame, in a :class:`Readout` (its element is the
    bridge's element 0, its time the frame's: ``index / rate`` on mesh time)."""

    bridge: int  #: the bridge that sampled it (u16)
    c1: int  #: counter value (u16) or sum of ADC codes for C1, in the record's mode
    c2: int
    flags: int = 0  #: :class:`SampleFlags` bits (u8); the overflow bits only


@dataclass(frozen=True, slots=True)
class Readout:
    """One skin frame as a subtree read it out (protocol version 4, docs/protocol.md §4).

    A bridge on the readout schedule sends, for every frame ``index``, one record holding
    its own element and every element of its subtree, each exactly once, in one of three
    states: a *sample* (``samples``: periodic, or event-based and changed), *unchanged*
    (``unchanged``: event-based, within the reporting threshold of the last sample it
    sent; a bit, not a sample) or *missing* (``missing``: its slot stayed empty after the
    retry, or its sample was not taken). A record too large for one frame, or holding
    samples of two modes, is sent as ``parts`` frames numbered ``part`` 0..parts-1, each
    with its own disjoint elements: a gateway's record of frame ``index`` is complete once
    all its parts arrived, and then it says what the host knows of every element routed
    through that gateway. ``span_us``: the schedule's readout length, from the frame's
    gate start to the end of the slots that filled this record (the host's deadline for
    the frame builds on it). Every list is strictly increasing by bridge id, and a bridge
    appears in one list of one part only (checked across the parts by the host).
    """

    frame_type: ClassVar[FrameType] = FrameType.READOUT
    index: int  #: the skin frame (u64): its gates started at mesh time index / rate
    rate: int  #: Hz the index counts in (u16, > 0)
    mode: Mode
    oversampling: int
    samples: tuple[ReadoutSample, ...]
    unchanged: tuple[int, ...] = ()
    missing: tuple[int, ...] = ()
    span_us: int = 0  #: readout length of the schedule (u32, microseconds)
    part: int = 0  #: this frame's number among the record's parts (u8)
    parts: int = 1  #: frames the record is made of (u8, >= 1)
    #: the time root whose mesh time ``index`` counts (u16; 0: not said). Skins not joined
    #: by any cell (two limbs, each with its gateways) keep two unrelated mesh times.
    root: int = 0
    #: µs of mesh time from the frame's gate start to when a gateway began writing this part
    #: on its serial line (u32; 0: not said, as on a cell). A record goes as soon as it is
    #: complete, so its arrival alone tells the host when the frame was sampled only to
    #: within the frame's whole readout; with its age, to within the serial line's delay.
    age_us: int = 0
    #: On a cell only: frames back to the last whole record the sender had acknowledged by
    #: this parent, when all it sent the parent since were READOUT_SAMEs (u8, 1 …
    #: :data:`SAME_STEP_MAX`; 0: not said). Those carried no sample, so a parent that lost
    #: some of them still holds every element of that record as its sender last sent it,
    #: and an *unchanged* here refers to that (:meth:`FrameReadout.child`).
    ref_step: int = 0

    def to_wire(self) -> list[Any]:
        wire = [self.index, self.rate, int(self.mode), self.oversampling,
                [list(s) for s in self.samples], list(self.unchanged), list(self.missing),
                self.span_us, self.part, self.parts, self.root]
        if self.ref_step:
            wire += (self.age_us, self.ref_step)
        elif self.age_us:
            wire.append(self.age_us)
        return wire

    @classmethod
    def from_wire(cls, obj: Any) -> Readout:
        root = age = step = 0
        n = len(obj) if type(obj) is list else -1
        if n == 10:  # a record written before the root was carried
            k, rate, mode, over, raw, unchanged, missing, span, part, parts = obj
        elif n == 12:  # a gateway's, with its age
            k, rate, mode, over, raw, unchanged, missing, span, part, parts, root, age = obj
            _uint(root, U16, "READOUT", "root")
            if type(age) is not int or not 1 <= age <= U32:  # (0 is said by leaving it out)
                raise _bad("READOUT", f"age_us must be an integer in 1..{U32}, got {age!r}")
        elif n == 13:  # with the step back to its reference (a bridge's, to its parent)
            k, rate, mode, over, raw, unchanged, missing, span, part, parts, root, age, step = obj
            _uint(root, U16, "READOUT", "root")
            _uint(age, U32, "READOUT", "age_us")
            if type(step) is not int or not 1 <= step <= SAME_STEP_MAX:
                raise _bad("READOUT", f"ref_step must be an integer in 1..{SAME_STEP_MAX}, got {step!r}")
        else:
            k, rate, mode, over, raw, unchanged, missing, span, part, parts, root = _array(obj, 11, "READOUT")
            _uint(root, U16, "READOUT", "root")
        _uint(k, U64, "READOUT", "index")
        if type(rate) is not int or not 1 <= rate <= U16:
            raise _bad("READOUT", f"rate must be an integer in 1..{U16}, got {rate!r}")
        _uint(span, U32, "READOUT", "span_us")
        if type(parts) is not int or not 1 <= parts <= U8:
            raise _bad("READOUT", f"parts must be an integer in 1..{U8}, got {parts!r}")
        if type(part) is not int or not 0 <= part < parts:
            raise _bad("READOUT", f"part must be an integer in 0..{parts - 1}, got {part!r}")
        if type(mode) is not int or mode not in (0, 1):
            raise _bad("READOUT", f"unknown mode {mode!r}")
        if mode == 0:
            if over != 1 or type(over) is not int:
                raise _bad("READOUT", f"oversampling must be 1 in counter mode, got {over!r}")
            limit = U16
        else:
            if type(over) is not int or not 1 <= over <= U16:
                raise _bad("READOUT", f"oversampling must be an integer in 1..{U16}, got {over!r}")
            limit = U8 * over
        if type(raw) is not list or type(unchanged) is not list or type(missing) is not list:
            raise _bad("READOUT", "samples, unchanged and missing must be arrays")
        lists = _readout_lists(raw, unchanged, missing, limit) or _readout_lists_checked(raw, unchanged, missing,
                                                                                       limit)
        return cls(k, rate, _MODES[mode], over, lists[0], lists[1], lists[2], span, part, parts, root, age, step)

    def bridges(self) -> int:
        """How many elements the record accounts for."""
        return len(self.samples) + len(self.unchanged) + len(self.missing)


@dataclass(frozen=True, slots=True)
class ReadoutSame:
    """A bridge's READOUT of one frame in which every element it accounts for is unchanged,
    told relative to an earlier record of its that its parent acknowledged (``ref``): "frame
    ``ref.index + step``: every element of record ``ref``, unchanged; rate, mode,
    oversampling, span and root as in ``ref``". It goes to the parent only (never on a
    serial line), unacknowledged: an idle skin's records were mostly a header, the record's
    own fields and a LINK_ACK around a one-byte id (docs/protocol.md §4). The parent rebuilds
    the whole :class:`Readout` from the record it holds, or, holding no record that matches
    ``ref``, drops it: the elements are then missing in that frame, never unchanged.

    ``step``: frames after the referenced record's (1-127: a bridge sends a whole record at
    least every 128 frames, so a parent that lost its copy waits that long at most).
    ``ref``: the low 7 bits of the referenced record's frame ``seq`` (a check that the
    parent's copy is the one meant)."""

    frame_type: ClassVar[FrameType] = FrameType.READOUT_SAME
    step: int
    ref: int

    def to_wire(self) -> list[Any]:
        return [self.step, self.ref]

    @classmethod
    def from_wire(cls, obj: Any) -> ReadoutSame:
        step, ref = _array(obj, 2, "READOUT_SAME")
        if type(step) is not int or not 1 <= step <= SAME_STEP_MAX:
            raise _bad("READOUT_SAME", f"step must be an integer in 1..{SAME_STEP_MAX}, got {step!r}")
        if type(ref) is not int or not 0 <= ref <= SAME_REF_MASK:
            raise _bad("READOUT_SAME", f"ref must be an integer in 0..{SAME_REF_MASK}, got {ref!r}")
        return cls(step, ref)

    def rebuild(self, ref: Readout) -> Readout:
        """The whole record this one stands for, given the record ``ref`` it refers to (the
        caller checked ``ref``'s seq): every element ``ref`` listed, unchanged."""
        ids = sorted((*(s.bridge for s in ref.samples), *ref.unchanged, *ref.missing))
        return Readout(ref.index + self.step, ref.rate, ref.mode, ref.oversampling, (), tuple(ids), (),
                       ref.span_us, 0, 1, ref.root)


#: A READOUT_SAME's largest ``step`` (a msgpack fixint: its payload is 3 bytes)
SAME_STEP_MAX = 127
#: A READOUT_SAME's ``ref``: this many low bits of the referenced record's ``seq``
SAME_REF_MASK = 0x7F


Message = Data | Beacon | Hello | BridgeStatus | Command | CommandReply | LinkAck | Bundle | Readout | ReadoutSame

MESSAGE_CLASSES: dict[int, type[Any]] = {
    cls.frame_type: cls
    for cls in (Data, Beacon, Hello, BridgeStatus, Command, CommandReply, LinkAck, Bundle, Readout, ReadoutSame)
}


_pack = msgpack.Packer(use_bin_type=True).pack
_BUNDLE_TYPE = int(FrameType.BUNDLE)  # plain int: comparing with an enum member costs more per frame


def pack_payload(message: Message) -> bytes:
    """msgpack bytes of a message's wire form: the canonical encoding (smallest int, array,
    str and bin forms; floats as float64), the only one :func:`unpack_payload` accepts."""
    return _pack(message.to_wire())


#: Parsers of the payloads whose layout an older protocol version had otherwise
#: (docs/protocol.md §3): old captures still decode, into today's messages (the fields a later
#: version added at their defaults). Version 1 had DATA, BEACON and HELLO shorter; version 2
#: wrote every DATA sample absolute.
_OLD_PARSERS: dict[int, dict[int, Any]] = {
    1: {FrameType.DATA: Data.from_wire_v1, FrameType.BEACON: Beacon.from_wire_v1, FrameType.HELLO: Hello.from_wire_v1},
    2: {FrameType.DATA: Data.from_wire_v2},
    3: {},  # version 4 only added READOUT (and READOUT_SAME): every version 3 payload reads as today's
}


def unpack_payload(frame_type: int, data: bytes, version: int = VERSION) -> Message:
    """Parse and validate a payload of protocol ``version``; any malformation becomes
    :class:`ProtocolError`.

    Only the canonical encoding is accepted (``pack_payload(unpack_payload(x)) == x`` for
    the current version): one message has exactly one byte string, so byte-level duplicate
    detection and caches see one frame as one frame.
    """
    try:
        obj = msgpack.unpackb(data)
    except Exception as exc:  # msgpack raises several unrelated types on bad input
        raise ProtocolError("payload", f"not valid msgpack ({type(exc).__name__})") from None
    try:
        canonical = _pack(obj) == data
    except Exception as exc:  # e.g. a map with keys msgpack cannot pack back
        raise ProtocolError("payload", f"not packable ({type(exc).__name__})") from None
    if not canonical:
        raise ProtocolError("payload", "not the canonical msgpack encoding (smallest forms, float64)")
    try:
        if version != VERSION:
            old = _OLD_PARSERS[version].get(frame_type)
            if old is not None:
                return old(obj)
        if frame_type == _BUNDLE_TYPE:
            return Bundle.from_wire(obj, version)
        return MESSAGE_CLASSES[frame_type].from_wire(obj)
    except ProtocolError:
        raise
    except (ValueError, TypeError, IndexError) as exc:  # e.g. unpacking a short array
        raise ProtocolError("payload", f"{FrameType(frame_type).name}: {exc}") from None
