"""Which (ΔC1, ΔC2) readings a contact can make: the element's (F, S) surface.

A disk of area S at pressure σ = F/S moves the two layers by
``ΔC_n = S·g_n(σ)`` (eq. 3), so every contact reading lies on the ray of ratio
ρ(σ) = g1/g2 through the origin, and ρ only takes values between its limit under full
saturation (ρ∞) and its peak (ρ_peak); ΔC1 can never exceed the whole element fully
saturated (``area·g1_max``). A part of a straddling contact sees the same pressure, so
it lies on the same rays. Readings outside that cone are made by something else: one
layer drifting alone (a parasitic moving with temperature), or both layers moving in a
proportion no pressure gives.

The calibrator uses this to tell a press held for an hour (keep it) from an element
drifting by itself (follow it, never report it as touched). Pure numpy, no state.

Limits: a reading is tested, not a history. A drift that happens to move both layers in
a proportion a contact also gives (e.g. a dielectric change of both foams, whose ratio
d2/d1 equals ρ∞ with the default foams) lies on the surface and cannot be told from a
saturated press by one reading.
"""

from __future__ import annotations

import numpy as np
from cellbridge.tactile.arrays import FloatArray
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.inversion import branch_info
from numpy.typing import NDArray

__all__ = ["ContactSurface"]


class ContactSurface:
    """Callable test ``surface(delta, noise=None) -> (N,) bool``: True where the (N, 2)
    reading ΔC lies within ``k_sigma`` noise sigmas (per channel) of a reading some
    contact makes. The noise is the larger of this object's ``noise`` and the optional
    (N, 2) measured noise of each reading (F): an ADC front end's coarse steps widen the
    tolerance by themselves.

    Rows with a non-finite value are False (no reading is no contact's reading). The
    tolerance keeps a light press whose ratio noise pushes past the peak on the surface:
    a press is never taken for drift because of its noise.
    """

    def __init__(self, params: ElementParams, noise: float, k_sigma: float = 3.0) -> None:
        if not (noise >= 0 and np.isfinite(noise)):
            raise ValueError(f"noise must be finite and >= 0 F, got {noise!r}")
        if not (k_sigma >= 0 and np.isfinite(k_sigma)):
            raise ValueError(f"k_sigma must be finite and >= 0, got {k_sigma!r}")
        info = branch_info(params)
        self.ratio_low = float(info.ratio_inf)  #: ΔC1/ΔC2 of a fully saturated press
        self.ratio_high = float(info.ratio_peak)  #: the largest ΔC1/ΔC2 any pressure gives
        self.dc1_max = float(params.area * params.g1_max)  #: ΔC1 of the whole element saturated
        self.noise = float(noise)
        self.k_sigma = float(k_sigma)

    def __call__(self, delta: FloatArray, noise: FloatArray | None = None) -> NDArray[np.bool_]:
        d = np.asarray(delta, dtype=np.float64)
        if d.ndim != 2 or d.shape[1] != 2:
            raise ValueError(f"delta must have shape (N, 2), got {d.shape}")
        sigma = np.full(d.shape, self.noise)
        if noise is not None:
            sigma = np.fmax(sigma, np.broadcast_to(np.asarray(noise, dtype=np.float64), d.shape))
        x, y = d[:, 0], d[:, 1]
        t1, t2 = self.k_sigma * sigma[:, 0], self.k_sigma * sigma[:, 1]
        # the box of half-widths (t1, t2) around (x, y) meets the cone ρ∞·y' ≤ x' ≤ ρ_peak·y',
        # y' ≥ 0: some y' in [y − t2, y + t2] (and ≥ 0) with (x − t1)/ρ_peak ≤ y' ≤ (x + t1)/ρ∞
        with np.errstate(invalid="ignore"):
            lo = np.maximum(np.maximum((x - t1) / self.ratio_high, y - t2), 0.0)
            hi = np.minimum((x + t1) / self.ratio_low, y + t2)
            ok = (lo <= hi) & (x <= self.dc1_max + t1)
        return ok & np.isfinite(d).all(axis=1)
