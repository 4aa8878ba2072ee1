"""The one-disk measurement model with analytic derivatives, compiled (numba).

A contact fit evaluates "what would the elements read for this disk, and how would
that change if the disk moved, grew or pressed harder" a few dozen times per
contact. In numpy every evaluation pays tens of microseconds of call overhead on
arrays of a dozen elements; compiled scalar code pays well under one, and analytic
derivatives replace the central differences that cost two more evaluations per
parameter. Everything here is scalar and allocation-light so that the fit kernel
(:mod:`cellbridge.tactile.fit_kernel`) can loop over every contact of a frame.

Exact geometry: the disk ∩ rectangle area is the closed form of
:func:`cellbridge.tactile.overlap.disk_rect_overlap` (same formulas, scalar), and its
derivatives are boundary integrals, also closed form:

* moving the centre by dx changes the area by (chord on the left edge − chord on the
  right edge)·dx, since the rectangle's edges sweep through the disk;
* the area is homogeneous of degree 2 in (r, edge offsets), so Euler's relation
  gives ``r·∂A/∂r = 2A − Σ_edges offset·chord`` without any arc-length bookkeeping.

Physics: eqs. 2-3 of the paper through the sensitivity g_n(σ) of
:mod:`cellbridge.tactile.element`, with the slope ``dg/dσ = g·e(λ)/σ`` from the
elasticity e; both are element's own closed forms compiled here (one copy of them).

Parameters of a disk are ``(x, y, ln D, ln F)``: logarithms keep D and F positive
and make steps relative, which is how their uncertainty behaves.
"""

from __future__ import annotations

import math

import numpy as np
from cellbridge.tactile import element
from cellbridge.tactile._jit import compiled
from cellbridge.tactile.element import ElementParams

__all__ = [
    "PRIOR_OFF", "element_vector", "overlap_grad", "layer_response", "sensitivity_slope", "disk_residuals", "prior_row", "whiten",
]

#: One-sigma width of the on-skin prior, as a fraction of the disk lying on no
#: observed element (see :func:`disk_residuals`).
PRIOR_OFF = 0.05


def element_vector(p: ElementParams) -> np.ndarray:
    """The element constants the compiled code needs: (E, d, d0, ε) per layer."""
    return np.array([p.E1, p.d1, p.d10, p.eps1, p.E2, p.d2, p.d20, p.eps2], dtype=np.float64)


@compiled
def _prim(t: float, root: float) -> float:
    return 0.5 * (t * root + math.asin(t))


@compiled
def _quadrant(a: float, b: float) -> float:
    # Area of the unit disk with x > a and y > b (see skin._quadrant).
    a = min(max(a, -1.0), 1.0)
    b = min(max(b, -1.0), 1.0)
    c = math.sqrt(1.0 - b * b)
    x1 = min(max(a, -c), c)
    pc = _prim(c, abs(b))
    px1 = _prim(x1, math.sqrt(max(1.0 - x1 * x1, 0.0)))
    common = pc - px1 - b * (c - x1)
    if b >= 0.0:
        return common
    pa = _prim(a, math.sqrt(1.0 - a * a))
    return 0.5 * math.pi - 2.0 * pa - pc + px1 - b * (c - x1)


@compiled
def _chord(e: float, c: float, r: float, ct: float, lo: float, hi: float) -> float:
    # Length of the line {coordinate = e} inside the disk (centre c along that axis,
    # ct across it) and inside [lo, hi].
    dd = e - c
    h2 = r * r - dd * dd
    if h2 <= 0.0:
        return 0.0
    h = math.sqrt(h2)
    return max(min(hi, ct + h) - max(lo, ct - h), 0.0)


