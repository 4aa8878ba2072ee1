"""The daemon's front end: a bridge's raw readings (counter values or summed ADC codes) →
capacitances, through the chip's transfer functions in :mod:`cellbridge.tactile`."""

from __future__ import annotations

import math

import numpy as np
from cellbridge.daemon.core.config import ChipSection
from cellbridge.daemon.core.wire import ADC_MODE, OVERFLOW_C1, OVERFLOW_C2
from cellbridge.tactile import (
    ChipParams,
    ElementParams,
    adc_mean_code,
    expected_counts,
)
from cellbridge.tactile.arrays import FloatArray
from cellbridge.tactile.transfer import C_MAX
from numpy.typing import NDArray


class Frontend:
    """Counts (counter mode) or summed ADC codes (ADC mode) → capacitances in farads.

    The counter's gate may differ per bridge (SET_GATE): C ∝ gate/count, so a count at
    gate g is converted as the count ``n·g0/g`` at the reference gate g0. ADC means are
    inverted through a dense table of the exact dithered mean-code curve (the
    transfer function's own Newton inversion is exact but far too slow per sample).

    A counter reading is converted with the arithmetic of :func:`~cellbridge.tactile.unwrap_counts`
    and :func:`~cellbridge.tactile.counts_to_capacitance`, step for step (every result theirs,
    bit for bit: ``tests/test_daemon_frontend.py``), in one pass without their checks of
    arguments that come from here: those checks and their numpy calls were most of a skin
    frame's conversion (about 125 samples of an event-based humanoid's frame).
    """

    def __init__(self, params: ElementParams, chip: ChipParams) -> None:
        self.chip = chip
        self.rest = np.array([params.C1_rest, params.C2_rest])
        self._nominal = expected_counts(self.rest, chip)  # counts at rest, reference gate
        caps = np.geomspace(0.5e-12, 1e-9, 6000)
        means = adc_mean_code(caps, chip)  # falls as C grows
        order = np.argsort(means, kind="stable")
        self._adc_means, self._adc_caps = means[order], caps[order]
        self._adc_top = chip.adc_levels - 1
        self._ov_bits = np.array([OVERFLOW_C1, OVERFLOW_C2])
        # the chip's constants as the transfer functions compute them (a frozen ChipParams)
        self._modulus = chip.counter_modulus
        self._gate_cycles = chip.gate_cycles
        self._gate_time = chip.gate_time
        self._per_count = 2.0 * math.log(2.0) * chip.R_osc  # counts_to_capacitance's divisor per count
        self._half_gate = chip.gate_cycles / 2.0

    def capacitance(self, mode: NDArray[np.int64], over: NDArray[np.int64], raw: NDArray[np.int64],
                    flags: NDArray[np.int64], gate: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """(C in F, saturated), both (n, 2), from (n, 2) raw readings. Saturated: a dead
        oscillator or a counter value no counter can hold, an ADC mean at a rail (C is NaN
        for the impossible and the railed)."""
        if raw.shape[0] == 0:  # (an event-based frame of unchanged elements only: no call's overhead)
            return np.empty((0, 2)), np.zeros((0, 2), dtype=bool)
        adc = mode == ADC_MODE
        if not adc.any():
            return self._counter(raw, flags, gate)
        caps = np.empty(raw.shape)
        sat = np.empty(raw.shape, dtype=bool)
        cnt = ~adc
        if cnt.any():
            caps[cnt], sat[cnt] = self._counter(raw[cnt], flags[cnt], gate[cnt])
        mean = raw[adc] / over[adc][:, None]
        rail = (mean <= 0) | (mean >= self._adc_top)
        caps[adc] = np.where(rail, np.nan, np.interp(mean, self._adc_means, self._adc_caps))
        sat[adc] = rail
        return caps, sat

    def _counter(self, raw: NDArray[np.int64], flags: NDArray[np.int64], gate: FloatArray
                 ) -> tuple[FloatArray, NDArray[np.bool_]]:
        """unwrap_counts (the overflow flags known) then counts_to_capacitance of the count
        at the reference gate, with their arithmetic; a counter value the chip's counter cannot
        hold is a corrupt reading (saturated, NaN). Raises ValueError where unwrap_counts
        would: a negative counter value, a gate that is not finite."""
        m = self._modulus
        bad: NDArray[np.bool_] | None = None
        if raw.max() >= m or raw.min() < 0:  # only a corrupt reading
            if raw.min() < 0:
                raise ValueError(f"raw counts must be integers in [0, {m})")
            bad = raw >= m
            raw = np.where(bad, 0, raw)
        if not np.isfinite(gate).all():  # (then the unwrap reference nominal·gate/gate_cycles is not)
            raise ValueError("the unwrap reference must be finite")
        ratio = (self._gate_cycles / gate)[:, None]
        ov = (flags[:, None] & self._ov_bits) != 0
        # unwrap_counts: k = max(rint((reference - raw) / m), 0), at least 1 with the overflow
        # flag, else 0; raw + k·m, exact in float64 as in int64 (counts far below 2^53)
        k = np.rint((self._nominal / ratio - raw) / m)
        n = raw + np.where(ov, np.maximum(k, 1.0), 0.0) * m
        nn = n * ratio
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            c = self._gate_time / (self._per_count * nn)
        caps = np.where((nn > 0) & (nn <= self._half_gate) & (c <= C_MAX), c, np.nan)
        sat = n <= 0
        if bad is not None:
            sat |= bad
            caps[bad] = np.nan
        return caps, sat


def chip_params(section: ChipSection) -> ChipParams:
    return ChipParams(clock_hz=section.clock_hz, gate_cycles=section.gate_cycles)
