"""Baseline, drift tracking, touch hysteresis and tare (cellbridge.tactile.calibration)."""

from __future__ import annotations

import math
from typing import cast

import numpy as np
import pytest
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
from cellbridge.tactile.layout import grid_layout
from cellbridge.tactile.response import skin_response
from hypothesis import given, settings
from hypothesis import strategies as st

pF = 1e-12
fF = 1e-15


def feed(cal, t, v):
    return cal.update(t, np.asarray(v, dtype=float))


def test_baseline_is_median_of_first_quiet_samples_and_ready_after_n():
    cal = Calibrator(3, 2, CalibrationConfig(n_baseline=5, common_mode=False))
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
    cfg = CalibrationConfig(n_baseline=3, enter=50 * fF, leave=25 * fF, holdoff=2.0, tau=1.0,
                            max_drift=20 * fF)
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
        cfg = CalibrationConfig(n_baseline=3, tau=5.0, enter=1.0, leave=0.5, max_drift=math.inf)
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
    cal = ready_calibrator(3, CalibrationConfig(n_baseline=3, common_mode=False))
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
    assert one.update(0.0, np.array([1.0, 2.0]) * pF).ready.all()  # (N,) accepted for one channel


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
    cfg = CalibrationConfig(n_baseline=1, enter=10.0, leave=5.0, tau=0.5, tau_negative=0.5,
                            max_drift=math.inf)
    cal = Calibrator(1, 1, cfg)
    for k, v in enumerate(vals):
        cal.update(k * dt, np.array([v]))
        assert min(vals[: k + 1]) - 1e-12 <= cal.baseline[0, 0] <= max(vals[: k + 1]) + 1e-12


# --------------------------------------------------------- ten minutes, held press


def _stream(rate: float, drift: str = "temperature", ramp: float = 0.0, **cfg):
    """10 min (simulated time) of a 2×2 skin with drift and a press held for 8 min.

    Drift: a shared temperature-like term (0.3 pF linear plus a ±0.1 pF swing with a
    5 min period: up to ≈2.6 fF/s) scaled ±8 % per element and channel, plus 1 fF rms
    noise — twelve times the smallest press the thresholds detect. ``"5fF/s"`` adds a
    drift common to all elements of 5 fF/s throughout (3 pF in 10 min). The press (3 N, D = 20 mm, centre of
    element 0, ΔC1 ≈ 2.2 pF) rises linearly over ``ramp`` seconds from t = 60 s and is
    held until 540 s.
    """
    lay = grid_layout(2, 2)
    p = ElementParams()
    rng = np.random.default_rng(7)
    t_end = 600.0
    t = np.arange(int(rate * t_end)) / rate
    common = 0.3 * pF * t / t_end + 0.1 * pF * np.sin(2 * math.pi * t / 300.0)
    same = 5 * fF * t if drift == "5fF/s" else np.zeros_like(t)
    scale = 1.0 + rng.uniform(-0.08, 0.08, (4, 2))
    rest = np.array([p.C1_rest, p.C2_rest])
    d1, d2 = skin_response(lay, [0.0, 0.0, 3.0, 0.020])
    press = np.stack([d1, d2], axis=1)  # (4, 2)
    on = np.clip((t - 60.0) / max(ramp, 1e-9), 0.0, 1.0) * (t < 540.0)
    readings = (
        rest[None, None, :]
        + common[:, None, None] * scale[None, :, :]
        + same[:, None, None]
        + on[:, None, None] * press[None, :, :]
        + rng.normal(0, 1 * fF, (t.size, 4, 2))
    )
    cal = Calibrator(4, 2, CalibrationConfig(**cfg))
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


def check_held_press(t, delta, touched, held_from=60.5):
    held = (t >= held_from) & (t < 540.0)
    assert touched[held, 0].all() and not touched[:, 1:].any()
    f, _, ok = inverse(delta[held, 0, 0], delta[held, 0, 1], noise=2 * fF)
    assert ok.all()
    assert np.abs(f / 3.0 - 1.0).max() < 0.05
    # Untouched neighbours: drift reduced to noise and the tracker's lag.
    late = t > 5.0
    assert np.abs(delta[late, 1:, :]).max() < 40 * fF
    # After release and hold-off the pressed element reads zero again.
    after = t > 560.0
    assert not touched[after, 0].any()
    assert np.abs(delta[after, 0, :]).max() < 40 * fF


def test_ten_minute_press_is_kept_while_neighbour_drift_is_removed(stream_100hz):
    check_held_press(*stream_100hz[:3])


def test_ten_minute_press_under_5_fF_per_second_common_drift():
    check_held_press(*_stream(20.0, drift="5fF/s")[:3])


def test_ten_minute_slow_press_is_reported_and_kept():
    # The press takes 60 s to build up (37 fF/s on C1): reported as soon as it clears
    # the threshold, held within 5 % once fully on.
    t, delta, touched, _ = _stream(20.0, ramp=60.0)
    assert touched[(t >= 63.0) & (t < 540.0), 0].all()
    check_held_press(t, delta, touched, held_from=120.0)


