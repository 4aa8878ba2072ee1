"""One :meth:`Calibrator.update <cellbridge.tactile.calibration.Calibrator.update>` step, compiled.

The calibrator's step is a few dozen numpy calls over every element (common offset,
hysteresis, drift tracking, the contact surface's test), each a pass over a thousand
elements and a few microseconds of call overhead: about 0.4 ms a skin frame on a
humanoid's 1 144 elements, half of the daemon's per-frame element stage. Here the step
is a few compiled passes (the reference elements, the common offset, then every element
through the remaining rules, which read its own state only, and the anchor), with the
same rules, the same order of updates and the same arithmetic, so every number is the
numpy step's, bit for bit
(tests/test_calibration_kernel.py steps both side by side and compares every output and
every piece of state). One exception, where no sensor goes: readings that overflow float64
(about 1e308 F) make a baseline NaN, and that NaN's sign bit may differ from the numpy
step's (a NaN's sign and payload follow the operand order the compiler picks); the values,
NaN where numpy has NaN, are the same. Two parts stay numpy, passed in: the tracker's gains
``-expm1(-dt/tau)`` (numpy's ``expm1`` is not the C library's on every machine, and
differs from it in the last bit), and whatever the step leaves to
:class:`~cellbridge.tactile.calibration.Calibrator` (baseline collection, the jump's
record, re-centring a baseline being collected).

Medians are :func:`cellbridge.tactile.arrays.median0`'s: the same order statistics
(selection by ``np.partition``), ``(0.0 + a + b) / 2`` of the two middle ones, NaN
where a column holds one.

:mod:`cellbridge.tactile.calibration` does not import this module (the calibration must
run where executable memory is denied, as the package's other kernels allow): a
calibrator made with ``compiled=True`` runs this step once :func:`warm_up` has run in
its process, and the numpy step until then. Compiling costs about 12 s once per
installation (cached as the other kernels are: :mod:`cellbridge.tactile._jit`; loading it
then, under a second); the daemon warms it up in a thread at its start, so its first
frames on a fresh installation are stepped by numpy meanwhile, with the same results.
Once warm, the step compiles nothing more: arguments of other types (a read-only array)
leave the step to numpy.
"""

from __future__ import annotations

import math
import threading

import numpy as np
from cellbridge.tactile._jit import compiled

__all__ = ["READY", "step", "warm_up"]

#: Whether :func:`warm_up` has finished in this process (the step is compiled or loaded).
READY = False
_lock = threading.Lock()

#: Codes :func:`step` returns: the step ran, or it changed nothing and the numpy step must
#: run instead (an element collecting its baseline has a reading: collection is numpy's;
#: or a time went backwards: numpy's step raises).
DONE, NUMPY = 0, 1

_TOUCHED_ST, _COLLECTING, _TRACKING, _HOLDOFF = 2, 0, 1, 3
_BIG = np.finfo(np.float64).max


def _median(buf: np.ndarray, n: int) -> float:
    """median0 of ``buf[:n]`` (n >= 1): NaN if one is NaN."""
    for k in range(n):
        if math.isnan(buf[k]):
            return buf[k]
    h = n // 2
    p = np.partition(buf[:n], h)
    if n % 2 == 1:
        return (0.0 + p[h]) / 1
    lo = p[0]
    for k in range(1, h):
        if p[k] > lo:
            lo = p[k]
    return (0.0 + lo + p[h]) / 2


