"""Transfer functions of the bridge chip's two capacitance front ends.

One description shared by the chip emulator (which must produce these numbers cycle
by cycle) and by the host daemon (which turns them back into capacitances). Keeping
both directions in one module is what guarantees they agree.

**RC self-oscillation counter.** The element's capacitor C and ``R_osc`` form a
relaxation oscillator of period ``T = 2·ln2·R_osc·C`` (thresholds at 1/3 and 2/3 of
the supply). A counter of ``counter_bits`` bits counts the oscillator's rising edges
during a gate of ``gate_cycles`` cycles of the chip clock; it wraps modulo
2^counter_bits and raises a sticky overflow flag when it does. With the defaults
(4.7 kΩ, 100 000 cycles of 50 MHz = 2 ms) a rest C1 of 15.67 pF gives ≈19 588 counts,
C2 of 19.44 pF ≈15 788, and 1 pF ≈ 1 250 (C1) / 810 (C2) counts.

The integer count modelled here is the ideal edge count: edges at times
``(phase + k)·T`` (k = 0, 1, …) after the gate opens, counted while ``< t_gate``.
Its mean over a uniformly random phase is exactly ``t_gate/T`` (:func:`expected_counts`),
which is why the inverse uses that formula with no half-count correction. The chip's
two-flop synchroniser delays every detected edge by the same 2-3 cycles, which shifts
the window but not its length, so the statistics are the same; it can only follow an
oscillator slower than half the clock (T ≥ 2 cycles, C ≥ ≈6.1 pF at the defaults).

**8-bit SAR ADC, charge-time method.** The channel is discharged, released to charge
through ``R_adc`` and sampled ``adc_sample_cycles`` cycles later, so the sampled
voltage is the supply times ``1 − exp(−t_s/(R_adc·C))``. An ideal SAR converter
returns ``floor`` of that fraction times 2^adc_bits, clipped to the code range.
Defaults (100 kΩ, 64 cycles = 1.28 µs): rest C1 → code 142 (142.9), C2 → 123 (123.5);
≈5.9 (C1) / 4.5 (C2) codes per pF. Input noise ``adc_noise_lsb`` (≈0.5 LSB rms)
dithers the quantiser, so the mean of N conversions resolves below one code; this
module gives the exact expected mean and its spread, so oversampled means invert
without bias.

**Crystal offset.** ``clock_ppm`` scales the chip clock: a crystal fast by +50 ppm
makes every cycle-defined time (gate, sample instant) 50 ppm shorter.

All times in seconds, capacitances in farads, resistances in ohms.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from cellbridge.tactile.arrays import FloatArray, IntArray
from cellbridge.tactile.element import ElementParams
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "ChipParams",
    "CounterUnwrapper",
    "adc_mean_band",
    "check_gate",
    "counter_span",
    "max_gate_cycles",
    "plausible_capacitance",
    "sync_min_capacitance",
    "oscillator_period",
    "expected_counts",
    "counts",
    "unwrap_counts",
    "counts_to_capacitance",
    "counter_delta",
    "counts_per_farad",
    "adc_input",
    "adc_code",
    "code_to_capacitance",
    "codes_per_farad",
    "adc_mean_code",
    "adc_mean_to_capacitance",
    "adc_resolution",
]


_LN2x2 = 2.0 * math.log(2.0)


@dataclass(frozen=True)
class ChipParams:
    """Bridge-chip front-end parameters; defaults are the reference chip."""

    clock_hz: float = 50e6
    gate_cycles: int = 100_000
    R_osc: float = 4.7e3
    R_adc: float = 100e3
    adc_sample_cycles: int = 64
    adc_bits: int = 8
    counter_bits: int = 16
    clock_ppm: float = 0.0
    adc_noise_lsb: float = 0.5

    def __post_init__(self) -> None:
        for name in ("clock_hz", "R_osc", "R_adc"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"ChipParams.{name} must be finite and > 0, got {v!r}")
        for name in ("gate_cycles", "adc_sample_cycles", "adc_bits", "counter_bits"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_)) and v > 0):
                raise ValueError(f"ChipParams.{name} must be a positive integer, got {v!r}")
        if not self.counter_bits <= 62:
            raise ValueError("ChipParams.counter_bits must be <= 62 (counts are int64)")
        if not self.adc_bits <= 24:
            raise ValueError("ChipParams.adc_bits must be <= 24")
        if not (math.isfinite(self.clock_ppm) and abs(self.clock_ppm) < 1e5):
            raise ValueError(f"ChipParams.clock_ppm must be finite and |ppm| < 1e5, got {self.clock_ppm!r}")
        if not (math.isfinite(self.adc_noise_lsb) and self.adc_noise_lsb >= 0):
            raise ValueError("ChipParams.adc_noise_lsb must be finite and >= 0")

    def with_ppm(self, ppm: float) -> ChipParams:
        """The same chip with another crystal offset (each chip draws its own)."""
        return replace(self, clock_ppm=ppm)

    @property
    def clock_actual_hz(self) -> float:
        """Clock frequency including the crystal offset (Hz)."""
        return self.clock_hz * (1.0 + 1e-6 * self.clock_ppm)

    @property
    def gate_time(self) -> float:
        """Counter gate length (s) as the crystal actually produces it."""
        return self.gate_cycles / self.clock_actual_hz

    @property
    def adc_sample_time(self) -> float:
        """Time (s) from release of the channel to the ADC's sampling instant."""
        return self.adc_sample_cycles / self.clock_actual_hz

    @property
    def counter_modulus(self) -> int:
        return 1 << self.counter_bits

    @property
    def adc_levels(self) -> int:
        return 1 << self.adc_bits


