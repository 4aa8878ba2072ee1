"""The element inverse of :func:`cellbridge.tactile.inversion.solve`, compiled.

The same rules, one reading at a time: a frame's dozen elements cost microseconds here
against ~170 µs of numpy's per-call overhead, a third of a one-contact frame of the
contact estimator, which already runs compiled kernels. :func:`solve` itself stays
numpy: the daemon's per-element physics must import and run where numba cannot
(no executable memory under ``MemoryDenyWriteExecute``). tests/test_tactile_inverse.py
checks that both give the same status bits and values within 1e-10.

One copy of the rules: the per-reading functions of :mod:`cellbridge.tactile.inversion`
(noise floor, branch range, Newton step, conditioning, area, ambiguity box) are
compiled here as they are, and :func:`solve_compiled` shares :func:`solve`'s checks,
tables and result through ``_solve_with``. Only the loop and the two table look-ups
are this module's own.
"""

from __future__ import annotations

import math

import numpy as np
from cellbridge.tactile import inversion
from cellbridge.tactile._jit import compiled
from cellbridge.tactile.disk_model import element_vector, layer_response
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.inversion import InverseResult, _solve_with, _Tables, solve
from numpy.typing import ArrayLike

__all__ = ["solve_compiled"]


def solve_compiled(
    dC1: ArrayLike, dC2: ArrayLike, params: ElementParams | None = None, **options: float
) -> InverseResult:
    """:func:`cellbridge.tactile.inversion.solve`, compiled: the same keywords with the
    same defaults (``noise``, ``max_error``, ``min_slope``, ``k_sigma``), the same answers."""
    if not options.keys() <= _SOLVE_DEFAULTS.keys():
        raise TypeError(f"solve_compiled() takes solve()'s keywords {sorted(_SOLVE_DEFAULTS)}, "
                        f"not {sorted(options.keys() - _SOLVE_DEFAULTS.keys())}")
    return _solve_with(_solve_flat, dC1, dC2, params, **{**_SOLVE_DEFAULTS, **options})


#: solve()'s keyword defaults, taken from solve itself so they are written once.
_SOLVE_DEFAULTS: dict[str, float] = dict(solve.__kwdefaults__ or {})


def _solve_flat(
    c1: np.ndarray, c2: np.ndarray, p: ElementParams, tab: _Tables, noise: float, max_error: float,
    min_slope: float, k_sigma: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:data:`cellbridge.tactile.inversion.FlatSolver`, compiled."""
    n = c1.size
    out = np.empty((5, n))
    status = np.empty(n, dtype=np.uint8)
    _solve_kernel(
        np.ascontiguousarray(c1), np.ascontiguousarray(c2), element_vector(p), tab.hi_q, tab.hi_lns, tab.ln_r_pk,
        tab.ln_r_end, tab.info.sigma_peak, tab.lo_r, tab.lo_c1_full, p.area, noise, max_error, min_slope,
        k_sigma, out, status,
    )
    return out[0], out[1], out[2], out[3], out[4], status


# inversion's per-reading rules, compiled as they are (numpy's error model: x/0 is
# inf or NaN as in the numpy inverse, which the rules then reject).
_strong = compiled(inversion._strong, error_model="numpy")
_on_falling_range = compiled(inversion._on_falling_range, error_model="numpy")
_branch_q = compiled(inversion._branch_q, error_model="numpy")
_newton_step = compiled(inversion._newton_step, error_model="numpy")
_judge = compiled(inversion._judge, error_model="numpy")
_noise_box = compiled(inversion._noise_box, error_model="numpy")
_in_lens = compiled(inversion._in_lens, error_model="numpy")


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
        if not _strong(a, b, floor):
            if finite:
                st |= 2  # BELOW_NOISE
            status[i] = st
            continue
        if not finite:
            status[i] = st
            continue
        lnr = math.log(a) - math.log(b)
        if not _on_falling_range(lnr, ln_r_end, ln_r_pk):
            status[i] = st | 4  # NO_SOLUTION
            continue
        # Falling-branch pressure: table, then one Newton step in ln σ.
        lns = _interp(_branch_q(lnr, ln_r_pk), hi_q, hi_lns)
        g1, e1 = layer_response(math.exp(lns), par[0], par[1], par[2], par[3])
        g2, e2 = layer_response(math.exp(lns), par[4], par[5], par[6], par[7])
        lns = lns - _newton_step(lnr, g1, g2, e1 - e2)
        sigma = math.exp(lns)
        g1, e1 = layer_response(sigma, par[0], par[1], par[2], par[3])
        g2, e2 = layer_response(sigma, par[4], par[5], par[6], par[7])
        force, area, force_rms, diameter_rms, well, fits = _judge(
            a, b, sigma, g1, e1, e2, _newton_step(lnr, g1, g2, e1 - e2), sigma_peak, elem_area, noise, max_error,
            min_slope, k_sigma,
        )
        if not well:
            st |= 16  # ILL_CONDITIONED
        if not fits:
            st |= 32  # AREA_EXCEEDS
        r_max, r_min = _noise_box(a, b, floor)
        if _in_lens(a, r_max, r_min, floor, _interp(min(r_max, r_pk), lo_r, lo_c1_full), r0, r_pk):
            st |= 8  # AMBIGUOUS
        status[i] = st
        if st == 0:
            out[0, i] = force
            out[1, i] = area
        out[2, i] = sigma
        out[3, i] = force_rms
        out[4, i] = diameter_rms