def test_without_common_mode_the_press_is_still_not_erased():
    # Frozen baseline only: the held element keeps its own drift during the press
    # (the shared drift over 8 min), but it is never tracked away. Without the
    # common mode each element must follow the whole drift (≈2.6 fF/s) itself.
    t, delta, touched, press = _stream(20.0, common_mode=False, max_drift=5 * fF)
    held = (t >= 60.5) & (t < 540.0)
    assert touched[held, 0].all() and not touched[:, 1:].any()
    assert np.abs(delta[held, 0, 0] / press[0, 0] - 1.0).max() < 0.2


def test_a_tracker_without_touch_detection_would_erase_the_press():
    # Negative control: with thresholds no press can reach and no bound on how fast a
    # baseline may rise, the tracker follows the press as if it were drift and the
    # contact is gone within minutes.
    t, delta, touched, press = _stream(20.0, enter=1.0, max_drift=math.inf)
    assert not touched.any()
    assert np.abs(delta[(t > 300.0) & (t < 540.0), 0, 0]).max() < 0.05 * press[0, 0]


def test_bounded_drift_alone_keeps_an_undetected_press():
    # The other half: the same blind thresholds, but the default bound on the
    # baseline's rise — the press is not absorbed (the tracker moves ≤ 1 fF/s).
    t, delta, touched, press = _stream(20.0, enter=1.0)
    held = (t > 300.0) & (t < 540.0)
    assert np.all(delta[held, 0, 0] > 0.7 * press[0, 0])


# ------------------------------------------------ issue 9: release and drift rules


def ready_skin(n=16, cfg=None, base=20 * pF, rate=10.0):
    """n elements, two channels, ready at t = (n_baseline − 1)/rate on a flat baseline."""
    cfg = cfg or CalibrationConfig()
    cal = Calibrator(n, 2, cfg)
    rng = np.random.default_rng(11)
    for k in range(cfg.n_baseline):
        feed(cal, k / rate, base + rng.normal(0, 1 * fF, (n, 2)))
    assert cal.ready.all()
    return cal, cfg.n_baseline / rate, rng


def run(cal, t0, t1, reading, rate=10.0):
    """Feed reading(t) from t0 to t1; return every step's touched mask (steps, N)."""
    out = []
    for t in np.arange(t0, t1, 1.0 / rate):
        out.append(feed(cal, t, reading(t)).touched)
    return np.array(out)


def test_a_common_step_is_drift_not_touch():
    # A supply step of +300 fF on all 16 elements (±8 % per element): no element is
    # ever touched, and ΔC returns to the noise once the step is absorbed.
    cal, t0, rng = ready_skin()
    scale = 1.0 + rng.uniform(-0.08, 0.08, (16, 2))
    touched = run(cal, t0, 600.0, lambda t: 20 * pF + (t > 10.0) * 300 * fF * scale
                  + rng.normal(0, 1 * fF, (16, 2)))
    assert not touched.any()
    s = feed(cal, 600.0, 20 * pF + 300 * fF * scale)
    assert np.abs(s.delta).max() < 5 * fF
    assert cal.common_drift == pytest.approx([300 * fF, 300 * fF], abs=30 * fF)
    assert cal.health()["common_jumps"] >= 1


def test_common_drift_of_5_fF_per_second_is_not_touch():
    cal, t0, rng = ready_skin()
    scale = 1.0 + rng.uniform(-0.08, 0.08, (16, 2))
    touched = run(cal, t0, 600.0, lambda t: 20 * pF + 5 * fF * t * scale
                  + rng.normal(0, 1 * fF, (16, 2)))
    assert not touched.any()


def test_max_touch_has_a_default_and_rebaselines_are_counted():
    cfg = CalibrationConfig()
    assert cfg.max_touch is not None and 480.0 < cfg.max_touch <= 3600.0
    # One element's connector shifts by +200 fF: a lone, steady phantom touch.
    cal, t0, rng = ready_skin(4)
    shift = np.zeros((4, 2))
    shift[2] = 200 * fF
    touched = run(cal, t0, t0 + cfg.max_touch + 30.0, lambda t: 20 * pF + shift
                  + rng.normal(0, 1 * fF, (4, 2)))
    assert touched[5:100, 2].all() and not touched[:, [0, 1, 3]].any()
    assert not touched[-20:].any()
    assert list(cal.rebaselines) == [0, 0, 1, 0]
    h = cal.health()
    assert h["rebaselines_total"] == 1 and h["rebaselined"] == [[2, 1]]
    assert h["touched"] == 0 and h["ready"] == 4
    # The step that re-baselines reports the element as not ready, with no ΔC.
    cal.tare()
    for k in range(cfg.n_baseline):
        feed(cal, 1000.0 + 0.1 * k, np.full((4, 2), 20 * pF))
    s = feed(cal, 1005.0, 20 * pF + shift)
    assert s.touched[2]
    s = feed(cal, 1005.0 + cfg.max_touch, 20 * pF + shift)
    assert list(cal.rebaselines) == [0, 0, 2, 0]
    assert not s.ready[2] and np.isnan(s.delta[2]).all() and s.ready[[0, 1, 3]].all()


def test_one_low_outlier_does_not_drag_the_baseline():
    cal, t0, rng = ready_skin(4)
    before = cal.baseline
    low = np.full((4, 2), 20 * pF)
    low[1, 0] = 10 * pF  # one reading far below (a glitch, a dropped edge count)
    feed(cal, t0, low)
    assert np.abs(cal.baseline - before).max() < 2 * fF  # unclipped: 330 fF
    touched = run(cal, t0 + 0.1, t0 + 120.0, lambda t: 20 * pF + rng.normal(0, 1 * fF, (4, 2)))
    assert not touched.any()


