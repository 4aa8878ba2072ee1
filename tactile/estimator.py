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
:mod:`cellbridge.tactile.disk_model` and :mod:`cellbridge.tactile.fit_kernel` (the
spread model in :mod:`cellbridge.tactile.spread_model`), the problems they are posed
in :mod:`cellbridge.tactile.fit_problems` (a frame's clusters gathered in one compiled
pass, :mod:`cellbridge.tactile.cluster_kernel`), the two-disk split in
:mod:`cellbridge.tactile.two_disks` and the light touch in
:mod:`cellbridge.tactile.light_touch`. Every fit of a frame runs in one kernel call
per kind (one-disk, two-disk, fixed-diameter).
"""

from __future__ import annotations

import itertools
import math
from typing import Literal, NamedTuple, Sequence

import numpy as np
from cellbridge.tactile.arrays import FloatArray, IntArray
from cellbridge.tactile.clusters import cluster_elements
from cellbridge.tactile.contact_result import Contact
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.fit_problems import Batch, Cluster, FitRunner, Fits, frame_noise
from cellbridge.tactile.inverse_kernel import solve_compiled as solve
from cellbridge.tactile.inversion import DEFAULT_NOISE, InverseStatus, branch_info
from cellbridge.tactile.layout import SkinLayout
from cellbridge.tactile.light_touch import locate_light, unlocated
from cellbridge.tactile.response import _check_spread, _spread_cells
from cellbridge.tactile.spread_model import DV, PROFILE_ROWS
from cellbridge.tactile.two_disks import MODEL_ERROR, split_clusters
from numpy.typing import ArrayLike, NDArray

__all__ = ["ContactEstimator", "estimate_contacts"]

#: Steps in ln F above a hard press's fit where its profile cost is taken.
FIRM_STEPS = np.array([0.05, 0.1, 0.2, 0.4, 0.8, 1.6])
#: (the status as a plain int: an enum member looked up and compared on every frame costs more)
_ILL_CONDITIONED = int(InverseStatus.ILL_CONDITIONED)


class Inverse(NamedTuple):
    """One or more frames' element inverses (:meth:`ContactEstimator._inverse`): (T, N) each."""

    valid: NDArray[np.bool_]
    force: FloatArray
    area: FloatArray
    firm: FloatArray | None  # None: no active element too noisy
    hard: NDArray[np.bool_] | None  # the active elements too noisy (None: none)

    def rows(self, rows: IntArray) -> Inverse:
        """The inverse of the elements ``rows`` alone: what :meth:`ContactEstimator._inverse`
        gives on their readings (``firm`` None where none of them is too noisy)."""
        hard = None if self.hard is None or not self.hard[:, rows].any() else self.hard[:, rows]
        return Inverse(self.valid[:, rows], self.force[:, rows], self.area[:, rows],
                       None if hard is None or self.firm is None else self.firm[:, rows], hard)


