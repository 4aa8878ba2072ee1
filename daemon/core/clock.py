"""Per-bridge clock sync: bridge cycle counter → host time (offset and skew).

A sample carries the bridge's cycle count at the start of its gate; subscribers want
host time. The host only sees *arrival* times, which are the sample time plus a delay
that is never negative (gate, queueing, hops, serial) and varies. So the mapping is fit
to the **lower envelope** of (bridge time, arrival − bridge time): per block of bridge
time the smallest residual is kept (the least-delayed frame), and a line through the
block minima gives offset and skew (crystal error, tens of ppm). Host times are thus
"at the earliest this could have arrived", consistent across bridges to within the
smallest delay, and free of the delay's jitter.

Counter wrap: cycles are taken modulo ``2**bits`` and unwrapped by the short way.
Bridge reset: a frame arriving more than ``max_jump`` seconds *before* its predicted
time; one whose count runs back more than ``max_jump`` or that arrives more than
``max_jump`` late just after the bridge's frame numbering restarted; or counts that stay
that far back for ``confirm`` bridge seconds on end: each restarts the fit (counted in
``resets``) instead of publishing nonsense times. Otherwise a frame far behind is an old
frame delayed (a queue or a long route in the mesh) and is kept out of the fit, and a
frame far late is a long delay, never a reset.
The skew is bounded by ``max_skew`` (crystals are tens of ppm off): over a few blocks,
wandering delays would otherwise pass for a clock running percents fast.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np
from cellbridge.daemon.core.wire import PART_BYTES, ReadoutColumns
from numpy.typing import NDArray

#: Global cycles fit 62 bits: an index whose instant does not is nonsense.
_CYCLE_END = 1 << 62
_NOT_HELD = (-1, 0.0, -1)  # SkinClock.held of a gateway with no point held


class BridgeClock:
    """Clock model of one bridge; feed ``observe(cycle, arrival)``, then map with ``to_host``."""

    def __init__(self, hz: float, bits: int = 64, block: float = 1.0, blocks: int = 64,
                 max_jump: float = 1.0, confirm: float = 2.0,
                 max_skew: float = 500e-6) -> None:
        self.hz = float(hz)
        self.bits = bits
        self._mod = 1 << bits
        self.block = block
        self.max_jump = max_jump
        self.steps = 0
        self.confirm = confirm
        self.max_skew = max_skew
        self._late_from: float | None = None  # bridge time of a run of frames far behind (see observe)
        self._suspect = False  # the frame numbering restarted: the next odd frame is a reset
        self._minima: deque[tuple[float, float]] = deque(maxlen=blocks)  # (x, residual) per closed block
        self._ref_raw: int | None = None  # raw cycle at the fit's origin
        self._ref_arrival = 0.0
        self._x_last = 0.0  # bridge seconds since the origin, of the newest observation
        self._cur: tuple[float, float] | None = None  # running minimum of the open block
        self._cur_start = 0.0
        self.offset = 0.0  # host = ref_arrival + offset + x·(1 + skew)
        self.skew = 0.0
        self.resets = 0
        self.observations = 0

    @property
    def synced(self) -> bool:
        return self._ref_raw is not None

    def _x(self, raw: int) -> float:
        d = (raw - self._ref_raw) % self._mod  # type: ignore[operator]  # called only once synced (_ref_raw set)
        if d >= self._mod >> 1:
            d -= self._mod
        return d / self.hz

    def _restart(self, raw: int, arrival: float) -> None:
        self._ref_raw = raw
        self._ref_arrival = arrival
        self._minima.clear()
        self._cur = (0.0, 0.0)
        self._cur_start = 0.0
        self._x_last = 0.0
        self._late_from = None
        self._suspect = False
        self.offset = 0.0
        self.skew = 0.0

    def restart(self, cycle: int, arrival: float, count: bool = True) -> None:
        """Begin the fit again at ``cycle``, arrived at ``arrival``, and count it: the owner
        knows the counts jumped (the skin's time went back), which :meth:`observe` only
        concludes after ``confirm`` bridge seconds of counts behind the newest. ``count``
        False: no reset, the owner's points before were only later than they could be."""
        self.resets += count
        self._restart(int(cycle) % self._mod, arrival)

    def suspect_reset(self) -> None:
        """The bridge's frame numbering restarted (it does when it starts): a frame that does not fit is a reset."""
        self._suspect = True

    def _rebase(self, raw: int, dx: float) -> None:
        """Move the origin to ``raw`` (dx bridge seconds later); residuals are unchanged."""
        self._ref_raw = raw
        self._ref_arrival += dx
        self._minima = deque(((x - dx, r) for x, r in self._minima), maxlen=self._minima.maxlen)
        if self._cur is not None:
            self._cur = (self._cur[0] - dx, self._cur[1])
        self._cur_start -= dx
        self._x_last -= dx

    def observe(self, cycle: int, arrival: float) -> bool:
        """The newest sample's cycle count and the frame's arrival time. True if the
        bridge's clock restarted (reset) and the fit began again."""
        self.observations += 1
        raw = int(cycle) % self._mod
        if self._ref_raw is None:
            self._restart(raw, arrival)
            return False
        x = self._x(raw)
        predicted = self._ref_arrival + self.offset + x * (1.0 + self.skew)
        # A frame whose count is far behind the newest is mostly an old frame delayed (a
        # queue or a long route in the mesh), and one far later than predicted is a long
        # delay: restarting on either would anchor the fit to its delay. A reset is a frame
        # that does not fit just after the bridge's frame numbering restarted, or counts
        # that stay far behind for ``confirm`` bridge seconds on end.
        behind = x < self._x_last - self.max_jump
        late = arrival - predicted > self.max_jump
        if not behind:
            self._late_from = None
        elif self._late_from is None or x < self._late_from:
            self._late_from = x
        confirmed = (self._suspect and (behind or late)) or (
            behind and x - self._late_from >= self.confirm)  # type: ignore[operator]  # behind: _late_from was set just above
        if predicted - arrival > self.max_jump or confirmed:  # no delay makes a frame arrive early
            self.resets += 1
            self._restart(raw, arrival)
            return True
        self._suspect = False
        if behind:
            return False  # kept out of the fit: an old frame says nothing about the envelope
        if x > (self._mod >> 3) / self.hz:  # stay far from half the modulus: move the origin
            self._rebase(raw, x)
            x = 0.0
        self._x_last = max(self._x_last, x)
        r = arrival - self._ref_arrival - x
        if x - self._cur_start >= self.block:  # a block closed: refit (once a block, not per frame)
            if self._cur is not None:
                self._minima.append(self._cur)
            self._cur, self._cur_start = (x, r), x
            self._fit()
        elif self._cur is None or r < self._cur[1]:
            self._cur = (x, r)
            below = r - (self.offset + self.skew * x)
            if below < 0 or len(self._minima) < 2:  # a new lowest point: lower the line onto it
                self._fit() if len(self._minima) < 2 else setattr(self, "offset", self.offset + below)
        return False

    def host_step(self, delta: float) -> None:
        """The host's wall clock stepped by ``delta`` seconds (the service sees it as a change
        of wall minus monotonic time): every arrival from now on is ``delta`` later, so
        the envelope, its minima and the line move by it at once."""
        self._minima = deque(((x, r + delta) for x, r in self._minima), maxlen=self._minima.maxlen)
        if self._cur is not None:
            self._cur = (self._cur[0], self._cur[1] + delta)
        self.offset += delta
        self.steps += 1

    def _fit(self) -> None:
        """Least-squares line through the closed blocks' minima (the open block's first
        points are no minimum yet), then lowered onto the envelope."""
        pts = list(self._minima)
        if len(pts) < 3:
            if self._cur is not None:
                pts.append(self._cur)
            self.offset, self.skew = min(p[1] for p in pts), 0.0
            return
        # Crystals are off by tens of ppm: a steeper line is the delays' wander, not skew.
        icpt, slope = _line(pts, self.max_skew)
        icpt += min(0.0, min(p[1] - (icpt + slope * p[0]) for p in pts))
        self.offset, self.skew = icpt, slope

    def params(self) -> tuple[int, float, float, float]:
        """(reference raw cycle, host time at it, 1 + skew, Hz): host = t + ((c - ref) mod 2^bits)/Hz·(1 + skew)."""
        if self._ref_raw is None:
            return 0, math.nan, 1.0, self.hz
        return self._ref_raw, self._ref_arrival + self.offset, 1.0 + self.skew, self.hz

    def to_host(self, cycles: NDArray[np.uint64]) -> NDArray[np.float64]:
        """Host times (s) of cycle counts of this bridge (vectorised, wrap-aware)."""
        ref, t, k, hz = self.params()
        n = cycles.shape[0]
        return rows_to_host(cycles, np.full(n, ref, dtype=np.uint64), np.full(n, t), np.full(n, k), np.full(n, hz),
                            self.bits)


    def to_host_one(self, cycle: int) -> float:
        """:meth:`to_host` of one cycle count (the same arithmetic, without arrays: a readout
        record's point, a hundred a second per gateway)."""
        ref, t, k, hz = self.params()
        bits = self.bits
        d = (cycle - ref) % (1 << 64)
        if bits < 64:
            d &= (1 << bits) - 1
        x = float(d)
        if d >= 1 << (bits - 1):
            x -= float(1 << bits)
        return t + x / hz * k


def _line(pts: list[tuple[float, float]], max_slope: float = math.inf) -> tuple[float, float]:
    """Least-squares (intercept, slope) through points (x, residual), the slope within ±max_slope."""
    n = len(pts)
    mx = sum(p[0] for p in pts) / n
    mr = sum(p[1] for p in pts) / n
    sxx = sum((p[0] - mx) ** 2 for p in pts)
    slope = sum((p[0] - mx) * (p[1] - mr) for p in pts) / sxx if sxx > 0 else 0.0
    slope = min(max(slope, -max_slope), max_slope)
    return mr - slope * mx, slope


def rows_to_host(cycles: NDArray[np.uint64], ref: NDArray[np.uint64], t: NDArray[np.float64],
                 k: NDArray[np.float64], hz: NDArray[np.float64], bits: int) -> NDArray[np.float64]:
    """Host times of samples of many bridges at once, from each row's bridge :meth:`BridgeClock.params`."""
    d = cycles.astype(np.uint64, copy=False) - ref  # uint64 arithmetic wraps modulo 2**64
    if bits < 64:
        d &= np.uint64((1 << bits) - 1)
    x = d.astype(np.float64)
    x = np.where(d >= np.uint64(1 << (bits - 1)), x - float(1 << bits), x) / hz
    return t + x * k


class SkinClock:
    """Mesh time → host time, one map for the whole skin.

    Every bridge on mesh time samples on one global clock (the time root's counter), and
    the gateways, one hop from the host over a short, steady serial line, measure how it
    maps: each gateway's own points (the global cycle of its own sample's gate, or of its
    readout record's end, with the arrival) feed the lower envelope of one
    :class:`BridgeClock` (docs/time.md). A frame's host time is fixed when it is first
    asked for (the map keeps learning; two bridges' samples of one frame carry one time).

    Jumps are believed only when confirmed: a gateway's point the map puts more than
    ``slack`` after its own arrival (a new root on another time, or a frame corrupted past
    the CRC), or more than ``slack`` behind that gateway's newest point (the skin's time
    went back; or records of frames seconds old, which a confused relay may still pass
    on in a burst), moves the map only once ``confirm`` such points in a row, over at least
    ``confirm_time`` s of arrivals, agree with each other (their mesh times as far apart as
    their arrivals); until then, frames behind such a point are not mapped. A point the map
    takes in between starts the count again.

    A point the map puts between ``tolerance`` and ``slack`` after its arrival would lower
    the envelope at once, and the envelope only ever goes down: one index corrupted past
    the CRC a few frames ahead moved every frame's host time that much early for a minute
    (and the frames' deadlines with it, before their records could come). Such a point is
    held until the same gateway's next point agrees with it (its mesh time as far after
    as its arrival, within ``tolerance``): a true earlier arrival is taught one point
    late, a wrong index never.
    """

    def __init__(self, hz: float, slack: float = 0.25, memory: float = 10.0, memory_keys: int = 2500,
                 confirm: int = 3, confirm_time: float = 0.1, tolerance: float = 0.005) -> None:
        self.hz = float(hz)
        self.slack = slack
        self.tolerance = tolerance
        # gateway -> its point that would lower the map, unconfirmed: (g, arrival, its frame's cycle)
        self._held: dict[int, tuple[int, float, int]] = {}
        self.confirm, self.confirm_time = confirm, confirm_time
        self.memory = memory  # s of frames whose host time is kept once given
        self.memory_keys = memory_keys  # frames kept before forgetting old ones is looked at
        self.map = BridgeClock(hz, bits=64)
        self.resets = 0
        self._memo: dict[int, float] = {}  # global cycle of a frame -> its host time
        self._newest = -1
        self._jump: list[tuple[int, float]] = []  # (g, arrival) of gateway points in a row ahead of or behind the map
        self._by_gateway: dict[int, int] = {}  # gateway -> newest frame (global cycle) of its own the map took
        self._back = -1  # while a jump back waits for confirmation: frames behind this are not believed

    @property
    def synced(self) -> bool:
        return self.map.synced

    def teach(self, gateway: int, g: int, now: float, frame: int = -1) -> bool:
        """A point of ``gateway``'s own: global cycle ``g`` reached the host at ``now``. True
        when the map began again (the skin's time jumped, confirmed): frame times given
        before no longer hold. ``frame``: the global cycle of the frame the point is of, when
        not ``g`` (a record's point is its frame's gate start plus its age): what
        :meth:`held` is asked with, and how far behind the gateway's newest it is: by their
        frames, not their points (a record written later than its span says no age and
        teaches its gate start: on a deep schedule, 0.3 s and more before the point of the
        gateway's record before, it passed for the skin's time gone back, and was refused)."""
        key = g if frame < 0 else frame
        floor = self._floor(gateway)
        back = key < floor
        # where the map puts the point (NaN: no map yet), worked out once for both checks (to_host_one:
        # the arithmetic of to_host without arrays, as every readout record teaches a point)
        at = self.map.to_host_one(g) if self.map.synced else math.nan
        if not back and self._hold(gateway, g, now, at, key):
            return False
        jumped = taught = self._believed(g, now, back, at)
        if taught and back:
            self.map.restart(g, now)  # the skin's time went back: two points agree
        elif taught:
            jumped = self.map.observe(g, now)
        if jumped:
            self._by_gateway.clear()
        if taught:
            self._by_gateway[gateway] = max(self._by_gateway.get(gateway, -1), key) if not jumped else key
        self._back = self._floor(gateway) if back and not taught else -1
        if jumped:
            self.resets += 1
            self._memo.clear()
            self._newest = -1
        return jumped

    def anew(self, g: int, now: float) -> None:
        """Begin the map's envelope again at the point (``g``, ``now``), the skin's time
        unchanged: the points it learned from were all later than the skin's (records that
        did not say their age, placed at their frame's gate start), and the quicker points
        from now on would lower it by that step, which the skew fit, its line through the
        old blocks' minima and the new, ran on downwards past the newest (frames put up to
        4 ms before their gate start for a minute). The frames already mapped keep their
        host times; no jump is counted."""
        if not self.map.synced:
            return
        self.map.restart(g, now, count=False)
        self._held.clear()
        self._jump = []

    def _hold(self, gateway: int, g: int, now: float, at: float, frame: int) -> bool:
        """Whether ``gateway``'s point (``g``, ``now``) is held back: the map puts it (at
        ``at``) more than ``tolerance`` (and at most ``slack``) after its arrival, and the
        gateway's previous point was not one such that agrees with it (see the class)."""
        held = self._held.pop(gateway, None)
        if not self.map.synced:
            return False
        ahead = at - now
        if not self.tolerance < ahead <= self.slack:
            return False
        if held is not None and g > held[0] and abs((g - held[0]) / self.hz - (now - held[1])) <= self.tolerance:
            return False
        self._held[gateway] = (g, now, frame)
        return True

    def held(self, gateway: int, frame: int) -> bool:
        """Whether ``gateway``'s point held back is of the frame at global cycle ``frame`` (the
        frame is not believed either: a record of it may hold an older sample under a wrong
        index). By the frame, not the point: each part of a record says its own age, and a
        part after the first, its point later by the line's time, was taken as that frame's."""
        return self._held.get(gateway, _NOT_HELD)[2] == frame

    def before(self, g: int, now: float) -> bool:
        """Whether the map puts global cycle ``g`` no more than ``tolerance`` after ``now``
        (or has no map yet): a frame whose gates could have started before a record of it
        arrived at ``now``."""
        return not self.map.synced or self.map.to_host_one(g) - now <= self.tolerance

    def _floor(self, gateway: int) -> int:
        """The global cycle more than ``slack`` behind the newest of ``gateway``'s own points
        the map took (its points come in order: one behind that is the skin's time gone back,
        or a corrupted frame; another gateway's line may lag)."""
        return self._by_gateway.get(gateway, -1) - int(self.slack * self.hz)

    def _believed(self, g: int, now: float, back: bool, at: float) -> bool:
        """Whether a gateway's point of global cycle ``g``, arrived at ``now``, may teach the
        map: at once unless the map puts it (at ``at``) more than ``slack`` after its own
        arrival or it is ``back``; then once ``confirm`` such points in a row, over
        ``confirm_time``, agree."""
        if not self.map.synced or (not back and at <= now + self.slack):
            if self._jump:  # (a new list for every point taught, most of them with none waiting)
                self._jump = []
            return True
        run = self._jump
        if run and not abs((g - run[-1][0]) / self.hz - (now - run[-1][1])) <= self.slack:
            run.clear()  # not the same jump: a point of its own
        run.append((g, now))
        if len(run) < self.confirm or now - run[0][1] < self.confirm_time - 1e-9:
            return False
        run.clear()
        return True

    def frame_time(self, g: int, now: float) -> float:
        """:meth:`frame_times` of one frame (a readout record's), without arrays: the same
        steps on one key, the map's point by :meth:`BridgeClock.to_host_one` (the arithmetic
        of ``to_host``, to the bit). A frame is mapped once, at its first record: arrays
        cost 12 µs there against 0.6, a hundred frames a second."""
        memo, back = self._memo, self._back
        t = memo.get(g)
        if t is not None and g >= back:
            return t
        if g < 0 or g < back or not self.map.synced:
            return math.nan  # (behind a jump back awaiting confirmation, or no map yet)
        t = self.map.to_host_one(g)
        if not t <= now + self.slack:  # after its arrival: never remembered
            return math.nan
        memo[g] = t
        if g > self._newest:
            self._newest = g
            if len(memo) > 4 * self.memory_keys:
                horizon = g - int(self.memory * self.hz)
                self._memo = {k: v for k, v in memo.items() if k >= horizon}
        return t

    def frame_times(self, g: NDArray[np.int64], now: float) -> NDArray[np.float64]:
        """Host time of each frame's global cycle ``g`` (-1: none), NaN for none, for a frame
        the map would put more than ``slack`` after ``now`` (its arrival: never remembered),
        and for one behind a jump back awaiting confirmation. Frames older than the newest by
        ``memory`` s are forgotten."""
        if g.shape == (1,):  # (a record's frame, once a frame: np.unique's cost for nothing)
            keys, inverse = g, np.zeros(1, dtype=np.intp)
        else:
            keys, inverse = np.unique(g, return_inverse=True)
        memo = self._memo
        new = [k for k in keys.tolist() if k >= 0 and k not in memo and k >= self._back]
        if new and self.map.synced:
            mapped = self.map.to_host(np.array(new, dtype=np.uint64)).tolist()
            kept = [(k, t) for k, t in zip(new, mapped) if t <= now + self.slack]
            new = [k for k, _ in kept]
            memo.update(kept)
            if new:
                newest = max(new)
                if newest > self._newest:
                    self._newest = newest
                    if len(memo) > 4 * self.memory_keys:
                        horizon = newest - int(self.memory * self.hz)
                        self._memo = memo = {k: v for k, v in memo.items() if k >= horizon}
        back = self._back
        t = np.array([memo.get(k, math.nan) if k >= back else math.nan for k in keys.tolist()])
        return t[inverse]


class BridgeClocks:
    """Every bridge's own clock fit (:class:`BridgeClock`), and its parameters in columns
    indexed by bridge id, so that a read's samples of many bridges map in one vector step.

    Samples not on mesh time (a bridge booting or cut off from the skin's time, protocol
    version 1) are timed by these fits; a fit starts at a bridge's first sample, at the
    chip's clock rate unless its HELLO said another (:meth:`rate`).
    """

    def __init__(self, hz: float, bits: int) -> None:
        self.hz = float(hz)
        self.bits = bits
        self._fits: dict[int, BridgeClock] = {}
        self._rates: dict[int, float] = {}  # bridges whose HELLO said a rate other than the chip's
        self._ref = np.zeros(0x10000, dtype=np.uint64)
        self._t_ref = np.full(0x10000, np.nan)
        self._k = np.ones(0x10000)
        self._hz = np.full(0x10000, self.hz)

    def __len__(self) -> int:
        return len(self._fits)

    def __contains__(self, bridge: object) -> bool:
        return bridge in self._fits

    def observe(self, bridge: int, cycle: int, now: float) -> bool:
        """``bridge``'s newest sample of a read, at ``cycle``, arrived at ``now``: True when its
        clock restarted (a reset) and the fit began again."""
        fit = self._fits.get(bridge)
        if fit is None:
            fit = self._fits[bridge] = BridgeClock(self._rates.get(bridge, self.hz), bits=self.bits)
        jumped = fit.observe(cycle, now)
        self._ref[bridge], self._t_ref[bridge], self._k[bridge], self._hz[bridge] = fit.params()
        return jumped

    def booted(self, bridge: int) -> bool:
        """``bridge`` restarted (HELLO numbered 0): its fit begins again with its next sample.
        True when it had one in sync (a resynchronisation worth counting)."""
        fit = self._fits.pop(bridge, None)
        return fit is not None and fit.synced

    def suspect_reset(self, bridge: int) -> None:
        """``bridge``'s frame numbering restarted without a HELLO: perhaps a reset (:meth:`BridgeClock.suspect_reset`)."""
        fit = self._fits.get(bridge)
        if fit is not None:
            fit.suspect_reset()

    def rate(self, bridge: int, hz: float) -> None:
        """``bridge``'s HELLO says its clock runs at ``hz``: its fit begins again at that rate."""
        self._rates[bridge] = float(hz)
        self._fits.pop(bridge, None)

    def forget(self, bridge: int) -> None:
        self._fits.pop(bridge, None)
        self._rates.pop(bridge, None)

    def to_host(self, bridges: NDArray[np.int64], cycles: NDArray[np.uint64]) -> NDArray[np.float64]:
        """Host times of samples (``bridges[i]``'s cycle count ``cycles[i]``), each bridge
        as of its last :meth:`observe`."""
        return rows_to_host(cycles, self._ref[bridges], self._t_ref[bridges], self._k[bridges], self._hz[bridges],
                            self.bits)

    def seconds(self, bridges: NDArray[np.int64], cycles: NDArray[np.uint64]) -> NDArray[np.float64]:
        """Each sample's bridge time: its cycle count in seconds of its bridge's clock."""
        return cycles.astype(np.float64) / self._hz[bridges]


def cycle_of(index: int, rate: int, hz: float) -> int:
    """The global cycle of skin frame ``index`` at ``rate`` frames a second of a ``hz`` clock
    (-1: its instant does not fit 62 bits, a nonsense index)."""
    g = index * int(hz) // rate
    return g if 0 <= g < _CYCLE_END else -1


def global_cycles(index: NDArray[np.uint64], rate: NDArray[np.int64], on_time: NDArray[np.bool_],
                  hz: float) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    """The global cycle of each mesh-time sample's frame (``index / rate`` s), -1 for the
    others: (on mesh time, cycle). A sample whose instant does not fit 62 bits is not on
    mesh time (its index is nonsense)."""
    with np.errstate(divide="ignore"):
        on_time = on_time & (index.astype(np.float64) * hz / np.maximum(rate, 1) < 2.0**62)
    if not on_time.any():
        return on_time, np.full(index.shape[0], -1, dtype=np.int64)
    r = np.where(on_time, rate, 1).astype(np.uint64)
    cps = np.uint64(int(hz))
    # index · hz // rate without index · hz, which wraps in uint64 below the check above
    # (at a high rate): a corrupted index was put on some frame of the last 65 days
    return on_time, np.where(on_time, (index // r * cps + index % r * cps // r).astype(np.int64), -1)


class MeshMaps(Protocol):
    """Each time root's map of mesh time to host time (:class:`~cellbridge.daemon.core.domains.TimeDomains`)."""

    def teach(self, root: int, gateway: int, g: int, now: float) -> bool: ...

    def frame_times(self, root: int, g: NDArray[np.int64], now: float) -> NDArray[np.float64] | None: ...

    def record(self, gateway: int, rec: ReadoutColumns, root: int, g: int, now: float,
               serial: float) -> tuple[float, bool]: ...


@dataclass(frozen=True, slots=True)
class SampleTimes:
    """One read's DATA samples timed (:meth:`HostTimes.samples`)."""

    t_host: NDArray[np.float64]  # host time of each sample
    t_bridge: NDArray[np.float64]  # its cycle count in seconds of its bridge's clock
    cycle: NDArray[np.int64]  # its frame's global cycle, -1 when not on mesh time
    newest: dict[int, int]  # each bridge's newest sample (its index), in the order first met
    resets: list[int]  # bridges whose own clock restarted (a reset), in that order
    rejected: NDArray[np.int64]  # the origin of each sample whose mesh-time index was not believed
    jumped: bool  # the skin's mesh-time map began again (its time jumped, confirmed)


class RecordTime(NamedTuple):
    """One readout record part timed (:meth:`HostTimes.records`): whether the skin's map
    began again, and, when the record joined its frame, the bridges it accounts for with a
    sample and as unchanged (None: refused, its frame not mapped). (A named tuple: one is
    made for every record part, a hundred a second per gateway, at 0.25 µs against a
    frozen dataclass's 0.43.)"""

    jumped: bool
    sampled: Sequence[int] | None
    unchanged: Sequence[int] | None


class HostTimes:
    """Host time for what a read holds: DATA samples and readout records.

    A sample on mesh time is timed by its time root's map (:func:`mesh_times`; the roots'
    maps and frame sequences are ``maps``, shared with the pipeline), any other by its
    bridge's own fit (:class:`BridgeClocks`); a record by its frame's global time, and it
    teaches its root's map. DATA samples of a link are on the root of that link's newest
    record. ``baud``: each link's line rate (a record part's time on the line bounds how
    late it may come)."""

    def __init__(self, maps: MeshMaps, hz: float, bits: int, baud: dict[str, int]) -> None:
        self.maps = maps
        self.hz = float(hz)
        self._hz_int = int(self.hz)  # (cycle_of's, once)
        self.bridges = BridgeClocks(hz, bits)
        self._baud = baud
        self._link_root: dict[str, int] = {}  # link -> the root of its newest record

    def __len__(self) -> int:
        """Bridges with a fit of their own."""
        return len(self.bridges)

    def booted(self, bridge: int) -> bool:
        """:meth:`BridgeClocks.booted`."""
        return self.bridges.booted(bridge)

    def suspect_reset(self, bridge: int) -> None:
        """:meth:`BridgeClocks.suspect_reset`."""
        self.bridges.suspect_reset(bridge)

    def rate(self, bridge: int, hz: float) -> None:
        """:meth:`BridgeClocks.rate`."""
        self.bridges.rate(bridge, hz)

    def forget(self, bridge: int) -> None:
        """``bridge`` is forgotten: its own fit goes (the roots' maps forget gateways themselves)."""
        self.bridges.forget(bridge)

    def samples(self, link: str, origin: NDArray[np.int64], cycle: NDArray[np.uint64], index: NDArray[np.uint64],
                rate: NDArray[np.int64], mesh: NDArray[np.bool_], gateways: Iterable[int], now: float) -> SampleTimes:
        """A read of ``link`` at ``now``: each sample's bridge, cycle count, frame index and
        rate, ``mesh``: not flagged ``NO_MESH_TIME``; ``gateways``: the read's link-level
        senders (their own samples teach the map)."""
        m = mesh_times(self.maps, self._link_root.get(link, 0), origin, index, rate, mesh, gateways, now, self.hz)
        origins = origin.tolist()
        newest = {o: i for i, o in enumerate(origins)}
        resets = [o for o, i in newest.items() if self.bridges.observe(o, int(cycle[i]), now)]
        t = self.bridges.to_host(origin, cycle)
        if m.t_frame is not None:
            t = np.where(m.on_time, m.t_frame, t)
        return SampleTimes(t, self.bridges.seconds(origin, cycle), m.cycle, newest, resets, m.rejected, m.jumped)

    def records(self, link: str, records: Iterable[tuple[int, ReadoutColumns]], now: float) -> list[RecordTime]:
        """READOUT record parts gateways wrote on ``link``, arrived at ``now``: each teaches
        its root's map (it cannot reach the host before its frame's gates opened: a gateway
        sends it as soon as it is complete, the schedule's end being only the latest) and
        joins its frame (``maps``)."""
        part_s = PART_BYTES * 10 / self._baud.get(link, 1_000_000)  # s a part takes on the line, at most
        out = []
        hz, record = self._hz_int, self.maps.record
        for gw, rec in records:
            g = rec.index * hz // rec.rate  # cycle_of (-1: a nonsense index, the record refused)
            if not 0 <= g < _CYCLE_END:
                g = -1
            root = rec.root
            self._link_root[link] = root
            t, jumped = record(gw, rec, root, g, now, rec.parts * part_s)
            if not math.isfinite(t):
                out.append(RecordTime(jumped, None, None))
                continue
            out.append(RecordTime(jumped, rec.samples[:, 0].tolist(), rec.unchanged.tolist()))
        return out


@dataclass(frozen=True, slots=True)
class MeshTimes:
    """The mesh-time side of one read's samples (:func:`mesh_times`)."""

    on_time: NDArray[np.bool_]  # mapped by the skin's map (else: by its bridge's own fit)
    cycle: NDArray[np.int64]  # each sample's global cycle, -1 when not on mesh time
    t_frame: NDArray[np.float64] | None  # host time of each on-time sample's frame (None: no map yet)
    rejected: NDArray[np.int64]  # the origin of each sample whose index was not believed
    jumped: bool  # the map began again (the skin's time jumped, confirmed)


def mesh_times(maps: MeshMaps, root: int, origin: NDArray[np.int64], index: NDArray[np.uint64],
               rate: NDArray[np.int64], mesh: NDArray[np.bool_], gateways: Iterable[int], now: float,
               hz: float) -> MeshTimes:
    """A read's samples on ``root``'s mesh time (``mesh``: not flagged ``NO_MESH_TIME``)
    arrived at ``now``. A sample on mesh time started its C1 gate at global time
    ``index / rate``: its host time comes from the skin's one map, so two bridges' samples
    of one index get one host time. The newest of the ``gateways``' own samples teaches
    the map. A frame the map puts after the sample's own arrival was never taken: its
    index is wrong (a frame corrupted past the CRC, a bridge on some other time); so is one
    behind a jump back of the skin's time not confirmed yet. Believed, it would move the
    skin frame that far and stop every estimate until then: such samples are rejected
    (timed by their bridge's own fit, and counted)."""
    on_time, g = global_cycles(index, rate, mesh & (rate > 0), hz)
    jumped = False
    none = origin[:0]
    if not on_time.any():
        return MeshTimes(on_time, g, None, none, jumped)
    gw = list(gateways)
    own = np.flatnonzero(on_time & np.isin(origin, np.array(gw, dtype=np.int64)))
    if own.size:
        newest = own[np.argmax(g[own])]
        jumped = maps.teach(root, int(origin[newest]), int(g[newest]), now)
    t_frame = maps.frame_times(root, np.where(on_time, g, -1), now)
    if t_frame is None:
        return MeshTimes(on_time, g, None, none, jumped)
    wrong = on_time & np.isnan(t_frame)
    if wrong.any():
        return MeshTimes(on_time & ~wrong, np.where(wrong, -1, g), t_frame, origin[wrong], jumped)
    return MeshTimes(on_time, g, t_frame, none, jumped)
