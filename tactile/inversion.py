"""Inverse of the element model: (ΔC1, ΔC2) → (force, area), with a validity flag.

Why it works: a contact of area S at pressure σ = F/S changes the two capacitors by
``S·g1(σ)`` and ``S·g2(σ)`` (:func:`cellbridge.tactile.element.sensitivity`), so the
ratio ρ = ΔC1/ΔC2 = g1(σ)/g2(σ) depends on σ alone. Solve σ from ρ, then
S = ΔC1/g1(σ) and F = σ·S.

Why it needs a flag: ρ(σ) is not monotonic. From ρ(0) (≈1.88 with the default
element) it rises to a peak ρ_pk (≈2.32 at σ ≈ 3.2 kPa) and then falls towards
g1(∞)/g2(∞) (0.60). Each ratio in (ρ(0), ρ_pk) has two pressures: a low one on
the rising branch and a high one on the falling branch. Nothing in the ratio tells
them apart; what sometimes does is the element size: the low-pressure reading of the
same (ΔC1, ΔC2) needs a larger area (g1 grows with σ), and when that area exceeds
the element the low reading is impossible and the high one is the answer. So this
module always solves the falling branch and declares the result valid only when

* both ΔC are finite and at least ``k_sigma·noise`` (a real signal, not noise);
* ρ lies inside the falling branch's range (otherwise no contact produces it);
* no point of the ±``k_sigma·noise`` box around (ΔC1, ΔC2) can be the reading of a
  rising-branch contact inside the element (so the answer is unique despite noise);
* the branch is not flat: ``|d ln ρ / d ln σ| ≥ min_slope`` (near the peak and in
  deep saturation the ratio stops carrying information);
* noise of ``noise`` rms on each channel moves F and the diameter D by at most
  ``max_error`` (relative, one sigma), from first-order error propagation;
* the area fits the element (S ≤ side², within ``k_sigma`` of its own noise).

Invalid entries get NaN force and area; a status bitmask says why (see :class:`InverseStatus`).
Speed comes from a precomputed table per :class:`ElementParams` (ln σ against
√(ln ρ_pk − ln ρ), smooth through the peak) and one vectorised Newton step in ln σ
with the analytic slope; a reading whose step did not converge is flagged too.
"""

from __future__ import annotations

import enum
import functools
from typing import Callable, NamedTuple

import numpy as np
from cellbridge.tactile.arrays import FloatArray
from cellbridge.tactile.element import DEFAULT_PARAMS, ElementParams, _elasticity, _g_of, _stretch
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "DEFAULT_NOISE",
    "InverseStatus",
    "InverseResult",
    "BranchInfo",
    "branch_info",
    "solve",
    "inverse",
    "ratio",
    "ratio_slope",
]


#: Default rms noise of one ΔC measurement (F): one 2 ms counter gate, as measured on
#: the emulated chip (bench/bench_chip.py, docs/emulator-chip.md): 0.27 fF on C1 and
#: 0.57 fF on C2 at rest, 0.64 fF on C2 at the quantiser's worst phase; rounded up.
DEFAULT_NOISE = 7e-16


class InverseStatus(enum.IntFlag):
    """Why an inverse entry is invalid (bits may combine). 0 means valid."""

    OK = 0
    NONFINITE = 1  #: a ΔC is NaN or infinite
    BELOW_NOISE = 2  #: a ΔC is below k_sigma·noise (includes zero and negative)
    NO_SOLUTION = 4  #: ratio above the peak, or at/below full saturation: no contact gives it
    AMBIGUOUS = 8  #: a low-pressure contact inside the element gives the same reading
    ILL_CONDITIONED = 16  #: ratio too flat in σ, noise gives more than max_error, or no convergence
    AREA_EXCEEDS = 32  #: the area found is larger than the element


class InverseResult(NamedTuple):
    """Full answer of :func:`solve`; arrays of the broadcast input shape."""

    force: FloatArray  #: N, NaN where invalid
    area: FloatArray  #: m², NaN where invalid
    valid: NDArray[np.bool_]
    pressure: FloatArray  #: Pa on the falling branch, NaN where there is none
    force_rms: FloatArray  #: N, one-sigma error from ``noise`` (first order)
    diameter_rms: FloatArray  #: m, one-sigma error of D = 2√(S/π) from ``noise``
    status: NDArray[np.uint8]  #: :class:`InverseStatus` bits


