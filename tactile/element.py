"""Forward model of one two-layer nonlinear tactile element (paper §II.B, eqs. 1-3).

An element is two stacked parallel-plate capacitors: a soft upper foam (C1) and a
hard lower foam (C2). Both foams follow the entropy-elasticity law of eq. 2, but
saturate at different pressures, so the pair (ΔC1, ΔC2) carries two independent
numbers about a contact: its force F and its area S. This module maps (F, S) to
(ΔC1, ΔC2); :mod:`cellbridge.tactile.inversion` goes back.

Assumptions (the paper's): uniform pressure σ = F/S over the contact (eq. 1), zero
Poisson ratio and negligible sheet tension, so each point of a foam compresses
according to its local pressure only, and no fringing fields. Under these, a contact
of area S at pressure σ changes capacitance n by exactly ``S·g_n(σ)`` where
``g_n = ε_n·Δd_n / (d_n·(d_n − Δd_n))`` (see :func:`sensitivity`), whatever the shape
of the contact and wherever it lies on the element. That is what lets the skin model
split a straddling contact over several elements by overlap area.

Everything is in SI units (Pa, m, F, N, m²) and vectorised over numpy arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from cellbridge.tactile.arrays import FloatArray
from numpy.typing import ArrayLike

__all__ = [
    "EPS0",
    "ElementParams",
    "compression",
    "sensitivity",
    "forward",
    "capacitance",
    "rest_capacitance",
]

#: Vacuum permittivity (F/m), CODATA 2018.
EPS0 = 8.8541878128e-12


@dataclass(frozen=True)
class ElementParams:
    """Geometry and materials of one element; defaults are the project's reference skin.

    Layer 1 is the soft upper foam (capacitor C1), layer 2 the hard lower foam (C2).
    ``d*0`` is the thickness a foam reaches under infinite pressure (eq. 2's λ = 0).
    ``side`` is the edge of the square element, equal to the pitch of the skin.
    ``parasitic*`` is the fixed capacitance the bridge sees in parallel with each foam
    capacitor (wiring, pads); it does not change with pressure.
    """

    E1: float = 4.8e3
    E2: float = 15e3
    d1: float = 5.0e-3
    d2: float = 3.0e-3
    d10: float = 1.0e-3
    d20: float = 0.6e-3
    eps_r1: float = 2.0
    eps_r2: float = 2.0
    side: float = 0.040
    parasitic1: float = 10e-12
    parasitic2: float = 10e-12

    def __post_init__(self) -> None:
        for name in ("E1", "E2", "d1", "d2", "eps_r1", "eps_r2", "side"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"ElementParams.{name} must be finite and > 0, got {v!r}")
        for name in ("d10", "d20", "parasitic1", "parasitic2"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"ElementParams.{name} must be finite and >= 0, got {v!r}")
        if not self.d10 < self.d1:
            raise ValueError(f"saturated thickness d10={self.d10} must be < d1={self.d1}")
        if not self.d20 < self.d2:
            raise ValueError(f"saturated thickness d20={self.d20} must be < d2={self.d2}")

    # Derived quantities. Plain properties (not cached) keep the dataclass frozen and
    # trivially picklable; each is a couple of float operations.
    @property
    def area(self) -> float:
        """Area of the element (m²): the largest contact area one element can see."""
        return self.side * self.side

    @property
    def eps1(self) -> float:
        """Permittivity of the soft foam (F/m)."""
        return EPS0 * self.eps_r1

    @property
    def eps2(self) -> float:
        """Permittivity of the hard foam (F/m)."""
        return EPS0 * self.eps_r2

    @property
    def C1_0(self) -> float:
        """Foam capacitance C1 at rest, without parasitics (F)."""
        return self.eps1 * self.area / self.d1

    @property
    def C2_0(self) -> float:
        """Foam capacitance C2 at rest, without parasitics (F)."""
        return self.eps2 * self.area / self.d2

    @property
    def C1_rest(self) -> float:
        """C1 at rest as the bridge measures it, parasitic included (F)."""
        return self.C1_0 + self.parasitic1

    @property
    def C2_rest(self) -> float:
        """C2 at rest as the bridge measures it, parasitic included (F)."""
        return self.C2_0 + self.parasitic2

    @property
    def g1_max(self) -> float:
        """Limit of ΔC1 per unit contact area as σ → ∞ (F/m²): the foam fully saturated."""
        return self.eps1 * (self.d1 - self.d10) / (self.d1 * self.d10)

    @property
    def g2_max(self) -> float:
        """Limit of ΔC2 per unit contact area as σ → ∞ (F/m²)."""
        return self.eps2 * (self.d2 - self.d20) / (self.d2 * self.d20)


DEFAULT_PARAMS = ElementParams()


def _stretch(u: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Root λ of λ³ + 3uλ − 1 = 0 (u = σ/E ≥ 0) and its complement 1 − λ.

    Eq. 2 with λ ∈ (0, 1] is this depressed cubic; for u ≥ 0 it has exactly one real
    root. Cardano's formula ``λ = A − u/A`` with ``A = ∛(½ + √(¼ + u³))`` is exact but
    cancels catastrophically for large u (λ ≈ 1/(3u) is the difference of two numbers
    ≈ √u), and ``1 − λ`` cancels for small u (where it is ≈ u). Both are rewritten
    without subtractions of nearly equal numbers:

    * u ≤ 1: ``λ = A²/(A⁴ + A²u + u²)`` (from A⁶ − u³ = A³), and
      ``1 − λ = (A²(A²−1) + A²u + u²)/(A⁴ + A²u + u²)`` with
      ``A − 1 = u³/((√(¼+u³) + ½)(A² + A + 1))`` — every term non-negative.
    * u > 1: with ``w = u^(−3/2)``, ``r = A²/u = ∛((w/2 + √(w²/4 + 1))²)`` and
      ``λ = r/(u(r² + r + 1))``; no overflow even for σ/E ≈ 1e300, and 1 − λ has
      no cancellation there because λ < 0.33.
    """
    big = u > 1.0
    any_big = bool(big.any())
    all_big = bool(big.all()) if any_big else False
    # Only the branches some entry needs: small arrays (one frame's elements) are
    # all on one side, and numpy's per-call overhead is most of their cost.
    if not all_big:
        # Small branch, evaluated on u clipped to [0, 1] so it never overflows.
        lam_s, one_m_s = _stretch_small(np.minimum(u, 1.0))
        if not any_big:
            return np.asarray(lam_s), np.asarray(one_m_s)

    # Large branch, on u clipped to [1, ∞].
    with np.errstate(invalid="ignore"):  # u = inf: inf·(finite) is fine, r/inf → 0
        lam_b = _stretch_large(np.maximum(u, 1.0))
    if all_big:
        return np.asarray(lam_b), np.asarray(1.0 - lam_b)
    lam = np.where(big, lam_b, lam_s)
    one_m = np.where(big, 1.0 - lam_b, one_m_s)
    return lam, one_m


# The closed forms themselves, elementwise (operators and numpy ufuncs only): numpy
# arrays here and in the inverse, floats in the compiled kernels, which compile these
# same functions (cellbridge.tactile.disk_model.layer_response), so one copy of the
# physics serves both.


def _stretch_small(u: FloatArray) -> tuple[FloatArray, FloatArray]:
    """λ and 1 − λ for 0 ≤ u ≤ 1, without cancellation (see :func:`_stretch`)."""
    us3 = u * u * u
    s = np.sqrt(0.25 + us3)
    a = np.cbrt(0.5 + s)
    a2 = a * a
    den = a2 * a2 + a2 * u + u * u
    am1 = us3 / ((s + 0.5) * (a2 + a + 1.0))
    return a2 / den, (a2 * am1 * (a + 1.0) + a2 * u + u * u) / den


def _stretch_large(u: FloatArray) -> FloatArray:
    """λ for u ≥ 1 (1 − λ does not cancel there), no overflow up to u = inf (see :func:`_stretch`)."""
    w = u**-1.5
    r = np.cbrt(np.square(0.5 * w + np.sqrt(0.25 * w * w + 1.0)))
    return r / (u * (r * r + r + 1.0))


def _g_of(lam: FloatArray, one_m: FloatArray, d: float, d0: float, eps: float) -> FloatArray:
    """ΔC per unit contact area of one layer from its stretch λ and 1 − λ (eq. 3's integrand)."""
    span = d - d0
    # d − Δd = d0 + (d − d0)·λ: written this way it never cancels near saturation.
    return eps * span * one_m / (d * (d0 + span * lam))


def _elasticity(lam: FloatArray, d: float, d0: float) -> FloatArray:
    """d ln g / d ln σ for one layer, written in λ so it never cancels.

    From g ∝ (1−λ)/(d0 + (d−d0)λ) and dσ/dλ of eq. 2:
    ``e = λ(1+λ+λ²)·d / ((1+2λ³)(d0 + (d−d0)λ))`` — 1 at rest, → 0 in saturation.
    """
    lam2 = lam * lam
    return lam * (1.0 + lam + lam2) * d / ((1.0 + 2.0 * lam2 * lam) * (d0 + (d - d0) * lam))


def _as_float_array(x: ArrayLike, name: str) -> FloatArray:
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a real number or array of them: {exc}") from None
    return arr


def _check_pressure(sigma: FloatArray) -> None:
    # NaN fails `>= 0`, so one test catches both negative and NaN entries.
    if not np.all(sigma >= 0.0):
        bad = sigma[~(sigma >= 0.0)].flat[0]
        raise ValueError(f"pressure sigma must be >= 0 Pa (and not NaN), got {bad!r}")


def compression(sigma: ArrayLike, E: float, d: float, d0: float) -> FloatArray:
    """Compression Δd (m) of one foam layer under uniform pressure ``sigma`` (Pa).

    Solves eq. 2, ``σ = E/3·(1/λ − λ²)`` with ``λ = 1 − Δd/(d − d0)``, for the one
    root λ ∈ (0, 1] in closed form (Cardano, rearranged to stay accurate to a few ulp
    from σ/E ≈ 1e-300 to 1e300 and at σ = +inf). Small σ gives the linear
    law Δd ≈ σ(d − d0)/E; σ → ∞ gives Δd → d − d0, the saturated thickness d0 left.
    """
    s = _as_float_array(sigma, "sigma")
    _check_pressure(s)
    if not (E > 0 and d > d0 >= 0):
        raise ValueError(f"need E > 0 and d > d0 >= 0, got E={E!r}, d={d!r}, d0={d0!r}")
    _, one_m = _stretch(s / E)
    return (d - d0) * one_m


def _g(sigma: FloatArray, E: float, d: float, d0: float, eps: float) -> FloatArray:
    """ΔC per unit contact area of one layer; no input checks (internal hot path)."""
    lam, one_m = _stretch(sigma / E)
    return _g_of(lam, one_m, d, d0, eps)


def _sensitivity(sigma: FloatArray, p: ElementParams) -> tuple[FloatArray, FloatArray]:
    return (
        _g(sigma, p.E1, p.d1, p.d10, p.eps1),
        _g(sigma, p.E2, p.d2, p.d20, p.eps2),
    )


def sensitivity(
    sigma: ArrayLike, params: ElementParams | None = None
) -> tuple[FloatArray, FloatArray]:
    """Capacitance change per unit of pressed area, (g1, g2) in F/m², at pressure σ (Pa).

    ``g_n = ε_n·Δd_n/(d_n·(d_n − Δd_n))`` is eq. 3's integrand change at one point.
    Because every point of a contact sees the same σ = F/S (eq. 1) and points do not
    interact (zero Poisson ratio, no tension), any part of area A of a contact that
    lies on an element changes that element by ``A·g_n(σ)``. The ratio g1/g2 depends
    on σ only, which is what the inverse exploits.
    """
    p = DEFAULT_PARAMS if params is None else params
    s = _as_float_array(sigma, "sigma")
    _check_pressure(s)
    return _sensitivity(s, p)


def _check_force_area(
    force: ArrayLike, area: ArrayLike, p: ElementParams
) -> tuple[FloatArray, FloatArray]:
    f = _as_float_array(force, "force")
    a = _as_float_array(area, "area")
    if not np.all(np.isfinite(f)):
        raise ValueError("force must be finite (got NaN or inf)")
    if not np.all(f >= 0.0):
        raise ValueError(f"force must be >= 0 N, got {f[f < 0].flat[0]!r}")
    if not np.all(np.isfinite(a)):
        raise ValueError("area must be finite (got NaN or inf)")
    if not np.all(a > 0.0):
        raise ValueError(f"contact area must be > 0 m², got {a[~(a > 0)].flat[0]!r}")
    # A contact larger than the element belongs to several elements: the skin model
    # splits it by overlap before calling this function. A relative slack of a few ulp
    # lets callers pass side**2 computed their own way.
    limit = p.area * (1.0 + 1e-12)
    if not np.all(a <= limit):
        raise ValueError(
            f"contact area {a[a > limit].flat[0]!r} m² exceeds the element area "
            f"{p.area!r} m² (side {p.side} m); split the contact over elements first"
        )
    try:
        f, a = np.broadcast_arrays(f, a)
    except ValueError:
        raise ValueError(
            f"force shape {f.shape} and area shape {a.shape} do not broadcast"
        ) from None
    return f, a


def forward(
    force: ArrayLike, area: ArrayLike, params: ElementParams | None = None
) -> tuple[FloatArray, FloatArray]:
    """Capacitance changes (ΔC1, ΔC2) in farads for a contact of ``force`` N over ``area`` m².

    The contact lies wholly on the element (area ≤ side²). Inputs broadcast against
    each other; force 0 gives exactly 0. Raises ValueError for negative, NaN or
    infinite inputs, for a non-positive area and for an area beyond the element.
    """
    p = DEFAULT_PARAMS if params is None else params
    f, a = _check_force_area(force, area, p)
    g1, g2 = _sensitivity(f / a, p)
    return a * g1, a * g2


def capacitance(
    force: ArrayLike, area: ArrayLike, params: ElementParams | None = None
) -> tuple[FloatArray, FloatArray]:
    """Absolute capacitances (C1, C2) in farads as the bridge sees them, parasitics included."""
    p = DEFAULT_PARAMS if params is None else params
    dc1, dc2 = forward(force, area, p)
    return p.C1_rest + dc1, p.C2_rest + dc2


def rest_capacitance(params: ElementParams | None = None) -> tuple[float, float]:
    """(C1, C2) of an untouched element, parasitics included (F)."""
    p = DEFAULT_PARAMS if params is None else params
    return p.C1_rest, p.C2_rest
