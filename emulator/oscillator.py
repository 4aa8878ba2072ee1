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
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from cellbridge.emulator.keyed_random import BLOCK_SIZE, Z_MAX

__all__ = ["BLOCK", "SYNC_LATENCY", "EdgeTrain", "JitterSource", "max_period_deviation"]

BLOCK = BLOCK_SIZE  #: periods per jitter block
SYNC_LATENCY = 3  #: window origin L = start_cycle − SYNC_LATENCY
_SQRT_BLOCK = math.sqrt(BLOCK)
_ARANGE_BLOCK = np.arange(BLOCK, dtype=np.float64)
_DETECT_MARGIN = 1e-6  # cycles of slack for float rounding in the all-edges-seen test

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


_OFFSETS = BLOCK * np.arange(4097, dtype=np.float64)


def _block_offsets(n: int) -> FloatArray:
    """Edge index of the first n block starts, as floats: 0, B, 2B, …"""
    return _OFFSETS[:n] if n <= _OFFSETS.size else BLOCK * np.arange(n, dtype=np.float64)


def max_period_deviation() -> float:
    """Largest |z| a period can have, in units of the jitter (clipping makes it finite)."""
    return 2.0 * Z_MAX + Z_MAX / _SQRT_BLOCK


_MAX_DEV = max_period_deviation()


class JitterSource(Protocol):
    """The clipped standard normals a train's jitter is made of (a keyed generator)."""

    def block_sums(self, n: int) -> FloatArray:
        """The first n block-sum normals y (a longer call extends a shorter one)."""

    def block_steps(self, b: int) -> FloatArray:
        """The BLOCK shape normals w of block b."""


class EdgeTrain:
    """The oscillator's rising edges for one gate of ``gate`` cycles.

    ``period`` is T in chip cycles, ``jitter`` the relative rms jitter of one period,
    ``phase`` ∈ [0, 1) places edge 0 at phase·T after the origin.
    """

    __slots__ = ("period", "jitter", "phase", "gate", "noise", "every_edge_seen", "_starts", "_sums")

    def __init__(
        self, period: float, jitter: float, phase: float, gate: int, noise: JitterSource
    ) -> None:
        if not (math.isfinite(period) and period > 0):
            raise ValueError(f"oscillator period must be finite and > 0 cycles, got {period!r}")
        if not (0.0 <= jitter * _MAX_DEV < 1.0):
            raise ValueError(
                f"jitter must lie in [0, {1 / _MAX_DEV:.4f}) so that every period "
                f"stays positive, got {jitter!r}"
            )
        if not (0.0 <= phase < 1.0):
            raise ValueError(f"phase must lie in [0, 1), got {phase!r}")
        if not (type(gate) is int or isinstance(gate, np.integer)) or gate <= 0:
            raise ValueError(f"gate must be a positive number of cycles, got {gate!r}")
        self.period = period
        self.jitter = jitter
        self.phase = phase
        self.gate = int(gate)
        self.noise = noise
        #: True when no half period can be shorter than one cycle, whatever the jitter draws:
        #: then the synchroniser sees every edge and the count has a closed form.
        self.every_edge_seen = 0.5 * period * (1.0 - jitter * _MAX_DEV) >= 1.0 + _DETECT_MARGIN
        self._starts: FloatArray | None = None
        self._sums: FloatArray | None = None

    # ------------------------------------------------------------ the definition

    @property
    def first_edge(self) -> float:
        """t_0 = phase·T."""
        return self.phase * self.period

    def block_starts(self) -> FloatArray:
        """Times of edges 0, B, 2B, … up to the first one beyond the gate."""
        if self._starts is not None:
            return self._starts
        n = int(self.gate / (self.period * BLOCK)) + 2
        while True:
            y = self.noise.block_sums(n)
            starts = np.empty(n + 1)
            starts[0] = 0.0
            y.cumsum(out=starts[1:])  # Σ y over the blocks before each start
            starts *= self.period * self.jitter * _SQRT_BLOCK
            starts += self.period * _block_offsets(n + 1)
            starts += self.phase * self.period
            if starts[-1] > self.gate:
                self._starts, self._sums = starts, y
                return starts
            n *= 2

    def _block_z(self, b: int, y_b: float) -> FloatArray:
        """The normalised period deviations z of block b (its shape w, its sum y_b·√B)."""
        z = self.noise.block_steps(b)
        z -= np.add.reduce(z) / BLOCK - y_b / _SQRT_BLOCK
        return z

    def block_rises(self, b: int) -> FloatArray:
        """Times of edges bB … bB + B − 1."""
        starts = self.block_starts()
        assert self._sums is not None
        z = self._block_z(b, float(self._sums[b]))
        rises = np.empty(BLOCK)
        rises[0] = 0.0
        z[:-1].cumsum(out=rises[1:])  # Σ z over the periods before each edge
        rises *= self.period * self.jitter
        rises += self.period * _ARANGE_BLOCK
        rises += starts[b]
        return rises

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
        """Number of counter increments in the gate (not wrapped).

        With every edge seen this is #{k : t_k ∈ (0, gate]}: find the block holding
        the gate's end from the block sums' prefix sums, then the edge within it. The
        few edge times it needs are evaluated as scalars with exactly the operations,
        in exactly the order, that :meth:`block_starts` and :meth:`block_rises` apply
        to whole arrays, so they are the same doubles (IEEE arithmetic is the same in
        numpy and Python).
        """
        if not self.every_edge_seen:
            return int(self.event_offsets().size)
        gate, period = self.gate, self.period
        k_sum = period * self.jitter * _SQRT_BLOCK
        t0 = self.phase * period
        n = int(gate / (period * BLOCK)) + 2
        while True:
            y = self.noise.block_sums(n)
            sums = y.cumsum()  # sums[b - 1] = Σ_{i<b} y_i

            def start(b: int) -> float:
                return ((float(sums[b - 1]) if b else 0.0) * k_sum + period * (BLOCK * b)) + t0

            if start(n) > gate:
                break
            n *= 2
        b = min(max(int((gate - t0) / (period * BLOCK)), 0), n - 1)
        while start(b + 1) <= gate:
            b += 1
        while b >= 0 and start(b) > gate:
            b -= 1
        if b < 0:  # edge 0 comes after the gate's end
            return 0
        z = self._block_z(b, float(y[b]))
        steps = z[:-1].cumsum()  # steps[i - 1] = Σ_{m<i} z_m
        k_step = period * self.jitter
        base = start(b)

        def rise(i: int) -> float:
            return ((float(steps[i - 1]) if i else 0.0) * k_step + period * i) + base

        i = min(max(int((gate - base) / period), 0), BLOCK - 1)
        while i + 1 < BLOCK and rise(i + 1) <= gate:
            i += 1
        while i >= 0 and rise(i) > gate:
            i -= 1
        return b * BLOCK + i + 1 - (1 if t0 <= 0.0 else 0)
