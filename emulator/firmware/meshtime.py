"""Mesh time: one clock for the whole skin, carried by the beacons (docs/time.md).

Every bridge counts cycles of its own crystal (:class:`Crystal`: ±50 ppm from nominal,
its own epoch). A skin is a camera only if every element samples the same instant, so
the bridges agree on a *global* time: the cycle counter of one bridge, the **time root**
(the lowest-id gateway alive). This is FTSP's scheme (flooding time synchronisation):

* a beacon carries the sender's estimate of global time, stamped by the transceiver at
  the cycle its transmission starts (:meth:`MeshClock.stamp`), with the root's id and the
  number of the root's round it descends from;
* the receiver stamps the same start-of-frame instant with its own cycle counter, and the
  pair (local, global) is a reference point; a regression over the last ``table`` points
  gives offset and skew (:meth:`MeshClock.global_at`), so a bridge extrapolates between
  beacons with the skew it measured rather than the nominal rate;
* a reference point is taken only from a round newer than the last one taken (the round
  number floods outwards from the root), so information never flows back towards the root,
  and from any neighbour: a relay that dies costs nothing, another neighbour carries the
  next round;
* a gateway that hears no round for ``root_timeout`` becomes the root itself, carrying on
  the global time it had (its fit, frozen), so the skin's time does not jump when the root
  dies; a lower-id root that appears takes over, and a bridge whose fit disagrees with it
  by more than ``throwout`` for several points in a row starts its table again.

Everything here is in the bridge's own cycles; the firmware converts to and from the
simulation's ticks through its :class:`Crystal`. Pure: no I/O, no clock of its own.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from cellbridge.protocol import MeshTime

_PPB = 1_000_000_000


class Crystal:
    """A chip's free-running cycle counter against true time (simulation ticks at 50 MHz).

    ``local(tick) = epoch + floor(tick * (1 + ppm·1e-6))``, in exact integer arithmetic
    (parts per billion), so that :meth:`tick_at` is its exact inverse.
    """

    def __init__(self, ppm: float = 0.0, epoch: int = 0) -> None:
        if not -1000.0 <= ppm <= 1000.0:
            raise ValueError(f"crystal offset must be within ±1000 ppm, got {ppm!r}")
        if epoch < 0:
            raise ValueError(f"epoch must be >= 0, got {epoch!r}")
        self.num = _PPB + round(ppm * 1000)
        self.epoch = epoch

    def local(self, tick: int) -> int:
        """The cycle counter at simulation tick ``tick``."""
        return self.epoch + tick * self.num // _PPB

    def tick_at(self, local: int) -> int:
        """The first tick at which the counter reads ``local`` or more."""
        return -((self.epoch - local) * _PPB // self.num)


def _newer(a: int, b: int) -> bool:
    """Round ``a`` is newer than round ``b`` (16-bit serial-number arithmetic)."""
    return 0 < (a - b) & 0xFFFF < 0x8000


@dataclass(frozen=True)
class MeshClockConfig:
    """Mesh-time parameters, in the bridge's cycles (50 MHz nominal)."""

    table: int = 8  #: reference points in the regression (FTSP's 8)
    min_points: int = 2  #: points before a bridge calls itself synced and passes time on
    root_timeout: int = 75_000_000  #: no new round for this long (1.5 s): the root is gone
    boot_listen: int = 30_000_000  #: a gateway listens this long (0.6 s) for a root after boot
    #: No reference point for this long (5 s): the bridge's samples say it has no mesh time.
    #: Its fit is still used, and still close (the skew is measured): this is a flag for
    #: the host, which then times those samples from their arrival.
    stale_after: int = 250_000_000
    throwout: int = 2_500  #: a point this far (50 µs) from the fit is an outlier ...
    max_outliers: int = 3  #: ... and after this many in a row the table starts again
    max_skew: float = 500e-6  #: a fit steeper than this is nonsense (crystals are ±50 ppm)