def test_a_sustained_low_reading_is_still_followed_fast():
    # The reason for tau_negative survives the clip: a baseline taken while something
    # rested on the element recovers within seconds once the reading stays low.
    cal, t0, rng = ready_skin(4, base=21 * pF)
    low = np.full((4, 2), 21 * pF)
    low[0] = 20 * pF
    for t in np.arange(t0, t0 + 15.0, 0.1):
        s = feed(cal, t, low)
    assert abs(s.delta[0, 0]) < cal.config.enter


def test_elements_without_readings_get_the_common_correction():
    # Element 0 is silent while the whole skin steps by +300 fF; it comes back untouched.
    cal, t0, rng = ready_skin(4)
    for t in np.arange(t0, t0 + 60.0, 0.1):
        v = 20 * pF + (t > t0 + 5.0) * 300 * fF + rng.normal(0, 1 * fF, (4, 2))
        v[0] = np.nan
        feed(cal, t, v)
    s = feed(cal, t0 + 60.0, np.full((4, 2), 20 * pF + 300 * fF))
    assert not s.touched.any()
    assert np.abs(s.delta[0]).max() < 5 * fF


def test_a_slow_press_is_reported():
    # 0 → 200 fF over 60 s on one element: drift is slow and bounded, a press is not.
    cal, t0, rng = ready_skin(4)
    press = np.zeros((4, 2))
    press[3] = [200 * fF, 120 * fF]
    touched = run(cal, t0, t0 + 90.0, lambda t: 20 * pF + min(max(t - t0, 0.0) / 60.0, 1.0) * press
                  + rng.normal(0, 1 * fF, (4, 2)))
    assert touched[-300:, 3].all() and not touched[:, :3].any()
    s = feed(cal, t0 + 90.0, 20 * pF + press)
    assert s.delta[3, 0] == pytest.approx(200 * fF, rel=0.15)


def test_tare_of_no_elements_is_a_no_op():
    cal = ready_calibrator(3)
    cal.tare([])
    cal.tare(np.array([], dtype=np.int64))
    assert (cal.state == TRACKING).all()


def test_config_validates_the_new_rules():
    with pytest.raises(ValueError, match="max_drift"):
        CalibrationConfig(max_drift=-1.0)
    with pytest.raises(ValueError, match="common_fraction"):
        CalibrationConfig(common_fraction=1.5)
    with pytest.raises(ValueError, match="negative_after"):
        CalibrationConfig(negative_after=math.nan)


def test_an_untouched_skin_stays_untouched_for_an_hour_of_drift_steps_and_outages():
    # 4×4 skin, 1 h at 5 Hz, all readings generated up front (vectorised):
    # temperature-like drift (±8 % per element), a common drift swinging at up to
    # 5 fF/s, ±300 fF common steps every few minutes, elements silent for 5-120 s at
    # random, 2 % of single readings missing, and rare low glitches.
    rng = np.random.default_rng(2024)
    rate, n = 5.0, 16
    t = np.arange(int(3600 * rate)) / rate
    scale = 1.0 + rng.uniform(-0.08, 0.08, (n, 2))
    temp = 0.4 * pF * t / 3600.0 + 0.15 * pF * np.sin(2 * math.pi * t / 900.0)
    swing = 0.5 * pF * np.sin(2 * math.pi * t / (2 * math.pi * 100.0))  # 5 fF/s peak
    step_times = np.sort(rng.uniform(60.0, 3600.0, 15))
    steps = (rng.choice([-1.0, 1.0], 15) * 300 * fF * (t[:, None] >= step_times)).sum(axis=1)
    v = (20 * pF + temp[:, None, None] * scale + (swing + steps)[:, None, None]
         + rng.normal(0, 1 * fF, (t.size, n, 2)))
    silent = np.zeros((t.size, n), dtype=bool)
    for _ in range(60):
        e = rng.integers(n)
        a = rng.uniform(20.0, 3500.0)
        silent[(t >= a) & (t < a + rng.uniform(5.0, 120.0)), e] = True
    silent |= rng.random((t.size, n)) < 0.02
    v[silent] = np.nan
    glitch = rng.random((t.size, n)) < 2e-4
    v[glitch, 0] -= 5 * pF
    cal = Calibrator(n, 2)
    touched = np.zeros(n, dtype=bool)
    for k in range(t.size):
        touched |= cal.update(t[k], v[k]).touched
    assert not touched.any()
    assert cal.rebaselines.sum() == 0 and cast(int, cal.health()["common_jumps"]) >= 5  # the upward steps
    last = cal.update(3600.0, 20 * pF + temp[-1] * scale + swing[-1] + steps[-1])
    assert np.abs(last.delta).max() < 25 * fF


