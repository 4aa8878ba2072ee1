"""The daemon's front end (counts → capacitance): every number the transfer functions'.

:class:`~cellbridge.daemon.core.frontend.Frontend` converts counter readings with the
arithmetic of :func:`unwrap_counts` and :func:`counts_to_capacitance` in one pass; these
tests hold it to theirs, bit for bit, on readings of every kind a bridge sends (a press,
rest, a counter that wrapped, a dead oscillator, a corrupt value, another gate, ADC rows
among counter rows), and to their refusals."""

from __future__ import annotations

import numpy as np
import pytest
from cellbridge.daemon.core.frontend import Frontend
from cellbridge.daemon.core.wire import ADC_MODE, OVERFLOW_C1, OVERFLOW_C2
from cellbridge.tactile import (
    ChipParams,
    ElementParams,
    counts,
    counts_to_capacitance,
    expected_counts,
    unwrap_counts,
)

CHIP = ChipParams()
PARAMS = ElementParams()


def reference(raw: np.ndarray, flags: np.ndarray, gate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The conversion as the transfer functions give it, call by call."""
    ratio = (CHIP.gate_cycles / gate)[:, None]
    bad = raw >= CHIP.counter_modulus
    raw = np.where(bad, 0, raw)
    ov = (flags[:, None] & np.array([OVERFLOW_C1, OVERFLOW_C2])) != 0
    nominal = expected_counts(np.array([PARAMS.C1_rest, PARAMS.C2_rest]), CHIP)
    n = unwrap_counts(raw, nominal / ratio, CHIP, ov)
    caps = counts_to_capacitance(n * ratio, CHIP)
    caps[bad] = np.nan
    return caps, (n <= 0) | bad


def readings(rng: np.random.Generator, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``k`` bridges' counter readings: capacitances from rest to a hard press (some
    wrapping the 16-bit counter, flagged), at the reference gate or another, with dead
    channels and corrupt values among them."""
    rest = np.array([PARAMS.C1_rest, PARAMS.C2_rest])
    caps = rest * rng.uniform(0.4, 3.0, (k, 2))
    gate = np.where(rng.random(k) < 0.3, rng.choice([25_000.0, 50_000.0, 200_000.0], k), float(CHIP.gate_cycles))
    chip_at = [ChipParams(gate_cycles=int(g)) for g in gate]
    raw = np.empty((k, 2), dtype=np.int64)
    flags = np.zeros(k, dtype=np.int64)
    for i in range(k):
        r, ov = counts(caps[i], chip_at[i], rng.random(2))
        raw[i] = r
        flags[i] = (OVERFLOW_C1 if ov[0] else 0) | (OVERFLOW_C2 if ov[1] else 0)
    raw[rng.random((k, 2)) < 0.05] = 0  # a dead oscillator
    raw[rng.random((k, 2)) < 0.03] = CHIP.counter_modulus + 7  # a value no 16-bit counter holds
    return raw, flags, gate


def test_counter_readings_are_the_transfer_functions_bit_for_bit() -> None:
    fe = Frontend(PARAMS, CHIP)
    rng = np.random.default_rng(3)
    wrapped = 0
    for k in (1, 7, 128, 1144):
        raw, flags, gate = readings(rng, k)
        wrapped += int(np.count_nonzero(flags))
        mode = np.zeros(k, dtype=np.int64)
        over = np.ones(k, dtype=np.int64)
        caps, sat = fe.capacitance(mode, over, raw, flags, gate)
        want_caps, want_sat = reference(raw, flags, gate)
        assert caps.tobytes() == want_caps.tobytes()  # NaN where they are NaN, every other bit equal
        assert np.array_equal(sat, want_sat)
    assert wrapped > 0  # (the readings did wrap the counter: the overflow flags were exercised)


def test_adc_rows_among_counter_rows_keep_their_own_conversion() -> None:
    fe = Frontend(PARAMS, CHIP)
    rng = np.random.default_rng(5)
    raw, flags, gate = readings(rng, 64)
    mode = np.zeros(64, dtype=np.int64)
    adc = rng.random(64) < 0.25
    mode[adc] = ADC_MODE
    over = np.full(64, 4, dtype=np.int64)
    raw[adc] = rng.integers(1, 4 * (CHIP.adc_levels - 1), (int(adc.sum()), 2))
    caps, sat = fe.capacitance(mode, over, raw, flags, gate)
    want_caps, want_sat = reference(raw[~adc], flags[~adc], gate[~adc])
    assert caps[~adc].tobytes() == want_caps.tobytes()
    assert np.array_equal(sat[~adc], want_sat)
    assert np.isfinite(caps[adc]).all() and not sat[adc].any()


def test_what_the_transfer_functions_refuse_is_refused() -> None:
    fe = Frontend(PARAMS, CHIP)
    mode, over, flags = np.zeros(2, dtype=np.int64), np.ones(2, dtype=np.int64), np.zeros(2, dtype=np.int64)
    gate = np.full(2, float(CHIP.gate_cycles))
    with pytest.raises(ValueError, match="raw counts"):
        fe.capacitance(mode, over, np.array([[5000, -1], [5000, 5000]]), flags, gate)
    with pytest.raises(ValueError, match="finite"):
        fe.capacitance(mode, over, np.array([[5000, 5000], [5000, 5000]]), flags, np.array([np.nan, 1e5]))
    with pytest.raises(ValueError, match="finite"):
        fe.capacitance(mode, over, np.array([[5000, 5000], [5000, 5000]]), flags, np.array([np.inf, 1e5]))


@pytest.mark.parametrize("gate", [0.0, -0.0, -5.0, 1e-320, 1.0, 3.7, float(2**32), float(2**40)])
def test_hostile_gates_and_counter_values_convert_as_the_transfer_functions_do(gate: float) -> None:
    """A gate no chip sets (zero, negative, subnormal, far longer than the counter could
    count) and counter values at and beyond the modulus, with and without the overflow
    flags: every value and saturation flag the transfer functions', bit for bit (NaN where
    they give no reading), and no error where they raise none."""
    m = CHIP.counter_modulus
    raw = np.array([[0, 1], [m - 1, m], [m + 1, 19_588], [15_788, 40_000], [65_535, 0]], dtype=np.int64)
    for flags in (np.zeros(5, dtype=np.int64), np.array([0, OVERFLOW_C1, OVERFLOW_C2, OVERFLOW_C1 | OVERFLOW_C2, 3])):
        gates = np.array([gate, 1e5, gate, gate, 25_000.0])
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            caps, sat = Frontend(PARAMS, CHIP).capacitance(np.zeros(5, dtype=np.int64), np.ones(5, dtype=np.int64),
                                                           raw, flags, gates)
            want_caps, want_sat = reference(raw, flags, gates)
        assert caps.tobytes() == want_caps.tobytes() and np.array_equal(sat, want_sat)
