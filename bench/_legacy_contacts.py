"""Frozen copy of the contact estimator as it was before the compiled fit kernel.

Kept only here, for ``bench/bench_contacts.py`` to measure the speed-up over it in
the same run, on the same readings; it is not part of the package and nothing else
imports it. Original module docstring follows.

Contacts from the whole array: clustering, force, area and a position finer than an element.

One element cannot tell where on it a contact sits (eq. 3 integrates over it). The
array can, as soon as a contact straddles a seam: how the footprint is shared between
the elements it lies on depends on where it is. Two estimates are made per contact:

* the paper's **force-weighted centroid** of the element centres (§III.B, Fig. 7),
  cheap but pulled towards the element centres: a 10 mm disk a few millimetres over a
  seam is placed tens of millimetres away from where it is;
* a **model-based fit** of one uniform-pressure disk (centre, diameter, force) to
  what every element of the cluster and its neighbours measured. Under eqs. 1-3 an
  element that sees area A of a disk at pressure σ = F/S changes by A·g_n(σ), and A
  is the exact disk∩element overlap (:func:`cellbridge.tactile.skin.disk_rect_overlap`),
  so the shares determine the centre. Fitting happens in capacitance space by
  default (weighted least squares with the measurement noise, so elements whose own
  inverse is invalid — a small share, a reading below the inverse's noise floor —
  still count, and quiet neighbours say "the disk is not here"); ``method="area"``
  fits the per-element areas S_i of the inverse instead. The membrane-tension spread
  model is used when it is on.

Every estimate comes with a covariance from the fit. Where the data cannot see a
coordinate at all — a disk wholly inside one element, or along a seam it straddles —
that coordinate is reported at the middle of the positions consistent with the
readings, with the standard deviation of a uniform distribution over them, never the
arbitrary point a solver stopped at.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Callable, Literal, NamedTuple, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellbridge.tactile.element import ElementParams, sensitivity
from cellbridge.tactile.inversion import DEFAULT_NOISE, InverseResult, solve
from cellbridge.tactile.skin import SkinLayout, _check_spread, _disk_response, disk_rect_overlap

__all__ = [
    "Contact",
    "ContactEstimator",
    "cluster_elements",
    "force_centroid",
    "estimate_contacts",
]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class Contact:
    """One contact on the skin (SI units; positions in the layout's frame).

    ``x, y`` is the best position: the model fit when it succeeded, else the
    centroid. ``force`` and ``diameter`` are the fitted disk's (else the sums of the
    elements and 2√(area/π)); ``area`` is the contact area the elements measured, so
    it leaves out any part of the disk off the skin or in a seam. ``sigma_x/y`` are
    one-sigma position uncertainties under the configured noise, ``sigma_xy`` the
    larger semi-axis of the covariance ``cov``. ``observable`` says per axis whether
    the readings determine that coordinate (False: the value is the middle of the
    consistent range). ``valid`` is False when no element's inverse gave a pressure
    (too light a touch, or the ambiguous low-pressure region): only the position is
    meaningful then.
    """

    x: float
    y: float
    force: float
    area: float
    diameter: float
    centroid_x: float
    centroid_y: float
    model_x: float
    model_y: float
    sigma_x: float
    sigma_y: float
    sigma_xy: float
    cov: tuple[tuple[float, float], tuple[float, float]]
    sigma_force: float
    sigma_diameter: float
    elements: tuple[int, ...]
    valid: bool
    fit_ok: bool
    observable: tuple[bool, bool]
    pressure: float
    force_sum: float
    chi2: float
    dof: int

    def to_dict(self) -> dict[str, object]:
        """Plain dict of Python scalars and lists (msgpack/JSON ready)."""
        d = asdict(self)
        d["cov"] = [list(r) for r in self.cov]
        d["elements"] = list(self.elements)
        d["observable"] = list(self.observable)
        return d


# ------------------------------------------------------------------------- clusters


def cluster_elements(
    layout: SkinLayout,
    active: ArrayLike,
    connectivity: Literal["edge", "corner"] = "edge",
) -> IntArray:
    """Connected components of the active elements: a label per element, -1 if inactive.

    Labels are 0..K-1, numbered by the lowest element index in each component.
    Neighbourhood comes from the layout's geometry (edge-sharing by default).
    """
    a = np.asarray(active, dtype=bool)
    if a.shape != (layout.n,):
        raise ValueError(f"active must have shape ({layout.n},), got {a.shape}")
    e = layout.edges if connectivity == "edge" else layout.corner_edges
    e = e[a[e[:, 0]] & a[e[:, 1]]]
    lab = np.arange(layout.n)
    while True:  # min-label propagation with pointer jumping: O(log diameter) passes
        m = np.minimum(lab[e[:, 0]], lab[e[:, 1]])
        new = lab.copy()
        np.minimum.at(new, e[:, 0], m)
        np.minimum.at(new, e[:, 1], m)
        new = new[new]
        if np.array_equal(new, lab):
            break
        lab = new
    out = np.full(layout.n, -1, dtype=np.int64)
    roots = np.unique(lab[a])
    out[a] = np.searchsorted(roots, lab[a])
    return out


def force_centroid(layout: SkinLayout, weights: ArrayLike, members: ArrayLike) -> tuple[float, float]:
    """The paper's spatial centroid Σw_i·c_i/Σw_i over ``members`` (indices)."""
    idx = np.asarray(members, dtype=np.int64)
    w = np.asarray(weights, dtype=np.float64)[idx]
    w = np.where(np.isfinite(w) & (w > 0), w, 0.0)
    tot = w.sum()
    c = layout.centres[idx]
    if not tot > 0:
        return float(c[:, 0].mean()), float(c[:, 1].mean())
    return float(w @ c[:, 0] / tot), float(w @ c[:, 1] / tot)