def test_missing_readings_do_not_restart_the_below_baseline_timer():
    # The fast negative tracker waits for a channel to stay low for negative_after;
    # a missing reading in between is no evidence that it came back up.
    cfg = CalibrationConfig(n_baseline=3, negative_after=1.0, tau_negative=0.5)
    cal = ready_calibrator(4, cfg, base=21 * pF)
    low = np.full((4, 2), 21 * pF)
    low[0] = 20 * pF
    gap = low.copy()
    gap[0] = np.nan
    for k in range(40):  # 4 s: a reading low, then a missing one, alternately
        feed(cal, 1.0 + 0.1 * k, low if k % 2 == 0 else gap)
    s = feed(cal, 5.0, low)
    assert abs(s.delta[0, 0]) < cfg.enter


# ------------------------------------------- small skins: one element far below the rest


def test_one_low_glitch_on_a_two_element_skin_does_not_touch_the_other():
    # With two tracked elements the "median" is their mean: a −5 pF glitch on one
    # used to pull the common offset down by 2.5 pF and report a 2.5 pF press on the
    # other. A reading below −enter is excluded from the common reference just like
    # one above +enter.
    cal, t0, rng = ready_skin(2)
    low = np.full((2, 2), 20 * pF)
    low[0] -= 5 * pF
    s = feed(cal, t0, low)
    assert not s.touched.any()
    assert np.abs(s.delta[1]).max() < 5 * fF
    assert np.abs(cal.common_drift).max() < 5 * fF


def test_tare_during_a_press_on_a_small_skin_does_not_touch_the_other_element():
    # The user tares element 0 while it is pressed; on release it reads 2.2 pF below
    # its baseline until the fast negative tracker has followed it. Meanwhile the
    # other element of the 1×2 skin must stay untouched and read ~0.
    cal, t0, rng = ready_skin(2)
    press = np.zeros((2, 2))
    press[0] = [2.2 * pF, 0.6 * pF]
    run(cal, t0, t0 + 2.0, lambda t: 20 * pF + press)
    cal.tare([0])
    run(cal, t0 + 2.0, t0 + 10.0, lambda t: 20 * pF + press)
    assert cal.ready.all()
    touched = run(cal, t0 + 10.0, t0 + 40.0, lambda t: 20 * pF + rng.normal(0, 1 * fF, (2, 2)))
    assert not touched[:, 1].any()
    s = feed(cal, t0 + 40.0, np.full((2, 2), 20 * pF))
    assert np.abs(s.delta).max() < 25 * fF  # element 0 followed back by the fast tracker


def test_a_common_step_down_on_a_two_element_skin_is_still_drift():
    # The counterpart of the rule above: when (nearly) all tracked elements fall
    # together it is a common change, taken in the same step.
    cal, t0, rng = ready_skin(2)
    before = cal.health()["common_jumps"]
    touched = run(cal, t0, t0 + 30.0, lambda t: 20 * pF - (t > t0 + 5.0) * 300 * fF
                  + rng.normal(0, 1 * fF, (2, 2)))
    assert not touched.any()
    s = feed(cal, t0 + 30.0, np.full((2, 2), 20 * pF - 300 * fF))
    assert np.abs(s.delta).max() < 5 * fF
    assert cal.common_drift == pytest.approx([-300 * fF, -300 * fF], abs=5 * fF)
    assert cal.health()["common_jumps"] == before + 1


def test_per_element_times_may_be_nan_where_there_is_no_reading():
    # A daemon that builds one time per element naturally leaves NaN where an
    # element gave no reading, as it does for the values; that frame used to be
    # refused whole ("time must be finite"), blinding every other element.
    cfg = CalibrationConfig(n_baseline=3)
    a, b = ready_calibrator(3, cfg), ready_calibrator(3, cfg)
    v = np.full((3, 2), 20 * pF)
    v[1] = np.nan
    v[0] += 300 * fF  # a press on element 0
    sa = a.update(np.array([1.0, np.nan, 1.0]), v)
    sb = b.update(1.0, v)
    np.testing.assert_array_equal(sa.delta, sb.delta)
    np.testing.assert_array_equal(sa.touched, sb.touched)
    assert sa.touched[0] and np.isnan(sa.delta[1]).all()
    for bad in ([np.nan, 2.0, 2.0], [2.0, np.inf, 2.0]):  # a reading needs a time; inf is no time
        with pytest.raises(ValueError, match="time"):
            a.update(np.array(bad), np.full((3, 2), 20 * pF))
    with pytest.raises(ValueError, match="time"):
        a.update(np.nan, np.full((3, 2), np.nan))  # a scalar time must be a time


# ------------------------------------ presses over (nearly) the whole skin: reported


@pytest.mark.parametrize("rows, diameter", [(2, 0.040), (3, 0.200), (4, 0.240)])
def test_a_press_over_the_whole_skin_is_reported_as_a_common_jump(rows, diameter):
    # The documented price of the common-mode rule: a press that lifts (nearly) every
    # tracked element alike in one step — any press centred on the junction of a 2×2
    # skin, a plate over a whole 3×3 or 4×4 — is taken for a common step and not
    # touched. It must
    # not vanish silently: the step says so and health() keeps when, how much and
    # on how many elements (the size alone does not tell it from a supply step).
    skin = grid_layout(rows, rows)
    c = 0.5 * (rows - 1) * 0.040
    d1, d2 = skin_response(skin, [[c, c, 5.0, diameter]])
    cal, t0, rng = ready_skin(skin.n)
    quiet = feed(cal, t0, np.full((skin.n, 2), 20 * pF))
    assert not quiet.common_jump and cal.health()["last_common_jump"] is None
    s = feed(cal, t0 + 0.1, 20 * pF + np.stack([d1, d2], axis=1))
    assert s.common_jump
    last = cal.health()["last_common_jump"]
    assert last["t"] == pytest.approx(t0 + 0.1)
    assert last["elements"] == skin.n and last["tracked"] == skin.n
    assert last["offset_change"][0] == pytest.approx(float(np.median(d1)), rel=0.01)
    assert last["offset_change"][0] > 100 * fF
    nxt = feed(cal, t0 + 0.2, 20 * pF + np.stack([d1, d2], axis=1))
    assert not nxt.common_jump and cal.health()["last_common_jump"] == last


