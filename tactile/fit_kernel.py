"""Compiled fit kernel: Levenberg–Marquardt on one or two disks, and honest error bars.

One call fits every problem of a frame (every contact, every candidate split,
every fixed-diameter fit of a light touch), so the per-frame cost is the fits
themselves rather than interpreter overhead. A problem is a slice of flat arrays:
its observed elements (cluster first, then the quiet ring) with their readings.

Speed by construction:

* analytic Jacobian (:func:`cellbridge.tactile.disk_model.disk_residuals`) and a
  start from the element ratios (:func:`share_start`) or from the previous frame,
  so a handful of Gauss–Newton/LM steps converge;
* an axis the readings resolve is checked with two profile points (± 2σ: does the
  cost rise as the curvature says?) instead of a scan;
* an axis they do not see at all (a disk wholly inside an element, the coordinate
  along a seam) has its plateau computed from the element edges (:func:`_plateau`),
  and only the short way beyond it, where the readings start to notice, is
  bracketed (doubling steps, bisection); an axis seen weakly (a disk barely over a
  seam) is bracketed from the fit outwards. The brackets give the range of
  positions consistent with the readings, hence σ.
"""

from __future__ import annotations

import math

import numpy as np
from cellbridge.tactile._jit import compiled
from cellbridge.tactile.disk_model import disk_residuals
from cellbridge.tactile.spread_model import DV, spread_residuals

#: (spread s in m, 0 for the uniform model; quadrature cells per element side;
#: profile rows of :mod:`cellbridge.tactile.spread_model`): which model a fit uses.
SpreadArgs = tuple  # (float, int, np.ndarray)

UNIFORM = (0.0, 1, np.zeros((2, 2)))

__all__ = ["share_start", "fit_batch", "UNIFORM"]

_LN_D_MIN = math.log(1e-5)  # 10 µm
_LN_F_MIN = math.log(1e-6)
_LN_F_MAX = math.log(1e5)


@compiled
def _eval(
    theta: np.ndarray, nd: int, bounds: np.ndarray, y: np.ndarray, w: np.ndarray, quiet: np.ndarray,
    nch: int, par: np.ndarray, sm: SpreadArgs, res: np.ndarray, jac: np.ndarray, want_jac: bool,
) -> tuple[float, float]:
    # The uniform-pressure model, or the spread model (one disk, ΔC) when s > 0.
    if sm[0] > 0.0:
        return spread_residuals(theta, bounds, y, w, quiet, par, sm[0], sm[1], sm[2], res, jac, want_jac)
    return disk_residuals(theta, nd, bounds, y, w, quiet, nch, par, res, jac, want_jac)


@compiled
def _cholesky_solve(A: np.ndarray, b: np.ndarray, n: int, out: np.ndarray) -> bool:
    # In-place Cholesky of the leading n×n block of A; solves A·out = b.
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= A[j, k] * A[j, k]
        if not s > 0.0:
            return False
        A[j, j] = math.sqrt(s)
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= A[i, k] * A[j, k]
            A[i, j] = t / A[j, j]
    for i in range(n):
        t = b[i]
        for k in range(i):
            t -= A[i, k] * out[k]
        out[i] = t / A[i, i]
    for i in range(n - 1, -1, -1):
        t = out[i]
        for k in range(i + 1, n):
            t -= A[k, i] * out[k]
        out[i] = t / A[i, i]
    return True


@compiled
def _scale(j: int, side: float) -> float:
    return side if j % 4 < 2 else 1.0


@compiled
def _clip_theta(theta: np.ndarray, nd: int, ln_dmax: float) -> None:
    for k in range(nd):
        theta[4 * k + 2] = min(max(theta[4 * k + 2], _LN_D_MIN), ln_dmax)
        theta[4 * k + 3] = min(max(theta[4 * k + 3], _LN_F_MIN), _LN_F_MAX)


