"""The bridge chip, cycle-exact: clock and crystal, RC-oscillator counter, charge-time ADC.

Time inside a chip is an integer cycle count of its own 50 MHz crystal, which runs
``crystal_ppm`` fast or slow (:meth:`Chip.cycles_at`). The physics — oscillator
period, ADC charging curve, crystal scaling — is
:mod:`cellbridge.tactile.transfer`'s (via :attr:`ChipConfig.transfer_params`), so the
emulator produces exactly what the host's inverse expects; this module adds what a
transfer function cannot: jitter, the synchroniser, the 16-bit register, noise and
cycle timing.

The fast path (this module, with :mod:`.oscillator` and :mod:`.adc`) gives the same
counts, flags, codes and cycles as the per-cycle stepper in :mod:`.reference`; the
tests check that bit for bit, and ``bench/bench_chip.py`` measures the speed-up.

Randomness is keyed, never sequential: a gate's phase and jitter and a conversion's
noise depend on (seed, channel, start cycle) only (:mod:`.keyed_random`), so any call
can be repeated or replayed in any order and gives the same answer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from cellbridge.emulator.chip.adc import AdcTiming, held_inputs, sar_codes
from cellbridge.emulator.chip.keyed_random import GateNoise, KeyedNormals, Stream
from cellbridge.emulator.chip.oscillator import EdgeTrain, gate_edge_count, gate_edge_counts, max_period_deviation
from cellbridge.tactile.transfer import C_MAX, ChipParams, adc_input, oscillator_period

__all__ = ["CLOCK_HZ", "MIN_PERIOD_CYCLES", "ChipConfig", "Chip"]

CLOCK_HZ: int = 50_000_000
#: Shortest oscillator period modelled (cycles). Faster oscillators are aliased by the
#: synchroniser into meaningless counts, and following each edge costs gate/T work.
#: At the defaults this is C ≥ 0.77 pF; a real channel has ≥ 10 pF of parasitics.
MIN_PERIOD_CYCLES = 0.25
#: Largest capacitance accepted (F): the transfer functions' bound, far above any
#: element and far below picofarads passed as farads.
MAX_CAPACITANCE = C_MAX


@dataclass(frozen=True)
class ChipConfig:
    """One chip's hardware; the defaults are the reference chip (docs/emulator-chip.md)."""

    clock_hz: int = CLOCK_HZ
    crystal_ppm: float = 0.0  #: this chip's crystal offset (host seconds -> chip cycles)
    r_ohm: float = 4700.0  #: RC oscillator resistor
    #: Per-period relative jitter (rms). Comparator noise in an RC relaxation oscillator
    #: gives period jitter of order 1e-4..1e-3; the upper end is taken, so that the
    #: counter's noise (docs/emulator-chip.md) is not optimistic.
    jitter: float = 1e-3
    gate_cycles: int = 100_000  #: default counter gate (2 ms)
    counter_bits: int = 16
    adc_r_ohm: float = 100e3  #: charge-time ADC resistor
    adc_sample_delay: int = 64  #: cycles from release to sample
    adc_discharge_cycles: int = 8  #: cycles the channel is shorted before release
    adc_bits: int = 8  #: SAR resolution, one bit decided per cycle
    adc_noise_lsb: float = 0.5  #: input noise, rms LSB
    crystal_tolerance_ppm: float = 50.0  #: range :meth:`with_random_crystal` draws from

    def __post_init__(self) -> None:
        for name in ("clock_hz", "gate_cycles", "counter_bits", "adc_sample_delay", "adc_bits"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v > 0):
                raise ValueError(f"ChipConfig.{name} must be a positive integer, got {v!r}")
        v = self.adc_discharge_cycles
        if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 0):
            raise ValueError(f"ChipConfig.adc_discharge_cycles must be an integer >= 0, got {v!r}")
        for name in ("r_ohm", "adc_r_ohm"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"ChipConfig.{name} must be finite and > 0, got {v!r}")
        for name in ("adc_noise_lsb", "crystal_tolerance_ppm"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"ChipConfig.{name} must be finite and >= 0, got {v!r}")
        limit = 1.0 / max_period_deviation()
        if not (math.isfinite(self.jitter) and 0.0 <= self.jitter < limit):
            raise ValueError(
                f"ChipConfig.jitter must lie in [0, {limit:.4f}) (periods stay positive), "
                f"got {self.jitter!r}"
            )
        # The transfer parameters check the rest (counter/ADC widths, crystal range).
        try:
            _ = self.transfer_params
        except ValueError as exc:
            raise ValueError(f"ChipConfig: {exc}") from None

    @property
    def transfer_params(self) -> ChipParams:
        """The same chip as :mod:`cellbridge.tactile.transfer` describes it."""
        return ChipParams(
            clock_hz=float(self.clock_hz),
            gate_cycles=self.gate_cycles,
            R_osc=self.r_ohm,
            R_adc=self.adc_r_ohm,
            adc_sample_cycles=self.adc_sample_delay,
            adc_bits=self.adc_bits,
            counter_bits=self.counter_bits,
            clock_ppm=self.crystal_ppm,
            adc_noise_lsb=self.adc_noise_lsb,
        )

    @property
    def adc_timing(self) -> AdcTiming:
        return AdcTiming(self.adc_discharge_cycles, self.adc_sample_delay, self.adc_bits)

    def with_random_crystal(self, seed: int) -> ChipConfig:
        """This config with a crystal offset drawn uniformly from ±crystal_tolerance_ppm.

        Deterministic for a seed, so a mesh can give each bridge its own crystal."""
        u = KeyedNormals(seed).uniform(Stream.CRYSTAL, 0, 0)
        ppm = (2.0 * u - 1.0) * self.crystal_tolerance_ppm
        return replace(self, crystal_ppm=ppm)


