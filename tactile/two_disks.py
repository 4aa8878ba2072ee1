"""Two touching contacts in one cluster: when to report two disks, and how to start them.

Two fingers on neighbouring elements press one connected group of elements, so
clustering makes one cluster of them and one disk fits it badly. Two disks are
fitted when the one-disk χ² leaves room for a significant gain, from seeds that
credit each element's area to the nearer of two seed elements (the strongest, and
the strongest not next to it or the second strongest; elements as far from both go
either way or half to each), or from two tracked disks lying on the cluster. The best
fit is reported when

* the second disk's four parameters buy (χ²₁ − χ²₂)/max(1, χ²₂/dof₂) > 23.51, the
  1 − 10⁻⁴ quantile of χ² with 4 degrees of freedom (the reduced χ² scale guards
  against model error: a single disk that fits poorly for another reason does not
  become two), with χ² counted against the noise *and* a model tolerance of
  ``model_error`` (relative) of the cluster's largest reading on every reading. No
  skin is its model: a few per cent of gain error per element, or the sheets'
  tension spilling signal onto the ring, leave a misfit far above the noise that a
  small second disk wholly inside one element soaks up (it sets that element's two
  readings freely). Without the tolerance such a "second contact" came back on a
  third to a half of single presses on perturbed readings (bench/bench_contacts.py);
  with it a second disk has to explain more than a model error could, and
* the two disks do not overlap (the model adds their areas; overlap is no answer).
"""

from __future__ import annotations

import math

import numpy as np
from cellbridge.tactile.arrays import FloatArray
from cellbridge.tactile.clusters import force_centroid
from cellbridge.tactile.contact_result import Contact
from cellbridge.tactile.fit_problems import Cluster, FitRunner, Fits
from cellbridge.tactile.overlap import disk_rect_overlap
from numpy.typing import NDArray

__all__ = ["MODEL_ERROR", "SPLIT_DCHI2", "split_clusters"]


#: Δχ² (in units of the noise, or of the two-disk fit's reduced χ² when that is
#: worse) that a second disk must gain to be reported.
SPLIT_DCHI2 = 23.51

#: Default relative model tolerance of the split test: per reading, this fraction of
#: the cluster's largest reading counts as model error beside the noise.
MODEL_ERROR = 0.01


def split_clusters(
    runner: FitRunner, clusters: list[Cluster], fits: Fits, dof: FloatArray,
    pair_hints: dict[int, FloatArray], adjacent: NDArray[np.bool_] | None, model_error: float = MODEL_ERROR,
) -> dict[int, list[Contact]]:
    """The clusters (by index) that are two contacts, with both contacts."""
    # χ² in units of the noise → in units of noise and model tolerance together (scale ≤ 1:
    # asked only of the clusters whose plain χ² could pass, most clusters of a frame fit).
    scale = np.ones(len(clusters))
    cand = []
    for k, cl in enumerate(clusters):
        # Two disks leave about dof − 4 of noise: only a one-disk χ² beyond that by
        # the threshold can pass the test.
        if cl.members.size < 2 or not dof[k] - 4 >= 2:
            continue
        if not (fits.chi2[k] > dof[k] - 4 + SPLIT_DCHI2 or k in pair_hints):
            continue
        peak = np.nanmax(np.abs(cl.y[:, : cl.members.size]), axis=1)
        tol = model_error * np.where(np.isfinite(peak), peak, 0.0)
        scale[k] = 1.0 / (1.0 + float(np.max(tol / runner.noise)) ** 2)
        if fits.chi2[k] * scale[k] > dof[k] - 4 + SPLIT_DCHI2 or k in pair_hints:
            cand.append(k)
    if not cand:
        return {}
    seeds, owners = [], []
    for k in cand:
        for s in _pair_seeds(runner, clusters[k], pair_hints.get(k), adjacent):
            seeds.append(s)
            owners.append(k)
    if not seeds:
        return {}
    two = runner.run(runner.batch([clusters[k] for k in owners]), np.array(seeds),
                     np.ones((len(owners), 8), dtype=bool), 2, False)
    best: dict[int, int] = {}
    for j, k in enumerate(owners):
        if np.isfinite(two.cost[j]) and (k not in best or two.cost[j] < two.cost[best[k]]):
            best[k] = j
    gained = []
    for k, j in best.items():
        sc = scale[k]
        if (fits.chi2[k] - two.chi2[j]) * sc / max(1.0, two.chi2[j] * sc / (dof[k] - 4)) > SPLIT_DCHI2:
            gained.append((k, two.theta[j]))
    if not gained:
        return {}
    final = runner.run(runner.batch([clusters[k] for k, _ in gained]),
                       np.array([th for _, th in gained]), np.ones((len(gained), 8), dtype=bool), 2, True)
    out = {}
    for j, (k, _) in enumerate(gained):
        # The overlap test runs after unresolved axes went to their plateaus' middles.
        th = final.theta[j]
        r1, r2 = 0.5 * math.exp(th[2]), 0.5 * math.exp(th[6])
        if math.hypot(th[0] - th[4], th[1] - th[5]) >= 0.8 * (r1 + r2) and final.ok[j]:
            out[k] = _split_contacts(runner, clusters[k], final, j, int(dof[k] - 4))
    return out