# ----------------------------------------------------------------------------- fit


def _lm(
    fun: Callable[[FloatArray], FloatArray],
    theta0: FloatArray,
    steps: FloatArray,
    ranges: FloatArray,
    max_iter: int = 60,
) -> tuple[FloatArray, FloatArray, FloatArray, bool]:
    """Levenberg–Marquardt on residuals ``fun(thetas (K, p)) -> (K, m)``.

    The central-difference Jacobian and the current point are evaluated in one
    batched call. A parameter whose column changes the residuals by less than 1e-3
    over its typical range ``ranges`` is held still in that iteration: the readings
    say nothing about it there (a disk inside one element does not see its position),
    and a solve would move it by round-off amplified. Returns (θ, residuals,
    Jacobian at θ, converged).
    """
    p = theta0.size
    theta = theta0.astype(np.float64).copy()
    eye = np.eye(p)

    def jac(th: FloatArray) -> tuple[FloatArray, FloatArray]:
        pts = np.concatenate([th[None], th + eye * steps, th - eye * steps])
        r = fun(pts)
        return r[0], ((r[1 : p + 1] - r[p + 1 :]) / (2.0 * steps[:, None])).T

    r, J = jac(theta)
    cost = float(r @ r)
    lam = 1e-3
    converged = False
    for _ in range(max_iter):
        free = np.sqrt((J * J).sum(axis=0)) * ranges > 1e-3
        if not free.any():
            converged = True
            break
        Jf = J[:, free]
        A = Jf.T @ Jf
        g = Jf.T @ r
        d = np.diag(A).copy()
        improved = False
        small = False
        while lam < 1e12:
            try:
                step = np.linalg.solve(A + lam * np.diag(d), -g)
            except np.linalg.LinAlgError:
                lam *= 10.0
                continue
            delta = np.zeros(p)
            delta[free] = step
            trial = theta + delta
            rt = fun(trial[None])[0]
            ct = float(rt @ rt)
            if np.isfinite(ct) and ct <= cost:
                # Whitened residuals: a cost change of 1e-12 is a millionth of a sigma.
                small = cost - ct <= 1e-9 * cost + 1e-12
                theta = trial
                cost = ct
                lam = max(lam / 5.0, 1e-12)
                improved = True
                break
            lam *= 5.0
        if not improved:
            converged = True  # no downhill step left at any damping: a minimum
            break
        r, J = jac(theta)
        if small or np.all(np.abs(delta) <= 1e-3 * steps):
            converged = True
            break
    return theta, r, J, converged


@dataclass
class _Obs:
    idx: IntArray  # layout indices of the elements observed in this fit
    bounds: FloatArray
    dc: FloatArray  # (2, n) observed ΔC1, ΔC2
    area: FloatArray  # (n,) area per element (inverse where valid, shared-pressure estimate else)
    quiet: NDArray[np.bool_]  # (n,) not touched: a neighbour in the ring around the cluster