@compiled
def lm(
    theta: np.ndarray, free: np.ndarray, nd: int, bounds: np.ndarray, y: np.ndarray, w: np.ndarray,
    quiet: np.ndarray, nch: int, par: np.ndarray, side: float, max_iter: int, sm: SpreadArgs,
) -> tuple[float, float, bool]:
    """Levenberg–Marquardt in place on ``theta``; returns (data cost, total cost, converged).

    A free parameter whose Jacobian column is negligible over its typical range is
    held still in that iteration: the readings say nothing about it there (a disk
    inside one element does not see its position), and a solve would move it by
    round-off amplified.
    """
    m = bounds.shape[0]
    p = 4 * nd
    nrow = nch * m + nd
    res = np.empty(nrow)
    jac = np.empty((nrow, p))
    rt = np.empty(nrow)
    jt = np.empty((nrow, p))
    trial = np.empty(p)
    A = np.empty((p, p))
    M = np.empty((p, p))
    g = np.empty(p)
    step = np.empty(p)
    idx = np.empty(p, dtype=np.int64)
    # Diameters up to 100 sides; with the spread model, up to what the profile rows cover.
    ln_dmax = math.log(100.0 * side)
    if sm[0] > 0.0:
        ln_dmax = math.log(2.0 * sm[0] * (sm[2].shape[0] - 2) * DV)
    _clip_theta(theta, nd, ln_dmax)
    data, cost = _eval(theta, nd, bounds, y, w, quiet, nch, par, sm, res, jac, True)
    lam = 1e-3
    conv = False
    evals = 0
    for _ in range(max_iter):
        n = 0
        for j in range(p):
            if not free[j]:
                continue
            c2 = 0.0
            for i in range(nrow):
                c2 += jac[i, j] * jac[i, j]
            sc = _scale(j, side)
            if c2 * sc * sc > 1e-6:
                idx[n] = j
                n += 1
        if n == 0:
            conv = True
            break
        for a in range(n):
            ja = idx[a]
            s = 0.0
            for i in range(nrow):
                s += jac[i, ja] * res[i]
            g[a] = -s
            for b in range(a, n):
                jb = idx[b]
                s = 0.0
                for i in range(nrow):
                    s += jac[i, ja] * jac[i, jb]
                A[a, b] = s
                A[b, a] = s
        improved = False
        small = False
        while lam < 1e12 and evals < 8 * max_iter:  # a bounded cost, whatever the data
            evals += 1
            for a in range(n):
                for b in range(n):
                    M[a, b] = A[a, b]
                M[a, a] = A[a, a] * (1.0 + lam) + 1e-300
            if not _cholesky_solve(M, g, n, step):
                lam *= 10.0
                continue
            for j in range(p):
                trial[j] = theta[j]
            big = 0.0
            for a in range(n):
                trial[idx[a]] += step[a]
                big = max(big, abs(step[a]) / _scale(idx[a], side))
            _clip_theta(trial, nd, ln_dmax)
            dt, ct = _eval(trial, nd, bounds, y, w, quiet, nch, par, sm, rt, jt, True)
            if ct <= cost:
                small = cost - ct <= 1e-10 * cost + 1e-14 or big < 1e-9
                for j in range(p):
                    theta[j] = trial[j]
                for i in range(nrow):
                    res[i] = rt[i]
                    for j in range(p):
                        jac[i, j] = jt[i, j]
                data = dt
                cost = ct
                lam = max(lam * 0.2, 1e-12)
                improved = True
                break
            lam *= 5.0
        if not improved or small:
            conv = True  # a minimum: no downhill step left, or steps no longer matter
            break
    return data, cost, conv


@compiled
def _profile(
    theta: np.ndarray, free: np.ndarray, j: int, value: float, nd: int, bounds: np.ndarray, y: np.ndarray,
    w: np.ndarray, quiet: np.ndarray, nch: int, par: np.ndarray, side: float, out: np.ndarray, sm: SpreadArgs,
) -> float:
    # Total cost with parameter j held at `value` and every other free one re-fitted.
    for i in range(theta.size):
        out[i] = theta[i]
    out[j] = value
    fr = free.copy()
    fr[j] = False
    _, cost, _ = lm(out, fr, nd, bounds, y, w, quiet, nch, par, side, 12, sm)
    return cost


