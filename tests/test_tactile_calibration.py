"""Baseline, drift tracking, touch hysteresis and tare (cellbridge.tactile.calibration)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cellbridge.tactile.calibration import (
    COLLECTING,
    HOLDOFF,
    TOUCHED,
    TRACKING,
    CalibrationConfig,
    Calibrator,
)
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.inversion import inverse
from cellbridge.tactile.skin import grid_layout, skin_response

pF = 1e-12
fF = 1e-15


def feed(cal, t, v):
    return cal.update(t, np.asarray(v, dtype=float))


def test_baseline_is_median_of_first_quiet_samples_and_ready_after_n():
    cal = Calibrator(3, 2, CalibrationConfig(n_baseline=5))
    rng = np.random.default_rng(0)
    vals = 20 * pF + rng.normal(0, 1 * fF, (5, 3, 2))
    vals[2, 1, 0] += 3 * pF  # one spike in the window: the median ignores it
    for k in range(4):
        step = feed(cal, 0.01 * k, vals[k])
        assert not step.ready.any() and np.isnan(step.delta).all()
        assert (cal.state == COLLECTING).all()
    step = feed(cal, 0.04, vals[4])
    assert step.ready.all() and (cal.state == TRACKING).all()
    np.testing.assert_allclose(cal.baseline, np.median(vals, axis=0))
    assert cal.baseline[1, 0] < 20 * pF + 5 * fF
    assert np.isnan(step.delta).all()  # the reading completing the baseline is not a delta yet
    before = cal.baseline
    nxt = feed(cal, 0.05, vals[4])
    np.testing.assert_allclose(nxt.delta, vals[4] - before, rtol=1e-12, atol=1e-30)


def test_noise_estimate_and_noise_scaled_thresholds():
    cal = Calibrator(2, 1, CalibrationConfig(n_baseline=400, enter=0.0, leave=0.0, k_enter=8, k_leave=4))
    rng = np.random.default_rng(1)
    sd = np.array([1 * fF, 100 * fF])
    for k in range(400):
        feed(cal, 0.01 * k, (10 * pF + rng.normal(0, 1, 2) * sd)[:, None])
    np.testing.assert_allclose(cal.noise[:, 0], sd, rtol=0.15)
    enter, leave = cal.thresholds()
    np.testing.assert_allclose(enter[:, 0], 8 * cal.noise[:, 0])
    np.testing.assert_allclose(leave[:, 0], 4 * cal.noise[:, 0])


def ready_calibrator(n=1, cfg=None, base=20 * pF):
    cal = Calibrator(n, 2, cfg or CalibrationConfig(n_baseline=3))
    for k in range(cal.config.n_baseline):
        feed(cal, 0.01 * k, np.full((n, 2), base))
    return cal


def test_hysteresis_holdoff_and_tracking():
    cfg = CalibrationConfig(n_baseline=3, enter=50 * fF, leave=25 * fF, holdoff=2.0, tau=1.0)
    cal = ready_calibrator(1, cfg)
    b = 20 * pF
    t = 1.0
    assert not feed(cal, t, [[b + 40 * fF, b]]).touched[0]  # below enter: tracked
    cal.tare()
    for k in range(3):
        feed(cal, t + 0.01 * k, [[b, b]])
    t = 2.0
    assert feed(cal, t, [[b + 60 * fF, b]]).touched[0] and cal.state[0] == TOUCHED
    # Between leave and enter: still touched (hysteresis), baseline frozen.
    for k in range(100):
        s = feed(cal, t + 0.1 * k, [[b + 30 * fF, b + 30 * fF]])
        assert s.touched[0]
    assert cal.baseline[0, 0] == b
    t += 10.0
    s = feed(cal, t, [[b + 10 * fF, b]])
    assert not s.touched[0] and cal.state[0] == HOLDOFF
    # During hold-off the baseline stays put even though the reading differs.
    feed(cal, t + 1.0, [[b + 10 * fF, b]])
    assert cal.baseline[0, 0] == b and cal.state[0] == HOLDOFF
    feed(cal, t + 2.5, [[b + 10 * fF, b]])
    assert cal.state[0] == TRACKING
    for k in range(1, 1000):
        feed(cal, t + 2.5 + 0.01 * k, [[b + 10 * fF, b]])
    assert cal.baseline[0, 0] == pytest.approx(b + 10 * fF, abs=0.01 * fF)


def test_exponential_tracker_uses_timestamps_not_sample_count():
    # The same ramp sampled at 10 Hz and 200 Hz ends with the same lag r·τ.
    for rate in (10.0, 200.0):
        cfg = CalibrationConfig(n_baseline=3, tau=5.0, enter=1.0, leave=0.5)
        cal = ready_calibrator(1, cfg, base=0.0)
        r = 1e-3  # units per second
        ts = 1.0 + np.arange(1, int(60 * rate)) / rate
        for t in ts:
            feed(cal, t, [[r * (t - 1.0), 0.0]])
        lag = r * (ts[-1] - 1.0) - cal.baseline[0, 0]
        assert lag == pytest.approx(r * 5.0, rel=0.06)


def test_fast_recovery_when_reading_falls_below_baseline():
    # A baseline taken while something rested on the skin reads negative once it is
    # lifted; no contact can do that, so the tracker catches up on tau_negative.
    cfg = CalibrationConfig(n_baseline=3, tau=60.0, tau_negative=1.0)
    cal = ready_calibrator(1, cfg, base=21 * pF)
    for k in range(1, 501):
        s = feed(cal, 1.0 + 0.01 * k, [[20 * pF, 20 * pF]])
    # Back inside the touch band (|ΔC| < enter) within 5 s, against minutes on tau.
    assert abs(s.delta[0, 0]) < cfg.enter


def test_tare_selected_elements_only():
    cal = ready_calibrator(3)
    cal.tare([1])
    assert list(cal.state) == [TRACKING, COLLECTING, TRACKING]
    s = feed(cal, 1.0, np.full((3, 2), 21 * pF))
    assert list(s.ready) == [True, False, True] and np.isnan(s.delta[1]).all()
    feed(cal, 1.01, np.full((3, 2), 21 * pF))
    s = feed(cal, 1.02, np.full((3, 2), 21 * pF))
    assert s.ready.all()
    assert cal.baseline[1, 0] == 21 * pF and cal.baseline[0, 0] < 21 * pF
    cal.tare(np.array([True, False, False]))
    assert cal.state[0] == COLLECTING
    with pytest.raises(ValueError):
        cal.tare([5])
    with pytest.raises(ValueError):
        cal.tare([0.5])


def test_missing_readings_per_element_times_and_errors():
    cal = ready_calibrator(2)
    s = feed(cal, 1.0, [[np.nan, np.nan], [20 * pF, 20 * pF]])
    assert np.isnan(s.delta[0]).all() and not np.isnan(s.delta[1]).any()
    cal.update(np.array([2.0, 1.5]), np.full((2, 2), 20 * pF))
    with pytest.raises(ValueError, match="backwards"):
        cal.update(np.array([1.9, 1.6]), np.full((2, 2), 20 * pF))
    with pytest.raises(ValueError):
        cal.update(3.0, np.zeros((3, 2)))
    with pytest.raises(ValueError):
        cal.update(np.nan, np.zeros((2, 2)))
    with pytest.raises(ValueError):
        CalibrationConfig(n_baseline=0)
    with pytest.raises(ValueError):
        CalibrationConfig(k_leave=9, k_enter=8)
    with pytest.raises(ValueError):
        Calibrator(2, 2, CalibrationConfig(enter=[1.0, 2.0, 3.0]))
    with pytest.raises(ValueError):
        Calibrator(2, 2, CalibrationConfig(enter=1.0, leave=2.0))
    one = Calibrator(2, 1, CalibrationConfig(n_baseline=1))
    assert one.update(0.0, np.array([1.0, 2.0])).ready.all()  # (N,) accepted for one channel


def test_max_touch_rebaselines_a_stuck_element():
    cfg = CalibrationConfig(n_baseline=3, max_touch=10.0)
    cal = ready_calibrator(1, cfg)
    t = 1.0
    while t < 12.0:
        s = feed(cal, t, [[21 * pF, 21 * pF]])
        t += 0.1
    # Touched at t = 1 s, re-baselined at 11 s, ready again three readings later.
    assert cal.state[0] == TRACKING and cal.baseline[0, 0] == 21 * pF
    assert s.delta[0, 0] == pytest.approx(0.0, abs=1e-20) and not s.touched[0]


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=5, max_size=60), st.floats(0.01, 1.0))
def test_tracked_baseline_stays_within_the_readings(vals, dt):
    # The tracker is a running convex combination: it can never leave the range of
    # what it was fed (no overshoot, whatever the sampling interval).
    cfg = CalibrationConfig(n_baseline=1, enter=10.0, leave=5.0, tau=0.5, tau_negative=0.5)
    cal = Calibrator(1, 1, cfg)
    for k, v in enumerate(vals):
        cal.update(k * dt, np.array([v]))
        assert min(vals[: k + 1]) - 1e-12 <= cal.baseline[0, 0] <= max(vals[: k + 1]) + 1e-12


# --------------------------------------------------------- ten minutes, held press


def _stream(rate: float, common_mode: bool = True, enter: float = 50 * fF):
    """10 min (simulated time) of a 2×2 skin with drift and a press held for 8 min.

    Drift: a shared temperature-like term (0.3 pF linear plus a ±0.1 pF swing with a
    5 min period: up to ≈2.6 fF/s) scaled ±8 % per element and channel, plus 1 fF
    rms noise — twelve times the smallest press the thresholds detect. The press
    (3 N, D = 20 mm, centre of element 0, ΔC1 ≈ 2.2 pF) lasts from t = 60 s to 540 s.
    """
    lay = grid_layout(2, 2)
    p = ElementParams()
    rng = np.random.default_rng(7)
    t_end = 600.0
    t = np.arange(int(rate * t_end)) / rate
    common = 0.3 * pF * t / t_end + 0.1 * pF * np.sin(2 * math.pi * t / 300.0)
    scale = 1.0 + rng.uniform(-0.08, 0.08, (4, 2))
    rest = np.array([p.C1_rest, p.C2_rest])
    d1, d2 = skin_response(lay, [0.0, 0.0, 3.0, 0.020])
    press = np.stack([d1, d2], axis=1)  # (4, 2)
    on = (t >= 60.0) & (t < 540.0)
    readings = (
        rest[None, None, :]
        + common[:, None, None] * scale[None, :, :]
        + on[:, None, None] * press[None, :, :]
        + rng.normal(0, 1 * fF, (t.size, 4, 2))
    )
    cal = Calibrator(4, 2, CalibrationConfig(common_mode=common_mode, enter=enter))
    delta = np.empty_like(readings)
    touched = np.empty((t.size, 4), dtype=bool)
    for k in range(t.size):
        s = cal.update(t[k], readings[k])
        delta[k] = s.delta
        touched[k] = s.touched
    return t, delta, touched, press


@pytest.fixture(scope="module")
def stream_100hz():
    return _stream(100.0)


def test_ten_minute_press_is_kept_while_neighbour_drift_is_removed(stream_100hz):
    t, delta, touched, press = stream_100hz
    held = (t >= 60.5) & (t < 540.0)
    assert touched[held, 0].all() and not touched[:, 1:].any()
    f, _, ok = inverse(delta[held, 0, 0], delta[held, 0, 1], noise=2 * fF)
    assert ok.all()
    assert np.abs(f / 3.0 - 1.0).max() < 0.05
    # Untouched neighbours: up to 0.44 pF of drift reduced to the tracker's lag.
    late = t > 5.0
    assert np.abs(delta[late, 1:, :]).max() < 40 * fF
    # After release and hold-off the pressed element reads zero again.
    after = t > 560.0
    assert not touched[after, 0].any()
    assert np.abs(delta[after, 0, :]).max() < 40 * fF


def test_without_common_mode_the_press_is_still_not_erased():
    # Frozen baseline only: the held element keeps its own drift during the press
    # (the shared drift over 8 min), but it is never tracked away.
    t, delta, touched, press = _stream(20.0, common_mode=False)
    held = (t >= 60.5) & (t < 540.0)
    assert touched[held, 0].all()
    assert np.abs(delta[held, 0, 0] / press[0, 0] - 1.0).max() < 0.2


def test_a_tracker_without_touch_detection_would_erase_the_press():
    # Negative control: with thresholds no press can reach, the tracker follows the
    # press as if it were drift and the contact is gone within minutes.
    t, delta, touched, press = _stream(20.0, enter=1.0)
    assert not touched.any()
    assert np.abs(delta[(t > 300.0) & (t < 540.0), 0, 0]).max() < 0.05 * press[0, 0]
