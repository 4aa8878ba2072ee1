"""A stand-in for the cycle-exact chip (``cellbridge.emulator.chip``), same interface.

Counts and codes come from the transfer functions in :mod:`cellbridge.tactile.transfer`
with Gaussian noise, deterministic for (seed, channel, start_cycle) as the real chip's
contract requires. The firmware and the mesh are written against this interface only,
so swapping in the real chip changes numbers, not code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

CLOCK_HZ = 50_000_000
_LN2x2 = 2.0 * math.log(2.0)
_M64 = (1 << 64) - 1


@dataclass(frozen=True)
class ChipConfig:
    clock_hz: int = CLOCK_HZ
    crystal_ppm: float = 0.0
    r_ohm: float = 4700.0
    jitter: float = 0.5  #: rms noise of one gate's count, in counts
    gate_cycles: int = 100_000
    adc_r_ohm: float = 100e3
    adc_sample_delay: int = 64
    adc_noise_lsb: float = 0.5
    counter_bits: int = 16
    adc_bits: int = 8
    adc_conversion_cycles: int = 8 + 64 + 8  #: discharge, charge to the sample instant, 8 SAR steps


def _mix(x: int) -> int:
    """splitmix64 finaliser: a cheap, well-spread hash for per-call noise."""
    x = (x + 0x9E3779B97F4A7C15) & _M64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _M64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _M64
    return x ^ (x >> 31)


def _uniforms(seed: int, channel: int, start: int) -> tuple[float, float, float]:
    h = _mix(_mix(seed * 0x100000001B3 + channel) ^ start)
    h2 = _mix(h)
    return ((h >> 11) + 0.5) / 2**53, ((h2 >> 11) + 0.5) / 2**53, ((_mix(h2) >> 11) + 0.5) / 2**53


class Chip:
    """Counter and ADC of one bridge chip (stand-in)."""

    def __init__(self, config: ChipConfig = ChipConfig(), seed: int = 0) -> None:
        self.config = config
        self.seed = seed
        self._clock = config.clock_hz * (1.0 + 1e-6 * config.crystal_ppm)

    def count(self, channel: int, capacitance: float, start_cycle: int, gate_cycles: int) -> tuple[int, bool]:
        c = self.config
        u1, u2, phase = _uniforms(self.seed, channel, start_cycle)
        gauss = math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)
        mean = gate_cycles / self._clock / (_LN2x2 * c.r_ohm * capacitance)
        n = max(0, math.ceil(mean + c.jitter * gauss - phase))
        mod = 1 << c.counter_bits
        return n % mod, n >= mod

    def convert(self, channel: int, capacitance: float, start_cycle: int, oversampling: int) -> tuple[int, int]:
        c = self.config
        levels = 1 << c.adc_bits
        x = levels * -math.expm1(-c.adc_sample_delay / self._clock / (c.adc_r_ohm * capacitance))
        total = 0
        for k in range(oversampling):
            u1, u2, _ = _uniforms(self.seed, channel, start_cycle + k * c.adc_conversion_cycles)
            gauss = math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)
            total += min(levels - 1, max(0, math.floor(x + c.adc_noise_lsb * gauss)))
        return total, oversampling * c.adc_conversion_cycles

    def cycles_at(self, host_seconds: float) -> int:
        return int(host_seconds * self._clock)