@compiled
def _covariance(
    theta: np.ndarray, use: np.ndarray, nd: int, bounds: np.ndarray, y: np.ndarray, w: np.ndarray,
    quiet: np.ndarray, nch: int, par: np.ndarray, side: float, cov: np.ndarray, sm: SpreadArgs,
) -> bool:
    # (JᵀJ)⁻¹ of the data rows (not the prior) over the parameters `use`; others NaN.
    m = bounds.shape[0]
    p = 4 * nd
    nrow = nch * m + nd
    res = np.empty(nrow)
    jac = np.empty((nrow, p))
    _eval(theta, nd, bounds, y, w, quiet, nch, par, sm, res, jac, True)
    idx = np.empty(p, dtype=np.int64)
    n = 0
    for j in range(p):
        if not use[j]:
            continue
        s = 0.0
        for i in range(nch * m):
            s += jac[i, j] * jac[i, j]
        sc = _scale(j, side)
        # A parameter the readings do not see is left out (NaN), the rest kept.
        if s * sc * sc > 1e-6:
            idx[n] = j
            n += 1
    for a in range(p):
        for b in range(p):
            cov[a, b] = np.nan
    if n == 0:
        return True
    A = np.empty((n, n))
    for a in range(n):
        for b in range(n):
            s = 0.0
            for i in range(nch * m):
                s += jac[i, idx[a]] * jac[i, idx[b]]
            A[a, b] = s
    # Scale to unit diagonal before inverting: positions (m) and logs differ by 1e4.
    d = np.empty(n)
    for a in range(n):
        d[a] = 1.0 / math.sqrt(A[a, a])
    L = np.empty((n, n))
    for a in range(n):
        for b in range(n):
            L[a, b] = A[a, b] * d[a] * d[b]
    e = np.zeros(n)
    col = np.empty(n)
    inv = np.empty((n, n))
    for b in range(n):
        Lc = L.copy()
        for a in range(n):
            e[a] = 1.0 if a == b else 0.0
        if not _cholesky_solve(Lc, e, n, col):
            return False
        for a in range(n):
            inv[a, b] = col[a]
    for a in range(n):
        if not inv[a, a] < 1e12:  # near-singular: as good as unknown
            return False
        for b in range(n):
            cov[idx[a], idx[b]] = inv[a, b] * d[a] * d[b]
    return True


@compiled
def _bracket(
    theta: np.ndarray, free: np.ndarray, j: int, c0: float, thr: float, step0: float, limit: float,
    nd: int, bounds: np.ndarray, y: np.ndarray, w: np.ndarray, quiet: np.ndarray, nch: int,
    par: np.ndarray, side: float, better: np.ndarray, sm: SpreadArgs, tol: float, start_lo: float,
    start_hi: float,
) -> tuple[float, float, float]:
    """Range of parameter j where the profile cost stays within ``c0 + thr``.

    From ``start_lo`` below and ``start_hi`` above the current value (known to be
    inside), doubling steps outwards, then bisection down to ``tol``. Returns
    (lo, hi, lowest cost seen); ``better`` holds the parameters at that lowest cost,
    so a caller can restart from a better minimum the local solver missed.
    """
    tmp = np.empty(theta.size)
    best = c0
    for i in range(theta.size):
        better[i] = theta[i]
    ends = np.empty(2)
    for side_i in range(2):
        sgn = -1.0 if side_i == 0 else 1.0
        t_in = start_lo if side_i == 0 else start_hi
        offset = t_in
        step = step0
        t = offset + step
        t_out = -1.0
        cur = theta.copy()
        while t <= limit:
            c = _profile(cur, free, j, theta[j] + sgn * t, nd, bounds, y, w, quiet, nch, par, side, tmp, sm)
            if c < best:
                best = c
                for i in range(theta.size):
                    better[i] = tmp[i]
            if c > c0 + thr:
                t_out = t
                break
            t_in = t
            for i in range(theta.size):
                cur[i] = tmp[i]
            step *= 2.0
            t = offset + step
        if t_out < 0.0:
            ends[side_i] = limit
            continue
        while t_out - t_in > tol:
            mid = 0.5 * (t_in + t_out)
            c = _profile(cur, free, j, theta[j] + sgn * mid, nd, bounds, y, w, quiet, nch, par, side, tmp, sm)
            if c <= c0 + thr:
                t_in = mid
            else:
                t_out = mid
        ends[side_i] = 0.5 * (t_in + t_out)
    return theta[j] - ends[0], theta[j] + ends[1], best


