"""Skin frames from the gateways' readout records: complete by the records, or by a deadline.

A bridge on the readout schedule samples frame ``k`` with every other bridge (its gates
start at mesh time ``k / rate``), and after the frame's readout its gateway writes one
READOUT record of ``k`` on its serial line, accounting for every element routed through
it: each is a *sample*, *unchanged* (its bridge said its reading stayed within the
reporting threshold of its last sample) or *missing* (its slot stayed empty). So the
host needs no guess from timing. :class:`SkinFrames` is fed the decoded records with
their arrival and gives out **skin frames**, in order, each once. Frame ``k`` is complete
as soon as every active gateway's record of it (one that delivered a record within
``active_for``) came whole, all its parts; else it goes out at its **deadline**: the
frame's host time + the largest readout span of the active gateways + the serial time
of their largest record + ``margin``, without what did not come (those elements are
unknown). A gateway writes a record as soon as it is complete, so records of two frames
may come in either order: a frame waits for the frames of its rate before it (each
complete or at its deadline), and a frame given out after one of which no record came
at all says so (``after_gap``: an "unchanged" in it may refer to a sample in the lost
record, so its bridges are missing there). So does the first record of a gateway that
came from another root's sequence (:meth:`SkinFrames.moved`): what its record before
said is in no frame here, and the index cannot show a loss across two roots' mesh
times, so its "unchanged" bridges are missing in that frame. A record of a frame already
given out is *late*: counted, never used to rewrite what was given out.

A gateway whose line is steadily late (a slower serial path, a USB adapter's buffering)
would miss every deadline and leave its elements unknown for good: each gateway's
*lag*, how much later than its readout and serial time its records arrived (the least
over the last ``LAG_WINDOW`` s, at most ``MAX_LAG``), is added to the deadlines of the
frames while it is active, when it is more than the ``margin`` covers.

Sans-I/O and layout-free: bridges are ids, times are the caller's. The caller maps a
frame's mesh time to host time (:class:`~cellbridge.daemon.core.clock.SkinClock`) and turns
the states into element readings (:mod:`cellbridge.daemon.core.readings`).

Bounded whatever arrives: at most ``max_pending`` frames wait (a new one beyond that
sends the oldest out at once, as if its deadline had passed), at most ``max_gateways``
gateways are followed, and a record whose frame lies after its own arrival (an index
corrupted past the CRC, a gateway on another time) is refused. A gateway whose records
go behind the frames given out while no other active gateway is ahead (the skin's time
went back: its root restarted and counts from 0) restarts the sequence once three in a
row over 0.1 s agree; fewer, or a burst of old records among current ones, are only late.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from operator import attrgetter
from typing import Any, Protocol

import numpy as np
from cellbridge.daemon.core.readout_columns import ReadoutColumns
from numpy.typing import NDArray

#: Frame instants are kept as integer nanoseconds of mesh time (``index * 1e9 // rate``),
#: so that frames of two rates order exactly and a u64 index never loses precision.
_NS = 1_000_000_000
#: s a record's frame may lie after the record's arrival (the host's map is off by
#: milliseconds at most; further, the index is wrong).
FUTURE_SLACK = 0.25
#: Records in a row behind the frames given out, consistent and over at least CONFIRM_TIME s
#: of arrivals, that restart the sequence (a burst of old records is no restart).
CONFIRM = 3
CONFIRM_TIME = 0.1
#: s over which a gateway's lag is the least of its records' (a line stalled, then
#: bursting, raises it for this long at most), and the most a deadline waits for it.
LAG_WINDOW = 1.0
MAX_LAG = 1.0
#: s of a record's readout span a deadline counts at most. Records are taken when their
#: frame's gates start before their arrival, whatever span they claim, so a span corrupt
#: past the CRC (up to 0xFFFFFFFF us, 71 min) would hold its frame, and every frame after
#: it, until ``max_pending`` newer ones push it out (64 s at 1 Hz). The deepest schedule
#: the shells run is 0.48 s (16 levels of 30 ms on an 8x8).
MAX_SPAN = 2.0
_SAMPLE, _UNCHANGED, _MISSING = 0, 1, 2
_BY_KEY = attrgetter("key")  # a pending frame's instant (the order frames go out in)


class RecordPart(Protocol):
    """What a READOUT frame carries (:class:`~cellbridge.daemon.core.readout_columns.ReadoutColumns`
    is one, and so is ``cellbridge.protocol.Readout``: the frame reads the samples, unchanged
    and missing lists of either)."""

    @property
    def index(self) -> int: ...
    @property
    def rate(self) -> int: ...
    @property
    def mode(self) -> int: ...
    @property
    def oversampling(self) -> int: ...
    @property
    def span_us(self) -> int: ...
    @property
    def part(self) -> int: ...
    @property
    def parts(self) -> int: ...
    @property
    def age_us(self) -> int: ...


@dataclass(frozen=True, slots=True)
class SkinFrame:
    """One skin frame as the records said it: each bridge accounted for is in exactly one
    of ``bridges`` (a sample, with ``c1``, ``c2``, ``flags``, ``mode``, ``oversampling``
    aligned), ``unchanged`` or ``missing``; a bridge in none is unknown too (its
    gateway's record did not arrive, or it is on no schedule). After a frame of which no
    record came at all (``after_gap``) no bridge is unchanged: "unchanged" may refer to a
    sample in the lost frame, so those bridges are ``missing`` (counted in
    ``unchanged_after_gap``); so are those a gateway's first record in the sequence says
    unchanged."""

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
    after_gap: bool = False  #: frames of its rate just before it were given out by no record
    root: int = 0  #: the time root whose mesh time ``index`` counts (0: not said)


class _Gateway:
    __slots__ = ("last_key", "arrival", "span", "serial", "back", "back_key", "back_at", "back_since", "lags")

    def __init__(self) -> None:
        self.last_key = -1  # instant of its newest record taken
        self.arrival = -math.inf  # when that record came
        self.span = 0.0  # s, its newest record's readout span
        self.serial = 0.0  # s, its newest record's time on the line
        self.back = 0  # records in a row behind the frames given out, as far apart as their arrivals
        self.back_key = -1  # the last of them, and when it came
        self.back_at = -math.inf
        self.back_since = -math.inf  # when the first of them came
        self.lags: deque[tuple[float, float]] = deque()  # (arrival, lag) of its records, lags increasing

    def note_lag(self, arrival: float, lag: float) -> None:
        """A record that arrived ``lag`` s after its frame's readout and serial time."""
        q = self.lags
        while q and q[-1][1] >= lag:
            q.pop()
        q.append((arrival, lag))
        while q[0][0] < arrival - LAG_WINDOW:
            q.popleft()

    @property
    def lag(self) -> float:
        """s its records came late, the least over the last ``LAG_WINDOW`` s (at most ``MAX_LAG``)."""
        return min(self.lags[0][1], MAX_LAG) if self.lags else 0.0


class _Pending:
    __slots__ = ("index", "rate", "key", "t", "deadline", "records", "fresh", "whole")

    def __init__(self, index: int, rate: int, key: int, t: float, deadline: float) -> None:
        self.index, self.rate, self.key, self.t, self.deadline = index, rate, key, t, deadline
        self.records: dict[int, dict[int, RecordPart]] = {}  # gateway -> part -> record part
        self.fresh: set[int] = set()  # gateways whose first record here is in this frame
        self.whole: set[int] = set()  # the gateways whose record came whole, every part


class SkinFrames:
    """Readout records in, skin frames out (see the module).

    ``margin``: s added to a frame's deadline beyond its readout and serial time (the
    host's own read and scheduling delay); ``active_for``: s a gateway counts as active
    after its last record (the daemon passes ``health.bridge_timeout``)."""

    def __init__(self, margin: float = 0.02, active_for: float = 2.0, max_pending: int = 64,
                 max_gateways: int = 1024, root: int = 0) -> None:
        if not (margin >= 0 and active_for > 0 and max_pending >= 1 and max_gateways >= 1):
            raise ValueError("SkinFrames needs margin >= 0, active_for > 0, max_pending >= 1, max_gateways >= 1")
        self.margin = float(margin)
        self.active_for = float(active_for)
        self.max_pending = int(max_pending)
        self.max_gateways = int(max_gateways)
        self.root = root  # the time root of every record added (frames given out carry it)
        self._gw: dict[int, _Gateway] = {}
        self._pending: dict[tuple[int, int], _Pending] = {}
        self._ready: list[SkinFrame] = []  # given out at the next take (pushed out, or flushed at a restart)
        self._done = -1  # instant of the newest frame given out
        # the frames given out at that instant: one of another rate at the same instant (every
        # 2nd of 40 Hz is one of 100 Hz) is not late for it
        self._done_at: set[tuple[int, int]] = set()
        self._last: tuple[int, int] | None = None  # (index, rate) of the newest frame given out
        # rate -> index of the newest frame of that rate given out: bridges at two rates make
        # frames of both, and a frame lost of one must show whatever came of the other between
        self._by_rate: dict[int, int] = {}
        self._restarted = False  # the sequence restarted: the next frame given out follows a gap
        self._moved: set[int] = set()  # gateways come from another root: their next record follows a gap
        # the time of the last take that left nothing more to give at that time, None once
        # anything take reads changed: a take at that same time again gives nothing (the
        # pipeline asks after every read and again for every contact job)
        self._taken: float | None = None
        self.counts: dict[str, int] = dict.fromkeys(
            ("records", "late_records", "rejected_records", "duplicate_parts", "conflicts", "unchanged_after_gap",
             "frames_complete", "frames_by_deadline", "frames_pushed_out", "frames_missed",
             "restarts"), 0)

    def configure(self, margin: float, active_for: float, max_pending: int) -> None:
        """A reload's settings (the frames waiting keep their deadlines)."""
        self.margin, self.active_for, self.max_pending = float(margin), float(active_for), int(max_pending)
        self._taken = None

    # -- in ------------------------------------------------------------------------------
    def add(self, gateway: int, rec: RecordPart, arrival: float, t_frame: float, serial: float = 0.0) -> None:
        """One record part written by ``gateway``, arrived at host time ``arrival``;
        ``t_frame``: the host time of its frame's gate start (NaN: not known, refused);
        ``serial``: s the record takes on the line. Never raises for what a line brings."""
        self._taken = None
        span = min(rec.span_us * 1e-6, MAX_SPAN)  # (a corrupt span holds no frame for minutes)
        # a frame whose gates start after the record's own arrival: a wrong index (or the
        # host's map not yet following a jump of the skin's time); refused, though it counts
        # towards a restart. (Not its span's end: a record goes as soon as it is complete,
        # well before the end of a deep skin's wide schedule.)
        mapped = math.isfinite(t_frame) and t_frame <= arrival + FUTURE_SLACK
        g = self._gw.get(gateway)
        if g is None:
            if not mapped or (len(self._gw) >= self.max_gateways and not self._prune(arrival)):
                self.counts["rejected_records"] += 1
                return
            g = self._gw[gateway] = _Gateway()
        key = rec.index * _NS // rec.rate
        if mapped:
            g.note_lag(arrival, max(0.0, arrival - t_frame - span - serial))
        behind = key < self._done or (key == self._done and (rec.index, rec.rate) in self._done_at)
        if behind and not self._went_back(gateway, g, key, arrival):
            self.counts["late_records" if mapped else "rejected_records"] += 1
            if mapped and key >= self._done - int(self.active_for * _NS):  # a gateway lagging (one
                # joining, or back): it is active, and the frames after this wait for its records
                g.arrival, g.last_key, g.span, g.serial = arrival, max(g.last_key, key), span, float(serial)
            return
        if not mapped:
            self.counts["rejected_records"] += 1
            return
        self.counts["records"] += 1
        g.back = 0
        g.last_key, g.arrival, g.span, g.serial = max(g.last_key, key), arrival, span, float(serial)
        p = self._pending.get((rec.index, rec.rate))
        if p is None:
            if len(self._pending) >= self.max_pending:  # (a backlog read at once: those ready go first)
                self._ready = self.take(arrival)
                self._taken = None  # (a frame is added below)
            if len(self._pending) >= self.max_pending:
                self._push_out()
            active = self._active(arrival)
            lag = max(a.lag for a in active)  # (within the margin, the margin covers it)
            deadline = (t_frame + max(a.span for a in active) + max(a.serial for a in active) + self.margin
                        + (lag if lag > self.margin else 0.0))
            p = self._pending[(rec.index, rec.rate)] = _Pending(rec.index, rec.rate, key, t_frame, deadline)
        parts = p.records.setdefault(gateway, {})
        first = next(iter(parts.values())) if parts else None
        if first is not None and first.parts != rec.parts:
            self.counts["rejected_records"] += 1  # a part of another record of the same frame: inconsistent
            return
        if rec.part in parts:
            self.counts["duplicate_parts"] += 1
            return
        parts[rec.part] = rec
        if gateway in self._moved:
            self._moved.discard(gateway)
            p.fresh.add(gateway)
        if len(parts) == rec.parts:
            p.whole.add(gateway)

    def _went_back(self, gateway: int, g: _Gateway, key: int, arrival: float) -> bool:
        """A record of ``gateway`` behind the frames given out: late (a relay may pass on a
        record seconds old), or the skin's time went back. True (and the sequence restarted)
        when this is the gateway's ``CONFIRM``-th such record in a row, over ``CONFIRM_TIME``
        s, each later than the one before by as much as it arrived later, and no other active
        gateway is ahead."""
        ok = g.back > 0 and key > g.back_key and abs((key - g.back_key) / _NS - (arrival - g.back_at)) <= FUTURE_SLACK
        if not ok:
            g.back_since = arrival
        g.back, g.back_key, g.back_at = (g.back + 1 if ok else 1), key, arrival
        if g.back < CONFIRM or arrival - g.back_since < CONFIRM_TIME - 1e-9:
            return False
        if any(o.last_key >= self._done for gw, o in self._gw.items()
               if gw != gateway and arrival - o.arrival <= self.active_for):
            return False
        self.restart()
        return True

    def restart(self) -> None:
        """The skin's time jumped (back, seen here; or either way, confirmed by the map of
        mesh time): the frames waiting go out as they are, and the sequence starts again,
        after a gap. Without this a jump forward counted every frame of the jump as missed
        (606 743 at a failover to a root whose map was last taught at boot)."""
        self._taken = None
        for p in sorted(self._pending.values(), key=lambda q: q.key):  # the old time's frames, as they are
            self._ready.append(self._give(p, None))
        self._done, self._last, self._restarted = -1, None, True
        self._by_rate.clear()
        self._done_at = set()
        for o in self._gw.values():
            o.last_key = -1
        self.counts["restarts"] += 1

    def forget(self, gateway: int) -> None:
        """Stop following ``gateway`` (gone for good): frames no longer wait for it."""
        self._taken = None
        self._gw.pop(gateway, None)
        self._moved.discard(gateway)

    def moved(self, gateway: int) -> None:
        """``gateway``'s records now name this sequence's root, after another's: the first
        of them joined here follows a gap (its "unchanged" bridges are missing there)."""
        self._moved.add(gateway)

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
        """The frames ready by ``now`` (see the module), oldest first, each given out once."""
        out, self._ready = self._ready, []
        if not self._pending or now == self._taken:
            return out
        for p in sorted(self._pending.values(), key=_BY_KEY):
            whole = self._whole(p, now)
            if p.deadline > now and not (whole and not self._gap_open(p, now)):
                break  # (in order: the frames after it wait for it)
            out.append(self._give(p, whole))
        self._taken = now  # (what stopped the walk is what it finds again at this time)
        return out

    def _whole(self, p: _Pending, now: float) -> bool:
        """Whether every gateway active at ``now`` (one at least) delivered its whole record
        of ``p``. Walks the gateways only until one active is missing: a read that completes
        no frame, most of them, stops at the first gateway still to come."""
        done = p.whole
        if not done:
            return False
        af = self.active_for
        any_active = False
        # newest gateway first: the gateways are kept in the order their first record came,
        # and their records of a frame come mostly in that order, so a frame's missing
        # gateways are at the end (the walk from the start passed half of them a read)
        for gw, g in reversed(self._gw.items()):
            if now - g.arrival <= af:
                if gw not in done:
                    return False
                any_active = True
        return any_active

    def due(self) -> float:
        """The host time at which :meth:`take` gives a frame out with no new record: the
        earliest deadline of a frame waiting (``inf``: none)."""
        if self._ready:
            return -math.inf
        return min((p.deadline for p in self._pending.values()), default=math.inf)

    def _gap_open(self, p: _Pending, now: float) -> bool:
        """Whether a frame of ``p``'s rate between the last given out and ``p`` may still come
        (a gateway writes each record as soon as it is complete: two frames' records may come
        in either order): until the deadline of the one just before ``p``."""
        prev = self._by_rate.get(p.rate)
        if prev is None or not 1 < p.index - prev <= self.max_pending:
            return False
        return now < p.deadline - 1.0 / p.rate

    def _push_out(self) -> None:
        """More than ``max_pending`` frames waiting: the oldest goes out now."""
        p = min(self._pending.values(), key=lambda q: q.key)
        self.counts["frames_pushed_out"] += 1
        self._ready.append(self._give(p, None))

    def _give(self, p: _Pending, whole: bool | None) -> SkinFrame:
        """``whole``: every active gateway's record of ``p`` came (None or False: given out
        at its deadline, or pushed out)."""
        del self._pending[(p.index, p.rate)]
        c = self.counts
        by_deadline = not whole
        c["frames_by_deadline" if by_deadline else "frames_complete"] += 1
        prev, gap = self._by_rate.get(p.rate), self._restarted
        if prev is not None and p.index > prev + 1:
            if (p.index - prev - 1) / p.rate <= self.active_for:  # (longer: its bridges were at another rate)
                c["frames_missed"] += p.index - prev - 1  # no record of them came at all
            gap = True
        elif prev is None and self._by_rate:  # a rate new here after another's frames: the sample its
            gap = True  # bridges last sent may be in a frame of the old rate that was lost
        if prev is None or p.index > prev:
            self._by_rate[p.rate] = p.index
        if p.key > self._done:
            self._done, self._last, self._restarted = p.key, (p.index, p.rate), False
            self._done_at = {(p.index, p.rate)}
        elif p.key == self._done:
            self._done_at.add((p.index, p.rate))
        return _frame(p, bool(whole), by_deadline, gap, self)

    def counters(self, now: float) -> dict[str, Any]:
        """What health reports of the frames (counts since start, and now)."""
        return {**self.counts, "pending": len(self._pending), "gateways_active": len(self._active(now)),
                "newest": None if self._last is None else {"index": self._last[0], "rate": self._last[1]}}


def _frame(p: _Pending, complete: bool, by_deadline: bool, after_gap: bool, owner: SkinFrames) -> SkinFrame:
    """The frame of ``p``'s record parts: every bridge in one state; a bridge two parts
    disagree on (not a sample or unchanged against missing) is missing, and counted."""
    blocks: list[NDArray[np.int64]] = []  # every part's samples, (n, 4) rows of bridge, c1, c2, flags, in order
    kinds: list[tuple[int, int, int]] = []  # per part with samples: its mode, oversampling, how many
    unchanged: list[NDArray[np.int64]] = []
    missing: list[NDArray[np.int64]] = []
    for gw, parts in p.records.items():
        fresh = gw in p.fresh and not after_gap  # its record before is in no frame here
        for part in parts.values():
            rec = part if type(part) is ReadoutColumns else ReadoutColumns.of(part)  # type: ignore[arg-type]  # a plain Readout
            n = rec.samples.shape[0]
            if n:
                blocks.append(rec.samples)
                kinds.append((rec.mode, rec.oversampling, n))
            if rec.unchanged.size:
                if fresh:
                    owner.counts["unchanged_after_gap"] += rec.unchanged.size
                    missing.append(rec.unchanged)
                else:
                    unchanged.append(rec.unchanged)
            if rec.missing.size:
                missing.append(rec.missing)
    if after_gap and unchanged:  # "unchanged" may refer to a sample in the frame lost
        owner.counts["unchanged_after_gap"] += sum(u.size for u in unchanged)
        missing, unchanged = missing + unchanged, []
    # The parts' columns joined: each part's samples are one array from its payload's bytes
    # (:mod:`cellbridge.daemon.core.readout_columns`), no Python object per sample.
    b, c1, c2, fl = (np.concatenate(blocks) if blocks else np.zeros((0, 4), np.int64)).T.copy()
    if kinds:
        k = np.array(kinds, dtype=np.int64)
        mo, ov = np.repeat(k[:, 0], k[:, 2]), np.repeat(k[:, 1], k[:, 2])
    else:
        mo = ov = np.zeros(0, np.int64)
    arrays = [b, c1, c2, fl, mo, ov]
    u = np.concatenate(unchanged) if unchanged else np.zeros(0, np.int64)
    m = np.concatenate(missing) if missing else np.zeros(0, np.int64)
    every = np.sort(np.concatenate([b, u, m]))
    if (every[1:] == every[:-1]).any():  # a bridge in two parts or two gateways' records (sorted:
        # side by side; np.unique hashed them, four times as long)
        arrays, u, m = _merge(arrays, u, m, owner)
    b, c1, c2, fl, mo, ov = arrays
    return SkinFrame(p.index, p.rate, p.t, b, c1, c2, fl, mo, ov, u, m, complete, by_deadline,
                     tuple(sorted(p.records)), after_gap, owner.root)


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
