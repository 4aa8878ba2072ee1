"""Inverse (ΔC1, ΔC2) → (F, S): accuracy where valid, refusal where not.

Ambiguity is checked against brute force: the low-pressure twin of a reading is found
here by bisection on the ratio, independently of the inverse's tables.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from cellbridge.tactile import (
    DEFAULT_NOISE,
    ElementParams,
    InverseStatus,
    branch_info,
    forward,
    inverse,
    ratio,
    ratio_slope,
    sensitivity,
    solve,
)
from hypothesis import given, settings
from hypothesis import strategies as st

P = ElementParams()
INFO = branch_info()

F_GRID = np.linspace(1.0, 20.0, 39)
D_GRID = np.linspace(10e-3, 40e-3, 31)


def disk_area(d):
    return np.pi * np.asarray(d) ** 2 / 4


def brute_ratio(sigma: float) -> float:
    g1, g2 = sensitivity(sigma)
    return float(g1 / g2)


def low_twin_sigma(r: float) -> float | None:
    """σ on the rising branch (0, σ_peak) with ratio r, by bisection; None if none."""
    lo, hi = 1e-9, INFO.sigma_peak
    if not brute_ratio(lo) <= r <= brute_ratio(hi):
        return None
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if brute_ratio(mid) < r:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def test_branch_landmarks_match_design():
    # DESIGN: "rises from ≈1.9 to ≈2.3 before falling".
    assert INFO.ratio_zero == pytest.approx(1.875, rel=1e-12)
    assert INFO.ratio_peak == pytest.approx(2.3, abs=0.05)
    assert INFO.ratio_inf == pytest.approx(0.6, rel=1e-12)
    s = np.geomspace(10, 1e6, 4001)
    r = np.array([brute_ratio(x) for x in s])
    i = int(np.argmax(r))
    assert INFO.sigma_peak == pytest.approx(s[i], rel=0.01)
    assert INFO.ratio_peak == pytest.approx(r.max(), rel=1e-6)
    assert brute_ratio(INFO.sigma_unique) == pytest.approx(INFO.ratio_zero, rel=1e-6)
    assert INFO.sigma_unique > INFO.sigma_peak
    # The analytic slope agrees with a finite difference of the ratio.
    for x in (100.0, 2e3, 5e3, 3e4, 2e5):
        h = 1e-5
        fd = (math.log(brute_ratio(x * (1 + h))) - math.log(brute_ratio(x * (1 - h)))) / (
            math.log(1 + h) - math.log(1 - h))
        assert float(ratio_slope(x)) == pytest.approx(fd, abs=1e-6)
    assert float(ratio(0.0)) == INFO.ratio_zero


@pytest.mark.parametrize("noise", [0.0, DEFAULT_NOISE])
def test_round_trip_over_the_target_grid(noise):
    F, D = np.meshgrid(F_GRID, D_GRID, indexing="ij")
    c1, c2 = forward(F, disk_area(D))
    f, s, ok = inverse(c1, c2, noise=noise)
    assert ok.shape == F.shape
    # Targets: F within 1 %, D within 0.2 mm; the solver does far better.
    d_est = 2 * np.sqrt(s[ok] / np.pi)
    assert np.max(np.abs(f[ok] / F[ok] - 1)) < 1e-10
    assert np.max(np.abs(d_est - D[ok])) < 1e-9
    # Invalid entries never carry a number.
    assert np.all(np.isnan(f[~ok])) and np.all(np.isnan(s[~ok]))
    # Most of the grid is valid, and along each D the valid forces form one interval
    # reaching up to 20 N: the refusal is a low-force threshold, not scattered holes.
    assert ok.mean() > 0.85
    for j in range(D.shape[1]):
        col = ok[:, j]
        first = int(np.argmax(col))
        assert col.any() and col[first:].all()
    # The paper: unique "when F is larger than a threshold, now around 1.0 N" — for
    # its smaller stimulators (D = 10 mm) everything from 1 N on is valid here.
    assert ok[:, 0].all()


def test_low_pressure_contacts_are_never_valid():
    # Every reading produced by a rising-branch contact has a falling-branch twin
    # with a smaller area: it is ambiguous by construction and must be refused.
    sigma = np.geomspace(1.0, 0.995 * INFO.sigma_peak, 300)
    area = np.geomspace(1e-6, P.area, 200)
    S, A = np.meshgrid(sigma, area, indexing="ij")
    c1, c2 = forward(S * A, A)
    for noise in (0.0, DEFAULT_NOISE):
        r = solve(c1, c2, noise=noise)
        assert not r.valid.any()
        # … and for the reason that matters, where the reading is above the noise.
        strong = (c1 > 3 * noise) & (c2 > 3 * noise)
        assert np.all((r.status[strong] & InverseStatus.AMBIGUOUS) != 0)


@settings(max_examples=200, deadline=None)
@given(
    c1=st.floats(min_value=1e-15, max_value=30e-12),
    r=st.floats(min_value=0.55, max_value=2.4),
)
def test_valid_answers_are_unique_and_consistent(c1, r):
    c2 = c1 / r
    res = solve(c1, c2, noise=0.0)
    if not res.valid:
        assert math.isnan(float(res.force)) and math.isnan(float(res.area))
        return
    f, s = float(res.force), float(res.area)
    assert 0 < s <= P.area * (1 + 1e-9)
    # Forward of the answer reproduces the reading.
    b1, b2 = forward(f, min(s, P.area))
    assert float(b1) == pytest.approx(c1, rel=1e-9, abs=0)
    assert float(b2) == pytest.approx(c2, rel=1e-9, abs=0)
    # It is on the falling branch, and the rising-branch twin (if any) would need
    # an area beyond the element.
    assert f / s > INFO.sigma_peak
    twin = low_twin_sigma(r)
    if twin is not None:
        g1_twin, _ = sensitivity(twin)
        assert c1 / float(g1_twin) > P.area


def test_status_reasons():
    a = disk_area(0.02)
    good1, good2 = forward(10.0, a)
    amb1, amb2 = forward(0.3, a)  # σ ≈ 950 Pa, rising branch
    sat1, sat2 = forward(1000.0, 1e-4)  # σ = 1e7 Pa: ratio flat
    pk1, pk2 = forward(INFO.sigma_peak * 1e-4 * 1.01, 1e-4)  # just past the peak
    c1 = np.array([good1, np.nan, -1e-13, 0.0, 1e-12, 1e-12, amb1, sat1, 40e-12, pk1])
    c2 = np.array([good2, 1e-12, 1e-12, 1e-12, 1e-12 / 2.5, 1e-12 / 0.5, amb2, sat2,
                   40e-12 / 1.7, pk2])
    r = solve(c1, c2, noise=0.0)
    st_ = [InverseStatus(int(x)) for x in r.status]
    assert st_[0] == InverseStatus.OK and r.valid[0]
    assert InverseStatus.NONFINITE in st_[1]
    assert InverseStatus.BELOW_NOISE in st_[2] and InverseStatus.BELOW_NOISE in st_[3]
    assert st_[4] == InverseStatus.NO_SOLUTION  # ratio above the peak
    assert st_[5] == InverseStatus.NO_SOLUTION  # ratio below saturation's 0.6
    assert InverseStatus.AMBIGUOUS in st_[6]
    assert InverseStatus.ILL_CONDITIONED in st_[7]
    assert InverseStatus.AREA_EXCEEDS in st_[8]
    assert InverseStatus.ILL_CONDITIONED in st_[9]
    assert r.valid.sum() == 1
    assert np.isnan(r.force[1:]).all() and np.isnan(r.area[1:]).all()
    # Below the noise floor: a real but tiny reading is refused only when noise is set.
    t1, t2 = forward(1e-3, 1e-7)  # σ = 10 kPa on 0.1 mm², ≈ 1e-16 F
    assert solve(t1, t2, noise=0.0).valid
    assert solve(t1, t2, noise=1e-15).status == InverseStatus.BELOW_NOISE


def test_more_noise_never_widens_the_valid_region():
    F, D = np.meshgrid(np.linspace(0.2, 25, 80), np.linspace(5e-3, 45e-3, 60), indexing="ij")
    c1, c2 = forward(F, disk_area(D))
    prev = None
    for noise in (0.0, 1e-15, 5e-15, 2e-14, 1e-13):
        ok = solve(c1, c2, noise=noise).valid
        if prev is not None:
            assert not (ok & ~prev).any()
        prev = ok
    assert prev is not None and prev.any()


def test_predicted_noise_matches_monte_carlo():
    rng = np.random.default_rng(7)
    f0, d0 = 8.0, 0.025
    c1, c2 = forward(f0, disk_area(d0))
    noise = 5e-15
    n = 40000
    res = solve(c1, c2, noise=noise)
    assert res.valid
    m = solve(c1 + rng.normal(0, noise, n), c2 + rng.normal(0, noise, n), noise=0.0)
    assert m.valid.all()
    d_est = 2 * np.sqrt(m.area / np.pi)
    assert np.std(m.force) == pytest.approx(float(res.force_rms), rel=0.05)
    assert np.std(d_est) == pytest.approx(float(res.diameter_rms), rel=0.05)


def test_shapes_and_broadcasting():
    c1, c2 = forward(np.array([5.0, 10.0]), disk_area(0.02))
    f, s, ok = inverse(c1[:, None], c2[:, None] * np.ones((1, 3)))
    assert f.shape == s.shape == ok.shape == (2, 3)
    f0, s0, ok0 = inverse(float(c1[0]), float(c2[0]))
    assert np.ndim(f0) == 0 and bool(ok0)
    assert float(f0) == pytest.approx(5.0, rel=1e-9)


def test_other_element_parameters():
    q = ElementParams(E1=3e3, E2=30e3, d1=6e-3, d10=1.5e-3, side=0.05)
    F, D = np.meshgrid(np.linspace(1, 20, 20), np.linspace(10e-3, 50e-3, 15), indexing="ij")
    c1, c2 = forward(F, disk_area(D), q)
    f, s, ok = inverse(c1, c2, q, noise=0.0)
    assert ok.mean() > 0.5
    assert np.allclose(f[ok], F[ok], rtol=1e-8, atol=0)
    # A stiffer upper layer gives no falling branch: the inverse says so clearly.
    with pytest.raises(ValueError, match="falling branch"):
        inverse(1e-12, 1e-12, ElementParams(E1=30e3, E2=4.8e3))


def test_option_validation():
    with pytest.raises(ValueError, match="noise"):
        inverse(1e-12, 1e-12, noise=-1.0)
    with pytest.raises(ValueError):
        solve(1e-12, 1e-12, max_error=0.0)


@pytest.mark.parametrize("c1, c2", [(1e308, 1e-300), (1e300, 1e300), (-1e308, 1e308), (1e-320, 1e308)])
def test_huge_or_tiny_inputs_warn_nothing_and_are_invalid(c1, c2):
    # Overflow inside the inverse is expected for garbage; it must not leak out as a
    # RuntimeWarning (an error under ``-W error``), and the answer must be invalid.
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = solve(np.array([c1, 1e-12]), np.array([c2, 1e-12]))
    assert not r.valid[0] and np.isnan(r.force[0])


def test_the_compiled_inverse_gives_solves_answers():
    """The contact estimator's compiled inverse (issue 17, point 21: numpy's per-call
    overhead was a third of a frame) follows the same rules as solve()."""
    from cellbridge.tactile.inverse_kernel import solve_compiled
    from cellbridge.tactile.inversion import solve

    rng = np.random.default_rng(0)
    n = 50_000
    c1 = 10 ** rng.uniform(-16, -10, n)
    c2 = c1 / rng.uniform(0.3, 2.5, n)
    c1[:100], c2[100:200], c1[200:300], c2[300:400], c1[400:500] = np.nan, -1e-13, 0.0, np.inf, 1e308
    for noise in (0.0, 7e-16, 1e-14):
        a, b = solve(c1, c2, noise=noise), solve_compiled(c1, c2, noise=noise)
        assert np.array_equal(a.status, b.status)
        for name in ("force", "area", "pressure", "force_rms", "diameter_rms"):
            x, y = getattr(a, name), getattr(b, name)
            assert np.array_equal(np.isnan(x), np.isnan(y))
            ok = ~np.isnan(x)
            assert np.allclose(x[ok], y[ok], rtol=1e-10, atol=0.0), name


def test_the_compiled_inverse_takes_solves_keywords_and_no_others():
    """solve_compiled takes solve's keyword defaults from solve itself; a misspelt
    option is refused by name, not ignored or reported against a private helper."""
    from cellbridge.tactile.inverse_kernel import solve_compiled
    from cellbridge.tactile.inversion import solve

    c1, c2 = forward(5.0, 4e-4)
    a, b = solve(c1, c2, k_sigma=2.0), solve_compiled(c1, c2, k_sigma=2.0)
    assert a.status == b.status and a.force == pytest.approx(b.force, rel=1e-10)
    with pytest.raises(TypeError, match=r"solve_compiled\(\).*\['max_eror'\]"):
        solve_compiled(c1, c2, max_eror=0.1)