# ------------------------------------------------ an element back from a long outage


def test_an_element_back_from_hours_of_silence_is_not_a_phantom_touch():
    # Element 3's bridge is silent for 2 h while its own drift (what the common mode
    # does not remove) moves it 150 fF, well within max_drift·2 h = 7.2 pF. It used
    # to come back "touched" and stay so for max_touch (10 min of phantom contact)
    # before being re-baselined. The tracker's rate bound holds across the gap: a
    # change the element could have drifted while silent is drift.
    cal, t0, rng = ready_skin(4)
    own = np.zeros((4, 2))
    silent = np.full((4, 2), 20 * pF)
    silent[3] = np.nan
    run(cal, t0, t0 + 5.0, lambda t: 20 * pF + rng.normal(0, 1 * fF, (4, 2)))
    run(cal, t0 + 5.0, t0 + 7205.0, lambda t: silent, rate=0.1)
    own[3] = [150 * fF, 90 * fF]
    touched = run(cal, t0 + 7205.0, t0 + 7265.0, lambda t: 20 * pF + own + rng.normal(0, 1 * fF, (4, 2)))
    assert not touched.any()
    s = feed(cal, t0 + 7265.0, 20 * pF + own)
    assert np.abs(s.delta).max() < 5 * fF
    assert cal.health()["outage_catchups"] == 1 and cal.rebaselines.sum() == 0


def test_a_press_larger_than_the_drift_an_outage_allows_is_reported_whole():
    # 60 s of silence allow 60 fF of drift: a 2.2 pF press present when the element
    # comes back is a touch, reported at its full size (no partial catch-up).
    cal, t0, rng = ready_skin(4)
    silent = np.full((4, 2), 20 * pF)
    silent[3] = np.nan
    run(cal, t0, t0 + 60.0, lambda t: silent)
    press = np.zeros((4, 2))
    press[3] = [2.2 * pF, 0.6 * pF]
    s = feed(cal, t0 + 60.0, 20 * pF + press)
    assert s.touched[3] and not s.touched[:3].any()
    assert s.delta[3, 0] == pytest.approx(2.2 * pF, abs=5 * fF)
    assert cal.health()["outage_catchups"] == 0


def test_counts_in_the_config_refuse_booleans_with_a_value_error():
    # n_baseline=True escaped as a TypeError from numpy; min_common=True and
    # Calibrator(True) were taken as 1.
    for kw in ({"n_baseline": True}, {"min_common": True}, {"n_baseline": np.True_}):
        with pytest.raises(ValueError, match=next(iter(kw))):
            CalibrationConfig(**kw)
    for args in ((True, 2), (2, True), ("3", 2)):
        with pytest.raises(ValueError, match="n_"):
            Calibrator(*args)
    assert Calibrator(np.int64(3), np.int32(2), CalibrationConfig(n_baseline=np.int16(5))).n_elements == 3  # type: ignore[arg-type]  # numpy integers, on purpose


def test_readings_in_picofarads_with_thresholds_in_farads_are_refused():
    # Counter readings in pF fed to the default (farad) config: the quantised
    # readings give a MAD of 0, so enter stays 5e-14 "pF" and one count of flicker
    # is a touch — a quiet 2×2 skin was touched in a quarter of all element-steps.
    # A reading 10⁹ times its touch threshold is a unit mix-up, refused up front.
    cal = Calibrator(4, 2)
    v = np.full((4, 2), 15.67)
    with pytest.raises(ValueError, match="picofarads"):
        cal.update(0.0, v)
    assert (cal.state == COLLECTING).all() and cal.health()["collecting"] == 4
    assert not cal.update(0.0, v * pF).ready.any()  # farads: fine
    same_unit = Calibrator(4, 2, CalibrationConfig(enter=0.05, leave=0.025, max_drift=1e-3))
    same_unit.update(0.0, v)  # picofarads throughout: fine
    blind = Calibrator(4, 2, CalibrationConfig(enter=0.0, leave=0.0))
    blind.update(0.0, v)  # no absolute threshold: nothing to compare against


