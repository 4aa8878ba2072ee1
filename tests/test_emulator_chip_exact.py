"""The chip's fast path against the per-cycle reference stepper, bit for bit.

Windows are short (≤ 3 000 cycles) so the stepper stays fast; capacitances reach down
to oscillators faster than the clock, so both the closed-form count and the
synchroniser rule are exercised, and narrow counters make short gates wrap.
"""

from __future__ import annotations

import numpy as np
from cellbridge.emulator.chip.adc import sar_codes
from cellbridge.emulator.chip.chip import Chip, ChipConfig
from cellbridge.emulator.chip.keyed_random import Z_MAX, GateNoise, KeyedNormals, Stream
from cellbridge.emulator.chip.oscillator import EdgeTrain, max_period_deviation
from cellbridge.emulator.chip.reference import step_conversions, step_counter
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

MAX_JITTER = 0.99 / max_period_deviation()

capacitances = st.floats(min_value=1e-12, max_value=60e-12)
ppms = st.floats(min_value=-100.0, max_value=100.0)
seeds = st.integers(min_value=0, max_value=2**64 - 1)
starts = st.integers(min_value=0, max_value=2**48)
gates = st.integers(min_value=1, max_value=3000)
jitters = st.one_of(st.just(0.0), st.floats(min_value=0.0, max_value=MAX_JITTER))
EXACT = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _train(chip: Chip, channel: int, c: float, start: int, gate: int, phase: float) -> EdgeTrain:
    """The chip's edge train for a gate, with the phase chosen by the test."""
    return EdgeTrain(
        chip.period_cycles(c), chip.config.jitter, phase, gate, GateNoise(chip._noise, channel, start)
    )


@EXACT
@given(
    c=capacitances,
    phase=st.floats(min_value=0.0, max_value=1.0, exclude_max=True),
    ppm=ppms,
    jitter=jitters,
    seed=seeds,
    channel=st.integers(0, 3),
    start=starts,
    gate=gates,
    bits=st.sampled_from([4, 6, 8, 16]),
)
def test_counter_fast_path_equals_reference(c, phase, ppm, jitter, seed, channel, start, gate, bits):
    chip = Chip(ChipConfig(crystal_ppm=ppm, jitter=jitter, counter_bits=bits), seed=seed)
    train = _train(chip, channel, c, start, gate, phase)
    ref = step_counter(train, start, bits)

    events = train.event_offsets() + start
    assert events.tolist() == ref.events
    n = train.edge_count()
    assert n == len(ref.events)
    assert (n % (1 << bits), n >= (1 << bits)) == (ref.register, ref.overflow)


@EXACT
@given(c=capacitances, ppm=ppms, jitter=jitters, seed=seeds, channel=st.integers(0, 1), start=starts, gate=gates)
def test_chip_count_equals_reference(c, ppm, jitter, seed, channel, start, gate):
    chip = Chip(ChipConfig(crystal_ppm=ppm, jitter=jitter, counter_bits=8), seed=seed)
    ref = step_counter(chip.edge_train(channel, c, start, gate), start, 8)
    assert chip.count(channel, c, start, gate) == (ref.register, ref.overflow)


@settings(max_examples=40, deadline=None)
@given(
    seed=seeds,
    start=starts,
    gate=st.integers(20_000, 40_000),
    c=st.floats(min_value=5e-12, max_value=60e-12),
    jitter=st.floats(min_value=0.0, max_value=MAX_JITTER),
)
def test_closed_form_spans_several_jitter_blocks(seed, start, gate, c, jitter):
    """Gates over many jitter blocks (large jitter: every block sum moves the edges by
    cycles): the block search and the in-block search agree with the stepper."""
    chip = Chip(ChipConfig(jitter=jitter), seed=seed)
    train = chip.edge_train(0, c, start, gate)
    ref = len(step_counter(train, start).events)
    assert train.edge_count() == ref
    assert ref == train.event_offsets().size


