"""One frame's fit problems: per-cluster data, the kernel's flat arrays, the results.

The estimator, the two-disk split and the light-touch locator all pose fits the same
way: a cluster's observed elements (the cluster, then its quiet ring) with their
readings, a start and which parameters are free. :class:`FitRunner` turns lists of
such problems into one call of :func:`cellbridge.tactile.fit_kernel.fit_batch` and
hands back :class:`Fits`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from cellbridge.tactile.arrays import FloatArray, IntArray, median0
from cellbridge.tactile.cluster_kernel import gather_clusters
from cellbridge.tactile.contact_result import Contact
from cellbridge.tactile.disk_model import element_vector, sensitivity_slope
from cellbridge.tactile.element import ElementParams
from cellbridge.tactile.fit_kernel import UNIFORM, fit_batch, share_start
from cellbridge.tactile.layout import SkinLayout
from numpy.typing import NDArray

__all__ = ["Cluster", "Batch", "Fits", "FitRunner", "RING_SIGNAL", "frame_noise", "major_axis"]

#: Noise sigmas above which a quiet ring element's reading is the disk's, not noise: a
#: footprint reaching onto it by a fraction of a millimetre reads tens of sigmas while
#: the touch threshold (an absolute ΔC, far above the noise) still calls it untouched.
#: Such a reading enters the fit two-sided like a member's: it is what places the disk
#: along the seam. Below it the ring only bounds the disks from above (a disk gains
#: nothing by grazing a neighbour to explain its noise). 5 sigma on either channel:
#: noise alone gets there about once in a million readings. The sigma is the larger of
#: the configured noise and the frame's own (:func:`frame_noise`).
RING_SIGNAL = 5.0
#: Fewest untouched elements whose readings measure a frame's noise; with fewer, no
#: ring reading is taken for signal (the configured noise alone may be far too small:
#: an ADC front end reads tens of times noisier than the counter it defaults to).
FRAME_NOISE_MIN = 6


def frame_noise(c1: FloatArray, c2: FloatArray, untouched: NDArray[np.bool_], floor: FloatArray) -> FloatArray:
    """(2,) noise of one frame's readings per channel: 1.4826·median |ΔC| of its untouched
    elements (about zero: a common offset counts as noise), at least ``floor``; infinite
    with fewer than :data:`FRAME_NOISE_MIN` untouched elements.

    Untouched elements read the noise (and the few sub-threshold shares of a press, which
    the median ignores), whatever the configured noise says: a skin whose readings are
    noisier than configured does not turn its quiet elements' noise into signal.
    """
    if int(untouched.sum()) < FRAME_NOISE_MIN:
        return np.full(2, np.inf)
    # (both channels' medians in one partition of an (n, 2) array: column by column the same
    # values as a median each, in half the numpy calls)
    mad = median0(np.abs(np.stack([c1[untouched], c2[untouched]], axis=1)))
    return np.maximum(floor, 1.4826 * mad)


@dataclass
class Cluster:
    """One cluster's data in one frame (indices are layout rows)."""

    members: IntArray
    obs: IntArray  # members first, then the quiet ring
    sigma0: float  # shared pressure from the valid elements (NaN: none)
    area: FloatArray  # per observed element
    y: FloatArray  # (2, observed) ΔC1, ΔC2 read: a cluster carries its frame's readings
    centroid: tuple[float, float]
    valid: bool  # a pressure and a positive area: the disk can be fitted
    base: dict = field(default_factory=dict)  # Contact fields known before any fit
    firm: bool = False  # the pressure is from too-noisy high-branch elements only
    bounds: FloatArray | None = None  # the layout's element bounds (a reference, for failed fits)
    #: (observed,) True: the reading only bounds the disks from above (a quiet ring
    #: element at the noise); None: the ring (every element after the members)
    quiet: NDArray[np.bool_] | None = None

    @cached_property
    def seen(self) -> IntArray:
        """Positions in ``obs`` of the elements that read the disk: the members, then
        the ring elements whose reading counts both ways (where a start looks).

        Computed once (``quiet`` does not change after the cluster is made: a changed
        cluster is a new one, ``dataclasses.replace``); asked many times a frame."""
        if self.quiet is None:
            return np.arange(self.members.size)
        return np.flatnonzero(~self.quiet)

    @cached_property
    def ring_reads(self) -> bool:
        """Whether a quiet ring element reads a share of the disk (one counts both ways):
        computed once, as :attr:`seen`, and asked by each stage of a frame's fits."""
        return self.quiet is not None and not bool(self.quiet[self.members.size :].all())