@compiled
def _plateau(theta: np.ndarray, k: int, a: int, bounds: np.ndarray) -> tuple[float, float]:
    """Positions along axis ``a`` where disk k reads exactly as it does now.

    Sliding the disk changes an element's share only when its extent crosses one of
    that element's edges (perpendicular to the axis, among the elements level with
    the disk). So the readings stay put between the nearest such edges on either
    side, less the radius. (NaN, NaN) when an edge cuts the disk: then the axis is
    not flat here and the caller brackets it by profile instead.
    """
    c = theta[4 * k + a]
    cb = theta[4 * k + 1 - a]
    r = 0.5 * math.exp(theta[4 * k + 2])
    lo = -math.inf
    hi = math.inf
    eps = 1e-9 * r
    for i in range(bounds.shape[0]):
        if bounds[i, 3 - a] <= cb - r or bounds[i, 1 - a] >= cb + r:
            continue  # not level with the disk
        for e in (bounds[i, a], bounds[i, a + 2]):
            if e <= c - r + eps:
                lo = max(lo, e + r)
            elif e >= c + r - eps:
                hi = min(hi, e - r)
            else:
                return np.nan, np.nan
    return lo, hi


@compiled
def fit_one(
    theta: np.ndarray, free: np.ndarray, nd: int, bounds: np.ndarray, y: np.ndarray, w: np.ndarray,
    quiet: np.ndarray, nch: int, par: np.ndarray, side: float,
    sig: np.ndarray, flat: np.ndarray, cov: np.ndarray, assess: bool, sm: SpreadArgs,
) -> tuple[float, float, bool]:
    """Fit in place and fill one-sigma ``sig`` per parameter, ``flat`` per position
    parameter (True: the readings do not resolve it; value = middle of the
    consistent range, σ = its width/√12) and the covariance. Returns (χ², cost, ok).
    Without ``assess`` the axes are not checked: σ is the curvature's alone."""
    p = 4 * nd
    m = bounds.shape[0]
    data, cost, conv = lm(theta, free, nd, bounds, y, w, quiet, nch, par, side, 60, sm)
    nfree = 0
    for j in range(p):
        nfree += free[j]
    dof = nch * m - nfree
    better = np.empty(p)
    tmp = np.empty(p)
    use = free.copy()
    # No disk explains the readings (χ² ten thousand times the noise): not worth
    # bracketing anything; the caller treats the cluster as one without a pressure.
    hopeless = data > 1e4 * max(dof, 1)
    if hopeless:
        assess = False
    for attempt in range(3 if assess else 0):
        infl = max(1.0, data / dof) if dof > 0 else 1.0
        for j in range(p):
            flat[j] = False
            sig[j] = np.nan
        # Position parameters the Jacobian does not see at all are flat from the start.
        for j in range(p):
            use[j] = free[j]
        ok_cov = _covariance(theta, use, nd, bounds, y, w, quiet, nch, par, side, cov, sm)
        restart = False
        for k in range(nd):
            for a in range(2):
                j = 4 * k + a
                if not free[j]:
                    continue
                sl = math.sqrt(cov[j, j] * infl) if ok_cov and cov[j, j] >= 0.0 else math.inf
                if sl < 0.05 * side:
                    cp = _profile(theta, free, j, theta[j] + 2.0 * sl, nd, bounds, y, w, quiet, nch, par, side, tmp, sm)
                    cm = _profile(theta, free, j, theta[j] - 2.0 * sl, nd, bounds, y, w, quiet, nch, par, side, tmp, sm)
                    if min(cp, cm) >= cost + 2.0 * infl:
                        sig[j] = sl
                        continue
                if sl == math.inf and sm[0] == 0.0:
                    plo, phi = _plateau(theta, k, a, bounds)
                    if plo <= phi:
                        # Unseen by the readings: take the middle of the plateau (same
                        # cost), then find how far beyond it the readings stay consistent.
                        plo = max(plo, theta[j] - 1.5 * side)
                        phi = min(phi, theta[j] + 1.5 * side)
                        theta[j] = 0.5 * (plo + phi)
                        lo, hi, best = _bracket(theta, free, j, cost, infl, side / 400.0, 1.5 * side, nd, bounds,
                                                y, w, quiet, nch, par, side, better, sm, 0.004 * side,
                                                theta[j] - plo, phi - theta[j])
                        if best < cost - 1e-3 * infl and attempt < 2:
                            restart = True
                            break
                        flat[j] = True
                        sig[j] = (hi - lo) / math.sqrt(12.0)
                        continue
                step0 = max(min(sl, 0.05 * side), side / 80.0)
                # The range sets σ = width/√12: a few per mille of the side is plenty.
                lo, hi, best = _bracket(theta, free, j, cost, infl, step0, 1.5 * side, nd, bounds, y, w,
                                        quiet, nch, par, side, better, sm, 0.004 * side, 0.0, 0.0)
                if best < cost - 1e-3 * infl and attempt < 2:
                    restart = True
                    break
                width = (hi - lo) / math.sqrt(12.0)
                if sl >= width:
                    # Report the middle of the flat bottom (positions the readings
                    # cannot tell apart at all), σ from the consistent range: the
                    # range may be lopsided where the skin ends.
                    flat[j] = True
                    plo, phi, _ = _bracket(theta, free, j, cost, 0.01 * infl, step0, 1.5 * side, nd, bounds, y,
                                           w, quiet, nch, par, side, better, sm, 0.0005 * side, 0.0, 0.0)
                    theta[j] = 0.5 * (plo + phi)
                    sig[j] = width
                else:
                    sig[j] = width
            if restart:
                break
        if restart:
            for j in range(p):
                theta[j] = better[j]
            data, cost, conv = lm(theta, free, nd, bounds, y, w, quiet, nch, par, side, 60, sm)
            continue
        break
    if not assess:
        for j in range(p):
            flat[j] = False
            sig[j] = np.nan
    anyflat = False
    for j in range(p):
        if flat[j]:
            anyflat = True
            use[j] = False
    if anyflat:
        data, cost, conv2 = lm(theta, use, nd, bounds, y, w, quiet, nch, par, side, 30, sm)
    infl = max(1.0, data / dof) if dof > 0 else 1.0
    ok_cov = _covariance(theta, use, nd, bounds, y, w, quiet, nch, par, side, cov, sm)
    for j in range(p):
        if use[j]:
            v = cov[j, j] * infl if ok_cov else np.nan
            sd = math.sqrt(v) if v >= 0.0 else np.inf
            if j % 4 < 2:
                sig[j] = max(sig[j], sd) if sig[j] == sig[j] else sd
            else:
                sig[j] = sd
            for i in range(p):
                cov[i, j] *= infl
    ok = (conv or data <= max(dof, 1)) and np.all(np.isfinite(theta)) and not hopeless
    return data, cost, ok  # type: ignore[return-value]  # numpy's bool from np.all; compiled, it is a bool