@pytest.mark.parametrize("rows, diameter, force", [(3, 0.080, 5.0), (3, 0.120, 20.0), (4, 0.160, 20.0)])
def test_an_uneven_palm_is_contacts_not_a_common_step_and_leaves_no_phantom(rows, diameter, force):
    # A palm centred on a 3×3 or 4×4 skin lifts every element past enter, but
    # unevenly (centre ≫ corners). It used to be taken for a common step: at most 4
    # elements touched during the press, and the fast negative tracker followed the
    # corners down to "below the offset", so after the release 4 elements stayed
    # touched (0.4-0.9 pF) until max_touch. A common step moves every element alike;
    # one that leaves the tracked elements spread beyond enter + common_spread·|step|
    # is contacts.
    skin = grid_layout(rows, rows)
    c = 0.5 * (rows - 1) * 0.040
    d1, d2 = skin_response(skin, [[c, c, force, diameter]])
    press = np.stack([d1, d2], axis=1)
    assert (d1 > 50 * fF).all()  # every element lifted past enter
    cal, t0, rng = ready_skin(skin.n)
    during = run(cal, t0, t0 + 60.0, lambda t: 20 * pF + press + rng.normal(0, 1 * fF, (skin.n, 2)))
    assert during[5:].all() and cal.health()["common_jumps"] == 0
    after = run(cal, t0 + 60.0, t0 + 120.0, lambda t: 20 * pF + rng.normal(0, 1 * fF, (skin.n, 2)))
    assert not after[-100:].any()  # released, hold-off over: nothing latched
    s = feed(cal, t0 + 120.0, np.full((skin.n, 2), 20 * pF))
    assert np.abs(s.delta).max() < 10 * fF


@pytest.mark.parametrize("size", [300 * fF, 1 * pF, 3 * pF, -3 * pF])
def test_large_common_steps_that_move_the_elements_alike_are_still_drift(size):
    # The "alike" condition scales with the step: elements that follow it to ±1 %
    # (what is left stays below enter) see a common step at any size, up or down,
    # also with a press held meanwhile.
    cal, t0, rng = ready_skin(16)
    scale = 1.0 + rng.uniform(-0.01, 0.01, (16, 2))
    press = np.zeros((16, 2))
    press[5] = [2.2 * pF, 0.6 * pF]
    touched = run(cal, t0, t0 + 60.0, lambda t: 20 * pF + press + (t > t0 + 5.0) * size * scale
                  + rng.normal(0, 1 * fF, (16, 2)))
    assert touched[:, 5].all() and not np.delete(touched, 5, axis=1).any()
    s = feed(cal, t0 + 60.0, 20 * pF + press + size * scale)
    assert s.delta[5, 0] == pytest.approx(2.2 * pF, rel=0.1)
    assert cal.health()["common_jumps"] >= 1


def test_common_spread_is_validated_and_inf_restores_the_fraction_rule_alone():
    for bad in (-0.1, math.nan):
        with pytest.raises(ValueError, match="common_spread"):
            CalibrationConfig(common_spread=bad)
    skin = grid_layout(3, 3)
    d1, d2 = skin_response(skin, [[0.04, 0.04, 5.0, 0.080]])
    cal, t0, rng = ready_skin(9, CalibrationConfig(common_spread=math.inf))
    s = feed(cal, t0, 20 * pF + np.stack([d1, d2], axis=1))
    assert s.common_jump and s.touched.sum() <= 4  # the palm taken for a common step


def test_adopt_carries_elements_over_to_a_grown_calibrator() -> None:
    cfg = CalibrationConfig(n_baseline=3)
    old = Calibrator(2, 2, cfg)
    for k in range(3):
        old.update(float(k), np.array([[1.0, 2.0], [3.0, 4.0]]) * 1e-12)
    new = Calibrator(3, 2, cfg)
    new.adopt(old, np.array([2, 0]), np.array([0, 1]))
    assert np.allclose(new.baseline[[2, 0]], np.array([[1.0, 2.0], [3.0, 4.0]]) * 1e-12, rtol=1e-9, atol=0)
    assert new.ready.tolist() == [True, False, True]
    with pytest.raises(ValueError, match="same configuration"):
        Calibrator(3, 2, CalibrationConfig(n_baseline=4)).adopt(old, np.array([0]), np.array([0]))


# -- a press held past max_touch, an element drifting by itself (ContactSurface) -------------

def _surface_calibrator(n: int, max_touch: float = 10.0) -> Calibrator:
    from cellbridge.tactile import ContactSurface

    cfg = CalibrationConfig(n_baseline=3, max_touch=max_touch)
    cal = Calibrator(n, 2, cfg, is_contact=ContactSurface(ElementParams(side=0.04), noise=2 * fF))
    for k in range(3):
        feed(cal, 0.1 * k, np.full((n, 2), 20 * pF))
    return cal


def test_contact_surface_holds_every_press_and_refuses_one_layer_alone():
    from cellbridge.tactile import ContactSurface

    p = ElementParams(side=0.04)
    surf = ContactSurface(p, noise=2 * fF)
    lay = grid_layout(3, 3)
    for force in (0.05, 0.3, 1.0, 3.0, 15.0, 50.0):
        for d in (0.008, 0.02, 0.03):
            for at in ((0.04, 0.04), (0.06, 0.05)):  # inside one element, straddling four
                d1, d2 = skin_response(lay, [(*at, force, d)], p)
                dc = np.stack([d1, d2], axis=1)[d1 > 1 * fF]
                assert surf(dc).all(), (force, d, at)
    assert not surf(np.array([[0.0, 300 * fF], [300 * fF, 0.0], [300 * fF, 50 * fF], [np.nan, 1 * fF]])).any()
    assert not surf(np.array([[1.1 * p.area * p.g1_max, 1e-9]])).any()  # more than the element saturated
    # an ADC front end's measured noise (0.2 pF steps) widens the tolerance of its readings
    assert surf(np.array([[0.0, 300 * fF]]), np.array([[200 * fF, 200 * fF]])).all()
    with pytest.raises(ValueError):
        surf(np.zeros(3))
    with pytest.raises(ValueError):
        ContactSurface(p, noise=-1.0)


