"""Forward model of one element: eq. 2 solved in closed form, eq. 3 for a disk.

Expected values are derived here independently of the implementation: eq. 2 is
evaluated forwards (σ from λ), roots are found by bisection, and eq. 3 is integrated
numerically over a grid of the element.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from cellbridge.tactile import (
    EPS0,
    ElementParams,
    capacitance,
    compression,
    forward,
    rest_capacitance,
    sensitivity,
)
from hypothesis import given, settings
from hypothesis import strategies as st

P = ElementParams()


def approx(expected, rel=1e-12, abs=0.0):
    """pytest.approx without its default 1e-12 absolute slack (our values are farads)."""
    return pytest.approx(expected, rel=rel, abs=abs)


def sigma_of_lambda(lam: float, E: float) -> float:
    """Eq. 2 as written in the paper."""
    return E / 3.0 * (1.0 / lam - lam * lam)


def sigma_of_compression(dd: np.ndarray, E: float, d: float, d0: float) -> np.ndarray:
    """Eq. 2 evaluated from x = Δd/(d − d0) = 1 − λ without cancellation.

    1/λ − λ² = (1 − λ³)/λ and 1 − λ³ = x(3 − 3x + x²), so σ = E·x(3 − 3x + x²)/(3(1 − x)).
    """
    x = dd / (d - d0)
    return E * x * (3.0 - 3.0 * x + x * x) / (3.0 * (1.0 - x))


def lambda_bisect(sigma: float, E: float) -> float:
    """Root of eq. 2 in (0, 1] by bisection: an independent, slow reference.

    Geometric midpoints while the bracket spans decades, so tiny roots are found too.
    """
    lo, hi = 1e-320, 1.0
    for _ in range(2000):
        mid = math.sqrt(lo) * math.sqrt(hi) if hi > 4 * lo else 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        if sigma_of_lambda(mid, E) > sigma:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def x_bisect(sigma: float, E: float) -> float:
    """x = 1 − λ = Δd/(d − d0) by bisection on the cancellation-free form of eq. 2.

    Accurate to a few ulp of x even when x is tiny (where 1 − λ from
    :func:`lambda_bisect` would have lost all its digits).
    """
    lo, hi = 1e-300, 1.0
    for _ in range(2000):
        mid = math.sqrt(lo) * math.sqrt(hi) if hi > 4 * lo else 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        if sigma_of_compression(np.float64(mid), E, 1.0, 0.0) < sigma:  # type: ignore[arg-type]  # elementwise: a scalar too
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def test_defaults_are_the_design_numbers():
    assert (P.E1, P.E2) == (4.8e3, 15e3)
    assert (P.d1, P.d2, P.d10, P.d20) == (5.0e-3, 3.0e-3, 1.0e-3, 0.6e-3)
    assert (P.eps_r1, P.eps_r2) == (2.0, 2.0)
    assert P.side == 0.040
    assert (P.parasitic1, P.parasitic2) == (10e-12, 10e-12)


def test_rest_capacitances():
    c1 = 8.8541878128e-12 * 2.0 * 0.04**2 / 5e-3
    c2 = 8.8541878128e-12 * 2.0 * 0.04**2 / 3e-3
    assert P.C1_0 == approx(c1, rel=1e-12)
    assert P.C2_0 == approx(c2, rel=1e-12)
    r1, r2 = rest_capacitance()
    assert r1 == approx(c1 + 10e-12, rel=1e-12)
    assert r2 == approx(c2 + 10e-12, rel=1e-12)
    # The numbers the chip's transfer functions are specified at.
    assert r1 == approx(15.67e-12, abs=0.01e-12)
    assert r2 == approx(19.44e-12, abs=0.01e-12)
    assert EPS0 == approx(8.8541878128e-12)


def test_small_stress_is_linear_with_modulus_slope():
    # The slope of eq. 2 at rest, by central differences of the formula itself.
    E = 4.8e3
    h = 1e-6
    slope = (sigma_of_lambda(1 + h, E) - sigma_of_lambda(1 - h, E)) / (2 * h)
    assert slope == approx(-E, rel=1e-8)
    # Hence Δd ≈ σ(d − d0)/E, with a relative error of the order of σ/E.
    d, d0 = 5e-3, 1e-3
    for sigma in (1e-12, 1e-6, 1e-3, 1.0):
        dd = compression(sigma, E, d, d0)
        lin = sigma * (d - d0) / E
        assert dd == approx(lin, rel=3 * sigma / E + 1e-14)
    # And it keeps full relative precision for absurdly small stresses.
    assert compression(1e-250, E, d, d0) == approx(1e-250 * (d - d0) / E, rel=1e-13)


def test_saturation_limit():
    d, d0 = 3e-3, 0.6e-3
    for sigma in (1e9, 1e15, 1e100, 1e300, math.inf):
        dd = float(compression(sigma, 15e3, d, d0))
        assert dd <= d - d0
        # The remaining gap is (d − d0)·λ ≈ (d − d0)·E/(3σ).
        assert dd == approx(d - d0, rel=15e3 / (3 * sigma) * 1.01 + 1e-16)
    # λ ≈ E/(3σ) at large σ: the remaining gap shrinks as 1/σ.
    gap = (d - d0) - compression(1e12, 15e3, d, d0)
    assert gap / (d - d0) == approx(15e3 / (3 * 1e12), rel=1e-4)


def test_zero_stress_gives_zero():
    assert compression(0.0, 4.8e3, 5e-3, 1e-3) == 0.0
    g1, g2 = sensitivity(0.0)
    assert g1 == 0.0 and g2 == 0.0


@settings(max_examples=300, deadline=None)
@given(
    log_u=st.floats(min_value=-250, max_value=250),
    E=st.floats(min_value=1e2, max_value=1e7),
    d=st.floats(min_value=1e-4, max_value=1e-1),
    frac0=st.floats(min_value=0.0, max_value=0.95),
)
def test_root_satisfies_eq2(log_u, E, d, frac0):
    sigma = E * 10.0**log_u
    d0 = frac0 * d
    dd = float(compression(sigma, E, d, d0))
    assert 0.0 <= dd <= d - d0
    x = dd / (d - d0)
    if x < 0.5:
        # σ back from Δd, written without cancellation: tight relative residual.
        back = float(sigma_of_compression(np.float64(dd), E, d, d0))  # type: ignore[arg-type]  # elementwise: a scalar too
        assert back == approx(sigma, rel=1e-12)
    else:
        # Δd near saturation fixes λ = 1 − x only to a few ulp of 1 (absolute), so
        # judge the cubic λ³ + 3(σ/E)λ − 1 = 0 by the λ error its residual implies.
        lam = 1.0 - x
        u = sigma / E
        res = lam**3 + 3 * u * lam - 1.0
        assert abs(res) / (3 * lam * lam + 3 * u) <= 1e-15


@settings(max_examples=200, deadline=None)
@given(log_u=st.floats(min_value=-3, max_value=250))
def test_stretch_keeps_relative_precision_in_saturation(log_u):
    # λ itself (not 1 − Δd/(d−d0)) stays accurate to ~ulp where it is tiny.
    from cellbridge.tactile.element import _stretch

    u = 10.0**log_u
    lam, one_m = _stretch(np.array([u]))
    ref = lambda_bisect(u, 1.0)
    assert lam[0] == approx(ref, rel=1e-13)
    assert lam[0] + one_m[0] == approx(1.0, rel=1e-15)


def test_matches_bisection_over_a_sweep():
    for sigma in np.geomspace(1e-6, 1e10, 80):
        x = x_bisect(sigma, 4.8e3)
        dd = compression(sigma, 4.8e3, 5e-3, 1e-3)
        assert dd == approx(x * 4e-3, rel=1e-13)


def test_compression_is_monotone_and_vectorised():
    s = np.geomspace(1e-6, 1e12, 20001)
    dd = compression(s, 15e3, 3e-3, 0.6e-3)
    assert dd.shape == s.shape
    assert np.all(np.diff(dd) > 0) or np.all(np.diff(dd) >= 0)
    assert np.all(np.diff(dd)[:15000] > 0)
    grid = compression(s.reshape(3, -1)[:, :5], 15e3, 3e-3, 0.6e-3)
    assert grid.shape == (3, 5)


def test_bad_pressure_raises():
    with pytest.raises(ValueError, match="sigma"):
        compression(-1.0, 4.8e3, 5e-3, 1e-3)
    with pytest.raises(ValueError, match="sigma"):
        sensitivity([1.0, np.nan])
    with pytest.raises(ValueError):
        compression(1.0, 4.8e3, 1e-3, 5e-3)  # d0 > d


def test_sensitivity_formula():
    sigma = np.array([10.0, 1e3, 1e4, 1e5])
    g1, g2 = sensitivity(sigma)
    for s, a, b in zip(sigma, g1, g2):
        dd1 = (1 - lambda_bisect(s, P.E1)) * (P.d1 - P.d10)
        dd2 = (1 - lambda_bisect(s, P.E2)) * (P.d2 - P.d20)
        e = EPS0 * 2.0
        assert a == approx(e * dd1 / (P.d1 * (P.d1 - dd1)), rel=1e-10)
        assert b == approx(e * dd2 / (P.d2 * (P.d2 - dd2)), rel=1e-10)
    gi1, gi2 = sensitivity(math.inf)
    assert gi1 == approx(P.g1_max) and gi2 == approx(P.g2_max)


def integrate_eq3(force, diameter, offset=(0.0, 0.0), n=600, sub=4):
    """ΔC1, ΔC2 by summing eq. 3 over an n×n grid of the element.

    Each cell's covered fraction of the disk comes from sub×sub sample points; the
    pressure inside the disk is F/S with S the disk's exact area (eq. 1), and the
    compression comes from bisection of eq. 2.
    """
    side = P.side
    h = side / n
    centres = (np.arange(n) + 0.5) * h - side / 2
    offs = ((np.arange(sub) + 0.5) / sub - 0.5) * h
    r2 = (diameter / 2) ** 2
    frac = np.zeros((n, n))
    for ox in offs:
        for oy in offs:
            X = centres[:, None] + ox - offset[0]
            Y = centres[None, :] + oy - offset[1]
            frac += (X * X + Y * Y) <= r2
    frac /= sub * sub
    S = math.pi * r2
    sigma = force / S
    out = []
    for E, d, d0, er in ((P.E1, P.d1, P.d10, P.eps_r1), (P.E2, P.d2, P.d20, P.eps_r2)):
        dd = (1 - lambda_bisect(sigma, E)) * (d - d0)
        eps = EPS0 * er
        local = frac * eps / (d - dd) + (1 - frac) * eps / d  # mean of ε/(d − Δd) over a cell
        C = local.sum() * h * h
        out.append(C - eps * side * side / d)
    return out


@pytest.mark.parametrize(
    "force,diameter,offset",
    [(1.0, 0.010, (0, 0)), (5.0, 0.020, (0.004, -0.003)), (20.0, 0.040, (0, 0)),
     (12.0, 0.030, (0.0, 0.002)), (0.2, 0.026, (0.0, 0.0))],
)
def test_forward_matches_numerical_integration_of_eq3(force, diameter, offset):
    dc1, dc2 = forward(force, math.pi * diameter**2 / 4)
    n1, n2 = integrate_eq3(force, diameter, offset)
    # The grid resolves the disk's edge to ~1e-4 of its area.
    assert dc1 == approx(n1, rel=5e-4)
    assert dc2 == approx(n2, rel=5e-4)


def test_partial_overlap_is_linear_in_area():
    # What the skin model relies on: a piece of area A of a disk at pressure σ gives A·g(σ).
    sigma = 8e3
    g1, g2 = sensitivity(sigma)
    for a in (1e-5, 3e-4, P.area):
        dc1, dc2 = forward(sigma * a, a)
        assert dc1 == approx(a * g1, rel=1e-12)
        assert dc2 == approx(a * g2, rel=1e-12)


def test_forward_broadcasts_and_capacitance_adds_rest():
    F = np.array([[0.0], [1.0], [10.0]])
    S = np.array([1e-4, 5e-4])
    dc1, dc2 = forward(F, S)
    assert dc1.shape == dc2.shape == (3, 2)
    assert np.all(dc1[0] == 0) and np.all(dc1[1:] > 0) and np.all(dc2[1:] > 0)
    c1, c2 = capacitance(F, S)
    assert np.allclose(c1 - P.C1_rest, dc1, rtol=0, atol=1e-26)
    assert np.allclose(c2 - P.C2_rest, dc2, rtol=0, atol=1e-26)
    # More force on the same area always raises both capacitances.
    f = np.linspace(0.1, 30, 300)
    a1, a2 = forward(f, 3e-4)
    assert np.all(np.diff(a1) > 0) and np.all(np.diff(a2) > 0)


@pytest.mark.parametrize(
    "force,area,match",
    [(-1.0, 1e-4, "force"), (np.nan, 1e-4, "force"), (np.inf, 1e-4, "force"),
     (1.0, 0.0, "area"), (1.0, -1e-4, "area"), (1.0, np.nan, "area"),
     (1.0, 0.0017, "element area"), ([1.0, 2.0, 3.0], [1e-4, 2e-4], "broadcast"),
     ("abc", 1e-4, "force")],
)
def test_forward_rejects_bad_input(force, area, match):
    with pytest.raises(ValueError, match=match):
        forward(force, area)


def test_whole_element_contact_is_allowed():
    dc1, _ = forward(3.0, 0.04 * 0.04)
    assert dc1 > 0


def test_params_validation():
    with pytest.raises(ValueError, match="d10"):
        ElementParams(d10=6e-3)
    with pytest.raises(ValueError, match="E1"):
        ElementParams(E1=-1.0)
    q = ElementParams(side=0.05, parasitic1=0.0)
    assert q.area == approx(0.0025)
    assert q.C1_rest == approx(q.C1_0)
    hash(q)  # frozen and hashable: the inverse caches its tables per parameter set