class ContactEstimator:
    """Turns per-element ΔC (and touch flags) of one time step into :class:`Contact` s.

    ``noise`` is the rms noise of one ΔC reading (F, scalar or per channel); it
    weights the fit and scales every reported uncertainty. ``spread`` is the
    membrane-tension model of :func:`cellbridge.tactile.skin.skin_response` (0: the
    paper's assumption). ``method`` picks what the disk is fitted to:
    ``"capacitance"`` (ΔC of the cluster and its neighbours; default) or ``"area"``
    (the per-element areas from the inverse; uniform pressure only).
    """

    def __init__(
        self,
        layout: SkinLayout,
        params: ElementParams | None = None,
        *,
        spread: float = 0.0,
        noise: float | Sequence[float] = DEFAULT_NOISE,
        method: Literal["capacitance", "area"] = "capacitance",
        connectivity: Literal["edge", "corner"] = "edge",
        quad_step: float | None = None,
        inverse_options: dict[str, float] | None = None,
    ):
        self.layout = layout
        self.params = params if params is not None else ElementParams(side=layout.side)
        self.spread = _check_spread(spread)
        nz = np.broadcast_to(np.asarray(noise, dtype=np.float64), (2,)).copy()
        if not np.all(np.isfinite(nz)) or not np.all(nz > 0):
            raise ValueError("noise must be > 0 F (one value or one per channel)")
        self.noise = nz
        if method not in ("capacitance", "area"):
            raise ValueError(f"method must be 'capacitance' or 'area', got {method!r}")
        if method == "area" and self.spread > 0:
            raise ValueError("method='area' assumes uniform pressure; use 'capacitance' with spread")
        self.method = method
        if connectivity not in ("edge", "corner"):
            raise ValueError(f"connectivity must be 'edge' or 'corner', got {connectivity!r}")
        self.connectivity = connectivity
        self.quad_step = quad_step
        self.inverse_options = dict(inverse_options or {})
        self._ring = layout.adjacency("corner")
        self._uniform = self if self.spread == 0 else ContactEstimator(
            layout, self.params, noise=tuple(nz), method=method, connectivity=connectivity,
            inverse_options=inverse_options,
        )

    # -- public -----------------------------------------------------------------------
    def estimate(
        self,
        dC1: ArrayLike,
        dC2: ArrayLike,
        active: ArrayLike | None = None,
    ) -> list[Contact]:
        """Contacts from ΔC (F) of every element; ``active`` = touched elements.

        Without ``active``, an element is active when either channel exceeds three
        noise sigmas. NaN readings count as inactive and are left out of the fits.
        """
        lay = self.layout
        c1 = np.asarray(dC1, dtype=np.float64)
        c2 = np.asarray(dC2, dtype=np.float64)
        if c1.shape != (lay.n,) or c2.shape != (lay.n,):
            raise ValueError(f"dC1 and dC2 must have shape ({lay.n},)")
        finite = np.isfinite(c1) & np.isfinite(c2)
        if active is None:
            act = finite & ((c1 > 3 * self.noise[0]) | (c2 > 3 * self.noise[1]))
        else:
            act = np.asarray(active, dtype=bool)
            if act.shape != (lay.n,):
                raise ValueError(f"active must have shape ({lay.n},)")
            act = act & finite
        inv = solve(c1, c2, self.params, noise=float(self.noise.max()), **self.inverse_options)
        labels = cluster_elements(lay, act, self.connectivity)
        out = []
        for k in range(int(labels.max()) + 1 if act.any() else 0):
            members = np.nonzero(labels == k)[0]
            out.append(self._one(members, labels, c1, c2, finite, inv))
        return out

    # -- one cluster --------------------------------------------------------------------
    def _one(
        self, members: IntArray, labels: IntArray, c1: FloatArray, c2: FloatArray,
        finite: NDArray[np.bool_], inv: InverseResult,
    ) -> Contact:
        lay = self.layout
        valid = inv.valid[members]
        ids = tuple(int(i) for i in lay.ids[members])
        # Shared pressure: every part of one uniform disk is at the same σ.
        fv = inv.force[members][valid]
        sv = inv.area[members][valid]
        sigma0 = float(fv.sum() / sv.sum()) if valid.any() else math.nan

        # Observed elements: the cluster, plus its ring of neighbours that belong to no
        # other cluster and have a reading (they say where the disk is *not*).
        ring = self._ring[members].any(axis=0)
        ring[members] = False
        ring &= (labels < 0) & finite
        idx = np.concatenate([members, np.nonzero(ring)[0]])
        dc = np.stack([c1[idx], c2[idx]])
        area_i, force_i = self._areas(idx, dc, sigma0, inv)

        wts = np.where(np.isfinite(force_i[: members.size]), force_i[: members.size], 0.0)
        if not (wts > 0).any():
            wts = np.maximum(c1[members], 0.0)  # no pressure known: weight by ΔC1
        full_w = np.zeros(lay.n)
        full_w[members] = wts
        cx, cy = force_centroid(lay, full_w, members)
        s_tot = float(np.nansum(np.maximum(area_i[: members.size], 0.0)))
        f_sum = float(np.nansum(force_i[: members.size])) if valid.any() else math.nan

        half = 0.5 * lay.side
        base = dict(
            centroid_x=cx, centroid_y=cy, elements=ids, pressure=sigma0, force_sum=f_sum,
            area=s_tot if valid.any() else math.nan,
        )
        if not valid.any() or not s_tot > 0:
            sx = sy = half / math.sqrt(3.0) * max(1, members.size)
            return Contact(
                x=cx, y=cy, force=f_sum, diameter=math.nan, model_x=math.nan, model_y=math.nan,
                sigma_x=sx, sigma_y=sy, sigma_xy=max(sx, sy), cov=((sx * sx, 0.0), (0.0, sy * sy)),
                valid=False, fit_ok=False, observable=(False, False), chi2=math.nan, dof=0,
                sigma_force=math.nan, sigma_diameter=math.nan, **base,
            )
        quiet = np.zeros(idx.size, dtype=bool)
        quiet[members.size :] = True
        obs = _Obs(idx, lay.bounds[idx], dc, area_i, quiet)
        return self._fit(obs, members.size, sigma0, s_tot, cx, cy, base)

    def _areas(
        self, idx: IntArray, dc: FloatArray, sigma0: float, inv: InverseResult
    ) -> tuple[FloatArray, FloatArray]:
        # Area and force per observed element: the inverse's where valid; elsewhere the
        # least-squares area at the cluster's pressure, A = (g·ΔC)/(g·g).
        a = inv.area[idx].copy()
        f = inv.force[idx].copy()
        if math.isfinite(sigma0):
            g1, g2 = sensitivity(sigma0, self.params)
            w1, w2 = 1.0 / self.noise[0] ** 2, 1.0 / self.noise[1] ** 2
            est = (w1 * g1 * dc[0] + w2 * g2 * dc[1]) / (w1 * g1 * g1 + w2 * g2 * g2)
            bad = ~inv.valid[idx]
            a[bad] = est[bad]
            f[bad] = sigma0 * est[bad]
        return a, f

    def _predict(self, obs: _Obs, thetas: FloatArray, spread: float) -> tuple[FloatArray, FloatArray]:
        """(K, m) predicted observations for parameter rows θ (areas, or ΔC1 then ΔC2),
        and (K,) the fraction of each disk's footprint lying on none of the observed
        elements (with a spread, the footprint is the disk widened by 1.5 s)."""
        b = obs.bounds
        # Keep trial diameters and forces within physical bounds whatever a search
        # step proposes (1 µm to 100 element sides; 1 µN to 100 kN).
        lnd = np.clip(thetas[:, 2], math.log(1e-6), math.log(100.0 * self.layout.side))
        r = 0.5 * np.exp(lnd)
        a = disk_rect_overlap(
            thetas[:, :1], thetas[:, 1:2], r[:, None],
            b[None, :, 0], b[None, :, 1], b[None, :, 2], b[None, :, 3],
        )
        off = np.maximum(1.0 - a.sum(axis=1) / (math.pi * r * r), 0.0)
        if self.method == "area":
            return a, off
        f = np.exp(np.clip(thetas[:, 3], math.log(1e-6), math.log(1e5)))
        if spread == 0:
            g1, g2 = sensitivity(f / (math.pi * r * r), self.params)
            return np.concatenate([a * g1[:, None], a * g2[:, None]], axis=1), off
        c = np.stack([thetas[:, 0], thetas[:, 1], f, 2.0 * r], axis=1)
        d1, d2 = _disk_response(b, self.layout.side, c, self.params, spread, self.quad_step)
        # Under tension the force reaches beyond the disk: a disk near the skin's edge
        # can lose blurred force off it and make up with size, so the on-skin prior
        # looks at the blurred footprint.
        rw = r + 1.5 * spread
        aw = disk_rect_overlap(
            thetas[:, :1], thetas[:, 1:2], rw[:, None],
            b[None, :, 0], b[None, :, 1], b[None, :, 2], b[None, :, 3],
        )
        off = np.maximum(1.0 - aw.sum(axis=1) / (math.pi * rw * rw), 0.0)
        return np.concatenate([d1, d2], axis=1), off

    def _model(self, obs: _Obs, sigma0: float, d0: float) -> _Model:
        if self.method == "area":
            g1, g2 = sensitivity(sigma0, self.params)
            # Area noise of one element: the ΔC noise through both sensitivities.
            s_noise = 1.0 / math.sqrt((g1 / self.noise[0]) ** 2 + (g2 / self.noise[1]) ** 2)
            target = np.nan_to_num(obs.area)
            scale = np.full(target.size, s_noise)
            strength = np.abs(target) / s_noise
            quiet = obs.quiet
        else:
            target = np.concatenate([obs.dc[0], obs.dc[1]])
            scale = np.repeat(self.noise, obs.idx.size)
            w = (obs.dc / self.noise[:, None]) ** 2
            strength = np.sqrt(w.sum(axis=0))
            quiet = np.concatenate([obs.quiet, obs.quiet])
        present = (strength > 3.0) & ~obs.quiet
        return _Model(self, obs, target, scale, present, strength[present], 0.5 * d0, quiet)

    def _fit(self, obs: _Obs, n_members: int, sigma0: float, s_tot: float, cx0: float, cy0: float, base: dict) -> Contact:
        lay = self.layout
        d0 = 2.0 * math.sqrt(s_tot / math.pi)
        f0 = sigma0 * s_tot
        area_m = self.method == "area"
        model = self._model(obs, sigma0, d0)

        steps = np.array([1e-7, 1e-7] + [1e-6] * (1 if area_m else 2))
        ranges = np.array([lay.side, lay.side] + [1.0] * (1 if area_m else 2))
        if self.spread > 0:
            # With the spread model every evaluation is a quadrature: start from the
            # uniform-pressure fit of the same readings (cheap, and its position is
            # close), and refine with the spread model from there.
            flat = self._uniform._fit(obs, n_members, sigma0, s_tot, cx0, cy0, base)
            if flat.fit_ok:
                start = np.array([flat.model_x, flat.model_y, math.log(flat.diameter), math.log(flat.force)])
                theta, _, _, conv = _lm(model.residuals, start, steps, ranges)
                return self._finish(model, theta, conv, steps, ranges, sigma0, d0, cx0, cy0, base)

        # Start: the best centre on a grid over the cluster (D and F from the element
        # sums), then Levenberg–Marquardt.
        b = obs.bounds[:n_members]
        x_lo, y_lo = b[:, 0].min(), b[:, 1].min()
        x_hi, y_hi = b[:, 2].max(), b[:, 3].max()
        h = min(max(0.25 * d0, 2.5e-4), lay.side / 40.0)
        while ((x_hi - x_lo) / h + 1) * ((y_hi - y_lo) / h + 1) > 20000:
            h *= 1.5
        gx = np.arange(x_lo + 0.5 * h, x_hi, h)
        gy = np.arange(y_lo + 0.5 * h, y_hi, h)
        GX, GY = np.meshgrid(gx, gy, indexing="ij")
        tail = [math.log(d0)] if area_m else [math.log(d0), math.log(f0)]
        th = np.column_stack([GX.ravel(), GY.ravel(), np.tile(tail, (GX.size, 1))])
        r0 = model.residuals(th, spread=0.0)
        cost = np.einsum("km,km->k", r0, r0)
        # Ties (a disk anywhere inside one element fits equally well) go to the
        # candidate nearest the centroid: inside the element, away from tangencies.
        tie = cost <= cost.min() * (1.0 + 1e-6) + 1e-12
        d2 = (th[:, 0] - cx0) ** 2 + (th[:, 1] - cy0) ** 2
        start = th[int(np.argmin(np.where(tie, d2, np.inf)))]
        # Stage 1 moves the centre only, D and F held at the element sums: with D free
        # from the start, a disk hanging off the skin's edge can trade lost area for
        # diameter and the solver crawls along that valley instead.
        tail_v = start[2:].copy()
        ctr, _, _, _ = _lm(
            lambda t: model.residuals(np.column_stack([t, np.tile(tail_v, (t.shape[0], 1))])),
            start[:2], np.array([1e-7, 1e-7]), np.array([lay.side, lay.side]), max_iter=30,
        )
        start = np.concatenate([ctr, tail_v])
        theta, _, _, conv = _lm(model.residuals, start, steps, ranges)
        return self._finish(model, theta, conv, steps, ranges, sigma0, d0, cx0, cy0, base)

    def _finish(
        self, model: _Model, theta: FloatArray, conv: bool, steps: FloatArray, ranges: FloatArray,
        sigma0: float, d0: float, cx0: float, cy0: float, base: dict,
    ) -> Contact:
        lay = self.layout
        area_m = self.method == "area"
        # The profile scans below also look for a better solution along each axis
        # (under a wide spread the cost can have a second, lower valley the local
        # solver did not reach); if they find one, solve again from there.
        for attempt in range(3):
            scans = [self._scan(model.residuals, theta, steps, ax) for ax in (0, 1)]
            best = min(scans, key=lambda sc: sc.best_cost)
            if attempt == 2 or not best.best_cost < best.cost - max(1e-3, 1e-9 * best.cost):
                break
            theta, _, _, conv = _lm(model.residuals, best.best_theta, steps, ranges)

        # Statistics from the measurements alone (not the search aids).
        m = model.target.size
        p = theta.size
        dof = m - p
        r = model.data_residuals(theta[None])[0]
        chi2 = float(r @ r)
        # A fit is usable when the solver stopped at a minimum or the readings are
        # explained to within their noise (a solver still creeping along a flat
        # valley of exact solutions is fine).
        ok = bool((conv or chi2 <= max(dof, 1)) and np.all(np.isfinite(theta)))

        # Where the disk can slide without changing any reading (wholly inside an
        # element, or along a seam it straddles), the solver's stopping point is
        # arbitrary: move to the middle of that plateau, and report the spread of a
        # uniform distribution over the positions consistent with the readings.
        flat = np.zeros(2, dtype=bool)
        consistent = np.zeros((2, 2))
        for ax, sc in enumerate(scans):
            consistent[ax] = sc.consistent
            step = sc.step
            if sc.plateau[1] - sc.plateau[0] > 1.5 * sc.step:
                flat[ax] = True
                theta[ax] = 0.5 * (sc.plateau[0] + sc.plateau[1])

        def covariance(th: FloatArray, drop: NDArray[np.bool_]) -> FloatArray:
            pts = np.concatenate([th[None], th + np.diag(steps), th - np.diag(steps)])
            rd = model.data_residuals(pts)
            J = ((rd[1 : p + 1] - rd[p + 1 :]) / (2.0 * steps[:, None])).T
            keep = np.ones(p, dtype=bool)
            keep[:2] = ~drop & (np.sqrt((J[:, :2] ** 2).sum(axis=0)) * lay.side > 1e-3)
            cov_p = np.full((p, p), np.inf)
            A = (J.T @ J)[np.ix_(keep, keep)]
            ev, vec = np.linalg.eigh(A)
            if ev.size and ev.min() > 1e-12 * max(ev.max(), 1e-300):
                infl = max(1.0, chi2 / dof) if dof > 0 else 1.0
                cov_p[np.ix_(keep, keep)] = (vec / ev) @ vec.T * infl
            return cov_p

        cov_p = covariance(theta, flat)
        uniform = (consistent[:, 1] - consistent[:, 0]) ** 2 / 12.0
        # A coordinate the local curvature claims to know less well than the scan
        # (near-singular: a disk under a wide spread sees position only through the
        # tails) is reported like a plateau: middle of the consistent range.
        # One axis at a time, worst first: a near-singular axis inflates the other's
        # variance through their correlation.
        for _ in range(2):
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio = np.where(flat, 0.0, np.nan_to_num(np.diag(cov_p)[:2] / uniform, nan=np.inf))
            ax = int(np.argmax(ratio))
            if not ratio[ax] > 1.0:
                break
            theta[ax] = consistent[ax].mean()
            flat[ax] = True
            cov_p = covariance(theta, flat)
        var = np.diag(cov_p)[:2].copy()
        for ax in (0, 1):
            sd = math.sqrt(var[ax]) if np.isfinite(var[ax]) else math.inf
            lo, hi = consistent[ax]
            # Never claim more precision than the scan shows: a disk barely over a
            # seam is pinned on one side only, which the local curvature cannot see.
            if flat[ax] or not math.isfinite(sd) or (hi - lo) > 4.0 * sd + 4.0 * step:
                var[ax] = uniform[ax]
        keep = ~flat
        cxy = float(cov_p[0, 1]) if keep.all() and np.isfinite(cov_p[0, 1]) else 0.0
        cov = ((float(var[0]), cxy), (cxy, float(var[1])))
        ev2 = np.linalg.eigvalsh(np.array(cov))
        diam = float(math.exp(theta[2]))
        force = sigma0 * math.pi * diam * diam / 4.0 if area_m else float(math.exp(theta[3]))
        xy = theta[:2] if ok else np.array([cx0, cy0])
        with np.errstate(invalid="ignore"):
            s_lnd = math.sqrt(cov_p[2, 2]) if np.isfinite(cov_p[2, 2]) else math.inf
            s_lnf = 2.0 * s_lnd if area_m else (math.sqrt(cov_p[3, 3]) if np.isfinite(cov_p[3, 3]) else math.inf)
        return Contact(
            x=float(xy[0]), y=float(xy[1]),
            force=force if ok else base["force_sum"],
            diameter=diam if ok else d0,
            model_x=float(theta[0]) if ok else math.nan,
            model_y=float(theta[1]) if ok else math.nan,
            sigma_x=float(math.sqrt(var[0])), sigma_y=float(math.sqrt(var[1])),
            sigma_xy=float(math.sqrt(max(float(ev2.max()), 0.0))),
            cov=cov, valid=True, fit_ok=ok, observable=(not flat[0], not flat[1]),
            sigma_force=force * s_lnf if ok else math.nan,
            sigma_diameter=diam * s_lnd if ok else math.nan,
            chi2=chi2, dof=int(dof), **base,
        )

    def _scan(
        self, fun: Callable[[FloatArray], FloatArray], theta: FloatArray, steps: FloatArray, ax: int
    ) -> _Scan:
        """Profile of the fit's cost along coordinate ``ax``, ±1 element side around it.

        At every scanned position the diameter and force are re-fitted (a few
        vectorised Gauss–Newton steps), so a valley where position trades against
        size — a disk near the skin's edge, or any disk under a wide spread — shows
        up as the wide range it is. Scan step: 1/80 of a side (1/10 with the spread
        model, whose evaluations cost more).
        """
        side = self.layout.side
        n = 80 if self.spread == 0 else 10
        off = np.linspace(-side, side, 2 * n + 1)
        k = off.size
        th = np.tile(theta, (k, 1))
        th[:, ax] += off
        q = theta.size - 2
        r = fun(th)
        c = np.einsum("km,km->k", r, r)
        c_at = float(c[n])
        eye = np.eye(theta.size)[2:] * steps[:, None][2:]
        for _ in range(3):
            pts = np.concatenate([th[None], th[None] + eye[:, None, :], th[None] - eye[:, None, :]])
            res = fun(pts.reshape(-1, theta.size)).reshape(1 + 2 * q, k, -1)
            J = ((res[1 : 1 + q] - res[1 + q :]) / (2.0 * steps[2:, None, None])).transpose(1, 2, 0)
            A = np.einsum("kmi,kmj->kij", J, J) + 1e-12 * np.eye(q)
            g = np.einsum("kmi,km->ki", J, res[0])
            try:
                delta = np.linalg.solve(A, -g[..., None])[..., 0]
            except np.linalg.LinAlgError:
                break
            trial = th.copy()
            trial[:, 2:] += np.clip(np.nan_to_num(delta), -0.5, 0.5)  # at most ×1.65 a step
            rt = fun(trial)
            ct = np.einsum("km,km->k", rt, rt)
            better = np.isfinite(ct) & (ct < c)
            th[better] = trial[better]
            c[better] = ct[better]
        c0 = min(float(c[n]), c_at)
        step = float(off[1] - off[0])

        def run(ok: NDArray[np.bool_]) -> tuple[float, float]:
            lo = hi = n
            while lo > 0 and ok[lo - 1]:
                lo -= 1
            while hi < k - 1 and ok[hi + 1]:
                hi += 1
            return float(theta[ax] + off[lo]), float(theta[ax] + off[hi])

        lo, hi = run(c <= c0 + 1.0)
        # The plateau is the flat bottom of that range; the fit may stop just beside
        # it (at a tangency, a hair off the skin), so look for it within the range.
        inside = (theta[ax] + off >= lo) & (theta[ax] + off <= hi)
        i = int(np.argmin(np.where(inside, c, np.inf)))
        flat_ok = inside & (c <= c[i] + 1e-2)  # indistinguishable: a tenth of a sigma
        a = b = i
        while a > 0 and flat_ok[a - 1]:
            a -= 1
        while b < k - 1 and flat_ok[b + 1]:
            b += 1
        plateau = (float(theta[ax] + off[a]), float(theta[ax] + off[b]))
        j = int(np.argmin(c))
        return _Scan(plateau, (lo - 0.5 * step, hi + 0.5 * step), step, c0, float(c[j]), th[j].copy())


