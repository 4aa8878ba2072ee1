"""Contacts from one frame of element readings: clusters, inverse, fits, results.

One element cannot tell where on it a contact sits (eq. 3 integrates over it). The
array can, as soon as a contact straddles a seam: how the footprint is shared
between the elements it lies on depends on where it is. Per cluster of touched
elements the estimator reports the paper's force-weighted centroid (§III.B, Fig. 7)
and a model-based fit of one uniform-pressure disk (centre, diameter, force) to
what every element of the cluster and its ring of neighbours measured; when two
disks explain a cluster significantly better than one (two fingers on neighbouring
elements), it reports both.

This module holds the orchestration only: the compiled model and fit are in
:mod:`cellbridge.tactile.disk_model` and :mod:`cellbridge.tactile.fit_kernel`, the
spread model in :mod:`cellbridge.tactile.spread_model`. Every fit of a frame runs in
one kernel call.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from cellbridge.tactile.clusters import cluster_elements, force_centroid
from cellbridge.tactile.contact_result import Contact
from cellbridge.tactile.disk_model import element_vector, sensitivity_slope
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.fit_kernel import UNIFORM, fit_batch, share_start
from cellbridge.tactile.inversion import DEFAULT_NOISE, solve
from cellbridge.tactile.skin import SkinLayout, _check_spread, _spread_cells
from cellbridge.tactile.spread_model import DV, PROFILE_ROWS

__all__ = ["ContactEstimator", "estimate_contacts"]

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Δχ² (in units of the noise, or of the two-disk fit's reduced χ² when that is
#: worse) that a second disk must gain to be reported: the 1 − 1e-4 quantile of
#: χ² with 4 degrees of freedom, the four parameters the second disk adds.
SPLIT_DCHI2 = 23.51


@dataclass
class _Cluster:
    """One cluster's data in one frame (indices are layout rows)."""

    members: IntArray
    obs: IntArray  # members first, then the quiet ring
    sigma0: float  # shared pressure from the valid elements (NaN: none)
    area: FloatArray  # per observed element
    centroid: tuple[float, float]
    valid: bool  # a pressure and a positive area: the disk can be fitted
    base: dict = field(default_factory=dict)


@dataclass
class _Batch:
    """Flat arrays of several fit problems, as the kernel takes them."""

    off: IntArray
    bounds: FloatArray
    y: FloatArray
    quiet: NDArray[np.bool_]
    w: FloatArray

    @property
    def n(self) -> int:
        return self.off.size - 1


@dataclass
class _Fits:
    theta: FloatArray
    sig: FloatArray
    flat: NDArray[np.bool_]
    cov: FloatArray
    chi2: FloatArray
    cost: FloatArray
    ok: NDArray[np.bool_]