class BranchInfo(NamedTuple):
    """Landmarks of ρ(σ) for one element; used by the inverse and the plot."""

    ratio_zero: float  #: ρ(σ → 0)
    ratio_peak: float  #: maximum of ρ
    sigma_peak: float  #: Pa where the maximum is
    ratio_inf: float  #: ρ(σ → ∞)
    sigma_unique: float  #: Pa on the falling branch where ρ = ρ(0): above it no ambiguity at all


def _layers(
    sigma: FloatArray, p: ElementParams
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """g1, g2 (F/m²) and their elasticities e1, e2 at σ."""
    lam1, om1 = _stretch(sigma / p.E1)
    lam2, om2 = _stretch(sigma / p.E2)
    g1 = _g_of(lam1, om1, p.d1, p.d10, p.eps1)
    g2 = _g_of(lam2, om2, p.d2, p.d20, p.eps2)
    return g1, g2, _elasticity(lam1, p.d1, p.d10), _elasticity(lam2, p.d2, p.d20)


def ratio(sigma: ArrayLike, params: ElementParams | None = None) -> FloatArray:
    """ρ(σ) = ΔC1/ΔC2 of a contact at pressure σ (Pa); the σ → 0 limit at σ = 0."""
    p = DEFAULT_PARAMS if params is None else params
    s = np.asarray(sigma, dtype=np.float64)
    r0 = _ratio_zero(p)
    with np.errstate(invalid="ignore", divide="ignore"):
        g1, g2, _, _ = _layers(s, p)
        return np.where(s > 0, g1 / g2, r0)


def ratio_slope(sigma: ArrayLike, params: ElementParams | None = None) -> FloatArray:
    """d ln ρ / d ln σ: how much the ratio says about σ (0 at the peak and at saturation)."""
    p = DEFAULT_PARAMS if params is None else params
    _, _, e1, e2 = _layers(np.asarray(sigma, dtype=np.float64), p)
    return e1 - e2


def _ratio_zero(p: ElementParams) -> float:
    # Small σ: g_n ≈ ε_n (d_n − d_n0) σ / (E_n d_n²).
    k1 = p.eps1 * (p.d1 - p.d10) / (p.E1 * p.d1**2)
    k2 = p.eps2 * (p.d2 - p.d20) / (p.E2 * p.d2**2)
    return k1 / k2


class _Tables(NamedTuple):
    info: BranchInfo
    # Falling branch: q = √(ln ρ_pk − ln ρ) (increasing with σ) → ln σ. Near the peak
    # ln ρ is quadratic in ln σ, so q is nearly linear there and interpolation in q
    # stays accurate where interpolation in ρ would meet a square-root singularity.
    hi_q: FloatArray
    hi_lns: FloatArray
    ln_r_pk: float
    ln_r_end: float  # ln ρ at the table's high-σ end
    # Rising branch: ρ (increasing) → ΔC1 of a whole-element contact at that ρ.
    lo_r: FloatArray
    lo_c1_full: FloatArray


_TABLE_POINTS = 4096


@functools.lru_cache(maxsize=32)
def _tables(p: ElementParams) -> _Tables:
    """Precompute both branches for one element (cached: ElementParams is hashable)."""
    e_min = min(p.E1, p.E2)
    # Locate the peak of ρ on a log grid, then refine with bisection on the slope.
    s = np.geomspace(1e-6 * e_min, 1e8 * e_min, 20001)
    slope = ratio_slope(s, p)
    i = int(np.argmax(slope < 0))
    if i == 0 or not slope[i] < 0:
        raise ValueError(
            "the ratio ΔC1/ΔC2 of these element parameters has no falling branch: "
            "the soft layer must saturate before the hard one (E1 < E2 or similar)"
        )
    lo, hi = s[i - 1], s[i]
    for _ in range(80):
        mid = np.sqrt(lo * hi)
        if ratio_slope(mid, p) > 0:
            lo = mid
        else:
            hi = mid
    sigma_pk = float(np.sqrt(lo * hi))
    r_pk = float(ratio(sigma_pk, p))
    r0 = _ratio_zero(p)
    g1i, g2i = p.g1_max, p.g2_max
    r_inf = g1i / g2i

    # Falling branch from the peak to where the ratio carries ~nothing (|slope| ≤ 1e-4).
    s_hi = np.geomspace(sigma_pk, 1e8 * e_min, 200001)
    sl = ratio_slope(s_hi, p)
    flat = np.nonzero(np.abs(sl) < 1e-4)[0]
    flat = flat[flat > 10]
    s_end = s_hi[flat[0]] if flat.size else s_hi[-1]
    s_hi = np.geomspace(sigma_pk, s_end, _TABLE_POINTS)
    r_hi = ratio(s_hi, p)
    if not np.all(np.diff(r_hi) < 0):
        raise ValueError("the falling branch of ΔC1/ΔC2 is not monotonic for these parameters")
    ln_r_pk = float(np.log(r_pk))
    hi_q = np.sqrt(np.maximum(ln_r_pk - np.log(r_hi), 0.0))
    hi_q[0] = 0.0
    hi_lns = np.log(s_hi)

    # σ where the falling branch comes back down to ρ(0).
    if r0 < r_pk and r0 > r_hi[-1]:
        sigma_unique = float(np.exp(np.interp(np.sqrt(ln_r_pk - np.log(r0)), hi_q, hi_lns)))
    else:
        sigma_unique = float("nan")

    # Rising branch: 0 … σ_pk, dense near both ends.
    t = np.linspace(0.0, 1.0, _TABLE_POINTS)
    s_lo = sigma_pk * (0.5 - 0.5 * np.cos(np.pi * t))
    r_lo = ratio(s_lo, p)
    r_lo = np.maximum.accumulate(r_lo)  # guard the last ulp near the peak
    g1_lo, _, _, _ = _layers(s_lo, p)
    info = BranchInfo(r0, r_pk, sigma_pk, r_inf, sigma_unique)
    return _Tables(info, hi_q, hi_lns, ln_r_pk, float(np.log(r_hi[-1])), r_lo, p.area * g1_lo)


def branch_info(params: ElementParams | None = None) -> BranchInfo:
    """Peak, limits and the unconditional-uniqueness pressure of ρ(σ) for one element."""
    return _tables(DEFAULT_PARAMS if params is None else params).info


# The rules per reading, written once. Each function is elementwise: solve() calls it
# on numpy arrays, and :mod:`cellbridge.tactile.inverse_kernel` compiles these same
# functions (numba, numpy's error model) for its loop over floats, so the numpy
# inverse and the compiled one cannot drift apart. Only operators and numpy ufuncs
# here, no branches on values: that is what both numpy and numba take as they are.


def _strong(c1: FloatArray, c2: FloatArray, floor: float) -> NDArray[np.bool_]:
    """Both readings clear the noise floor; written as `>` so NaN fails it, and a
    strictly positive signal is demanded when the floor is 0."""
    return (c1 > floor) & (c2 > floor) & (c1 > 0) & (c2 > 0)


def _on_falling_range(lnr: FloatArray, ln_r_end: float, ln_r_pk: float) -> NDArray[np.bool_]:
    """ln ρ lies on the falling branch's table (else no contact gives the reading)."""
    return (lnr >= ln_r_end) & (lnr <= ln_r_pk)


def _branch_q(lnr: FloatArray, ln_r_pk: float) -> FloatArray:
    """The falling-branch table's coordinate √(ln ρ_pk − ln ρ) of a ratio."""
    return np.sqrt(np.maximum(ln_r_pk - lnr, 0.0))


def _newton_step(lnr: FloatArray, g1: FloatArray, g2: FloatArray, slope: FloatArray) -> FloatArray:
    """Newton step in ln σ towards ln(g1/g2) = ln ρ, with ``slope`` = e1 − e2 = d ln ρ / d ln σ."""
    return (np.log(g1) - np.log(g2) - lnr) / slope


def _judge(
    c1: FloatArray, c2: FloatArray, sigma: FloatArray, g1: FloatArray, e1: FloatArray, e2: FloatArray,
    left: FloatArray, sigma_peak: float, elem_area: float, noise: float, max_error: float, min_slope: float,
    k_sigma: float,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, NDArray[np.bool_], NDArray[np.bool_]]:
    """Force, area, their noise and the two tests of a solved reading.

    ``sigma`` is the falling-branch pressure after the Newton step, g1, e1, e2 the
    layers' response there and ``left`` the next Newton step from it. Returns (force,
    area, force_rms, diameter_rms, well_conditioned, fits_element); the caller masks
    what its status rejects.
    """
    slope = e1 - e2
    # What the step left over, as an error of ln σ; a guard, not a tolerance
    # that normal readings come near (they reach ~1e-10).
    converged = np.abs(left) <= 1e-8
    on_branch = sigma >= sigma_peak
    area = c1 / g1
    force = sigma * area
    # First-order noise propagation through the log-Jacobian
    # [[e1, 1−e1], [e2, 1−e2]] of (ln F, ln S) → (ln ΔC1, ln ΔC2).
    n1 = noise / c1
    n2 = noise / c2
    inv = 1.0 / np.abs(slope)
    rel_f = np.hypot((1.0 - e2) * n1, (1.0 - e1) * n2) * inv
    rel_s = np.hypot(e2 * n1, e1 * n2) * inv
    rel_d = 0.5 * rel_s
    well = (np.abs(slope) >= min_slope) & (rel_f <= max_error) & (rel_d <= max_error) & converged & on_branch
    fits = area - k_sigma * rel_s * area <= elem_area * (1.0 + 1e-9)
    diam = 2.0 * np.sqrt(c1 / g1 / np.pi)
    return force, area, rel_f * sigma * c1 / g1, rel_d * diam, well, fits


def _noise_box(c1: FloatArray, c2: FloatArray, margin: float) -> tuple[FloatArray, FloatArray]:
    """Largest and smallest ratio ΔC1/ΔC2 in the box ±``margin`` around a reading."""
    return (c1 + margin) / (c2 - margin), (c1 - margin) / (c2 + margin)


def _in_lens(
    c1: FloatArray, r_max: FloatArray, r_min: FloatArray, margin: float, h: FloatArray, r0: float, r_pk: float
) -> NDArray[np.bool_]:
    """The noise box may touch the rising branch's lens; ``h`` = h(min(r_max, ρ_pk))."""
    return (r_max >= r0) & (r_min <= r_pk) & (c1 - margin <= h)


def _ambiguous(c1: FloatArray, c2: FloatArray, margin: float, tab: _Tables) -> NDArray[np.bool_]:
    """True where a rising-branch contact inside the element may give the same reading.

    The rising branch maps onto the lens ρ ∈ [ρ(0), ρ_pk], ΔC1 ≤ h(ρ) where
    h(ρ) = A·g1(σ_low(ρ)) is the whole-element reading at that ratio (h grows with
    ρ). A reading is ambiguous when its box ±``margin`` on each channel may touch
    the lens. The test is conservative: the smallest ΔC1 of the box against h at the
    largest ratio the box reaches (capped at the peak), so noise can never carry a
    reading across the lens boundary unflagged.
    """
    r0 = tab.lo_r[0]
    r_pk = tab.lo_r[-1]
    r_max, r_min = _noise_box(c1, c2, margin)
    # c2 ≤ margin only happens for readings already rejected as below the noise.
    r_max = np.where(c2 > margin, r_max, np.inf)
    h = np.interp(np.minimum(r_max, r_pk), tab.lo_r, tab.lo_c1_full)
    return _in_lens(c1, r_max, r_min, margin, h, r0, r_pk)


_B_NONFINITE = np.uint8(InverseStatus.NONFINITE)
_B_BELOW_NOISE = np.uint8(InverseStatus.BELOW_NOISE)
_B_NO_SOLUTION = np.uint8(InverseStatus.NO_SOLUTION)
_B_AMBIGUOUS = np.uint8(InverseStatus.AMBIGUOUS)
_B_ILL_CONDITIONED = np.uint8(InverseStatus.ILL_CONDITIONED)
_B_AREA_EXCEEDS = np.uint8(InverseStatus.AREA_EXCEEDS)

#: What an inverse computes on flat (1-D) readings: (force, area, pressure, force_rms,
#: diameter_rms, status), NaN where the status says so. Arguments: c1, c2, element,
#: tables, noise, max_error, min_slope, k_sigma (already checked).
FlatSolver = Callable[
    [FloatArray, FloatArray, ElementParams, _Tables, float, float, float, float],
    tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, NDArray[np.uint8]],
]