def _step(
    t0: float, v: np.ndarray, st: np.ndarray, last_t: np.ndarray, base: np.ndarray, base0: np.ndarray,
    noise: np.ndarray, since: np.ndarray, below_since: np.ndarray, off_since: np.ndarray,
    holds: np.ndarray, rebaselines: np.ndarray, count: np.ndarray,
    enter: np.ndarray, leave: np.ndarray, drift: np.ndarray, clip: np.ndarray, common: np.ndarray,
    spread: np.ndarray, gains: np.ndarray, ages: np.ndarray,
    k_enter: float, min_common: int, common_mode: bool, common_fraction: float, common_spread: float,
    tau: float, holdoff: float, max_touch: float, has_max_touch: bool, negative_after: float,
    surface: bool, s_noise: float, s_k: float, s_low: float, s_high: float, s_dc1_max: float,
    delta: np.ndarray, out: np.ndarray,
) -> tuple:
    """The step at time ``t0`` on readings ``v`` (n, c); state arrays updated in place.

    ``ages``: [spread_age, anchor_age] (in place). ``gains`` (n, 2): each element's tracker
    gain at ``tau`` and at ``tau_negative`` over its time since its last reading (taken as 0
    here where that time is not finite). ``surface``: the contact test is the ContactSurface of
    the ``s_*`` constants (else none). ``delta`` (n, c): ΔC out; ``out`` (3, n) bool:
    touched, ready, re-baselined.

    Returns ``(code, jumped, most, tracked, catchups, rebased, anchored, r, change)``: ``code``
    DONE or NUMPY (nothing changed); whether the common offset jumped (``most`` elements
    of ``tracked``); elements caught up after a silence; whether any was re-baselined;
    whether the anchor moved the offset by ``r`` (c,); the common offset's change by this
    step's median (c,), before the anchor's (the jump's record).

    The numpy step's passes are rule by rule over every element; the rules after the
    common offset depend on an element's own state only, so here they run element by
    element in one pass, each element through them in the numpy step's order.
    """
    n, c = v.shape
    r = np.zeros(c)
    chg = np.zeros(c)
    # every check before any state changes; each element's reading, readiness, tracking
    live = np.empty(n, dtype=np.bool_)
    ref = np.empty(n, dtype=np.bool_)
    ntrk = 0
    for i in range(n):
        ok = True
        for j in range(c):
            if not math.isfinite(v[i, j]):
                ok = False
        if ok and (st[i] == _COLLECTING or last_t[i] > t0):
            return NUMPY, False, 0, 0, 0, False, False, r, chg
        live[i] = ok and st[i] != _COLLECTING
        ref[i] = st[i] == _TRACKING
        ntrk += ref[i]
    buf = np.empty(n)
    # -- the reference elements (Calibrator._reference): tracked, and not drifting by themselves
    if ntrk >= min_common:
        if ages[0] <= 0:
            for j in range(c):
                m = 0
                for i in range(n):
                    if ref[i]:
                        buf[m] = abs(base[i, j] - base0[i, j])
                        m += 1
                spread[j] = 1.4826 * _median(buf, m)
            ages[0] = 32
        ages[0] -= 1
        steady = np.empty(n, dtype=np.bool_)
        nsteady = 0
        for i in range(n):
            s = ref[i] and not math.isfinite(off_since[i])
            if s:
                for j in range(c):
                    b = k_enter * spread[j]
                    e = enter[i, j]
                    lim = e if e >= b else b  # np.maximum: NaN if either is
                    if math.isnan(e) or math.isnan(b):
                        lim = math.nan
                    if not (abs(base[i, j] - base0[i, j]) <= lim):
                        s = False
            steady[i] = s
            nsteady += s
        if nsteady >= min_common:
            ref = steady
    # -- the common offset (Calibrator._update_common, _common_reference)
    jumped = False
    most = 0
    k = 0
    if common_mode:
        trk = np.empty(n, dtype=np.bool_)
        for i in range(n):
            trk[i] = live[i] and ref[i]
            k += trk[i]
        if k >= min_common:
            moved = np.zeros(n, dtype=np.bool_)  # jumped past ±enter, up or down
            nup = 0
            ndown = 0
            for i in range(n):
                if trk[i]:
                    u = False
                    d = False
                    for j in range(c):
                        o = (v[i, j] - base[i, j]) - common[j]
                        if o > enter[i, j]:
                            u = True
                        if o < -enter[i, j]:
                            d = True
                    nup += u
                    ndown += d
                    moved[i] = u or d
            need = common_fraction * k
            most = max(nup, ndown)
            jump = most > 0 and most >= need
            if jump:
                stp = np.empty(c)
                for j in range(c):
                    m = 0
                    for i in range(n):
                        if trk[i]:
                            buf[m] = (v[i, j] - base[i, j]) - common[j]
                            m += 1
                    stp[j] = _median(buf, m)
                nalike = 0
                for i in range(n):
                    if trk[i]:
                        a = True
                        for j in range(c):
                            tol = enter[i, j] + common_spread * abs(stp[j])
                            if math.isnan(tol):
                                tol = math.inf
                            if not (abs(((v[i, j] - base[i, j]) - common[j]) - stp[j]) <= tol):
                                a = False
                        nalike += a
                jump = nalike >= need
            nref = 0
            for i in range(n):
                nref += trk[i] and (jump or not moved[i])
            if nref >= min_common:
                for j in range(c):
                    m = 0
                    for i in range(n):
                        if trk[i] and (jump or not moved[i]):
                            buf[m] = v[i, j] - base[i, j]
                            m += 1
                    med = _median(buf, m)
                    chg[j] = med - common[j]  # the jump's record: before the anchor moves the offset too
                    common[j] = med
                jumped = jump
    # -- element by element: ΔC, catch-up, contact test, touch state, drift, time
    catchups = 0
    rebased = False
    anytrk = False
    zeros = False  # a baseline at exactly ±0 left out of the tracker's pass (numpy adds 0.0 to it)
    for i in range(n):
        li = live[i]
        for j in range(c):
            delta[i, j] = (v[i, j] - base[i, j]) - common[j] if li else np.nan
        # Calibrator._catch_up
        if li and st[i] == _TRACKING:
            gap = t0 - last_t[i]
            if gap > tau:
                fit = True
                for j in range(c):
                    if not (abs(delta[i, j]) <= drift[j] * gap):
                        fit = False
                if fit:
                    for j in range(c):
                        base[i, j] += delta[i, j]
                        delta[i, j] = 0.0
                    catchups += 1
        # Calibrator._contact_readings: asked where touched or above leave (True elsewhere)
        contact = True
        if surface and li:
            asked = st[i] == _TOUCHED_ST
            for j in range(c):
                if delta[i, j] > leave[i, j]:
                    asked = True
            if asked:
                x = delta[i, 0]
                y = delta[i, 1]
                m0 = _nan_to_num(noise[i, 0])
                m1 = _nan_to_num(noise[i, 1])
                t1 = s_k * (s_noise if s_noise >= m0 else m0)
                t2 = s_k * (s_noise if s_noise >= m1 else m1)
                lo = _nanmax(_nanmax((x - t1) / s_high, y - t2), 0.0)
                hi = _nanmin((x + t1) / s_low, y + t2)
                contact = (lo <= hi) and (x <= s_dc1_max + t1) and math.isfinite(x) and math.isfinite(y)
        # Calibrator._hysteresis
        if li:
            if st[i] != _TOUCHED_ST:
                up_i = False
                for j in range(c):
                    if delta[i, j] > enter[i, j]:
                        up_i = True
                if up_i and contact:
                    st[i] = _TOUCHED_ST
                    since[i] = t0
            else:
                dn = True
                for j in range(c):
                    if not (delta[i, j] < leave[i, j]):
                        dn = False
                if dn:
                    st[i] = _HOLDOFF
                    since[i] = t0
        if st[i] == _HOLDOFF and t0 - since[i] >= holdoff:
            st[i] = _TRACKING
        stuck = False
        if has_max_touch and st[i] == _TOUCHED_ST and t0 - since[i] >= max_touch:
            if not surface:
                stuck = True
            elif li:
                if contact:
                    holds[i] += 1
                    since[i] = t0
                else:
                    stuck = True
        if stuck:  # Calibrator.tare
            rebaselines[i] += 1
            st[i] = _COLLECTING
            count[i] = 0
            for j in range(c):
                base[i, j] = np.nan
                base0[i, j] = np.nan
                noise[i, j] = np.nan
                below_since[i, j] = np.inf
            off_since[i] = np.inf
            rebased = True
        # Calibrator._track
        trk_i = li and st[i] == _TRACKING
        anytrk = anytrk or trk_i
        drifted = False
        if surface:
            following = t0 - off_since[i] >= negative_after
            off_i = False
            if trk_i and not contact:
                over_e = False
                over_l = False
                for j in range(c):
                    if delta[i, j] > enter[i, j]:
                        over_e = True
                    if delta[i, j] > leave[i, j]:
                        over_l = True
                off_i = over_e or (following and over_l)
            if off_i:
                if t0 < off_since[i]:
                    off_since[i] = t0
                drifted = t0 - off_since[i] >= negative_after
            elif li:
                off_since[i] = np.inf
        seen = math.isfinite(t0 - last_t[i])  # (numpy's step: no time since a reading, no step)
        for j in range(c):
            fast = drifted
            if trk_i and delta[i, j] < -enter[i, j]:
                if t0 < below_since[i, j]:
                    below_since[i, j] = t0
                fast = fast or t0 - below_since[i, j] >= negative_after
            elif li:
                below_since[i, j] = np.inf
            if trk_i:
                d = delta[i, j]
                if fast:
                    base[i, j] += (gains[i, 1] if seen else 0.0) * d
                else:
                    base[i, j] += (gains[i, 0] if seen else 0.0) * _nanmin(_nanmax(d, -clip[j]), clip[j])
            elif base[i, j] == 0.0:
                zeros = True
        if li:
            last_t[i] = t0
        if st[i] == _COLLECTING:
            for j in range(c):
                delta[i, j] = np.nan
        out[0, i] = st[i] == _TOUCHED_ST
        out[1, i] = st[i] != _COLLECTING
        out[2, i] = stuck
    if anytrk and zeros:  # numpy's tracker adds 0.0 to every other baseline: -0.0 becomes 0.0
        for i in range(n):
            if not (live[i] and st[i] == _TRACKING):
                for j in range(c):
                    if base[i, j] == 0.0:
                        base[i, j] += 0.0
    # -- the anchor (Calibrator._anchor)
    anchored = False
    if common_mode:
        ages[1] -= 1
        if ages[1] <= 0:
            nref = 0
            for i in range(n):
                nref += ref[i] and st[i] == _TRACKING
            if nref >= min_common:
                ages[1] = 8
                nz = False
                for j in range(c):
                    m = 0
                    for i in range(n):
                        if ref[i] and st[i] == _TRACKING:
                            buf[m] = base[i, j] - base0[i, j]
                            m += 1
                    r[j] = _median(buf, m)
                    if r[j] != 0.0:
                        nz = True
                if nz:
                    for i in range(n):
                        if st[i] == _TRACKING:
                            for j in range(c):
                                base[i, j] -= r[j]
                    for j in range(c):
                        common[j] += r[j]
                    anchored = True
    return DONE, jumped, most, k, catchups, rebased, anchored, r, chg


