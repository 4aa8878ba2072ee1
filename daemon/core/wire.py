"""The daemon's one adapter to :mod:`cellbridge.protocol`: bytes in, sorted frames and sample arrays out.

Everything the daemon needs from the wire protocol passes through here (stream
decoding per link, cross-link duplicate removal, reassembly, bundles, command
frames), so a change of the protocol's API touches this module only (and
:mod:`~cellbridge.daemon.core.readout_columns`, its reader of READOUT payloads). Samples
leave as numpy columns at once: per-sample Python objects beyond the decoder would cap
ingest far below 100 000 samples a second; a readout record's samples are never objects.
"""

from __future__ import annotations

import itertools
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np
from cellbridge.daemon.core.readout_columns import ReadoutColumns, readout_columns
from cellbridge.protocol import (
    ADDR_BROADCAST,
    ADDR_HOST,
    MAX_FRAME,
    Beacon,
    BridgeStatus,
    Command,
    CommandReply,
    Data,
    DuplicateFilter,
    Fragment,
    Frame,
    Hello,
    HostReceiver,
    Mode,
    Op,
    Readout,
    Reassembler,
    SampleFlags,
    StreamDecoder,
    encode_stream,
)
from numpy.typing import NDArray

__all__ = ["ADC_MODE", "ADDR_BROADCAST", "Decoded", "HELD", "NO_MESH_TIME", "Ingress", "Mode", "OPS", "OVERFLOW_C1", "OVERFLOW_C2",
           "PART_BYTES", "Readout", "ReadoutColumns", "SampleColumns", "command_bytes", "mode_value"]

#: The protocol's numbers the sample columns carry, as plain ints for numpy.
ADC_MODE = int(Mode.ADC)
OVERFLOW_C1 = int(SampleFlags.OVERFLOW_C1)
OVERFLOW_C2 = int(SampleFlags.OVERFLOW_C2)
#: Sample flags the daemon acts on (docs/protocol.md): a sample without mesh time is timed
#: from its arrival; a held sample (event-based reporting) stands for the frames not sent.
NO_MESH_TIME = int(SampleFlags.NO_MESH_TIME)
HELD = int(SampleFlags.HELD)

#: Bytes a record part takes on a serial line at most: a whole frame, COBS and the delimiters.
PART_BYTES = MAX_FRAME + 3

#: Control parameter names → downlink op. SET_REPORTING is added by the emulator's protocol
#: change; it is offered exactly when the protocol defines it.
OPS: dict[str, Op] = {
    name: op
    for name, op in (
        ("rate", Op.SET_RATE),
        ("mode", Op.SET_MODE),
        ("gate", Op.SET_GATE),
        ("oversampling", Op.SET_OVERSAMPLING),
        ("reporting", getattr(Op, "SET_REPORTING", None)),
    )
    if op is not None
}
PING = Op.PING
MODE_NAMES = {m.name.lower(): m for m in Mode}


def mode_value(value: object) -> int:
    """A mode given by name ('counter', 'adc') or number, as the CMD value."""
    if isinstance(value, str) and value.lower() in MODE_NAMES:
        return int(MODE_NAMES[value.lower()])
    if isinstance(value, int) and not isinstance(value, bool) and value in {int(m) for m in Mode}:
        return value
    raise ValueError(f"mode must be one of {sorted(MODE_NAMES)}, got {value!r}")


@dataclass(slots=True)
class SampleColumns:
    """All samples of one ingest batch, column-wise (one row per sample)."""

    origin: NDArray[np.int64]
    element: NDArray[np.int64]
    cycle: NDArray[np.uint64]
    c1: NDArray[np.int64]
    c2: NDArray[np.int64]
    flags: NDArray[np.int64]
    mode: NDArray[np.int64]
    oversampling: NDArray[np.int64]
    seq: NDArray[np.int64]  # sequence number of the frame each sample came in
    index: NDArray[np.uint64]  # sample index: the skin frame (with NO_MESH_TIME: the bridge's own count)
    rate: NDArray[np.int64]  # sampling rate (Hz) the index counts in; 0: none (protocol version 1)

    def __len__(self) -> int:
        return int(self.origin.shape[0])


