"""Measure the emulated chip's reading noise the way the host sees it.

The host turns a counter value into a capacitance with
:func:`~cellbridge.tactile.transfer.counts_to_capacitance` and an oversampled ADC sum
with :func:`~cellbridge.tactile.transfer.adc_mean_to_capacitance`; the rms spread of
those capacitances over many readings of a fixed element is the noise one ΔC reading
carries. That figure is what the tactile inverse's default noise
(:data:`cellbridge.tactile.DEFAULT_NOISE`) is set from (docs/emulator-chip.md).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from cellbridge.emulator.chip.chip import Chip
from cellbridge.tactile.transfer import (
    adc_mean_to_capacitance,
    counts_to_capacitance,
    expected_counts,
    unwrap_counts,
)

__all__ = ["NoiseFigure", "counter_noise", "adc_noise"]


class NoiseFigure(NamedTuple):
    mean: float  #: mean reading (counts, or mean code per conversion)
    rms: float  #: rms spread of one reading, in the same unit
    farads: float  #: rms spread of the capacitance the host computes from one reading


def counter_noise(
    chip: Chip,
    channel: int,
    capacitance: float,
    readings: int = 400,
    gate_cycles: int | None = None,
    first_cycle: int = 0,
) -> NoiseFigure:
    """Noise of ``readings`` counter gates, back to back from ``first_cycle``."""
    gate = chip.config.gate_cycles if gate_cycles is None else gate_cycles
    params = chip.params
    if gate != params.gate_cycles:
        params = type(params)(**{**params.__dict__, "gate_cycles": gate})
    raw, ovf = zip(
        *(chip.count(channel, capacitance, first_cycle + i * gate, gate) for i in range(readings))
    )
    n = unwrap_counts(np.array(raw), expected_counts(capacitance, params), params, np.array(ovf))
    c = counts_to_capacitance(n, params)
    return NoiseFigure(float(n.mean()), float(n.std(ddof=1)), float(c.std(ddof=1)))


def adc_noise(
    chip: Chip,
    channel: int,
    capacitance: float,
    oversampling: int,
    readings: int = 400,
    first_cycle: int = 0,
) -> NoiseFigure:
    """Noise of ``readings`` oversampled ADC reads (mean of ``oversampling`` codes each)."""
    mean_codes = np.empty(readings)
    cycle = first_cycle
    for i in range(readings):
        total, cycles = chip.convert(channel, capacitance, cycle, oversampling)
        mean_codes[i] = total / oversampling
        cycle += cycles
    c = adc_mean_to_capacitance(mean_codes, chip.params)
    return NoiseFigure(float(mean_codes.mean()), float(mean_codes.std(ddof=1)), float(np.nanstd(c, ddof=1)))
