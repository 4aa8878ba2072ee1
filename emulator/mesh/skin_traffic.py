"""A whole skin's gateway lines at frame level: the scheduled readout without the cells.

The virtual-time mesh (:mod:`cellbridge.emulator.mesh.virtual`) runs every chip, its firmware
and every cell, cycle-exact: about 0.2 s of CPU per bridge and virtual second, far too
slow for a humanoid's thousand bridges over minutes. On a settled, lossless skin on mesh
time, what reaches the host is only the readout (docs/time.md): per frame and gateway,
one READOUT record of every element routed through it. :class:`SkinTraffic` writes those
records directly, frame by frame, vectorised over the elements:

* the **same frames** the gateway's firmware writes: each record built by
  :func:`~cellbridge.emulator.firmware.readout.record_parts` (the firmware's own code: the split
  into parts that fit a frame, their numbering, ``span_us``), with the age the gateway
  stamps on them (``age_us``: when it began writing), framed as the gateway frames its own
  messages (origin the gateway, its host numbering) and COBS-encoded on the line;
* the **same states**: periodic, every element a sample; event-based, each bridge's
  :class:`~cellbridge.emulator.firmware.reporting.Reporter` (threshold, follow-up, heartbeat slot,
  settling) and the readout's refresh on the cells (every ``readout_refresh`` frames in
  the bridge's slot) decide sample or *unchanged*, as on the chip, and the gateway's
  refresh of its line (every ``serial_refresh`` frames in the element's slot) writes an
  unchanged element as the last sample its bridge sent, as the gateway does (its own
  element sampled afresh then);
* the **same readings**: the world's capacitances (:class:`~cellbridge.emulator.world.world.World`,
  band ghosts included) at each gate's middle, counted by the closed-form counter
  (:func:`cellbridge.tactile.transfer.counts`) at a random oscillator phase.

What differs from the cycle-level mesh, exactly: no cells, so no collisions, losses, bit
errors, retries, beacons, HELLO, STATUS or routing traffic (a settled, lossless skin); the
routing tree is the shortest-hop tree to the nearest gateway (what the mesh's ETX routing
settles to on lossless cells), fixed; mesh time is the host's time (no crystal offsets,
no sync error; a gateway's line is the host's clock); the counter has no per-period
jitter; and a record's arrival is modelled, not simulated: after the gates, each hop of
the tree costs its record's airtime at 1 Mbit/s plus an acknowledgement, deepest first,
and the gateway's record then its serial time at ``baudrate`` (never later than the
gateway's slot). Nothing is ever missing.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np
from cellbridge.emulator.firmware.commands import Settings
from cellbridge.emulator.firmware.firmware import FirmwareConfig
from cellbridge.emulator.firmware.readout import AGE_ROOM, ReadoutConfig, record_parts
from cellbridge.emulator.firmware.readout import stagger as _stagger
from cellbridge.emulator.firmware.reporting import Reporter
from cellbridge.emulator.mesh.skin_mesh import mesh_from_skin, neighbour_pairs
from cellbridge.emulator.world.world import World
from cellbridge.protocol import ADDR_HOST, Mode, ReadoutSample, Sample, own, reframe, to_serial
from cellbridge.tactile.skin_geometry import SkinGeometry
from cellbridge.tactile.transfer import ChipParams, counts
from numpy.typing import NDArray

__all__ = ["ReadoutTree", "SkinTraffic", "readout_tree"]

CLOCK_HZ = 50_000_000
_CELL_BIT = 1e-6  #: s a bit takes on a cell (1 Mbit/s)
_HOP_EXTRA = 150e-6  #: s of a hop besides the record's airtime: the idle wait and the acknowledgement
_RECORD_BYTES = 24  #: a cell frame's header, CRC and READOUT fields besides its states (about)
_SAMPLE_BYTES = 9  #: a sample in a record (about; unchanged: 3)


@dataclass(frozen=True)
class ReadoutTree:
    """Rows (into the skin's per-element arrays) of each element's gateway and parent
    (-1: it is a gateway) and its depth in hops."""

    gateway: NDArray[np.int64]
    parent: NDArray[np.int64]
    depth: NDArray[np.int64]


def readout_tree(skin: SkinGeometry) -> ReadoutTree:
    """The shortest-hop tree of ``skin``'s cells to the nearest gateway (ties: the lower id).
    ValueError naming an element no gateway reaches."""
    n = skin.n
    nbrs: list[list[int]] = [[] for _ in range(n)]
    for i, j in neighbour_pairs(skin).tolist():
        nbrs[i].append(j)
        nbrs[j].append(i)
    gw = np.full(n, -1, dtype=np.int64)
    parent = np.full(n, -1, dtype=np.int64)
    depth = np.full(n, -1, dtype=np.int64)
    queue: deque[int] = deque()
    for bid in sorted(skin.gateway_ids()):
        r = skin.row_of(bid)
        gw[r], depth[r] = r, 0
        queue.append(r)
    while queue:
        r = queue.popleft()
        for q in sorted(nbrs[r], key=lambda k: int(skin.ids[k])):
            if depth[q] < 0:
                gw[q], parent[q], depth[q] = gw[r], r, depth[r] + 1
                queue.append(q)
    if (depth < 0).any():
        raise ValueError(f"element {int(skin.ids[np.flatnonzero(depth < 0)[0]])}: no gateway reaches it")
    return ReadoutTree(gw, parent, depth)


class SkinTraffic:
    """The serial bytes each gateway of ``skin`` writes, frame by frame (see the module).

    ``world``: the stimuli (None: untouched); ``settings``: every bridge's (rate, mode
    COUNTER only, reporting); ``refresh`` and ``serial_refresh``: the readout's refresh of
    event-based bridges on the cells and the gateways' of their lines (frames, 0: none;
    the firmware's defaults); ``baudrate``: the gateways' lines. Deterministic for a ``seed``."""

    def __init__(self, skin: SkinGeometry, world: World | None = None, *, settings: Settings = Settings(),
                 seed: int = 0, refresh: int = FirmwareConfig(0).cell_refresh,
                 serial_refresh: int = FirmwareConfig.serial_refresh, baudrate: int = 1_000_000,
                 readout: ReadoutConfig | None = None) -> None:
        if settings.mode is not Mode.COUNTER:
            raise ValueError("SkinTraffic reads counter mode only")
        self.skin = skin
        self.settings = settings
        self.world = world if world is not None else World(mesh_from_skin(skin))
        self.rng = np.random.default_rng(seed)
        self.tree = readout_tree(skin)
        self.ids = skin.ids.astype(np.int64)
        self.refresh = refresh
        self.serial_refresh = serial_refresh
        self.baudrate = baudrate
        self.chip = ChipParams(gate_cycles=settings.gate_cycles)
        depths = int(self.tree.depth.max()) + 2  # the skin's depth plus two, as a mesh file gives it
        self.readout = readout or ReadoutConfig(depths=depths, window=6 * CLOCK_HZ // 1000)
        self.span_us = (settings.measure_cycles() + self.readout.depths * self.readout.window) // 50
        self.gateways = sorted(int(self.ids[r]) for r in np.unique(self.tree.gateway))
        self._gw_rows = np.array([skin.row_of(g) for g in self.gateways], dtype=np.int64)
        self._seq = dict.fromkeys(self.gateways, 0)
        # the world's element order (the mesh's bridge order) to the skin's rows
        world_ids = self.world.layout.ids.astype(np.int64)
        self._world_rows = np.array([self.world.index[int(b)] for b in self.ids], dtype=np.int64)
        assert np.array_equal(world_ids[self._world_rows], self.ids)
        periodic = settings.reporting.periodic
        self._reporters = None if periodic else [
            Reporter(settings.reporting, CLOCK_HZ // 1000, phase=_stagger(int(b), 1 << 16) / (1 << 16))
            for b in self.ids.tolist()]
        self._refresh_slot: NDArray[np.int64] | None = (
            np.array([_stagger(int(b), refresh) for b in self.ids.tolist()], dtype=np.int64) if refresh else None)
        self._serial_slot: NDArray[np.int64] | None = (
            np.array([_stagger(int(b), serial_refresh) for b in self.ids.tolist()], dtype=np.int64)
            if serial_refresh else None)
        self._is_gateway = self.tree.parent < 0
        order = np.argsort(self.tree.depth, kind="stable")[::-1]
        self._levels = [order[self.tree.depth[order] == d] for d in range(int(self.tree.depth.max()), 0, -1)]
        self.counters: Counter[str] = Counter()

    def _readings(self, t: float) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
        """(c1, c2, flags) of every element for the frame whose gates start at ``t``."""
        gate = self.settings.gate_cycles / CLOCK_HZ
        c1 = self.world.capacitances(t + 0.5 * gate)[0][self._world_rows]
        c2 = self.world.capacitances(t + 1.5 * gate)[1][self._world_rows]
        n = c1.shape[0]
        r1, o1 = counts(c1, self.chip, self.rng.random(n))
        r2, o2 = counts(c2, self.chip, self.rng.random(n))
        return r1, r2, (o1.astype(np.int64) | (o2.astype(np.int64) << 1))

    def _phase(self, slots: NDArray[np.int64] | None, every: int, index: int) -> list[bool]:
        n = self.ids.shape[0]
        return np.equal(slots, index % every).tolist() if slots is not None else [False] * n

    def _kept(self, index: int, start: int, c1: NDArray[np.int64], c2: NDArray[np.int64],
              flags: NDArray[np.int64]) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """Which elements send a sample in frame ``index`` on the cells, and which the
        gateway writes as a sample (the rest: unchanged). An element the gateway refreshes
        has its reading in ``c1``, ``c2``, ``flags`` replaced by the last sample it sent."""
        n = c1.shape[0]
        if self._reporters is None:
            every = np.ones(n, dtype=bool)
            return every, every
        period = CLOCK_HZ // self.settings.rate_hz
        kept = np.empty(n, dtype=bool)
        written = np.empty(n, dtype=bool)
        refresh = self._phase(self._refresh_slot, self.refresh, index)
        serial = self._phase(self._serial_slot, self.serial_refresh, index)
        gateway = self._is_gateway.tolist()
        for i, (rep, a, b, f) in enumerate(zip(self._reporters, c1.tolist(), c2.tolist(), flags.tolist())):
            s = Sample(0, start, a, b, f, index)
            k = rep.wants(s, period, True)
            if not k and (serial[i] if gateway[i] else refresh[i]):  # (a gateway's own: its line's refresh)
                k = True
                rep.sent(s)
                self.counters["readout_refreshed"] += 1
            kept[i] = k
            written[i] = k
            if not k and serial[i]:
                ref = rep.reference
                if ref is not None:
                    c1[i], c2[i], flags[i] = ref.c1, ref.c2, ref.flags
                    written[i] = True
                    self.counters["readout_serial_refreshed"] += 1
        return kept, written

    def _arrivals(self, kept: NDArray[np.bool_]) -> NDArray[np.float64]:
        """s after the gates' end at which each element's record is complete (modelled)."""
        n = kept.shape[0]
        size = np.where(kept, _SAMPLE_BYTES, 3).astype(np.float64)  # bytes of each own state
        done = np.zeros(n)
        p = self.tree.parent
        for rows in self._levels:  # deepest first: a record goes when its children's are in
            np.add.at(size, p[rows], size[rows])
            hop = done[rows] + (_RECORD_BYTES + size[rows]) * 8 * _CELL_BIT + _HOP_EXTRA
            np.maximum.at(done, p[rows], hop)
        return done

    def frame(self, index: int) -> list[tuple[float, int, bytes]]:
        """(arrival s, gateway id, serial bytes) of frame ``index`` on every gateway's line."""
        rate = self.settings.rate_hz
        start = index * CLOCK_HZ // rate
        t = start / CLOCK_HZ
        c1, c2, flags = self._readings(t)
        cells, kept = self._kept(index, start, c1, c2, flags)
        gate_end = t + self.settings.measure_cycles() / CLOCK_HZ
        done = self._arrivals(cells)
        latest = t + self.span_us * 1e-6
        ids, gw = self.ids, self.tree.gateway
        out = []
        for g_id, g_row in zip(self.gateways, self._gw_rows.tolist()):
            rows = np.flatnonzero(gw == g_row)
            rows = rows[np.argsort(ids[rows], kind="stable")]
            k = kept[rows]
            sr = rows[k]
            samples = [ReadoutSample(b, a, c, f) for b, a, c, f in
                       zip(ids[sr].tolist(), c1[sr].tolist(), c2[sr].tolist(), flags[sr].tolist())]
            unchanged = ids[rows[~k]].tolist()
            # written once its subtree's records are in (the slots bound it), with its age
            written = min(gate_end + float(done[g_row]), latest)
            age = max(1, int((written - t) * 1e6))
            parts = [replace(r, age_us=age) for r in
                     record_parts(index, rate, {(Mode.COUNTER, 1): (samples, unchanged, [])}, self.span_us,
                                  room=AGE_ROOM)]
            data = bytearray()
            for rec in parts:
                seq = self._seq[g_id]
                self._seq[g_id] = (seq + 1) & 0xFFFF
                data += to_serial(reframe(own(rec, g_id, seq), g_id, ADDR_HOST))  # as the firmware's _emit
            self.counters["records"] += 1
            self.counters["parts"] += len(parts)
            self.counters["samples"] += len(samples)
            self.counters["unchanged"] += len(unchanged)
            arrival = min(written + len(data) * 10 / self.baudrate, latest)
            out.append((arrival, g_id, bytes(data)))
        return out

    def run(self, seconds: float, start: float = 0.0) -> Iterator[tuple[float, int, bytes]]:
        """(arrival s, gateway, bytes) of every frame whose gates start in [start, start +
        seconds), in order of arrival within each frame, frame after frame."""
        rate = self.settings.rate_hz
        first = math.ceil(start * rate - 1e-9)
        last = math.ceil((start + seconds) * rate - 1e-9)
        for k in range(first, last):
            yield from sorted(self.frame(k))

