"""Where a light touch is, when the inverse gives it no pressure.

Too light a touch, or the inverse's ambiguous low-pressure region, leaves a cluster
with no valid element: no force and no diameter. At low pressure ΔC ≈ k·F whatever
the area, so the diameter is not known; but for any given diameter the elements'
shares still fix the centre along a straddled axis. So the disk is fitted at fixed
diameters over the plausible range (force free), and again with the diameter free
from each local minimum of that grid (the ambiguous region has two discrete branches,
which a coarse grid can step over). The fits within +4 of the best cost (95 % for
one parameter; and two grid points either side, so a diameter between grid points
is bracketed with room to spare) give the span of centres, ± their own σ: the contact is reported at its middle with
σ = √(span²/12 + σ_fit²).

Those two branches are two discrete answers, not two points of one smooth profile: a
small disk straddling a seam and a disk as large as an element further in can read
alike to within the noise, and then which of them costs less is the noise's choice.
+4 (a one-parameter profile's 95 %) would drop the other branch when it is only
e^-2 ≈ 14 % as likely, and report the chosen one with its own, tight σ: a confident
untruth whenever the noise chose wrong. So every local minimum of the grid is a
branch, and so is a free-diameter fit started at each pressure the cluster's summed
ΔC1/ΔC2 allows (the ratio fixes a branch's pressure so closely that its valley in D
can lie between two grid points, unmarked by any local minimum); a branch is kept
while its likelihood is above the 3σ tail of the best one's (cost within
:data:`BRANCH`), and within each kept branch the fits within +4 of its own minimum
count, as above. An axis along which a kept disk lies inside its element is
unresolved, whatever another branch says (a large disk over the skin's edge is pinned
along it by the on-skin prior, not by the readings).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from cellbridge.tactile.contact_result import Contact
from cellbridge.tactile.element import ElementParams, sensitivity
from cellbridge.tactile.fit_problems import Cluster, FitRunner
from cellbridge.tactile.inversion import branch_info, ratio

__all__ = ["locate_light", "unlocated"]


N_DIAMETERS = 20  #: grid of fixed diameters, log-spaced over 0.05–1.5 element sides
#: Cost rise that still counts as consistent: the 95 % range of a one-parameter
#: profile (the diameter), so the span holds the truth at least as often as the 2σ
#: the contact reports.
CONSISTENT = 4.0
#: Cost rise at which another branch (another local minimum of the diameter grid) stops
#: counting: its likelihood ratio to the best's e^(-rise/2) is then below the two-sided
#: 3σ tail, 0.27 % (2·ln(0.9973/0.0027) ≈ 11.8); reported σ, whose 3σ must hold the
#: truth, may not leave out an answer more likely than that.
BRANCH = 2.0 * math.log(0.9973 / 0.0027)


def unlocated(cl: Cluster, side: float) -> Contact:
    """Nothing finer than the elements: the ΔC1-weighted centroid, σ = side/√12 per element."""
    sx = sy = side / math.sqrt(12.0) * cl.members.size
    x, y = cl.centroid
    return Contact(
        x=float(x), y=float(y), force=math.nan, diameter=math.nan, model_x=math.nan, model_y=math.nan,
        sigma_x=sx, sigma_y=sy, sigma_xy=sx, cov=((sx * sx, 0.0), (0.0, sy * sy)), sigma_force=math.nan,
        sigma_diameter=math.nan, valid=False, fit_ok=False, observable=(False, False), chi2=math.nan,
        dof=0, **cl.base,
    )


def locate_light(runner: FitRunner, clusters: list[Cluster]) -> list[Contact]:
    """A contact per cluster: located by the span of consistent fits, or :func:`unlocated`."""
    lay = runner.layout
    diam = np.geomspace(0.05 * lay.side, 1.5 * lay.side, N_DIAMETERS)
    p = runner.params
    k_low = p.eps1 * (p.d1 - p.d10) / (p.E1 * p.d1 * p.d1)  # g1/σ as σ → 0
    probs: list[Cluster] = []
    areas, lnf = [], []
    for cl in clusters:
        tot = float(np.maximum(cl.y[0, cl.seen], 0.0).sum())
        share = _shares(cl)
        f0 = max(tot / k_low, 1e-6) if tot > 0 else 1e-3
        for d in diam:
            areas.append(share * math.pi * d * d / 4)
            lnf.append(math.log(f0))
            probs.append(cl)
    st = runner.starts(probs, areas)
    t0 = np.column_stack([st[:, :2], np.log(np.tile(diam, len(clusters))), lnf])
    free = np.tile(np.array([True, True, False, True]), (len(probs), 1))
    # ΔC fits whatever the estimator's method: the area method needs a pressure.
    fits = runner.run(runner.batch(probs, areas=False), t0, free, 1, False)
    cost = fits.cost.reshape(len(clusters), N_DIAMETERS)
    padded = np.pad(cost, ((0, 0), (1, 1)), constant_values=np.inf)
    loc = np.isfinite(cost) & (cost <= padded[:, :-2]) & (cost <= padded[:, 2:])
    qk, qd = np.nonzero(loc)
    # The branches' own diameters, from the cluster's ratio: each branch's valley in D is
    # narrow (the ratio fixes the pressure to a fraction of a per cent), and the grid
    # steps over one that lies between two of its points.
    bk, bd, bf = [], [], []
    for i, cl in enumerate(clusters):
        for d, f in _ratio_branches(runner.params, cl):
            bk.append(i)
            bd.append(d)
            bf.append(f)
    t_ref = fits.theta[qk * N_DIAMETERS + qd]
    if bk:
        sb = runner.starts([clusters[k] for k in bk],
                           [_shares(clusters[k]) * math.pi * d * d / 4 for k, d in zip(bk, bd)])
        t_ref = np.vstack([t_ref, np.column_stack([sb[:, :2], np.log(bd), np.log(bf)])])
    qk = np.concatenate([qk, np.asarray(bk, dtype=np.int64)])
    qd = np.concatenate([qd, np.full(len(bk), -1, dtype=np.int64)])  # -1: no grid valley
    ref = runner.run(runner.batch([clusters[k] for k in qk], areas=False),
                     t_ref, np.ones((qk.size, 4), dtype=bool), 1, False)
    out = []
    for i, cl in enumerate(clusters):
        sl = slice(i * N_DIAMETERS, (i + 1) * N_DIAMETERS)
        mine = qk == i
        c_ref = ref.cost[mine]
        floor = min(float(np.nanmin(cost[i])), float(np.nanmin(c_ref)) if c_ref.size else np.inf)
        best, kref = _branches(cost[i], qd[mine], c_ref, floor)
        keep = best.copy()
        for step in (1, 2):
            keep[step:] |= best[:-step]
            keep[:-step] |= best[step:]
        keep &= np.isfinite(cost[i])
        b = lay.bounds[cl.members]
        pos, sig, obs = [0.0, 0.0], [0.0, 0.0], [False, False]
        for ax in (0, 1):
            # A free-diameter refinement whose covariance is singular (at low pressure
            # D and F nearly trade off) only sets the cost floor; the fixed-diameter
            # fits around it carry its position. One that resolves the other axis but
            # not this one is a consistent disk this axis's readings do not place (it
            # lies inside its element along it): then no other branch's fit, pinned
            # perhaps by the skin's edge, may say where along it the touch is.
            rs = ref.sig[mine, ax][kref]
            flat = bool(np.any(~np.isfinite(rs) & np.isfinite(ref.sig[mine, 1 - ax][kref])))
            v = np.concatenate([fits.theta[sl, ax][keep], ref.theta[mine, ax][kref][np.isfinite(rs)]])
            s = np.concatenate([fits.sig[sl, ax][keep], rs[np.isfinite(rs)]])
            if v.size and not flat and np.all(np.isfinite(s)) and s.max() < 0.25 * lay.side:
                lo, hi = float(np.min(v - s)), float(np.max(v + s))
                pos[ax] = 0.5 * (lo + hi)
                sig[ax] = math.sqrt((hi - lo) ** 2 / 12.0 + float(np.mean(s * s)))
                obs[ax] = True
            else:
                # Unseen: uniform over the cluster's extent less the smallest disk.
                lo_e, hi_e = b[:, ax].min(), b[:, ax + 2].max()
                # (With no grid fit kept, the whole extent: a refinement's diameter is
                # too sharp a bound, the disk may hang over the cluster's edge.)
                d_kept = np.concatenate([diam[keep], np.exp(ref.theta[mine, 2][kref])])
                dmin = float(np.nanmin(d_kept)) if keep.any() else 0.0
                pos[ax] = 0.5 * (lo_e + hi_e)
                sig[ax] = max(hi_e - lo_e - dmin, 0.0) / math.sqrt(12.0)
        # A best fit far worse than the noise found no disk that explains the
        # readings (the search missed, or it is no disk): no interval then.
        dof = 2 * cl.obs.size - 3
        plausible = floor <= dof + 5.0 * math.sqrt(2.0 * max(dof, 1)) + 10.0
        if not ((keep.any() or kref.any()) and any(obs) and plausible):
            out.append(unlocated(cl, lay.side))
            continue
        (x, y), (sx, sy) = pos, sig
        out.append(Contact(
            x=float(x), y=float(y), force=math.nan, diameter=math.nan, model_x=float(x), model_y=float(y),
            sigma_x=float(sx), sigma_y=float(sy), sigma_xy=float(max(sx, sy)),
            cov=((float(sx * sx), 0.0), (0.0, float(sy * sy))), sigma_force=math.nan,
            sigma_diameter=math.nan, valid=False, fit_ok=True, observable=(bool(obs[0]), bool(obs[1])),
            chi2=float(fits.chi2[sl][int(np.nanargmin(cost[i]))]), dof=int(dof), **cl.base,
        ))
    return out


def _branches(cost: np.ndarray, minima: np.ndarray, c_ref: np.ndarray, floor: float) -> tuple[np.ndarray, np.ndarray]:
    """(grid fits, refined fits) that count, of one cluster: per branch whose minimum is
    within :data:`BRANCH` of ``floor``, the fits within :data:`CONSISTENT` of that minimum.

    ``cost``: the grid's costs; ``minima``: its local minima (grid indices; -1: a start
    from a branch's diameter, :func:`_ratio_branches`), whose free-diameter refinements
    cost ``c_ref``. A branch is the grid's valley around a local
    minimum (out to where the cost stops rising), its minimum the lower of the grid
    point's and the refinement's cost.
    """
    n = cost.size
    grid = np.zeros(n, dtype=bool)
    ref = np.zeros(c_ref.size, dtype=bool)
    fin = np.isfinite(cost)
    for m, (j, cr) in enumerate(zip(minima.tolist(), c_ref.tolist())):
        if j < 0:  # a refinement from a branch's diameter: no valley of the grid
            ref[m] = math.isfinite(cr) and cr <= floor + BRANCH
            continue
        low = min(float(cost[j]), cr) if math.isfinite(cr) else float(cost[j])
        if not low <= floor + BRANCH:
            continue
        lo = j
        while lo > 0 and fin[lo - 1] and cost[lo - 1] >= cost[lo]:
            lo -= 1
        hi = j
        while hi < n - 1 and fin[hi + 1] and cost[hi + 1] >= cost[hi]:
            hi += 1
        grid[lo : hi + 1] |= fin[lo : hi + 1] & (cost[lo : hi + 1] <= low + CONSISTENT)
        ref[m] = math.isfinite(cr) and cr <= low + CONSISTENT
    # Grid fits in no valley of a local minimum (a plateau's edge) as before: against the floor.
    grid |= fin & (cost <= floor + CONSISTENT)
    return grid, ref


def _shares(cl: Cluster) -> np.ndarray:
    """Each share of the cluster's ΔC1 over the elements that read the disk
    (:attr:`Cluster.seen`; equal shares when they read none)."""
    s1 = np.maximum(cl.y[0, cl.seen], 0.0)
    tot = s1.sum()
    return s1 / tot if tot > 0 else np.full(s1.size, 1.0 / s1.size)


@functools.lru_cache(maxsize=8)
def _ratio_table(params: ElementParams) -> tuple[np.ndarray, np.ndarray]:
    """(ln σ, ρ(σ)) from far below the ratio's peak to above where it is unique."""
    info = branch_info(params)
    ln_s = np.linspace(math.log(info.sigma_peak) - 12.0, math.log(info.sigma_unique) + 1.0, 600)
    return ln_s, ratio(np.exp(ln_s), params)


