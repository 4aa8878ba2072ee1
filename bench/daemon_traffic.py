"""Synthesized gateway traffic for daemon tests and benchmarks (no emulator).

A skin of bridges (one element each, ids from 1) on a grid; each sampling slot every
bridge reports its element's counter values for the capacitances a chosen press gives
(``cellbridge.tactile.skin_response`` + the chip's transfer function), in DATA frames
built with ``cellbridge.protocol``.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from cellbridge.protocol import (
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
)
from cellbridge.tactile import ChipParams, ElementParams, counts, grid_layout, skin_response

CLOCK = 50_000_000


@dataclass
class Skin:
    rows: int = 2
    cols: int = 2
    rate: float = 100.0  # sampling slots per second
    gateway: int = 1
    chip: ChipParams = field(default_factory=ChipParams)
    cycle0: int = 1_000_000

    def __post_init__(self) -> None:
        self.layout = grid_layout(self.rows, self.cols, first_id=1)
        self.params = ElementParams(side=self.layout.side)
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

    def counts_for(self, press: tuple[float, float, float, float] | None, phase: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Counter values (C1, C2) of every element for a press (x, y, F, D) or none."""
        n = self.layout.n
        if press is None:
            d1 = d2 = np.zeros(n)
        else:
            d1, d2 = skin_response(self.layout, [press], self.params)
        ph = self.rng.uniform(0, 1, (2, n)) if phase is None else phase
        k1, _ = counts(self.params.C1_rest + d1, self.chip, ph[0])
        k2, _ = counts(self.params.C2_rest + d2, self.chip, ph[1])
        return k1, k2

    def slot(self, k: int, press: tuple[float, float, float, float] | None = None,
             per_frame: int = 1) -> bytes:
        """One sampling slot: every bridge's sample (``per_frame`` slots batched per frame)."""
        k1, k2 = self.counts_for(press)
        cyc = self.cycle0 + int(k * CLOCK / self.rate)
        return b"".join(
            self._frame(b, Data(Mode.COUNTER, tuple(Sample(0, cyc + j, int(k1[i]), int(k2[i]), 0)
                                                    for j in range(per_frame))))
            for i, b in enumerate(self.ids)
        )

    def stream(self, n_slots: int, press: tuple[float, float, float, float] | None = None,
               start: int = 0) -> Iterator[tuple[int, bytes]]:
        for k in range(start, start + n_slots):
            yield k, self.slot(k, press)

    def readout(self, k: int, press: tuple[float, float, float, float] | None = None, gateway: int | None = None,
                bridges: list[int] | None = None, unchanged: tuple[int, ...] = (), missing: tuple[int, ...] = (),
                span_us: int = 4000, parts: int = 1) -> bytes:
        """``gateway``'s READOUT record of skin frame ``k`` (mesh time ``k / rate``), accounting
        for ``bridges`` (default: every bridge): each a sample of ``press``, except those
        ``unchanged`` or ``missing``; in ``parts`` frames (the bridges split among them)."""
        gw = self.gateway if gateway is None else gateway
        ids = self.ids if bridges is None else sorted(bridges)
        k1, k2 = self.counts_for(press)
        col = {b: i for i, b in enumerate(self.ids)}
        groups = [ids[i::parts] for i in range(parts)]
        out = b""
        for part, group in enumerate(groups):
            samples = tuple(ReadoutSample(b, int(k1[col[b]]), int(k2[col[b]]), 0) for b in group
                            if b not in unchanged and b not in missing)
            rec = Readout(k, int(self.rate), Mode.COUNTER, 1, samples, tuple(b for b in group if b in unchanged),
                          tuple(b for b in group if b in missing), span_us, part, parts)
            seq = self.seq.setdefault(gw, 0)
            self.seq[gw] = (seq + 1) & 0xFFFF
            out += encode_stream(Frame(src=gw, dst=0, origin=gw, seq=seq, payload=rec))
        return out

    def reply(self, origin: int, token: int, op: Op, value: int | None = None) -> bytes:
        return self._frame(origin, CommandReply(token, op, Status.OK, value))



def staggered(sk: Skin, n_slots: int, press: tuple[float, float, float, float], on: int, off: int,
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