def _check_int(name: str, v: object, minimum: int) -> int:
    if type(v) is int and v >= minimum:  # the common case, checked cheaply
        return v
    if not (isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= minimum):
        raise ValueError(f"{name} must be an integer >= {minimum}, got {v!r}")
    return int(v)


def _check_capacitance(c: object) -> float:
    try:
        v = float(c)  # type: ignore[arg-type]  # any object: float() decides whether it is a number
    except (TypeError, ValueError):
        raise ValueError(f"capacitance must be a number in farads, got {c!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"capacitance must be finite and > 0 F, got {c!r}")
    if v > MAX_CAPACITANCE:
        raise ValueError(
            f"capacitance must be in farads (<= {MAX_CAPACITANCE:g} F), got {c!r}: "
            "picofarads passed as farads?"
        )
    return v


class Chip:
    """One bridge chip: counts and conversions on demand at given cycles.

    Stateless between calls: each call is a function of (config, seed, its arguments).
    ``channel`` is the channel index (by convention 0 = C1, 1 = C2); it keys the noise.
    """

    def __init__(self, config: ChipConfig = ChipConfig(), seed: int = 0) -> None:
        self.config = config
        self.seed = seed
        self.params = config.transfer_params
        self._clock = self.params.clock_actual_hz
        self._noise = KeyedNormals(seed)
        self._modulus = 1 << config.counter_bits
        self._timing = config.adc_timing
        self._adc_cache: dict[float, float] = {}
        #: counts computed ahead (:meth:`prefetch`): (channel, capacitance, start, gate) -> result
        self._ahead: dict[tuple[int, float, int, int], tuple[int, bool]] = {}
        self.prefetch_hits = 0  #: counts answered from :meth:`prefetch`
        # T is linear in C: evaluate transfer.oscillator_period once, not per gate.
        self._period_per_farad = float(oscillator_period(1e-12, self.params)) * self._clock / 1e-12
        #: whether count may take gate_edge_count's path: a jitter EdgeTrain accepts (else
        #: every count builds the train, which says what is wrong)
        self._fast_ok = math.isfinite(self._period_per_farad) and 0.0 <= config.jitter * max_period_deviation() < 1.0

    # ------------------------------------------------------------------ clock

    def cycles_at(self, host_seconds: float) -> int:
        """The chip's cycle counter at a host time (crystal offset applied)."""
        if not math.isfinite(host_seconds) or host_seconds < 0:
            raise ValueError(f"host_seconds must be finite and >= 0, got {host_seconds!r}")
        return math.floor(host_seconds * self._clock)

    def seconds_at(self, cycle: int) -> float:
        """Host time (s) at which the chip's counter reaches ``cycle`` (inverse of cycles_at)."""
        return cycle / self._clock

    # ---------------------------------------------------------------- counter

    def period_cycles(self, capacitance: float) -> float:
        """Oscillator period in this chip's cycles."""
        return capacitance * self._period_per_farad

    def edge_train(self, channel: int, capacitance: float, start_cycle: int, gate_cycles: int) -> EdgeTrain:
        """The oscillator's edges for one gate (the definition both paths evaluate)."""
        channel = _check_int("channel", channel, 0)
        start_cycle = _check_int("start_cycle", start_cycle, 0)
        gate_cycles = _check_int("gate_cycles", gate_cycles, 1)
        c = _check_capacitance(capacitance)
        period = self.period_cycles(c)
        if period < MIN_PERIOD_CYCLES:
            raise ValueError(
                f"capacitance {c!r} F gives an oscillator period of {period:.3g} cycles; the chip "
                f"model needs >= {MIN_PERIOD_CYCLES} (C >= {MIN_PERIOD_CYCLES / self._period_per_farad:.3g} F)"
            )
        return EdgeTrain(
            period, self.config.jitter, None, gate_cycles, GateNoise(self._noise, channel, start_cycle)
        )

    def count(self, channel: int, capacitance: float, start_cycle: int, gate_cycles: int) -> tuple[int, bool]:
        """16-bit edge count over [start_cycle, start_cycle+gate_cycles) and the overflow flag.

        ``capacitance`` is the channel's total capacitance in farads (parasitic included).
        Deterministic for (seed, channel, start_cycle): the same call twice gives the same answer.
        """
        if self._ahead:
            got = self._ahead.pop((channel, capacitance, start_cycle, gate_cycles), None)
            if got is not None:
                self.prefetch_hits += 1
                return got
        n = None
        if (type(capacitance) is float and 0.0 < capacitance <= MAX_CAPACITANCE and type(channel) is int
                and channel >= 0 and type(start_cycle) is int and start_cycle >= 0
                and type(gate_cycles) is int and gate_cycles >= 1 and self._fast_ok):
            period = capacitance * self._period_per_farad  # period_cycles, inline
            if period >= MIN_PERIOD_CYCLES:
                n = gate_edge_count(period, self.config.jitter, gate_cycles, self._noise, channel, start_cycle)
        if n is None:  # arguments to check, or an oscillator the synchroniser misses edges of
            n = self.edge_train(channel, capacitance, start_cycle, gate_cycles).edge_count()
        return n % self._modulus, n >= self._modulus

    def prefetch(self, gates: list[tuple[int, float, int, int]]) -> None:
        """Compute the counts of ``gates`` (channel, capacitance, start_cycle, gate_cycles)
        now, for :meth:`count` to answer from later when called with exactly those
        arguments; others are computed then, as ever. A count is a function of its
        arguments alone, so the answers are the same either way. What this buys is
        *when* the work runs: a real-time bridge process computes the next gates' counts
        back to back in one wake, with the chip model's code and data warm, instead of
        each in a wake of its own after 16 other processes ran (several times the CPU).
        What was computed ahead and not asked for before ``gates``' first start is
        forgotten here."""
        if not gates:
            return
        first = min(g[2] for g in gates)
        ahead = self._ahead
        for key in [k for k in ahead if k[2] < first]:
            del ahead[key]
        todo: dict[tuple[int, float, int], list[int]] = {}  # (channel, capacitance, gate) -> starts
        # Gates for the fast path are only noted here and enter ``ahead`` once computed:
        # a place held in it with a dummy count would be answered by count() if anything
        # below raised (a gate whose count() refuses its arguments, an interrupt).
        held: set[tuple[int, float, int, int]] = set()
        room = 64 - len(ahead)
        for key in gates:
            if room > 0 and key not in ahead and key not in held:
                ch, c, start, gate = key
                if (type(c) is float and 0.0 < c <= MAX_CAPACITANCE and type(ch) is int and ch >= 0
                        and type(start) is int and start >= 0 and type(gate) is int and gate >= 1 and self._fast_ok
                        and c * self._period_per_farad >= MIN_PERIOD_CYCLES):
                    todo.setdefault((ch, c, gate), []).append(start)  # computed below with its channel's others
                    held.add(key)
                else:
                    ahead[key] = self.count(*key)
                room -= 1
        # the gates of one channel and capacitance together (gate_edge_counts: the same counts)
        modulus = self._modulus
        for (ch, c, gate), starts in todo.items():
            got = gate_edge_counts(c * self._period_per_farad, self.config.jitter, gate, self._noise, ch, starts)
            for start, n in zip(starts, got if got is not None else [None] * len(starts)):
                if n is None:
                    n = self.edge_train(ch, c, start, gate).edge_count()
                ahead[(ch, c, start, gate)] = (n % modulus, n >= modulus)

    def computed(self, channel: int, capacitance: float, start_cycle: int, gate_cycles: int) -> bool:
        """Whether :meth:`count` with these arguments is answered from :meth:`prefetch`."""
        return (channel, capacitance, start_cycle, gate_cycles) in self._ahead

    # -------------------------------------------------------------------- ADC

    def held_inputs(self, channel: int, capacitance: float, start_cycle: int, oversampling: int) -> np.ndarray:
        """Sample-and-hold values (LSB) of the conversions one :meth:`convert` call runs."""
        channel = _check_int("channel", channel, 0)
        start_cycle = _check_int("start_cycle", start_cycle, 0)
        oversampling = _check_int("oversampling", oversampling, 1)
        clean = self._adc_clean(_check_capacitance(capacitance))
        noise = self._noise.normals(Stream.ADC, channel, start_cycle, oversampling)
        return held_inputs(clean, noise * self.config.adc_noise_lsb)

    def _adc_clean(self, capacitance: float) -> float:
        """Noise-free held value (LSB), memoised: a channel at rest repeats its capacitance."""
        v = self._adc_cache.get(capacitance)
        if v is None:
            if len(self._adc_cache) >= 4096:
                self._adc_cache.clear()
            v = self._adc_cache[capacitance] = float(adc_input(capacitance, self.params))
        return v

    def convert(self, channel: int, capacitance: float, start_cycle: int, oversampling: int) -> tuple[int, int]:
        """Sum of `oversampling` 8-bit charge-time conversions and the cycles they took."""
        held = self.held_inputs(channel, capacitance, start_cycle, oversampling)
        codes = sar_codes(held, self.config.adc_bits)
        return int(codes.sum()), oversampling * self._timing.conversion_cycles
