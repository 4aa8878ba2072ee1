"""The 8-bit SAR ADC's charge-time conversions: timing and the sampled input.

A conversion takes ``discharge + sample_delay + bits`` cycles: the channel is shorted
for ``discharge`` cycles, released to charge through R_adc, held at the sampling
instant ``sample_delay`` cycles later, and the SAR then decides one bit per cycle.
Oversampling runs N conversions back to back. The sampling instant and the held
value are defined here once; the per-cycle SAR stepper
(:func:`cellbridge.emulator.chip.reference.step_conversions`) and the vectorised
:func:`sar_codes` both read them.

The held value is :func:`cellbridge.tactile.transfer.adc_input` (the RC charging
curve at the crystal-scaled sampling time, in LSB) plus the conversion's input noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

__all__ = ["AdcTiming", "held_inputs", "sar_codes"]


@dataclass(frozen=True)
class AdcTiming:
    """Cycle budget of one charge-time conversion."""

    discharge: int
    sample_delay: int
    bits: int

    @property
    def conversion_cycles(self) -> int:
        return self.discharge + self.sample_delay + self.bits

    def sample_cycles(self, start_cycle: int, n: int) -> NDArray[np.int64]:
        """Sampling instant of each of ``n`` back-to-back conversions from ``start_cycle``."""
        return (
            start_cycle
            + self.conversion_cycles * np.arange(n, dtype=np.int64)
            + (self.discharge + self.sample_delay)
        )


def held_inputs(clean_lsb: float, noise_lsb: NDArray[np.float64]) -> NDArray[np.float64]:
    """Sample-and-hold values (LSB) of conversions with the given input noise."""
    return clean_lsb + noise_lsb


def sar_codes(held: NDArray[np.float64], bits: int) -> NDArray[np.int64]:
    """What an ideal SAR returns for each held value: the largest code k with k ≤ x.

    Successive approximation keeps bit j when ``x ≥ code | 2^j``; that binary search
    ends at floor(x) clipped to [0, 2^bits − 1], computed here in one step.
    """
    codes = np.floor(held)
    np.minimum(codes, (1 << bits) - 1, out=codes)
    np.maximum(codes, 0.0, out=codes)
    return codes.astype(np.int64)