def _ratio_branches(params: ElementParams, cl: Cluster) -> list[tuple[float, float]]:
    """(D, F) of a disk wholly on the elements that read it at each pressure their summed ΔC1/ΔC2 allows.

    The ratio of a light touch has two pressures (one each side of the ratio's peak;
    the peak's when noise puts the ratio above it), and each, with the summed ΔC1,
    gives the area and so the diameter: starts for the fit on each branch.
    """
    c1 = float(np.maximum(cl.y[0, cl.seen], 0.0).sum())
    c2 = float(np.maximum(cl.y[1, cl.seen], 0.0).sum())
    if not (c1 > 0 and c2 > 0):
        return []
    ln_s, rho = _ratio_table(params)
    above = rho > c1 / c2
    cross = np.flatnonzero(above[1:] != above[:-1])
    if cross.size == 0:
        if not c1 / c2 > rho.max():
            return []  # below every light pressure's ratio: the grid alone
        sig = [branch_info(params).sigma_peak]
    else:
        sig = []
        for j in cross.tolist():
            r0, r1 = rho[j] - c1 / c2, rho[j + 1] - c1 / c2
            t = r0 / (r0 - r1) if r0 != r1 else 0.5
            sig.append(math.exp(ln_s[j] + t * (ln_s[j + 1] - ln_s[j])))
    out = []
    for sg in sig:
        g1 = float(sensitivity(sg, params)[0])
        if g1 > 0:
            area = c1 / g1
            out.append((math.sqrt(4.0 * area / math.pi), sg * area))
    return out