def _nanmax(a: float, b: float) -> float:
    """np.maximum of two floats: NaN if either is."""
    if math.isnan(a) or math.isnan(b):
        return math.nan
    return a if a >= b else b


def _nan_to_num(a: float) -> float:
    """np.nan_to_num of a float: NaN 0, ±inf the largest finite float."""
    if math.isnan(a):
        return 0.0
    if math.isinf(a):
        return _BIG if a > 0 else -_BIG
    return a


def _nanmin(a: float, b: float) -> float:
    """np.minimum of two floats: NaN if either is."""
    if math.isnan(a) or math.isnan(b):
        return math.nan
    return a if a <= b else b


_median = compiled(_median)
_nanmax = compiled(_nanmax)
_nan_to_num = compiled(_nan_to_num)
_nanmin = compiled(_nanmin)
step = compiled(_step)


def warm_up() -> None:
    """Compile the step (or load it from the cache) with the argument types a calibrator
    passes, by one step of a small calibrator; then :data:`READY`. Safe to call from
    several threads and more than once."""
    global READY
    with _lock:
        if READY:
            return
        from cellbridge.tactile.calibration import CalibrationConfig, Calibrator
        from cellbridge.tactile.contact_surface import ContactSurface
        from cellbridge.tactile.element import ElementParams

        cal = Calibrator(4, 2, CalibrationConfig(n_baseline=1), is_contact=ContactSurface(ElementParams(), 2e-15),
                         compiled=True)
        cal.update(0.0, np.full((4, 2), 1e-11))
        if cal.update_compiled(0.01, np.full((4, 2), 1e-11)) is None:  # the compiled step itself, before READY
            raise RuntimeError("the compiled calibration step did not run on its warm-up")
        # no compiling once warm: a step with other argument types (a read-only array) is
        # numpy's, not seconds of compiling in the middle of a skin frame
        step.disable_compile()
        READY = True