def _solve_with(
    flat: FlatSolver, dC1: ArrayLike, dC2: ArrayLike, params: ElementParams | None, noise: float,
    max_error: float, min_slope: float, k_sigma: float,
) -> InverseResult:
    """:func:`solve`'s checks, tables and shapes around ``flat``, the per-reading work
    (numpy here, compiled in :mod:`cellbridge.tactile.inverse_kernel`)."""
    p = DEFAULT_PARAMS if params is None else params
    if not (np.isfinite(noise) and noise >= 0):
        raise ValueError(f"noise must be a finite rms capacitance >= 0 F, got {noise!r}")
    if not (max_error > 0 and min_slope >= 0 and k_sigma >= 0):
        raise ValueError("need max_error > 0, min_slope >= 0 and k_sigma >= 0")
    c1, c2 = np.broadcast_arrays(np.asarray(dC1, dtype=np.float64), np.asarray(dC2, dtype=np.float64))
    shape = c1.shape
    force, area, sigma, force_rms, diameter_rms, status = flat(
        c1.ravel(), c2.ravel(), p, _tables(p), float(noise), float(max_error), float(min_slope), float(k_sigma)
    )
    return InverseResult(
        force.reshape(shape),
        area.reshape(shape),
        (status == 0).reshape(shape),
        sigma.reshape(shape),
        force_rms.reshape(shape),
        diameter_rms.reshape(shape),
        status.reshape(shape),
    )


