"""The element inverse of :func:`cellbridge.tactile.inversion.solve`, compiled.

The same rules, one reading at a time: a frame's dozen elements cost microseconds here
against ~170 µs of numpy's per-call overhead, a third of a one-contact frame of the
contact estimator, which already runs compiled kernels. :func:`solve` itself stays
numpy: the daemon's per-element physics must import and run where numba cannot
(no executable memory under ``MemoryDenyWriteExecute``). tests/test_tactile_inverse.py
checks that both give the same status bits and values within 1e-10.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from cellbridge.tactile._jit import compiled
from cellbridge.tactile.disk_model import element_vector, layer_response
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.inversion import DEFAULT_NOISE, InverseResult, _inputs

__all__ = ["solve_compiled"]


def solve_compiled(
    dC1: ArrayLike,
    dC2: ArrayLike,
    params: ElementParams | None = None,
    *,
    noise: float = DEFAULT_NOISE,
    max_error: float = 0.05,
    min_slope: float = 0.02,
    k_sigma: float = 3.0,
) -> InverseResult:
    """:func:`cellbridge.tactile.inversion.solve`, compiled (same arguments, same answers)."""
    p, tab, c1, c2 = _inputs(dC1, dC2, params, noise, max_error, min_slope, k_sigma)
    shape = c1.shape
    n = c1.size
    out = np.empty((6, n))
    status = np.empty(n, dtype=np.uint8)
    _solve_kernel(
        np.ascontiguousarray(c1).ravel(), np.ascontiguousarray(c2).ravel(), element_vector(p), tab.hi_q,
        tab.hi_lns, tab.ln_r_pk, tab.ln_r_end, tab.info.sigma_peak, tab.lo_r, tab.lo_c1_full, p.area,
        float(noise), float(max_error), float(min_slope), float(k_sigma), out, status,
    )
    return InverseResult(
        out[0].reshape(shape), out[1].reshape(shape), (status == 0).reshape(shape), out[2].reshape(shape),
        out[3].reshape(shape), out[4].reshape(shape), status.reshape(shape),
    )


@compiled
def _interp(x: float, xp: np.ndarray, fp: np.ndarray) -> float:
    """np.interp for one x (numba's costs a pass over the table per call): bisection."""
    n = xp.size
    if not x >= xp[0]:  # NaN included, as np.interp gives fp[0] below the table
        return fp[0] if x == x else x
    if x >= xp[n - 1]:
        return fp[n - 1]
    lo, hi = 0, n - 1
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if xp[mid] <= x:
            lo = mid
        else:
            hi = mid
    slope = (fp[hi] - fp[lo]) / (xp[hi] - xp[lo])
    return slope * (x - xp[lo]) + fp[lo]


@compiled
def _solve_kernel(
    c1: np.ndarray, c2: np.ndarray, par: np.ndarray, hi_q: np.ndarray, hi_lns: np.ndarray, ln_r_pk: float,
    ln_r_end: float, sigma_peak: float, lo_r: np.ndarray, lo_c1_full: np.ndarray, elem_area: float,
    noise: float, max_error: float, min_slope: float, k_sigma: float, out: np.ndarray, status: np.ndarray,
) -> None:
    """The rules of :func:`solve`, one reading at a time (compiled: a frame's dozen
    elements cost microseconds, not the ~170 µs of numpy's per-call overhead).

    ``out`` rows: force, area, pressure, force_rms, diameter_rms (NaN where the
    rules say so); ``status``: the :class:`InverseStatus` bits.
    """
    floor = k_sigma * noise
    r0 = lo_r[0]
    r_pk = lo_r[-1]
    nan = np.nan
    for i in range(c1.size):
        a = c1[i]
        b = c2[i]
        for k in range(5):
            out[k, i] = nan
        st = 0
        finite = math.isfinite(a) and math.isfinite(b)
        if not finite:
            st |= 1  # NONFINITE
        # `not >` keeps NaN out and demands a strictly positive signal when noise is 0.
        if not (a > floor and b > floor and a > 0.0 and b > 0.0):
            if finite:
                st |= 2  # BELOW_NOISE
            status[i] = st
            continue
        if not finite:
            status[i] = st
            continue
        lnr = math.log(a) - math.log(b)
        if not (lnr >= ln_r_end and lnr <= ln_r_pk):
            status[i] = st | 4  # NO_SOLUTION
            continue
        # Falling-branch pressure: table, then one Newton step in ln σ.
        q = math.sqrt(max(ln_r_pk - lnr, 0.0))
        lns = _interp(q, hi_q, hi_lns)
        g1, e1 = layer_response(math.exp(lns), par[0], par[1], par[2], par[3])
        g2, e2 = layer_response(math.exp(lns), par[4], par[5], par[6], par[7])
        slope = e1 - e2
        converged = slope != 0.0
        if converged:
            lns = lns - (math.log(g1) - math.log(g2) - lnr) / slope
        sigma = math.exp(lns)
        g1, e1 = layer_response(sigma, par[0], par[1], par[2], par[3])
        g2, e2 = layer_response(sigma, par[4], par[5], par[6], par[7])
        slope = e1 - e2
        # What the step left over, as an error of ln σ; a guard, not a tolerance
        # that normal readings come near (they reach ~1e-10).
        converged = converged and slope != 0.0 and abs((math.log(g1) - math.log(g2) - lnr) / slope) <= 1e-8
        on_branch = sigma >= sigma_peak
        area = a / g1
        force = sigma * area
        # First-order noise propagation through the log-Jacobian
        # [[e1, 1−e1], [e2, 1−e2]] of (ln F, ln S) → (ln ΔC1, ln ΔC2).
        n1 = noise / a
        n2 = noise / b
        inv = 1.0 / abs(slope) if slope != 0.0 else math.inf
        rel_f = math.hypot((1.0 - e2) * n1, (1.0 - e1) * n2) * inv
        rel_s = math.hypot(e2 * n1, e1 * n2) * inv
        rel_d = 0.5 * rel_s
        if not (abs(slope) >= min_slope and rel_f <= max_error and rel_d <= max_error and converged and on_branch):
            st |= 16  # ILL_CONDITIONED
        if not (area - k_sigma * rel_s * area <= elem_area * (1.0 + 1e-9)):
            st |= 32  # AREA_EXCEEDS
        # Ambiguity (see _ambiguous): the box ±floor around the reading against the lens.
        r_max = (a + floor) / (b - floor)
        r_min = (a - floor) / (b + floor)
        h = _interp(min(r_max, r_pk), lo_r, lo_c1_full)
        if r_max >= r0 and r_min <= r_pk and a - floor <= h:
            st |= 8  # AMBIGUOUS
        status[i] = st
        if st == 0:
            out[0, i] = force
            out[1, i] = area
        out[2, i] = sigma
        diam = 2.0 * math.sqrt(a / g1 / math.pi)
        out[3, i] = rel_f * sigma * a / g1
        out[4, i] = rel_d * diam