@dataclass
class Batch:
    """Flat arrays of several fit problems, as the kernel takes them."""

    off: IntArray
    bounds: FloatArray
    y: FloatArray
    quiet: NDArray[np.bool_]
    w: FloatArray
    nch: int

    @property
    def n(self) -> int:
        return self.off.size - 1

    def dof(self, nfree: int) -> FloatArray:
        """Readings minus free parameters, per problem."""
        return (self.nch * (self.off[1:] - self.off[:-1]) - nfree).astype(np.float64)


@dataclass
class Fits:
    """Kernel results, one row per problem (parameters ``(x, y, ln D, ln F)`` per disk)."""

    theta: FloatArray
    sig: FloatArray
    flat: NDArray[np.bool_]
    cov: FloatArray
    chi2: FloatArray
    cost: FloatArray
    ok: NDArray[np.bool_]

    def take(self, k: int, other: Fits, j: int) -> None:
        """Row k becomes row j of ``other``."""
        for name in ("theta", "sig", "flat", "cov", "chi2", "cost", "ok"):
            getattr(self, name)[k] = getattr(other, name)[j]

    def contact(self, cl: Cluster, k: int, dof: int, area_force: bool = False, disk: int = 0,
                **over: object) -> Contact:
        """The :class:`Contact` of disk ``disk`` of problem k (``over`` replaces base fields).

        ``area_force``: the force is σ₀·πD²/4 (fits to areas, where F is no parameter).
        """
        # (Python floats from here: the same arithmetic, without numpy scalars' overhead.)
        return _contact(cl, self.theta[k, 4 * disk : 4 * disk + 4].tolist(), self.sig[k, 4 * disk : 4 * disk + 4].tolist(),
                        self.flat[k, 4 * disk : 4 * disk + 2].tolist(), float(self.cov[k, 4 * disk, 4 * disk + 1]),
                        bool(self.ok[k]), float(self.chi2[k]), dof, area_force, over)

    def contacts(self, clusters: list[Cluster], dof: FloatArray, area_force: bool = False) -> list[Contact]:
        """:meth:`contact` of every problem's (first) disk, problem k being ``clusters[k]``
        with ``int(dof[k])`` degrees of freedom. Each array is read into Python lists once,
        not sliced and converted a problem at a time (six numpy calls a contact, ten
        contacts a frame, were a tenth of the fit's set-up)."""
        theta, sig, flat = self.theta[:, :4].tolist(), self.sig[:, :4].tolist(), self.flat[:, :2].tolist()
        cv01, ok, chi2, dofs = self.cov[:, 0, 1].tolist(), self.ok.tolist(), self.chi2.tolist(), dof.tolist()
        return [_contact(cl, theta[k], sig[k], flat[k], cv01[k], ok[k], chi2[k], int(dofs[k]), area_force, {})
                for k, cl in enumerate(clusters)]