DEFAULT_CHIP = ChipParams()


def _chip(chip: ChipParams | None) -> ChipParams:
    return DEFAULT_CHIP if chip is None else chip


#: Largest capacitance any function here accepts (F): far above any element, far
#: below a value in picofarads passed where farads are expected.
C_MAX = 1e-3


def _cap(c: ArrayLike) -> FloatArray:
    arr = np.asarray(c, dtype=np.float64)
    if not np.all(np.isfinite(arr)) or not np.all(arr > 0):
        raise ValueError("capacitance must be finite and > 0 F")
    if np.any(arr > C_MAX):
        raise ValueError(
            f"capacitance must be in farads (0 < C <= {C_MAX:g} F), got up to "
            f"{float(arr.max()):g}: picofarads passed as farads?"
        )
    return arr


def sync_min_capacitance(chip: ChipParams | None = None) -> float:
    """Smallest C (F) the counter can count: the two-flop synchroniser needs T ≥ 2 cycles."""
    ch = _chip(chip)
    return 2.0 / (ch.clock_actual_hz * _LN2x2 * ch.R_osc)


# --------------------------------------------------------------------- oscillator


def oscillator_period(C: ArrayLike, chip: ChipParams | None = None) -> FloatArray:
    """Period ``2·ln2·R_osc·C`` (s) of the relaxation oscillator on capacitance C."""
    return _LN2x2 * _chip(chip).R_osc * _cap(C)


def expected_counts(C: ArrayLike, chip: ChipParams | None = None) -> FloatArray:
    """Mean number of rising edges in one gate (not wrapped): ``t_gate / T``.

    Exactly the average of :func:`counts` over a uniformly random oscillator phase.
    """
    ch = _chip(chip)
    return ch.gate_time / (_LN2x2 * ch.R_osc * _cap(C))


def counts(
    C: ArrayLike, chip: ChipParams | None = None, phase: ArrayLike = 0.0
) -> tuple[IntArray, NDArray[np.bool_]]:
    """(register value, overflow flag) the counter holds after one gate.

    ``phase`` ∈ [0, 1) places the first rising edge at ``phase·T`` after the gate
    opens; edges at exactly the gate end are not counted. The register is the edge
    count modulo 2^counter_bits; the flag is set if the count reached the modulus.
    C below :func:`sync_min_capacitance` is refused: the chip cannot count it.
    """
    ch = _chip(chip)
    ph = np.asarray(phase, dtype=np.float64)
    if not (np.all(ph >= 0) and np.all(ph < 1)):
        raise ValueError("phase must lie in [0, 1)")
    c = _cap(C)
    c_min = sync_min_capacitance(ch)
    if np.any(c < c_min):
        raise ValueError(
            f"capacitance {float(c.min()):g} F is below the synchroniser's limit "
            f"{c_min:g} F (oscillator period < 2 clock cycles): the chip cannot count it"
        )
    x = expected_counts(c, ch)
    n = np.maximum(np.ceil(x - ph), 0.0).astype(np.int64)
    return n % ch.counter_modulus, n >= ch.counter_modulus