@compiled
def overlap_grad(
    cx: float, cy: float, r: float, x0: float, y0: float, x1: float, y1: float
) -> tuple[float, float, float, float]:
    """Area of the disk on [x0,x1]×[y0,y1] and its derivatives by cx, cy and r."""
    if r <= 0.0:
        return 0.0, 0.0, 0.0, 0.0
    # Quick exits: no overlap, or the disk wholly inside (the common cases).
    if cx + r <= x0 or cx - r >= x1 or cy + r <= y0 or cy - r >= y1:
        return 0.0, 0.0, 0.0, 0.0
    if cx - r >= x0 and cx + r <= x1 and cy - r >= y0 and cy + r <= y1:
        return math.pi * r * r, 0.0, 0.0, 2.0 * math.pi * r
    ax0 = (x0 - cx) / r
    ax1 = (x1 - cx) / r
    by0 = (y0 - cy) / r
    by1 = (y1 - cy) / r
    u = _quadrant(ax0, by0) - _quadrant(ax1, by0) - _quadrant(ax0, by1) + _quadrant(ax1, by1)
    area = min(max(u * r * r, 0.0), min(math.pi * r * r, (x1 - x0) * (y1 - y0)))
    lx0 = _chord(x0, cx, r, cy, y0, y1)
    lx1 = _chord(x1, cx, r, cy, y0, y1)
    ly0 = _chord(y0, cy, r, cx, x0, x1)
    ly1 = _chord(y1, cy, r, cx, x0, x1)
    dx = lx0 - lx1
    dy = ly0 - ly1
    dr = (2.0 * area - (x1 - cx) * lx1 + (x0 - cx) * lx0 - (y1 - cy) * ly1 + (y0 - cy) * ly0) / r
    return area, dx, dy, max(dr, 0.0)


# element's closed forms, compiled as they are (one copy of the physics for numpy and here).
_stretch_small = compiled(element._stretch_small)
_stretch_large = compiled(element._stretch_large)
_g_of = compiled(element._g_of)
_elasticity = compiled(element._elasticity)


@compiled
def layer_response(sig: float, E: float, d: float, d0: float, eps: float) -> tuple[float, float]:
    """g(σ) of one layer (F/m²) and its elasticity e = d ln g / d ln σ, for σ >= 0
    (element._stretch's branches, one value at a time, and the same closed forms)."""
    u = sig / E
    if u <= 1.0:
        lam, one_m = _stretch_small(u)
    else:
        lam = _stretch_large(u)
        one_m = 1.0 - lam
    return _g_of(lam, one_m, d, d0, eps), _elasticity(lam, d, d0)


@compiled
def sensitivity_slope(sig: float, E: float, d: float, d0: float, eps: float) -> tuple[float, float]:
    """g(σ) of one layer (F/m²) and dg/dσ, for σ >= 0 (see element._stretch)."""
    if sig <= 0.0:
        return 0.0, eps * (d - d0) / (E * d * d)
    g, e = layer_response(sig, E, d, d0, eps)
    return g, g * e / sig


