"""Which bridge and element sits where (the layout file, else the bridges' HELLO geometry),
and the stages built for that layout.

:class:`LayoutStages` owns the layout-dependent stages (channel health, calibration and
inverse, each element's reading of the skin frames contacts are estimated on, the contact spec) and rebuilds them when
the HELLO-derived layout changes. A bridge the layout
does not place is *reported* (health ``unplaced``), never guessed into a position.
Layout ids are bridge ids; a bridge's element index 0 is the element the layout places.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import replace
from typing import Any

import numpy as np
from cellbridge.daemon.core.config import CalibrationSection, Config, ContactSection, InverseSection
from cellbridge.daemon.core.contacts import ContactSnapshot, ContactSpec
from cellbridge.daemon.core.elements import Calibrated, ElementStage, calibration_config, default_params
from cellbridge.daemon.core.health import ChannelHealth
from cellbridge.daemon.core.readings import SPARE, ElementReadings
from cellbridge.tactile import SkinLayout
from cellbridge.tactile.layout import MAX_REACH, MAX_SIDE
from cellbridge.tactile.skin_geometry import Band
from numpy.typing import NDArray

_IDS = 0x10000


def skin_settings(config: Config) -> tuple[CalibrationSection, InverseSection, ContactSection]:
    """The settings :class:`LayoutStages` builds its stages from (a change rebuilds them)."""
    return config.calibration, config.inverse, config.contact


class LayoutStages:
    """The layout and its stages; see the module's docstring. ``config``: the daemon's."""

    def __init__(self, config: Config, layout: SkinLayout | None,
                 previous: LayoutStages | None = None) -> None:
        """``previous``: the stages these replace (a SIGHUP that changed the layout or the
        contact settings, not calibration or inverse): elements that kept their place keep
        their baselines and touch state, so a press held across the reload goes on."""
        self.config = config
        self._previous = previous
        self.from_file = layout is not None
        self.geometry: dict[int, tuple[float, float, float]] = {}  # HELLO: bridge -> (x, y, side)
        self.rejected: list[int] = []
        self._index: PlacedIndex | None = None  # the HELLO layout's elements, for joins
        self.layout: SkinLayout | None = None
        self.elements: ElementStage | None = None
        self.contact_spec: ContactSpec | None = None  # what the service's worker process builds from
        self._banded: tuple[ContactSpec, tuple[Band, ...], ContactSpec] | None = None  # (spec, bands, spec with them)
        self.channels: ChannelHealth | None = None
        self.row = np.full(_IDS, -1, dtype=np.int64)
        self.readings: ElementReadings | None = None
        self.rebuilds = 0
        self.dirty = False  # the next contact snapshot is due even if no new frame came (tare)
        if layout is not None:
            self._install(layout)

    def reconfigured(self, config: Config, layout: SkinLayout | None) -> tuple[LayoutStages, bool]:
        """The stages for a reload's ``config`` and ``layout`` (the layout file's, or None),
        and whether they were rebuilt. They are rebuilt only when their settings or the
        layout changed: a SIGHUP that changes nothing of theirs (log rotation, client keys)
        must not erase a press being held. Calibration and inverse unchanged, elements that
        keep their place keep their baselines (a press held across the reload goes on, and
        so does its contact's id); else every baseline is taken again."""
        old = self.config
        same_layout = (layout is None and not self.from_file) or (
            layout is not None and self.from_file and self.layout is not None
            and layout_dict(layout) == layout_dict(self.layout))
        if same_layout and skin_settings(old) == skin_settings(config):
            self.config = config
            return self, False
        same_elements = (old.calibration, old.inverse) == (config.calibration, config.inverse)
        stages = LayoutStages(config, layout, self if same_elements else None)
        stages.hello(self.geometry)
        return stages, True

    def _install(self, layout: SkinLayout) -> None:
        src = self if self.layout is not None or self._previous is None else self._previous
        self._previous = None
        old_layout, old_elements, old_channels, old_readings = src.layout, src.elements, src.channels, src.readings
        params = default_params(layout)
        inv = self.config.inverse
        self.layout = layout
        cal = self.config.calibration
        self.elements = ElementStage(layout, params, calibration_config(cal), inv.noise, cal.max_step_rate)
        self.contact_spec = ContactSpec.of(layout, inv.noise, self.config.contact)
        self.channels = ChannelHealth(layout.n)
        self.row[:] = -1
        ids = layout.ids
        inside = (ids >= 0) & (ids < _IDS)
        self.row[ids[inside]] = np.nonzero(inside)[0]
        con = self.config.contact  # memory in readings: max_lag reaches back at most max_lag_readings
        depth = min(math.ceil(con.max_lag * cal.max_step_rate), con.max_lag_readings) + SPARE
        self.readings = ElementReadings(layout.n, depth)
        self.rebuilds += 1
        if old_layout is not None and old_elements is not None and old_layout.side == layout.side:
            # Elements that kept their place keep their baselines: a bridge joining late (or
            # one moved) must not re-take every other element's baseline under a press.
            rows, old_rows = _kept(old_layout, layout)
            if rows.size:
                self.elements.adopt(old_elements, rows, old_rows)
                assert old_channels is not None and old_readings is not None
                self.channels.adopt(old_channels, rows, old_rows)
                self.readings.adopt(old_readings, rows, old_rows)

    def hello(self, geometry: dict[int, tuple[float, float, float]]) -> bool:
        """Geometry {bridge: (x, y, side)} announced in HELLOs; True when the layout changed.

        A bridge joining (or moving on) a skin already placed is checked alone against
        the placed elements' grid (:class:`PlacedIndex`) and the layout's arrays are
        extended, not rebuilt: milliseconds at 1 000 bridges, where a rebuild per join
        blocked the loop ~0.5 s. A joining bridge that overlaps one already placed is
        rejected (the placed one keeps its place and baseline); a full placement (the
        first HELLOs, another side length) rejects the higher id of two that overlap."""
        new = {b: g for b, g in geometry.items() if self.geometry.get(b) != g}
        if not new:
            return False
        self.geometry.update(new)
        if self.from_file:
            return False
        index = self._index
        if index is not None and all(math.isclose(g[2], index.side, rel_tol=1e-6) for g in new.values()):
            if not self._join(index, new):
                return False
        else:
            index, self.rejected = place(self.geometry)
            if index is None:
                return False
            self._index = index
        self._install(layout_of(index))
        return True

    def _join(self, index: PlacedIndex, new: dict[int, tuple[float, float, float]]) -> bool:
        """Place ``new`` (joining or moved bridges, all of the index's side) into ``index``;
        True when what it places changed."""
        rejected = set(self.rejected)
        changed = moved = False
        for b in sorted(new):
            if b in index.where:
                index.remove(b)
                changed = moved = True
            rejected.discard(b)
            x, y, _ = new[b]
            if index.fits(x, y):
                index.add(b, x, y)
                changed = True
            else:
                rejected.add(b)
        if moved:  # a bridge that moved away may leave room for one rejected before
            for b in sorted(rejected):
                x, y, s = self.geometry[b]
                if math.isclose(s, index.side, rel_tol=1e-6) and index.fits(x, y):
                    index.add(b, x, y)
                    rejected.discard(b)
                    changed = True
        self.rejected = sorted(rejected)
        return changed

    def rows_of(self, origin: NDArray[np.int64], element: NDArray[np.int64]) -> NDArray[np.int64]:
        """Layout row of each sample, -1 where the layout does not place it."""
        return np.where(element == 0, self.row[origin], -1)

    def bridge_rows(self, bridges: NDArray[np.int64]) -> NDArray[np.int64]:
        """Layout row of each bridge's element 0 (a skin frame's), -1 where the layout does not
        place it: :meth:`rows_of` without the element column."""
        return self.row[bridges]

    def placed(self, bridge: int) -> bool:
        return bool(self.row[bridge] >= 0)

    def split_placed(self, ids: Iterable[int]) -> tuple[list[int], list[int]]:
        """(placed, not placed) of ``ids``, in their order: one array lookup for all, as
        health and topology walk every origin heard (65 530 after a noisy line)."""
        a = np.fromiter(ids, np.int64)
        m = np.zeros(a.shape, dtype=bool)
        inside = (a >= 0) & (a < _IDS)
        m[inside] = self.row[a[inside]] >= 0
        return a[m].tolist(), a[~m].tolist()

    @property
    def ready(self) -> bool:
        """A layout is in place: samples can be calibrated and contacts estimated."""
        return self.elements is not None

    def step(self, rows: NDArray[np.int64], raw: NDArray[np.int64], saturated: NDArray[np.bool_],
             caps: NDArray[np.float64], t_sample: NDArray[np.float64], cycle: NDArray[np.uint64],
             now: float, held: NDArray[np.bool_], on_time: NDArray[np.bool_],
             period: NDArray[np.float64], inverse: bool = True) -> dict[str, NDArray[Any]]:
        """One read's placed DATA samples (bridges on no readout schedule) through channel
        health → calibration and inverse → the readings contacts are estimated on; the
        element stage's columns back (force and area only with ``inverse``:
        :meth:`ElementStage.step`).

        ``rows``: layout row of each sample (all placed); ``raw``/``saturated``/``caps``:
        (n, 2) readings, their saturation and capacitance (F); ``t_sample``: host time of
        each sample; ``now``: the read's arrival time; ``held``, ``on_time``, ``period``:
        each reading's kind and sample period (:meth:`ElementReadings.record`). Requires :attr:`ready`."""
        assert self.elements is not None and self.channels is not None and self.readings is not None
        cal = self._calibrate(rows, raw, saturated, caps, now, held, inverse)
        res, dc = cal.columns, cal.dc
        r = self.readings
        touched = r.classify(rows, dc, *self.elements.thresholds())
        r.record(rows, t_sample, cycle, dc, touched, now, held, on_time, period)
        r.settle(cal.stepped.rows, cal.stepped.touched)
        return res

    def frame(self, t: float, cycle: int, sampled: NDArray[np.int64], raw: NDArray[np.int64],
              saturated: NDArray[np.bool_], caps: NDArray[np.float64], unchanged: NDArray[np.int64],
              now: float, inverse: bool = True, root: int = 0,
              missing: NDArray[np.int64] | None = None) -> tuple[dict[str, NDArray[Any]], int]:
        """One complete scheduled skin frame at host time ``t`` (global cycle ``cycle``) of
        time root ``root``: ``sampled`` rows with their readings (``raw``, ``saturated``,
        ``caps`` as in :meth:`step`), ``unchanged`` rows (their previous reading, while the
        host has it), ``missing`` rows; every other element of that root is unknown in it
        (:meth:`ElementReadings.scheduled`). The element stage's columns of the samples
        back, and how many elements the frame leaves unknown. Requires :attr:`ready`."""
        assert self.elements is not None and self.channels is not None and self.readings is not None
        r = self.readings
        kept, kept_caps = r.references(unchanged, t)
        known = np.concatenate([sampled, kept])
        every = np.concatenate([caps, kept_caps])
        ns = sampled.shape[0]
        # (channel health is of the samples alone: the raw readings of the first ns rows)
        cal = self._calibrate(known, raw, saturated, every, now, None, inverse, channels=ns)
        res, dc = cal.columns, cal.dc
        # the touch flags of the rows the step classified, the calibrator's hysteresis of the
        # others (a frame's step, when the rate allows one, classifies every known row)
        stepped = np.zeros(r.n, dtype=bool)
        stepped[cal.stepped.rows] = True
        touched = cal.stepped.touched[known]
        rest = np.flatnonzero(~stepped[known])
        if rest.size:
            touched[rest] = r.classify(known[rest], dc[rest], *self.elements.thresholds())
        accounted = np.concatenate([sampled, unchanged, missing if missing is not None else sampled[:0]])
        unknown = r.scheduled(t, cycle, sampled, caps, known, dc, touched, root, accounted)
        return {k: v[:ns] for k, v in res.items()}, unknown

    def _calibrate(self, rows: NDArray[np.int64], raw: NDArray[np.int64], saturated: NDArray[np.bool_],
                   caps: NDArray[np.float64], now: float, held: NDArray[np.bool_] | None, inverse: bool,
                   channels: int | None = None) -> Calibrated:
        """Channel health (of the first ``channels`` readings: all by default; ``raw`` and
        ``saturated`` need only those) and the element stage on ``rows``' readings."""
        assert self.elements is not None and self.channels is not None
        self.elements.hold_for(self._hold())
        groups = _newest(rows)
        c = rows.shape[0] if channels is None else channels
        if c:
            self.channels.update(rows[:c], raw[:c], saturated[:c], groups if c == rows.shape[0] else _newest(rows[:c]),
                                 now)
        return self.elements.step(rows, caps, groups, now, held, inverse)

    def snapshot(self, now: float, bridge_timeout: float, scheduled: bool) -> ContactSnapshot | None:
        """The newest skin frame not estimated yet, each element's reading of it or unknown
        (:mod:`cellbridge.daemon.core.readings`); ``scheduled``: a gateway is on the readout
        schedule (its frames are the ones estimated)."""
        if self.elements is None or self.readings is None or self.layout is None:
            return None
        r = self.readings
        self.elements.hold_for(self._hold())
        stepped = self.elements.flush(now)
        if stepped.rows.size:  # (most calls: nothing was waiting for a step)
            r.settle(stepped.rows, stepped.touched)
        got = r.take(now, bridge_timeout, self.config.contact.max_lag, scheduled, force=self.dirty)
        if got is None:
            return None
        self.dirty = False
        return ContactSnapshot(got.dc, got.touched, now, got.t_sample, got.cycle, self.layout.ids, got.t,
                               got.unknown)

    def _hold(self) -> float:
        """How long a held reading stands in the calibrator's steps: while its bridge is live
        (``bridge_timeout``, reloadable), and ``tau`` at least (a heartbeat may be longer than
        ``tau``; then the idle elements' readings lapsed between heartbeats)."""
        return max(self.config.calibration.tau, self.config.health.bridge_timeout)

    def spec(self, bands: tuple[Band, ...] = ()) -> ContactSpec | None:
        """What a contact estimate of this layout is built from (None: no layout yet), with
        the skin description's ``bands`` (contacts across wrap seams) when it has any: built
        once per spec and bands, as a job carries it a hundred times a second."""
        spec = self.contact_spec
        if spec is None or not bands or spec.bands == bands:
            return spec
        memo = self._banded
        if memo is None or memo[0] is not spec or memo[1] != bands:
            self._banded = memo = (spec, bands, replace(spec, bands=bands))
        return memo[2]

    def take_rebaselined(self) -> list[int]:
        """Bridge ids of the elements re-baselined under a touch (after ``max_touch``, their
        reading no contact's) since the last call, each once."""
        if self.elements is None or self.layout is None:
            return []
        return [int(b) for b in self.layout.ids[self.elements.take_rebaselined()]]

    def snapshot_due(self, now: float, idle: bool, scheduled: bool) -> float:
        """``now`` when :meth:`snapshot` has a frame to give (:meth:`ElementReadings.due`),
        else ``inf``; also ``inf`` with no layout."""
        if self.readings is None:
            return math.inf
        return now if self.dirty else self.readings.due(now, idle, scheduled)

    def tare(self, bridges: list[int] | None) -> int:
        if self.elements is None:
            return 0
        assert self.readings is not None
        self.dirty = True
        if bridges is None:
            self.elements.tare(None)
            self.readings.forget(slice(None))
            return self.layout.n  # type: ignore[union-attr]  # elements exist only with a layout
        rows = self.row[np.asarray(bridges, dtype=np.int64)]
        rows = rows[rows >= 0]
        if rows.size:
            self.elements.tare(rows)
            self.readings.forget(rows)
        return int(rows.size)

    def report(self, now: float, stuck_after: float) -> dict[str, Any]:
        out: dict[str, Any] = {"source": "file" if self.from_file else "hello", "rebuilds": self.rebuilds,
                               "rejected": self.rejected}
        if self.layout is None:
            out.update(elements=0, stuck=[], saturated=[], touched=[], not_ready=[], late=[], late_estimates=0)
            return out
        ids = self.layout.ids
        ch = self.channels
        assert ch is not None and self.elements is not None
        stuck = ch.stuck(stuck_after)
        out.update(
            elements=self.layout.n,
            stuck=[{"bridge": int(ids[i]), "channel": int(c) + 1} for i, c in zip(*np.nonzero(stuck))],
            saturated=[{"bridge": int(ids[i]), "channel": int(c) + 1} for i, c in zip(*np.nonzero(ch.saturated))],
            saturated_samples=int(ch.saturated_samples.sum()),
            touched=ids[self.elements.touched_rows()].tolist(),
            not_ready=ids[self.elements.not_ready_rows()].tolist(),
            late=ids[self.readings.late].tolist() if self.readings is not None else [],
            late_estimates=self.readings.late_frames if self.readings is not None else 0,
        )
        cal: dict[str, Any] = self.elements.calibration_health()
        cal["rebaselined"] = [[int(ids[i]), count] for i, count in cal["rebaselined"]]  # indices -> bridge ids
        out["calibration"] = cal
        return out

    def layout_report(self) -> dict[str, Any] | None:
        return None if self.layout is None else layout_dict(self.layout)


def _kept(old: SkinLayout, new: SkinLayout) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Rows of ``new`` and of ``old`` holding the same element id at the same centre."""
    order = np.argsort(old.ids, kind="stable")
    pos = np.minimum(np.searchsorted(old.ids[order], new.ids), old.n - 1)
    old_rows = order[pos]
    same = (old.ids[old_rows] == new.ids) & np.all(old.centres[old_rows] == new.centres, axis=1)
    return np.flatnonzero(same).astype(np.int64), old_rows[same].astype(np.int64)


class PlacedIndex:
    """The elements a HELLO layout places, on a grid of side-sized cells: whether a new
    square overlaps one of them costs the few elements of 9 cells, not a layout rebuild.

    Overlap is what :class:`SkinLayout` refuses (both signed gaps below -1e-9 side);
    touching edges are fine. Also checks what SkinLayout checks of one element alone
    (a finite centre within its reach of the origin)."""

    def __init__(self, side: float) -> None:
        self.side = side
        self.where: dict[int, tuple[float, float]] = {}  # bridge -> centre
        self._cells: dict[tuple[int, int], dict[int, tuple[float, float]]] = {}

    def _cell(self, x: float, y: float) -> tuple[int, int]:
        return math.floor(x / self.side), math.floor(y / self.side)

    def fits(self, x: float, y: float) -> bool:
        """The square at (x, y) is valid alone and overlaps no element placed."""
        reach = MAX_REACH * self.side
        if not (math.isfinite(x) and math.isfinite(y) and abs(x) <= reach and abs(y) <= reach):
            return False
        cx, cy = self._cell(x, y)
        eps = 1e-9 * self.side
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for px, py in self._cells.get((cx + dx, cy + dy), {}).values():
                    if abs(x - px) - self.side < -eps and abs(y - py) - self.side < -eps:
                        return False
        return True

    def add(self, bridge: int, x: float, y: float) -> None:
        self.where[bridge] = (x, y)
        self._cells.setdefault(self._cell(x, y), {})[bridge] = (x, y)

    def remove(self, bridge: int) -> None:
        x, y = self.where.pop(bridge)
        cell = self._cells[self._cell(x, y)]
        del cell[bridge]
        if not cell:
            del self._cells[self._cell(x, y)]


def place(geometry: dict[int, tuple[float, float, float]]) -> tuple[PlacedIndex | None, list[int]]:
    """Place HELLO geometry {bridge: (x, y, side)} from scratch: (index of the placed,
    rejected bridges). Elements must share one side length (the layout model's; the most
    common one is taken); bridges announcing another side, or overlapping a bridge of a
    lower id, are rejected and reported rather than placed wrongly. O(n)."""
    if not geometry:
        return None, []
    ids = sorted(geometry)
    sides = [geometry[i][2] for i in ids]
    side = max(set(sides), key=sides.count)
    if not (math.isfinite(side) and 0 < side <= MAX_SIDE):
        return None, ids
    index = PlacedIndex(side)
    rejected = []
    for i in ids:
        x, y, s = geometry[i]
        if math.isclose(s, side, rel_tol=1e-6) and index.fits(x, y):
            index.add(i, x, y)
        else:
            rejected.append(i)
    return (index if index.where else None), rejected


def layout_of(index: PlacedIndex) -> SkinLayout:
    """The layout of what ``index`` places, rows in id order."""
    ids = np.array(sorted(index.where), dtype=np.int64)
    centres = np.array([index.where[i] for i in ids.tolist()], dtype=np.float64).reshape(-1, 2)
    return SkinLayout(centres, side=index.side, ids=ids)


def layout_from_geometry(geometry: dict[int, tuple[float, float, float]]) -> tuple[SkinLayout | None, list[int]]:
    """A layout from the bridges' HELLO geometry {bridge: (x, y, side)} (see :func:`place`).

    Returns (layout, rejected bridges)."""
    index, rejected = place(geometry)
    return (None if index is None else layout_of(index)), rejected


def layout_dict(layout: SkinLayout) -> dict[str, Any]:
    return {"side": layout.side, "ids": layout.ids.tolist(), "x": layout.centres[:, 0].tolist(),
            "y": layout.centres[:, 1].tolist()}


def _newest(rows: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Each row once, in the order it first appears, with the index of its newest reading.
    A skin frame holds each element once: then that is ``rows`` itself, without a Python
    loop over a thousand elements per frame."""
    n = rows.shape[0]
    if n < 2 or np.bincount(rows).max() < 2:  # (rows are layout rows: small, never negative)
        return rows, np.arange(n, dtype=np.int64)
    last = {x: i for i, x in enumerate(rows.tolist())}
    return np.fromiter(last, np.int64, len(last)), np.fromiter(last.values(), np.int64, len(last))
