"""The cell medium: who hears a transmission, collisions, loss, bit errors, cuts.

Sans-I/O and clock-free: the caller reports ``start(src, data, cells, tick)`` and,
at the transmission's end tick, calls ``finish(tx)``; the medium returns the
deliveries. A bridge sends a frame on one or more of its cells (a unicast on a cell
it shares with the next hop, a broadcast on all), and every other bridge on those
cells hears it. A bridge has a receiver per cell: two transmissions that overlap in
time on the same cell corrupt each other there (a collision), and a bridge receives
nothing while it transmits (half duplex). A delivery that survives is lost with the
edge's loss probability, and each of its bits flips with the edge's bit-error rate,
independently (the number of flipped bits is binomial: at a high rate, several per
frame, and about one corrupted frame in 65 536 then passes the receiver's CRC-16, as
on a real line: the host must cope with it). Every outcome is counted
(``bit_errors``: corrupted deliveries; ``bits_flipped``); a collision or half-duplex loss
at the bridge a frame was addressed to is also counted as ``collision_at_addressee`` or
``half_duplex_at_addressee`` (the rest are copies overheard by neighbours, lost to no one).
"""

from __future__ import annotations

import math
import random
from collections import Counter
from dataclasses import dataclass, field

from cellbridge.emulator.firmware.transceiver import PREAMBLE_BITS
from cellbridge.emulator.mesh.mesh import Mesh


@dataclass
class Transmission:
    id: int
    src: int
    data: bytes
    start: int
    end: int
    receivers: list[tuple[int, int]]  #: (bridge, cell) that sense it (carrier) and may receive it
    spoiled: dict[tuple[int, int], str] = field(default_factory=dict)  #: (receiver, cell) -> cause
    #: the tick the sender's transceiver started it (its start-of-frame stamp); ``start``
    #: unless a real-time medium heard of it later
    sent: int = -1


class Medium:
    """Deliveries between the bridges of one mesh."""

    def __init__(self, mesh: Mesh, seed: int = 0, bit_cycles: int | None = None) -> None:
        self.mesh = mesh
        self.bit_cycles = bit_cycles if bit_cycles is not None else 50_000_000 // mesh.bitrate
        self._rng = random.Random(seed)
        self.cut: set[int] = set()
        self.dead: set[int] = set()
        self._next_id = 0
        self._tx_end: dict[int, int] = {}  # bridge -> end of its current transmission
        self._rx: dict[tuple[int, int], dict[int, Transmission]] = {
            (b.id, c): {} for b in mesh.bridges for c in b.cells}
        self._cells_of = {b.id: b.cells for b in mesh.bridges}
        self.counters: Counter[str] = Counter()
        self._rebuild()

    def _rebuild(self) -> None:
        cut = frozenset(self.cut)
        self._members = self.mesh.members(cut)
        self._edge = {(a, b, c): self.mesh.link_params(a, b, c)
                      for (a, b), cells in self.mesh.shared_cells(cut).items() for c in cells}

    # -- faults ---------------------------------------------------------------------
    def cut_cell(self, cell: int) -> None:
        self.mesh.cell(cell)
        self.cut.add(cell)
        self._rebuild()

    def restore_cell(self, cell: int) -> None:
        self.cut.discard(cell)
        self._rebuild()

    def kill(self, bridge: int) -> None:
        self.dead.add(bridge)
        self._tx_end.pop(bridge, None)
        for c in self._cells_of[bridge]:
            self._rx[(bridge, c)].clear()

    def revive(self, bridge: int) -> None:
        self.dead.discard(bridge)

    # -- transmissions --------------------------------------------------------------
    def airtime(self, n_bytes: int) -> int:
        return (n_bytes * 8 + PREAMBLE_BITS) * self.bit_cycles

    def start(self, src: int, data: bytes, cells: tuple[int, ...], tick: int, sent: int = -1) -> Transmission:
        """``src`` starts sending ``data`` on ``cells`` at ``tick`` (its transceiver started
        it at ``sent``, by default ``tick``); returns the transmission (its ``receivers``
        should be told the carrier until ``end``)."""
        self._next_id += 1
        tx = Transmission(self._next_id, src, data, tick, tick + self.airtime(len(data)), [],
                          sent=tick if sent < 0 else sent)
        self.counters["transmissions"] += 1
        self.counters["bits"] += len(data) * 8
        if src in self.dead:
            return tx
        self._tx_end[src] = tx.end
        for c in self._cells_of[src]:  # half duplex: sending spoils what src was receiving
            for other in self._rx[(src, c)].values():
                if other.end > tick:
                    other.spoiled.setdefault((src, c), "half_duplex")
        dead, tx_end, rx = self.dead, self._tx_end, self._rx
        for c in cells:
            for r in self._members.get(c, ()):
                if r == src or r in dead:
                    continue
                key = (r, c)
                tx.receivers.append(key)
                if tx_end.get(r, -1) > tick:
                    tx.spoiled[key] = "half_duplex"
                active = rx[key]
                for other in active.values():  # ended ones may await finish() (a real-time caller)
                    if other.end > tick:
                        tx.spoiled[key] = "collision"
                        other.spoiled.setdefault(key, "collision")
                active[tx.id] = tx
        return tx

    def finish(self, tx: Transmission) -> list[tuple[int, int, bytes]]:
        """The deliveries of ``tx`` at its end: (receiver, cell, bytes as received)."""
        out: list[tuple[int, int, bytes]] = []
        got: set[int] = set()
        d = tx.data
        dst = (d[5] << 8 | d[6]) if len(d) > 6 else -1
        if self._tx_end.get(tx.src) == tx.end:
            del self._tx_end[tx.src]
        for key in tx.receivers:
            r, c = key
            if self._rx[key].pop(tx.id, None) is None or r in self.dead:
                self.counters["to_dead"] += 1
                continue
            if r in got:  # heard on another shared cell already: one frame, one delivery
                continue
            cause = tx.spoiled.get(key)
            edge = self._edge.get((tx.src, r, c))
            if cause is None and edge is None:
                cause = "cut"
            if cause is not None:
                self.counters[cause] += 1
                if r == dst:  # spoilt for the bridge it was sent to (not only a copy overheard)
                    self.counters[f"{cause}_at_addressee"] += 1
                continue
            loss, ber = edge  # type: ignore[misc]  # edge is set here: a missing edge made cause 'cut' above
            if loss and self._rng.random() < loss:
                self.counters["lost"] += 1
                continue
            data = tx.data
            if ber:
                data = self._flip(data, ber)
            self.counters["delivered"] += 1
            got.add(r)
            out.append((r, c, data))
        return out

    def _flip(self, data: bytes, ber: float) -> bytes:
        """Each bit flipped with probability ``ber``, independently: the gaps between
        flipped bits are geometric, so a frame costs one draw when it comes through
        clean (the usual case) and one more per flipped bit."""
        n = len(data) * 8
        if ber >= 1.0:
            return bytes(b ^ 0xFF for b in data)
        log_keep = math.log1p(-ber)
        buf: bytearray | None = None
        bit = -1
        while True:
            # bits until the next flip: P(gap = k) = (1 - ber)^k · ber
            bit += 1 + int(math.log(1.0 - self._rng.random()) / log_keep)
            if bit >= n:
                break
            if buf is None:
                buf = bytearray(data)
            buf[bit // 8] ^= 1 << (bit % 8)
            self.counters["bits_flipped"] += 1
        if buf is None:
            return data
        self.counters["bit_errors"] += 1
        return bytes(buf)