class ContactEstimator:
    """Turns per-element ΔC (and touch flags) of one time step into :class:`Contact` s.

    ``noise`` is the rms noise of one ΔC reading (F, scalar or per channel); it
    weights the fit and scales every reported uncertainty. ``spread`` is the
    membrane-tension model of :func:`cellbridge.tactile.skin.skin_response` (0: the
    paper's assumption). ``method`` picks what the disk is fitted to:
    ``"capacitance"`` (ΔC of the cluster and its neighbours; default) or ``"area"``
    (the per-element areas from the inverse; uniform pressure only). ``split``
    allows a cluster to be reported as two contacts when two disks explain it
    significantly better than one.
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
        split: bool = True,
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
        self.split = bool(split)
        self._par = element_vector(self.params)
        e = layout.corner_edges
        self._ring_of = [np.concatenate([e[e[:, 0] == i, 1], e[e[:, 1] == i, 0]]) for i in range(layout.n)]
        self._adj_edge = layout.adjacency("edge") if layout.n <= 4096 else None
        if self.spread > 0:
            _spread_cells(layout.side, self.spread, quad_step)  # validates quad_step now

    # -- public -----------------------------------------------------------------------
    def estimate(
        self,
        dC1: ArrayLike,
        dC2: ArrayLike,
        active: ArrayLike | None = None,
        *,
        hints: ArrayLike | None = None,
    ) -> list[Contact]:
        """Contacts from ΔC (F) of every element; ``active`` = touched elements.

        Without ``active``, an element is active when either channel exceeds three
        noise sigmas. NaN readings count as inactive and are left out of the fits.
        ``hints`` are ``(x, y, diameter, force)`` rows of contacts expected in this
        frame (the previous frame's, from :class:`~cellbridge.tactile.tracker.ContactTracker`):
        a cluster containing one starts its fit there.
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
        h = np.zeros((0, 4)) if hints is None else np.asarray(hints, dtype=np.float64).reshape(-1, 4)
        if not act.any():
            return []
        idx = np.nonzero(act)[0]
        inv = solve(c1[idx], c2[idx], self.params, noise=float(self.noise.max()), **self.inverse_options)
        valid = np.zeros(lay.n, dtype=bool)
        force = np.full(lay.n, np.nan)
        area = np.full(lay.n, np.nan)
        valid[idx] = inv.valid
        force[idx] = inv.force
        area[idx] = inv.area
        labels = cluster_elements(lay, act, self.connectivity)
        order = np.argsort(labels, kind="stable")
        starts = np.searchsorted(labels[order], np.arange(int(labels.max()) + 2))
        clusters = [
            self._cluster(order[starts[k] : starts[k + 1]], labels, c1, c2, finite, valid, force, area)
            for k in range(int(labels.max()) + 1)
        ]
        out: list[Contact | None] = [None] * len(clusters)
        good = [k for k, cl in enumerate(clusters) if cl.valid]
        if good:
            for k, cs in zip(good, self._fit_valid([clusters[k] for k in good], c1, c2, h)):
                out[k] = cs
        # A light touch on one element says nothing finer than the element: no fit.
        light = [k for k, cl in enumerate(clusters) if not cl.valid and cl.members.size > 1]
        for k, cl in enumerate(clusters):
            if not cl.valid and cl.members.size == 1:
                out[k] = self._unlocated(cl)
        if light:
            for k, c in zip(light, self._fit_light([clusters[k] for k in light], c1, c2)):
                out[k] = c
        flat: list[Contact] = []
        for item in out:
            if isinstance(item, list):
                flat.extend(item)
            elif item is not None:
                flat.append(item)
        return flat

    # -- per cluster data ---------------------------------------------------------------
    def _cluster(
        self, members: IntArray, labels: IntArray, c1: FloatArray, c2: FloatArray,
        finite: NDArray[np.bool_], valid: NDArray[np.bool_], force: FloatArray, area: FloatArray,
    ) -> _Cluster:
        lay = self.layout
        members = np.sort(members)
        ring = np.unique(np.concatenate([self._ring_of[i] for i in members]))
        ring = ring[(labels[ring] < 0) & finite[ring]]
        obs = np.concatenate([members, ring])
        vm = valid[members]
        sigma0 = float(force[members][vm].sum() / area[members][vm].sum()) if vm.any() else math.nan
        # Area per observed element: the inverse's where valid; elsewhere the
        # least-squares area at the cluster's pressure, A = (g·ΔC)/(g·g).
        a = area[obs].copy()
        f = force[obs].copy()
        if math.isfinite(sigma0):
            g1, g2 = self._g(sigma0)
            w1, w2 = 1.0 / self.noise[0] ** 2, 1.0 / self.noise[1] ** 2
            est = (w1 * g1 * c1[obs] + w2 * g2 * c2[obs]) / (w1 * g1 * g1 + w2 * g2 * g2)
            bad = ~valid[obs]
            a[bad] = est[bad]
            f[bad] = sigma0 * est[bad]
        nm = members.size
        wts = np.where(np.isfinite(f[:nm]), f[:nm], 0.0)
        if not (wts > 0).any():
            wts = np.maximum(c1[members], 0.0)  # no pressure known: weight by ΔC1
        full_w = np.zeros(lay.n)
        full_w[members] = wts
        cx, cy = force_centroid(lay, full_w, members)
        s_tot = float(np.nansum(np.maximum(a[:nm], 0.0)))
        ok = bool(vm.any())
        base = dict(
            centroid_x=cx, centroid_y=cy, elements=tuple(int(i) for i in lay.ids[members]),
            pressure=sigma0, force_sum=float(np.nansum(f[:nm])) if ok else math.nan,
            area=s_tot if ok else math.nan,
        )
        return _Cluster(members, obs, sigma0, a, (cx, cy), ok and s_tot > 0, base)

    def _g(self, sigma: float) -> tuple[float, float]:
        """Sensitivities (g1, g2) at one pressure (the compiled scalar: no array overhead)."""
        p = self._par
        return sensitivity_slope(sigma, *p[:4])[0], sensitivity_slope(sigma, *p[4:])[0]

    def _batch(self, clusters: list[_Cluster], c1: FloatArray, c2: FloatArray, reps: int = 1) -> _Batch:
        """Kernel arrays for the clusters, each repeated ``reps`` times in a row."""
        lay = self.layout
        obs = [cl.obs for cl in clusters for _ in range(reps)]
        sizes = np.array([o.size for o in obs])
        off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        allobs = np.concatenate(obs)
        quiet = np.concatenate([np.arange(o.size) >= cl.members.size for cl in clusters for o in [cl.obs] * reps])
        if self.method == "area":
            y = np.zeros((2, allobs.size))
            y[0] = np.nan_to_num(np.concatenate([cl.area for cl in clusters for _ in range(reps)]))
            w = np.empty((len(obs), 2))
            for k, cl in enumerate(clusters):
                g1, g2 = self._g(cl.sigma0)
                # Area noise of one element: the ΔC noise through both sensitivities.
                w[k * reps : (k + 1) * reps] = math.sqrt((g1 / self.noise[0]) ** 2 + (g2 / self.noise[1]) ** 2)
        else:
            y = np.stack([c1[allobs], c2[allobs]])
            w = np.tile(1.0 / self.noise, (len(obs), 1))
        return _Batch(off, np.ascontiguousarray(lay.bounds[allobs]), np.ascontiguousarray(y), quiet, w)

    def _run(
        self, b: _Batch, theta0: FloatArray, free: NDArray[np.bool_], nd: int, assess: bool, sm: tuple = UNIFORM
    ) -> _Fits:
        n, p = b.n, 4 * nd
        r = _Fits(np.empty((n, p)), np.empty((n, p)), np.zeros((n, p), dtype=bool), np.empty((n, p, p)),
                  np.empty(n), np.empty(n), np.zeros(n, dtype=bool))
        fit_batch(b.off, b.bounds, b.y, b.quiet, np.ascontiguousarray(theta0, dtype=np.float64),
                  np.ascontiguousarray(free), nd, b.w, 1 if self.method == "area" else 2, self._par,
                  float(self.layout.side), assess, r.theta, r.sig, r.flat, r.cov, r.chi2, r.cost, r.ok, sm)
        return r

    def _starts(self, clusters: list[_Cluster], areas: list[FloatArray] | None = None) -> FloatArray:
        """(K, 3) share-based (x, y, r) of each cluster (areas over its members)."""
        lay = self.layout
        mem = [cl.members for cl in clusters]
        ar = [cl.area[: cl.members.size] for cl in clusters] if areas is None else areas
        nmem = np.array([m.size for m in mem], dtype=np.int64)
        off = np.concatenate([[0], np.cumsum(nmem)]).astype(np.int64)
        out = np.empty((len(mem), 3))
        share_start(off, nmem, np.ascontiguousarray(lay.bounds[np.concatenate(mem)]),
                    np.nan_to_num(np.concatenate(ar)), out)
        return out

    # -- clusters with a pressure ---------------------------------------------------------
    def _fit_valid(self, clusters: list[_Cluster], c1: FloatArray, c2: FloatArray, hints: FloatArray) -> list[list[Contact]]:
        nd_free = np.array([True, True, True, self.method != "area"])
        st = self._starts(clusters)
        theta0 = np.empty((len(clusters), 4))
        theta0[:, :2] = st[:, :2]
        theta0[:, 2] = np.log(2.0 * st[:, 2])
        theta0[:, 3] = np.log(np.array([cl.sigma0 for cl in clusters]) * math.pi * st[:, 2] ** 2)
        pair_hints: dict[int, FloatArray] = {}
        hinted = np.zeros(len(clusters), dtype=bool)
        for k, cl in enumerate(clusters):
            inside = self._hints_in(cl, hints, 2.0 * st[k, 2])
            if inside.shape[0] >= 1:
                hinted[k] = True
                theta0[k] = [inside[0, 0], inside[0, 1], math.log(inside[0, 2]), math.log(inside[0, 3])]
            if inside.shape[0] >= 2:
                pair_hints[k] = inside[:2]
        free = np.tile(nd_free, (len(clusters), 1))
        batch = self._batch(clusters, c1, c2)
        fits = self._run(batch, theta0, free, 1, True)
        # A warm start in the wrong valley (the disk moved far since last frame) is
        # caught by its fit quality and redone from the readings' own start.
        dof = self._dof(batch, 4 if self.method != "area" else 3)
        redo = np.nonzero(hinted & (fits.chi2 > dof + 3.0 * np.sqrt(2.0 * np.maximum(dof, 1)) + 1.0))[0]
        if redo.size:
            sub = [clusters[k] for k in redo]
            t0 = np.column_stack([st[redo, :2], np.log(2 * st[redo, 2]),
                                  np.log([clusters[k].sigma0 * math.pi * st[k, 2] ** 2 for k in redo])])
            again = self._run(self._batch(sub, c1, c2), t0, free[redo], 1, True)
            for j, k in enumerate(redo):
                if again.cost[j] < fits.cost[k]:
                    for name in ("theta", "sig", "flat", "cov", "chi2", "cost", "ok"):
                        getattr(fits, name)[k] = getattr(again, name)[j]
        if self.spread > 0:
            fits = self._spread_refine(batch, fits)
        results = [[self._contact(cl, fits, k, int(dof[k]))] for k, cl in enumerate(clusters)]
        # A pressure from an element's inverse that no disk agrees with (a reading
        # that passed the inverse's checks on the wrong branch): locate the touch as
        # one without a pressure, if that finds a disk that fits.
        failed = [k for k in range(len(clusters)) if not fits.ok[k] and clusters[k].members.size > 1]
        if failed:
            for k, c in zip(failed, self._fit_light([clusters[k] for k in failed], c1, c2)):
                if c.fit_ok:
                    results[k] = [c]
        # Two disks need the uniform model: under a spread, a one-disk misfit of the
        # uniform model is no evidence of a second contact.
        if self.split and self.method != "area" and self.spread == 0:
            self._try_splits(clusters, fits, dof, c1, c2, pair_hints, results)
        return results

    def _spread_refine(self, batch: _Batch, uni: _Fits) -> _Fits:
        """The uniform fits, refined with the spread model (cheap start, close position).

        Axes the uniform fit found unresolved stay at the middle of their range (a
        disk inside one element sees its position under tension only through the
        tails, which the readings resolve no better); the others, D and F are fitted
        again, and their σ come from the spread model's curvature.
        """
        s = self.spread
        d_max = float(np.exp(uni.theta[:, 2]).max())
        rows = PROFILE_ROWS.upto(int(math.ceil((0.5 * d_max * 1.5 / s + 2.0) / DV)) + 2)
        sm = (s, _spread_cells(self.layout.side, s, self.quad_step), rows)
        free = np.ones(uni.theta.shape, dtype=bool)
        free[:, :2] = ~uni.flat[:, :2]
        good = uni.ok
        out = self._run(batch, uni.theta, free, 1, False, sm)
        for j in range(2):
            keep = uni.flat[:, j] | ~good
            out.sig[keep, j] = uni.sig[keep, j]
            out.flat[:, j] = uni.flat[:, j]
        out.ok &= good
        return out

    def _hints_in(self, cl: _Cluster, hints: FloatArray, d_start: float) -> FloatArray:
        """The hints that can be this cluster's disk, nearest its centroid first.

        A hint must sit on one of the cluster's elements (a quarter side of slack:
        the disk moved) and have a diameter within a factor 2 of what the readings
        say now; anything else (a finger lifted here and pressed there) would start
        the fit in a wrong valley, slower and worse than the readings' own start.
        """
        if hints.shape[0] == 0:
            return hints
        b = self.layout.bounds[cl.members]
        m = 0.25 * self.layout.side
        on = (
            (hints[:, None, 0] >= b[None, :, 0] - m) & (hints[:, None, 0] <= b[None, :, 2] + m)
            & (hints[:, None, 1] >= b[None, :, 1] - m) & (hints[:, None, 1] <= b[None, :, 3] + m)
        ).any(axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            size_ok = np.abs(np.log(hints[:, 2] / d_start)) <= math.log(2.0)
        ok = on & np.all(np.isfinite(hints), axis=1) & (hints[:, 2] > 0) & (hints[:, 3] > 0) & size_ok
        h = hints[ok]
        cx, cy = cl.centroid
        return h[np.argsort(np.hypot(h[:, 0] - cx, h[:, 1] - cy))]

    def _dof(self, b: _Batch, nfree: int) -> FloatArray:
        nch = 1 if self.method == "area" else 2
        return (nch * np.diff(b.off) - nfree).astype(np.float64)

    def _contact(self, cl: _Cluster, f: _Fits, k: int, dof: int, disk: int = 0, **over: object) -> Contact:
        th = f.theta[k, 4 * disk : 4 * disk + 4]
        sig = f.sig[k, 4 * disk : 4 * disk + 4]
        flat = f.flat[k, 4 * disk : 4 * disk + 2]
        cv = f.cov[k, 4 * disk : 4 * disk + 4, 4 * disk : 4 * disk + 4]
        ok = bool(f.ok[k])
        base = dict(cl.base)
        base.update(over)
        diam = float(math.exp(th[2]))
        if self.method == "area":
            force = cl.sigma0 * math.pi * diam * diam / 4.0
            s_lnf = 2.0 * sig[2]
        else:
            force = float(math.exp(th[3]))
            s_lnf = sig[3]
        cxy = float(cv[0, 1]) if not flat.any() and np.isfinite(cv[0, 1]) else 0.0
        sx, sy = float(sig[0]), float(sig[1])
        cov = ((sx * sx, cxy), (cxy, sy * sy))
        cx, cy = base["centroid_x"], base["centroid_y"]
        return Contact(
            x=float(th[0]) if ok else cx, y=float(th[1]) if ok else cy,
            force=force if ok else base["force_sum"],
            diameter=diam if ok else 2.0 * math.sqrt(max(base["area"], 0.0) / math.pi),
            model_x=float(th[0]) if ok else math.nan, model_y=float(th[1]) if ok else math.nan,
            sigma_x=sx, sigma_y=sy, sigma_xy=_major(sx * sx, sy * sy, cxy), cov=cov,
            sigma_force=float(force * s_lnf) if ok else math.nan,
            sigma_diameter=float(diam * sig[2]) if ok else math.nan,
            valid=True, fit_ok=ok, observable=(not bool(flat[0]), not bool(flat[1])),
            chi2=float(f.chi2[k]), dof=dof, **base,
        )

    # -- two disks in one cluster -----------------------------------------------------------
    def _try_splits(
        self, clusters: list[_Cluster], fits: _Fits, dof: FloatArray, c1: FloatArray, c2: FloatArray,
        pair_hints: dict[int, FloatArray], results: list[list[Contact]],
    ) -> None:
        cand = [
            k for k, cl in enumerate(clusters)
            if cl.members.size >= 2 and dof[k] - 4 >= 2
            # Two disks leave about dof − 4 of noise: only a one-disk χ² beyond that
            # by the threshold can pass the test below.
            and (fits.chi2[k] > dof[k] - 4 + SPLIT_DCHI2 or k in pair_hints)
        ]
        if not cand:
            return
        seeds, owners = [], []
        for k in cand:
            for s in self._pair_seeds(clusters[k], c1, c2, pair_hints.get(k)):
                seeds.append(s)
                owners.append(k)
        sub = [clusters[k] for k in owners]
        free = np.ones((len(sub), 8), dtype=bool)
        two = self._run(self._batch(sub, c1, c2), np.array(seeds), free, 2, False)
        best: dict[int, int] = {}
        for j, k in enumerate(owners):
            if np.isfinite(two.cost[j]) and (k not in best or two.cost[j] < two.cost[best[k]]):
                best[k] = j
        gained = []
        for k, j in best.items():
            infl = max(1.0, two.chi2[j] / (dof[k] - 4))
            if (fits.chi2[k] - two.chi2[j]) / infl > SPLIT_DCHI2:
                gained.append((k, two.theta[j]))
        if not gained:
            return
        final = self._run(self._batch([clusters[k] for k, _ in gained], c1, c2),
                          np.array([th for _, th in gained]), np.ones((len(gained), 8), dtype=bool), 2, True)
        for j, (k, _) in enumerate(gained):
            # Two disks that overlap are no physical answer (the model adds their
            # areas); the test runs after unresolved axes went to their ranges' middles.
            th = final.theta[j]
            r1, r2 = 0.5 * math.exp(th[2]), 0.5 * math.exp(th[6])
            if math.hypot(th[0] - th[4], th[1] - th[5]) >= 0.8 * (r1 + r2) and final.ok[j]:
                results[k] = self._split_contacts(clusters[k], final, j, int(dof[k] - 4))

    def _pair_seeds(self, cl: _Cluster, c1: FloatArray, c2: FloatArray, hinted: FloatArray | None) -> list[FloatArray]:
        """Starting points for two disks: each disk from the area it is credited with."""
        seeds = []
        if hinted is not None:
            seeds.append(np.array([hinted[0, 0], hinted[0, 1], math.log(hinted[0, 2]), math.log(hinted[0, 3]),
                                   hinted[1, 0], hinted[1, 1], math.log(hinted[1, 2]), math.log(hinted[1, 3])]))
        mem = cl.members
        nm = mem.size
        a = np.maximum(np.nan_to_num(cl.area[:nm]), 0.0)
        i1 = int(np.argmax(c1[mem]))
        cen = self.layout.centres[mem]
        sig = np.array([cl.base["pressure"]] * nm)
        # Pressures seen by each member (the inverse's, where it had one).
        g1n, g2n = self.noise
        with np.errstate(divide="ignore", invalid="ignore"):
            press = np.where(np.isfinite(cl.area[:nm]), 0, np.nan)  # placeholder shape
        del press, sig
        order = np.argsort(-c1[mem])
        adj = self._adj_edge
        i2 = next((int(i) for i in order[1:] if adj is None or not adj[mem[i1], mem[i]]), int(order[1]))
        d1 = np.hypot(*(cen - cen[i1]).T)
        d2 = np.hypot(*(cen - cen[i2]).T)
        share1 = np.where(d1 < d2, 1.0, np.where(d1 > d2, 0.0, 0.5))
        for part in (share1,):
            aa, bb = a * part, a * (1.0 - part)
            st = self._starts([cl, cl], [aa, bb])
            s0 = cl.sigma0
            seeds.append(np.array([st[0, 0], st[0, 1], math.log(2 * st[0, 2]), math.log(s0 * aa.sum()),
                                   st[1, 0], st[1, 1], math.log(2 * st[1, 2]), math.log(s0 * bb.sum())]))
        del g1n, g2n
        return [s for s in seeds if np.all(np.isfinite(s))]

    def _split_contacts(self, cl: _Cluster, f: _Fits, j: int, dof: int) -> list[Contact]:
        lay = self.layout
        out = []
        th = f.theta[j]
        b = lay.bounds[cl.members]
        from cellbridge.tactile.skin import disk_rect_overlap

        shares = []
        for d in range(2):
            r = 0.5 * math.exp(th[4 * d + 2])
            shares.append(disk_rect_overlap(th[4 * d], th[4 * d + 1], r, b[:, 0], b[:, 1], b[:, 2], b[:, 3]))
        tot_f = math.exp(th[3]) + math.exp(th[7])
        for d in range(2):
            a = shares[d]
            sig_d = math.exp(th[4 * d + 3]) / (math.pi * (0.5 * math.exp(th[4 * d + 2])) ** 2)
            g1, _ = self._g(sig_d)
            mine = a * g1 > 3.0 * self.noise[0]
            if not mine.any():
                mine = a >= a.max()
            w = np.zeros(lay.n)
            w[cl.members] = a * sig_d
            cx, cy = force_centroid(lay, w, cl.members[mine])
            fsum = cl.base["force_sum"] * math.exp(th[4 * d + 3]) / tot_f
            out.append(self._contact(
                cl, f, j, dof, disk=d, centroid_x=cx, centroid_y=cy,
                elements=tuple(int(i) for i in lay.ids[cl.members[mine]]), pressure=sig_d,
                force_sum=fsum, area=float(a.sum()),
            ))
        return out

    # -- clusters without a pressure: the light touch ---------------------------------------
    def _unlocated(self, cl: _Cluster) -> Contact:
        # Uniform over the cluster's elements: the ΔC1-weighted centroid, σ = side/√12 per element.
        sx = sy = self.layout.side / math.sqrt(12.0) * cl.members.size
        x, y = cl.centroid
        return Contact(
            x=float(x), y=float(y), force=math.nan, diameter=math.nan, model_x=math.nan, model_y=math.nan,
            sigma_x=sx, sigma_y=sy, sigma_xy=sx, cov=((sx * sx, 0.0), (0.0, sy * sy)), sigma_force=math.nan,
            sigma_diameter=math.nan, valid=False, fit_ok=False, observable=(False, False), chi2=math.nan,
            dof=0, **cl.base,
        )

    def _fit_light(self, clusters: list[_Cluster], c1: FloatArray, c2: FloatArray) -> list[Contact]:
        """Position of a touch whose pressure the inverse cannot give.

        At low pressure ΔC ≈ k·F whatever the area, so the diameter is not known;
        but for any given diameter the elements' shares still fix the centre along a
        straddled axis. Fits at fixed diameters over the plausible range (force
        free) and free fits from the grid's local minima; keeps those consistent with
        the readings (cost within 1 of the best) and reports the span of their
        centres (± their own σ): centre of the span, σ = span/√12 combined with the
        fits' own σ.
        """
        lay = self.layout
        nd_grid = 20
        out = []
        diam = np.geomspace(0.05 * lay.side, 1.5 * lay.side, nd_grid)
        probs: list[_Cluster] = []
        p = self.params
        k_low = p.eps1 * (p.d1 - p.d10) / (p.E1 * p.d1 * p.d1)  # g1/σ as σ → 0
        areas, lnf = [], []
        for cl in clusters:
            nm = cl.members.size
            s1 = np.maximum(c1[cl.members], 0.0)
            tot = s1.sum()
            share = s1 / tot if tot > 0 else np.full(nm, 1.0 / nm)
            f0 = max(tot / k_low, 1e-6) if tot > 0 else 1e-3
            for d in diam:
                areas.append(share * math.pi * d * d / 4)
                lnf.append(math.log(f0))
                probs.append(cl)
        st = self._starts(probs, areas)
        t0 = np.column_stack([st[:, :2], np.log(np.tile(diam, len(clusters))), lnf])
        free = np.tile(np.array([True, True, False, True]), (len(probs), 1))
        saved = self.method
        self.method = "capacitance"  # the area method needs a pressure; ΔC does not
        try:
            fits = self._run(self._batch(probs, c1, c2), t0, free, 1, False)
            # The grid is coarse near a sharp minimum (the ambiguous region has two
            # discrete branches): every local minimum of the grid is refined with the
            # diameter free as well.
            cost = fits.cost.reshape(len(clusters), nd_grid)
            padded = np.pad(cost, ((0, 0), (1, 1)), constant_values=np.inf)
            loc = np.isfinite(cost) & (cost <= padded[:, :-2]) & (cost <= padded[:, 2:])
            qk, qd = np.nonzero(loc)
            rows = qk * nd_grid + qd
            ref = self._run(self._batch([clusters[k] for k in qk], c1, c2), fits.theta[rows],
                            np.ones((qk.size, 4), dtype=bool), 1, False)
        finally:
            self.method = saved
        for i, cl in enumerate(clusters):
            sl = slice(i * nd_grid, (i + 1) * nd_grid)
            mine = qk == i
            c_ref = ref.cost[mine]
            floor = min(float(np.nanmin(cost[i])), float(np.nanmin(c_ref)) if c_ref.size else np.inf)
            best = np.isfinite(cost[i]) & (cost[i] <= floor + 1.0)
            # The true diameter may lie between two grid points: the neighbours of a
            # consistent one count too, so the span brackets it.
            keep = best.copy()
            keep[1:] |= best[:-1]
            keep[:-1] |= best[1:]
            keep &= np.isfinite(cost[i])
            kref = np.isfinite(c_ref) & (c_ref <= floor + 1.0)
            b = lay.bounds[cl.members]
            pos, sig, obs = [0.0, 0.0], [0.0, 0.0], [False, False]
            dmin = float(diam[keep].min()) if keep.any() else 0.0
            for ax in (0, 1):
                v = np.concatenate([fits.theta[sl, ax][keep], ref.theta[mine, ax][kref]])
                s = np.concatenate([fits.sig[sl, ax][keep], ref.sig[mine, ax][kref]])
                lo_e, hi_e = b[:, ax].min(), b[:, ax + 2].max()
                if v.size and np.all(np.isfinite(s)) and s.max() < 0.25 * lay.side:
                    lo, hi = float(np.min(v - s)), float(np.max(v + s))
                    pos[ax] = 0.5 * (lo + hi)
                    sig[ax] = math.sqrt((hi - lo) ** 2 / 12.0 + float(np.mean(s * s)))
                    obs[ax] = True
                else:
                    pos[ax] = 0.5 * (lo_e + hi_e)
                    sig[ax] = max(hi_e - lo_e - dmin, 0.0) / math.sqrt(12.0)
            # A best fit far worse than the noise found no disk that explains the
            # readings (the search missed, or it is no disk): no interval then.
            dof = 2 * cl.obs.size - 3
            plausible = floor <= dof + 5.0 * math.sqrt(2.0 * max(dof, 1)) + 10.0
            if not ((keep.any() or kref.any()) and any(obs) and plausible):
                out.append(self._unlocated(cl))
                continue
            x, y = pos
            sx, sy = sig
            j = int(np.nanargmin(cost[i]))
            out.append(Contact(
                x=float(x), y=float(y), force=math.nan, diameter=math.nan, model_x=float(x), model_y=float(y),
                sigma_x=float(sx), sigma_y=float(sy), sigma_xy=float(max(sx, sy)),
                cov=((float(sx * sx), 0.0), (0.0, float(sy * sy))), sigma_force=math.nan,
                sigma_diameter=math.nan, valid=False, fit_ok=True, observable=(bool(obs[0]), bool(obs[1])),
                chi2=float(fits.chi2[sl][j]), dof=int(dof), **cl.base,
            ))
        return out


def _major(vx: float, vy: float, cxy: float) -> float:
    """Larger semi-axis (one sigma) of a 2×2 covariance, in closed form."""
    half = 0.5 * (vx + vy)
    return math.sqrt(max(half + math.hypot(0.5 * (vx - vy), cxy), 0.0))


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