class MeshClock:
    """One bridge's estimate of global time (sans-I/O: fed beacons and local cycles).

    Args:
        me: this bridge's id.
        eligible_root: whether it may become the time root (gateways only).
        config: timing parameters.
        boot_local: the local cycle at power-on (root timeouts count from there).
    """

    def __init__(self, me: int, eligible_root: bool, config: MeshClockConfig = MeshClockConfig(),
                 boot_local: int = 0) -> None:
        self.me = me
        self.eligible_root = eligible_root
        self.config = config
        self.root: int | None = None  #: the time root followed (or ``me``); None: none yet
        self.seq = 0  #: the newest round taken (or sent, as root)
        self._points: deque[tuple[int, int]] = deque(maxlen=config.table)  # (local, global)
        # local cycle of the last round taken; at boot a gateway listens ``boot_listen`` for
        # a root before it becomes one (a skin that boots together has one root at once)
        self._heard = boot_local - (config.root_timeout - config.boot_listen if eligible_root else 0)
        self._outliers = 0
        # the root given up last, the newest round taken from it, and until when (local)
        # beacons of neighbours that have not timed out yet may still carry its rounds
        self._gone: tuple[int, int, int] | None = None
        # fit: global = local + offset + skew * (local - x0)
        self._x0 = 0
        self._offset = 0.0
        self._skew = 0.0
        self.counters = {"time_points": 0, "time_outliers": 0, "time_resyncs": 0, "root_changes": 0,
                         "time_ignored": 0, "time_echoes": 0}

    # -- the estimate -----------------------------------------------------------------
    @property
    def is_root(self) -> bool:
        return self.root == self.me

    def has_fit(self) -> bool:
        return self.is_root or len(self._points) >= self.config.min_points

    def synced(self, local: int) -> bool:
        """Whether samples taken at ``local`` carry mesh time (a fit, fresh enough)."""
        if self.is_root:
            return True
        return len(self._points) >= self.config.min_points and local - self._heard <= self.config.stale_after

    def global_at(self, local: int) -> int:
        """Global time at local cycle ``local`` (the identity with no fit yet)."""
        return local + round(self._offset + self._skew * (local - self._x0))

    def local_at(self, global_time: int) -> int:
        """The local cycle at which global time reaches ``global_time`` (inverse of
        :meth:`global_at` to within a cycle; the smallest local cycle at or after it)."""
        guess = self._x0 + round((global_time - self._x0 - self._offset) / (1.0 + self._skew))
        while self.global_at(guess) < global_time:
            guess += 1
        while self.global_at(guess - 1) >= global_time:
            guess -= 1
        return guess

    def skew(self) -> float:
        """Rate of global time against local time, minus one (the measured crystal error)."""
        return self._skew

    # -- beacons ------------------------------------------------------------------------
    def stamp(self, local: int) -> MeshTime | None:
        """The time part of a beacon whose transmission starts at ``local``; None when this
        bridge has no time to pass on (no root, or no fit yet)."""
        if self.root is None or not self.has_fit():
            return None
        return MeshTime(self.root, self.seq, self.global_at(local) & 0xFFFF_FFFF_FFFF_FFFF)

    def next_round(self, local: int) -> None:
        """The root starts a new round (once per beacon period, before stamping)."""
        if self.is_root:
            self.seq = (self.seq + 1) & 0xFFFF
            self._heard = local

    def heard(self, t: MeshTime, local: int) -> bool:
        """A beacon's time, its start of frame stamped ``local`` here; True when taken."""
        c = self.counters
        gone = self._gone
        if gone is not None and t.root == gone[0] and not _newer(t.seq, gone[1]) and local <= gone[2]:
            # an echo of the root this bridge gave up: a neighbour that has not timed out
            # yet still passes its last rounds on. Following it again (a gateway that just
            # took over cleared its table for it, then ran on its bare crystal: 7 µs/s off)
            # would bring back a root that is gone. Only for ``root_timeout`` after giving it
            # up (every neighbour has timed out by then): a root that rebooted numbers its
            # rounds from 1 again, and must be heard.
            c["time_echoes"] += 1
            return False
        if self.is_root:
            if t.root < self.me:  # a lower-id root: follow it
                self._follow(t, local)
                return self._take(t, local)
            c["time_ignored"] += 1
            return False
        if self.root is None:
            # the first root, or the next after ours timed out (that one carries the old
            # root's time on: the table stays, an outlier check guards it)
            self.root = t.root
            return self._take(t, local)
        if t.root < self.root:  # a lower root: back after a failover, or another skin's
            self._follow(t, local)
            return self._take(t, local)
        if t.root == self.root and _newer(t.seq, self.seq):
            return self._take(t, local)
        c["time_ignored"] += 1
        return False

    def tick(self, local: int) -> None:
        """Timeouts at ``local``: a root silent for ``root_timeout`` is given up, and a
        gateway then becomes the root, carrying on its own estimate of global time."""
        if self.is_root or local - self._heard <= self.config.root_timeout:
            return
        if self.root is not None:
            self._gone = (self.root, self.seq, local + self.config.root_timeout)
        if self.eligible_root:
            # Freeze the fit: the root's global time is its estimate as it was, so the skin's
            # time carries on instead of jumping to this bridge's own counter.
            self.root = self.me
            self.seq = (self.seq + 1) & 0xFFFF
            self._heard = local
            self.counters["root_changes"] += 1
        elif self.root is not None:
            self.root = None  # take the next root heard, whoever it is

    def next_wake(self) -> int:
        """The local cycle at which :meth:`tick` has something to do."""
        return self._heard + self.config.root_timeout + 1

    # -- internals ----------------------------------------------------------------------
    def _follow(self, t: MeshTime, local: int) -> None:
        """Follow the lower root of ``t``. Its time is the skin's when it agrees with this
        bridge's fit within ``throwout`` (the root gateway back after a failover or a cut:
        the gateway that took over carried its time on): the table stays, so the skin's
        time neither jumps nor loses its measured skew (a cleared table left every bridge
        unsynced for a round, its samples off mesh time, then on one point and a bare
        crystal: 27 µs off). Another skin's time starts the table again."""
        self.counters["root_changes"] += 1
        self.root = t.root
        if len(self._points) < self.config.min_points or abs(self.global_at(local) - t.time) > self.config.throwout:
            self._clear()

    def _clear(self) -> None:
        self._points.clear()
        self._outliers = 0
        self._offset = 0.0
        self._skew = 0.0
        self._x0 = 0

    def _take(self, t: MeshTime, local: int) -> bool:
        cfg = self.config
        c = self.counters
        if len(self._points) >= cfg.min_points and abs(self.global_at(local) - t.time) > cfg.throwout:
            c["time_outliers"] += 1
            self._outliers += 1
            if self._outliers <= cfg.max_outliers:
                return False
            c["time_resyncs"] += 1  # the root's time moved (a new root): start again
            self._clear()
        self._outliers = 0
        self.seq = t.seq
        self._heard = local
        self._points.append((local, t.time))
        c["time_points"] += 1
        self._fit()
        return True

    def _fit(self) -> None:
        """Least squares of offset (global - local) on local, centred for precision."""
        pts = self._points
        n = len(pts)
        x0 = pts[-1][0]
        xs = [x - x0 for x, _ in pts]
        ys = [g - x for x, g in pts]
        xm = sum(xs) / n
        ym = sum(ys) / n
        sxx = sum((x - xm) ** 2 for x in xs)
        skew = 0.0
        if n >= 2 and sxx > 0:
            skew = sum((x - xm) * (y - ym) for x, y in zip(xs, ys)) / sxx
            if abs(skew) > self.config.max_skew:  # inconsistent points: keep only the newest
                c = self.counters
                c["time_resyncs"] += 1
                last = pts[-1]
                pts.clear()
                pts.append(last)
                skew, xm, ym = 0.0, 0.0, float(last[1] - last[0])
        self._x0 = x0
        self._skew = skew
        self._offset = ym - skew * xm


