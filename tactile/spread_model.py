"""The disk's readings under the membrane-tension spread, with analytic derivatives.

With a spread s the pressure is the disk's F/S blurred by a 2-D Gaussian, and an
element reads ``∫ g_n(σ·Φ(ρ)) dA`` over its area, Φ being the blurred disk's radial
profile (:func:`cellbridge.tactile.response._disk_blur`). Φ depends on ρ/s and R/s
only, so it is tabulated once per dimensionless radius v = R/s (rows every 0.05 in
v, 1/40 in u = ρ/s, built on demand and kept for the process, whatever s is) and
interpolated linearly in both. Per evaluation the kernel turns the two neighbouring
rows into tables of g, ∂g/∂u, ∂g/∂ln F and ∂g/∂ln R along u (a few hundred
sensitivity evaluations), then sums them over the quadrature nodes of each observed
element that the blurred disk reaches: the same 2×2-point Gauss rule on cells of
``quad_step`` as :func:`cellbridge.tactile.response.skin_response`, generated on the fly.
"""

from __future__ import annotations

import math

import numpy as np
from cellbridge.tactile._jit import compiled
from cellbridge.tactile.disk_model import overlap_grad, prior_row, sensitivity_slope, whiten
from cellbridge.tactile.response import _disk_blur

__all__ = ["ProfileRows", "spread_residuals", "DV", "DU", "U_SPAN"]

DV = 0.05  #: row step in v = R/s
DU = 1.0 / 40.0  #: step in u = ρ/s within a row
U_SPAN = 8.0  #: a row covers u ∈ [max(v − 8, 0), max(v − 8, 0) + 16]
NU = int(round(2 * U_SPAN / DU)) + 1
REACH = 6.0  #: nodes farther than R + 6s from the centre get nothing (Φ < 1e-9)


class ProfileRows:
    """Φ(u; v) rows for v = k·DV, k = 0, 1, …, computed when first asked for."""

    def __init__(self) -> None:
        self.rows = np.zeros((0, NU))

    def upto(self, k_max: int) -> np.ndarray:
        """All rows 0..k_max (built now if missing)."""
        have = self.rows.shape[0]
        if k_max >= have:
            # In blocks: the quadrature's temporaries grow with the rows built at once.
            new = []
            for k0 in range(have, k_max + 1, 64):
                v = np.arange(k0, min(k0 + 64, k_max + 1)) * DV
                u0 = np.maximum(v - U_SPAN, 0.0)
                u = u0[:, None] + DU * np.arange(NU)[None, :]
                new.append(_disk_blur(u, np.broadcast_to(v[:, None], u.shape).copy(), 1.0))
            self.rows = np.concatenate([self.rows, *new])
        return self.rows


#: One table for the whole process: rows are dimensionless, so every estimator shares them.
PROFILE_ROWS = ProfileRows()


@compiled
def _row_at(tab: np.ndarray, k: int, u: float) -> float:
    u0 = max(k * DV - U_SPAN, 0.0)
    x = (u - u0) / DU
    if x <= 0.0:
        return tab[k, 0]
    j = int(x)
    if j >= NU - 1:
        return 0.0
    f = x - j
    return tab[k, j] * (1.0 - f) + tab[k, j + 1] * f