class _Scan(NamedTuple):
    plateau: tuple[float, float]  #: flat bottom of the cost (within 0.01)
    consistent: tuple[float, float]  #: range where it rises by at most 1
    step: float
    cost: float  #: cost at the fit
    best_cost: float  #: lowest cost seen along the scan
    best_theta: FloatArray


class _Model:
    """Residuals of one disk against one cluster's readings, plus two search aids.

    Readings of quiet neighbours (in the ring around the cluster, not touched) enter
    one-sided: the disk may not put more on them than they read.

    * **presence**: an element with a clear signal that the disk does not reach adds
      ``strength·distance/R``. Without it the cost is flat wherever the disk sits
      wholly inside one element, and a solver started there never finds a small
      share across a seam. It is zero at any disk that reaches every signalling
      element, so it does not bias the answer.
    * **on-skin prior**: the fraction of the disk lying on none of the observed
      elements, over ``PRIOR_OFF``. A disk partly off the skin's outer edge and a
      smaller disk fully on it can give identical readings; the prior picks the one
      on the skin instead of wandering along that valley of exact solutions. With a
      spread the footprint is the disk widened by 1.5 s, where the blurred force
      still is. (Seams between elements count as "off" too, a small pull on disks
      across wide seams.)

    Both are left out of χ² and of the covariance.
    """

    PRIOR_OFF = 0.05  # one-sigma width of the on-skin prior (fraction of the disk)

    def __init__(self, est: ContactEstimator, obs: _Obs, target: FloatArray, scale: FloatArray,
                 present: NDArray[np.bool_], strength: FloatArray, r0: float, quiet: NDArray[np.bool_]):
        self.est, self.obs, self.target, self.scale = est, obs, target, scale
        self.quiet = quiet
        self.pb = obs.bounds[present]
        self.strength = strength
        self.r0 = r0

    def data_residuals(self, th: FloatArray, spread: float | None = None) -> FloatArray:
        return self._both(th, spread)[0]

    def _both(self, th: FloatArray, spread: float | None) -> tuple[FloatArray, FloatArray]:
        s = self.est.spread if spread is None else spread
        pred, off = self.est._predict(self.obs, th, s)
        r = (pred - self.target) / self.scale
        # Quiet neighbours only bound the disk: predicting more than they read is
        # penalised, less is not (their reading is noise around zero, and a disk
        # grazing them to "explain" that noise is a spurious optimum).
        r[:, self.quiet] = np.maximum(r[:, self.quiet], 0.0)
        return r, off

    def residuals(self, th: FloatArray, spread: float | None = None) -> FloatArray:
        rd, off = self._both(th, spread)
        b = self.pb
        dx = np.maximum(np.maximum(b[None, :, 0] - th[:, :1], th[:, :1] - b[None, :, 2]), 0.0)
        dy = np.maximum(np.maximum(b[None, :, 1] - th[:, 1:2], th[:, 1:2] - b[None, :, 3]), 0.0)
        r = 0.5 * np.exp(th[:, 2:3])
        gap = np.maximum(np.hypot(dx, dy) - r, 0.0)
        pres = self.strength[None, :] * gap / self.r0
        return np.concatenate([rd, pres, off[:, None] / self.PRIOR_OFF], axis=1)


def estimate_contacts(
    layout: SkinLayout,
    dC1: ArrayLike,
    dC2: ArrayLike,
    active: ArrayLike | None = None,
    params: ElementParams | None = None,
    **options: object,
) -> list[Contact]:
    """One-shot :class:`ContactEstimator` (same keyword options)."""
    return ContactEstimator(layout, params, **options).estimate(dC1, dC2, active)  # type: ignore[arg-type]