@settings(max_examples=60, deadline=None)
@given(
    seed=seeds,
    start=starts,
    gate=st.integers(1, 400_000),
    c=st.floats(min_value=2e-12, max_value=60e-12),
    jitter=jitters,
    channel=st.integers(0, 3),
)
def test_chip_count_takes_the_train_count_on_long_gates(seed, start, gate, c, jitter, channel):
    """The chip's count (its own path, without a train) equals the train's edge count on
    gates of up to 8 ms, where the gate's end falls in the hint block or, with large
    jitter, another one; passed as numpy scalars (the train's path) the same."""
    chip = Chip(ChipConfig(jitter=jitter, counter_bits=32), seed=seed)
    n = chip.edge_train(channel, c, start, gate).edge_count()
    assert chip.count(channel, c, start, gate) == (n, False)
    assert chip.count(np.int64(channel), np.float64(c), np.int64(start), np.int64(gate)) == (n, False)  # type: ignore[arg-type]  # numpy scalars, as a caller may pass


def test_edges_are_seen_by_the_rule_not_assumed():
    """An oscillator faster than half the clock loses edges in the synchroniser: the
    count is then well below gate/T, and still equal to the stepper's."""
    chip = Chip(ChipConfig(jitter=0.0), seed=3)
    train = _train(chip, 0, 3e-12, 1000, 2000, 0.25)  # T ≈ 0.98 cycles
    assert not train.every_edge_seen
    n = train.edge_count()
    assert n == len(step_counter(train, 1000).events)
    assert n < 0.9 * 2000 / train.period


@EXACT
@given(
    c=st.floats(min_value=1e-13, max_value=1e-9),
    ppm=ppms,
    noise=st.floats(min_value=0.0, max_value=3.0),
    seed=seeds,
    channel=st.integers(0, 1),
    start=starts,
    n=st.integers(1, 8),
)
def test_adc_fast_path_equals_reference(c, ppm, noise, seed, channel, start, n):
    chip = Chip(ChipConfig(crystal_ppm=ppm, adc_noise_lsb=noise), seed=seed)
    timing = chip.config.adc_timing
    held = chip.held_inputs(channel, c, start, n)
    ref = step_conversions(timing, held, start, chip.config.adc_bits)

    codes = sar_codes(held, chip.config.adc_bits)
    assert codes.tolist() == ref.codes
    samples = timing.sample_cycles(start, n)
    assert samples.tolist() == ref.sample_cycles
    assert (samples + chip.config.adc_bits - 1).tolist() == ref.done_cycles
    assert chip.convert(channel, c, start, n) == (sum(ref.codes), ref.cycles)


@settings(max_examples=100, deadline=None)
@given(x=st.floats(min_value=-50.0, max_value=400.0), bits=st.integers(1, 12))
def test_sar_search_is_floor_clipped(x, bits):
    """Held values anywhere, including beyond both rails."""
    from cellbridge.emulator.chip.adc import AdcTiming

    held = np.array([x])
    ref = step_conversions(AdcTiming(0, 1, bits), held, 0, bits)
    assert sar_codes(held, bits).tolist() == ref.codes


def test_keyed_streams_are_addressable_and_independent():
    """A draw depends on (seed, stream, channel, cycle, substream) only: repeating it,
    after any other draw, gives the same numbers; changing any key gives others."""
    k = KeyedNormals(7)
    a = k.normals(Stream.JITTER_STEPS, 1, 99, 5, 3)
    k.normals(Stream.ADC, 0, 12, 50)
    assert np.array_equal(a, k.normals(Stream.JITTER_STEPS, 1, 99, 5, 3))
    assert np.array_equal(a, k.normals(Stream.JITTER_STEPS, 1, 99, 500, 3)[:5])
    for other in (
        KeyedNormals(8).normals(Stream.JITTER_STEPS, 1, 99, 5, 3),
        k.normals(Stream.ADC, 1, 99, 5, 3),
        k.normals(Stream.JITTER_STEPS, 2, 99, 5, 3),
        k.normals(Stream.JITTER_STEPS, 1, 100, 5, 3),
        k.normals(Stream.JITTER_STEPS, 1, 99, 5, 4),
    ):
        assert not np.array_equal(a, other)
    assert np.all(np.abs(k.normals(Stream.ADC, 0, 0, 100_000)) <= Z_MAX)