def unwrap_counts(
    raw: ArrayLike,
    reference: ArrayLike,
    chip: ChipParams | None = None,
    overflow: ArrayLike | None = None,
) -> IntArray:
    """True edge count from a wrapped register value: ``raw + k·2^bits`` nearest ``reference``.

    ``reference`` is the channel's previous unwrapped count (or, for its first
    sample, the expected count of its rest capacitance); the answer is right while
    the count moved less than half a modulus (32 768 at 16 bits) since then, which
    :func:`check_gate` guarantees for any plausible reading. If the overflow flag is
    known it is used: no overflow means k = 0 exactly; overflow means k ≥ 1. This is
    the stateless rule; :class:`CounterUnwrapper` keeps the reference per channel and
    flags samples that cannot be trusted.
    """
    ch = _chip(chip)
    m = ch.counter_modulus
    r = np.asarray(raw)
    if not np.issubdtype(r.dtype, np.integer) or np.any(r < 0) or np.any(r >= m):
        raise ValueError(f"raw counts must be integers in [0, {m})")
    r = r.astype(np.int64)
    nom = np.asarray(reference, dtype=np.float64)
    if not np.all(np.isfinite(nom)):
        raise ValueError("the unwrap reference must be finite")
    k = np.maximum(np.rint((nom - r) / m), 0).astype(np.int64)
    if overflow is not None:
        ov = np.asarray(overflow, dtype=bool)
        k = np.where(ov, np.maximum(k, 1), 0)
    return r + k * m


def plausible_capacitance(
    params: ElementParams | None = None, margin: float = 0.1
) -> tuple[FloatArray, FloatArray]:
    """(lo, hi) per channel (C1, C2) in F: what an element can read, with ``margin``.

    lo is the rest capacitance less ``margin`` (drift of parasitics and foam), hi the
    fully saturated foam over the whole element plus ``margin``.
    """
    p = ElementParams() if params is None else params
    if not (0 <= margin < 1):
        raise ValueError(f"margin must lie in [0, 1), got {margin!r}")
    rest = np.array([p.C1_rest, p.C2_rest])
    full = rest + p.area * np.array([p.g1_max, p.g2_max])
    return rest * (1 - margin), full * (1 + margin)


#: Counts by which two integer readings may differ beyond their expected counts
#: difference (each is the expected count rounded up or down by the phase).
_COUNT_SLACK = 2


def counter_span(C_lo: ArrayLike, C_hi: ArrayLike, chip: ChipParams | None = None) -> FloatArray:
    """Counts between the lowest and the highest plausible capacitance, per channel."""
    ch = _chip(chip)
    return np.abs(expected_counts(C_lo, ch) - expected_counts(C_hi, ch))


def _range(C_lo: ArrayLike | None, C_hi: ArrayLike | None) -> tuple[FloatArray, FloatArray]:
    if (C_lo is None) != (C_hi is None):
        raise ValueError("give both C_lo and C_hi, or neither (the default element's range)")
    if C_lo is None or C_hi is None:
        return plausible_capacitance()
    lo, hi = np.broadcast_arrays(_cap(C_lo), _cap(C_hi))
    if np.any(hi <= lo):
        raise ValueError("the plausible range needs C_hi > C_lo")
    return lo, hi


