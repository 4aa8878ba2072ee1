"""A batch of readings through capacitance and the element stages: the fields of its
``raw`` and ``element`` messages (sans-I/O).

A batch is one read's DATA samples (bridges on no readout schedule, timed by the
pipeline's clocks) or one complete skin frame (:mod:`cellbridge.daemon.core.frames`, timed by
its frame). Raw counts or ADC sums become capacitance at each bridge's counter gate
(:class:`~cellbridge.daemon.core.frontend.Frontend`), the layout's element stages calibrate
them (:class:`~cellbridge.daemon.core.layout.LayoutStages`), and what comes back is a
:class:`Batch`: the messages' fields (each only when asked for) and the samples the
layout does not place, for the pipeline to stamp and to count.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from cellbridge.daemon.core.clock import cycle_of
from cellbridge.daemon.core.frames import SkinFrame
from cellbridge.daemon.core.frontend import Frontend
from cellbridge.daemon.core.layout import LayoutStages
from cellbridge.daemon.core.wire import HELD, SampleColumns
from numpy.typing import NDArray

_HELD = np.int64(HELD)
#: The element stage's columns an ``element`` message carries, in its order.
_ELEMENT_COLUMNS = ("dc1", "dc2", "force", "area", "valid", "status", "touched")


@dataclass(frozen=True, slots=True)
class Batch:
    """What one batch gave: the ``raw`` and ``element`` messages' fields (None: not asked
    for, or nothing to say), the origin of each sample the layout does not place, and how
    many elements a skin frame leaves unknown."""

    raw: dict[str, Any] | None
    element: dict[str, Any] | None
    unplaced: NDArray[np.int64]
    unknown: int = 0


class Batches:
    """Capacitance and the element stages for batches of readings; each bridge's counter
    gate (:meth:`set_gate`, from its GATE command's reply) is kept here.

    ``raw``/``element`` in each call: whether that message is wanted (the inverse runs
    only for ``element``); ``wall``: the wall-clock offset stamped on sample times."""

    def __init__(self, frontend: Frontend, clock_hz: float, gate_cycles: float) -> None:
        self.frontend = frontend
        self.hz = clock_hz
        self.gate = np.full(0x10000, float(gate_cycles))

    def set_gate(self, bridge: int, cycles: int) -> None:
        self.gate[bridge] = float(cycles)

    def samples(self, skin: LayoutStages, link: str, s: SampleColumns, t_sample: NDArray[np.float64],
                t_bridge: NDArray[np.float64], g: NDArray[np.int64], now: float, wall: float,
                raw: bool, element: bool) -> Batch:
        """One read of ``link``: its DATA samples ``s`` with their host times, bridge times
        and global cycles (-1: not on mesh time), arrived at ``now``."""
        o = s.origin
        counts = np.stack([s.c1, s.c2], axis=1)
        caps_all, sat_all = self.frontend.capacitance(s.mode, s.oversampling, counts, s.flags, self.gate[o])
        rows = skin.rows_of(o, s.element)
        placed = rows >= 0
        all_placed = bool(placed.all())
        raw_body = None if not raw else {
            "link": link, "bridge": o.tolist(), "element": s.element.tolist(), "cycle": s.cycle.tolist(),
            "t_bridge": t_bridge.tolist(), "c1": s.c1.tolist(), "c2": s.c2.tolist(), "flags": s.flags.tolist(),
            "mode": s.mode.tolist(), "oversampling": s.oversampling.tolist()}
        unplaced = o[~placed] if not all_placed else o[:0]
        if not skin.ready or not placed.any():
            return Batch(raw_body, None, unplaced)
        sel = slice(None) if all_placed else placed
        caps, flags, rate = caps_all[sel], s.flags[sel], s.rate[sel]
        with np.errstate(divide="ignore"):
            period = np.where(rate > 0, 1.0 / rate, np.nan)
        res = skin.step(rows[sel], counts[sel], sat_all[sel], caps, t_sample[sel], s.cycle[sel], now,
                        (flags & _HELD) != 0, g[sel] >= 0, period, inverse=element)
        body = None if not element else _element_body(
            o[sel], s.element[sel].tolist(), s.cycle[sel].tolist(), t_bridge[sel].tolist(),
            (t_sample[sel] + wall).tolist(), s.index[sel].tolist(), (g[sel] >= 0).tolist(), caps, res)
        return Batch(raw_body, body, unplaced)

    def frame(self, skin: LayoutStages, link: str, f: SkinFrame, now: float, wall: float,
              raw: bool, element: bool) -> Batch:
        """One complete skin frame ``f``, its first gateway on ``link``, given out at
        ``now``: its samples, its unchanged (previous reading) and missing elements into the
        element stages (:meth:`LayoutStages.frame`)."""
        g = cycle_of(f.index, f.rate, self.hz)
        counts = np.stack([f.c1, f.c2], axis=1)
        n = f.bridges.size
        raw_body = None if not (raw and n) else {
            "link": link, "bridge": f.bridges.tolist(), "element": [0] * n, "cycle": [g] * n,
            "t_bridge": [g / self.hz] * n, "c1": f.c1.tolist(), "c2": f.c2.tolist(), "flags": f.flags.tolist(),
            "mode": f.mode.tolist(), "oversampling": f.oversampling.tolist()}
        if not skin.ready:
            return Batch(raw_body, None, f.bridges[:0])
        rows = skin.bridge_rows(f.bridges)
        placed = rows >= 0
        caps, sat = self.frontend.capacitance(f.mode, f.oversampling, counts, f.flags, self.gate[f.bridges])
        unchanged = skin.bridge_rows(f.unchanged)
        missing = skin.bridge_rows(f.missing)
        res, unknown = skin.frame(f.t, g, rows[placed], counts[placed], sat[placed], caps[placed],
                                  unchanged[unchanged >= 0], now, inverse=element, root=f.root,
                                  missing=missing[missing >= 0])
        body = None
        if element and placed.any():
            k = int(placed.sum())
            body = _element_body(f.bridges[placed], [0] * k, [g] * k, [g / self.hz] * k, [f.t + wall] * k,
                                 [f.index] * k, [True] * k, caps[placed], res)
        return Batch(raw_body, body, f.bridges[~placed], unknown)


def _element_body(bridges: NDArray[np.int64], element: list[int], cycle: list[int], t_bridge: list[float],
                  t_sample: list[float], index: list[int], on_time: list[bool], caps: NDArray[np.float64],
                  res: dict[str, NDArray[Any]]) -> dict[str, Any]:
    return {"bridge": bridges.tolist(), "element": element, "cycle": cycle, "t_bridge": t_bridge,
            "t_sample": t_sample, "index": index, "on_time": on_time, "c1": caps[:, 0].tolist(),
            "c2": caps[:, 1].tolist(), **{k: res[k].tolist() for k in _ELEMENT_COLUMNS}}