@compiled
def spread_residuals(
    theta: np.ndarray, bounds: np.ndarray, y: np.ndarray, w: np.ndarray, quiet: np.ndarray,
    par: np.ndarray, s: float, q: int, tab: np.ndarray, res: np.ndarray, jac: np.ndarray, want_jac: bool,
) -> tuple[float, float]:
    """Whitened residuals and Jacobian of one disk under spread ``s``, rows as in
    :func:`cellbridge.tactile.disk_model.disk_residuals` (ΔC1, ΔC2, then the prior,
    here on the disk widened by 1.5 s, where the blurred force still is)."""
    m = bounds.shape[0]
    nrow = 2 * m + 1
    for i in range(nrow):
        res[i] = 0.0
        for j in range(4):
            jac[i, j] = 0.0
    cx = theta[0]
    cy = theta[1]
    R = 0.5 * math.exp(theta[2])
    F = math.exp(theta[3])
    sig0 = F / (math.pi * R * R)
    v = R / s
    kf = v / DV
    k = min(int(kf), tab.shape[0] - 2)
    t = kf - k
    u0 = max(k * DV - U_SPAN, 0.0)
    # Tables along u (grid of row k): g, ∂g/∂u, ∂g/∂lnF, ∂g/∂lnR for both layers.
    phi = np.empty(NU)
    phv = np.empty(NU)
    for j in range(NU):
        u = u0 + j * DU
        a = tab[k, j]
        b = _row_at(tab, k + 1, u)
        phi[j] = a * (1.0 - t) + b * t
        phv[j] = (b - a) / DV
    T = np.empty((8, NU))
    for j in range(NU):
        p = sig0 * phi[j]
        ju = min(max(j, 1), NU - 2)
        dphi_du = (phi[ju + 1] - phi[ju - 1]) / (2.0 * DU)
        dp_dlnr = sig0 * v * phv[j] - 2.0 * p
        for c in range(2):
            g, gs = sensitivity_slope(p, par[4 * c], par[4 * c + 1], par[4 * c + 2], par[4 * c + 3])
            T[4 * c, j] = g
            T[4 * c + 1, j] = gs * sig0 * dphi_du
            T[4 * c + 2, j] = gs * p
            T[4 * c + 3, j] = gs * dp_dlnr
    reach = R + REACH * s
    umax = u0 + (NU - 1) * DU
    gq = 0.5 / math.sqrt(3.0)
    for i in range(m):
        x0, y0, x1, y1 = bounds[i, 0], bounds[i, 1], bounds[i, 2], bounds[i, 3]
        hx = (x1 - x0) / q
        hy = (y1 - y0) / q
        ia = max(int(math.floor((cx - reach - x0) / hx)), 0)
        ib = min(int(math.ceil((cx + reach - x0) / hx)), q)
        ja = max(int(math.floor((cy - reach - y0) / hy)), 0)
        jb = min(int(math.ceil((cy + reach - y0) / hy)), q)
        wn = hx * hy * 0.25
        for a in range(ia, ib):
            for ox in range(2):
                xn = x0 + (a + 0.5 + (gq if ox else -gq)) * hx
                dx = cx - xn
                for b in range(ja, jb):
                    for oy in range(2):
                        yn = y0 + (b + 0.5 + (gq if oy else -gq)) * hy
                        dy = cy - yn
                        rho = math.sqrt(dx * dx + dy * dy)
                        u = rho / s
                        if u >= umax:
                            continue
                        xx = (u - u0) / DU
                        if xx < 0.0:
                            jj = 0
                            f = 0.0
                        else:
                            jj = min(int(xx), NU - 2)
                            f = xx - jj
                        for c in range(2):
                            row = c * m + i
                            g = T[4 * c, jj] * (1.0 - f) + T[4 * c, jj + 1] * f
                            res[row] += wn * g
                            if want_jac:
                                gu = T[4 * c + 1, jj] * (1.0 - f) + T[4 * c + 1, jj + 1] * f
                                if rho > 0.0:
                                    jac[row, 0] += wn * gu * dx / (rho * s)
                                    jac[row, 1] += wn * gu * dy / (rho * s)
                                jac[row, 2] += wn * (T[4 * c + 3, jj] * (1.0 - f) + T[4 * c + 3, jj + 1] * f)
                                jac[row, 3] += wn * (T[4 * c + 2, jj] * (1.0 - f) + T[4 * c + 2, jj + 1] * f)
    data = whiten(res, jac, y, w, quiet, 2, m, True, want_jac)
    # On-skin prior on the widened footprint (∂rw/∂ln R = R).
    rw = R + 1.5 * s
    tot = 0.0
    tx = 0.0
    ty = 0.0
    tr = 0.0
    for i in range(m):
        a, ax, ay, ar = overlap_grad(cx, cy, rw, bounds[i, 0], bounds[i, 1], bounds[i, 2], bounds[i, 3])
        tot += a
        tx += ax
        ty += ay
        tr += ar
    disk = math.pi * rw * rw
    prior_row(res, jac, 2 * m, 0, tot, tx, ty, -tr * R / disk + 2.0 * tot * R / (disk * rw), disk, want_jac)
    total = data + res[2 * m] ** 2
    return data, total
