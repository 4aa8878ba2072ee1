"""The skin at one moment: each element's reading at (or just before) a common sample time.

Bridges sample at their own phases and their frames reach the host after different
delays (hops, queues, a late bridge process), so the *newest* reading of every element
mixes elements that already see a press (or its release) with elements that do not
yet. Physically the elements change together; an estimator shown such a skin reports
a contact where only part of the footprint is, or a second, ghost contact. Contacts are
therefore estimated on the skin at the newest time ``T`` that every live element has
reported past, in host time from the per-bridge clock sync (``t_sample``); each element
contributes its reading at or just before ``T``.

A reading counts as reported once the calibrator has classified it (its touch flag is
from that reading, not the one before). Elements whose bridge has sent nothing for
``bridge_timeout`` do not hold ``T`` back (a dead bridge must not freeze contacts);
they contribute their last reading. The extra latency is about one sample period of
the slowest live bridge plus its delay relative to the others.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from cellbridge.tactile.arrays import FloatArray


#: Readings kept per element beyond ``max_lag`` at the fastest sampling rate.
SPARE = 4


class Moment(NamedTuple):
    """Each element's reading at one moment ``t`` (host time): ΔC (n, 2), touched (n,), the
    sample time (NaN: unknown) and bridge cycle of the reading used."""

    t: float
    dc: FloatArray
    touched: NDArray[np.bool_]
    t_sample: FloatArray
    cycle: NDArray[np.uint64]


class Moments:
    """The last ``depth`` readings (ΔC, touch flag, sample time, cycle) of every element."""

    def __init__(self, n: int, depth: int) -> None:
        self.depth = depth
        self.t = np.full((n, depth), np.nan)  # host time of the sample (NaN: empty slot)
        self.dc = np.full((n, depth, 2), np.nan)
        self.touched = np.zeros((n, depth), dtype=bool)
        self.cycle = np.zeros((n, depth), dtype=np.uint64)
        self.count = np.zeros(n, dtype=np.int64)  # readings ever written (ring position)
        self.settled = np.full(n, np.nan)  # sample time of the newest reading the calibrator classified
        self.arrival = np.full(n, -math.inf)  # host time the newest reading arrived
        self.t_moment = -math.inf  # the moment of the last snapshot
        self.hold_since = math.nan  # first moment held back for a transition (NaN: none held)
        self.holding = np.zeros(n, dtype=bool)  # elements the last moment waited for (the others: their newest)
        self.late = np.zeros(n, dtype=bool)  # live elements not waited for: their data trail by more than max_lag
        self.late_estimates = 0  # snapshots that left a live element out for being late
        self._all = np.arange(n)

    def record(self, rows: NDArray[np.int64], t: FloatArray, cycle: NDArray[np.uint64], dc: FloatArray,
               unique: bool, now: float, enter: FloatArray, leave: FloatArray) -> None:
        """One batch of readings in arrival order; ``unique``: each row occurs once.

        The calibrator classifies an element's newest reading when it steps (at most
        ``max_step_rate`` times a second; :meth:`settle`), not each reading. Until then a
        reading is touched by the calibrator's own hysteresis on its thresholds (``enter``,
        ``leave``: (n, 2)): over ``enter``, or over ``leave`` after a touched reading — so
        a reading taken after a release never carries the touch flag of the one before."""
        with np.errstate(invalid="ignore"):
            over_enter = (dc > enter[rows]).any(axis=1)
            over_leave = (dc > leave[rows]).any(axis=1)
        prev = self.touched[rows, (self.count[rows] - 1) % self.depth] & (self.count[rows] > 0)
        touched = over_enter | (prev & over_leave)
        if unique:
            idx, rank = None, 0
            r = rows
        else:  # several readings of an element: each its own slot, the newest ``depth`` kept
            order = np.argsort(rows, kind="stable")
            sr = rows[order]
            starts = np.flatnonzero(np.r_[True, sr[1:] != sr[:-1]])
            sizes = np.diff(np.r_[starts, sr.shape[0]])
            rank_s = np.arange(sr.shape[0]) - np.repeat(starts, sizes)
            keep = rank_s >= np.repeat(sizes, sizes) - self.depth
            idx, rank = order[keep], rank_s[keep]
            r = rows[idx]
            t, cycle, dc, touched = t[idx], cycle[idx], dc[idx], touched[idx]
        pos = (self.count[r] + rank) % self.depth
        self.t[r, pos] = t
        self.cycle[r, pos] = cycle
        self.dc[r, pos] = dc
        self.touched[r, pos] = touched
        if idx is None:
            self.count[r] += 1
        else:
            self.count += np.bincount(r, minlength=self.count.shape[0])
        self.arrival[r] = now

    def settle(self, rows: NDArray[np.int64], touched: NDArray[np.bool_]) -> None:
        """The calibrator stepped on the newest reading of ``rows``: their touch flags."""
        if rows.shape[0] == 0:
            return
        newest = (self.count[rows] - 1) % self.depth
        self.touched[rows, newest] = touched[rows]
        self.settled[rows] = self.t[rows, newest]

    def forget(self, rows: NDArray[np.int64] | slice) -> None:
        """Tare: the readings taken against the old baselines no longer count."""
        self.dc[rows] = np.nan

    def take(self, now: float, timeout: float, max_lag: float, force: bool = False) -> Moment | None:
        """The skin at the newest moment every live element has reported past (:meth:`moment`),
        if that moment advanced since the last one taken (or ``force``: a tare asks for
        one at once). None while it did not, and while an element is between a touched
        and an untouched reading at it: a press or release fell between two of its
        samples, so the moment is held back until it is past that (one sample period of
        that element at most; ``force`` does not wait)."""
        t = self.moment(now, timeout, max_lag)
        if math.isnan(t) or (t <= self.t_moment and not force):
            return None
        dc, touched, t_sample, cycle, transition = self.at(t)
        if transition and not force:
            if math.isnan(self.hold_since):
                self.hold_since = t
            if t - self.hold_since < transition:
                return None
        self.hold_since = math.nan
        self.late_estimates += bool(self.late.any())
        self.t_moment = t
        return Moment(t, dc, touched, t_sample, cycle)

    def moment(self, now: float, timeout: float, max_lag: float) -> float:
        """The newest time every live element has reported past (NaN: none reported yet).
        Elements silent for ``timeout`` or trailing the newest data by more than
        ``max_lag`` hold nothing back; :meth:`at` gives their newest reading."""
        live = (now - self.arrival <= timeout) & np.isfinite(self.settled)
        if not live.any():
            self.holding = self.late = live
            return math.nan
        newest = float(self.settled[live].max())
        self.holding = live & (self.settled >= newest - max_lag)
        self.late = live & ~self.holding
        return max(float(self.settled[self.holding].min()), self.t_moment)

    def at(self, moment: float) -> tuple[FloatArray, NDArray[np.bool_], FloatArray, NDArray[np.uint64], float]:
        """(ΔC (n, 2), touched, sample time, cycle) of each element's reading at or just
        before ``moment`` — the newest one for elements the moment did not wait for
        (silent, or late), NaN/False (unknown) if none is kept — and
        how long the skin is still in transition there: an element whose next reading
        is touched where this one is not (or the reverse) was pressed or released
        between its two samples, so at ``moment`` its state is unknown for up to the
        longest such interval (0.0: no element in transition)."""
        with np.errstate(invalid="ignore"):
            before = self.t <= moment
            after = self.t > moment
        j = np.where(before, self.t, -math.inf).argmax(axis=1)
        none_before = ~before.any(axis=1)
        rows = self._all
        nxt = np.where(after, self.t, math.inf).argmin(axis=1)
        changing = self.holding & after.any(axis=1) & ~none_before & (self.touched[rows, j] != self.touched[rows, nxt])
        gap = float((self.t[changing, nxt[changing]] - self.t[changing, j[changing]]).max()) if changing.any() else 0.0
        newest = (self.count - 1) % self.depth
        j = np.where(self.holding, j, newest)  # silent or late: the newest reading, the best there is
        dc, touched = self.dc[rows, j], self.touched[rows, j]
        unknown = (self.holding & none_before) | (self.count == 0)  # nothing kept that old, or nothing at all
        if unknown.any():
            dc[unknown] = np.nan
            touched[unknown] = False
        return dc, touched, self.t[rows, j], self.cycle[rows, j], gap
