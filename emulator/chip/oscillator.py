"""The RC oscillator's edge times around one counter gate, and what the counter makes of them.

One definition of the edge times (:class:`EdgeTrain`) serves both the per-cycle
reference stepper (:mod:`cellbridge.emulator.chip.reference`) and the fast path here; the
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
period. The gate's *head* draw holds the phase, a fixed number of y (enough to pass
the gate's end whatever they are) and the shape of the block where the gate most
likely ends (the *hint* block, from the jitter-free edge times); every other block
has its own substream. So the fast path's usual cost is one seek and one draw.

**Synchroniser and counter.** The oscillator output is sampled at each integer cycle
by flop 1, then flop 2; the counter increments at cycle n when flop 2 was high and
its previous value low before edge n, i.e. ``level(n−2) = 1`` and ``level(n−3) = 0``
(an edge whose first high sample is cycle L + a, a = ⌈t⌉, increments the register at
L + a + 2, i.e. 2–3 cycles after the edge itself). The counter counts increments
at cycles ``[start, start + gate)``. When every half period is at least one cycle
long, every edge is seen and the count is simply the number of edges in
``(0, gate]``: the fast path's closed form. Otherwise (oscillator near or above half
the clock) :meth:`EdgeTrain.event_offsets` applies the synchroniser rule to every
edge, vectorised.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

import numpy as np
from cellbridge.emulator.chip.keyed_random import BLOCK_SIZE, Z_MAX, KeyedNormals, Stream
from numpy.typing import NDArray

__all__ = ["BLOCK", "SYNC_LATENCY", "EdgeTrain", "JitterSource", "gate_edge_count", "gate_edge_counts",
           "max_period_deviation"]

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

    def head(self, n: int) -> tuple[float, FloatArray, FloatArray]:
        """(uniform phase, n block-sum normals y, BLOCK shape normals of the hint block)."""

    def block_steps(self, b: int) -> FloatArray:
        """The BLOCK shape normals w of block b (any block but the hint block)."""


class EdgeTrain:
    """The oscillator's rising edges for one gate of ``gate`` cycles.

    ``period`` is T in chip cycles, ``jitter`` the relative rms jitter of one period,
    ``phase`` ∈ [0, 1) places edge 0 at phase·T after the origin (None: the phase
    the noise source draws, as the chip does).
    """

    __slots__ = (
        "period", "jitter", "gate", "noise", "every_edge_seen", "n_blocks",
        "_phase", "_sums", "_hint", "_hint_steps", "_starts",
    )

    def __init__(
        self, period: float, jitter: float, phase: float | None, gate: int, noise: JitterSource
    ) -> None:
        if not (math.isfinite(period) and period > 0):
            raise ValueError(f"oscillator period must be finite and > 0 cycles, got {period!r}")
        if not (0.0 <= jitter * _MAX_DEV < 1.0):
            raise ValueError(
                f"jitter must lie in [0, {1 / _MAX_DEV:.4f}) so that every period "
                f"stays positive, got {jitter!r}"
            )
        if phase is not None and not (0.0 <= phase < 1.0):
            raise ValueError(f"phase must lie in [0, 1), got {phase!r}")
        if not (type(gate) is int or isinstance(gate, np.integer)) or gate <= 0:
            raise ValueError(f"gate must be a positive number of cycles, got {gate!r}")
        self.period = period
        self.jitter = jitter
        self.gate = int(gate)
        self.noise = noise
        #: True when no half period can be shorter than one cycle, whatever the jitter draws:
        #: then the synchroniser sees every edge and the count has a closed form.
        self.every_edge_seen = 0.5 * period * (1.0 - jitter * _MAX_DEV) >= 1.0 + _DETECT_MARGIN
        #: Block sums drawn: enough that block n_blocks starts after the gate's end even
        #: if every y sits at −Z_MAX (start(b) ≥ T·b·(B − jitter·√B·Z_MAX)).
        self.n_blocks = int((self.gate + 1) / (period * (BLOCK - jitter * _SQRT_BLOCK * Z_MAX))) + 2
        self._phase = phase
        self._sums: FloatArray | None = None
        self._hint = -1
        self._hint_steps: FloatArray | None = None
        self._starts: FloatArray | None = None

    # ------------------------------------------------------------ the definition

    def _draw_head(self) -> FloatArray:
        """Block sums y (drawing the gate's head once); sets the phase and the hint block."""
        if self._sums is None:
            phase, y, steps = self.noise.head(self.n_blocks)
            if self._phase is None:
                self._phase = phase
            t0 = self._phase * self.period
            self._hint = min(max(int((self.gate - t0) / (self.period * BLOCK)), 0), self.n_blocks - 1)
            self._sums, self._hint_steps = y, steps
        return self._sums

    @property
    def phase(self) -> float:
        """Edge 0 is at phase·T after the origin."""
        self._draw_head()
        assert self._phase is not None
        return self._phase

    def block_starts(self) -> FloatArray:
        """Times of edges 0, B, 2B, …, n_blocks·B (the last one is beyond the gate)."""
        if self._starts is None:
            y = self._draw_head()
            n = self.n_blocks
            starts = np.empty(n + 1)
            starts[0] = 0.0
            y.cumsum(out=starts[1:])  # Σ y over the blocks before each start
            starts *= self.period * self.jitter * _SQRT_BLOCK
            starts += self.period * _block_offsets(n + 1)
            starts += self.phase * self.period
            self._starts = starts
        return self._starts

    def _block_shape(self, b: int) -> tuple[FloatArray, float]:
        """Prefix sums W of block b's shape normals w (W[i] = Σ_{j≤i} w_j) and the shift
        m with z_i = w_i − m (m = mean(w) − y_b/√B, so that the block's z sum to y_b·√B)."""
        y = self._draw_head()
        w = self._hint_steps if b == self._hint else self.noise.block_steps(b)
        assert w is not None
        cum = w.cumsum()
        return cum, float(cum[-1]) / BLOCK - float(y[b]) / _SQRT_BLOCK

    def block_rises(self, b: int) -> FloatArray:
        """Times of edges bB … bB + B − 1."""
        starts = self.block_starts()
        cum, m = self._block_shape(b)
        rises = np.empty(BLOCK)
        rises[0] = 0.0
        rises[1:] = cum[:-1]  # Σ w over the periods before each edge …
        rises -= m * _ARANGE_BLOCK  # … minus the shift: Σ z
        rises *= self.period * self.jitter
        rises += self.period * _ARANGE_BLOCK
        rises += starts[b]
        return rises

    def edges(self) -> tuple[FloatArray, FloatArray]:
        """(rises, falls) of every edge that can matter: the previous period's edge,
        then edges 0, 1, … through the block that holds the gate's end."""
        starts = self.block_starts()
        last = int(np.searchsorted(starts, self.gate, side="right")) - 1
        t0 = self.phase * self.period
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
        the gate's end from the block sums' prefix sums, then the edge within it
        (:func:`_edges_to`, evaluating only the edge times it needs).
        """
        if not self.every_edge_seen:
            return int(self.event_offsets().size)
        y = self._draw_head()
        phase, hint, steps = self._phase, self._hint, self._hint_steps
        assert phase is not None and steps is not None
        return _edges_to(self.period, self.jitter, self.gate, phase * self.period, y, hint,
                         lambda b: steps if b == hint else self.noise.block_steps(b))


_JITTER_STEPS = int(Stream.JITTER_STEPS)


def _head_blocks(period: float, jitter: float, gate: int) -> int:
    """:attr:`EdgeTrain.n_blocks` of a gate: the block sums its head draw holds."""
    return int((gate + 1) / (period * (BLOCK - jitter * _SQRT_BLOCK * Z_MAX))) + 2


def gate_edge_count(period: float, jitter: float, gate: int, normals: KeyedNormals, channel: int,
                    cycle: int) -> int | None:
    """:meth:`EdgeTrain.edge_count` of the gate at (``channel``, ``cycle``) of a chip whose
    keyed normals are ``normals``, without building the train: the same draws, the same
    doubles, the same answer (``tests/test_emulator_chip*.py`` hold it to the per-cycle
    reference). None when not every edge is seen (the caller builds the train: its
    synchroniser path). The arguments are trusted (the chip validated them).

    Why it exists: two counts per sample on every bridge are the largest single share of
    an emulated skin's CPU, and of one count's ~19 µs the train's validation and its
    objects (EdgeTrain, GateNoise, slices, the head's bookkeeping) took several.
    """
    if not 0.5 * period * (1.0 - jitter * _MAX_DEV) >= 1.0 + _DETECT_MARGIN:
        return None
    n = _head_blocks(period, jitter, gate)
    phase, z = normals.gate_head(channel, cycle, n)
    t0 = phase * period
    hint = int((gate - t0) / (period * BLOCK))
    hint = 0 if hint < 0 else n - 1 if hint >= n else hint
    y = z[:n]
    return _edges_to(period, jitter, gate, t0, y, hint, None, y.cumsum(), z[n:].cumsum(), normals, channel, cycle)


def gate_edge_counts(period: float, jitter: float, gate: int, normals: KeyedNormals, channel: int,
                     cycles: list[int]) -> list[int] | None:
    """:func:`gate_edge_count` of several gates of one channel and oscillator period (at
    ``cycles``), the same answers: each gate's head is drawn into a row of one array, and
    the clipping and the prefix sums run once on all the rows (numpy's accumulation along
    a row is the same sequential sum as on a lone array: the same doubles). What it buys
    is the call overhead of those array operations, which on a gate's few hundred numbers
    costs more than the arithmetic: a real-time bridge computes its next samples' counts
    together (:meth:`Chip.prefetch <cellbridge.emulator.chip.chip.Chip.prefetch>`)."""
    if not 0.5 * period * (1.0 - jitter * _MAX_DEV) >= 1.0 + _DETECT_MARGIN:
        return None
    n = _head_blocks(period, jitter, gate)
    z = np.empty((len(cycles), n + BLOCK))
    phases = normals.gate_heads(channel, cycles, z)
    ycum = z[:, :n].cumsum(axis=1)
    wcum = z[:, n:].cumsum(axis=1)
    out = []
    for k, cycle in enumerate(cycles):
        t0 = phases[k] * period
        hint = int((gate - t0) / (period * BLOCK))
        hint = 0 if hint < 0 else n - 1 if hint >= n else hint
        out.append(_edges_to(period, jitter, gate, t0, z[k, :n], hint, None, ycum[k], wcum[k], normals, channel,
                             cycle))
    return out


def _edges_to(period: float, jitter: float, gate: int, t0: float, y: FloatArray, hint: int,
              shape: Callable[[int], FloatArray] | None, ycum: FloatArray | None = None,
              hint_cum: FloatArray | None = None, normals: KeyedNormals | None = None, channel: int = 0,
              cycle: int = 0) -> int:
    """#{k : t_k ∈ (0, gate]} with every edge seen: edge 0 at ``t0``, block sums ``y``,
    ``shape(b)`` block b's shape normals; the search starts at block ``hint``. The few edge
    times it needs are evaluated as scalars with exactly the operations, in exactly the
    order, that :meth:`EdgeTrain.block_starts` and :meth:`EdgeTrain.block_rises` apply to
    whole arrays, so they are the same doubles (IEEE arithmetic is the same in numpy and
    Python). The counter's fast path passes what it computed already instead: ``ycum``
    (the prefix sums of ``y``), ``hint_cum`` (those of the hint block's shape) and the keyed
    normals a gate's other blocks are drawn from (``shape`` None)."""
    item = (y.cumsum() if ycum is None else ycum).item  # item(b) = Σ_{i≤b} y_i
    k_sum = period * jitter * _SQRT_BLOCK
    # start(b) = ((Σ_{i<b} y_i)·k_sum + T·(B·b)) + t0, inline (this runs twice a sample)
    b = hint
    while (item(b) * k_sum + period * (BLOCK * (b + 1))) + t0 <= gate:  # start(b + 1)
        b += 1
    while b >= 0 and ((item(b - 1) if b else 0.0) * k_sum + period * (BLOCK * b)) + t0 > gate:
        b -= 1
    if b < 0:  # edge 0 comes after the gate's end
        return 0
    base = ((item(b - 1) if b else 0.0) * k_sum + period * (BLOCK * b)) + t0
    if shape is not None:
        cum = shape(b).cumsum()  # cum[i - 1] = Σ_{j<i} w_j
    elif b == hint and hint_cum is not None:
        cum = hint_cum
    else:
        assert normals is not None
        cum = normals.normals(_JITTER_STEPS, channel, cycle, BLOCK, b).cumsum()
    m = cum.item(-1) / BLOCK - y.item(b) / _SQRT_BLOCK  # z_i = w_i − m: the block's z sum to y_b·√B
    k_step = period * jitter
    step = cum.item
    # rise(i) = (((Σ_{j<i} w_j) − m·i)·k_step + T·i) + base
    i = int((gate - base) / period)
    i = 0 if i < 0 else BLOCK - 1 if i > BLOCK - 1 else i
    while i + 1 < BLOCK and (((step(i) - m * (i + 1)) * k_step + period * (i + 1)) + base) <= gate:
        i += 1
    while i >= 0 and ((((step(i - 1) if i else 0.0) - m * i) * k_step + period * i) + base) > gate:
        i -= 1
    return b * BLOCK + i + 1 - (1 if t0 <= 0.0 else 0)