def _contact(cl: Cluster, th: list[float], sig: list[float], flat: list[bool], cv01: float, ok: bool, chi2: float,
             dof: int, area_force: bool, over: dict[str, object]) -> Contact:
    """:meth:`Fits.contact` of one disk, its row's values given as Python floats: ``th``,
    ``sig`` (x, y, ln D, ln F), ``flat`` (x, y), ``cv01`` its covariance of x and y."""
    base = dict(cl.base)
    base.update(over)
    diam = math.exp(th[2])
    if area_force:
        force = cl.sigma0 * math.pi * diam * diam / 4.0
        s_lnf = 2.0 * sig[2]
    else:
        force = math.exp(th[3])
        s_lnf = sig[3]
    cxy = cv01 if not (flat[0] or flat[1]) and math.isfinite(cv01) else 0.0
    sx, sy = sig[0], sig[1]
    cx, cy = base["centroid_x"], base["centroid_y"]
    # A coordinate is observable where the readings pin it: not flat, and with a
    # finite σ (a covariance that failed to solve leaves σ infinite without a flat
    # bottom found: the readings do not pin that coordinate either).
    seen = (not bool(flat[0]) and math.isfinite(sx), not bool(flat[1]) and math.isfinite(sy))
    if not ok:
        # The position is the centroid, which says only that the contact is on the
        # cluster: σ of a uniform spread out to the farther edge of the cluster on
        # each side (a failed fit's covariance says nothing about the centroid).
        assert cl.bounds is not None  # every cluster built here carries its layout's bounds
        b = cl.bounds[cl.members]
        sx, sy = (max(c - float(b[:, a].min()), float(b[:, a + 2].max()) - c) / math.sqrt(3.0)
                  for a, c in ((0, cx), (1, cy)))
        cxy, seen = 0.0, (False, False)
    return Contact(
        x=float(th[0]) if ok else cx, y=float(th[1]) if ok else cy,
        force=force if ok else base["force_sum"],
        diameter=diam if ok else 2.0 * math.sqrt(max(base["area"], 0.0) / math.pi),
        model_x=float(th[0]) if ok else math.nan, model_y=float(th[1]) if ok else math.nan,
        sigma_x=sx, sigma_y=sy, sigma_xy=major_axis(sx * sx, sy * sy, cxy), cov=((sx * sx, cxy), (cxy, sy * sy)),
        sigma_force=float(force * s_lnf) if ok else math.nan,
        sigma_diameter=float(diam * sig[2]) if ok else math.nan,
        valid=True, fit_ok=ok, observable=seen,
        chi2=chi2, dof=dof, **base,
    )


def _finite(x: FloatArray) -> FloatArray:
    """``np.nan_to_num(x)`` of a float array, without its cost where every value is finite
    (nearly always; its wrapper cost more than the kernel call it feeds)."""
    return x if np.isfinite(x).all() else np.nan_to_num(x)


def _offsets(sizes: IntArray) -> IntArray:
    """(K + 1,) int64 starts of K consecutive runs of ``sizes``: 0, then their running sums."""
    off = np.zeros(sizes.size + 1, dtype=np.int64)
    np.cumsum(sizes, out=off[1:])
    return off


def major_axis(vx: float, vy: float, cxy: float) -> float:
    """Larger semi-axis (one sigma) of a 2×2 covariance, in closed form."""
    half = 0.5 * (vx + vy)
    return math.sqrt(max(half + math.hypot(0.5 * (vx - vy), cxy), 0.0))


