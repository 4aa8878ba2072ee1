"""Hand-crafted gateway traffic for daemon tests and benchmarks: frames a test chooses.

:class:`GridFrames` writes the frames of a skin of bridges on a grid (one element each,
ids from 1, the emulator's ``meshgen.grid`` geometry) that a test wants one by one:
HELLO, BEACON, command replies, DATA samples of a sampling slot, and READOUT records
with the unchanged, missing bridges and the split into parts a test chooses. It is not a
second model of the skin: what a press does to the elements is the emulator's one world
model (:class:`cellbridge.emulator.world.world.World` holding the press as a static contact:
its capacitances, band ghosts included), counted by the chip's transfer function; a
READOUT record a test does not split by hand is the firmware's own
(:func:`cellbridge.emulator.firmware.readout.record_parts`), framed as the gateway frames it (as
:meth:`cellbridge.emulator.mesh.skin_traffic.SkinTraffic.frame` does). For a whole skin's
scheduled traffic frame after frame, use :class:`~cellbridge.emulator.mesh.skin_traffic.SkinTraffic`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from cellbridge.emulator.firmware.readout import record_parts
from cellbridge.emulator.mesh import meshgen
from cellbridge.emulator.world.world import Contact, World
from cellbridge.protocol import (
    ADDR_HOST,
    Beacon,
    CommandReply,
    Data,
    Frame,
    Hello,
    Message,
    Mode,
    Op,
    Readout,
    ReadoutSample,
    Sample,
    Status,
    encode_stream,
    own,
    reframe,
    to_serial,
)
from cellbridge.tactile import ChipParams, counts

CLOCK = 50_000_000

Press = tuple[float, float, float, float]  #: a static press: x, y (m), force (N), diameter (m)


@dataclass
class GridFrames:
    """Frames of a ``rows`` x ``cols`` grid skin, gateway ``gateway``, sampling ``rate`` slots a second.

    Counter values jitter from call to call (a random oscillator phase, seed 7), as a
    chip's do; everything else is deterministic."""

    rows: int = 2
    cols: int = 2
    rate: float = 100.0  # sampling slots per second
    gateway: int = 1
    chip: ChipParams = field(default_factory=ChipParams)
    cycle0: int = 1_000_000

    def __post_init__(self) -> None:
        self.world = World(meshgen.grid(self.rows, self.cols, gateways=(self.gateway,)))
        self.layout = self.world.layout  # ids from 1, row-major, on the mesh's pitch
        self.params = self.world.params
        self.seq = {int(b): 0 for b in self.layout.ids}
        self.rng = np.random.default_rng(7)

    @property
    def ids(self) -> list[int]:
        return [int(b) for b in self.layout.ids]

    def _frame(self, origin: int, payload: Message) -> bytes:
        seq = self.seq[origin]
        self.seq[origin] = (seq + 1) & 0xFFFF
        return encode_stream(Frame(src=self.gateway, dst=0, origin=origin, seq=seq, payload=payload,
                                   hops=0 if origin == self.gateway else 1))

    def hellos(self) -> bytes:
        return b"".join(
            self._frame(b, Hello(b, "test-1", float(self.layout.centres[i, 0]), float(self.layout.centres[i, 1]),
                                 float(self.layout.side), CLOCK, 3))
            for i, b in enumerate(self.ids)
        )

    def beacons(self) -> bytes:
        return b"".join(self._frame(b, Beacon(0 if b == self.gateway else self.gateway, 0 if b == self.gateway
                                              else 10, 0 if b == self.gateway else 1)) for b in self.ids)

    def capacitances(self, press: Press | None) -> tuple[np.ndarray, np.ndarray]:
        """(C1, C2) of every element (in ``ids`` order) under a static ``press`` or none: the world's."""
        self.world.set_contacts([] if press is None else [Contact(0.0, math.inf, *press)])
        return self.world.capacitances(0.0)

    def counts_for(self, press: Press | None, phase: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Counter values (C1, C2) of every element for a press (x, y, F, D) or none."""
        c1, c2 = self.capacitances(press)
        ph = self.rng.uniform(0, 1, (2, self.layout.n)) if phase is None else phase
        k1, _ = counts(c1, self.chip, ph[0])
        k2, _ = counts(c2, self.chip, ph[1])
        return k1, k2

    def slot(self, k: int, press: Press | None = None,
             per_frame: int = 1) -> bytes:
        """One sampling slot: every bridge's sample (``per_frame`` slots batched per frame)."""
        k1, k2 = self.counts_for(press)
        cyc = self.cycle0 + int(k * CLOCK / self.rate)
        return b"".join(
            self._frame(b, Data(Mode.COUNTER, tuple(Sample(0, cyc + j, int(k1[i]), int(k2[i]), 0)
                                                    for j in range(per_frame))))
            for i, b in enumerate(self.ids)
        )

    def stream(self, n_slots: int, press: Press | None = None,
               start: int = 0) -> Iterator[tuple[int, bytes]]:
        for k in range(start, start + n_slots):
            yield k, self.slot(k, press)

    def readout(self, k: int, press: Press | None = None, gateway: int | None = None,
                bridges: list[int] | None = None, unchanged: tuple[int, ...] = (), missing: tuple[int, ...] = (),
                span_us: int = 4000, parts: int | None = None) -> bytes:
        """``gateway``'s READOUT record of skin frame ``k`` (mesh time ``k / rate``), accounting
        for ``bridges`` (default: every bridge): each a sample of ``press``, except those
        ``unchanged`` or ``missing``. Split as the firmware splits a record
        (:func:`~cellbridge.emulator.firmware.readout.record_parts`: one frame while it fits), or, with
        ``parts``, into that many frames with the bridges dealt among them in turn (a split
        a test chooses). Framed as the gateway frames its own record, COBS on the line."""
        gw = self.gateway if gateway is None else gateway
        ids = self.ids if bridges is None else sorted(bridges)
        k1, k2 = self.counts_for(press)
        col = {b: i for i, b in enumerate(self.ids)}

        def samples(group: list[int]) -> tuple[ReadoutSample, ...]:
            return tuple(ReadoutSample(b, int(k1[col[b]]), int(k2[col[b]]), 0) for b in group
                         if b not in unchanged and b not in missing)

        if parts is None:
            records = record_parts(k, int(self.rate), {(Mode.COUNTER, 1): (
                list(samples(ids)), [b for b in ids if b in unchanged], [b for b in ids if b in missing])}, span_us)
        else:
            groups = [ids[i::parts] for i in range(parts)]
            records = [Readout(k, int(self.rate), Mode.COUNTER, 1, samples(group),
                               tuple(b for b in group if b in unchanged), tuple(b for b in group if b in missing),
                               span_us, part, parts) for part, group in enumerate(groups)]
        out = b""
        for rec in records:
            seq = self.seq.setdefault(gw, 0)
            self.seq[gw] = (seq + 1) & 0xFFFF
            out += to_serial(reframe(own(rec, gw, seq), gw, ADDR_HOST))  # as the gateway's firmware emits it
        return out

    def reply(self, origin: int, token: int, op: Op, value: int | None = None) -> bytes:
        return self._frame(origin, CommandReply(token, op, Status.OK, value))


def staggered(sk: GridFrames, n_slots: int, press: Press, on: int, off: int,
              max_delay: float, per_frame: int = 1, seed: int = 3) -> list[tuple[float, bytes]]:
    """(arrival time from 0, one DATA frame) of every bridge, sorted by arrival: the skin
    as it reaches a host for real. Each bridge samples at its own phase within a slot and
    sees ``press`` in slots ``on`` ≤ k < ``off`` of its own sampling; it sends
    ``per_frame`` samples a frame, which arrives 0..``max_delay`` s after its last sample
    (a bridge's frames never overtake each other)."""
    rng = np.random.default_rng(seed)
    period = 1.0 / sk.rate
    phase = rng.uniform(0.0, 1.0, sk.layout.n)
    quiet, pressed = sk.counts_for(None), sk.counts_for(press)
    frames: list[tuple[float, bytes]] = []
    for i, b in enumerate(sk.ids):
        last = 0.0
        for k0 in range(0, n_slots, per_frame):
            samples = []
            for k in range(k0, min(k0 + per_frame, n_slots)):
                k1, k2 = pressed if on <= k < off else quiet
                samples.append(Sample(0, sk.cycle0 + int((k + phase[i]) * period * CLOCK), int(k1[i]), int(k2[i]), 0))
            t = (k + phase[i]) * period
            last = max(last, t + rng.uniform(0.0, max_delay))
            frames.append((last, sk._frame(b, Data(Mode.COUNTER, tuple(samples)))))
    frames.sort(key=lambda f: f[0])
    return frames
