"""The emulated chip against the tactile transfer functions, its clock, its
determinism and its input checks.

Statistical checks use bounds derived from the model: one gate's count is the
transfer function's count for the gate's phase, moved by the accumulated jitter
(rms jitter·√K periods over K periods); oversampled ADC means scatter by the
dithered quantiser's spread over √N.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from cellbridge.emulator.chip.chip import CLOCK_HZ, Chip, ChipConfig
from cellbridge.tactile import ElementParams, forward
from cellbridge.tactile.transfer import adc_mean_code, counts, expected_counts, unwrap_counts

P = ElementParams()
# At rest, and under the paper's presses (stimulators D = 10…40 mm, forces 1…8 N).
PRESSES = [(f, d) for f in (1.0, 3.0, 8.0) for d in (10e-3, 16e-3, 20e-3, 26e-3, 30e-3, 40e-3)]


def _pressed(force: float, diameter: float) -> tuple[float, float]:
    dc1, dc2 = forward(force, math.pi * diameter**2 / 4)
    return P.C1_rest + float(dc1), P.C2_rest + float(dc2)


CASES = [("rest", (P.C1_rest, P.C2_rest))] + [
    (f"{f:g} N, D {d * 1e3:g} mm", _pressed(f, d)) for f, d in PRESSES
]


@pytest.mark.parametrize("label, caps", CASES, ids=[c[0] for c in CASES])
def test_counts_follow_the_transfer_function_within_the_jitter(label, caps):
    chip = Chip(ChipConfig(crystal_ppm=20.0), seed=11)
    params = chip.params
    gate = chip.config.gate_cycles
    for channel, c in enumerate(caps):
        x = float(expected_counts(c, params))
        jitter_rms = chip.config.jitter * math.sqrt(x)  # accumulated over the gate, in periods
        n_gates = 60
        got = []
        for i in range(n_gates):
            start = 7 + i * gate
            raw, overflow = chip.count(channel, c, start, gate)
            assert not overflow
            # The transfer function's count for this gate's phase, moved by jitter only.
            phase = chip.edge_train(channel, c, start, gate).phase
            ideal = int(counts(c, params, phase)[0])
            assert abs(raw - ideal) <= math.ceil(6 * jitter_rms), (label, channel, i)
            got.append(raw)
        # The mean over random phases is t_gate/T (the inverse's formula).
        spread = math.sqrt(0.25 + jitter_rms**2)
        assert abs(np.mean(got) - x) < 4.5 * spread / math.sqrt(n_gates) + 1e-9, (label, channel)


@pytest.mark.parametrize("label, caps", CASES[::3], ids=[c[0] for c in CASES[::3]])
def test_adc_codes_follow_the_transfer_function_within_the_noise(label, caps):
    chip = Chip(ChipConfig(crystal_ppm=-35.0), seed=12)
    params = chip.params
    n, reads = 16, 60
    for channel, c in enumerate(caps):
        means = []
        cycle = 5
        for _ in range(reads):
            total, cycles = chip.convert(channel, c, cycle, n)
            means.append(total / n)
            cycle += cycles
        expect = float(adc_mean_code(c, params))
        per_conversion = math.sqrt(chip.config.adc_noise_lsb**2 + 1 / 12)
        assert abs(np.mean(means) - expect) < 4.5 * per_conversion / math.sqrt(n * reads), (label, channel)
        # The spread of one oversampled mean is the dithered quantiser's over √N.
        assert np.std(means, ddof=1) == pytest.approx(per_conversion / math.sqrt(n), rel=0.35)


def test_rest_numbers_of_the_design():
    chip = Chip(seed=2)
    gate = chip.config.gate_cycles
    c1 = [chip.count(0, P.C1_rest, i * gate, gate)[0] for i in range(20)]
    c2 = [chip.count(1, P.C2_rest, i * gate, gate)[0] for i in range(20)]
    assert abs(np.mean(c1) - 19_600) < 50 and abs(np.mean(c2) - 15_800) < 50
    one = [chip.convert(0, P.C1_rest, i * 1000, 1)[0] for i in range(1000)]
    two = [chip.convert(1, P.C2_rest, i * 1000, 1)[0] for i in range(1000)]
    # The noise-free code is floor(input); dithered codes average to input − ½.
    assert math.floor(np.mean(one) + 0.5) == 142 and math.floor(np.mean(two) + 0.5) == 123
    # 0.5 LSB input noise: single codes straddle neighbours, never jump far.
    assert set(one) <= set(range(140, 146)) and len(set(one)) >= 2


def test_counter_wraps_and_flags_overflow():
    chip = Chip(seed=4)
    c, gate = 7e-12, 160_000  # T ≈ 2.28 cycles: ≈ 70 000 edges in the gate
    params = chip.params
    x = float(expected_counts(c, params)) * gate / params.gate_cycles
    assert x > 65_536
    for i in range(5):
        raw, overflow = chip.count(0, c, i * gate, gate)
        assert overflow and 0 <= raw < 65_536
        assert abs(raw + 65_536 - x) < 3
    # The short gate of the same capacitance does not overflow.
    raw, overflow = chip.count(0, c, 0, params.gate_cycles)
    assert not overflow
    assert int(unwrap_counts(np.array(raw), x / 1.6, params, overflow)) == raw


def test_crystal_offset_scales_counts_and_clock():
    gate = 100_000
    fast = Chip(ChipConfig(crystal_ppm=50.0), seed=3)
    slow = Chip(ChipConfig(crystal_ppm=-50.0), seed=3)
    n_fast = np.mean([fast.count(0, P.C1_rest, i * gate, gate)[0] for i in range(300)])
    n_slow = np.mean([slow.count(0, P.C1_rest, i * gate, gate)[0] for i in range(300)])
    # A fast crystal makes the 100 000-cycle gate 100 ppm shorter than the slow one's.
    x = float(expected_counts(P.C1_rest))
    assert n_slow - n_fast == pytest.approx(x * 100e-6 / (1 - 2.5e-9), abs=0.25)
    assert fast.cycles_at(1.0) == 50_002_500
    assert slow.cycles_at(2.0) == 99_995_000
    assert Chip().cycles_at(0.0) == 0 and Chip().cycles_at(1e-6) == CLOCK_HZ // 1_000_000
    assert fast.cycles_at(fast.seconds_at(123_456_789) + 1e-12) == 123_456_789


def test_random_crystal_within_tolerance_and_reproducible():
    cfg = ChipConfig()
    ppms = [cfg.with_random_crystal(s).crystal_ppm for s in range(200)]
    assert all(abs(p) <= 50.0 for p in ppms)
    assert min(ppms) < -40 and max(ppms) > 40
    assert cfg.with_random_crystal(17) == cfg.with_random_crystal(17)
    narrow = ChipConfig(crystal_tolerance_ppm=5.0).with_random_crystal(3)
    assert abs(narrow.crystal_ppm) <= 5.0


def test_deterministic_for_seed_channel_and_start():
    a, b = Chip(seed=9), Chip(seed=9)
    calls = [(ch, c, s) for ch in (0, 1) for c in (P.C1_rest, 21e-12) for s in (0, 100_000, 2**40)]
    first = [a.count(ch, c, s, 100_000) for ch, c, s in calls]
    # Same answers from another chip with the seed, in reverse order, and repeated.
    assert [b.count(*k, 100_000) for k in reversed(calls)][::-1] == first
    assert [a.count(*k, 100_000) for k in calls] == first
    assert a.convert(1, P.C2_rest, 77, 64) == b.convert(1, P.C2_rest, 77, 64)
    # Other seeds and other channels are other noise.
    for other in (Chip(seed=10), None):
        ch_shift = 1 if other is None else 0
        chip = a if other is None else other
        seq = [chip.count(ch_shift, P.C1_rest, i * 100_000, 100_000)[0] for i in range(40)]
        ref = [a.count(0, P.C1_rest, i * 100_000, 100_000)[0] for i in range(40)]
        assert seq != ref
    held = [a.held_inputs(0, P.C1_rest, s, 4) for s in (0, 1)]
    assert not np.array_equal(held[0], held[1])


def test_conversion_takes_its_cycles():
    cfg = ChipConfig(adc_discharge_cycles=10, adc_sample_delay=64, adc_bits=8)
    chip = Chip(cfg)
    assert chip.convert(0, P.C1_rest, 0, 1)[1] == 82
    assert chip.convert(0, P.C1_rest, 0, 64)[1] == 64 * 82


@pytest.mark.parametrize(
    "kwargs, key",
    [
        ({"jitter": 0.5}, "jitter"),
        ({"jitter": -1e-3}, "jitter"),
        ({"gate_cycles": 0}, "gate_cycles"),
        ({"clock_hz": 50e6}, "clock_hz"),
        ({"r_ohm": 0.0}, "r_ohm"),
        ({"adc_noise_lsb": float("nan")}, "adc_noise_lsb"),
        ({"adc_discharge_cycles": -1}, "adc_discharge_cycles"),
        ({"counter_bits": 80}, "counter_bits"),
        ({"crystal_ppm": float("inf")}, "clock_ppm"),
    ],
)
def test_bad_config_names_the_key(kwargs, key):
    with pytest.raises(ValueError, match=key):
        ChipConfig(**kwargs)


@pytest.mark.parametrize(
    "call, key",
    [
        (lambda c: c.count(-1, 15e-12, 0, 100), "channel"),
        (lambda c: c.count(0, 0.0, 0, 100), "capacitance"),
        (lambda c: c.count(0, float("nan"), 0, 100), "capacitance"),
        (lambda c: c.count(0, "15p", 0, 100), "capacitance"),
        (lambda c: c.count(0, 0.5e-12, 0, 100), "capacitance"),
        (lambda c: c.count(0, 15.67, 0, 100), "picofarads"),  # oscillator faster than 4x the clock
        (lambda c: c.count(0, 15e-12, -5, 100), "start_cycle"),
        (lambda c: c.count(0, 15e-12, 0, 0), "gate_cycles"),
        (lambda c: c.count(0, 15e-12, 0, 1.5), "gate_cycles"),
        (lambda c: c.convert(0, 15e-12, 0, 0), "oversampling"),
        (lambda c: c.convert(0, -1e-12, 0, 4), "capacitance"),
        (lambda c: c.cycles_at(-1.0), "host_seconds"),
    ],
)
def test_bad_calls_name_the_argument(call, key):
    with pytest.raises(ValueError, match=key):
        call(Chip())


def test_synchroniser_limit_is_the_transfer_modules():
    """transfer.sync_min_capacitance (T = 2 cycles) is where the chip stops seeing
    every edge: just above it all edges count, well below it edges are lost."""
    from cellbridge.tactile.transfer import sync_min_capacitance

    chip = Chip(seed=5)
    c_min = sync_min_capacitance(chip.params)
    above = chip.edge_train(0, 1.03 * c_min, 0, 100_000)
    assert above.every_edge_seen
    gate = chip.config.gate_cycles
    c = 0.8 * c_min  # T = 1.6 cycles: the low half (0.8 cycles) can fall between samples
    got = np.mean([chip.count(0, c, i * gate, gate)[0] for i in range(10)])
    assert not chip.edge_train(0, c, 0, gate).every_edge_seen
    assert got < 0.9 * float(expected_counts(c, chip.params))


def test_counts_computed_ahead_are_the_counts_each_answered_once() -> None:
    # Chip.prefetch computes counts before they are asked for (a real-time bridge, while
    # the chip model's code is warm): count() then answers with exactly what it computes
    # itself, once each; anything else it asks is computed as ever.
    gates = [(ch, c, 1_000 + 100_000 * k + ch * 100_000, 100_000)
             for k in range(8) for ch, c in ((0, 15.67e-12), (1, 19.44e-12))]
    chip, fresh = Chip(ChipConfig(), seed=7), Chip(ChipConfig(), seed=7)
    chip.prefetch(gates)
    assert all(chip.computed(*g) for g in gates)
    assert [chip.count(*g) for g in gates] == [fresh.count(*g) for g in gates]
    assert chip.prefetch_hits == len(gates)
    assert not any(chip.computed(*g) for g in gates)
    other = (0, 15.68e-12, gates[0][2], 100_000)  # another capacitance: computed when asked
    chip.prefetch(gates[:2])
    assert chip.count(*other) == fresh.count(*other) and chip.prefetch_hits == len(gates)
    chip.prefetch(gates[4:6])  # what was computed for gates before the new first is forgotten
    assert not chip.computed(*gates[0])


def test_a_prefetch_that_raises_leaves_no_count_it_did_not_compute() -> None:
    # A prefetch whose later gate count() refuses (a capacitance below the modelled
    # oscillator) raised after holding places for the earlier gates with a dummy (0,
    # False): count() then answered those gates with it, not with their counts.
    chip, fresh = Chip(ChipConfig(), seed=0), Chip(ChipConfig(), seed=0)
    good, bad = (0, 211.6e-12, 0, 100_000), (1, 0.5e-12, 0, 100_000)
    with pytest.raises(ValueError):
        chip.prefetch([good, bad])
    assert chip.count(*good) == fresh.count(*good) != (0, False)
