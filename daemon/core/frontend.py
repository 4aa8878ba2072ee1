"""The daemon's front end: a bridge's raw readings (counter values or summed ADC codes) →
capacitances, through the chip's transfer functions in :mod:`cellbridge.tactile`."""

from __future__ import annotations

import numpy as np
from cellbridge.daemon.core.config import ChipSection
from cellbridge.daemon.core.wire import ADC_MODE, OVERFLOW_C1, OVERFLOW_C2
from cellbridge.tactile import (
    ChipParams,
    ElementParams,
    adc_mean_code,
    counts_to_capacitance,
    expected_counts,
    unwrap_counts,
)
from cellbridge.tactile.arrays import FloatArray
from numpy.typing import NDArray


class Frontend:
    """Counts (counter mode) or summed ADC codes (ADC mode) → capacitances in farads.

    The counter's gate may differ per bridge (SET_GATE): C ∝ gate/count, so a count at
    gate g is converted as the count ``n·g0/g`` at the reference gate g0. ADC means are
    inverted through a dense table of the exact dithered mean-code curve (the
    transfer function's own Newton inversion is exact but far too slow per sample).
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
        ratio = (self.chip.gate_cycles / gate)[:, None]
        bad = raw >= self.chip.counter_modulus  # only a corrupt reading: the counter has 16 bits
        if bad.any():
            raw = np.where(bad, 0, raw)
        ov = (flags[:, None] & self._ov_bits) != 0
        n = unwrap_counts(raw, self._nominal / ratio, self.chip, ov)
        caps = counts_to_capacitance(n * ratio, self.chip)
        sat = (n <= 0) | bad
        if bad.any():
            caps[bad] = np.nan
        return caps, sat


def chip_params(section: ChipSection) -> ChipParams:
    return ChipParams(clock_hz=section.clock_hz, gate_cycles=section.gate_cycles)
