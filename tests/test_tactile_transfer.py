"""Transfer functions of the bridge chip: the design's rest numbers and round trips.

Expected values come from first principles here: the relaxation oscillator's two
half-periods are RC charges between 1/3 and 2/3 of the supply, the counter counts
edges of a phase-shifted pulse train, and the ADC samples an RC charging curve.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from cellbridge.tactile import (
    ChipParams,
    ElementParams,
    adc_code,
    adc_input,
    adc_mean_code,
    adc_mean_to_capacitance,
    adc_resolution,
    code_to_capacitance,
    codes_per_farad,
    counts,
    counts_per_farad,
    counts_to_capacitance,
    expected_counts,
    oscillator_period,
    unwrap_counts,
)
from hypothesis import given, settings
from hypothesis import strategies as st

P = ElementParams()
C_REST = np.array([P.C1_rest, P.C2_rest])
CHIP = ChipParams()


def approx(expected, rel=1e-12, abs=0.0):
    return pytest.approx(expected, rel=rel, abs=abs)


def period_first_principles(R: float, C: float) -> float:
    # Charge from 1/3 to 2/3 of V towards V, then discharge from 2/3 to 1/3 towards 0:
    # each takes RC·ln((1 − 1/3)/(1 − 2/3)) = RC·ln 2.
    half = R * C * math.log((1 - 1 / 3) / (1 - 2 / 3))
    return 2 * half


def test_chip_defaults():
    assert CHIP.clock_hz == 50e6 and CHIP.gate_cycles == 100_000
    assert CHIP.R_osc == 4.7e3 and CHIP.R_adc == 100e3
    assert CHIP.adc_sample_cycles == 64 and CHIP.adc_bits == 8 and CHIP.counter_bits == 16
    assert CHIP.gate_time == approx(2e-3)
    assert CHIP.adc_sample_time == approx(1.28e-6)


def test_oscillator_rest_numbers():
    T = oscillator_period(C_REST)
    for t, c in zip(T, C_REST):
        assert t == approx(period_first_principles(4.7e3, c))
    n = expected_counts(C_REST)
    # DESIGN: "about 19 600 counts on C1 and 15 800 on C2; 1 pF ≈ 1 200 counts".
    assert n[0] == pytest.approx(19600, rel=0.005)
    assert n[1] == pytest.approx(15800, rel=0.005)
    assert n[0] == approx(2e-3 / period_first_principles(4.7e3, P.C1_rest))
    per_pf = counts_per_farad(C_REST) * 1e-12
    assert per_pf[0] == pytest.approx(1200, rel=0.06)
    # The slope is the derivative of the count: check by a 1 fF finite difference.
    fd = expected_counts(C_REST) - expected_counts(C_REST + 1e-15)
    assert fd * 1e3 == pytest.approx(per_pf, rel=1e-3)


def edge_count_reference(C: float, phase: float, chip: ChipParams) -> int:
    """Count pulses of a train with first edge at phase·T by walking the edges."""
    T = period_first_principles(chip.R_osc, C)
    t_gate = chip.gate_cycles / (chip.clock_hz * (1 + 1e-6 * chip.clock_ppm))
    k = 0
    t = phase * T
    while t < t_gate:
        k += 1
        t = (phase + k) * T
    return k


@settings(max_examples=60, deadline=None)
@given(
    c=st.floats(min_value=8e-12, max_value=60e-12),
    phase=st.floats(min_value=0.0, max_value=0.999999),
    ppm=st.floats(min_value=-100, max_value=100),
)
def test_integer_counts_walk_the_edges(c, phase, ppm):
    chip = CHIP.with_ppm(ppm)
    raw, ov = counts(c, chip, phase)
    assert int(raw) == edge_count_reference(c, phase, chip)
    assert not ov


def test_mean_count_over_phase_is_the_expected_count():
    phases = (np.arange(4000) + 0.5) / 4000
    for c in C_REST:
        raw, _ = counts(c, CHIP, phases)
        assert raw.mean() == pytest.approx(float(expected_counts(c)), abs=1e-3)


def test_crystal_offset_scales_counts():
    fast = CHIP.with_ppm(50.0)
    ratio_ = expected_counts(C_REST, fast) / expected_counts(C_REST, CHIP)
    assert ratio_ == approx(1 / (1 + 50e-6))
    assert fast.clock_actual_hz == approx(50e6 * (1 + 50e-6))


def test_counts_round_trip():
    c = np.linspace(6.2e-12, 80e-12, 500)  # from the synchroniser's limit (≈6.14 pF)
    assert counts_to_capacitance(expected_counts(c)) == approx(c, rel=1e-13)
    # One integer count is worth ≈ 1/1250 pF at rest on C1.
    raw, _ = counts(P.C1_rest)
    assert float(counts_to_capacitance(raw)) == pytest.approx(P.C1_rest, abs=1e-15, rel=0)
    assert np.isnan(counts_to_capacitance(0))  # no edges: no reading, not C = ∞


def test_counter_wraps_and_unwraps():
    chip = ChipParams(gate_cycles=400_000)  # 8 ms: ≈78 000 counts at rest on C1
    n = expected_counts(C_REST, chip)
    assert n[0] > 65536 > n[1]
    raw, ov = counts(C_REST, chip, 0.25)
    true = np.ceil(n - 0.25).astype(np.int64)
    assert list(raw) == list(true % 65536)
    assert list(ov) == [True, False]
    # Unwrap with the rest counts as nominal, with and without the overflow flag.
    pressed = C_REST + np.array([3e-12, 5e-12])
    raw_p, ov_p = counts(pressed, chip, 0.5)
    true_p = np.ceil(expected_counts(pressed, chip) - 0.5).astype(np.int64)
    assert list(unwrap_counts(raw_p, n, chip)) == list(true_p)
    assert list(unwrap_counts(raw_p, n, chip, ov_p)) == list(true_p)
    assert counts_to_capacitance(unwrap_counts(raw_p, n, chip), chip) == pytest.approx(
        pressed, abs=1e-15, rel=0)
    # Overflow flag clear means no wrap, whatever the nominal says.
    assert int(unwrap_counts(100, 70000.0, chip, overflow=False)) == 100
    assert int(unwrap_counts(100, 70000.0, chip, overflow=True)) == 65636
    with pytest.raises(ValueError):
        unwrap_counts(70000, 1.0, chip)


def adc_fraction_first_principles(C: float, chip: ChipParams) -> float:
    t = chip.adc_sample_cycles / chip.clock_actual_hz
    return 1 - math.exp(-t / (chip.R_adc * C))


def test_adc_rest_numbers():
    codes = adc_code(C_REST)
    # DESIGN: "At rest ≈ code 142 (C1) and 123 (C2); 1 pF ≈ 5 codes".
    assert list(codes) == [142, 123]
    for c, x in zip(C_REST, adc_input(C_REST)):
        assert x == approx(256 * adc_fraction_first_principles(c, CHIP))
    per_pf = codes_per_farad(C_REST) * 1e-12
    assert np.all((per_pf > 4) & (per_pf < 6.5))
    fd = adc_input(C_REST - 0.5e-15) - adc_input(C_REST + 0.5e-15)
    assert fd * 1e3 == pytest.approx(per_pf, rel=1e-4)


def test_adc_code_steps_invert():
    c = np.linspace(3e-12, 60e-12, 20000)
    codes = adc_code(c)
    assert np.all(np.diff(codes) <= 0)  # more capacitance charges more slowly
    back = code_to_capacitance(codes)
    # The step of code k spans inputs [k, k+1): its middle maps back inside it.
    assert np.all(adc_code(back) == codes)
    step = codes < 255
    assert np.all(code_to_capacitance(codes[step] + 1) < back[step])  # higher code: less C
    with pytest.raises(ValueError):
        code_to_capacitance(256)


def test_adc_rails():
    assert int(adc_code(1e-15)) == 255
    assert int(adc_code(1e-6)) == 0


def test_oversampled_mean_matches_monte_carlo_and_inverts():
    rng = np.random.default_rng(3)
    n = 200_000
    for c in (P.C1_rest, P.C2_rest, P.C1_rest + 2.3e-12):
        noise = rng.normal(0.0, 0.5, n)
        mc = adc_code(np.full(n, c), noise=noise)
        expected = float(adc_mean_code(c))
        sd = mc.std()
        assert mc.mean() == pytest.approx(expected, abs=4 * sd / math.sqrt(n))
        # ≈ input − ½ for 0.5 LSB noise: the dither linearises the quantiser.
        assert expected == pytest.approx(float(adc_input(c)) - 0.5, abs=0.005)
        # Spread of one dithered code: ≈ √(σ² + 1/12) LSB.
        assert sd == pytest.approx(math.sqrt(0.25 + 1 / 12), rel=0.02)
        # The exact mean inverts to the capacitance.
        assert float(adc_mean_to_capacitance(expected)) == pytest.approx(c, rel=1e-7, abs=0)
        # The Monte Carlo mean inverts to within the predicted resolution.
        res = float(adc_resolution(c, n))
        got = float(adc_mean_to_capacitance(mc.mean()))
        assert abs(got - c) < 4 * res


def test_resolution_scales_with_oversampling():
    r1 = adc_resolution(P.C1_rest, 1)
    r64 = adc_resolution(P.C1_rest, 64)
    assert r1 / r64 == approx(8.0, rel=1e-9)
    lsb = 1 / float(codes_per_farad(P.C1_rest))
    assert float(r1) == pytest.approx(math.sqrt(0.25 + 1 / 12) * lsb, rel=0.01)
    # Without noise averaging buys nothing.
    assert float(adc_resolution(P.C1_rest, 64, noise_lsb=0.0)) == approx(lsb / math.sqrt(12))
    with pytest.raises(ValueError):
        adc_mean_to_capacitance(100.0, noise_lsb=0.0)


def test_erfc_approximation():
    from cellbridge.tactile.transfer import _erfc

    z = np.linspace(-7, 7, 2001)
    ref = np.array([math.erfc(x) for x in z])
    assert np.max(np.abs(_erfc(z) / ref - 1)) < 2e-7


def test_chip_params_validation():
    with pytest.raises(ValueError):
        ChipParams(gate_cycles=0)
    with pytest.raises(ValueError):
        ChipParams(R_osc=-1.0)
    with pytest.raises(ValueError):
        ChipParams(gate_cycles=1.5)  # type: ignore[arg-type]  # the point: a wrong type is refused
    with pytest.raises(ValueError):
        expected_counts(-1e-12)


def test_counter_delta_is_within_one_count_of_the_truth() -> None:
    from cellbridge.tactile import ElementParams, counter_delta, counts_per_farad

    rest = ElementParams().C1_rest
    dC = np.linspace(0.0, 8e-12, 200)
    phase = np.linspace(0.0, 0.999, 200)
    got = counter_delta(dC, rest, phase)
    lsb = 1.0 / counts_per_farad(rest + dC)  # one count, in farads
    assert np.all(np.abs(got - dC) <= 1.01 * lsb)
    assert np.any(got != dC)  # it does quantise


# ------------------------------------------------------- issue 9: points 12-15


def test_long_gates_are_refused_not_unwrapped_wrongly():
    from cellbridge.tactile.transfer import check_gate, max_gate_cycles

    # The old rule (count nearest the rest count, overflow flag) at 510 000 cycles:
    # +7.65 pF on C1 comes back as a plausible negative ΔC. The gate is refused now.
    chip = ChipParams(gate_cycles=510_000)
    raw, ov = counts(P.C1_rest + 7.65e-12, chip, 0.3)
    wrong = counts_to_capacitance(unwrap_counts(raw, expected_counts(P.C1_rest, chip), chip, ov), chip)
    assert float(wrong) - P.C1_rest == pytest.approx(-3.87e-12, abs=0.05e-12)
    for gate in (510_000, 1_000_000, 300_000):
        with pytest.raises(ValueError, match="half the counter"):
            check_gate(ChipParams(gate_cycles=gate))
    limit = max_gate_cycles()
    assert 150_000 < limit < 300_000
    check_gate(ChipParams(gate_cycles=limit))
    with pytest.raises(ValueError):
        check_gate(ChipParams(gate_cycles=limit + 1))
    check_gate(CHIP)  # the default 2 ms gate is fine


def test_unwrapper_follows_each_channel_from_its_previous_sample():
    from cellbridge.tactile.transfer import CounterUnwrapper

    # 12-bit counter, 1 ms gate: the rest counts (≈9 800 / 7 900) are two moduli
    # and more. The parasitics drift 3 pF below the nominal rest (counts +2 300,
    # more than half a modulus) and then a +3 pF press comes and goes: only the
    # previous sample knows which wrap the count is on.
    chip = ChipParams(counter_bits=12, gate_cycles=50_000)
    un = CounterUnwrapper(C_REST * 0.98, C_REST + 3e-12, chip, start=C_REST)
    rng = np.random.default_rng(5)
    base = C_REST - np.linspace(0, 3e-12, 300)[:, None] * np.array([1.0, 0.8])
    press = np.concatenate([np.linspace(0, 3e-12, 20), np.linspace(3e-12, 0, 20)])[:, None]
    path = np.concatenate([base, base[-1] + press * np.array([1.0, 0.6])])
    for c in path:
        ph = rng.uniform(0, 1, 2)
        raw, ov = counts(c, chip, ph)
        n, amb = un.unwrap(raw, ov)
        assert list(n) == list(np.ceil(expected_counts(c, chip) - ph).astype(np.int64))
        assert not amb.any()
    assert list(un.ambiguous) == [0, 0]
    # The stateless rule (nearest to the rest count) is a modulus off by now.
    raw, ov = counts(base[-1], chip, 0.5)
    bad = unwrap_counts(raw, expected_counts(C_REST, chip), chip, ov)
    assert abs(int(bad[0]) - float(expected_counts(base[-1], chip)[0])) > 4000


def test_unwrapper_flags_implausible_and_contradictory_samples():
    from cellbridge.tactile.transfer import CounterUnwrapper

    un = CounterUnwrapper(C_REST * 0.9, C_REST + 20e-12, CHIP, start=C_REST)
    raw, ov = counts(C_REST, CHIP, 0.5)
    n, amb = un.unwrap(raw, ov)
    assert not amb.any()
    # A count no plausible capacitance gives (a glitch), and a wrong overflow flag.
    n2, amb2 = un.unwrap(np.array([100, int(raw[1])]), np.array([False, True]))
    assert list(amb2) == [True, True]
    assert list(un.ambiguous) == [1, 1]
    # The reference is not dragged by a flagged sample: the next good one is exact.
    n3, amb3 = un.unwrap(raw, ov)
    assert not amb3.any() and list(n3) == list(n)
    with pytest.raises(ValueError, match="half the counter"):
        CounterUnwrapper(C_REST * 0.9, C_REST + 20e-12, ChipParams(gate_cycles=510_000))
    with pytest.raises(ValueError):
        un.unwrap(np.array([1, 2, 3]))


def test_adc_rails_are_never_a_capacitance():
    # An open channel (C → 0) sits on the top code, a shorted one (C → ∞) on code 0;
    # 64 dithered conversions must never invert to 0 F, inf or a number.
    rng = np.random.default_rng(9)
    for c in (1e-15, 1e-14, 1e-4, 1e-3):
        means = adc_code(np.full((2000, 64), c), noise=rng.normal(0, 0.5, (2000, 64))).mean(axis=1)
        got = adc_mean_to_capacitance(means)
        assert np.isnan(got).all(), c
    for m in (0.0, 0.01, 0.3, 254.9, 255.0, -1.0, 256.0):
        assert np.isnan(adc_mean_to_capacitance(m)), m
    # Inside the band every mean inverts to a finite, positive capacitance.
    from cellbridge.tactile.transfer import adc_mean_band

    lo, hi = adc_mean_band()
    assert 0.3 < lo < 1.0 and 254.0 < hi < 255.0
    inside = adc_mean_to_capacitance(np.linspace(lo, hi, 200))
    assert np.all(np.isfinite(inside) & (inside > 0))


@pytest.mark.parametrize("sigma", [0.15, 0.25, 0.5, 2.0])
def test_mean_code_inversion_is_bracketed_and_checked(sigma):
    c = np.linspace(5e-12, 80e-12, 4001)
    m = adc_mean_code(c, noise_lsb=sigma)
    back = adc_mean_to_capacitance(m, noise_lsb=sigma)
    ok = np.isfinite(back)
    assert ok.mean() > 0.99
    np.testing.assert_allclose(back[ok], c[ok], rtol=1e-6)


def test_mean_code_inversion_gives_nan_where_the_mean_is_flat():
    # With 0.02 LSB of noise the mean is flat to rounding between codes: no
    # capacitance can be read from it, and none is invented.
    c = np.linspace(15e-12, 16e-12, 2001)
    m = adc_mean_code(c, noise_lsb=0.02)
    back = adc_mean_to_capacitance(m, noise_lsb=0.02)
    ok = np.isfinite(back)
    assert ok.any() and not ok.all()
    np.testing.assert_allclose(back[ok], c[ok], rtol=1e-4)


def test_garbage_in_is_rejected_or_flagged():
    # Non-finite input never reaches an integer cast.
    with pytest.raises(ValueError):
        adc_code(P.C1_rest, noise=np.nan)
    with pytest.raises(ValueError):
        adc_code(P.C1_rest, noise=np.inf)
    with pytest.raises(ValueError):
        counts(np.nan)
    with pytest.raises(ValueError):
        code_to_capacitance(np.nan)
    with pytest.raises(ValueError):
        code_to_capacitance(3.5)
    # Out of the chip's range: too small for the synchroniser, or pF passed as F.
    with pytest.raises(ValueError, match="synchroniser"):
        counts(1e-30)
    with pytest.raises(ValueError, match="synchroniser"):
        counts(5e-12)
    for bad in (15.67, 0.5):
        with pytest.raises(ValueError, match="farads"):
            counts(bad)
        with pytest.raises(ValueError, match="farads"):
            adc_code(bad)
        with pytest.raises(ValueError, match="farads"):
            expected_counts(bad)
    # Host side: a count is NaN-in NaN-out, and counts no oscillator in range can
    # produce (zero, negative, faster than the synchroniser) are NaN, not a value.
    assert np.isnan(counts_to_capacitance(np.nan))
    assert np.isnan(counts_to_capacitance(0))
    assert np.isnan(counts_to_capacitance(-5))
    assert np.isnan(counts_to_capacitance(CHIP.gate_cycles))  # T = 1 cycle
    assert np.isfinite(counts_to_capacitance(19_593))


@settings(max_examples=40, deadline=None)
@given(
    st.lists(st.tuples(st.floats(0.0, 1.0), st.floats(0.0, 1.0), st.floats(0.0, 0.999)),
             min_size=1, max_size=30),
    st.floats(-100.0, 100.0),
)
def test_unwrapper_is_exact_for_any_plausible_sequence_at_the_longest_gate(path, ppm):
    # Any jump between plausible readings, from one sample to the next, at the
    # longest gate check_gate allows: the count is exact and never flagged.
    from cellbridge.tactile.transfer import CounterUnwrapper, max_gate_cycles, plausible_capacitance

    lo, hi = plausible_capacitance()
    chip = ChipParams(gate_cycles=max_gate_cycles(chip=CHIP.with_ppm(ppm)), clock_ppm=ppm)
    un = CounterUnwrapper(lo, hi, chip, start=C_REST)
    for u1, u2, ph in path:
        c = lo + np.array([u1, u2]) * (hi - lo)
        raw, ov = counts(c, chip, ph)
        n, amb = un.unwrap(raw, ov)
        assert list(n) == list(np.ceil(expected_counts(c, chip) - ph).astype(np.int64))
        assert not amb.any()


@settings(max_examples=60, deadline=None)
@given(st.floats(6e-12, 200e-12), st.floats(0.05, 3.0))
def test_mean_code_inversion_is_right_or_nan(c, sigma):
    back = float(adc_mean_to_capacitance(adc_mean_code(c, noise_lsb=sigma), noise_lsb=sigma))
    assert math.isnan(back) or back == pytest.approx(c, rel=1e-5)
    if sigma >= 0.15:
        assert not math.isnan(back)


def test_a_tiny_mean_count_is_no_reading_not_an_infinite_capacitance():
    # A denormal or sub-count mean (a channel that almost never fired in the window)
    # used to come back as inf F or tenths of a farad; anything above C_MAX is no
    # capacitance any element has, so it is "no reading" like a zero count.
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = counts_to_capacitance(np.array([5e-324, 1e-300, 1e-6, 0.5, 19_593.0]))
    assert np.isnan(out[:3]).all()
    assert np.isfinite(out[3:]).all() and out[3] <= 1e-3


def test_unwrapper_takes_nan_for_channels_without_a_sample():
    # The daemon's readings are NaN where a channel gave none, like every other
    # per-element array; a float array with NaN in unsampled channels used to be
    # refused whole ("raw counts must be integers"), losing the sampled channels.
    from cellbridge.tactile.transfer import CounterUnwrapper

    un = CounterUnwrapper.for_elements(2)
    ref = CounterUnwrapper.for_elements(2)
    raw, ov = counts(np.broadcast_to(C_REST, (2, 2)), CHIP, 0.5)
    fl = raw.astype(np.float64)
    fl[1, 0] = np.nan
    sampled = np.isfinite(fl)
    n, amb = un.unwrap(fl, ov, sampled)
    n_ref, amb_ref = ref.unwrap(np.where(sampled, raw, 0), ov, sampled)
    np.testing.assert_array_equal(n, n_ref)
    np.testing.assert_array_equal(amb, amb_ref)
    assert n[1, 0] == 0 and n[0, 0] == raw[0, 0] and not amb.any()
    np.testing.assert_array_equal(un.previous, ref.previous)
    for bad in (np.nan, 19_588.5, -1.0):  # a sampled channel still needs an integer count
        fl2 = raw.astype(np.float64)
        fl2[0, 1] = bad
        with pytest.raises(ValueError, match="integers"):
            un.unwrap(fl2, ov, np.ones((2, 2), dtype=bool))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.tuples(st.floats(0.05, 1.0), st.floats(0.0, 1.0), st.floats(0.0, 0.999)),
                min_size=2, max_size=12))
def test_unwrapper_follows_set_gate_mid_stream(changes):
    # SET_GATE mid-stream on a 12-bit counter (wraps at every realistic gate): the
    # unwrapper rescales each channel's reference to the new gate and stays exact,
    # also for a channel whose parasitics drifted 3 pF below the nominal rest — which
    # a fresh unwrapper anchored at rest gets a modulus wrong. Counters survive.
    from cellbridge.tactile.transfer import CounterUnwrapper, max_gate_cycles

    base = ChipParams(counter_bits=12, gate_cycles=20_000)
    lo, hi = C_REST * 0.98, C_REST + 3e-12
    longest = max_gate_cycles(lo, hi, base)
    un = CounterUnwrapper(lo, hi, base, start=C_REST)
    drifted = C_REST - np.array([3e-12, 2.4e-12])
    chip = base
    for k, (g, u, ph) in enumerate(changes):
        steps = np.linspace(C_REST, drifted, 40) if k == 0 else [drifted + u * 1e-12] * 3
        for c in steps:
            raw, ov = counts(c, chip, ph)
            n, amb = un.unwrap(raw, ov)
            assert list(n) == list(np.ceil(expected_counts(c, chip) - ph).astype(np.int64))
            assert not amb.any()
        gate = max(int(g * longest), 200)
        un.set_gate(gate)
        chip = ChipParams(counter_bits=12, gate_cycles=gate)
        assert un.chip == chip
    with pytest.raises(ValueError, match="half the counter"):
        un.set_gate(longest + 1)
    assert un.chip == chip  # a refused gate changes nothing
    assert list(un.ambiguous) == [0, 0]


def test_integer_chip_parameters_refuse_booleans():
    # ChipParams(gate_cycles=True) was a 1-cycle gate, counter_bits=True a 1-bit
    # counter, CounterUnwrapper(resync=True) one sample: a bool is not a count.
    from cellbridge.tactile.transfer import CounterUnwrapper

    for name in ("gate_cycles", "adc_sample_cycles", "adc_bits", "counter_bits"):
        with pytest.raises(ValueError, match=name):
            ChipParams(**{name: True})
    with pytest.raises(ValueError, match="resync"):
        CounterUnwrapper(C_REST * 0.9, C_REST + 20e-12, CHIP, resync=True)
    assert ChipParams(gate_cycles=np.int64(50_000)).gate_cycles == 50_000  # type: ignore[arg-type]  # a numpy integer, on purpose


def test_unwrapper_refuses_a_sampled_mask_it_would_read_across_channels():
    # For a 2-element skin (2, 2), sampled=[True, False] meant "element 0 only" to
    # its caller but was broadcast over the channel axis ("C1 of every element"),
    # silently unwrapping element 1's stale register. Only raw's shape or one flag
    # per element (N, 1) are accepted.
    from cellbridge.tactile.transfer import CounterUnwrapper

    un = CounterUnwrapper.for_elements(2)
    raw, ov = counts(np.broadcast_to(C_REST, (2, 2)), CHIP, 0.5)
    with pytest.raises(ValueError, match="sampled"):
        un.unwrap(raw, ov, np.array([True, False]))
    n, amb = un.unwrap(raw, ov, np.array([[True], [False]]))
    assert list(n[:, 0]) == [raw[0, 0], 0] and list(n[1]) == [0, 0] and not amb.any()
    n, amb = un.unwrap(raw, ov, True)
    np.testing.assert_array_equal(n, raw)


def test_counter_delta_refuses_a_gate_check_gate_refuses():
    """Issue 17, point 20: at a 510 000-cycle gate the simulation helper returned
    −3.87 pF for a +7.65 pF press, silently; the host path refuses such a gate."""
    from cellbridge.tactile import ElementParams, counter_delta
    from cellbridge.tactile.transfer import ChipParams, check_gate, max_gate_cycles

    long_gate = ChipParams(gate_cycles=510_000)
    with pytest.raises(ValueError):
        check_gate(long_gate)
    with pytest.raises(ValueError, match="longest unambiguous gate"):
        counter_delta(7.65e-12, ElementParams().C1_rest, 0.0, long_gate)
    ok = ChipParams(gate_cycles=max_gate_cycles())
    assert counter_delta(7.65e-12, ElementParams().C1_rest, 0.0, ok) == pytest.approx(7.65e-12, rel=1e-3)
