"""The RC oscillator's edge times around one counter gate, and what the counter makes of them.

One definition of the edge times (:class:`EdgeTrain`) serves both the per-cycle
reference stepper (:mod:`cellbridge.emulator.reference`) and the fast path here; the
fast path only evaluates fewer of them. Times are float cycles relative to the
window origin ``L = start_cycle − SYNC_LATENCY``, so they stay small (a gate, not the
chip's whole uptime) and keep ~1e-10-cycle precision.

**Edges.** Rising edge k ≥ 0 is at ``t_k = phase·T + Σ_{i<k} T·(1 + jitter·z_i)``;
the previous period's edge is at ``t_0 − T`` and the output is low before it. Each
period is high for its first half (a relaxation oscillator charging and discharging
through the same R between 1/3 and 2/3 of the supply).

**Jitter, addressable.** The z_i are grouped into blocks of :data:`BLOCK` periods.
Block b draws its *sum* ``Z_b = √B·y_b`` directly and its shape from B further normals
w: ``z = w − mean(w) + Z_b/B``. Since ``w − mean(w)`` is independent of ``mean(w)``,
this is exactly i.i.d. N(0, 1) periods — but the start of any block is a prefix sum
of the y alone, so the gate's last edge needs ~gate/(B·T) + B normals, not one per
period.

**Synchroniser and counter.** The oscillator output is sampled at each integer cycle
by flop 1, then flop 2; the counter increments at cycle n when flop 2 was high and
its previous value low before edge n, i.e. ``level(n−2) = 1`` and ``level(n−3) = 0``
(relative to L: an edge whose first high sample is a increments at a + 2 − 3 cycles
after the gate opens, the DESIGN's 2–3-cycle latency). The counter counts increments
at cycles ``[start, start + gate)``. When every half period is at least one cycle
long, every edge is seen and the count is simply the number of edges in
``(0, gate]``: the fast path's closed form. Otherwise (oscillator near or above half
the clock) :meth:`EdgeTrain.event_offsets` applies the synchroniser rule to every
edge, vectorised.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from cellbridge.emulator.keyed_random import Z_MAX

__all__ = ["BLOCK", "SYNC_LATENCY", "EdgeTrain", "max_period_deviation"]

BLOCK = 128  #: periods per jitter block
SYNC_LATENCY = 3  #: window origin L = start_cycle − SYNC_LATENCY
_SQRT_BLOCK = math.sqrt(BLOCK)
_ARANGE_BLOCK = np.arange(BLOCK, dtype=np.float64)
_DETECT_MARGIN = 1e-6  # cycles of slack for float rounding in the all-edges-seen test

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def max_period_deviation() -> float:
    """Largest |z| a period can have, in units of the jitter (clipping makes it finite)."""
    return 2.0 * Z_MAX + Z_MAX / _SQRT_BLOCK


@dataclass
class EdgeTrain:
    """The oscillator's rising edges for one gate.

    ``block_sums(n)`` returns the first n block-sum normals y (a longer call extends a
    shorter one); ``block_steps(b)`` the BLOCK shape normals w of block b. Both are
    clipped standard normals from the chip's keyed generator.
    """

    period: float  #: T in chip cycles
    jitter: float  #: relative rms jitter of one period
    phase: float  #: first edge at phase·T after the origin, in [0, 1)
    gate: int  #: gate length in cycles
    block_sums: Callable[[int], FloatArray]
    block_steps: Callable[[int], FloatArray]
    _starts: FloatArray = field(default_factory=lambda: np.empty(0), repr=False)
    _sums: FloatArray = field(default_factory=lambda: np.empty(0), repr=False)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(f"oscillator period must be finite and > 0 cycles, got {self.period!r}")
        if not (0.0 <= self.jitter * max_period_deviation() < 1.0):
            raise ValueError(
                f"jitter must lie in [0, {1 / max_period_deviation():.4f}) so that every period "
                f"stays positive, got {self.jitter!r}"
            )
        if not (0.0 <= self.phase < 1.0):
            raise ValueError(f"phase must lie in [0, 1), got {self.phase!r}")
        if not (isinstance(self.gate, (int, np.integer)) and self.gate > 0):
            raise ValueError(f"gate must be a positive number of cycles, got {self.gate!r}")

    # ------------------------------------------------------------ the definition

    @property
    def first_edge(self) -> float:
        """t_0 = phase·T."""
        return self.phase * self.period

    def block_starts(self) -> FloatArray:
        """Times of edges 0, B, 2B, … up to the first one beyond the gate."""
        if self._starts.size and self._starts[-1] > self.gate:
            return self._starts
        n = max(2, int(self.gate / (self.period * BLOCK)) + 2)
        while True:
            y = self.block_sums(n)
            s = np.empty(n + 1)
            s[0] = 0.0
            np.cumsum(y * _SQRT_BLOCK, out=s[1:])
            starts = self.first_edge + self.period * (BLOCK * np.arange(n + 1)) + (
                self.period * self.jitter
            ) * s
            if starts[-1] > self.gate:
                self._starts, self._sums = starts, y
                return starts
            n *= 2

    def block_rises(self, b: int) -> FloatArray:
        """Times of edges bB … bB + B − 1."""
        starts = self.block_starts()
        w = self.block_steps(b)
        z = w - w.mean() + self._sums[b] / _SQRT_BLOCK
        c = np.empty(BLOCK)
        c[0] = 0.0
        np.cumsum(z[:-1], out=c[1:])
        return starts[b] + self.period * _ARANGE_BLOCK + (self.period * self.jitter) * c

    def edges(self) -> tuple[FloatArray, FloatArray]:
        """(rises, falls) of every edge that can matter: the previous period's edge,
        then edges 0, 1, … through the block that holds the gate's end."""
        starts = self.block_starts()
        last = int(np.searchsorted(starts, self.gate, side="right")) - 1
        t0 = self.first_edge
        rises = np.concatenate(
            [[t0 - self.period], *(self.block_rises(b) for b in range(last + 1))]
        )
        nxt = np.empty_like(rises)
        nxt[:-1] = rises[1:]
        nxt[-1] = starts[last + 1]
        falls = rises + 0.5 * (nxt - rises)
        return rises, falls

    # ------------------------------------------------------------ the fast path

    @property
    def every_edge_seen(self) -> bool:
        """True when no half period can be shorter than one cycle, whatever the jitter draws."""
        shortest = self.period * (1.0 - self.jitter * max_period_deviation())
        return 0.5 * shortest >= 1.0 + _DETECT_MARGIN

    def event_offsets(self) -> IntArray:
        """Counter increments in the gate, as cycles after its start (0 … gate − 1).

        The synchroniser rule applied to every edge: edge k (first high sample a_k =
        ceil(t_k), first low sample b_k = ceil(fall_k)) is seen iff a_k < b_k and the
        sample a_k − 1 is low, i.e. the last edge j with a_j < a_k has b_j < a_k.
        """
        rises, falls = self.edges()
        a = np.ceil(rises).astype(np.int64)
        b = np.ceil(falls).astype(np.int64)
        prev = np.searchsorted(a, a, side="left") - 1
        prev_high = (prev >= 0) & (b[np.maximum(prev, 0)] >= a)
        seen = (a < b) & ~prev_high & (a >= 1) & (a <= self.gate)
        return a[seen] - 1

    def edge_count(self) -> int:
        """Number of counter increments in the gate (not wrapped)."""
        if not self.every_edge_seen:
            return int(self.event_offsets().size)
        starts = self.block_starts()
        last = int(np.searchsorted(starts, self.gate, side="right")) - 1
        rises = self.block_rises(last)
        n = last * BLOCK + int(np.searchsorted(rises, self.gate, side="right"))
        return n - (1 if self.first_edge <= 0.0 else 0)