@dataclass(slots=True)
class Decoded:
    """What one chunk of bytes from one link held, after dedupe and reassembly."""

    samples: SampleColumns | None = None
    hellos: list[tuple[int, Hello]] = field(default_factory=list)
    boots: list[int] = field(default_factory=list)  # origins whose HELLO is numbered 0: they restarted
    beacons: list[tuple[int, int, Beacon]] = field(default_factory=list)  # (origin, src, beacon)
    statuses: list[tuple[int, BridgeStatus]] = field(default_factory=list)
    replies: list[tuple[int, CommandReply]] = field(default_factory=list)
    frames_by_origin: dict[int, list[int]] = field(default_factory=dict)  # origin -> seqs, arrival order
    gateways: set[int] = field(default_factory=set)  # link-level senders (the gateway bridge)
    # READOUT record parts a gateway wrote itself (origin = link-level sender), in arrival
    # order: (gateway, record part as columns)
    readouts: list[tuple[int, ReadoutColumns]] = field(default_factory=list)
    foreign_readouts: int = 0  # READOUT frames whose origin is not the gateway that wrote them
    ignored: int = 0  # frames the host has no use for (LINK_ACK, CMD heard back)


class Ingress:
    """Per-link stream decoders in front of the protocol's host receive path.

    :class:`~cellbridge.protocol.HostReceiver` reassembles first and filters whole frames
    (bundles opened), the order in which a second gateway's copies make up for the first
    one's losses; the counters it moves during one link's read are charged to that link.
    """

    def __init__(self, dedupe_window: int = 256, reassembly_timeout: float = 2.0) -> None:
        self.decoders: dict[str, StreamDecoder] = {}
        self.receiver = HostReceiver(DuplicateFilter(window=dedupe_window), Reassembler(timeout=reassembly_timeout))
        self.dedupe = self.receiver.dedupe
        self.reassembler = self.receiver.reassembler
        self.duplicates_by_link: dict[str, int] = {}
        self.reassembly_drops: Counter[int] = Counter()  # by origin: drops met handling its fragments

    def decoder(self, link: str) -> StreamDecoder:
        d = self.decoders.get(link)
        if d is None:
            d = self.decoders[link] = StreamDecoder(readout=readout_columns)
            self.duplicates_by_link[link] = 0
        return d

    def reset_link(self, link: str) -> None:
        """A reconnected link starts mid-stream: forget its partial frame, keep its counters."""
        old = self.decoder(link)
        fresh = StreamDecoder(readout=readout_columns)
        fresh.frames_ok, fresh.bytes_ok, fresh.bytes_in = old.frames_ok, old.bytes_ok, old.bytes_in
        fresh.frames_dropped, fresh.bytes_dropped = old.frames_dropped, old.bytes_dropped
        self.decoders[link] = fresh

    def feed(self, link: str, data: bytes, now: float) -> Decoded:
        out = Decoded()
        rows: list[tuple[int, ...]] = []
        meta: list[tuple[int, int, int, int, int, int]] = []  # (origin, mode, oversampling, n, seq, rate)
        dedupe, reassembler, receive = self.dedupe, self.reassembler, self.receiver.receive
        dropped_before = dedupe.duplicates + dedupe.stale
        same_before = self.receiver.readout_same
        decoder = self.decoders.get(link)
        if decoder is None:
            decoder = self.decoder(link)
        by_origin, gateways, route = out.frames_by_origin, out.gateways, self._route
        for frame in decoder.feed(data):
            gateways.add(frame.src)
            if type(frame.payload) is Fragment:
                reassembler.expire(now)  # timeouts first, so a drop below is this bridge's own doing
                before = reassembler.drops.total()
                wholes = receive(frame, now)
                lost = reassembler.drops.total() - before
                if lost:
                    self.reassembly_drops[frame.origin] += lost
            else:
                wholes = receive(frame, now)
            for whole in wholes:
                seqs = by_origin.get(whole.origin)
                if seqs is None:
                    by_origin[whole.origin] = [whole.seq]
                else:
                    seqs.append(whole.seq)
                route(whole, out, rows, meta)
        self.duplicates_by_link[link] += dedupe.duplicates + dedupe.stale - dropped_before
        out.ignored += self.receiver.readout_same - same_before  # (a bridge-to-parent frame: HostReceiver)
        if rows:
            out.samples = _columns(rows, meta)
        return out

    def _route(self, frame: Frame, out: Decoded, rows: list, meta: list) -> None:
        p: Any = frame.payload
        if type(p) is ReadoutColumns or type(p) is Readout:  # (first: a skin on the readout
            # schedule sends little else; a plain one was reassembled or bundled) a gateway
            # writes its own record on its line; one relayed is no gateway's record
            if frame.src == frame.origin:
                out.readouts.append((frame.origin, ReadoutColumns.of(p) if type(p) is Readout else cast(ReadoutColumns, p)))
            else:
                out.foreign_readouts += 1
        elif type(p) is Data:
            rows.extend(p.samples)
            meta.append((frame.origin, int(p.mode), p.oversampling, len(p.samples), frame.seq, p.rate))
        elif type(p) is Hello:
            out.hellos.append((frame.origin, p))
            if frame.seq == 0:  # a bridge numbers from 0 after every reset and says HELLO first
                out.boots.append(frame.origin)
        elif type(p) is Beacon:
            out.beacons.append((frame.origin, frame.src, p))
        elif type(p) is BridgeStatus:
            out.statuses.append((frame.origin, p))
        elif type(p) is CommandReply:
            out.replies.append((frame.origin, p))
        else:
            out.ignored += 1

    def counters(self, link: str) -> dict[str, object]:
        c = self.decoder(link).counters()
        c["duplicates"] = self.duplicates_by_link.get(link, 0)
        return c

    def dedupe_window(self) -> int:
        """Sequence numbers the duplicate filter remembers per bridge: a number further back
        than this is a restart of the bridge's numbering, not a duplicate."""
        return self.dedupe.window

    def expire(self, now: float) -> None:
        """Drop fragments waiting longer than the reassembly timeout (counted as drops)."""
        self.reassembler.expire(now)

    def drops_of(self, bridge: int) -> int:
        """Reassembly drops met handling ``bridge``'s fragments."""
        return self.reassembly_drops.get(bridge, 0)

    def forget(self, bridge: int) -> None:
        """``bridge`` is forgotten: its count of reassembly drops goes with it."""
        self.reassembly_drops.pop(bridge, None)

    def totals(self) -> dict[str, object]:
        """The receive path's counters over every link: reassembly, duplicates, dedupe."""
        return {"reassembly": self.reassembler.counters(), "duplicates": self.dedupe.duplicates,
                "dedupe": self.dedupe.counters()}