def max_gate_cycles(
    C_lo: ArrayLike | None = None, C_hi: ArrayLike | None = None, chip: ChipParams | None = None
) -> int:
    """Longest gate (cycles) whose plausible count span stays within half a modulus.

    Within that, a reading can move between any two plausible values from one sample
    to the next and still be unwrapped unambiguously. Default range:
    :func:`plausible_capacitance` of the default element (≈ 226 000 cycles, 4.5 ms).
    """
    ch = _chip(chip)
    lo, hi = _range(C_lo, C_hi)
    per_cycle = float(np.max(counter_span(lo, hi, ch))) / ch.gate_cycles
    return int(math.floor((0.5 * ch.counter_modulus - _COUNT_SLACK) / per_cycle))


def check_gate(
    chip: ChipParams | None = None, C_lo: ArrayLike | None = None, C_hi: ArrayLike | None = None
) -> None:
    """ValueError if ``chip.gate_cycles`` is too long to unwrap the counter unambiguously.

    Whoever sets a gate (``SET_GATE``, configuration) asks this first: beyond
    :func:`max_gate_cycles` a press and a wrap look alike, and the error would be a
    plausible wrong ΔC, not a visible one.
    """
    ch = _chip(chip)
    limit = max_gate_cycles(C_lo, C_hi, ch)
    if ch.gate_cycles > limit:
        span = float(np.max(counter_span(*_range(C_lo, C_hi), ch)))
        raise ValueError(
            f"gate of {ch.gate_cycles} cycles: plausible readings span {span:.0f} counts, "
            f"more than half the counter's modulus ({ch.counter_modulus // 2}); the "
            f"longest unambiguous gate is {limit} cycles"
        )


