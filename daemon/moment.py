"""The skin at one moment: a skin frame, each element's reading of it or *unknown*.

On mesh time every bridge starts sample ``k`` at the same global instant, and the
pipeline gives all samples of one index one host time (``t_sample``): a skin frame.
Contacts are estimated on the newest frame every live element has reported (their
frames reach the host after different delays). An element contributes its reading *of
that frame*, never an older one: a sample lost or still in flight makes the element
unknown for the frame. (Bridges may sample at different rates, one set faster by the
``set rate`` control request: at a frame of a finer rate, an element's last sample is its
reading of that frame until its next sample is due.) Two kinds of reading stand for more
than their own instant:

* a **held** reading (event-based reporting, flag ``HELD``): the bridge promised that
  its readings stay within the threshold of it until it sends another, so it stands
  for the frames after it (while the bridge is live);
* a reading without mesh time (a bridge booting or cut off: timed from its arrival):
  the one at or just before the moment, within one sample period, as close as the
  host can tell.

Elements silent for ``timeout`` (``bridge_timeout``) are unknown, not touched, and hold
nothing back; so is an element whose reading has no ΔC (no baseline yet: at start, or
after a tare until ``n_baseline`` new readings came). At a press's onset, the untouched neighbours of a touch just begun are
unknown for a frame until they reported past it (``ONSET_WAIT``): their held readings from
before the press may be overtaken by a change still on its way. A periodic element whose data trail the newest by more than ``max_lag``
holds nothing back either (it is unknown for the newer frames). A held element has
reported past every instant a change of its would already have reached the host: its
bridge sends a change at once, so a held element holds the moment back only to ``now``
minus its own delivery delay (a decaying mark of arrival minus sample time of its
on-time readings, with a margin: the highest lately for an element touched or next to a
touch, the second highest for the others, see ``_hold``), and never more than
``held_wait`` behind the newest data. Waiting by the element's own delay, not a fixed ``held_wait``, is what makes
an event-based skin's contacts come tens of milliseconds after a press, not half a
second: an idle element's last heartbeat is up to a heartbeat old, and what matters is
only whether a change could still be on its way. A held reading that begins a touch and
arrives after its frame was taken (an onset later than the holds: the bridges under a
press contend for the cells) has the last frame taken again at once, not a frame later.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from cellbridge.tactile.arrays import FloatArray


#: Readings kept per element beyond ``max_lag`` at the fastest sampling rate.
SPARE = 4
#: An element's delivery delay bound forgets old delays with this time constant (s): a
#: route that got faster, or the seconds-long delays of a skin still forming its routes,
#: stop holding frames back within seconds, whether the element reports 100 times a
#: second or sends a heartbeat a second.
DELAY_FORGET_S = 5.0
#: A held element is waited for this many times its delay high-water mark, plus ``DELAY_MARGIN`` s
#: (the mark is already the largest delay seen lately: a change later than that is rare).
DELAY_FACTOR = 1.0
DELAY_MARGIN = 0.002
#: The untouched neighbours of an element that began a touch within this long (s) of a
#: frame are *unknown* for that frame until they have reported past it, or until their
#: delivery delay plus this much has passed. A press sets off the bridges under it at
#: one instant, and they contend for the same cells: one of them retried (a collision
#: costs an acknowledgement timeout, 10 ms and more) reaches the host after its usual
#: delay. Its held reading from before the press would say "not touched", and a corner
#: press seen on three of its four elements is fitted as two contacts (an extra id).
#: Unknown, it leaves the fit free there and holds nothing back.
ONSET_WAIT = 0.030


class Moment(NamedTuple):
    """Each element's reading at one moment ``t`` (host time): ΔC (n, 2), touched (n,), the
    sample time (NaN: unknown) and bridge cycle of the reading used, and which elements
    are unknown at ``t`` (no reading of that frame: lost, late, or the bridge silent)."""

    t: float
    dc: FloatArray
    touched: NDArray[np.bool_]
    t_sample: FloatArray
    cycle: NDArray[np.uint64]
    unknown: NDArray[np.bool_]
    again: bool = False  # the moment taken last, taken again (a late onset of it came)


class Moments:
    """The last ``depth`` readings (ΔC, touch flag, sample time, cycle) of every element."""

    def __init__(self, n: int, depth: int, near: NDArray[np.int64] | None = None) -> None:
        """``n`` elements, ``depth`` readings kept of each; ``near``: (E, 2) pairs of
        elements next to each other, corners included (``SkinLayout.corner_edges``; None:
        no element is a neighbour of another)."""
        self.depth = depth
        self.near = np.zeros((0, 2), dtype=np.int64) if near is None else np.asarray(near, dtype=np.int64)
        self.t = np.full((n, depth), np.nan)  # host time of the sample (NaN: empty slot)
        self.dc = np.full((n, depth, 2), np.nan)
        self.touched = np.zeros((n, depth), dtype=bool)
        self.cycle = np.zeros((n, depth), dtype=np.uint64)
        self.held = np.zeros((n, depth), dtype=bool)  # event-based: stands for the frames after it
        self.on_time = np.zeros((n, depth), dtype=bool)  # a mesh-time reading (its frame's exact time)
        self.period = np.full(n, np.nan)  # s between the element's samples (1 / rate; NaN: not known)
        self.silent_told = False  # a moment with every element unknown was taken since the data stopped
        self.live = np.ones(n, dtype=bool)  # elements heard within the timeout, as of the last moment()
        self.count = np.zeros(n, dtype=np.int64)  # readings ever written (ring position)
        self.settled = np.full(n, np.nan)  # sample time of the newest reading the calibrator classified
        self.arrival = np.full(n, -math.inf)  # host time the newest reading arrived
        self.delay = np.full(n, np.nan)  # decaying high-water of arrival - sample time, on-time readings
        # ... and the second-highest: the mark an element away from any touch is waited by
        # (one retried frame, late by an acknowledgement wait, must not hold every frame of
        # the skin back for seconds; see _hold)
        self.delay2 = np.full(n, np.nan)
        self.delay_at = np.zeros(n)  # host time the delay marks were last updated
        self.t_moment = -math.inf  # the moment of the last snapshot
        self.on_grid = True  # the last moment() was a frame (False: no live element on mesh time)
        self.hold_since = math.nan  # first moment held back for a transition (NaN: none held)
        self.holding = np.zeros(n, dtype=bool)  # elements the last moment waited for (the others: their newest)
        self.late = np.zeros(n, dtype=bool)  # live elements not waited for: their data trail by more than max_lag
        self.late_estimates = 0  # snapshots that left a live element out for being late
        # A held reading that began a touch arrived for a frame already taken (an onset
        # later than the frame's holds): the last frame is taken again at the next look.
        self.retake = False
        self.retaken = 0  # frames taken again for a late onset
        self.last_touched = np.zeros(n, dtype=bool)  # each element's touch flag in the last moment taken
        self.touch_began = np.full(n, -math.inf)  # sample time of the reading that began the element's touch
        self._all = np.arange(n)

    _PER_ELEMENT = ("period", "live", "settled", "arrival", "delay", "delay2", "delay_at", "holding", "late", "touch_began",
                    "last_touched")
    _RINGS = ("t", "dc", "touched", "cycle", "held", "on_time")

    def adopt(self, old: Moments, rows: NDArray[np.int64], old_rows: NDArray[np.int64]) -> None:
        """Take over ``old``'s readings of its elements ``old_rows`` as ``rows`` (a layout that
        grew: a bridge joined late). Begun empty, every element was unknown until it sent
        again, and a held element under a steady press sends only at its heartbeat: the
        press ended and came back under a new id. The newest readings that fit are kept."""
        k = min(self.depth, old.depth)
        count = old.count[old_rows]
        shift = np.where(count >= k, count - k, 0)
        src = (shift[:, None] + np.arange(k)[None, :]) % old.depth
        for name in self._RINGS:
            getattr(self, name)[rows, :k] = getattr(old, name)[old_rows[:, None], src]
        self.count[rows] = np.minimum(count, k)
        for name in self._PER_ELEMENT:
            getattr(self, name)[rows] = getattr(old, name)[old_rows]
        self.t_moment, self.silent_told, self.late_estimates = old.t_moment, old.silent_told, old.late_estimates
        self.retake, self.retaken = old.retake, old.retaken  # (a late onset not looked at yet is still owed)

    def record(self, rows: NDArray[np.int64], t: FloatArray, cycle: NDArray[np.uint64], dc: FloatArray,
               unique: bool, now: float, enter: FloatArray, leave: FloatArray,
               held: NDArray[np.bool_], on_time: NDArray[np.bool_], period: FloatArray) -> None:
        """One batch of readings in arrival order; ``unique``: each row occurs once;
        ``held``/``on_time``: each reading's kind (see the module); ``period``: each
        reading's sample period in s (NaN: not known).

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
        began = touched & ~prev
        if not unique and began.any():  # after another reading of its element in this batch: that one's flag
            order = np.argsort(rows, kind="stable")
            after = np.flatnonzero(rows[order][1:] == rows[order][:-1]) + 1
            began[order[after]] &= ~touched[order[after - 1]]
        if began.any():  # the newest onset of an element counts
            np.maximum.at(self.touch_began, rows[began], t[began])
            # an onset later than its frame's holds: that frame (or one after it, which
            # this held reading stands for) was taken with the element untouched
            with np.errstate(invalid="ignore"):
                self.retake |= bool((began & held & (t <= self.t_moment + 1e-9)).any())
        rank: int | NDArray[np.int64]  # each reading's slot after the element's newest
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
            held, on_time, period = held[idx], on_time[idx], period[idx]
        pos = (self.count[r] + rank) % self.depth
        self.t[r, pos] = t
        self.cycle[r, pos] = cycle
        self.dc[r, pos] = dc
        self.touched[r, pos] = touched
        self.held[r, pos] = held
        self.on_time[r, pos] = on_time
        self.period[r] = period
        self.silent_told = False
        if idx is None:
            self.count[r] += 1
        else:
            self.count += np.bincount(r, minlength=self.count.shape[0])
        self.arrival[r] = now
        if on_time.any():
            d = np.full(self.delay.shape[0], -math.inf)
            np.maximum.at(d, r[on_time], now - t[on_time])
            seen = np.isfinite(d)
            fade = np.exp(-np.clip(now - self.delay_at[seen], 0.0, None) / DELAY_FORGET_S)
            first = np.fmax(self.delay[seen] * fade, -math.inf)  # (fmax: -inf where no mark, NaN)
            second = np.fmax(self.delay2[seen] * fade, -math.inf)
            new = d[seen]
            top = new >= first
            runner_up = np.where(top, first, np.fmax(second, new))
            self.delay[seen] = np.where(top, new, first)
            self.delay2[seen] = np.where(np.isfinite(runner_up), runner_up, np.nan)
            self.delay_at[seen] = now

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

    def take(self, now: float, timeout: float, max_lag: float, force: bool = False,
             held_wait: float = 0.5) -> Moment | None:
        """The skin at the newest moment every live element has reported past (:meth:`moment`),
        if that moment advanced since the last one taken (or ``force``: a tare asks for
        one at once; or a held reading that began a touch came for a frame already
        taken: that frame again, once, at the first look after it came; counted in
        ``retaken``). None while it did not, and while an element is between a touched
        and an untouched reading at it: a press or release fell between two of its
        samples, so the moment is held back until it is past that (one sample period of
        that element at most; ``force`` does not wait)."""
        t = self.moment(now, timeout, max_lag, held_wait)
        retake, self.retake = self.retake, False  # one look only, whatever it finds
        if math.isnan(t):
            return self._all_silent()
        retake = retake and t <= self.t_moment
        if t <= self.t_moment and not (force or retake):
            return None
        dc, touched, t_sample, cycle, unknown, transition = self.at(t, now)
        if retake and not force and np.array_equal(touched, self.last_touched):
            return None  # the onset's element is not touched there after all (released since, or drift): no news
        if transition and not force:
            if math.isnan(self.hold_since):
                self.hold_since = t
            if self._in_transition(t, transition):
                return None
        self.hold_since = math.nan
        self.late_estimates += bool(self.late.any())
        self.retaken += retake
        self.t_moment = t
        self.last_touched = touched.copy()
        return Moment(t, dc, touched, t_sample, cycle, unknown, retake)

    def _all_silent(self) -> Moment | None:
        """No element is live (every bridge silent, or the gateway line down): once, a
        moment with every element unknown, so that subscribers learn that the contacts
        they hold are no longer known; then nothing until data comes back."""
        if self.silent_told or not math.isfinite(self.t_moment):
            return None
        self.silent_told = True
        n = self.count.shape[0]
        self.last_touched = np.zeros(n, dtype=bool)
        return Moment(self.t_moment, np.full((n, 2), np.nan), np.zeros(n, dtype=bool), np.full(n, np.nan),
                      np.zeros(n, dtype=np.uint64), np.ones(n, dtype=bool))

    def moment(self, now: float, timeout: float, max_lag: float, held_wait: float = 0.5) -> float:
        """The newest time every live element has reported past (NaN: no element live).
        Elements silent for ``timeout``, or periodic ones trailing the newest data by more
        than ``max_lag``, hold nothing back; a held element has reported past ``now`` minus
        its own delivery delay (at most ``held_wait``: see the module)."""
        live = (now - self.arrival <= timeout) & np.isfinite(self.settled)
        self.live = live
        if not live.any():
            self.holding = self.late = live
            return math.nan
        newest = float(self.settled[live].max())
        held = self._held_now()
        wait = min(held_wait, max_lag)
        through = np.where(held, np.fmax(self.settled, now - self._hold(wait, now)), self.settled)
        self.holding = live & (through >= newest - np.where(held, wait, max_lag))
        self.late = live & ~self.holding & ~held
        t = max(float(through[self.holding].min()), self.t_moment)
        # On mesh time the moment is a frame: the newest frame instant at or before it. (A
        # bridge timed from its arrivals, booting or cut off, would otherwise put the moment
        # between two frames, where no bridge on mesh time has a reading.)
        with np.errstate(invalid="ignore"):
            frames = np.where(self.on_time & (self.t <= t) & live[:, None], self.t, -math.inf)
        frame = float(frames.max()) if frames.size else -math.inf
        self.on_grid = math.isfinite(frame)
        if not self.on_grid:
            return t
        # Frames go on where no new reading came: a held reading stands for the frames
        # after it (an event-based skin sends little), so the moment moves on the frame
        # grid up to ``t`` (a periodic element's own readings reach ``t`` anyway).
        with np.errstate(invalid="ignore"):
            per = float(np.nanmin(np.where(live, self.period, np.nan))) if np.isfinite(self.period[live]).any() else math.nan
        if per > 0 and t - frame >= per:
            frame += math.floor((t - frame) / per) * per
        return max(frame, self.t_moment)

    def due(self, now: float, timeout: float, max_lag: float, held_wait: float = 0.5) -> float:
        """When the moment moves on to its next frame with no new data: the host time at
        which the held elements it waits for have reported past that frame (their holds
        run out), or ``inf`` when only new data moves it (an element it waits for is
        periodic, none is held, none is live, no rate known). An event-based skin sends
        little: a shell that estimated only when data came would take a press's
        frames up to a heartbeat late; it sleeps until this time or until data comes."""
        t = self.moment(now, timeout, max_lag, held_wait)
        live = self.live
        if self.retake and not math.isnan(t):  # a late onset: the frame taken without it, again
            return now
        if math.isnan(t) or not np.isfinite(self.period[live]).any():
            return math.inf
        # A frame not taken yet is there now (its holds ran out before anyone looked),
        # unless a transition holds it back: then the frame after it is what comes next.
        # (Naming the frame after it here put a shell that woke a moment past a due to
        # sleep a whole frame more: the press's first frame was skipped, +10 ms.)
        # Off the grid (no live element on mesh time: every reading timed from its arrival)
        # the moment moves on with ``now``, a held element's by the microsecond: a moment
        # less than a period past the last one taken is no new frame. (Called due at once,
        # it woke the contact loop back to back on an idle skin: a look that ships nothing
        # costs the pacer nothing, so nothing else spaced the looks: a core at 100 %.)
        per = float(np.nanmin(np.where(live, self.period, np.nan)))
        if t > self.t_moment and (self.on_grid or t >= self.t_moment + per):
            if not self._in_transition(t, self.at(t, now)[5]):
                return now
            nxt = t + per
        else:
            nxt = (t if self.on_grid else self.t_moment) + per
        with np.errstate(invalid="ignore"):
            waits = self.holding & ~(self.settled >= nxt)
        held = self._held_now()
        if not waits.any() or (waits & ~held).any():
            return math.inf
        # (a microsecond on: at the exact instant, rounding may leave the frame one short)
        return nxt + float(self._hold_for(nxt, min(held_wait, max_lag), now)[waits].max()) + 1e-6

    def unseen(self) -> bool:
        """Whether some element has a reading newer than the last moment taken. Until one
        comes, the frames after that moment repeat its held readings: an idle skin's
        (nothing touched, no contact left) need no look. A late onset of a frame taken
        (:meth:`take`) is worth one."""
        if self.retake:
            return True
        newest = self.t[self._all, (self.count - 1) % self.depth]
        with np.errstate(invalid="ignore"):
            return bool(((newest > self.t_moment) & (self.count > 0)).any())

    def _in_transition(self, t: float, transition: float) -> bool:
        """Whether the moment ``t`` is held back for an element between a touched and an
        untouched reading there (``transition``: the longest such interval, 0.0: none),
        counted from the first moment held back (:meth:`take`)."""
        since = t if math.isnan(self.hold_since) else self.hold_since
        return transition > 0 and t - since < transition

    def _onset_pending(self, moment: float, now: float, touched: NDArray[np.bool_], t_j: FloatArray,
                       held: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """Untouched held elements next to a touch that began within ``ONSET_WAIT`` of
        ``moment``, that have not reported past ``moment`` and whose delay plus
        ``ONSET_WAIT`` has not passed since: a change of theirs may still be retried."""
        pending = np.zeros(touched.shape[0], dtype=bool)
        fresh = touched & (moment - self.touch_began < ONSET_WAIT)
        if not fresh.any() or self.near.shape[0] == 0:
            return pending
        a, b = self.near[:, 0], self.near[:, 1]
        pending[b[fresh[a]]] = True
        pending[a[fresh[b]]] = True
        with np.errstate(invalid="ignore"):
            reported = self.settled >= moment - 1e-9
            waited = now - moment >= np.nan_to_num(self._marks(now)[0], nan=0.0) + ONSET_WAIT
        return pending & ~touched & held & (t_j < moment - 1e-9) & ~reported & ~waited

    def _held_now(self) -> NDArray[np.bool_]:
        """Whether each element's newest reading is held (stands for the frames after it)."""
        return self.held[self._all, (self.count - 1) % self.depth]

    def _marks(self, now: float) -> tuple[FloatArray, FloatArray]:
        """Each element's delivery delay marks, forgotten down to ``now``, with their margin:
        (highest, second highest; the highest where only one delay is known). NaN: none known."""
        fade = np.exp(-np.clip(now - self.delay_at, 0.0, None) / DELAY_FORGET_S)
        second = np.where(np.isnan(self.delay2), self.delay, self.delay2)
        return (self.delay * fade * DELAY_FACTOR + DELAY_MARGIN, second * fade * DELAY_FACTOR + DELAY_MARGIN)

    def _onset_end(self) -> FloatArray:
        """Per element, the last instant of the onset window (``ONSET_WAIT``) of the earliest
        touch on it or on a neighbour now (inf: no touch there). Up to that instant an
        untouched neighbour is unknown until it reported (:meth:`_onset_pending`); past it,
        a change of the element shapes a contact (a slide across a seam seen on one side
        only is two disks) and it is waited for by its highest delay lately."""
        touched = self.touched[self._all, (self.count - 1) % self.depth] & (self.count > 0)
        began = np.where(touched, self.touch_began, math.inf)
        if touched.any() and self.near.shape[0]:
            own = began.copy()
            a, b = self.near[:, 0], self.near[:, 1]
            np.minimum.at(began, b, own[a])
            np.minimum.at(began, a, own[b])
        return began + (ONSET_WAIT - 1e-9)

    def _hold(self, wait: float, now: float) -> FloatArray:
        """How far behind ``now`` each held element has reported: a change of its would have
        reached the host by its delivery delay (with a margin); ``wait`` at most, and while
        its delay is not known yet. Away from a touch (and before a touch's onset window
        ended) the delay is its second highest lately: one retried frame of an idle element
        held every frame of the skin back; past the onset window of a touch on it or next
        to it, the highest (:meth:`_onset_end`). The marks forget between the element's
        readings too (a heartbeat may be seconds apart)."""
        full, second = self._capped_marks(wait, now)
        by_second, end = now - second, self._onset_end()
        return now - np.where(np.isinf(end), by_second, np.fmax(now - full, np.fmin(by_second, end)))

    def _hold_for(self, frame: float, wait: float, now: float) -> FloatArray:
        """Each element's hold for ``frame`` (:meth:`_hold`): the time after ``frame`` at
        which it has reported past it."""
        full, second = self._capped_marks(wait, now)
        return np.where(frame > self._onset_end(), full, second)

    def _capped_marks(self, wait: float, now: float) -> tuple[FloatArray, FloatArray]:
        """:meth:`_marks`, each at most ``wait`` and ``wait`` where not known yet."""
        full, second = self._marks(now)
        return np.fmin(full, wait), np.fmin(second, wait)  # (fmin: ``wait`` where a mark is NaN)

    def at(self, moment: float, now: float = math.inf) -> tuple[FloatArray, NDArray[np.bool_], FloatArray,
                                                               NDArray[np.uint64], NDArray[np.bool_], float]:
        """(ΔC (n, 2), touched, sample time, cycle, unknown) of each element at ``moment``
        (see the module for which reading counts; an unknown element has NaN/False; at
        host time ``now``, an untouched neighbour of a touch just begun may still be
        unknown: ``ONSET_WAIT``) and
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
        # A held reading on mesh time followed by one on mesh time is no transition: its
        # bridge sampled every frame between the two and would have sent a change, so the
        # frames before the next reading are known (holding them back put a press's first
        # frame off by one whenever a neighbour's touch began a frame later: +10 ms).
        exact = self.held[rows, j] & self.on_time[rows, j] & self.on_time[rows, nxt]
        changing = (self.holding & after.any(axis=1) & ~none_before & ~exact
                    & (self.touched[rows, j] != self.touched[rows, nxt]))
        gap = float((self.t[changing, nxt[changing]] - self.t[changing, j[changing]]).max()) if changing.any() else 0.0
        newest = (self.count - 1) % self.depth
        j = np.where(self.holding, j, newest)  # not waited for: its newest reading, if that still stands
        dc, touched = self.dc[rows, j], self.touched[rows, j]
        t_j = self.t[rows, j]
        held = self.held[rows, j]
        # Which reading stands for the moment: a mesh-time reading until the element's next
        # sample was due (of this very frame; at a frame of a finer rate between its own
        # samples, its last one: bridges may sample at different rates; a quarter of the
        # finest period covers rounding of the host's map), a held one at or before it, a
        # reading timed from its arrival within one period before it.
        with np.errstate(invalid="ignore"):
            age = moment - t_j
            tol = np.where(np.isfinite(self.period), self.period, np.inf)  # no rate (protocol 1): as before
            rates = self.period[self.live & np.isfinite(self.period)]
            slack = 0.25 * float(rates.min()) if rates.size else 0.0
            stands = np.where(self.on_time[rows, j], age < tol - slack, age <= tol)
        stands = (stands | held) & (age >= -1e-9)
        unknown = ~self.live | ~stands | (self.count == 0) | (self.holding & none_before)
        unknown |= np.isnan(dc).all(axis=1)  # no ΔC: no baseline yet (at start, after a tare), or forgotten
        unknown |= self._onset_pending(moment, now, touched & ~unknown, t_j, held)
        if unknown.any():
            dc[unknown] = np.nan
            touched[unknown] = False
        return dc, touched, t_j, self.cycle[rows, j], unknown, gap
