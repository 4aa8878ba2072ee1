"""Skin frames from the gateways' readout records: complete by construction, or by a deadline.

A bridge on the readout schedule samples frame ``k`` with every other bridge (its gates
start at mesh time ``k / rate``), and after the frame's readout its gateway writes one
READOUT record of ``k`` on its serial line, accounting for every element routed through
it: each is a *sample*, *unchanged* (its bridge said its reading stayed within the
reporting threshold of its last sample) or *missing* (its slot stayed empty). So the
host needs no guess from timing. :class:`SkinFrames` is fed the decoded records with
their arrival and gives out **complete skin frames**, in order, each once. Frame ``k``
is complete as soon as, for every active gateway (one that delivered a record within
``active_for``), either its record of ``k`` is in (all its parts) or a record of a
later frame is (a serial line keeps its order: the record of ``k`` was lost, and the
elements it would have accounted for are unknown). Else it goes out at its
**deadline**: the frame's host time + the largest readout span of the active gateways
+ the serial time of their largest record + ``margin``. A record of a frame already
given out is *late*: counted, never used to rewrite what was given out.

Sans-I/O and layout-free: bridges are ids, times are the caller's. The caller maps a
frame's mesh time to host time (:class:`~cellbridge.daemon.clock.SkinClock`) and turns
the states into element readings (:mod:`cellbridge.daemon.readings`).

Bounded whatever arrives: at most ``max_pending`` frames wait (a new one beyond that
sends the oldest out at once, as if its deadline had passed), at most ``max_gateways``
gateways are followed, and a record whose frame lies after its own arrival (an index
corrupted past the CRC, a gateway on another time) is refused. A gateway whose
records go behind the frames given out while no other active gateway is ahead
(the skin's time went back: its root restarted and counts from 0) restarts the
sequence once its next record agrees; one such record alone is only late.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

#: Frame instants are kept as integer nanoseconds of mesh time (``index * 1e9 // rate``),
#: so that frames of two rates order exactly and a u64 index never loses precision.
_NS = 1_000_000_000
#: s a record's frame may lie after the record's arrival (the host's map is off by
#: milliseconds at most; further, the index is wrong).
FUTURE_SLACK = 0.25
_SAMPLE, _UNCHANGED, _MISSING = 0, 1, 2


class RecordPart(Protocol):
    """What a READOUT frame carries (``cellbridge.protocol.Readout`` is one)."""

    @property
    def index(self) -> int: ...
    @property
    def rate(self) -> int: ...
    @property
    def mode(self) -> int: ...
    @property
    def oversampling(self) -> int: ...
    @property
    def samples(self) -> Sequence[tuple[int, int, int, int]]: ...
    @property
    def unchanged(self) -> Sequence[int]: ...
    @property
    def missing(self) -> Sequence[int]: ...
    @property
    def span_us(self) -> int: ...
    @property
    def part(self) -> int: ...
    @property
    def parts(self) -> int: ...


@dataclass(frozen=True, slots=True)
class SkinFrame:
    """One skin frame as the records said it: each bridge accounted for is in exactly one
    of ``bridges`` (a sample, with ``c1``, ``c2``, ``flags``, ``mode``, ``oversampling``
    aligned), ``unchanged`` or ``missing``; a bridge in none is unknown too (its
    gateway's record did not arrive, or it is on no schedule). A gateway whose record of
    the frame before did not come (lost on its line: no bridge knows) cannot vouch for
    "unchanged": its bridges said so are ``missing`` here (counted in ``unchanged_after_gap``)."""

    index: int
    rate: int
    t: float  #: host time of the frame's gate start
    bridges: NDArray[np.int64]
    c1: NDArray[np.int64]
    c2: NDArray[np.int64]
    flags: NDArray[np.int64]
    mode: NDArray[np.int64]
    oversampling: NDArray[np.int64]
    unchanged: NDArray[np.int64]
    missing: NDArray[np.int64]  #: said missing, in two records that disagree, or unchanged after a gap
    complete: bool  #: every active gateway's record came, whole
    by_deadline: bool  #: given out at its deadline (or pushed out by newer frames), not by the records
    gateways: tuple[int, ...]  #: the gateways whose record of it came (whole or in part)


class _Gateway:
    __slots__ = ("last_key", "last", "arrival", "span", "serial", "back", "back_key")

    def __init__(self) -> None:
        self.last_key = -1  # instant of its newest record taken
        self.last: tuple[int, int] | None = None  # (index, rate) of that record
        self.arrival = -math.inf  # when that record came
        self.span = 0.0  # s, its newest record's readout span
        self.serial = 0.0  # s, its newest record's time on the line
        self.back = 0  # records in a row behind the frames given out
        self.back_key = -1


class _Pending:
    __slots__ = ("index", "rate", "key", "t", "deadline", "records", "gaps")

    def __init__(self, index: int, rate: int, key: int, t: float, deadline: float) -> None:
        self.index, self.rate, self.key, self.t, self.deadline = index, rate, key, t, deadline
        self.records: dict[int, dict[int, RecordPart]] = {}  # gateway -> part -> record part
        self.gaps: set[int] = set()  # gateways whose record before this one was not of the frame before


class SkinFrames:
    """Readout records in, complete skin frames out (see the module).

    ``margin``: s added to a frame's deadline beyond its readout and serial time (the
    host's own read and scheduling delay); ``active_for``: s a gateway counts as active
    after its last record (the daemon passes ``health.bridge_timeout``)."""

    def __init__(self, margin: float = 0.01, active_for: float = 2.0, max_pending: int = 64,
                 max_gateways: int = 1024) -> None:
        if not (margin >= 0 and active_for > 0 and max_pending >= 1 and max_gateways >= 1):
            raise ValueError("SkinFrames needs margin >= 0, active_for > 0, max_pending >= 1, max_gateways >= 1")
        self.margin = float(margin)
        self.active_for = float(active_for)
        self.max_pending = int(max_pending)
        self.max_gateways = int(max_gateways)
        self._gw: dict[int, _Gateway] = {}
        self._pending: dict[tuple[int, int], _Pending] = {}
        self._ready: list[SkinFrame] = []  # given out at the next take (pushed out, or flushed at a restart)
        self._done = -1  # instant of the newest frame given out
        self._last: tuple[int, int] | None = None  # (index, rate) of the newest frame given out
        self.counts: dict[str, int] = dict.fromkeys(
            ("records", "late_records", "rejected_records", "duplicate_parts", "conflicts", "unchanged_after_gap",
             "frames_complete", "frames_incomplete", "frames_by_deadline", "frames_pushed_out", "frames_missed",
             "restarts"), 0)

    def configure(self, margin: float, active_for: float, max_pending: int) -> None:
        """A reload's settings (the frames waiting keep their deadlines)."""
        self.margin, self.active_for, self.max_pending = float(margin), float(active_for), int(max_pending)

    # -- in ------------------------------------------------------------------------------
    def add(self, gateway: int, rec: RecordPart, arrival: float, t_frame: float, serial: float = 0.0) -> None:
        """One record part written by ``gateway``, arrived at host time ``arrival``;
        ``t_frame``: the host time of its frame's gate start (NaN: not known, refused);
        ``serial``: s the record took on the line. Never raises for what a line brings."""
        span = rec.span_us * 1e-6
        if not (math.isfinite(t_frame) and t_frame + span <= arrival + FUTURE_SLACK and rec.rate > 0):
            self.counts["rejected_records"] += 1  # its frame lies after its own arrival: a wrong index
            return
        g = self._gw.get(gateway)
        if g is None:
            if len(self._gw) >= self.max_gateways and not self._prune(arrival):
                self.counts["rejected_records"] += 1
                return
            g = self._gw[gateway] = _Gateway()
        key = rec.index * _NS // rec.rate
        self.counts["records"] += 1
        if key <= self._done:
            if not self._went_back(gateway, g, key, arrival):
                self.counts["late_records"] += 1
                if key >= self._done - int(self.active_for * _NS):  # a gateway lagging (one joining, or
                    # back): it is active, and the frames after this wait for it
                    g.arrival, g.last_key, g.last = arrival, max(g.last_key, key), None
                    g.span, g.serial = span, float(serial)
                return
        g.back = 0
        gap = g.last is not None and g.last != (rec.index, rec.rate) and g.last != (rec.index - 1, rec.rate)
        g.last_key, g.last, g.arrival, g.span, g.serial = key, (rec.index, rec.rate), arrival, span, float(serial)
        p = self._pending.get((rec.index, rec.rate))
        if p is None:
            if len(self._pending) >= self.max_pending:
                self._push_out()
            p = self._pending[(rec.index, rec.rate)] = _Pending(rec.index, rec.rate, key, t_frame, math.nan)
            active = self._active(arrival)
            p.deadline = t_frame + max(g.span for g in active) + max(g.serial for g in active) + self.margin
        if gap:
            p.gaps.add(gateway)
        parts = p.records.setdefault(gateway, {})
        first = next(iter(parts.values()), None)
        if first is not None and first.parts != rec.parts:
            self.counts["rejected_records"] += 1  # a part of another record of the same frame: inconsistent
            return
        if rec.part in parts:
            self.counts["duplicate_parts"] += 1
            return
        parts[rec.part] = rec

    def _went_back(self, gateway: int, g: _Gateway, key: int, arrival: float) -> bool:
        """A record of ``gateway`` behind the frames given out: late, or the skin's time went
        back. True (and the sequence restarted) when this is the gateway's second such record
        in a row, later than the first, and no other active gateway is ahead."""
        again = g.back > 0 and key > g.back_key
        g.back, g.back_key = g.back + 1, key
        if not again:
            return False
        if any(o.last_key >= self._done for gw, o in self._gw.items()
               if gw != gateway and arrival - o.arrival <= self.active_for):
            return False
        self._flush()
        self._done, self._last = -1, None
        for o in self._gw.values():
            o.last_key, o.last = -1, None
        self.counts["restarts"] += 1
        return True

    def forget(self, gateway: int) -> None:
        """Stop following ``gateway`` (gone for good): frames no longer wait for it."""
        self._gw.pop(gateway, None)

    def _prune(self, now: float) -> bool:
        """Forget gateways inactive for ten times ``active_for``; whether room was made."""
        old = [gw for gw, g in self._gw.items() if now - g.arrival > 10 * self.active_for]
        for gw in old:
            del self._gw[gw]
        return bool(old)

    # -- out -----------------------------------------------------------------------------
    def _active(self, now: float) -> list[_Gateway]:
        return [g for g in self._gw.values() if now - g.arrival <= self.active_for]

    def active(self, now: float) -> bool:
        """Whether some gateway is on the schedule (delivered a record within ``active_for``)."""
        return any(now - g.arrival <= self.active_for for g in self._gw.values())

    def take(self, now: float) -> list[SkinFrame]:
        """The frames complete by ``now`` (see the module), oldest first, each given out once."""
        out, self._ready = self._ready, []
        if not self._pending:
            return out
        active = {gw: g for gw, g in self._gw.items() if now - g.arrival <= self.active_for}
        ordered = sorted(self._pending.values(), key=lambda p: p.key)
        last, whole = -1, []
        for i, p in enumerate(ordered):
            w = self._whole(p, active)
            whole.append(w)
            if (w is not None and active) or p.deadline <= now:
                last = i
        for p, w in zip(ordered[:last + 1], whole):
            out.append(self._give(p, w, by_deadline=w is None or not active))
        return out

    def due(self) -> float:
        """The host time at which :meth:`take` gives a frame out with no new record: the
        earliest deadline of a frame waiting (``inf``: none)."""
        if self._ready:
            return -math.inf
        return min((p.deadline for p in self._pending.values()), default=math.inf)

    def _whole(self, p: _Pending, active: dict[int, _Gateway]) -> bool | None:
        """None while an active gateway's record of ``p`` may still come; else whether every
        one came whole (False: one was lost, or came in part, as a later record shows)."""
        whole = True
        for gw, g in active.items():
            parts = p.records.get(gw)
            if parts and len(parts) == next(iter(parts.values())).parts:
                continue
            if g.last_key <= p.key:
                return None
            whole = False
        return whole

    def _push_out(self) -> None:
        """More than ``max_pending`` frames waiting: the oldest goes out now."""
        p = min(self._pending.values(), key=lambda q: q.key)
        self.counts["frames_pushed_out"] += 1
        self._ready.append(self._give(p, None, by_deadline=True))

    def _flush(self) -> None:
        """The sequence restarts: every frame waiting goes out as it is."""
        for p in sorted(self._pending.values(), key=lambda q: q.key):
            self._ready.append(self._give(p, None, by_deadline=True))

    def _give(self, p: _Pending, whole: bool | None, by_deadline: bool) -> SkinFrame:
        del self._pending[(p.index, p.rate)]
        c = self.counts
        if by_deadline:
            c["frames_by_deadline"] += 1
        elif whole:
            c["frames_complete"] += 1
        else:
            c["frames_incomplete"] += 1
        if self._last is not None and self._last[1] == p.rate and p.index > self._last[0] + 1:
            c["frames_missed"] += p.index - self._last[0] - 1  # no record of them came at all
        if p.key > self._done:
            self._done, self._last = p.key, (p.index, p.rate)
        return _frame(p, bool(whole) and not by_deadline, by_deadline, self)

    def counters(self, now: float) -> dict[str, Any]:
        """What health reports of the frames (counts since start, and now)."""
        return {**self.counts, "pending": len(self._pending), "gateways_active": len(self._active(now)),
                "newest": None if self._last is None else {"index": self._last[0], "rate": self._last[1]}}


def _frame(p: _Pending, complete: bool, by_deadline: bool, owner: SkinFrames) -> SkinFrame:
    """The frame of ``p``'s record parts: every bridge in one state; a bridge two parts
    disagree on (not a sample or unchanged against missing) is missing, and counted."""
    cols: list[list[int]] = [[], [], [], [], [], []]  # bridge, c1, c2, flags, mode, oversampling
    unchanged: list[int] = []
    missing: list[int] = []
    for gw, parts in p.records.items():
        for rec in parts.values():
            n = len(rec.samples)
            if n:
                for col, vals in zip(cols, zip(*rec.samples)):
                    col.extend(vals)
                cols[4].extend([int(rec.mode)] * n)
                cols[5].extend([rec.oversampling] * n)
            if gw in p.gaps:  # a record of this gateway was lost before: "unchanged" may refer to
                missing.extend(rec.unchanged)  # a sample the host never got
                owner.counts["unchanged_after_gap"] += len(rec.unchanged)
            else:
                unchanged.extend(rec.unchanged)
            missing.extend(rec.missing)
    arrays = [np.array(c, dtype=np.int64) for c in cols]
    u, m = np.array(unchanged, dtype=np.int64), np.array(missing, dtype=np.int64)
    every = np.concatenate([arrays[0], u, m])
    if np.unique(every).size != every.size:  # a bridge in two parts or two gateways' records
        arrays, u, m = _merge(arrays, u, m, owner)
    b, c1, c2, fl, mo, ov = arrays
    return SkinFrame(p.index, p.rate, p.t, b, c1, c2, fl, mo, ov, u, m, complete, by_deadline, tuple(sorted(p.records)))


def _merge(arrays: list[NDArray[np.int64]], u: NDArray[np.int64], m: NDArray[np.int64],
           owner: SkinFrames) -> tuple[list[NDArray[np.int64]], NDArray[np.int64], NDArray[np.int64]]:
    """One state per bridge: the same state twice is one; a sample or unchanged beats
    missing (the bridge's word came through one route); any other disagreement (two
    samples that differ, a sample and unchanged) is missing, counted in ``conflicts``."""
    state: dict[int, tuple[int, ...]] = {}
    conflict: set[int] = set()
    rows = [(_SAMPLE, *r) for r in zip(*(a.tolist() for a in arrays))]
    rows += [(_UNCHANGED, b) for b in u.tolist()] + [(_MISSING, b) for b in m.tolist()]
    for r in rows:
        b = r[1]
        old = state.get(b)
        if old is None or old[0] == _MISSING:
            state[b] = r
        elif r != old and r[0] != _MISSING:
            conflict.add(b)
    owner.counts["conflicts"] += len(conflict)
    samples = [r[1:] for b, r in sorted(state.items()) if r[0] == _SAMPLE and b not in conflict]
    cols = [np.array(c, dtype=np.int64) for c in zip(*samples)] if samples else [np.zeros(0, np.int64)] * 6
    unch = sorted(b for b, r in state.items() if r[0] == _UNCHANGED and b not in conflict)
    miss = sorted(b for b, r in state.items() if r[0] == _MISSING or b in conflict)
    return cols, np.array(unch, dtype=np.int64), np.array(miss, dtype=np.int64)