class CounterUnwrapper:
    """Unwraps each channel's counter against its own previous sample, and says when
    it cannot be trusted. One per link or skin; arrays of any shape (e.g. N × 2).

    A sample is *ambiguous* (counted per channel in :attr:`ambiguous`, returned as a
    flag) when its count moved more than the plausible span since the last good
    sample, contradicts the overflow flag, or lies beyond what the synchroniser can
    count. An ambiguous sample does not move the reference; after ``resync``
    ambiguous samples in a row the channel re-anchors on the stateless rule around
    ``start`` (e.g. after an outage that spanned a press).
    """

    def __init__(
        self,
        C_lo: ArrayLike,
        C_hi: ArrayLike,
        chip: ChipParams | None = None,
        start: ArrayLike | None = None,
        resync: int = 3,
    ):
        self.chip = _chip(chip)
        lo, hi = _range(C_lo, C_hi)
        check_gate(self.chip, lo, hi)
        if not (isinstance(resync, (int, np.integer)) and not isinstance(resync, (bool, np.bool_))
                and resync >= 1):
            raise ValueError(f"resync must be an integer >= 1, got {resync!r}")
        self.resync = int(resync)
        self._lo, self._hi = lo, hi
        self._span = counter_span(lo, hi, self.chip) + _COUNT_SLACK
        c0 = np.sqrt(lo * hi) if start is None else np.broadcast_to(_cap(start), lo.shape)
        self._c0 = c0
        self._nominal = np.rint(expected_counts(c0, self.chip)).astype(np.int64)
        self._prev = self._nominal.copy()
        self._ambiguous = np.zeros(lo.shape, dtype=np.int64)
        self._run = np.zeros(lo.shape, dtype=np.int64)
        self._max = self.chip.gate_cycles / 2.0  # T ≥ 2 cycles

    @classmethod
    def for_elements(
        cls, n: int, chip: ChipParams | None = None, params: ElementParams | None = None
    ) -> CounterUnwrapper:
        """(n, 2) channels of elements ``params``, starting from their rest counts."""
        p = ElementParams() if params is None else params
        lo, hi = plausible_capacitance(p)
        shape = (int(n), 2)
        rest = np.broadcast_to([p.C1_rest, p.C2_rest], shape)
        return cls(np.broadcast_to(lo, shape), np.broadcast_to(hi, shape), chip, rest)

    def set_gate(self, gate_cycles: int) -> None:
        """Follow a gate change (``SET_GATE``) mid-stream, keeping every channel's reference.

        Counts scale with the gate, so each channel's last trusted count is rescaled
        to the new gate (off by at most the gate ratio plus one count, far inside the
        plausible span) — a fresh unwrapper anchored at rest would lose a channel
        whose parasitics drifted beyond the plausible range. A gate too long for the
        channels' range is refused (:func:`check_gate`) and changes nothing; the
        ``ambiguous`` counts are kept.
        """
        chip = replace(self.chip, gate_cycles=gate_cycles)
        check_gate(chip, self._lo, self._hi)
        ratio = chip.gate_cycles / self.chip.gate_cycles
        self._prev = np.rint(self._prev * ratio).astype(np.int64)
        self._nominal = np.rint(expected_counts(self._c0, chip)).astype(np.int64)
        self._span = counter_span(self._lo, self._hi, chip) + _COUNT_SLACK
        self._max = chip.gate_cycles / 2.0
        self._run[...] = 0
        self.chip = chip

    @property
    def previous(self) -> IntArray:
        """Each channel's last trusted count."""
        return self._prev.copy()

    @property
    def ambiguous(self) -> IntArray:
        """How many samples of each channel were flagged ambiguous."""
        return self._ambiguous.copy()

    def unwrap(
        self, raw: ArrayLike, overflow: ArrayLike | None = None, sampled: ArrayLike | None = None
    ) -> tuple[IntArray, NDArray[np.bool_]]:
        """(counts, ambiguous) for one sample of every channel (``sampled``: which
        channels carry a new sample, raw's shape or (…, 1) per element; the others
        are left alone and returned as 0).

        ``raw`` may be a float array with NaN (or anything) in the channels that were
        not sampled, as the rest of the host's per-element arrays are; the sampled
        ones must hold integer counts."""
        r = np.asarray(raw)
        if r.shape != self._prev.shape:
            raise ValueError(f"raw must have shape {self._prev.shape}, got {r.shape}")
        if sampled is None:
            s = np.ones(r.shape, dtype=bool)
        else:
            sm = np.asarray(sampled, dtype=bool)
            per_element = r.shape[:-1] + (1,)
            if sm.ndim and sm.shape not in (r.shape, per_element):
                # e.g. (N,) for N = C would broadcast over the channels, not the elements
                raise ValueError(
                    f"sampled must have raw's shape {r.shape}, one flag per element "
                    f"{per_element} or be a scalar, got {sm.shape}"
                )
            s = np.broadcast_to(sm, r.shape)
        r = np.where(s, r, 0)
        if r.dtype.kind == "f":
            m = self.chip.counter_modulus
            if not np.all((r == np.round(r)) & (r >= 0) & (r < m)):  # False for NaN
                raise ValueError(f"raw counts must be integers in [0, {m})")
            r = r.astype(np.int64)
        ov = None if overflow is None else np.where(s, np.asarray(overflow, dtype=bool), False)
        n = unwrap_counts(r, self._prev, self.chip, ov)
        amb = s & ((np.abs(n - self._prev) > self._span) | (n <= 0) | (n > self._max))
        good = s & ~amb
        self._prev = np.where(good, n, self._prev)
        self._run = np.where(good, 0, self._run + amb)
        self._ambiguous += amb
        lost = self._run >= self.resync
        if lost.any():
            self._prev = np.where(lost, unwrap_counts(r, self._nominal, self.chip, ov), self._prev)
            self._run[lost] = 0
        return np.where(s, n, 0), amb


