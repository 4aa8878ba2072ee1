"""The chip's reading noise, measured as the host sees it, against the figures the
tactile layer uses: the inverse's default noise and the ADC's resolution formula."""

from __future__ import annotations

import math

import numpy as np
import pytest
from cellbridge.emulator.chip.chip import Chip
from cellbridge.emulator.chip.chip_noise import adc_noise, counter_noise
from cellbridge.tactile import DEFAULT_NOISE, ElementParams
from cellbridge.tactile.transfer import adc_resolution, counts_per_farad, expected_counts

P = ElementParams()
REST = (P.C1_rest, P.C2_rest)


def test_default_noise_is_the_counters_measured_noise():
    """DEFAULT_NOISE covers one counter gate at rest on both channels, and is not
    far above the worse one (it is that figure, rounded up)."""
    chip = Chip(seed=21)
    measured = [counter_noise(chip, ch, c, readings=600).farads for ch, c in enumerate(REST)]
    assert max(measured) <= DEFAULT_NOISE <= 1.6 * max(measured)
    # The worst case over the quantiser's phase (±½ count) plus the gate's jitter.
    jitter = chip.config.jitter
    worst = max(
        math.sqrt(0.25 + jitter**2 * float(expected_counts(c))) / float(counts_per_farad(c))
        for c in REST
    )
    assert worst <= DEFAULT_NOISE < 1.2 * worst


def _count_rms(x: float, jitter_periods: float) -> float:
    """rms of ceil(x + δ − p), p ~ U[0, 1), δ ~ N(0, s²): the gate's last edge moved
    by the accumulated jitter δ, then quantised with variance f(1−f) (f = frac(x + δ))."""
    d = np.linspace(-8, 8, 4001) * jitter_periods
    w = np.exp(-0.5 * (d / jitter_periods) ** 2) if jitter_periods > 0 else np.ones(1)
    d = d if jitter_periods > 0 else np.zeros(1)
    f = np.mod(x + d, 1.0)
    return math.sqrt(jitter_periods**2 + float(np.sum(w * f * (1 - f)) / np.sum(w)))


def test_counter_noise_is_quantisation_and_jitter():
    """Quantisation of the gate's end (at most ½ count rms) plus accumulated jitter."""
    chip = Chip(seed=22)
    for ch, c in enumerate(REST):
        x = float(expected_counts(c, chip.params))
        fig = counter_noise(chip, ch, c, readings=800)
        predicted = _count_rms(x, chip.config.jitter * math.sqrt(x))
        assert fig.rms == pytest.approx(predicted, rel=0.15)
        assert fig.mean == pytest.approx(x, abs=4 * predicted / math.sqrt(800))


@pytest.mark.parametrize("n", [1, 16])
def test_adc_noise_matches_the_transfer_resolution(n):
    chip = Chip(seed=23)
    for ch, c in enumerate(REST):
        fig = adc_noise(chip, ch, c, n, readings=600)
        assert fig.farads == pytest.approx(float(adc_resolution(c, n, chip.params)), rel=0.15)
        # The ADC is the coarse channel: far above the counter's default noise.
        assert fig.farads > 10 * DEFAULT_NOISE