def _pair_seeds(
    runner: FitRunner, cl: Cluster, hinted: FloatArray | None, adjacent: NDArray[np.bool_] | None
) -> list[FloatArray]:
    """Starting points for two disks: each disk from the area it is credited with."""
    seeds = []
    if hinted is not None:
        seeds.append(np.concatenate([[h[0], h[1], math.log(h[2]), math.log(h[3])] for h in hinted[:2]]))
    mem = cl.members
    a = np.maximum(np.nan_to_num(cl.area[: mem.size]), 0.0)
    order = np.argsort(-cl.y[0, : mem.size])
    i1 = int(order[0])
    # The second seed element: the strongest one not edge-adjacent to the first
    # (two fingers rarely peak on neighbours), and the second strongest.
    far = next((int(i) for i in order[1:] if adjacent is None or not adjacent[mem[i1], mem[i]]), int(order[1]))
    cen = runner.layout.centres[mem]
    d1 = np.hypot(*(cen - cen[i1]).T)
    s0 = cl.sigma0
    parts = []
    for i2 in {far, int(order[1])}:
        d2 = np.hypot(*(cen - cen[i2]).T)
        # Elements as far from both go to one disk, the other, or half to each.
        for tie in (1.0, 0.0, 0.5):
            parts.append(np.where(d1 < d2, 1.0, np.where(d1 > d2, 0.0, tie)))
    pairs = [(cl, cl)] * len(parts)
    st = runner.starts([c for pair in pairs for c in pair], [x for p in parts for x in (a * p, a * (1.0 - p))])
    for j, p in enumerate(parts):
        s1, s2 = st[2 * j], st[2 * j + 1]
        # A side credited no area (an element touched but reading nothing, e.g. held
        # by the calibrator's hysteresis) gives -inf here: that seed is dropped below.
        with np.errstate(divide="ignore", invalid="ignore"):
            seeds.append(np.array([s1[0], s1[1], np.log(2 * s1[2]), np.log(s0 * (a * p).sum()),
                                   s2[0], s2[1], np.log(2 * s2[2]), np.log(s0 * (a * (1.0 - p)).sum())]))
    return [s for s in seeds if np.all(np.isfinite(s))]


def _split_contacts(runner: FitRunner, cl: Cluster, f: Fits, j: int, dof: int) -> list[Contact]:
    """Both disks as contacts: each names the elements where its ΔC1 clears 3 noise
    sigmas, and gets its own centroid and its share of the cluster's force sum."""
    lay = runner.layout
    th = f.theta[j]
    b = lay.bounds[cl.members]
    tot_f = math.exp(th[3]) + math.exp(th[7])
    out = []
    for d in range(2):
        r = 0.5 * math.exp(th[4 * d + 2])
        a = disk_rect_overlap(th[4 * d], th[4 * d + 1], r, b[:, 0], b[:, 1], b[:, 2], b[:, 3])
        sig_d = math.exp(th[4 * d + 3]) / (math.pi * r * r)
        mine = a * runner.g(sig_d)[0] > 3.0 * runner.noise[0]
        if not mine.any():
            mine = a >= a.max()
        w = np.zeros(lay.n)
        w[cl.members] = a * sig_d
        cx, cy = force_centroid(lay, w, cl.members[mine])
        out.append(f.contact(
            cl, j, dof, disk=d, centroid_x=cx, centroid_y=cy,
            elements=tuple(int(i) for i in lay.ids[cl.members[mine]]), pressure=sig_d,
            force_sum=cl.base["force_sum"] * math.exp(th[4 * d + 3]) / tot_f, area=float(a.sum()),
        ))
    return out
