"""Per-bridge clock sync: offset and skew from delayed arrivals, counter wrap, bridge reset."""

from __future__ import annotations

import numpy as np
import pytest
from cellbridge.daemon.core.clock import BridgeClock
from hypothesis import given, settings
from hypothesis import strategies as st

HZ = 50e6


def _run(clock: BridgeClock, ppm: float, t0: float, seconds: float, rng: np.random.Generator,
         c0: int = 10**9, bits: int = 64, rate: float = 50.0) -> tuple[np.ndarray, np.ndarray]:
    """Feed observations of a bridge whose crystal is ``ppm`` off; returns (true times, cycles)."""
    ts = np.arange(0.0, seconds, 1.0 / rate)
    cycles = (c0 + np.round(ts * HZ * (1 + ppm * 1e-6)).astype(np.int64)) % np.int64(min(1 << bits, 1 << 62))
    delays = 0.002 + rng.exponential(0.003, ts.size)  # never negative, jittery
    for t, c, d in zip(ts, cycles, delays):
        clock.observe(int(c), t0 + t + d)
    return t0 + ts, cycles.astype(np.uint64)


@settings(max_examples=25, deadline=None)
@given(ppm=st.floats(-80, 80), seed=st.integers(0, 2**32 - 1))
def test_recovers_offset_and_skew_from_delayed_arrivals(ppm: float, seed: int) -> None:
    clock = BridgeClock(HZ)
    truth, cycles = _run(clock, ppm, 5000.0, 30.0, np.random.default_rng(seed))
    err = clock.to_host(cycles[-500:]) - truth[-500:]
    # Mapped to the least-delayed arrival: within the 2 ms minimum delay plus a little, no jitter.
    assert np.all(err > 0.0015) and np.all(err < 0.0030), (err.min(), err.max())
    assert abs(clock.skew + ppm * 1e-6) < 10e-6  # a fast crystal (ppm > 0) runs ahead: host time is slower


def test_jitter_does_not_reach_the_timestamps() -> None:
    clock = BridgeClock(HZ)
    truth, cycles = _run(clock, 30.0, 0.0, 20.0, np.random.default_rng(1))
    err = clock.to_host(cycles) - truth
    assert np.std(err[-200:]) < 2e-4  # arrival jitter is 3 ms rms


def test_counter_wrap_is_unwrapped() -> None:
    bits = 32
    clock = BridgeClock(HZ, bits=bits)
    start = (1 << bits) - int(HZ * 3)  # wraps 3 s in
    truth, cycles = _run(clock, 0.0, 100.0, 10.0, np.random.default_rng(2), c0=start, bits=bits)
    assert cycles.min() < 10**8 and cycles.max() > (1 << bits) - 10**8  # it did wrap
    err = clock.to_host(cycles[-100:]) - truth[-100:]
    assert np.all(np.abs(err) < 0.01)
    assert clock.resets == 0


def test_long_run_with_a_narrow_counter_keeps_its_fit() -> None:
    clock = BridgeClock(HZ, bits=32)  # wraps every 86 s; the origin must move, not reset
    truth, cycles = _run(clock, 20.0, 0.0, 200.0, np.random.default_rng(3), rate=10.0)
    assert clock.resets == 0
    assert np.all(np.abs(clock.to_host(cycles[-50:]) - truth[-50:]) < 0.01)


def test_bridge_reset_restarts_the_fit() -> None:
    clock = BridgeClock(HZ)
    rng = np.random.default_rng(4)
    _run(clock, 10.0, 0.0, 10.0, rng, c0=10**10)
    truth, cycles = _run(clock, 10.0, 10.5, 5.0, rng, c0=0)  # counter restarted from zero
    assert clock.resets == 1
    assert np.all(np.abs(clock.to_host(cycles[-50:]) - truth[-50:]) < 0.01)


def test_unsynced_clock_maps_to_nan() -> None:
    assert np.isnan(BridgeClock(HZ).to_host(np.array([1, 2], dtype=np.uint64))).all()


@settings(max_examples=6, deadline=None)
@given(step=st.sampled_from([-0.9, -0.5, -0.2, 0.2, 0.5, 0.9]), ppm=st.floats(-80, 80))
def test_a_host_clock_step_below_the_jump_limit_is_followed_within_seconds(step: float, ppm: float) -> None:
    """An NTP step of the host clock by less than ``max_jump``: the lower envelope moves
    by the step at once. The fit used to mix minima from both sides of it for a whole
    window (64 s) of times up to the step off; now it follows within a few blocks."""
    rng = np.random.default_rng(3)
    clock = BridgeClock(HZ)
    ts = np.arange(0.0, 200.0, 0.05)
    cycles = (10**9 + np.round(ts * HZ * (1 + ppm * 1e-6))).astype(np.int64)
    host = 5000.0 + ts + np.where(ts >= 100.0, step, 0.0)  # the host's clock, stepped at t = 100 s
    errs = []
    for t, c, h in zip(ts, cycles, host):
        if t == 100.0:
            clock.host_step(step)  # the service sees wall minus monotonic time change
        clock.observe(int(c), h + 0.002 + rng.exponential(0.003))
        errs.append(clock.to_host(np.array([c], dtype=np.uint64))[0] - h)
    err = np.array(errs)
    after = ts >= 104.0
    assert np.all(np.abs(err[after]) < 0.005), (err[after].min(), err[after].max())
    assert clock.resets == 0 and abs(clock.skew + ppm * 1e-6) < 10e-6