def _columns(rows: list[tuple[int, ...]], meta: list[tuple[int, int, int, int, int, int]]) -> SampleColumns:
    a = np.array(rows, dtype=np.uint64).reshape(-1, 6)  # every field is unsigned; cycle and index need 64 bits
    m = np.array(meta, dtype=np.int64)
    counts = m[:, 3]
    return SampleColumns(
        origin=np.repeat(m[:, 0], counts),
        element=a[:, 0].astype(np.int64),
        cycle=a[:, 1],
        c1=a[:, 2].astype(np.int64),
        c2=a[:, 3].astype(np.int64),
        flags=a[:, 4].astype(np.int64),
        mode=np.repeat(m[:, 1], counts),
        oversampling=np.repeat(m[:, 2], counts),
        seq=np.repeat(m[:, 4], counts),
        index=a[:, 5],
        rate=np.repeat(m[:, 5], counts),
    )


_host_seq = itertools.count()


def command_bytes(target: int, token: int, op: Op, value: int | None) -> bytes:
    """Serial-line bytes of one downlink command from the host to ``target`` (or broadcast)."""
    seq = next(_host_seq) & 0xFFFF
    frame = Frame(src=ADDR_HOST, dst=target, origin=ADDR_HOST, seq=seq, payload=Command(token, op, value))
    return encode_stream(frame)


def reply_fields(reply: CommandReply) -> dict[str, object]:
    return {"op": reply.op.name, "status": reply.status.name, "value": reply.value}
