"""The skin's response: (ΔC1, ΔC2) of every element for several simultaneous disk
contacts, under the paper's assumptions (uniform pressure F/S, no sheet tension) or with
an optional membrane-tension spread (a 2-D Gaussian blur of the pressure field, paper
§III.A). Units are SI (m, N, Pa, F)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from cellbridge.tactile.arrays import FloatArray, IntArray
from cellbridge.tactile.element import ElementParams, sensitivity
from cellbridge.tactile.layout import SkinLayout
from cellbridge.tactile.overlap import disk_rect_overlap
from numpy.typing import ArrayLike

__all__ = ["as_contacts", "disk_response", "pressure_field", "skin_response"]


def as_contacts(contacts: ArrayLike) -> FloatArray:
    """Validate contacts as an (M, 4) array of ``(x, y, force, diameter)`` rows.

    A single contact may be given as a flat 4-sequence; an empty list is no contact.
    """
    c = np.asarray(contacts, dtype=np.float64)
    if c.size == 0:
        return np.zeros((0, 4))
    if c.ndim == 1:
        c = c[None, :]
    if c.ndim != 2 or c.shape[1] != 4:
        raise ValueError(f"contacts must be (x, y, force, diameter) rows, got shape {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("contacts must be finite")
    if np.any(c[:, 2] < 0):
        raise ValueError("contact force must be >= 0 N")
    if np.any(c[:, 3] <= 0):
        raise ValueError("contact diameter must be > 0 m")
    return c


def _i0e(x: FloatArray) -> FloatArray:
    # exp(−x)·I0(x) for x >= 0 without overflow: numpy's i0 below 500, the
    # asymptotic series (error < 1e-12 there) above.
    out = np.empty_like(x)
    small = x < 500.0
    xs = x[small]
    out[small] = np.i0(xs) * np.exp(-xs)
    xl = x[~small]
    t = 1.0 / (8.0 * xl)
    out[~small] = (1.0 + t * (1.0 + t * (4.5 + t * 37.5))) / np.sqrt(2.0 * np.pi * xl)
    return out


_GL_R = np.polynomial.legendre.leggauss(24)


def _disk_blur(rho: FloatArray, radius: FloatArray, s: float) -> FloatArray:
    """Indicator of a disk convolved with an isotropic 2-D Gaussian (std s), at distance ρ.

    In polar coordinates around the disk centre the angular integral is a Bessel
    function: Φ(ρ) = ∫₀ᴿ (r/s²)·exp(−(r−ρ)²/2s²)·i0e(rρ/s²) dr. The integrand is
    negligible (< e⁻³²) beyond |r − ρ| > 8s, and a 24-point Gauss–Legendre rule over
    that window is accurate to ~1e-14.
    """
    lo = np.maximum(rho - 8.0 * s, 0.0)
    hi = np.minimum(rho + 8.0 * s, radius)
    ok = hi > lo
    t, w = _GL_R
    mid = 0.5 * (hi + lo)
    half = np.where(ok, 0.5 * (hi - lo), 0.0)
    r = mid[..., None] + half[..., None] * t
    rr = rho[..., None]
    f = (r / (s * s)) * np.exp(-0.5 * ((r - rr) / s) ** 2) * _i0e(r * rr / (s * s))
    return np.clip((f * w).sum(axis=-1) * half, 0.0, 1.0)


@dataclass(frozen=True)
class _Nodes:
    xy: FloatArray  # (P, 2) quadrature points
    w: FloatArray  # (P,) weights (m²)
    elem: IntArray  # (P,) element index of each point


_NODE_CACHE: dict[tuple[bytes, int], _Nodes] = {}


def _element_nodes(bounds: FloatArray, q: int) -> _Nodes:
    # Tensor-product Gauss rule on q×q sub-cells per element, 2×2 points per cell:
    # fourth-order accurate for the smooth (blurred) integrand.
    key = (bounds.tobytes(), q)
    hit = _NODE_CACHE.get(key)
    if hit is not None:
        return hit
    g = 0.5 + 0.5 * np.array([-1.0, 1.0]) / math.sqrt(3.0)
    u = ((np.arange(q)[:, None] + g[None, :]) / q).ravel()  # in (0, 1)
    ux, uy = np.meshgrid(u, u, indexing="ij")
    wx = bounds[:, 2] - bounds[:, 0]
    wy = bounds[:, 3] - bounds[:, 1]
    x = bounds[:, None, 0] + ux.ravel()[None, :] * wx[:, None]
    y = bounds[:, None, 1] + uy.ravel()[None, :] * wy[:, None]
    xy = np.stack([x.ravel(), y.ravel()], axis=1)
    w = np.repeat(wx * wy / (4.0 * q * q), u.size * u.size)
    elem = np.repeat(np.arange(bounds.shape[0]), u.size * u.size)
    nodes = _Nodes(xy, w, elem)
    if len(_NODE_CACHE) > 64:
        _NODE_CACHE.clear()
    _NODE_CACHE[key] = nodes
    return nodes


def _spread_cells(side: float, spread: float, quad_step: float | None) -> int:
    step = 0.5 * spread if quad_step is None else float(quad_step)
    if not (math.isfinite(step) and step > 0):
        raise ValueError(f"quad_step must be > 0 m, got {quad_step!r}")
    return int(min(max(math.ceil(side / step), 4), 256))


def pressure_field(
    points: ArrayLike, contacts: ArrayLike, spread: float = 0.0
) -> FloatArray:
    """Pressure (Pa) at ``points`` (…, 2) from disk contacts, after the tension spread.

    ``spread = 0`` is eq. 1: F/S inside each disk, 0 outside. ``spread = s > 0`` blurs
    that field with a normalised 2-D Gaussian of standard deviation s (per axis), which
    keeps each contact's total force but spreads it beyond the footprint.
    """
    c = as_contacts(contacts)
    p = np.asarray(points, dtype=np.float64)
    if p.shape[-1:] != (2,):
        raise ValueError(f"points must have shape (..., 2), got {p.shape}")
    s = _check_spread(spread)
    flat = p.reshape(-1, 2)
    out = np.zeros(flat.shape[0])
    for x, y, f, d in c:
        rad = 0.5 * d
        sigma = _nominal_pressure(f, rad)
        rho = np.hypot(flat[:, 0] - x, flat[:, 1] - y)
        if s == 0.0:
            out += np.where(rho <= rad, sigma, 0.0)
        else:
            out += _blurred_pressure(rho, rad, sigma, s)
    return out.reshape(p.shape[:-1])


_Real = TypeVar("_Real", float, FloatArray)


def _nominal_pressure(force: _Real, radius: _Real) -> _Real:
    """Eq. 1: F/S of a disk, the pressure on its footprint before any spread."""
    return force / (math.pi * radius * radius)


def _blurred_pressure(rho: FloatArray, radius: float, sigma: float, s: float) -> FloatArray:
    """Pressure at distances ρ from the centre of a disk of nominal pressure σ after
    the tension spread s > 0 (through the disk's tabulated profile)."""
    grid, prof = _disk_profile(radius, s)
    return sigma * _on_profile(rho, grid, prof)


def _on_profile(rho: FloatArray, grid: FloatArray, table: FloatArray) -> FloatArray:
    """A table over a disk's profile grid at distances ρ: its first value inside the
    grid's start (the flat middle of the disk), 0 beyond the blurred rim."""
    return np.interp(rho, grid, table, left=table[0], right=0.0)


def _per_element(
    elem: IntArray, w: FloatArray, g1: FloatArray, g2: FloatArray, n: int
) -> tuple[FloatArray, FloatArray]:
    """(ΔC1, ΔC2) of ``n`` elements: the quadrature sums of g1 and g2 at nodes
    ``elem`` of weights ``w``."""
    return (  # type: ignore[return-value]  # numpy's stubs type bincount as integer even with float weights
        np.bincount(elem, weights=g1 * w, minlength=n),
        np.bincount(elem, weights=g2 * w, minlength=n),
    )


#: Smallest non-zero spread (m): below it the blurred rim is narrower than float64
#: resolves at a contact's radius, and the profile table collapses.
MIN_SPREAD = 1e-9


def _check_spread(spread: float) -> float:
    s = float(spread)
    if not (math.isfinite(s) and s >= 0):
        raise ValueError(f"spread must be finite and >= 0 m, got {spread!r}")
    if 0 < s < MIN_SPREAD:
        raise ValueError(
            f"spread must be 0 or >= {MIN_SPREAD:g} m (a sub-nanometre blur is none), got {spread!r}"
        )
    return s


def disk_response(
    layout: SkinLayout,
    contacts: ArrayLike,
    params: ElementParams | None = None,
    spread: float = 0.0,
    quad_step: float | None = None,
) -> tuple[FloatArray, FloatArray]:
    """(M, N) ΔC1 and ΔC2 of every element for each contact *on its own*.

    Without spread, responses of separate (non-overlapping) disks add, so
    :func:`skin_response` is the column sum of this. With spread they do not (the
    foams are nonlinear in the summed pressure); this is then what each contact would
    do alone, which is what a one-disk fit needs for many candidate disks at once.
    """
    return _disk_response(layout.bounds, layout.side, as_contacts(contacts), params, spread, quad_step)


def _disk_response(
    bounds: FloatArray,
    side: float,
    c: FloatArray,
    params: ElementParams | None,
    spread: float,
    quad_step: float | None,
) -> tuple[FloatArray, FloatArray]:
    # Per-disk responses on the elements ``bounds`` (any subset of a layout).
    s = _check_spread(spread)
    m, n = c.shape[0], bounds.shape[0]
    if m == 0:
        return np.zeros((0, n)), np.zeros((0, n))
    rad = 0.5 * c[:, 3]
    sigma = _nominal_pressure(c[:, 2], rad)
    if s == 0.0:
        g1, g2 = sensitivity(sigma, params)
        a = disk_rect_overlap(
            c[:, :1], c[:, 1:2], rad[:, None],
            bounds[None, :, 0], bounds[None, :, 1], bounds[None, :, 2], bounds[None, :, 3],
        )
        return a * g1[:, None], a * g2[:, None]
    nodes = _element_nodes(bounds, _spread_cells(side, s, quad_step))
    out1 = np.zeros((m, n))
    out2 = np.zeros((m, n))
    for k in range(m):  # per contact: only the nodes it can reach are evaluated
        p = _disk_g_on_nodes(nodes, c[k], s, params)
        if p is None:
            continue
        idx, g1, g2 = p
        out1[k], out2[k] = _per_element(nodes.elem[idx], nodes.w[idx], g1, g2, n)
    return out1, out2


_PROFILE_STEPS_PER_S = 40


_PROFILE_CACHE: dict[tuple[float, float], tuple[FloatArray, FloatArray]] = {}


def _disk_profile(radius: float, s: float) -> tuple[FloatArray, FloatArray]:
    """Φ(ρ) of :func:`_disk_blur` tabulated every s/40 over the disk's blurred rim.

    The profile is smooth on the scale s, so linear interpolation in this table is
    accurate to ~2e-5 and costs one Bessel quadrature per table point instead of one
    per quadrature node of the elements. Profiles are cached by (R, s): a fit
    evaluates many disks of the same size at different places.
    """
    key = (float(radius), float(s))
    hit = _PROFILE_CACHE.get(key)
    if hit is not None:
        return hit
    lo = max(radius - 8.0 * s, 0.0)
    hi = radius + 8.0 * s
    n = int(math.ceil((hi - lo) / s * _PROFILE_STEPS_PER_S)) + 1
    rho = np.linspace(lo, hi, n)
    out = (rho, _disk_blur(rho, np.full(n, radius), s))
    if len(_PROFILE_CACHE) >= 256:
        _PROFILE_CACHE.clear()
    _PROFILE_CACHE[key] = out
    return out


def _near_nodes(nodes: _Nodes, x: float, y: float, reach: float) -> tuple[IntArray, FloatArray]:
    dx = nodes.xy[:, 0] - x
    dy = nodes.xy[:, 1] - y
    idx = np.nonzero((np.abs(dx) < reach) & (np.abs(dy) < reach))[0]
    return idx, np.hypot(dx[idx], dy[idx])


def _profile_near(
    nodes: _Nodes, contact: FloatArray, s: float
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray, float] | None:
    """Nodes a blurred disk reaches, their distance to its centre, the disk's radial
    profile and its nominal pressure; None when the contact touches no node."""
    x, y, f, d = contact
    rad = 0.5 * d
    if f == 0.0:
        return None
    idx, rho = _near_nodes(nodes, x, y, rad + 8.0 * s)
    if idx.size == 0:
        return None
    grid, prof = _disk_profile(rad, s)
    return idx, rho, grid, prof, _nominal_pressure(f, rad)


def _blurred_on_nodes(nodes: _Nodes, contact: FloatArray, s: float) -> tuple[IntArray, FloatArray] | None:
    near = _profile_near(nodes, contact, s)
    if near is None:
        return None
    idx, rho, grid, prof, sigma = near
    return idx, sigma * _on_profile(rho, grid, prof)


def _disk_g_on_nodes(
    nodes: _Nodes, contact: FloatArray, s: float, params: ElementParams | None
) -> tuple[IntArray, FloatArray, FloatArray] | None:
    # One contact alone: g_n(σ·Φ(ρ)) is itself a smooth function of ρ, so it is
    # tabulated on the profile grid and interpolated, instead of solving eq. 2 at
    # every node.
    near = _profile_near(nodes, contact, s)
    if near is None:
        return None
    idx, rho, grid, prof, sigma = near
    g1t, g2t = sensitivity(sigma * prof, params)
    return idx, _on_profile(rho, grid, g1t), _on_profile(rho, grid, g2t)


def skin_response(
    layout: SkinLayout,
    contacts: ArrayLike,
    params: ElementParams | None = None,
    spread: float = 0.0,
    quad_step: float | None = None,
) -> tuple[FloatArray, FloatArray]:
    """(ΔC1, ΔC2) in farads of every element, shape (N,), for simultaneous disk contacts.

    ``contacts`` are ``(x, y, force, diameter)`` rows (m, m, N, m); the disks must not
    overlap one another. With ``spread = 0`` (the paper's assumption) each element sees
    the exact part of each disk lying on it at that disk's pressure F/S, and parts add:
    ``ΔC_n,i = Σ_j A_ij·g_n(F_j/S_j)``. Force that lands in a seam or off the skin is
    simply not measured.

    ``spread = s > 0`` models the tension of the conductive sheets (paper §III.A,
    Fig. 5): the pressure field of all contacts is summed and blurred with a 2-D
    Gaussian of standard deviation s (force conserved), and eqs. 2–3 are applied
    point by point, ``ΔC_n,i = ∫_element g_n(σ_blurred(x, y)) dA``, integrated with a
    2×2-point Gauss rule on cells of ``quad_step`` (default s/2). The paper's eq. 4
    writes the same bell as exp(−x²/s_paper²), i.e. s_paper = √2·s.
    """
    c = as_contacts(contacts)
    s = _check_spread(spread)
    if c.shape[0] == 0:
        return np.zeros(layout.n), np.zeros(layout.n)
    if s == 0.0:
        d1, d2 = disk_response(layout, c, params)
        return d1.sum(axis=0), d2.sum(axis=0)
    nodes = _element_nodes(layout.bounds, _spread_cells(layout.side, s, quad_step))
    press = np.zeros(nodes.xy.shape[0])
    for k in range(c.shape[0]):
        p = _blurred_on_nodes(nodes, c[k], s)
        if p is not None:
            press[p[0]] += p[1]
    g1, g2 = sensitivity(press, params)
    return _per_element(nodes.elem, nodes.w, g1, g2, layout.n)
