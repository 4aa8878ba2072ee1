"""Each element's reading of a skin frame, or *unknown*: what a contact estimate is given.

An element on the readout schedule is read by its frame (:mod:`cellbridge.daemon.core.frames`):

* a **sample** is its new reading;
* **unchanged** is its previous reading, kept *because its bridge said so* (its reading
  stayed within the reporting threshold of the last sample it sent). That holds only
  while the host has that last sample: once the element was unknown in a frame (missing,
  or its gateway's record lost), a sample of it may have been lost too, and it stays
  unknown until its next sample comes;
* **missing**, or not accounted for (its gateway's record did not come by the deadline):
  unknown.

An element not on the schedule (a bridge booting or without mesh time, a capture of
protocol versions 1 to 3) sends DATA frames, whose completeness nobody can know. The
fallback rule is minimal: its newest reading within one sample period of the frame
counts, else it is unknown. Without a scheduled frame to estimate (no gateway on the
schedule) the frame is the newest instant every live periodic element has reported past,
on the frame grid where readings are on mesh time; an element whose readings trail the
newest by more than ``max_lag`` holds it back no longer (it is *late*, unknown). A held
(event-based) DATA reading holds nothing back.

An element with no ΔC (no baseline yet) is unknown, and so is every element of a bridge
silent for ``timeout``; when nothing is live any more, one frame with every element
unknown says so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from cellbridge.tactile.arrays import FloatArray, rows_all, rows_any
from numpy.typing import NDArray

#: Readings kept per element beyond ``max_lag`` at the fastest sampling rate.
SPARE = 4


@dataclass(frozen=True)
class FrameReading:
    """Each element's reading of one skin frame at host time ``t``: ΔC (n, 2), touched,
    the sample time (NaN: unknown) and bridge cycle of the reading, and which are unknown."""

    t: float
    dc: FloatArray
    touched: NDArray[np.bool_]
    t_sample: FloatArray
    cycle: NDArray[np.uint64]
    unknown: NDArray[np.bool_]


class ElementReadings:
    """Per element: its last scheduled sample, the newest scheduled frame, and its last
    ``depth`` unscheduled (DATA) readings; see the module."""

    def __init__(self, n: int, depth: int) -> None:
        self.n, self.depth = n, depth
        # scheduled: the last sample the host got of each element (what "unchanged" refers to)
        self.caps = np.full((n, 2), np.nan)
        self.ref = np.zeros(n, dtype=bool)  # that sample is the one its bridge last sent, as far as the host knows
        self.ref_t = np.full(n, np.nan)  # its frame's host time
        self.ref_cycle = np.zeros(n, dtype=np.uint64)
        self.last_touched = np.zeros(n, dtype=bool)  # each element's touch flag in its newest reading
        # the time root whose frames last accounted for each element (-1: none yet): a frame
        # speaks for its own root's elements only (parts no cell joins keep their own mesh time)
        self.domain = np.full(n, -1, dtype=np.int64)
        self._frame: FrameReading | None = None  # the newest scheduled frame
        self._news = False  # that frame has a sample, or its known elements changed
        # unscheduled: a ring of the newest readings
        self.t = np.full((n, depth), np.nan)
        self.dc = np.full((n, depth, 2), np.nan)
        self.touched = np.zeros((n, depth), dtype=bool)
        self.cycle = np.zeros((n, depth), dtype=np.uint64)
        self.held = np.zeros((n, depth), dtype=bool)
        self.on_time = np.zeros((n, depth), dtype=bool)
        self.period = np.full(n, np.nan)  # s between the element's DATA samples (NaN: not known)
        self.count = np.zeros(n, dtype=np.int64)
        self.arrival = np.full(n, -math.inf)  # host time its newest DATA reading came
        self.late = np.zeros(n, dtype=bool)  # live elements the last frame did not wait for (max_lag)
        self.late_frames = 0  # frames that left a late element out
        self.taken = -math.inf  # the frame last taken
        self._unseen = False  # a DATA reading came since the last take
        self._silent_told = False
        self._all = np.arange(n)

    _ROWS = ("caps", "ref", "ref_t", "ref_cycle", "last_touched", "domain", "period", "count", "arrival")
    _RINGS = ("t", "dc", "touched", "cycle", "held", "on_time")

    def adopt(self, old: ElementReadings, rows: NDArray[np.int64], old_rows: NDArray[np.int64]) -> None:
        """Take over ``old``'s readings of its elements ``old_rows`` as ``rows`` (a layout
        that grew: a bridge joined late); a held press goes on under its id."""
        k = min(self.depth, old.depth)
        count = old.count[old_rows]
        shift = np.where(count >= k, count - k, 0)
        src = (shift[:, None] + np.arange(k)[None, :]) % old.depth
        for name in self._RINGS:
            getattr(self, name)[rows, :k] = getattr(old, name)[old_rows[:, None], src]
        for name in self._ROWS:
            getattr(self, name)[rows] = getattr(old, name)[old_rows]
        self.count[rows] = np.minimum(count, k)
        self.taken, self.late_frames = old.taken, old.late_frames

    # -- scheduled -----------------------------------------------------------------------
    def references(self, rows: NDArray[np.int64], t: float = math.inf) -> tuple[NDArray[np.int64], FloatArray]:
        """Of ``rows`` said unchanged in a frame at host time ``t``, those whose last sample the
        host has, and its capacitances. "Unchanged" refers to a sample sent before the frame:
        a reference taken from a later frame is not it (two roots' frames of one skin
        interleave while a gateway's records flap between them at a failover)."""
        with np.errstate(invalid="ignore"):
            ok = rows[self.ref[rows] & ~(self.ref_t[rows] > t)]
        return ok, self.caps[ok]

    def scheduled(self, t: float, cycle: int, sampled: NDArray[np.int64], caps: FloatArray,
                  known: NDArray[np.int64], dc: FloatArray, touched: NDArray[np.bool_],
                  root: int = 0, accounted: NDArray[np.int64] | None = None) -> int:
        """A scheduled frame at host time ``t`` (global cycle ``cycle``) of time root ``root``:
        ``sampled`` rows with their new capacitances ``caps``; ``known`` rows (sampled, then
        unchanged with a reference) with their ΔC and touch flags; ``accounted``: every row
        the frame's records named (sampled, unchanged or missing; default ``known``). The
        frame speaks for the elements of its root (those its root's frames named last, and
        those no frame named yet): every one of them not known is unknown in it, and its
        reference is gone until its next sample; the elements of other roots keep what
        their own newest frame said. Returns how many the frame leaves unknown (an element
        without a baseline yet is unknown too, but not counted here)."""
        self.domain[known if accounted is None else accounted] = root
        scope = (self.domain == root) | (self.domain < 0)
        whole = bool(scope.all())  # (one root: the frame speaks for every element)
        ok = np.zeros(self.n, dtype=bool)
        ok[known] = True
        self.ref &= ok if whole else ok | ~scope
        with np.errstate(invalid="ignore"):  # a sample of an earlier frame than the reference's (another
            newer = ~(self.ref_t[sampled] > t)  # root's frame, given out after) is not what the bridge last sent
        if newer.all():  # (every sample but at a failover: no copies of them)
            fresh = sampled
            self.caps[fresh] = caps
        else:
            fresh = sampled[newer]
            self.caps[fresh] = caps[newer]
        self.ref[fresh] = True
        self.ref_t[fresh] = t
        self.ref_cycle[fresh] = cycle
        full = np.full((self.n, 2), np.nan)
        full[known] = dc
        ok &= rows_all(np.isfinite(full))  # no ΔC: no baseline yet
        tch = np.zeros(self.n, dtype=bool)
        tch[known] = touched
        self.last_touched[known] = touched
        t_sample = np.where(ok, self.ref_t, np.nan)
        cyc = np.where(ok, self.ref_cycle, np.uint64(0))
        unknown = ~ok
        prev = self._frame
        if not whole:  # another root's elements: as their own newest frame said
            other = ~scope
            if prev is None:
                unknown[other] = True
            else:
                full[other], tch[other], t_sample[other] = prev.dc[other], prev.touched[other], prev.t_sample[other]
                cyc[other], unknown[other] = prev.cycle[other], prev.unknown[other]
        self._news = sampled.size > 0 or prev is None or not np.array_equal(prev.unknown, unknown)
        self._frame = FrameReading(t, full, tch & ~unknown, t_sample, cyc, unknown)
        if whole:
            return self.n - known.shape[0]
        return int(np.count_nonzero(scope) - np.count_nonzero(scope[known]))

    # -- unscheduled (DATA) ----------------------------------------------------------------
    def record(self, rows: NDArray[np.int64], t: FloatArray, cycle: NDArray[np.uint64], dc: FloatArray,
               touched: NDArray[np.bool_], now: float, held: NDArray[np.bool_], on_time: NDArray[np.bool_],
               period: FloatArray) -> None:
        """One read's DATA readings in arrival order (an element may come several times);
        ``period``: each one's sample period in s (NaN: not known; then the element's own
        spacing of readings, once it has two)."""
        order = np.argsort(rows, kind="stable")
        sr = rows[order]
        starts = np.flatnonzero(np.r_[True, sr[1:] != sr[:-1]])
        sizes = np.diff(np.r_[starts, sr.shape[0]])
        rank = np.arange(sr.shape[0]) - np.repeat(starts, sizes)
        keep = rank >= np.repeat(sizes, sizes) - self.depth
        idx, rank = order[keep], rank[keep]
        r = rows[idx]
        pos = (self.count[r] + rank) % self.depth
        self.t[r, pos], self.cycle[r, pos], self.dc[r, pos] = t[idx], cycle[idx], dc[idx]
        self.touched[r, pos], self.held[r, pos], self.on_time[r, pos] = touched[idx], held[idx], on_time[idx]
        self.count += np.bincount(r, minlength=self.n)
        last = (self.count - 1) % self.depth
        before = (self.count - 2) % self.depth
        seen = np.unique(r)
        spacing = self.t[seen, last[seen]] - self.t[seen, before[seen]]
        p = np.full(self.n, np.nan)
        p[r] = period[idx]
        self.period[seen] = np.where(np.isfinite(p[seen]), p[seen],
                                     np.where((self.count[seen] > 1) & (spacing > 0), spacing, np.nan))
        self.last_touched[r] = touched[idx]
        self.arrival[r] = now
        self._unseen = True
        self._silent_told = False

    def settle(self, rows: NDArray[np.int64], touched: NDArray[np.bool_]) -> None:
        """The calibrator classified the newest DATA reading of ``rows``: their touch flags."""
        if rows.size:
            newest = (self.count[rows] - 1) % self.depth
            self.touched[rows, newest] = touched[rows]

    def forget(self, rows: NDArray[np.int64] | slice) -> None:
        """Tare: the readings taken against the old baselines no longer count."""
        self.dc[rows] = np.nan
        if self._frame is not None:
            self._frame.dc[rows] = np.nan
            self._frame.unknown[rows] = True
            self._frame.touched[rows] = False

    # -- the frame to estimate ---------------------------------------------------------------
    def take(self, now: float, timeout: float, max_lag: float, scheduled: bool,
             force: bool = False) -> FrameReading | None:
        """The newest frame not taken yet (or again, with ``force``: a tare), each element's
        reading of it or unknown (see the module); None when there is none. ``scheduled``:
        a gateway is on the schedule, so frames come from it (and not from DATA readings)."""
        unseen, self._unseen = self._unseen, False
        f = self._frame
        if f is not None and (f.t > self.taken or (force and scheduled)):
            return self._taken(self._fill(f, now, timeout))
        if scheduled:
            return None
        live = (now - self.arrival <= timeout) & (self.count > 0)
        if not live.any():
            self.late = live
            return self._all_silent()
        if not (unseen or force):
            return None
        t = self._instant(live, max_lag)
        if t <= self.taken and not force:
            return None
        empty = FrameReading(t, np.full((self.n, 2), np.nan), np.zeros(self.n, dtype=bool), np.full(self.n, np.nan),
                             np.zeros(self.n, dtype=np.uint64), np.ones(self.n, dtype=bool))
        self.late_frames += bool(self.late.any())
        return self._taken(self._fill(empty, now, timeout))

    def _taken(self, f: FrameReading) -> FrameReading:
        self.taken = max(self.taken, f.t)
        self._silent_told = False
        return f

    def due(self, now: float, idle: bool, scheduled: bool) -> float:
        """``now`` when :meth:`take` has a frame (a scheduled frame not taken, worth a look
        after an ``idle`` estimate only when it says something new; or a DATA reading came),
        else ``inf``."""
        f = self._frame
        if f is not None and f.t > self.taken and (self._news or not idle):
            return now
        return now if self._unseen and not scheduled else math.inf

    def _instant(self, live: NDArray[np.bool_], max_lag: float) -> float:
        """The newest instant every ``live`` periodic DATA element has reported past (on the
        frame grid where readings are on mesh time)."""
        newest_at = (self.count - 1) % self.depth
        newest = self.t[self._all, newest_at]
        top = float(newest[live].max())
        periodic = live & ~self.held[self._all, newest_at]
        waits = periodic & (newest >= top - max_lag)
        self.late = periodic & ~waits
        t = float(newest[waits].min()) if waits.any() else top
        with np.errstate(invalid="ignore"):
            grid = np.where(self.on_time & (self.t <= t + 1e-9) & live[:, None], self.t, -math.inf)
        frame = float(grid.max()) if grid.size else -math.inf
        return frame if math.isfinite(frame) else t

    def classify(self, rows: NDArray[np.int64], dc: FloatArray, enter: FloatArray, leave: FloatArray
                 ) -> NDArray[np.bool_]:
        """Touch flags of new readings of ``rows`` by the calibrator's hysteresis (over
        ``enter``, or over ``leave`` after a touched reading), until it classifies them."""
        with np.errstate(invalid="ignore"):
            over_enter = rows_any(dc > enter[rows])
            over_leave = rows_any(dc > leave[rows])
        return over_enter | (self.last_touched[rows] & over_leave)

    def _fill(self, f: FrameReading, now: float, timeout: float) -> FrameReading:
        """``f`` with each element it leaves unknown read by the fallback rule: its newest
        DATA reading at or before ``f.t`` within one sample period, if its bridge is live."""
        rows = np.flatnonzero(f.unknown & (self.count > 0) & (now - self.arrival <= timeout))
        if rows.size == 0:
            return f
        with np.errstate(invalid="ignore"):
            before = self.t[rows] <= f.t + 1e-9
        j = np.where(before, self.t[rows], -math.inf).argmax(axis=1)
        t_j = self.t[rows, j]
        age = f.t - t_j
        per = self.period[rows]
        finest = np.nanmin(self.period[np.isfinite(self.period)], initial=math.inf)
        slack = 0.25 * finest if math.isfinite(finest) else 0.0
        with np.errstate(invalid="ignore"):
            # on mesh time: the reading of this very frame, or for a bridge at a slower rate its
            # last one until its next is due; else within one period before
            stands = np.where(self.on_time[rows, j], age < per - slack, age <= per + 1e-9)
        dc = self.dc[rows, j]
        # A reading before the frame whose next reading (already in) is touched where it is
        # not, or the reverse: the element was pressed or released between the two, perhaps
        # before the frame. Readings off mesh time are not of one instant (each bridge samples
        # at its own phase), and without this a press's first frame was a press on one element.
        with np.errstate(invalid="ignore"):
            after = self.t[rows] > f.t + 1e-9
        nxt = np.where(after, self.t[rows], math.inf).argmin(axis=1)
        flips = after.any(axis=1) & (self.touched[rows, j] != self.touched[rows, nxt]) & (age > 1e-9)
        ok = before.any(axis=1) & stands & (age >= -1e-9) & np.isfinite(dc).all(axis=1) & ~flips
        rows, j = rows[ok], j[ok]
        out = FrameReading(f.t, f.dc.copy(), f.touched.copy(), f.t_sample.copy(), f.cycle.copy(), f.unknown.copy())
        out.dc[rows] = self.dc[rows, j]
        out.touched[rows] = self.touched[rows, j]
        out.t_sample[rows] = self.t[rows, j]
        out.cycle[rows] = self.cycle[rows, j]
        out.unknown[rows] = False
        return out

    def _all_silent(self) -> FrameReading | None:
        """Nothing live (every bridge silent, the line down): once, a frame with every
        element unknown, so that subscribers learn their contacts are no longer known."""
        if self._silent_told or not math.isfinite(self.taken):
            return None
        self._silent_told = True
        n = self.n
        return FrameReading(self.taken, np.full((n, 2), np.nan), np.zeros(n, dtype=bool), np.full(n, np.nan),
                            np.zeros(n, dtype=np.uint64), np.ones(n, dtype=bool))
