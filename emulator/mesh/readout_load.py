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

from cellbridge.emulator.firmware.readout import _split
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
    return sum(8 * (HEADER_LEN + CRC_LEN + len(pack_payload(p))) + PREAMBLE_BITS + tc.difs_bits
               for p in parts), len(parts)


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
    memo: dict[int, tuple[int, int]] = {}
    for b, p in parent.items():
        n = subtree[b]
        if n not in memo:
            memo[n] = record_frames(n, rate)
        frames, parts = memo[n]
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
    if load.busiest is None:
        return f"readout at {load.rate} Hz: no cell carries a record"
    return (f"readout at {load.rate} Hz (periodic): the busiest cell, {load.busiest}, spends {load.peak:.0%} of its "
            f"airtime on records and acknowledgements (fits below {FITS_BELOW:.0%})")


def load_warning(load: CellLoad) -> str:
    """What a user is told when the readout does not fit, and what to change."""
    return (f"warning: at {load.rate} Hz the readout needs {load.peak:.0%} of cell {load.busiest}'s airtime: its "
            "records will collide and miss their slots, and the host will list their elements missing in most "
            "frames. Put fewer bridges on one cell, add gateways, or sample at a lower rate (cellbridge mesh check "
            "--rate R tells the load).")