@compiled
def fit_batch(
    off: np.ndarray, bounds: np.ndarray, y: np.ndarray, quiet: np.ndarray, theta0: np.ndarray,
    free: np.ndarray, nd: int, w: np.ndarray, nch: int, par: np.ndarray, side: float, assess: bool,
    theta: np.ndarray, sig: np.ndarray, flat: np.ndarray, cov: np.ndarray, chi2: np.ndarray,
    cost: np.ndarray, ok: np.ndarray, sm: SpreadArgs,
) -> None:
    """Fit problem q on observations ``off[q]:off[q+1]`` from ``theta0[q]``, all q
    (``w[q]``: the weights 1/noise of its channels)."""
    for q in range(off.size - 1):
        a, b = off[q], off[q + 1]
        th = theta0[q].copy()
        c2, ct, good = fit_one(th, free[q], nd, bounds[a:b], y[:, a:b], w[q], quiet[a:b], nch, par, side,
                               sig[q], flat[q], cov[q], assess, sm)
        theta[q] = th
        chi2[q] = c2
        cost[q] = ct
        ok[q] = good


@compiled
def _frac_right(t: float) -> float:
    # Fraction of a unit disk beyond the line at signed distance t from its centre.
    t = min(max(t, -1.0), 1.0)
    return (math.acos(t) - t * math.sqrt(1.0 - t * t)) / math.pi


