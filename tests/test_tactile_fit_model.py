"""The compiled disk models and the fit kernel's start (disk_model, spread_model, fit_kernel)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from cellbridge.tactile.disk_model import disk_residuals, element_vector, overlap_grad, sensitivity_slope
from cellbridge.tactile.element import ElementParams, sensitivity
from cellbridge.tactile.fit_kernel import share_start
from cellbridge.tactile.layout import grid_layout
from cellbridge.tactile.overlap import disk_rect_overlap
from cellbridge.tactile.response import _spread_cells, skin_response
from cellbridge.tactile.spread_model import DV, PROFILE_ROWS, spread_residuals
from hypothesis import given, settings
from hypothesis import strategies as st

P = ElementParams()
PAR = element_vector(P)
RECT = (0.0, 0.0, 1.0, 0.7)


def area(cx, cy, r):
    return float(disk_rect_overlap(cx, cy, r, *RECT))


@settings(max_examples=300, deadline=None)
@given(st.floats(-1.0, 2.0), st.floats(-1.0, 1.7), st.floats(0.02, 2.0))
def test_overlap_and_its_derivatives(cx, cy, r):
    a, ax, ay, ar = overlap_grad(cx, cy, r, *RECT)
    assert a == pytest.approx(area(cx, cy, r), abs=1e-12)
    h = 1e-8
    # Central differences of the exact area. The area is C¹ in the centre and the
    # radius (its derivatives are chord lengths), but a chord grows like a square
    # root where the circle meets a corner or an edge: there the difference is off
    # by O(√h) = 1e-4. A wrong derivative is off by O(1).
    assert ax == pytest.approx((area(cx + h, cy, r) - area(cx - h, cy, r)) / (2 * h), abs=1e-3)
    assert ay == pytest.approx((area(cx, cy + h, r) - area(cx, cy - h, r)) / (2 * h), abs=1e-3)
    assert ar == pytest.approx((area(cx, cy, r + h) - area(cx, cy, r - h)) / (2 * h), abs=1e-3)


def test_overlap_limits():
    assert overlap_grad(0.5, 0.35, 0.1, *RECT) == pytest.approx((math.pi * 0.01, 0.0, 0.0, 2 * math.pi * 0.1))
    a, ax, ay, ar = overlap_grad(0.5, 0.35, 5.0, *RECT)  # the rectangle inside the disk
    assert a == pytest.approx(0.7) and ax == ay == ar == 0.0
    assert overlap_grad(3.0, 0.0, 0.5, *RECT) == (0.0, 0.0, 0.0, 0.0)


@pytest.mark.parametrize("sigma", [0.0, 1e-3, 10.0, 500.0, 3.2e3, 1e4, 1e5, 1e8])
def test_sensitivity_and_slope(sigma):
    for layer, (E, d, d0, eps) in enumerate(((P.E1, P.d1, P.d10, P.eps1), (P.E2, P.d2, P.d20, P.eps2))):
        g, slope = sensitivity_slope(sigma, E, d, d0, eps)
        ref = float(sensitivity(sigma, P)[layer])
        assert g == pytest.approx(ref, rel=1e-12, abs=1e-300)
        h = max(sigma * 1e-5, 1e-4)
        lo = max(sigma - h, 0.0)
        fd = (float(sensitivity(sigma + h, P)[layer]) - float(sensitivity(lo, P)[layer])) / (sigma + h - lo)
        assert slope == pytest.approx(fd, rel=1e-4)


def _residuals(fun, theta, m, nrow, p, *args):
    res = np.empty(nrow)
    jac = np.empty((nrow, p))
    fun(theta, *args, res, jac, True)
    return res, jac


def test_disk_residuals_match_the_skin_model_and_jacobian():
    lay = grid_layout(2, 3)
    truth = [0.031, 0.018, 4.0, 0.014]
    dc1, dc2 = skin_response(lay, truth)
    y = np.stack([dc1, dc2])
    w = np.array([1e15, 1e15])
    quiet = np.zeros(lay.n, dtype=bool)
    th = np.array([truth[0], truth[1], math.log(truth[3]), math.log(truth[2])])
    m = lay.n

    def run(t):
        return _residuals(lambda *a: disk_residuals(a[0], 1, lay.bounds, y, w, quiet, 2, PAR, *a[1:]),
                          t, m, 2 * m + 1, 4)

    res, jac = run(th)
    assert np.max(np.abs(res[: 2 * m])) < 1e-6  # the truth reproduces the readings
    for j in range(4):
        h = 1e-7 if j < 2 else 1e-6
        e = np.zeros(4)
        e[j] = h
        fd = (run(th + e)[0] - run(th - e)[0]) / (2 * h)
        assert np.allclose(jac[: 2 * m, j], fd[: 2 * m], rtol=1e-4, atol=1e-3 * np.abs(fd).max())


def test_spread_residuals_match_the_skin_model_and_jacobian():
    s = 0.002
    lay = grid_layout(2, 2)
    # R/s = 2.525: midway between two profile rows (v is interpolated linearly, so
    # ∂/∂R is one slope per row interval, and differences across a row would mix two).
    truth = [0.018, 0.003, 3.0, 0.0101]
    dc1, dc2 = skin_response(lay, truth, spread=s)
    y = np.stack([dc1, dc2])
    w = np.array([1e15, 1e15])
    quiet = np.zeros(lay.n, dtype=bool)
    rows = PROFILE_ROWS.upto(int(0.5 * 0.02 / s / DV) + 2)
    q = _spread_cells(lay.side, s, None)
    th = np.array([truth[0], truth[1], math.log(truth[3]), math.log(truth[2])])
    m = lay.n

    def run(t):
        return _residuals(lambda *a: spread_residuals(a[0], lay.bounds, y, w, quiet, PAR, s, q, rows, *a[1:]),
                          t, m, 2 * m + 1, 4)

    res, jac = run(th)
    # Readings of ≈ 1 pF to within a few fF (the profile table is interpolated).
    assert np.max(np.abs(res[: 2 * m])) < 5.0
    for j in range(4):
        h = 2e-6 if j < 2 else 1e-4
        e = np.zeros(4)
        e[j] = h
        fd = (run(th + e)[0] - run(th - e)[0]) / (2 * h)
        # Compared as changes of the whitened residuals over one step: a y step of
        # a disk that stays inside its row changes nothing (≈ 1e-8 on both sides).
        assert np.allclose(h * jac[: 2 * m, j], h * fd[: 2 * m], rtol=0.02, atol=1e-3)
        assert np.abs(h * fd[: 2 * m]).max() > 0.05 or j == 1


@settings(max_examples=60, deadline=None)
@given(st.floats(-0.45, 0.45), st.floats(-0.45, 0.45), st.floats(0.008, 0.030))
def test_share_start_is_exact_for_a_disk_over_a_corner(fx, fy, d):
    # Noise-free areas of a disk over the corner of four elements: the segment
    # inversion gives the centre exactly (the disk reaches all four).
    lay = grid_layout(2, 2)
    x, y = 0.020 + fx * d, 0.020 + fy * d
    a = disk_rect_overlap(x, y, d / 2, *lay.bounds.T)
    out = np.empty((1, 3))
    share_start(np.array([0, 4]), np.array([4]), np.ascontiguousarray(lay.bounds), a, out)
    assert out[0, 0] == pytest.approx(x, abs=1e-9) and out[0, 1] == pytest.approx(y, abs=1e-9)
    assert 2 * out[0, 2] == pytest.approx(d, rel=1e-9)