def test_a_press_held_past_max_touch_is_kept_while_its_reading_is_a_contacts():
    """Main re-baselined every touch at max_touch: a press held for an hour vanished."""
    p = ElementParams(side=0.04)
    d1, d2 = skin_response(grid_layout(1, 1), [(0.0, 0.0, 3.0, 0.02)], p)
    cal = _surface_calibrator(2)
    press = np.array([[20 * pF + d1[0], 20 * pF + d2[0]], [20 * pF, 20 * pF]])
    t = 1.0
    while t < 65.0:
        s = feed(cal, t, press)
        assert s.touched[0] and s.rebaselined is None, t
        t += 0.1
    assert s.delta[0] == pytest.approx([d1[0], d2[0]], rel=1e-9)
    assert cal.holds[0] == 6 and cal.rebaselines.sum() == 0 and cal.health()["holds_total"] == 6


def test_a_touch_whose_reading_left_the_surface_is_rebaselined_at_max_touch_and_said():
    cal = _surface_calibrator(1)
    feed(cal, 1.0, [[20 * pF + 200 * fF, 20 * pF + 100 * fF]])  # a press's ratio: touched
    assert cal.touched[0]
    t, said = 1.1, []
    while t < 12.0:
        s = feed(cal, t, [[20 * pF + 900 * fF, 20 * pF + 100 * fF]])  # C1 alone moved on: ratio 9
        if s.rebaselined is not None:
            said.append((round(t, 1), s.rebaselined.tolist()))
        t += 0.1
    assert len(said) == 1 and 11.0 <= said[0][0] <= 11.1 and said[0][1] == [True]  # touched at 1 s
    assert cal.rebaselines[0] == 1 and cal.holds[0] == 0


@pytest.mark.parametrize("channel", [0, 1])
def test_one_layer_drifting_is_never_touched_and_is_followed(channel):
    """5 fF/s on one channel, five times max_drift: main touched it once it passed enter."""
    cal = _surface_calibrator(3, max_touch=600.0)
    t, worst = 0.3, 0.0
    while t < 120.0:
        v = np.full((3, 2), 20 * pF)
        v[1, channel] += 5 * fF * t
        s = feed(cal, t, v)
        assert not s.touched.any(), t
        if t > 60.0:
            worst = max(worst, float(np.abs(s.delta[1]).max()))
        t += 0.1
    assert worst < 70 * fF and cal.drifting.sum() <= 1


def test_without_a_surface_test_max_touch_behaves_as_before():
    cfg = CalibrationConfig(n_baseline=3, max_touch=10.0)
    cal = ready_calibrator(1, cfg)
    s = None
    for k in range(120):
        s = feed(cal, 1.0 + 0.1 * k, [[20 * pF + 200 * fF, 20 * pF + 100 * fF]])
        if s.rebaselined is not None:
            break
    assert s is not None and s.rebaselined is not None and cal.rebaselines[0] == 1


@pytest.mark.parametrize("seed", [1, 2])
def test_a_held_press_does_not_carry_a_ratchet_of_the_common_offset(seed):
    """A 3×3 skin read at 10 Hz as the daemon feeds it: each frame's readings arrive in
    two to four groups, one step each. The corner's C2 drifts by itself at 2 fF/s (its
    clipped tracker lags by up to ``enter``) while the centre is pressed. On main the
    offset climbed 9–10 fF in 5 min with no drift in the world (the tracked baselines
    followed each step's biased median down, lifting the next one), the press's frozen
    baseline carried it (35 fF off on C2 at worst), and it grows with the hold (140 fF in
    an hour). Now the press's baseline stays within 4 fF of the element at rest from 60 s
    on (1.9 fF at worst: a median of the few elements of a step), and the offset near
    zero."""
    from cellbridge.tactile import ContactSurface

    rng = np.random.default_rng(seed)
    n, pressed, drifting = 9, 4, 8
    press = np.array([2.22 * pF, 1.37 * pF])
    cal = Calibrator(n, 2, CalibrationConfig(), is_contact=ContactSurface(ElementParams(side=0.04), 2 * fF))
    worst = np.zeros(2)
    for k in range(3000):
        t = 0.1 * k
        truth = np.tile([8 * pF, 6 * pF], (n, 1))
        truth[drifting, 1] += 2 * fF * t
        if t >= 10.0:
            truth[pressed] += press
        v = np.round((truth + rng.normal(0.0, 0.5 * fF, (n, 2))) / (0.83 * fF)) * 0.83 * fF  # counter steps
        groups = np.split(rng.permutation(n), np.sort(rng.choice(np.arange(1, n), rng.integers(1, 4), replace=False)))
        for j, g in enumerate(groups):
            x = np.full((n, 2), np.nan)
            x[g] = v[g]
            s = feed(cal, t + 0.001 * j, x)
            if t > 60.0 and pressed in g:
                assert s.touched[pressed]
                worst = np.maximum(worst, np.abs(cal.baseline[pressed] - [8 * pF, 6 * pF]))
    assert np.all(worst < 4 * fF), worst / fF
    assert np.all(np.abs(cal.common_drift) < 1 * fF), cal.common_drift / fF
    assert not cal.touched[drifting]


