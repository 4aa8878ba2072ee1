"""How much of each cell's airtime the readout schedule takes: whether a skin can carry
its frames at a sampling rate before it is run.

Every frame, each bridge on the readout sends one record of its subtree to its parent
(periodic: a sample per element), acknowledged by the parent; a record larger than a
frame goes in parts, each with its header, acknowledgement and gaps. A bridge's radio
sends on all its cells at once, so every transmission of a bridge takes the airtime of
each of its cells. Where one cell carries more than its frame period of that (many
bridges on one cell: a star), records collide and miss their slots, and the host lists
their elements missing frame after frame: honest, but the skin is mostly unknown. This
module estimates the load from the mesh alone, so that ``cellbridge mesh check`` and
``mesh up`` say so first.

The estimate is a lower bound of the cells' work: the routing tree is the shortest one
(each bridge's parent the lowest id one hop nearer a gateway), every record goes once
(no retries, no collisions) and beacons, HELLOs and commands are left out. A load near
or above 1 does not fit; well below, the schedule has room for retries.
"""

from __future__ import annotations

from dataclasses import dataclass

from cellbridge.emulator.firmware.readout import _fits, _part, _split
from cellbridge.emulator.firmware.transceiver import PREAMBLE_BITS, TransceiverConfig
from cellbridge.emulator.mesh.mesh import Mesh
from cellbridge.protocol import CRC_LEN, HEADER_LEN, Mode, Readout, ReadoutSample
from cellbridge.protocol.messages import pack_payload

#: Bytes of a LINK_ACK frame on a cell (header, its fields and CRC).
ACK_BYTES = 24
#: A load above this is reported as not fitting (the schedule also needs room to retry).
FITS_BELOW = 0.9


def ack_bits(tc: TransceiverConfig | None = None) -> int:
    """Airtime of one acknowledgement, in bits: the turnaround before it, its preamble and frame."""
    tc = tc or TransceiverConfig()
    return 8 * ACK_BYTES + PREAMBLE_BITS + tc.sifs_bits


def record_frames(samples: int, rate: int, tc: TransceiverConfig | None = None) -> tuple[int, int]:
    """Airtime of one periodic record of ``samples`` samples at ``rate`` Hz on its sender's
    cells, in bits (each part's idle gap before it, preamble, header, payload and CRC), and
    its parts (each acknowledged by the parent, :func:`ack_bits`). Counts as large as a
    skin's (c1 and c2 near 2**20) are assumed, so that the payload is not underestimated."""
    tc = tc or TransceiverConfig()
    r = Readout(10**6, rate, Mode.COUNTER, 1,
                tuple(ReadoutSample(b, 1 << 20, 1 << 20, 0) for b in range(1, samples + 1)), (), (), 100_000)
    parts = _split(r)
    return sum(_frame_bits(p, tc) for p in parts), len(parts)


def _frame_bits(part: Readout, tc: TransceiverConfig) -> int:
    return 8 * (HEADER_LEN + CRC_LEN + len(pack_payload(part))) + PREAMBLE_BITS + tc.difs_bits


def records_frames(sizes: set[int], rate: int, tc: TransceiverConfig | None = None) -> dict[int, tuple[int, int]]:
    """:func:`record_frames` of records of each of ``sizes`` samples, the same answers,
    without splitting each record anew. A record is split greedily (each part the longest
    run of the samples left that fits a frame), and its samples are those of the largest
    record's first ones: so its parts are the largest record's, up to the one it ends in,
    cut there. Splitting each record whole packs its samples again and again (quadratic in
    its size, per record): the subtrees of a long line are of every size, and a mesh of a
    thousand bridges took a minute before ``mesh check`` printed."""
    tc = tc or TransceiverConfig()
    if not sizes:
        return {}
    top = max(sizes)
    whole = Readout(10**6, rate, Mode.COUNTER, 1,
                    tuple(ReadoutSample(b, 1 << 20, 1 << 20, 0) for b in range(1, top + 1)), (), (), 100_000)
    items: list[tuple[str, object]] = [("s", s) for s in whole.samples]

    def fits(first: int, n: int) -> bool:
        return _fits(_part(whole, items[first:first + n]))

    ends = [0]  # the largest record's parts: samples [ends[k], ends[k + 1])
    while ends[-1] < top:
        first, rest = ends[-1], top - ends[-1]
        good, bad, probe = 1, rest + 1, 2  # one sample a part at least (_split's)
        while probe <= rest:  # galloping, then bisection: the longest run that fits
            if not fits(first, probe):
                bad = probe
                break
            good, probe = probe, 2 * probe
        else:
            if good < rest and fits(first, rest):
                good = rest
            elif good < rest:
                bad = rest
        while bad - good > 1:
            mid = (good + bad) // 2
            if fits(first, mid):
                good = mid
            else:
                bad = mid
        ends.append(first + good)
    done = [0]  # bits of the largest record's first k parts
    for a, b in zip(ends, ends[1:]):
        done.append(done[-1] + _frame_bits(_part(whole, items[a:b]), tc))
    out: dict[int, tuple[int, int]] = {}
    k = 0
    alone = True  # whether the records so far fit a frame whole (a longer one fits no better)
    for n in sorted(sizes):
        if alone:
            r = Readout(whole.index, rate, Mode.COUNTER, 1, whole.samples[:n], (), (), whole.span_us)
            if n < 1 or _fits(r):  # a record that fits one frame goes whole, as itself
                out[n] = (_frame_bits(r, tc), 1)
                continue
            alone = False
        while ends[k + 1] < n:
            k += 1
        out[n] = (done[k] + _frame_bits(_part(whole, items[ends[k]:n]), tc), k + 1)
    return out