class ContactEstimator:
    """Turns per-element ΔC (and touch flags) of one time step into :class:`Contact` s.

    ``noise`` is the rms noise of one ΔC reading (F, scalar or per channel); it
    weights the fit and scales every reported uncertainty. ``spread`` is the
    membrane-tension model of :func:`cellbridge.tactile.response.skin_response` (0: the
    paper's assumption). ``method`` picks what the disk is fitted to:
    ``"capacitance"`` (ΔC of the cluster and its neighbours; default) or ``"area"``
    (the per-element areas from the inverse; uniform pressure only). ``split``
    allows a cluster to be reported as two contacts when two disks explain it
    significantly better than one; ``model_error`` is how far (relative to a
    cluster's largest reading) any reading may stray from the model for another
    reason than noise (gain errors, the sheets' tension, foam ageing): a second disk
    must explain more than that (:mod:`cellbridge.tactile.two_disks`). 0 trusts the
    model to the noise, which only readings the model made deserve.
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
        model_error: float = MODEL_ERROR,
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
        if not (math.isfinite(model_error) and 0.0 <= model_error < 1.0):
            raise ValueError(f"model_error must be a fraction in [0, 1), got {model_error!r}")
        self.model_error = float(model_error)
        self._runner = FitRunner(layout, self.params, nz, method == "area")
        self._sigma_unique = branch_info(self.params).sigma_unique
        lo, hi = layout.bounds[:, :2].min(axis=0), layout.bounds[:, 2:].max(axis=0)
        # Each element's rectangle with a quarter side of slack, where a hint counts as on it
        # (:meth:`_hints_in`): the same sums every frame, made once.
        slack = 0.25 * layout.side
        self._grown = layout.bounds + np.array([-slack, -slack, slack, slack])
        self._skin_diagonal = float(np.hypot(*(hi - lo)))
        self._adj_edge = layout.adjacency("edge") if layout.n <= 4096 else None
        if self.spread > 0:
            _spread_cells(layout.side, self.spread, quad_step)  # validates quad_step now
            # The spread model's profile rows for disks up to an element side, built
            # now (≈ 1 s once per process, at most 300 rows) rather than in a frame.
            PROFILE_ROWS.upto(min(int(math.ceil((0.5 * layout.side / self.spread + 2.0) / DV)) + 2, 300))

    # -- public -----------------------------------------------------------------------
    def estimate(
        self,
        dC1: ArrayLike,
        dC2: ArrayLike,
        active: ArrayLike | None = None,
        *,
        hints: ArrayLike | None = None,
        replaced: NDArray[np.bool_] | None = None,
    ) -> list[Contact]:
        """Contacts from ΔC (F) of every element; ``active`` = touched elements.

        Without ``active``, an element is active when either channel exceeds three
        noise sigmas. NaN readings count as inactive and are left out of the fits.
        ``hints`` are ``(x, y, diameter, force)`` rows of contacts expected in this
        frame (the previous frame's, from :class:`~cellbridge.tactile.tracker.ContactTracker`):
        a cluster containing one starts its fit there (rows with NaN diameter or force only
        say where a contact was: touches on two sides of an element with no reading stay
        two clusters where each side holds one).

        ``replaced``: (N,) the elements whose contacts the caller takes from elsewhere and
        drops here (:class:`~cellbridge.tactile.seam_estimator.SeamEstimator`: those of a
        press across a wrap seam). A cluster wholly on them is not estimated: every contact
        a cluster gives names one of its elements at least, so each would have been dropped;
        the other clusters' contacts are what they are without it (each cluster is fitted
        on its own readings), in the same order.
        """
        (per_frame,) = self._estimate(*self._readings(dC1, dC2, active, 1), _checked_hints(hints),
                                      self._replaced_mask(replaced))
        return per_frame

    def _replaced_mask(self, replaced: ArrayLike | None) -> NDArray[np.bool_] | None:
        """``replaced`` checked: (N,) flags, one per element of the layout, or None.

        Raises ValueError for anything else: element rows or ids, or another layout's
        mask, would index the clusters' members silently and drop the wrong contacts."""
        if replaced is None:
            return None
        r = np.asarray(replaced)
        if r.dtype != np.bool_ or r.shape != (self.layout.n,):
            raise ValueError(f"replaced must be ({self.layout.n},) bool flags, one per element; "
                             f"got {r.dtype} of shape {r.shape}")
        return r

    def estimate_frames(
        self, dC1: ArrayLike, dC2: ArrayLike, active: ArrayLike | None = None
    ) -> list[list[Contact]]:
        """:meth:`estimate` for T frames at once: ``dC1``, ``dC2`` (and ``active``)
        of shape (T, N); one list of contacts per frame.

        The same answers, cheaper per frame: one inverse call and one kernel call per
        kind of fit serve every frame (for a backlog, a recording, or several skins'
        frames that arrive together).
        """
        c1, c2, act = self._readings(dC1, dC2, active, None)
        return self._estimate(c1, c2, act, np.zeros((0, 4)))

    # -- per frame ------------------------------------------------------------------------
    def _readings(
        self, dC1: ArrayLike, dC2: ArrayLike, active: ArrayLike | None, frames: int | None
    ) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        """(T, N) readings and active flags, checked; ``frames=1``: one frame of (N,)."""
        n = self.layout.n
        c1 = np.asarray(dC1, dtype=np.float64)
        c2 = np.asarray(dC2, dtype=np.float64)
        want = (n,) if frames == 1 else (c1.shape[0] if c1.ndim == 2 else -1, n)
        if c1.shape != want or c2.shape != want:
            shape = f"({n},)" if frames == 1 else f"(T, {n})"
            raise ValueError(f"dC1 and dC2 must have shape {shape}, got {c1.shape} and {c2.shape}")
        c1, c2 = c1.reshape(-1, n), c2.reshape(-1, n)
        finite = np.isfinite(c1) & np.isfinite(c2)
        if active is None:
            act = finite & ((c1 > 3 * self.noise[0]) | (c2 > 3 * self.noise[1]))
        else:
            act = np.asarray(active, dtype=bool)
            if act.shape != want:
                raise ValueError(f"active must have the readings' shape {want}, got {act.shape}")
            act = act.reshape(-1, n) & finite
        return c1, c2, act

    def _inverse(self, c1: FloatArray, c2: FloatArray, act: NDArray[np.bool_]) -> Inverse:
        """Each active element's inverse, as (T, N) arrays: whether it gave a pressure
        (``valid``), its force and area (NaN where none), and ``firm`` (see
        :meth:`FitRunner.frame_clusters`; None where no active element is too noisy).

        Each element's inverse is its readings' alone, so the same readings give the same
        values on any layout holding the element (a band's second chart, whose frame is
        the skin's: :class:`~cellbridge.tactile.seam_estimator.SeamEstimator`, :meth:`Inverse.rows`)."""
        valid = np.zeros(c1.shape, dtype=bool)
        force = np.full(c1.shape, np.nan)
        area = np.full(c1.shape, np.nan)
        firm = None
        hard_at = None
        if act.any():
            inv = solve(c1[act], c2[act], self.params, noise=float(self.noise.max()), **self.inverse_options)
            valid[act] = inv.valid
            force[act] = inv.force
            area[act] = inv.area
            # A hard press (saturating foam, a small tip) can be too noisy for one
            # element's inverse, yet its pressure is on the unique high branch: no
            # light touch reads like it. The cluster's fit, over all its elements,
            # still measures the force (with its own σ); the pressure starts it.
            hard = inv.status == _ILL_CONDITIONED
            if hard.any():
                firm = np.full(c1.shape, np.nan)
                firm[act] = np.where(hard & (inv.pressure >= self._sigma_unique), inv.pressure, np.nan)
                hard_at = np.zeros(c1.shape, dtype=bool)
                hard_at[act] = hard
        return Inverse(valid, force, area, firm, hard_at)

    def _estimate(
        self, c1: FloatArray, c2: FloatArray, act: NDArray[np.bool_], hints: FloatArray,
        replaced: NDArray[np.bool_] | None = None, inverse: Inverse | None = None,
    ) -> list[list[Contact]]:
        lay = self.layout
        valid, force, area, firm, _ = self._inverse(c1, c2, act) if inverse is None else inverse
        clusters: list[Cluster] = []
        frame_of: list[int] = []
        for t in range(c1.shape[0]):
            if not act[t].any():
                continue
            finite = np.isfinite(c1[t]) & np.isfinite(c2[t])
            labels = self._clusters(act[t], finite, hints)
            ring_noise = frame_noise(c1[t], c2[t], finite & ~act[t], self.noise)
            # (clusters wholly on replaced elements left out: see estimate)
            these = self._runner.frame_clusters(labels, c1[t], c2[t], finite, valid[t], force[t], area[t],
                                                None if firm is None else firm[t], ring_noise, replaced)
            clusters.extend(these)
            frame_of.extend([t] * len(these))
        out: list[list[Contact]] = [[] for _ in clusters]
        good = [k for k, cl in enumerate(clusters) if cl.valid]
        if good:
            for k, cs in zip(good, self._fit_valid([clusters[k] for k in good], hints)):
                out[k] = cs
        # A light touch on one element says nothing finer than the element (no fit),
        # unless a quiet neighbour reads a share of it (fit_problems.RING_SIGNAL).
        light = [k for k, cl in enumerate(clusters) if not cl.valid and (cl.members.size > 1 or cl.ring_reads)]
        for k, cl in enumerate(clusters):
            if not cl.valid and cl.members.size == 1 and not cl.ring_reads:
                out[k] = [unlocated(cl, lay.side)]
        if light:
            for k, c in zip(light, locate_light(self._runner, [clusters[k] for k in light])):
                out[k] = [c]
        frames: list[list[Contact]] = [[] for _ in range(c1.shape[0])]
        for t, cs in zip(frame_of, out):
            frames[t].extend(cs)
        return frames

    def _clusters(self, act: NDArray[np.bool_], finite: NDArray[np.bool_], hints: FloatArray) -> IntArray:
        """Cluster labels of one frame's active elements (see ``cluster_elements``).

        Active elements around one unknown element are one cluster: a corner press whose
        two edge elements have no reading yet would otherwise come out as two contacts on
        its diagonal elements. Their readings alone cannot tell that from two presses, one
        on each diagonal element: where the hints (the contacts of the frames before) put
        a contact on each side, the sides stay apart."""
        lay = self.layout
        edge = cluster_elements(lay, act, self.connectivity)
        if finite.all():
            return edge
        joined = cluster_elements(lay, act, self.connectivity, unknown=~finite)
        if hints.shape[0] >= 2:
            owners = lay.element_at(hints[:, :2])
            held = np.unique(edge[owners[owners >= 0]])
            held = held[held >= 0]  # the edge clusters a hinted contact lies on
            if held.size >= 2:
                sel = np.isin(edge, held)
                pairs = np.unique(np.stack([joined[sel], edge[sel]], axis=1), axis=0)
                two = np.bincount(pairs[:, 0], minlength=int(joined.max()) + 1) >= 2
                keep = act & two[np.maximum(joined, 0)]
                if keep.any():  # those joined clusters go back to their edge clusters
                    pieces = np.where(keep, edge + int(joined.max()) + 1, joined)[act]
                    _, first, inv = np.unique(pieces, return_index=True, return_inverse=True)
                    res = np.full(lay.n, -1, dtype=np.int64)
                    res[act] = np.argsort(np.argsort(first))[inv]  # numbered by lowest element
                    return res
        return joined

    # -- clusters with a pressure ---------------------------------------------------------
    def _fit_valid(self, clusters: list[Cluster], hints: FloatArray) -> list[list[Contact]]:
        nd_free = np.array([True, True, True, self.method != "area"])
        run = self._runner
        batch = run.batch(clusters)
        st = run.starts(clusters, batch=batch)
        theta0 = np.empty((len(clusters), 4))
        theta0[:, :2] = st[:, :2]
        theta0[:, 2] = np.log(2.0 * st[:, 2])
        theta0[:, 3] = np.log(np.array([cl.sigma0 for cl in clusters]) * math.pi * st[:, 2] ** 2)
        pair_hints: dict[int, FloatArray] = {}
        hinted = np.zeros(len(clusters), dtype=bool)
        if hints.shape[0]:  # (no hints, no cluster has one: nothing to ask per cluster)
            for k, inside in enumerate(self._hints_in(clusters, hints, 2.0 * st[:, 2])):
                if inside.shape[0] >= 1:
                    hinted[k] = True
                    hx, hy, hd, hf = inside[0].tolist()
                    theta0[k] = (hx, hy, math.log(hd), math.log(hf))
                if inside.shape[0] >= 2:
                    pair_hints[k] = inside[:2]
        free = np.empty((len(clusters), 4), dtype=bool)
        free[:] = nd_free
        fits = run.run(batch, theta0, free, 1, True)
        # A warm start in the wrong valley (the disk moved far since last frame) is
        # caught by its fit quality and redone from the readings' own start.
        dof = batch.dof(4 if self.method != "area" else 3)
        redo = np.nonzero(hinted & (fits.chi2 > dof + 3.0 * np.sqrt(2.0 * np.maximum(dof, 1)) + 1.0))[0]
        if redo.size:
            sub = [clusters[k] for k in redo]
            t0 = np.column_stack([st[redo, :2], np.log(2 * st[redo, 2]),
                                  np.log([clusters[k].sigma0 * math.pi * st[k, 2] ** 2 for k in redo])])
            again = run.run(run.batch(sub), t0, free[redo], 1, True)
            for j, k in enumerate(redo.tolist()):
                if again.cost[j] < fits.cost[k]:
                    fits.take(k, again, j)
        # Measured on the uniform fit (the foam's saturation, not the tension, makes
        # the force's cost flat upwards), applied to whichever fit is reported.
        firm_sig = self._firm_force_sigma(clusters, fits, free)
        shifts = self._ring_shifts(clusters, fits, free) if self.method != "area" else {}
        if self.spread > 0:
            fits = self._spread_refine(batch, fits)
        for k, s_lnf in firm_sig.items():
            fits.sig[k, 3] = max(fits.sig[k, 3], s_lnf)
        for k, shift in shifts.items():
            for a in (0, 1):
                if not fits.flat[k, a]:
                    fits.sig[k, a] = math.hypot(fits.sig[k, a], shift[a])
                    fits.cov[k, a, a] += shift[a] ** 2
        area_force = self.method == "area"
        results = {k: [c] for k, c in enumerate(fits.contacts(clusters, dof, area_force))}
        # Two disks need the uniform model: under a spread, a one-disk misfit of the
        # uniform model is no evidence of a second contact.
        split: dict[int, list[Contact]] = {}
        if self.split and self.method != "area" and self.spread == 0:
            split = split_clusters(run, clusters, fits, dof, pair_hints, self._adj_edge, self.model_error)
            results.update(split)
        # A pressure from an element's inverse that no disk (nor two) agrees with (a
        # reading that passed the inverse's checks on the wrong branch): locate the
        # touch as one without a pressure, if that finds a disk that fits.
        failed = [k for k in range(len(clusters))
                  if not fits.ok[k] and clusters[k].members.size > 1 and k not in split]
        if failed:
            for k, c in zip(failed, locate_light(run, [clusters[k] for k in failed])):
                if c.fit_ok:
                    results[k] = [c]
        return list(results.values())

    def _ring_shifts(self, clusters: list[Cluster], fits: Fits, free: NDArray[np.bool_]) -> dict[int, FloatArray]:
        """Per fit placed by a quiet neighbour's reading, how far its centre moves (x, y)
        when that reading is smaller by the model tolerance: added to σ of each resolved axis.

        A footprint's share on an untouched neighbour is a few per cent of the cluster's
        readings, and it alone places the disk along that seam: a gain error, the sheets'
        tension, or the drift tracker absorbing the share while a press is held (at
        ``max_drift``, over tens of seconds) moves it, and the noise-only σ (hundredths of
        a millimetre) would then not hold the truth. So each such fit is redone (uniform
        model) with those readings lowered by ``model_error`` of the cluster's largest
        reading (at least to 0): the same tolerance a second disk must beat
        (:mod:`cellbridge.tactile.two_disks`). A refit that fails says nothing of the
        shift: then the element's own spread, side/√12.
        """
        rows = [k for k, cl in enumerate(clusters) if fits.ok[k] and cl.ring_reads]
        if not rows or self.model_error == 0.0:
            return {}
        # (the clusters' batch, its readings lowered where they are ring readings that count:
        # the same values as a batch of changed clusters, without a copy of each cluster)
        batch = self._runner.batch([clusters[k] for k in rows])
        for k, at in zip(rows, batch.off[:-1].tolist()):
            cl = clusters[k]
            nm = cl.members.size
            peak = np.fmax.reduce(np.abs(cl.y[:, :nm]), axis=1)  # (nanmax's values, without its copies)
            tol = self.model_error * np.where(np.isfinite(peak), peak, 0.0)
            ring = at + cl.seen[cl.seen >= nm]
            batch.y[:, ring] = np.maximum(batch.y[:, ring] - tol[:, None], 0.0)
        moved = self._runner.run(batch, fits.theta[rows].copy(), free[rows], 1, False)
        wide = np.full(2, self.layout.side / math.sqrt(12.0))
        return {k: (moved.theta[j, :2] - fits.theta[k, :2] if moved.ok[j] else wide) for j, k in enumerate(rows)}

    def _firm_force_sigma(self, clusters: list[Cluster], fits: Fits, free: NDArray[np.bool_]) -> dict[int, float]:
        """Least σ of ln F of each hard press, from the profile upwards, not the curvature alone.

        Where the foam saturates, more force barely changes the readings: the cost
        in ln F is flat upwards, so the curvature's σ is too small on that side (the
        truth lay 3–6 σ above the fit). The force held at a few steps above the fit,
        the rest re-fitted, gives where the cost has risen by 4 (2σ); σ_F is at least
        half of that excursion.
        """
        if not any(cl.firm for cl in clusters):
            return {}
        firm = np.array([k for k, cl in enumerate(clusters) if cl.firm and fits.ok[k] and free[k, 3]], dtype=np.int64)
        if firm.size == 0:
            return {}
        steps = FIRM_STEPS
        t0 = np.repeat(fits.theta[firm], steps.size, axis=0)
        t0[:, 3] += np.tile(steps, firm.size)
        fr = np.tile(np.array([True, True, True, False]), (t0.shape[0], 1))
        sub = self._runner.batch([clusters[k] for k in firm for _ in steps])
        prof = self._runner.run(sub, t0, fr, 1, False)
        rise = prof.cost.reshape(firm.size, steps.size) - fits.cost[firm, None]
        out = {}
        for i, k in enumerate(firm):
            over = np.nonzero(~(rise[i] <= 4.0))[0]
            if over.size == 0:
                up = 2.0 * steps[-1]
            elif over[0] == 0:
                up = steps[0]
            else:
                j = over[0]
                r0, r1 = max(rise[i, j - 1], 0.0), rise[i, j]
                frac = (4.0 - r0) / (r1 - r0) if np.isfinite(r1) and r1 > r0 else 1.0
                up = steps[j - 1] + frac * (steps[j] - steps[j - 1])
            out[int(k)] = 0.5 * math.expm1(up)
        return out

    def _spread_refine(self, batch: Batch, uni: Fits) -> Fits:
        """The uniform fits, refined with the spread model (cheap start, close position).

        Axes the uniform fit found unresolved stay at the middle of their range (a
        disk inside one element sees its position under tension only through the
        tails, which the readings resolve no better); the others, D and F are fitted
        again, and their σ come from the spread model's curvature.
        """
        s = self.spread
        # Rows for the fits kept (a failed fit may sit at any size, up to 100 sides),
        # and for no disk larger than the skin: each row costs memory for the process.
        d_kept = np.exp(uni.theta[uni.ok, 2])
        d_max = min(float(d_kept.max(initial=0.0)), self._skin_diagonal)
        rows = PROFILE_ROWS.upto(int(math.ceil((0.5 * d_max * 1.5 / s + 2.0) / DV)) + 2)
        sm = (s, _spread_cells(self.layout.side, s, self.quad_step), rows)
        free = np.ones(uni.theta.shape, dtype=bool)
        free[:, :2] = ~uni.flat[:, :2]
        good = uni.ok
        out = self._runner.run(batch, uni.theta, free, 1, False, sm)
        for j in range(2):
            keep = uni.flat[:, j] | ~good
            out.sig[keep, j] = uni.sig[keep, j]
            out.flat[:, j] = uni.flat[:, j]
        out.ok &= good
        return out

    def _hints_in(self, clusters: list[Cluster], hints: FloatArray, d_start: FloatArray) -> list[FloatArray]:
        """Per cluster, the hints that can be its disk, nearest its centroid first
        (``d_start``: (K,) the diameter each cluster's readings say).

        A hint must sit on one of the cluster's elements (a quarter side of slack:
        the disk moved), be whole (finite, positive diameter and force) and have a
        diameter within a factor 2 of what the readings say now; anything else (a finger
        lifted here and pressed there) would start the fit in a wrong valley, slower and
        worse than the readings' own start.

        Every cluster in one pass, over its members only: each (hint, element) comparison
        and each (hint, cluster) ratio is the one a cluster at a time computes, and on a
        humanoid's 1 144 elements comparing every hint with every element, then asking
        each cluster apart, cost a tenth of a frame's estimate."""
        members = [cl.members for cl in clusters]
        g = self._grown[np.concatenate(members)]  # (the members' rectangles with the slack, as (M, 4))
        hx, hy = hints[:, 0:1], hints[:, 1:2]  # (H, 1) each
        on = (hx >= g[:, 0]) & (hx <= g[:, 2]) & (hy >= g[:, 1]) & (hy <= g[:, 3])
        # (K, H): on one of the cluster's elements (a cluster has one member at least)
        starts = list(itertools.accumulate([m.size for m in members[:-1]], initial=0))
        on_cluster = np.logical_or.reduceat(on, starts, axis=1).T
        sound = np.isfinite(hints).all(axis=1) & (hints[:, 2] > 0) & (hints[:, 3] > 0)
        with np.errstate(invalid="ignore", divide="ignore"):
            size_ok = np.abs(np.log(hints[None, :, 2] / np.asarray(d_start, dtype=np.float64)[:, None])) <= math.log(2.0)
        ok = on_cluster & sound[None, :] & size_ok
        # (a cluster's hints by their rows, a view for one: most clusters hold one hint or none)
        none = hints[:0]
        out = []
        for k, at in enumerate(ok.tolist()):
            n = at.count(True)
            if n == 0:
                out.append(none)
            elif n == 1:
                j = at.index(True)
                out.append(hints[j : j + 1])
            else:
                h = hints[ok[k]]
                cx, cy = clusters[k].centroid
                out.append(h[np.argsort(np.hypot(h[:, 0] - cx, h[:, 1] - cy))])
        return out


def _checked_hints(hints: ArrayLike | None) -> FloatArray:
    """``hints`` of :meth:`ContactEstimator.estimate` as (H, 4) rows; ValueError for another shape."""
    h = np.zeros((0, 4)) if hints is None else np.asarray(hints, dtype=np.float64)
    if h.ndim == 1 and h.size in (0, 4):
        h = h.reshape(-1, 4)
    if h.ndim != 2 or h.shape[1] != 4:
        raise ValueError(f"hints must be (x, y, diameter, force) rows, got shape {h.shape}")
    return h



def estimate_contacts(
    layout: SkinLayout,
    dC1: ArrayLike,
    dC2: ArrayLike,
    active: ArrayLike | None = None,
    params: ElementParams | None = None,
    **options: object,
) -> list[Contact]:
    """One-shot :class:`ContactEstimator` (same keyword options)."""
    return ContactEstimator(layout, params, **options).estimate(dC1, dC2, active)  # type: ignore[arg-type]  # the options are ContactEstimator's own keywords, checked there