@compiled
def disk_residuals(
    theta: np.ndarray,
    nd: int,
    bounds: np.ndarray,
    y: np.ndarray,
    w: np.ndarray,
    quiet: np.ndarray,
    nch: int,
    par: np.ndarray,
    res: np.ndarray,
    jac: np.ndarray,
    want_jac: bool,
) -> tuple[float, float]:
    """Whitened residuals (and Jacobian) of ``nd`` disks against one cluster's readings.

    Rows: channel-major ``(pred − y)·w`` over the ``M`` observed elements (``nch = 2``:
    ΔC1 then ΔC2 with ``pred = Σ_k A_ik·g_n(σ_k)``; ``nch = 1``: areas, ``pred = Σ_k A_ik``),
    then one on-skin prior row per disk. Quiet elements (the ring around a cluster)
    bound the disks one-sided: predicting more than they read costs, less does not
    (their reading is noise around zero, and a disk grazing them to "explain" that
    noise would be a spurious optimum). The prior row is the fraction of the disk on
    no observed element over :data:`PRIOR_OFF`: a disk partly off the skin's edge and
    a smaller one on it can read the same, and the prior prefers the one on the skin;
    it is zero for any disk wholly on the elements, so it biases nothing else.
    Returns (data cost, total cost), costs being sums of squared rows.
    """
    m = bounds.shape[0]
    nrow = nch * m + nd
    p = 4 * nd
    for i in range(nrow):
        res[i] = 0.0
        if want_jac:
            for j in range(p):
                jac[i, j] = 0.0
    for k in range(nd):
        cx = theta[4 * k]
        cy = theta[4 * k + 1]
        r = 0.5 * math.exp(theta[4 * k + 2])
        f = math.exp(theta[4 * k + 3])
        disk = math.pi * r * r
        sig = f / disk
        g0 = 1.0
        g1 = 0.0
        s0 = 0.0
        s1 = 0.0
        if nch == 2:
            g0, s0 = sensitivity_slope(sig, par[0], par[1], par[2], par[3])
            g1, s1 = sensitivity_slope(sig, par[4], par[5], par[6], par[7])
        tot = 0.0
        tx = 0.0
        ty = 0.0
        tr = 0.0
        for i in range(m):
            a, ax, ay, ar = overlap_grad(cx, cy, r, bounds[i, 0], bounds[i, 1], bounds[i, 2], bounds[i, 3])
            if a == 0.0 and ar == 0.0:
                continue
            tot += a
            tx += ax
            ty += ay
            tr += ar
            for c in range(nch):
                g = g0 if c == 0 else g1
                s = s0 if c == 0 else s1
                row = c * m + i
                res[row] += a * g
                if want_jac:
                    jac[row, 4 * k] += ax * g * w[c]
                    jac[row, 4 * k + 1] += ay * g * w[c]
                    jac[row, 4 * k + 2] += (ar * r * g - 2.0 * a * s * sig) * w[c]
                    jac[row, 4 * k + 3] += a * s * sig * w[c]
        prior_row(res, jac, nch * m + k, 4 * k, tot, tx, ty, -tr * r / disk + 2.0 * tot / disk, disk, want_jac)
    data = whiten(res, jac, y, w, quiet, nch, m, False, want_jac)
    total = data
    for k in range(nd):
        total += res[nch * m + k] ** 2
    return data, total


@compiled
def prior_row(
    res: np.ndarray, jac: np.ndarray, row: int, col: int, tot: float, tx: float, ty: float,
    doff_dlnr: float, disk: float, want_jac: bool,
) -> None:
    """The on-skin prior's row: off-footprint fraction ``1 − tot/disk`` over
    :data:`PRIOR_OFF`, zero when the footprint lies wholly on the observed elements."""
    off = 1.0 - tot / disk
    if off > 0.0:
        res[row] = off / PRIOR_OFF
        if want_jac:
            jac[row, col] = -tx / disk / PRIOR_OFF
            jac[row, col + 1] = -ty / disk / PRIOR_OFF
            jac[row, col + 2] = doff_dlnr / PRIOR_OFF


@compiled
def whiten(
    res: np.ndarray, jac: np.ndarray, y: np.ndarray, w: np.ndarray, quiet: np.ndarray, nch: int, m: int,
    scale_jac: bool, want_jac: bool,
) -> float:
    """Turn predictions in ``res`` into whitened residuals (data rows); returns their
    cost. Quiet elements only bound the prediction from above. ``scale_jac``:
    multiply the Jacobian's data rows by w (False: they already carry it)."""
    data = 0.0
    p = jac.shape[1]
    for c in range(nch):
        for i in range(m):
            row = c * m + i
            v = (res[row] - y[c, i]) * w[c]
            if want_jac and scale_jac:
                for j in range(p):
                    jac[row, j] *= w[c]
            if quiet[i] and v < 0.0:
                v = 0.0
                if want_jac:
                    for j in range(p):
                        jac[row, j] = 0.0
            res[row] = v
            data += v * v
    return data