def counts_to_capacitance(
    n: ArrayLike, chip: ChipParams | None = None
) -> FloatArray:
    """Capacitance (F) whose expected count is ``n`` (unwrapped; may be a mean).

    NaN for anything no counted oscillator gives: non-finite, zero or negative (a
    dead oscillator or no reading), so few edges that C would exceed ``C_MAX``, or
    more than one edge per two cycles (beyond the synchroniser). A NaN is "no
    reading", which every later stage handles.
    """
    ch = _chip(chip)
    nn = np.asarray(n, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        c = ch.gate_time / (_LN2x2 * ch.R_osc * nn)
    ok = (nn > 0) & (nn <= ch.gate_cycles / 2.0) & (c <= C_MAX)
    return np.where(ok, c, np.nan)


def counter_delta(
    dC: ArrayLike, C_rest: ArrayLike, phase: ArrayLike = 0.0, chip: ChipParams | None = None
) -> FloatArray:
    """ΔC as one counter gate reports it: ``C_rest + dC`` counted, unwrapped and
    converted back, minus ``C_rest``. The quantisation a host sees from a noise-free
    element, for simulations and benchmarks of everything downstream of the counter.

    ValueError for a gate :func:`check_gate` refuses (as the host's
    :class:`CounterUnwrapper` does): beyond it a press unwraps as a wrap, and a +7.65 pF
    press came back as −3.87 pF, a plausible wrong answer rather than a visible one.
    """
    ch = _chip(chip)
    check_gate(ch)
    rest = np.asarray(C_rest, dtype=np.float64)
    raw, overflow = counts(rest + np.asarray(dC, dtype=np.float64), ch, phase)
    n = unwrap_counts(raw, expected_counts(rest, ch), ch, overflow)
    return counts_to_capacitance(n, ch) - rest


def counts_per_farad(C: ArrayLike, chip: ChipParams | None = None) -> FloatArray:
    """|d counts / dC| at C (counts per farad; × 1e-12 for counts per pF)."""
    ch = _chip(chip)
    c = _cap(C)
    return ch.gate_time / (_LN2x2 * ch.R_osc * c * c)


# --------------------------------------------------------------------------- ADC


def adc_input(C: ArrayLike, chip: ChipParams | None = None) -> FloatArray:
    """Sampled voltage in LSB (continuous code, before quantisation): 2^bits·(1 − e^(−t/RC))."""
    ch = _chip(chip)
    return ch.adc_levels * -np.expm1(-ch.adc_sample_time / (ch.R_adc * _cap(C)))


def adc_code(
    C: ArrayLike, chip: ChipParams | None = None, noise: ArrayLike | None = None
) -> IntArray:
    """Code of one conversion: floor of the input (plus ``noise`` in LSB), clipped.

    ``noise`` is input-referred noise the caller draws (e.g. ``rng.normal(0, 0.5, n)``),
    so this function stays deterministic and the emulator controls its randomness.
    """
    ch = _chip(chip)
    x = adc_input(C, ch)
    if noise is not None:
        nz = np.asarray(noise, dtype=np.float64)
        if not np.all(np.isfinite(nz)):
            raise ValueError("ADC noise must be finite (LSB)")
        x = x + nz
    return np.clip(np.floor(x), 0, ch.adc_levels - 1).astype(np.int64)


def _input_to_cap(x: FloatArray, ch: ChipParams) -> FloatArray:
    # Input 0 LSB is C → ∞, full scale is C → 0: neither is a capacitance, so NaN.
    frac = x / ch.adc_levels
    with np.errstate(divide="ignore", invalid="ignore"):
        c = ch.adc_sample_time / (ch.R_adc * -np.log1p(-frac))
    return np.where((frac > 0) & (frac < 1), c, np.nan)


def code_to_capacitance(code: ArrayLike, chip: ChipParams | None = None) -> FloatArray:
    """Capacitance (F) at the middle of a code's input step (one conversion).

    The rail codes are open-ended (0: C ≤ …, top code: C ≥ …); they still map to their
    step middle, and a caller that meets them should treat the value as a bound.
    """
    ch = _chip(chip)
    k = np.asarray(code)
    if k.dtype.kind not in "iu" and not (
        k.dtype.kind == "f" and np.all(np.isfinite(k)) and np.all(k == np.round(k))
    ):
        raise ValueError(f"ADC codes must be integers, got {code!r}")
    if np.any(k < 0) or np.any(k >= ch.adc_levels):
        raise ValueError(f"ADC code must lie in [0, {ch.adc_levels})")
    return _input_to_cap(k.astype(np.float64) + 0.5, ch)


def codes_per_farad(C: ArrayLike, chip: ChipParams | None = None) -> FloatArray:
    """|d code / dC| at C (LSB per farad; × 1e-12 for codes per pF)."""
    ch = _chip(chip)
    c = _cap(C)
    t = ch.adc_sample_time / (ch.R_adc * c)
    return ch.adc_levels * np.exp(-t) * t / c


_SQRT1_2 = 1.0 / math.sqrt(2.0)


def _erfc(z: FloatArray) -> FloatArray:
    """Complementary error function, |relative error| < 1.2e-7 (Chebyshev fit, pure numpy).

    numpy has no erf; this accuracy is far below the ADC's resolution.
    """
    a = np.abs(z)
    t = 1.0 / (1.0 + 0.5 * a)
    poly = -a * a - 1.26551223 + t * (1.00002368 + t * (0.37409196 + t * (0.09678418
        + t * (-0.18628806 + t * (0.27886807 + t * (-1.13520398 + t * (1.48851587
        + t * (-0.82215223 + t * 0.17087277))))))))
    r = t * np.exp(poly)
    return np.where(z >= 0, r, 2.0 - r)


def _code_moments(
    x: FloatArray, sigma: float, levels: int
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Mean, variance and d(mean)/dx of clip(floor(x + n)), n ~ N(0, σ²), in LSB.

    code = Σ_{k=1}^{L−1} [x + n ≥ k], so E[code] = Σ Φ((x − k)/σ) and
    E[code²] = Σ (2k − 1)·Φ((x − k)/σ). Only thresholds within ±9σ of x contribute
    a fraction; the rest are 0 or 1 and are counted in closed form.
    """
    w = int(math.ceil(9.0 * sigma)) + 1
    base = np.floor(x)
    mean = np.clip(base - w, 0, levels - 1)  # thresholds k ≤ base − w: all passed
    # E[code²] of those: Σ_{k=1}^{m} (2k−1) = m²
    sq = mean * mean
    dmean = np.zeros_like(x)
    for off in range(-w + 1, w + 1):
        k = base + off
        inside = (k >= 1) & (k <= levels - 1)
        z = (x - k) / sigma
        phi = 0.5 * _erfc(-z * _SQRT1_2)
        pdf = np.exp(-0.5 * z * z) / (sigma * math.sqrt(2.0 * math.pi))
        mean = mean + np.where(inside, phi, 0.0)
        sq = sq + np.where(inside, (2.0 * k - 1.0) * phi, 0.0)
        dmean = dmean + np.where(inside, pdf, 0.0)
    return mean, np.maximum(sq - mean * mean, 0.0), dmean


def _noise_lsb(ch: ChipParams, noise_lsb: float | None) -> float:
    s = ch.adc_noise_lsb if noise_lsb is None else float(noise_lsb)
    if not (math.isfinite(s) and s >= 0):
        raise ValueError(f"ADC noise must be finite and >= 0 LSB, got {noise_lsb!r}")
    return s


def adc_mean_code(
    C: ArrayLike, chip: ChipParams | None = None, noise_lsb: float | None = None
) -> FloatArray:
    """Expected code averaged over many conversions with Gaussian input noise.

    With ``noise_lsb`` (default ``chip.adc_noise_lsb``) of 0 this is the plain code.
    With 0.5 LSB it is the input minus ½ to within ≈0.002 LSB; the exact sum is used.
    """
    ch = _chip(chip)
    s = _noise_lsb(ch, noise_lsb)
    x = adc_input(C, ch)
    if s == 0:
        return np.clip(np.floor(x), 0, ch.adc_levels - 1)
    return _code_moments(np.asarray(x, dtype=np.float64), s, ch.adc_levels)[0]


def adc_mean_band(chip: ChipParams | None = None, noise_lsb: float | None = None) -> tuple[float, float]:
    """(lo, hi): the mean codes that say something about C.

    They are the means at inputs of 1 LSB and full scale − 1 LSB, the first and last
    code thresholds. Below lo the channel reads like a short (C → ∞), above hi like an
    open input (C → 0); :func:`adc_mean_to_capacitance` gives NaN there.
    """
    ch = _chip(chip)
    s = _noise_lsb(ch, noise_lsb)
    if s == 0:
        return 1.0, float(ch.adc_levels - 1)
    m = _code_moments(np.array([1.0, ch.adc_levels - 1.0]), s, ch.adc_levels)[0]
    return float(m[0]), float(m[1])


#: |mean − target| at which the inversion stops (LSB), and the largest input error
#: (LSB) accepted: a bracket that narrow, or a leftover that small where the mean is
#: flat; otherwise NaN.
_MEAN_TOL = 1e-11
_INPUT_TOL = 1e-6


def adc_mean_to_capacitance(
    mean_code: ArrayLike, chip: ChipParams | None = None, noise_lsb: float | None = None
) -> FloatArray:
    """Capacitance (F) whose expected oversampled mean code is ``mean_code``.

    Inverts :func:`adc_mean_code` for the input (LSB) by Newton's method kept inside
    a bracket (the mean is monotone in the input; a step leaving the bracket is
    replaced by bisection), and checks the result: NaN where it did not converge or
    where the mean is too flat to fix the input to ``1e-6`` LSB (little noise,
    between codes), and for means outside :func:`adc_mean_band` (open or shorted
    channel). Needs noise > 0: the dither is what makes the mean a function of C.
    """
    ch = _chip(chip)
    s = _noise_lsb(ch, noise_lsb)
    if not s > 0:
        raise ValueError("inverting a mean code needs adc noise > 0 (use code_to_capacitance)")
    m = np.asarray(mean_code, dtype=np.float64)
    levels = ch.adc_levels
    band_lo, band_hi = adc_mean_band(ch, s)
    inside = ((m >= band_lo) & (m <= band_hi)).ravel()  # False for NaN
    target = np.where(inside, m.ravel(), 0.5 * (band_lo + band_hi))
    lo = np.full(target.shape, 1.0)
    hi = np.full(target.shape, levels - 1.0)
    x = np.clip(target + 0.5, lo, hi)
    for _ in range(200):
        mu, _, dmu = _code_moments(x, s, levels)
        r = mu - target
        lo = np.where(r < 0, x, lo)
        hi = np.where(r > 0, x, hi)
        done = (np.abs(r) <= _MEAN_TOL) | (hi - lo <= _INPUT_TOL)
        if done.all():
            break
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            step = x - r / dmu
        keep = (step >= lo) & (step <= hi)  # False for NaN
        x = np.where(done, x, np.where(keep, step, 0.5 * (lo + hi)))
    # Converged: the bracket itself pins the input, or the mean matches where it is
    # steep enough that the leftover means < _INPUT_TOL (on a float-flat stretch
    # between codes the match says nothing about where on the stretch we are).
    with np.errstate(divide="ignore"):
        converged = (hi - lo <= _INPUT_TOL) | ((np.abs(r) <= _MEAN_TOL) & (_MEAN_TOL / dmu <= _INPUT_TOL))
    ok = inside & converged
    return np.where(ok, _input_to_cap(x, ch), np.nan).reshape(m.shape)


def adc_resolution(
    C: ArrayLike,
    n: ArrayLike = 1,
    chip: ChipParams | None = None,
    noise_lsb: float | None = None,
) -> FloatArray:
    """RMS capacitance error (F) of the mean of ``n`` conversions at capacitance C.

    The spread of one dithered code (≈√(σ² + 1/12) LSB for σ ≳ 0.3) shrinks as
    1/√n; divided by the local slope d(mean)/dC. With no noise the code does not
    average out, so the answer is the quantisation step's 1/√12 whatever n is.
    """
    ch = _chip(chip)
    s = _noise_lsb(ch, noise_lsb)
    nn = np.asarray(n, dtype=np.float64)
    if np.any(nn < 1):
        raise ValueError("number of conversions n must be >= 1")
    x = adc_input(C, ch)
    slope_c = codes_per_farad(C, ch)
    if s == 0:
        return np.broadcast_to(1.0 / math.sqrt(12.0) / slope_c, np.broadcast(x, nn).shape).copy()
    _, var, dmu = _code_moments(np.asarray(x, dtype=np.float64), s, ch.adc_levels)
    return np.sqrt(var / nn) / (dmu * slope_c)