@dataclass(frozen=True)
class CellLoad:
    """The readout's share of each cell's airtime at one rate (``load``: cell id -> bits a
    frame over the bits a frame period holds), the busiest cell, and the bridges no
    gateway reaches (they send no record)."""

    rate: int
    load: dict[int, float]
    busiest: int | None
    unreached: tuple[int, ...]

    @property
    def peak(self) -> float:
        """The busiest cell's load (0 for a mesh without cells)."""
        return self.load[self.busiest] if self.busiest is not None else 0.0

    @property
    def fits(self) -> bool:
        """Whether every cell carries its readout with room to spare (below ``FITS_BELOW``)."""
        return self.peak < FITS_BELOW


def readout_load(mesh: Mesh, rate: int, acked: bool = True) -> CellLoad:
    """Each cell's share of airtime the periodic readout takes at ``rate`` Hz (see the module);
    ``acked``: the records are acknowledged hop by hop (the firmware's default; the
    real-time shells send them once). Raises ValueError for a rate that is not positive."""
    if rate <= 0:
        raise ValueError(f"readout load: rate must be positive, got {rate}")
    hops = mesh.hops()
    nb = mesh.neighbours()
    parent = {b: min(n for n in nb[b] if hops.get(n) == hops[b] - 1) for b in hops if hops[b] > 0}
    subtree = dict.fromkeys(hops, 1)
    for b in sorted(parent, key=lambda x: -hops[x]):  # deepest first: a subtree is whole before its parent's
        subtree[parent[b]] += subtree[b]
    bits: dict[int, int] = {c.id: 0 for c in mesh.cells}
    ack = ack_bits() if acked else 0
    memo = records_frames({subtree[b] for b in parent}, rate)
    for b, p in parent.items():
        frames, parts = memo[subtree[b]]
        for c in mesh.bridge(b).cells:  # the record's frames on the sender's cells
            bits[c] += frames
        for c in mesh.bridge(p).cells:  # and the parent's acknowledgements on its own
            bits[c] += parts * ack
    per_frame = mesh.bitrate / rate
    load = {c: v / per_frame for c, v in bits.items()}
    busiest = max(load, key=lambda c: (load[c], -c)) if load else None
    return CellLoad(rate, load, busiest, tuple(sorted(set(mesh.ids) - set(hops))))



def load_line(load: CellLoad) -> str:
    """One line that states the load (``mesh check`` prints it)."""
    if load.busiest is None or load.peak == 0:  # (no cells, or gateways alone: they write to the host)
        return f"readout at {load.rate} Hz: no cell carries a record"
    return (f"readout at {load.rate} Hz (periodic): the busiest cell, {load.busiest}, spends {load.peak:.0%} of its "
            f"airtime on records and acknowledgements (fits below {FITS_BELOW:.0%})")


def load_warning(load: CellLoad) -> str:
    """What a user is told when the readout does not fit, and what to change."""
    return (f"warning: at {load.rate} Hz the readout needs {load.peak:.0%} of cell {load.busiest}'s airtime: its "
            "records will collide and miss their slots, and the host will list their elements missing in most "
            "frames. Put fewer bridges on one cell, add gateways, or sample at a lower rate (cellbridge mesh check "
            "--rate R tells the load).")

