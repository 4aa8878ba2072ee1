"""One frame's clusters gathered in one compiled pass: rings, readings, pressures, centroids.

:meth:`cellbridge.tactile.fit_problems.FitRunner.frame_clusters` poses every cluster of a
frame as a fit problem. Per cluster that is a few dozen steps on a handful of elements
(its ring of quiet neighbours, which ring readings count as signal, the shared pressure,
the areas of the elements without one, the centroid and the sums); done with numpy per
cluster, the calls cost far more than the arithmetic (about 70 µs a cluster, most of a
10-contact frame's set-up). This kernel does them all in one call, with the same rules
and the same arithmetic; sums run in element order (numpy's pairwise sums of eight or
more terms may differ in the last bits).
"""

from __future__ import annotations

import math

import numpy as np
from cellbridge.tactile._jit import compiled
from cellbridge.tactile.disk_model import sensitivity_slope

__all__ = ["gather_clusters", "components"]


def _gather_clusters(
    labels: np.ndarray, nb_ptr: np.ndarray, nb: np.ndarray, finite: np.ndarray, c1: np.ndarray, c2: np.ndarray,
    valid: np.ndarray, force: np.ndarray, area: np.ndarray, firm: np.ndarray, has_firm: bool,
    ring_signal: np.ndarray, centres: np.ndarray, par: np.ndarray, w1: float, w2: float,
) -> tuple:
    """Every cluster of one frame (``labels`` 0..K-1 per element, -1 untouched; K ≥ 1).

    A cluster's observed elements are its members (ascending rows), then its ring: the
    members' corner neighbours (CSR ``nb_ptr``, ``nb``) in no cluster and with a reading
    (``finite``), ascending. A ring element reads signal when a channel exceeds
    ``ring_signal`` (2,) and it borders no other cluster; else it is quiet. The pressure
    is the valid members' Σforce/Σarea; with none valid, the ΔC1-weighted geometric mean
    of the members' ``firm`` pressures (finite ones; ``has_firm``), which makes the
    cluster firm. Elements without a valid inverse get the least-squares area at that
    pressure, ``A = (w1·g1·ΔC1 + w2·g2·ΔC2)/(w1·g1² + w2·g2²)``, and force σ·A.

    Returns ``(ooff, nm, obs, quiet, area, force, y, sigma0, any_valid, is_firm, cx, cy,
    area_sum, force_sum)``: cluster k's observed elements are ``obs[ooff[k]:ooff[k+1]]``,
    its first ``nm[k]`` the members; ``area``, ``force``, ``quiet`` and ``y`` (2, ·) (ΔC1,
    ΔC2) per observed element; per cluster the pressure (NaN: none), whether a member's
    inverse was valid, whether the pressure is firm, the centroid (weights: the members'
    finite positive forces, else ΔC1; none positive, the centres' mean), Σ max(area, 0)
    and Σ force over the members (NaN taken as 0).
    """
    n = labels.size
    k_n = 0
    for i in range(n):
        if labels[i] + 1 > k_n:
            k_n = labels[i] + 1
    nm = np.zeros(k_n, dtype=np.int64)
    for i in range(n):
        if labels[i] >= 0:
            nm[labels[i]] += 1
    moff = np.zeros(k_n + 1, dtype=np.int64)
    for k in range(k_n):
        moff[k + 1] = moff[k] + nm[k]
    members = np.empty(moff[k_n], dtype=np.int64)
    fill = moff[:k_n].copy()
    for i in range(n):
        if labels[i] >= 0:
            members[fill[labels[i]]] = i
            fill[labels[i]] += 1
    # rings, each ascending, marked per cluster in a scratch mask
    mark = np.zeros(n, dtype=np.bool_)
    cap = 0
    for j in range(members.size):
        cap += nb_ptr[members[j] + 1] - nb_ptr[members[j]]
    obs = np.empty(members.size + cap, dtype=np.int64)
    ooff = np.zeros(k_n + 1, dtype=np.int64)
    quiet = np.zeros(members.size + cap, dtype=np.bool_)
    pos = 0
    for k in range(k_n):
        ooff[k] = pos
        for j in range(moff[k], moff[k + 1]):
            obs[pos] = members[j]
            pos += 1
        r0 = pos
        for j in range(moff[k], moff[k + 1]):
            m = members[j]
            for q in range(nb_ptr[m], nb_ptr[m + 1]):
                r = nb[q]
                if labels[r] < 0 and finite[r] and not mark[r]:
                    mark[r] = True
                    obs[pos] = r
                    pos += 1
        for p in range(r0 + 1, pos):  # insertion sort: a ring is a few elements (np.sort doubled the compile time)
            v = obs[p]
            q = p - 1
            while q >= r0 and obs[q] > v:
                obs[q + 1] = obs[q]
                q -= 1
            obs[q + 1] = v
        for p in range(r0, pos):
            r = obs[p]
            mark[r] = False
            sig = c1[r] > ring_signal[0] or c2[r] > ring_signal[1]
            if sig:
                for q in range(nb_ptr[r], nb_ptr[r + 1]):
                    lb = labels[nb[q]]
                    if lb >= 0 and lb != k:
                        sig = False
                        break
            quiet[p] = not sig
    ooff[k_n] = pos
    obs = obs[:pos]
    quiet = quiet[:pos]
    y = np.empty((2, pos))
    a = np.empty(pos)
    f = np.empty(pos)
    for p in range(pos):
        y[0, p] = c1[obs[p]]
        y[1, p] = c2[obs[p]]
        a[p] = area[obs[p]]
        f[p] = force[obs[p]]
    sigma0 = np.full(k_n, np.nan)
    any_valid = np.zeros(k_n, dtype=np.bool_)
    is_firm = np.zeros(k_n, dtype=np.bool_)
    cx = np.empty(k_n)
    cy = np.empty(k_n)
    area_sum = np.empty(k_n)
    force_sum = np.empty(k_n)
    for k in range(k_n):
        s = ooff[k]
        e = s + nm[k]
        sf = 0.0
        sa = 0.0
        for p in range(s, e):
            if valid[obs[p]]:
                any_valid[k] = True
                sf += f[p]
                sa += a[p]
        if any_valid[k]:
            sigma0[k] = sf / sa
        elif has_firm:
            sw = 0.0
            swl = 0.0
            hard = False
            for p in range(s, e):
                fm = firm[obs[p]]
                if np.isfinite(fm):
                    hard = True
                    w = max(y[0, p], 0.0) + 1e-300
                    swl += w * math.log(fm)
                    sw += w
            if hard:
                sigma0[k] = math.exp(swl / sw)
                is_firm[k] = True
        sg = sigma0[k]
        if np.isfinite(sg):
            g1 = sensitivity_slope(sg, par[0], par[1], par[2], par[3])[0]
            g2 = sensitivity_slope(sg, par[4], par[5], par[6], par[7])[0]
            for p in range(s, ooff[k + 1]):
                if not valid[obs[p]]:
                    est = (w1 * g1 * y[0, p] + w2 * g2 * y[1, p]) / (w1 * g1 * g1 + w2 * g2 * g2)
                    a[p] = est
                    f[p] = sg * est
        positive = False
        for p in range(s, e):
            if np.isfinite(f[p]) and f[p] > 0.0:
                positive = True
        tot = 0.0
        sx = 0.0
        sy = 0.0
        for p in range(s, e):
            w = f[p] if positive else max(y[0, p], 0.0)
            if not (np.isfinite(w) and w > 0.0):
                w = 0.0
            tot += w
            sx += w * centres[obs[p], 0]
            sy += w * centres[obs[p], 1]
        if tot > 0.0:
            cx[k] = sx / tot
            cy[k] = sy / tot
        else:
            mx = 0.0
            my = 0.0
            for p in range(s, e):
                mx += centres[obs[p], 0]
                my += centres[obs[p], 1]
            cx[k] = mx / nm[k]
            cy[k] = my / nm[k]
        st = 0.0
        sfo = 0.0
        for p in range(s, e):
            if not np.isnan(a[p]):
                st += max(a[p], 0.0)
            if not np.isnan(f[p]):
                sfo += f[p]
        area_sum[k] = st
        force_sum[k] = sfo
    return ooff, nm, obs, quiet, a, f, y, sigma0, any_valid, is_firm, cx, cy, area_sum, force_sum


