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
Bridge reset: a cycle count that runs backwards, or one whose predicted host time is
off from the arrival by more than ``max_jump`` seconds, restarts the fit (counted in
``resets``) instead of publishing nonsense times.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import NDArray


class BridgeClock:
    """Clock model of one bridge; feed ``observe(cycle, arrival)``, then map with ``to_host``."""

    def __init__(self, hz: float, bits: int = 64, block: float = 1.0, blocks: int = 64,
                 max_jump: float = 1.0, max_step: float = 0.05) -> None:
        self.hz = float(hz)
        self.bits = bits
        self._mod = 1 << bits
        self.block = block
        self.max_jump = max_jump
        self.max_step = max_step  # s: a block minimum this far off the line is a host clock step
        self.steps = 0
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
        d = (raw - self._ref_raw) % self._mod  # type: ignore[operator]
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
        self.offset = 0.0
        self.skew = 0.0

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
        if x < self._x_last - self.max_jump or abs(arrival - predicted) > self.max_jump:
            self.resets += 1
            self._restart(raw, arrival)
            return True
        if x > (self._mod >> 3) / self.hz:  # stay far from half the modulus: move the origin
            self._rebase(raw, x)
            x = 0.0
        self._x_last = max(self._x_last, x)
        r = arrival - self._ref_arrival - x
        if x - self._cur_start >= self.block:  # a block closed: refit (once a block, not per frame)
            if self._cur is not None:
                self._minima.append(self._cur)
                self._follow_step()
            self._cur, self._cur_start = (x, r), x
            self._fit()
        elif self._cur is None or r < self._cur[1]:
            self._cur = (x, r)
            below = r - (self.offset + self.skew * x)
            if below < 0 or len(self._minima) < 2:  # a new lowest point: lower the line onto it
                self._fit() if len(self._minima) < 2 else setattr(self, "offset", self.offset + below)
        return False

    def _follow_step(self) -> None:
        """The host clock stepped (NTP) by less than ``max_jump``: every arrival since moves
        by the step, so the envelope does. The newest block minimum ``max_step`` below the
        line of the earlier ones (delay cannot go negative), or the two newest above it,
        is such a step: the minima from before it are moved by it, keeping the skew,
        instead of a fit across the step for a whole window of wrong times."""
        pts = list(self._minima)
        if len(pts) < 5:
            return
        icpt, slope = _line(pts[:-2])
        dev = [r - (icpt + slope * x) for x, r in pts]
        if dev[-1] < -self.max_step:
            d = dev[-1]
        elif min(dev[-2:]) > self.max_step:
            d = min(dev[-2:])
        else:
            return
        self.steps += 1
        self._minima = deque(((x, r + d) if abs(dv - d) > self.max_step else (x, r)
                              for (x, r), dv in zip(pts, dev)), maxlen=self._minima.maxlen)

    def _fit(self) -> None:
        """Least-squares line through the closed blocks' minima (the open block's first
        points are no minimum yet), then lowered onto the envelope."""
        pts = list(self._minima)
        if len(pts) < 3:
            if self._cur is not None:
                pts.append(self._cur)
            self.offset, self.skew = min(p[1] for p in pts), 0.0
            return
        icpt, slope = _line(pts)
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


def _line(pts: list[tuple[float, float]]) -> tuple[float, float]:
    """Least-squares (intercept, slope) through points (x, residual)."""
    n = len(pts)
    mx = sum(p[0] for p in pts) / n
    mr = sum(p[1] for p in pts) / n
    sxx = sum((p[0] - mx) ** 2 for p in pts)
    slope = sum((p[0] - mx) * (p[1] - mr) for p in pts) / sxx if sxx > 0 else 0.0
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