def test_seconds_of_congestion_are_a_delay_not_a_reset() -> None:
    """The mesh holds a bridge's frames back 1.5..3 s for 10 s, and old frames arrive after
    newer ones: no reset, and the times stay on the least-delayed frames seen before."""
    clock = BridgeClock(HZ)
    rng = np.random.default_rng(5)
    truth, cycles = _run(clock, 20.0, 0.0, 5.0, rng, c0=10**10)
    ts = np.arange(5.0, 15.0, 0.02)
    cyc = 10**10 + np.round(ts * HZ * (1 + 20e-6)).astype(np.int64)
    order = np.arange(ts.size)
    order[100:400:7], order[101:401:7] = order[101:401:7], order[100:400:7]  # old frames after newer ones
    for i in order:
        clock.observe(int(cyc[i]), ts[i] + 1.5 + rng.uniform(0.0, 1.5))
    assert clock.resets == 0
    err = clock.to_host(cyc[-50:].astype(np.uint64)) - ts[-50:]
    assert np.all(np.abs(err) < 0.01), (err.min(), err.max())
    assert abs(clock.skew) <= clock.max_skew


def test_a_reset_is_taken_at_once_after_the_numbering_restarted() -> None:
    clock = BridgeClock(HZ)
    rng = np.random.default_rng(6)
    _run(clock, 0.0, 0.0, 3.0, rng, c0=10**10)
    clock.suspect_reset()  # the pipeline saw the bridge's frame numbers start again
    truth, cycles = _run(clock, 0.0, 3.5, 0.2, rng, c0=10**5)  # booted again: counter near zero
    assert clock.resets == 1
    assert np.all(np.abs(clock.to_host(cycles[-5:]) - truth[-5:]) < 0.02)


def test_the_skin_clock_follows_a_jump_back_but_not_a_burst_of_old_frames() -> None:
    """A gateway's points a few seconds behind its newest, in bursts between current ones (a
    confused relay passing old records on), are not the skin's time going back: the map
    keeps its time (it restarted on each burst of three). Points behind that keep coming,
    consistent, for 0.1 s are: then it follows."""
    from cellbridge.daemon.core.clock import SkinClock

    hz = 50_000_000
    clock = SkinClock(hz)
    for k in range(200):
        t = 10.0 + k * 0.01
        assert not clock.teach(1, k * hz // 100, t + 0.004)
        if k % 7 == 0 and k > 100:
            for old in range(k - 90, k - 86):  # four old frames at once
                assert not clock.teach(1, old * hz // 100, t + 0.004)
    assert clock.resets == 0
    assert clock.frame_time(199 * hz // 100, 12.0) == pytest.approx(10.0 + 1.99 + 0.004, abs=1e-3)
    jumped = [clock.teach(1, k * hz // 100, 12.0 + k * 0.01 + 0.004) for k in range(15)]  # back to 0
    assert jumped.index(True) == 10 and clock.resets == 1


@settings(max_examples=300, deadline=None)
@given(bits=st.sampled_from([32, 48, 64]), start=st.integers(0, 2**64 - 1), step=st.integers(1, 10**7),
       cycles=st.lists(st.integers(0, 2**64 - 1), min_size=1, max_size=20))
def test_to_host_one_is_to_host_of_one_cycle(bits: int, start: int, step: int, cycles: list[int]) -> None:
    """The scalar map (a readout record's point) gives bit for bit what the vectorised one does."""
    mask = (1 << bits) - 1
    c = BridgeClock(50e6, bits=bits)
    for i in range(12):
        c.observe((start + i * step) & mask, 100.0 + i * step / 50e6 + (i % 3) * 1e-4)
    for g in cycles:
        g &= mask
        assert c.to_host_one(g) == float(c.to_host(np.array([g], dtype=np.uint64))[0])


_steps = st.lists(st.tuples(
    st.sampled_from(["teach", "ask"]),
    # the next frame number after the one before: 100 Hz frames of a 50 MHz mesh time, mostly
    # forward, now and then back (below 0: a nonsense index)
    st.one_of(st.integers(0, 3), st.integers(-60, 60)),
    st.floats(-0.5, 0.5),  # host time of the step after the frame's own instant
), min_size=10, max_size=80)


@settings(max_examples=300, deadline=None)
@given(steps=_steps, memory_keys=st.integers(1, 3), memory=st.sampled_from([0.05, 0.5, 10.0]))
def test_frame_time_of_one_frame_is_frame_times_of_it(steps: list[tuple[str, int, float]], memory_keys: int,
                                                      memory: float) -> None:
    """A readout record's frame is mapped by the scalar path (frame_time): it gives, and
    remembers, what the array path (frame_times of that one frame) gives, to the bit, on
    any sequence of points taught and frames asked (a map not made yet, jumps back and
    ahead held or confirmed, frames after their arrival, the memory pruned)."""
    from cellbridge.daemon.core.clock import SkinClock

    hz = 50_000_000
    one, arr = SkinClock(hz, memory=memory, memory_keys=memory_keys), SkinClock(hz, memory=memory,
                                                                               memory_keys=memory_keys)
    k = 0
    for what, step, dt in steps:
        k += step
        g = k * hz // 100 if k >= 0 else -1
        now = 100.0 + k * 0.01 + dt
        if what == "teach" and g >= 0:
            assert one.teach(7, g, now) == arr.teach(7, g, now)
            continue
        a = one.frame_time(g, now)
        b = float(arr.frame_times(np.array([g], dtype=np.int64), now)[0])
        assert a == b or (np.isnan(a) and np.isnan(b)), (a, b)
        assert one._memo == arr._memo and one._newest == arr._newest  # what later frames are given