def test_is_contact_is_asked_only_of_readings_it_decides_and_answers_alike():
    """A step asks ``is_contact`` only of readings above ``leave`` or of touched elements (a
    quiet skin of a thousand elements asks nothing); the steps come out as when every live
    reading is asked (a wrapper that asks all rows and answers for the rows given)."""
    from cellbridge.tactile import ContactSurface

    surf = ContactSurface(ElementParams(side=0.04), noise=2 * fF)
    asked: list[int] = []

    def counting(delta, noise):
        asked.append(delta.shape[0])
        return surf(delta, noise)

    cfg = CalibrationConfig(n_baseline=3, max_touch=2.0)
    n = 40
    a = Calibrator(n, 2, cfg, is_contact=counting)
    b = Calibrator(n, 2, cfg, is_contact=surf)
    # b asks of every live reading (a finite ΔC), as each step did before it asked fewer
    def every_live(rows: np.ndarray, delta: np.ndarray) -> np.ndarray | None:
        return Calibrator._contact_readings(b, np.asarray(np.isfinite(delta).all(axis=1)), delta)

    b._contact_readings = every_live  # type: ignore[method-assign,assignment]
    rng = np.random.default_rng(3)
    base = np.full((n, 2), 20 * pF)
    for k in range(3):
        feed(a, 0.1 * k, base)
        feed(b, 0.1 * k, base)
    asked.clear()
    quiet = base + rng.normal(0, 1 * fF, (n, 2))
    feed(a, 0.3, quiet)
    feed(b, 0.3, quiet)
    assert asked == []  # quiet: nothing to decide
    for k in range(4, 120):
        v = base + rng.normal(0, 1 * fF, (n, 2))
        v[k % n] += [200 * fF, 100 * fF]  # a press's ratio
        v[(3 * k) % n, 0] += 900 * fF  # one layer alone: drift
        v[n - 1] += [200 * fF, 100 * fF] if k < 60 else [900 * fF, 100 * fF]  # held; then no contact's
        if k % 7 == 0:
            v[rng.integers(n)] = np.nan
        sa, sb = feed(a, 0.1 * k, v), feed(b, 0.1 * k, v)
        assert np.array_equal(sa.delta, sb.delta, equal_nan=True) and np.array_equal(sa.touched, sb.touched)
        assert (sa.rebaselined is None) == (sb.rebaselined is None)
    assert 0 < max(asked) < n
    assert a.rebaselines[n - 1] >= 1 and a.holds[n - 1] >= 1  # max_touch both ways, alike
    assert np.array_equal(a.rebaselines, b.rebaselines) and np.array_equal(a.holds, b.holds)


@pytest.mark.parametrize("seed", range(4))
def test_one_time_for_all_steps_as_that_time_per_element(seed):
    """A scalar time (the daemon's every step, checked as a number) and the same time given
    per element (checked as an array) step alike, bit for bit: presses, releases, readings
    below the baseline, one layer drifting, elements without a reading, a common step."""
    from cellbridge.tactile import ContactSurface

    rng = np.random.default_rng(seed)
    n = 40
    cfg = CalibrationConfig(n_baseline=5, holdoff=0.05, max_touch=0.5, negative_after=0.05)
    surface = ContactSurface(ElementParams(), 1 * fF)
    one, per = (Calibrator(n, 2, cfg, is_contact=surface) for _ in range(2))
    base = rng.uniform(15, 25, (n, 2)) * pF
    press = np.zeros((n, 2))
    for k in range(300):
        t = 0.01 * k
        if k % 40 == 20:  # presses on a few elements, a light one, one layer drifting alone
            rows = rng.choice(n, 4, replace=False)
            press[:] = 0.0
            press[rows[0]] = [300 * fF, 120 * fF]
            press[rows[1]] = [60 * fF, 10 * fF]
            press[rows[2], 0] = 200 * fF
            press[rows[3]] = [-150 * fF, -150 * fF]
        if k % 40 == 35:
            press[:] = 0.0
        v = base + press + rng.normal(0, 2 * fF, (n, 2)) + (30 * fF if k > 250 else 0.0)
        v[rng.random(n) < 0.1] = np.nan
        a, b = one.update(t, v), per.update(np.full(n, t), v)
        assert np.array_equal(a.delta, b.delta, equal_nan=True), k
        assert np.array_equal(a.touched, b.touched) and np.array_equal(a.ready, b.ready), k
        assert a.common_jump == b.common_jump, k
        assert (a.rebaselined is None) == (b.rebaselined is None), k
        if a.rebaselined is not None and b.rebaselined is not None:
            assert np.array_equal(a.rebaselined, b.rebaselined), k
    for name in Calibrator._PER_ELEMENT + ("_common",):
        assert np.array_equal(getattr(one, name), getattr(per, name), equal_nan=True), name
    assert one.health() == per.health()
    with pytest.raises(ValueError, match="backwards"):
        one.update(t - 1.0, base)
    with pytest.raises(ValueError, match="finite"):
        one.update(math.inf, base)