@compiled
def _axis_start(centre: np.ndarray, hi_edge: np.ndarray, area: np.ndarray, total: float, r: float) -> float:
    # Best boundary: the internal element edge that splits the area closest to half.
    best = -1.0
    pos = 0.0
    n = area.size
    for i in range(n):
        b = hi_edge[i]
        beyond = 0.0
        inner = False
        for k in range(n):
            if centre[k] > b:
                beyond += area[k]
                inner = True
        if not inner:
            continue
        f = beyond / total
        if f <= 1e-4 or f >= 1.0 - 1e-4:
            continue
        score = abs(f - 0.5)
        if best < 0.0 or score < best:
            lo, hi = -1.0, 1.0
            for _ in range(40):
                mid = 0.5 * (lo + hi)
                if _frac_right(mid) > f:
                    lo = mid
                else:
                    hi = mid
            best = score
            pos = b - 0.5 * (lo + hi) * r
    if best < 0.0:
        s = 0.0
        for i in range(n):
            s += area[i] * centre[i]
        pos = s / total
    return pos


@compiled
def share_start(off: np.ndarray, nmem: np.ndarray, bounds: np.ndarray, area: np.ndarray, out: np.ndarray) -> None:
    """Disk centre and radius from how a cluster's area is shared between its elements.

    Along x, the area right of an internal element edge at b is the part of the disk
    beyond b: ``S·frac((b − x)/r)`` with the circular-segment fraction ``frac``. The
    edge that splits the area closest to half is the best conditioned; inverting
    ``frac`` there gives x (likewise y). An axis with no internal edge starts at the
    area-weighted centre. ``out[q] = (x, y, r)``.
    """
    for q in range(off.size - 1):
        a = off[q]
        n = nmem[q]
        ar = np.maximum(area[a : a + n], 0.0)
        total = ar.sum()
        b = bounds[a : a + n]
        if not total > 0.0:
            out[q, 0] = 0.5 * (b[:, 0].min() + b[:, 2].max())
            out[q, 1] = 0.5 * (b[:, 1].min() + b[:, 3].max())
            out[q, 2] = np.nan
            continue
        r = math.sqrt(total / math.pi)
        cxs = 0.5 * (b[:, 0] + b[:, 2])
        cys = 0.5 * (b[:, 1] + b[:, 3])
        out[q, 0] = _axis_start(cxs, b[:, 2].copy(), ar, total, r)
        out[q, 1] = _axis_start(cys, b[:, 3].copy(), ar, total, r)
        out[q, 2] = r