class FitRunner:
    """Builds clusters and kernel batches for one skin, and runs the kernel."""

    def __init__(self, layout: SkinLayout, params: ElementParams, noise: FloatArray, area_method: bool):
        self.layout = layout
        self.params = params
        self.noise = noise
        self.area_method = area_method
        self.par = element_vector(params)
        # Each element's corner neighbours, as CSR (rows of element i: _nb[_nb_ptr[i]:_nb_ptr[i + 1]]):
        # built once per layout, read by every frame's ring search.
        e = layout.corner_edges
        both = np.concatenate([e, e[:, ::-1]])
        both = both[np.argsort(both[:, 0], kind="stable")]
        self._nb = np.ascontiguousarray(both[:, 1])
        self._nb_ptr = np.concatenate([[0], np.cumsum(np.bincount(both[:, 0], minlength=layout.n))]).astype(np.int64)

    def g(self, sigma: float) -> tuple[float, float]:
        """Sensitivities (g1, g2) at one pressure (the compiled scalar: no array overhead)."""
        p = self.par
        return sensitivity_slope(sigma, *p[:4])[0], sensitivity_slope(sigma, *p[4:])[0]

    def frame_clusters(
        self, labels: IntArray, c1: FloatArray, c2: FloatArray,
        finite: NDArray[np.bool_], valid: NDArray[np.bool_], force: FloatArray, area: FloatArray,
        firm: FloatArray | None = None, ring_noise: FloatArray | None = None,
        replaced: NDArray[np.bool_] | None = None,
    ) -> list[Cluster]:
        """Every cluster of one frame (``labels``: 0..K-1 per element, -1 untouched), in
        label order: observed elements, shared pressure, areas, centroid and base fields.

        A cluster's observed elements are its members (ascending rows), then its ring: the
        members' corner neighbours that belong to no cluster and have a reading (ascending).
        ``firm``: per element, a high-branch pressure its inverse found too noisy to
        report (NaN elsewhere); with no valid element, the ΔC1-weighted mean of these
        is the cluster's pressure, so a hard press is fitted, not taken for a light one.
        ``ring_noise``: (2,) the frame's noise (:func:`frame_noise`) against which a
        quiet ring element's reading counts as the disk's (:data:`RING_SIGNAL`); None:
        the ring only bounds the disk from above. ``replaced``: (N,) elements whose
        contacts the caller takes from elsewhere: a cluster wholly on them is left out of
        the list (it still shapes the others' rings, as every cluster does).
        """
        # (One compiled pass over the frame's clusters: per cluster, numpy's calls cost far
        # more than the arithmetic; see cluster_kernel.)
        lay = self.layout
        if not (labels >= 0).any():
            return []
        has_firm = firm is not None
        rs = np.full(2, np.inf) if ring_noise is None else RING_SIGNAL * np.asarray(ring_noise, dtype=np.float64)
        # contiguous, whatever the caller's readings are (a grid's columns of its (n, 2) ΔC, a
        # robot link's gathered rows): one compiled signature, the one the worker's warm-up
        # loads (a second cost 25 ms of compiling, mid-run, at a robot skin's first press)
        c1, c2 = np.ascontiguousarray(c1), np.ascontiguousarray(c2)
        firm = None if firm is None else np.ascontiguousarray(firm)
        ooff, nm, obs, quiet, a, f, y, sigma0, any_valid, is_firm, cx, cy, s_tot, f_sum = gather_clusters(
            labels, self._nb_ptr, self._nb, finite, c1, c2, valid, force, area, firm if has_firm else c1, has_firm,
            rs, lay.centres, self.par, float(1.0 / self.noise[0] ** 2), float(1.0 / self.noise[1] ** 2))
        out = []
        ok = any_valid | is_firm  # a valid member's pressure, or a firm one
        if replaced is None:
            posed: Iterable[int] = range(nm.size)
        else:  # (the clusters with a member not replaced: those a contact of theirs would be kept from)
            some = np.zeros(nm.size, dtype=bool)
            some[labels[(labels >= 0) & ~replaced]] = True
            posed = np.flatnonzero(some).tolist()
        # (every per-cluster value read into Python once, not a numpy scalar at a time)
        starts, ends, sizes = ooff[:-1].tolist(), ooff[1:].tolist(), nm.tolist()
        ids = lay.ids[obs].tolist()
        oks, firms, s_tots, f_sums, sigmas = ok.tolist(), is_firm.tolist(), s_tot.tolist(), f_sum.tolist(), sigma0.tolist()
        cxs, cys = cx.tolist(), cy.tolist()
        for k in posed:
            s, e, m = starts[k], ends[k], sizes[k]
            fit = oks[k]
            st = s_tots[k]
            sg = sigmas[k] if fit else math.nan  # (math.nan itself: equal to itself in a dict)
            base = dict(
                centroid_x=cxs[k], centroid_y=cys[k], elements=tuple(ids[s : s + m]),
                pressure=sg, force_sum=f_sums[k] if fit else math.nan,
                area=st if fit else math.nan,
            )
            out.append(Cluster(obs[s : s + m], obs[s:e], sg, a[s:e], y[:, s:e], (cxs[k], cys[k]),
                               fit and st > 0, base, firms[k], lay.bounds, quiet[s:e]))
        return out

    def batch(self, clusters: list[Cluster], areas: bool | None = None) -> Batch:
        """Kernel arrays for the clusters; ``areas`` (default: the estimator's method)
        fits the per-element areas instead of ΔC."""
        lay = self.layout
        area_fit = self.area_method if areas is None else areas
        sizes = np.array([cl.obs.size for cl in clusters])
        off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        allobs = np.concatenate([cl.obs for cl in clusters])
        quiet = np.concatenate([np.arange(cl.obs.size) >= cl.members.size if cl.quiet is None else cl.quiet
                                for cl in clusters])
        if area_fit:
            y = np.zeros((2, allobs.size))
            y[0] = _finite(np.concatenate([cl.area for cl in clusters]))
            w = np.empty((len(clusters), 2))
            for k, cl in enumerate(clusters):
                g1, g2 = self.g(cl.sigma0)
                # Area noise of one element: the ΔC noise through both sensitivities.
                w[k] = math.sqrt((g1 / self.noise[0]) ** 2 + (g2 / self.noise[1]) ** 2)
        else:
            y = np.concatenate([cl.y for cl in clusters], axis=1)
            w = np.empty((len(clusters), 2))
            w[:] = 1.0 / self.noise
        return Batch(off, np.ascontiguousarray(lay.bounds[allobs]), np.ascontiguousarray(y), quiet, w,
                     1 if area_fit else 2)

    def run(self, b: Batch, theta0: FloatArray, free: NDArray[np.bool_], nd: int, assess: bool,
            sm: tuple = UNIFORM) -> Fits:
        """Fit every problem of the batch (``nd`` disks each) in one kernel call."""
        n, p = b.n, 4 * nd
        r = Fits(np.empty((n, p)), np.empty((n, p)), np.zeros((n, p), dtype=bool), np.empty((n, p, p)),
                 np.empty(n), np.empty(n), np.zeros(n, dtype=bool))
        fit_batch(b.off, b.bounds, b.y, b.quiet, np.ascontiguousarray(theta0, dtype=np.float64),
                  np.ascontiguousarray(free), nd, b.w, b.nch, self.par, float(self.layout.side), assess,
                  r.theta, r.sig, r.flat, r.cov, r.chi2, r.cost, r.ok, sm)
        return r

    def starts(self, clusters: list[Cluster], areas: list[FloatArray] | None = None,
               batch: Batch | None = None) -> FloatArray:
        """(K, 3) share-based (x, y, r) of each cluster (areas over its members and the
        ring elements that read the disk, :attr:`Cluster.seen`, in that order). ``batch``:
        the clusters' own (:meth:`batch`), whose flat arrays serve here too."""
        if areas is None and batch is not None:
            # (the batch's observed elements, the quiet ones masked out: each cluster's
            # ``seen`` in its order, its elements' rectangles already gathered)
            seen = ~batch.quiet
            nmem = np.add.reduceat(seen, batch.off[:-1], dtype=np.int64)
            out = np.empty((len(clusters), 3))
            share_start(_offsets(nmem), nmem, batch.bounds[seen],
                        _finite(np.concatenate([cl.area for cl in clusters])[seen]), out)
            return out
        quiet = [cl.quiet for cl in clusters if cl.quiet is not None] if areas is None else []
        if areas is None and len(quiet) == len(clusters) and all(q.size for q in quiet):
            # (the clusters' observed elements gathered once and the quiet ones masked out:
            # the same elements in the same order as each cluster's ``seen``, without a
            # fancy index and a ``seen`` per cluster: a tenth of the fit's set-up)
            seen = ~np.concatenate(quiet)
            sizes = np.fromiter((q.size for q in quiet), dtype=np.int64, count=len(quiet))
            nmem = np.add.reduceat(seen, _offsets(sizes)[:-1], dtype=np.int64)
            rows = np.concatenate([cl.obs for cl in clusters])[seen]
            ar_flat = np.concatenate([cl.area for cl in clusters])[seen]
        else:
            mem = [cl.obs[cl.seen] for cl in clusters]
            ar = [cl.area[cl.seen] for cl in clusters] if areas is None else areas
            nmem = np.array([m.size for m in mem], dtype=np.int64)
            rows = np.concatenate(mem)
            ar_flat = np.concatenate(ar)
        out = np.empty((len(clusters), 3))
        share_start(_offsets(nmem), nmem, np.ascontiguousarray(self.layout.bounds[rows]), _finite(ar_flat), out)
        return out