def solve(
    dC1: ArrayLike,
    dC2: ArrayLike,
    params: ElementParams | None = None,
    *,
    noise: float = DEFAULT_NOISE,
    max_error: float = 0.05,
    min_slope: float = 0.02,
    k_sigma: float = 3.0,
) -> InverseResult:
    """Invert capacitance changes (F) to force (N) and area (m²) with diagnostics.

    ``noise`` is the rms noise of each ΔC (F); 0 means exact data. ``max_error``
    bounds the one-sigma relative error of F and of D = 2√(S/π) that noise may cause;
    ``min_slope`` rejects the flat parts of ρ(σ) even for exact data; ``k_sigma``
    sets how many sigmas a signal must clear, and how wide the ambiguity and area
    checks look. See the module docstring for the rules.
    """
    return _solve_with(_solve_flat, dC1, dC2, params, noise, max_error, min_slope, k_sigma)


def _solve_flat(
    c1: FloatArray, c2: FloatArray, p: ElementParams, tab: _Tables, noise: float, max_error: float,
    min_slope: float, k_sigma: float,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, NDArray[np.uint8]]:
    """The rules on flat arrays, in numpy (see :data:`FlatSolver`)."""
    status = np.zeros(c1.shape, dtype=np.uint8)

    finite = np.isfinite(c1) & np.isfinite(c2)
    status[~finite] |= _B_NONFINITE
    floor = k_sigma * noise
    weak = ~_strong(c1, c2, floor)
    status[weak & finite] |= _B_BELOW_NOISE

    with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
        # Garbage readings (e.g. 1e308 F) overflow here too; they are flagged.
        lnr = np.log(c1) - np.log(c2)
        out_of_range = ~_on_falling_range(lnr, tab.ln_r_end, tab.ln_r_pk)
        status[out_of_range & ~weak & finite] |= _B_NO_SOLUTION

        # Falling-branch pressure: table, then one Newton step in ln σ.
        lns = np.interp(_branch_q(lnr, tab.ln_r_pk), tab.hi_q, tab.hi_lns)
        g1, g2, e1, e2 = _layers(np.exp(lns), p)
        lns = lns - _newton_step(lnr, g1, g2, e1 - e2)
        sigma = np.exp(lns)
        g1, g2, e1, e2 = _layers(sigma, p)
        force, area, force_rms, diameter_rms, well, fits = _judge(
            c1, c2, sigma, g1, e1, e2, _newton_step(lnr, g1, g2, e1 - e2), tab.info.sigma_peak, p.area, noise,
            max_error, min_slope, k_sigma,
        )
        amb = _ambiguous(c1, c2, floor, tab)

    solvable = finite & ~weak & ~out_of_range
    status[solvable & ~well] |= _B_ILL_CONDITIONED
    status[solvable & ~fits] |= _B_AREA_EXCEEDS
    status[solvable & amb] |= _B_AMBIGUOUS
    valid = status == 0

    nan = np.float64(np.nan)
    return (
        np.where(valid, force, nan),
        np.where(valid, area, nan),
        np.where(solvable, sigma, nan),
        np.where(solvable, force_rms, nan),
        np.where(solvable, diameter_rms, nan),
        status,
    )


def inverse(
    dC1: ArrayLike,
    dC2: ArrayLike,
    params: ElementParams | None = None,
    noise: float = DEFAULT_NOISE,
    **options: float,
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """(force N, area m², valid) from capacitance changes (ΔC1, ΔC2) in farads.

    Shorthand for :func:`solve` (same keywords: ``max_error``, ``min_slope``,
    ``k_sigma``). Invalid entries carry NaN force and area, never a guess.
    """
    r = solve(dC1, dC2, params, noise=noise, **options)
    return r.force, r.area, r.valid