__all__ = ["Crystal", "MeshClock", "MeshClockConfig"]


class Timebase:
    """What the sampler needs of time: a bridge's crystal and its mesh clock together,
    in simulation ticks (the owner's time) and sample indices.

    Sample ``k`` at ``rate`` Hz starts its C1 gate at global time ``k / rate`` seconds,
    that is global cycle ``k * clock_hz // rate`` (global cycles are the root's).
    """

    def __init__(self, crystal: Crystal, clock: MeshClock, clock_hz: int) -> None:
        self.crystal = crystal
        self.clock = clock
        self.clock_hz = clock_hz

    def local(self, tick: int) -> int:
        return self.crystal.local(tick)

    def synced(self, tick: int) -> bool:
        return self.clock.synced(self.crystal.local(tick))

    def gate_tick(self, index: int, rate: int) -> int:
        """The tick at which this bridge starts the C1 gate of sample ``index``."""
        return self.crystal.tick_at(self.clock.local_at(index * self.clock_hz // rate))

    def first_index(self, tick: int, rate: int) -> int:
        """The first sample index whose gate starts (in global time) at or after ``tick``."""
        g = self.clock.global_at(self.crystal.local(tick))
        return -(-g * rate // self.clock_hz)

    def after_local(self, tick: int, cycles: int) -> int:
        """The tick ``cycles`` of this bridge's own clock after ``tick``."""
        return self.crystal.tick_at(self.crystal.local(tick) + cycles)


__all__ += ["Timebase"]