#: x/0 gives inf or NaN as numpy's arithmetic did before this kernel, never an exception
#: (a valid element of zero area makes a cluster without a pressure, not a failed frame).
gather_clusters = compiled(_gather_clusters, error_model="numpy")


@compiled
def components(n: int, e: np.ndarray, active: np.ndarray) -> np.ndarray:
    """Connected components of the ``active`` elements among ``n`` over the pairs ``e``
    (E, 2) (each pair's ends active): a label per element, -1 if inactive, 0..K-1 numbered
    by the lowest element index of each component (:func:`cellbridge.tactile.clusters.cluster_elements`).

    Union-find, each root the lowest index of its set, then one pass in index order: a
    component is met first at its lowest element. Integers only, so the labels are the
    ones numpy's min-label propagation gave, in one call instead of a dozen numpy passes
    over the whole skin per frame (two per frame: clusters by edge, and across unknown
    elements)."""
    parent = np.arange(n)
    for k in range(e.shape[0]):
        i = e[k, 0]
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        j = e[k, 1]
        while parent[j] != j:
            parent[j] = parent[parent[j]]
            j = parent[j]
        if i < j:
            parent[j] = i
        elif j < i:
            parent[i] = j
    out = np.full(n, -1, dtype=np.int64)
    label = np.full(n, -1, dtype=np.int64)
    k = 0
    for i in range(n):
        if not active[i]:
            continue
        r = i
        while parent[r] != r:
            r = parent[r]
        if label[r] < 0:
            label[r] = k
            k += 1
        out[i] = label[r]
    return out
