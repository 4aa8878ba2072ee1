"""Baseline and drift of every element's capacitances: from readings to ΔC.

The inverse needs capacitance *changes*. A change is only meaningful against a
baseline, and a soft skin's baseline is not constant: parasitics and foam
permittivity move with temperature and humidity, slowly but by amounts comparable to a
light touch, and a supply step moves every element at once. Following that drift is
easy; the hard part is not following a contact. A tracker that adapts all the time
would absorb a hand resting on the robot within a few time constants and report it as
gone. So:

* **Baseline** per element: the median of its first ``n_baseline`` readings (assumed
  quiet), with the noise estimated from their MAD. Until then the element is not
  *ready* and its ΔC is NaN.
* **Common mode**: a change every element sees at once is drift, never touch. Each
  step the skin's common offset is the median residual of the tracked elements that
  did not jump past their touch threshold, up or down — or of all tracked elements
  when nearly all of them (``common_fraction``) jumped together the same way and
  alike (within ``enter + common_spread·|step|``), which no contact but one pressing
  them all equally does (that one is absorbed, and reported as a common jump). The
  offset is subtracted from *every* ready element (tracked, touched, held off, or
  without a reading this step), so a press held for minutes neither fades nor picks up the
  skin's drift, and an element that was silent comes back corrected. Elements drifting
  by themselves (own drift standing out from the others', or reading what no contact
  gives) are no reference for it while enough others are, and the tracked elements'
  median own drift is moved into the offset every 8 steps: the offset and the own
  baselines are only known through their sum, and without that anchor a biased median
  ratcheted the offset under a press held for an hour (see :meth:`Calibrator._anchor`).
* **Touch state** with hysteresis: an element becomes *touched* when any channel rises
  above ``enter`` and *released* when every channel is back below ``leave``
  (``leave < enter``), both raised to a multiple of the measured noise if that is
  larger. After release a **hold-off** lets the foam recover before tracking resumes.
* **Element drift** (what is left after the common mode) is followed only while an
  element is untouched and past its hold-off: an exponential tracker with time
  constant ``tau`` (seconds of the timestamps passed in, not of any clock) whose
  innovation is clipped to ``±max_drift·tau``. The clip bounds how fast a baseline may
  move (``max_drift`` F/s), so one outlier cannot drag it and a slow press outruns it
  and is reported. A channel that has read below ``−enter`` for ``negative_after``
  seconds — which no contact can cause, e.g. a baseline taken while something rested
  on the skin — is followed unclipped on ``tau_negative``. An element back from a
  silence longer than ``tau`` may have drifted ``max_drift`` per second of it: a
  change within that is taken as baseline at once (counted), a larger one is a touch.
* **Contact readings** (optional ``is_contact``, e.g. a
  :class:`~cellbridge.tactile.ContactSurface`): the two layers tell a press from an
  element drifting by itself. A press moves (ΔC1, ΔC2) along the element's (F, S)
  surface; one layer drifting alone does not. An element whose reading is above
  ``enter`` but no contact's is not touched: it is drift, and after ``negative_after``
  seconds of such readings its baseline follows them unclipped on ``tau_negative`` (as a
  channel below −enter is followed), so it is never reported and never latches.
* **Stuck touch**: an element touched for longer than ``max_touch`` seconds is
  re-baselined (as by :meth:`Calibrator.tare`) and the event counted per element
  (:attr:`Calibrator.rebaselines`, :meth:`Calibrator.health`, and the step's
  ``rebaselined``), so a phantom cannot latch forever and the user can see that it
  happened — unless ``is_contact`` is given and the element's reading is still a
  contact's: then the touch is a press held that long, it is kept (its ``max_touch``
  clock restarts, counted in :attr:`Calibrator.holds`) and nothing is re-baselined.
* **Tare** re-takes the baseline of all or some elements on command.

Plain object, no clocks or I/O: :meth:`Calibrator.update` takes one time and the
readings of every element (NaN for an element without a reading at that step) and
returns ΔC, touch and readiness for all of them. Each step is vectorised over
elements. Readings are in whatever unit the caller uses consistently (farads from
the transfer functions, normally); the default thresholds and rates assume farads.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np
from cellbridge.tactile.arrays import FloatArray, median0, rows_all, rows_any
from cellbridge.tactile.contact_surface import ContactSurface
from numpy.typing import ArrayLike, NDArray

__all__ = [
    "CalibrationConfig",
    "CalibrationStep",
    "Calibrator",
    "COLLECTING",
    "TRACKING",
    "TOUCHED",
    "HOLDOFF",
]


#: Steps between two measurements of the spread of the tracked elements' own drift
#: (:meth:`Calibrator._reference`), and between two anchorings of the common offset
#: (:meth:`Calibrator._anchor`): each is a median over the skin, and what they correct
#: moves far slower than a step (the offset's ratchet: about 0.04 fF/s).
_SPREAD_EVERY = 32
_ANCHOR_EVERY = 8


def _is_count(v: object, minimum: int = 1) -> bool:
    """An integer (Python or numpy, never a bool) of at least ``minimum``."""
    return bool(isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))
                and v >= minimum)

#: A reading this many times its channel's absolute touch threshold is in another
#: unit (farads: 20 pF / 50 fF = 400; picofarads against farad thresholds: 4e14).
_UNIT_RATIO = 1e9

#: Element states (values of :attr:`Calibrator.state`).
COLLECTING = 0  #: gathering quiet readings for the baseline; not ready
TRACKING = 1  #: untouched, baseline follows drift
TOUCHED = 2  #: contact present, baseline frozen (common-mode drift only)
HOLDOFF = 3  #: just released, baseline frozen until ``holdoff`` has passed


@dataclass(frozen=True)
class CalibrationConfig:
    """Tuning of :class:`Calibrator`; defaults suit the counter front end in farads.

    ``enter``/``leave``/``max_drift`` are per channel (a scalar applies to all
    channels). The defaults (50 fF / 25 fF) sit a few tens of counter counts above the
    2 ms gate's quantisation and correspond to roughly 0.05 N on a 10-20 mm contact;
    the ADC front end (1 LSB ≈ 0.2 pF) needs about ten times more, which the noise
    multiples ``k_enter``/``k_leave`` provide automatically when the baseline
    readings are that noisy.
    """

    n_baseline: int = 50  #: quiet readings before an element is ready (0.5 s at 100 Hz)
    enter: float | Sequence[float] = 50e-15  #: ΔC above which a channel signals touch
    leave: float | Sequence[float] = 25e-15  #: every channel below this: released
    k_enter: float = 8.0  #: enter at least this many noise sigmas (MAD of the baseline)
    k_leave: float = 4.0  #: leave at least this many noise sigmas
    holdoff: float = 2.0  #: s after release before drift tracking resumes
    tau: float = 10.0  #: s, time constant of the drift tracker
    #: F/s, fastest element drift followed: the tracker's innovation is clipped to
    #: ±max_drift·tau, so a press rising faster than this is reported, not absorbed
    max_drift: float | Sequence[float] = 1e-15
    tau_negative: float = 3.0  #: s, tracker time constant while reading below −enter
    negative_after: float = 1.0  #: s below −enter before tau_negative applies
    common_mode: bool = True  #: subtract the skin's common offset from every element
    min_common: int = 2  #: tracked elements needed for a common-mode estimate
    #: share of the tracked elements that must jump past ``enter`` together for the
    #: jump to count as common (drift), not as contacts
    common_fraction: float = 0.9
    #: a common step moves the tracked elements alike: after it, ``common_fraction`` of
    #: them must lie within ``enter + common_spread·|step|`` of it, or it is contacts
    #: (inf: any jump of enough elements is common)
    common_spread: float = 0.25
    #: s; an element touched this long is re-baselined and counted (None: never)
    max_touch: float | None = 600.0

    def __post_init__(self) -> None:
        if not _is_count(self.n_baseline):
            raise ValueError(f"n_baseline must be an integer >= 1, got {self.n_baseline!r}")
        for name in ("enter", "leave", "max_drift"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.ndim > 1 or np.any(np.isnan(v)) or not np.all(v >= 0):
                raise ValueError(f"{name} must be a threshold >= 0 or one per channel, got {v!r}")
            if name != "max_drift" and not np.all(np.isfinite(v)):
                raise ValueError(f"{name} must be finite, got {v!r}")
        for name in ("k_enter", "k_leave", "holdoff", "negative_after"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v!r}")
        for name in ("tau", "tau_negative"):
            v = getattr(self, name)
            if not (v > 0):  # inf allowed: a frozen baseline
                raise ValueError(f"{name} must be > 0 s, got {v!r}")
        if self.k_leave > self.k_enter:
            raise ValueError("k_leave must not exceed k_enter (hysteresis)")
        if not _is_count(self.min_common):
            raise ValueError(f"min_common must be an integer >= 1, got {self.min_common!r}")
        if not (self.common_spread >= 0):  # inf allowed, NaN not
            raise ValueError(f"common_spread must be >= 0, got {self.common_spread!r}")
        if not (0.5 < self.common_fraction <= 1.0):
            raise ValueError(f"common_fraction must lie in (0.5, 1], got {self.common_fraction!r}")
        if self.max_touch is not None and not (self.max_touch > 0):
            raise ValueError("max_touch must be > 0 s or None")


def _check_unit(v: FloatArray, col: NDArray[np.bool_], enter: FloatArray) -> None:
    """ValueError for readings far too large for the absolute thresholds ``enter``
    (C,): a unit mix-up, checked on the readings ``col`` a baseline is built from.

    Quantised readings in pF give a MAD of 0, so the noise multiples cannot rescue
    farad thresholds: every count of flicker would be a touch.
    """
    if not col.any():
        return
    lim = _UNIT_RATIO * enter
    big = (np.abs(v[col]) > lim) & (lim > 0)
    if big.any():
        i, j = np.argwhere(big)[0]
        e = int(np.nonzero(col)[0][i])
        raise ValueError(
            f"element {e} channel {j} reads {v[e, j]:g}, more than {_UNIT_RATIO:g} times its "
            f"touch threshold {enter[j]:g}: readings in picofarads with thresholds in "
            "farads? Give readings and CalibrationConfig in one unit (farads by default)"
        )


def _common_reference(
    off: FloatArray, trk: NDArray[np.bool_], enter: FloatArray, cfg: CalibrationConfig
) -> tuple[bool, int, NDArray[np.bool_]]:
    """(common jump?, elements that jumped, elements whose median is the offset).

    ``off`` is every element's residual beyond the current offset. A jump is common
    when ``common_fraction`` of the tracked elements jumped past ±enter the same way
    *and* lie within ``enter + common_spread·|step|`` of its median step; otherwise
    the reference is the tracked elements that did not jump either way.
    """
    up = trk & rows_any(off > enter)
    down = trk & rows_any(off < -enter)
    need = cfg.common_fraction * int(trk.sum())
    most = max(int(up.sum()), int(down.sum()))
    jump = bool(most and most >= need)
    if jump:
        step = median0(off[trk])
        with np.errstate(invalid="ignore"):  # inf · 0 when common_spread is inf
            tol = enter + cfg.common_spread * np.abs(step)
        alike = trk & rows_all(np.abs(off - step) <= np.where(np.isnan(tol), np.inf, tol))
        jump = int(alike.sum()) >= need
    return jump, most, (trk if jump else trk & ~up & ~down)


class CalibrationStep(NamedTuple):
    """What one :meth:`Calibrator.update` returns; arrays over elements."""

    delta: FloatArray  #: (N, C) reading − baseline; NaN where not ready or not sampled
    touched: NDArray[np.bool_]  #: (N,) contact present (hysteresis state)
    ready: NDArray[np.bool_]  #: (N,) baseline available
    #: this step's common offset took a jump: a common step, or a press lifting
    #: (nearly) every tracked element at once, which cannot be told apart here
    common_jump: bool = False
    #: (N,) elements re-baselined by this step after ``max_touch`` (all touched until
    #: then: a re-baseline under what was reported as a contact); None: none
    rebaselined: NDArray[np.bool_] | None = None


class Calibrator:
    """Baselines, drift tracking and touch hysteresis for N elements × C channels."""

    def __init__(self, n_elements: int, n_channels: int = 2, config: CalibrationConfig | None = None,
                 is_contact: Callable[[FloatArray, FloatArray], NDArray[np.bool_]] | None = None,
                 compiled: bool = False):
        """``is_contact(delta, noise)`` takes (k, C) ΔC rows and their measured noise
        (k, C; 0 where not known) and says which a contact can make (see
        :class:`~cellbridge.tactile.ContactSurface`); None: every reading could be a
        contact's, and a touch still ends at ``max_touch`` (no way to tell a phantom).
        ``compiled``: step with :mod:`cellbridge.tactile.calibration_kernel` (the same
        numbers) once its ``warm_up`` has run in this process; this module never imports
        it, and until then (and for a step the kernel leaves to numpy: a time per
        element, an element collecting its baseline, another ``is_contact``) the step is
        numpy's."""
        if not _is_count(n_elements):
            raise ValueError(f"n_elements must be an integer >= 1, got {n_elements!r}")
        if not _is_count(n_channels):
            raise ValueError(f"n_channels must be an integer >= 1, got {n_channels!r}")
        self.config = CalibrationConfig() if config is None else config
        self.is_contact = is_contact
        n, c = int(n_elements), int(n_channels)
        self.n_elements, self.n_channels = n, c
        cfg = self.config
        self._enter = self._per_channel(cfg.enter, "enter")
        self._leave = self._per_channel(cfg.leave, "leave")
        if np.any(self._leave > self._enter):
            raise ValueError("leave thresholds must not exceed enter thresholds (hysteresis)")
        drift = self._per_channel(cfg.max_drift, "max_drift")
        self._drift = drift
        with np.errstate(invalid="ignore"):  # 0 F/s on a frozen (tau = inf) baseline: 0
            self._clip = np.where(drift > 0, drift * cfg.tau, 0.0)
        self._buf = np.zeros((n, cfg.n_baseline, c))
        self._count = np.zeros(n, dtype=np.int64)
        self._base = np.full((n, c), np.nan)  # element's own baseline, without the common offset
        self._base0 = np.full((n, c), np.nan)  # that baseline as collected: own drift is _base − _base0
        self._common = np.zeros(c)  # the skin's common offset, carried by every element
        self._noise = np.full((n, c), np.nan)
        self._state = np.full(n, COLLECTING, dtype=np.int8)
        self._last_t = np.full(n, -np.inf)
        self._since = np.full(n, -np.inf)  # time of the last state change into TOUCHED/HOLDOFF
        self._below_since = np.full((n, c), np.inf)  # reading below −enter since (per channel)
        self._rebaselines = np.zeros(n, dtype=np.int64)
        self._holds = np.zeros(n, dtype=np.int64)  # touches kept past max_touch: still a contact's reading
        self._off_since = np.full(n, np.inf)  # tracked, above enter, reading no contact's, since
        self._common_jumps = 0
        self._catchups = 0
        self._last_jump: dict[str, object] | None = None
        self._thr: tuple[FloatArray, FloatArray] | None = None  # cache, reset when noise changes
        self._spread = np.zeros(c)  # spread of the tracked elements' own drift (1.4826·MAD about 0)
        self._spread_age = 0  # steps until it is measured again
        self._anchor_age = 0  # steps until the offset is anchored again
        self._compiled = compiled
        self._taus = np.array([cfg.tau, cfg.tau_negative])  # the compiled step's two time constants
        self._frozen = not np.isfinite(self._taus).all()
        self._kernel: Any = None  # the compiled step's module, once it is warm

    _PER_ELEMENT = ("_buf", "_count", "_base", "_base0", "_noise", "_state", "_last_t", "_since", "_below_since",
                    "_rebaselines", "_holds", "_off_since")

    def adopt(self, old: Calibrator, rows: NDArray[np.int64], old_rows: NDArray[np.int64]) -> None:
        """Take over ``old``'s state of its elements ``old_rows`` as this calibrator's
        ``rows`` (a layout that grew: the elements already there keep their baselines and
        touch state instead of being re-taken under a press). Same configuration only."""
        if old.config != self.config or old.n_channels != self.n_channels:
            raise ValueError("adopt needs a calibrator of the same configuration and channel count")
        for name in self._PER_ELEMENT:
            getattr(self, name)[rows] = getattr(old, name)[old_rows]
        self._common = old._common.copy()
        self._common_jumps, self._catchups, self._last_jump = old._common_jumps, old._catchups, old._last_jump
        self._thr = None

    def _per_channel(self, v: float | Sequence[float], name: str) -> FloatArray:
        a = np.asarray(v, dtype=np.float64)
        if a.ndim == 0:
            return np.full(self.n_channels, float(a))
        if a.shape != (self.n_channels,):
            raise ValueError(f"{name} needs one value per channel ({self.n_channels}), got {a.shape}")
        return a.copy()

    # -- inspection -----------------------------------------------------------------
    @property
    def baseline(self) -> FloatArray:
        """(N, C) current baselines, common offset included (NaN while collecting)."""
        return self._base + self._common

    @property
    def noise(self) -> FloatArray:
        """(N, C) rms noise estimated from the baseline readings (1.4826·MAD)."""
        return self._noise.copy()

    @property
    def state(self) -> NDArray[np.int8]:
        """(N,) element states: COLLECTING, TRACKING, TOUCHED or HOLDOFF."""
        return self._state.copy()

    @property
    def ready(self) -> NDArray[np.bool_]:
        return self._state != COLLECTING

    @property
    def touched(self) -> NDArray[np.bool_]:
        return self._state == TOUCHED

    @property
    def common_drift(self) -> FloatArray:
        """(C,) the skin's common offset since start, carried by every element."""
        return self._common.copy()

    @property
    def rebaselines(self) -> NDArray[np.int64]:
        """(N,) how often each element was re-baselined after ``max_touch`` (not tares)."""
        return self._rebaselines.copy()

    @property
    def holds(self) -> NDArray[np.int64]:
        """(N,) how often each element's touch reached ``max_touch`` with a contact's
        reading and was kept (a press held that long), not re-baselined."""
        return self._holds.copy()

    @property
    def drifting(self) -> NDArray[np.bool_]:
        """(N,) tracked elements reading above ``enter`` what no contact gives (drift)."""
        return np.isfinite(self._off_since)

    def health(self) -> dict[str, object]:
        """Plain-Python summary for a health message (element *indices*, not ids)."""
        st = self._state
        hit = np.nonzero(self._rebaselines)[0]
        return {
            "ready": int(np.count_nonzero(st != COLLECTING)),
            "collecting": int(np.count_nonzero(st == COLLECTING)),
            "touched": int(np.count_nonzero(st == TOUCHED)),
            "holdoff": int(np.count_nonzero(st == HOLDOFF)),
            "rebaselines_total": int(self._rebaselines.sum()),
            "rebaselined": [[int(i), int(self._rebaselines[i])] for i in hit],
            "holds_total": int(self._holds.sum()),
            "drifting": int(np.count_nonzero(np.isfinite(self._off_since))),
            "common_offset": [float(x) for x in self._common],
            "common_jumps": self._common_jumps,
            "outage_catchups": self._catchups,
            # when, by how much and on how many elements the offset last jumped: a
            # common step or a press over (nearly) the whole skin (None: never)
            "last_common_jump": None if self._last_jump is None else dict(self._last_jump),
        }

    def thresholds(self) -> tuple[FloatArray, FloatArray]:
        """(N, C) enter and leave thresholds in effect (absolute or noise-scaled)."""
        if self._thr is None:
            noise = np.nan_to_num(self._noise, nan=0.0)
            enter = np.maximum(self._enter, self.config.k_enter * noise)
            leave = np.maximum(self._leave, self.config.k_leave * noise)
            self._thr = (enter, np.minimum(leave, enter))
        return self._thr[0].copy(), self._thr[1].copy()

    # -- commands -------------------------------------------------------------------
    def tare(self, elements: ArrayLike | None = None) -> None:
        """Re-take the baseline of the given elements (indices or a bool mask; None: all).

        They go back to collecting and are not ready until ``n_baseline`` new
        readings arrived; whatever touches them meanwhile becomes part of the
        baseline, as the user asked. An empty selection does nothing.
        """
        sel = self._select(elements)
        self._state[sel] = COLLECTING
        self._count[sel] = 0
        self._base[sel] = np.nan
        self._base0[sel] = np.nan
        self._noise[sel] = np.nan
        self._below_since[sel] = np.inf
        self._off_since[sel] = np.inf
        self._thr = None

    def _select(self, elements: ArrayLike | None) -> NDArray[np.bool_]:
        if elements is None:
            return np.ones(self.n_elements, dtype=bool)
        e = np.asarray(elements)
        if e.dtype == bool:
            if e.shape != (self.n_elements,):
                raise ValueError(f"element mask must have shape ({self.n_elements},)")
            return e.copy()
        if e.size == 0:
            return np.zeros(self.n_elements, dtype=bool)
        if e.dtype.kind not in "iu":
            raise ValueError("elements must be integer indices or a boolean mask")
        e = np.atleast_1d(e)
        if np.any(e < 0) or np.any(e >= self.n_elements):
            raise ValueError(f"element index out of range 0..{self.n_elements - 1}")
        m = np.zeros(self.n_elements, dtype=bool)
        m[e] = True
        return m

    # -- the step -------------------------------------------------------------------
    def update(self, t: float | ArrayLike, values: ArrayLike) -> CalibrationStep:
        """Feed the readings of all elements at time ``t`` (s); NaN = no reading.

        ``values`` is (N, C), or (N,) when there is one channel. ``t`` is a scalar or
        one time per element (NaN for an element without a reading); times must not
        go backwards for any element. Feed one
        vector per sampling period (the latest reading of every element, NaN where
        none came): the common offset is estimated across the elements of one step.
        """
        n, c = self.n_elements, self.n_channels
        v = np.asarray(values, dtype=np.float64)
        if v.shape == (n,) and c == 1:
            v = v[:, None]
        if v.shape != (n, c):
            raise ValueError(f"values must have shape ({n}, {c}), got {v.shape}")
        t_arr = np.asarray(t, dtype=np.float64)
        if self._compiled and t_arr.ndim == 0 and self._kernel_ready():
            done = self.update_compiled(float(t_arr), v)
            if done is not None:
                return done
        sampled = rows_all(np.isfinite(v))
        # NaN is allowed as the time of an element without a reading (as its values);
        # inf never: it would end every hold-off and trip max_touch at once.
        if t_arr.ndim == 0:  # one time for all (the daemon's every step): checked as a number
            t0 = float(t_arr)
            if not math.isfinite(t0):
                raise ValueError("time must be finite (NaN only for an element without a reading)")
            tt = np.full(n, t0)
            if (sampled & (self._last_t > t0)).any():
                raise ValueError("time went backwards for an element")
        else:
            tt = np.broadcast_to(t_arr, (n,))
            if not np.all(np.isfinite(tt) | (np.isnan(tt) & ~sampled)):
                raise ValueError("time must be finite (NaN only for an element without a reading)")
            if np.any(tt[sampled] < self._last_t[sampled]):
                raise ValueError("time went backwards for an element")
        if self._thr is None:
            self.thresholds()
        enter, leave = self._thr  # type: ignore[misc]  # thresholds() has just set _thr
        st = self._state
        _check_unit(v, sampled & (st == COLLECTING), self._enter)
        live = sampled & (st != COLLECTING)  # ready elements with a reading this step
        resid = v - self._base  # NaN where not ready or not sampled
        jumps = self._common_jumps
        ref = self._reference(enter)
        if self.config.common_mode:
            self._update_common(resid, live & ref, enter, tt)
        self._collect(sampled & (st == COLLECTING), v)

        delta = np.where(live[:, None], resid - self._common, np.nan)
        self._catch_up(live & (st == TRACKING), tt, delta)
        # whether a reading is a contact's decides only where a channel is above leave (a touch
        # beginning, an element drifting above its thresholds) or the element is touched (held
        # past max_touch); every other live reading is answered True, as its answer is not read
        with np.errstate(invalid="ignore"):
            asked = live & ((st == TOUCHED) | rows_any(delta > leave))
        contact = self._contact_readings(asked, delta)
        rebased = self._hysteresis(live, tt, delta, enter, leave, contact)
        self._track(live & (st == TRACKING), live, tt, delta, enter, leave, contact)
        if self.config.common_mode:
            self._anchor(ref & (st == TRACKING))
        self._last_t[sampled] = tt[sampled]
        delta[st == COLLECTING] = np.nan  # re-baselined after max_touch: not ready
        return CalibrationStep(delta, st == TOUCHED, st != COLLECTING, self._common_jumps != jumps, rebased)

    def _kernel_ready(self) -> bool:
        """Whether the compiled step is warm in this process (looked up until it is)."""
        if self._kernel is None:
            mod = sys.modules.get("cellbridge.tactile.calibration_kernel")
            if mod is None or not mod.READY:
                return False
            self._kernel = mod
        return True

    def update_compiled(self, t0: float, v: FloatArray) -> CalibrationStep | None:
        """:meth:`update` at one time ``t0`` by the compiled step alone (its module imported):
        None, and nothing changed, where the step is numpy's to take (see ``compiled`` in the
        constructor). :meth:`update` calls it once the kernel is warm. ValueError for readings
        of another shape than :meth:`update` takes (the kernel indexes the state by theirs)."""
        n, c = self.n_elements, self.n_channels
        if np.shape(v) == (n,) and c == 1:
            v = np.asarray(v)[:, None]
        if np.shape(v) != (n, c):
            raise ValueError(f"values must have shape ({n}, {c}), got {np.shape(v)}")
        kern = self._kernel if self._kernel is not None else sys.modules["cellbridge.tactile.calibration_kernel"]
        surface = self.is_contact
        if not math.isfinite(t0) or (surface is not None and (type(surface) is not ContactSurface
                                                              or self.n_channels != 2)):
            return None
        if self._thr is None:
            self.thresholds()
        enter, leave = self._thr  # type: ignore[misc]  # thresholds() has just set _thr
        cfg = self.config
        # the tracker's gains at tau and tau_negative over each element's time since its last
        # reading, by numpy's expm1 (the kernel takes 0 where that time is not finite)
        lag = -(t0 - self._last_t)[:, None]
        if self._frozen:  # tau = inf: -inf / inf (no reading yet) is NaN, and not used
            with np.errstate(invalid="ignore"):
                gains = -np.expm1(lag / self._taus)
        else:
            gains = -np.expm1(lag / self._taus)
        delta = np.empty((n, c))
        out = np.empty((3, n), dtype=bool)
        ages = np.array([self._spread_age, self._anchor_age], dtype=np.int64)
        has = surface is not None
        s = surface if has else None
        try:
            got = kern.step(
                t0, np.ascontiguousarray(v, dtype=np.float64), self._state, self._last_t, self._base, self._base0,
                self._noise, self._since, self._below_since, self._off_since, self._holds, self._rebaselines,
                self._count, enter, leave, self._drift, self._clip, self._common, self._spread, gains, ages,
                # (min_common past the skin's size is never reached, as one beyond 64 bits is not)
                float(cfg.k_enter), min(int(cfg.min_common), n + 1), bool(cfg.common_mode), float(cfg.common_fraction),
                float(cfg.common_spread), float(cfg.tau), float(cfg.holdoff),
                math.inf if cfg.max_touch is None else float(cfg.max_touch), cfg.max_touch is not None,
                float(cfg.negative_after), has, float(s.noise) if s is not None else 0.0,
                float(s.k_sigma) if s is not None else 0.0, float(s.ratio_low) if s is not None else 1.0,
                float(s.ratio_high) if s is not None else 1.0, float(s.dc1_max) if s is not None else 0.0,
                delta, out)
        except TypeError:  # argument types it was not compiled for (and compiles no more): numpy's
            return None
        code, jumped, most, k, catchups, rebased, anchored, r, change = got
        if code != kern.DONE:
            return None
        self._spread_age, self._anchor_age = int(ages[0]), int(ages[1])
        self._catchups += int(catchups)
        if jumped:
            self._common_jumps += 1
            # the jump's own change: an anchoring in the same step moved the offset after it
            self._last_jump = {"t": t0, "offset_change": [float(x) for x in change],
                               "elements": int(most), "tracked": int(k)}
        if rebased:
            self._thr = None
        if anchored:
            col = self._state == COLLECTING
            if col.any():  # collected relative to the offset of their step: re-centre them too (_anchor)
                idx = np.nonzero(col)[0]
                stored = np.arange(cfg.n_baseline)[None, :] < self._count[idx, None]
                self._buf[idx] -= np.where(stored[:, :, None], r, 0.0)
        return CalibrationStep(delta, out[0], out[1], bool(jumped), out[2] if rebased else None)

    def _contact_readings(self, live: NDArray[np.bool_], delta: FloatArray) -> NDArray[np.bool_] | None:
        """(N,) whether each ``live`` element's ΔC is a reading some contact makes (True
        elsewhere); None without ``is_contact``. ``is_contact`` judges each row by itself, so
        asking it of fewer rows changes none of their answers."""
        if self.is_contact is None:
            return None
        ok = np.ones(self.n_elements, dtype=bool)
        if live.any():
            ok[live] = np.asarray(self.is_contact(delta[live], np.nan_to_num(self._noise[live])), dtype=bool)
        return ok

    def _update_common(
        self, resid: FloatArray, trk: NDArray[np.bool_], enter: FloatArray, tt: FloatArray
    ) -> None:
        """The skin's common offset: median residual of the tracked elements that did
        not jump past ±``enter`` — or of all of them when nearly all jumped together
        the same way, and alike.

        Both directions are excluded: with two tracked elements the median is their
        mean, so one element far below the rest (a glitch, a baseline tared under a
        press) would otherwise shift every other element by half its drop. A jump
        that lifts the elements unevenly (a palm: centre ≫ corners) is contacts: taken
        as common it would hide the press, and the fast negative tracker would follow
        the elements left below the offset, which then latch touched on release."""
        k = int(trk.sum())
        if k < self.config.min_common:
            return  # too few to tell drift from touch: the offset is carried
        jump, most, ref = _common_reference(resid - self._common, trk, enter, self.config)
        if int(ref.sum()) >= self.config.min_common:
            new = median0(resid[ref])
            if jump:
                self._common_jumps += 1
                self._last_jump = {
                    "t": float(tt[trk].max()),
                    "offset_change": [float(x) for x in new - self._common],
                    "elements": most,
                    "tracked": k,
                }
            self._common = new

    def _reference(self, enter: FloatArray) -> NDArray[np.bool_]:
        """(N,) the elements whose readings tell the skin's drift: tracked, and not
        drifting by themselves — or every tracked element when fewer than
        ``min_common`` of the skin are that steady.

        Drifting by itself: reading above ``enter`` what no contact gives, or an own
        drift (since the element's baseline was taken) that stands out from the other
        tracked elements' by more than ``enter`` (or ``k_enter`` times their spread, so a
        skin whose elements all wander apart over days keeps them all). Such an element
        is followed with a lag (up to ``enter`` on the clipped tracker): in a step where
        few elements report, a median of two is their mean, and that lag moved the
        offset of the whole skin by half of it for the step (25 fF on a press's ΔC2, in
        one of every 20 steps)."""
        trk = self._state == TRACKING
        if int(trk.sum()) < self.config.min_common:
            return trk
        own = np.abs(self._base - self._base0)  # about zero, where the anchor keeps their median
        if self._spread_age <= 0:  # the spread moves slowly: a median now and then is enough
            self._spread = 1.4826 * median0(own[trk])
            self._spread_age = _SPREAD_EVERY
        self._spread_age -= 1
        with np.errstate(invalid="ignore"):  # NaN own drift: not ready, and not tracked
            steady = trk & rows_all(own <= np.maximum(enter, self.config.k_enter * self._spread))
        steady &= ~np.isfinite(self._off_since)
        return steady if int(steady.sum()) >= self.config.min_common else trk

    def _anchor(self, ref: NDArray[np.bool_]) -> None:
        """Keep the tracked elements' own drift centred on zero: their median is the
        skin's, and belongs in the common offset.

        The common offset and the elements' own baselines are only known through their
        sum: each step the offset is the median residual against the tracked baselines,
        and the trackers then follow what is left. An offset estimate biased by ε (one
        element's tracker lagging its own drift is enough: a step's median of few
        elements, or one outlier on one side of the median) pulls every tracked
        baseline down by α·ε, which lifts the next median: the offset ratchets by about
        ε/tau per second with no restoring force. Tracked elements do not mind (their
        sum stays right), but a touched element carries the offset on a frozen
        baseline, so a press held for an hour read 10 % low on ΔC2. Moving the median
        own drift of the tracked elements back into the offset (their sums unchanged),
        every ``_ANCHOR_EVERY`` steps (what builds up between: far below a fF), removes
        the ratchet: what a touched element carries is then what the tracked
        elements moved together since their baselines were taken. Elements drifting by
        themselves are left out of the median (``ref``: :meth:`_reference`, still
        tracked after this step).
        """
        self._anchor_age -= 1
        if self._anchor_age > 0 or int(ref.sum()) < self.config.min_common:
            return
        self._anchor_age = _ANCHOR_EVERY
        r = median0(self._base[ref] - self._base0[ref])
        if not np.any(r):
            return
        self._base -= np.where((self._state == TRACKING)[:, None], r, 0.0)
        self._common += r
        col = self._state == COLLECTING
        if col.any():  # collected relative to the offset of their step: re-centre them too
            idx = np.nonzero(col)[0]
            stored = np.arange(self.config.n_baseline)[None, :] < self._count[idx, None]
            self._buf[idx] -= np.where(stored[:, :, None], r, 0.0)

    def _collect(self, col: NDArray[np.bool_], v: FloatArray) -> None:
        """Baseline collection (relative to the common offset of each reading's step)."""
        if not col.any():
            return
        cfg = self.config
        idx = np.nonzero(col)[0]
        self._buf[idx, self._count[idx]] = v[idx] - self._common
        self._count[idx] += 1
        done = idx[self._count[idx] >= cfg.n_baseline]
        if done.size:
            b = self._buf[done]
            med = np.median(b, axis=1)
            self._base[done] = med
            self._base0[done] = med
            self._noise[done] = 1.4826 * np.median(np.abs(b - med[:, None, :]), axis=1)
            self._state[done] = TRACKING
            self._count[done] = 0
            self._thr = None

    def _catch_up(self, trk: NDArray[np.bool_], tt: FloatArray, delta: FloatArray) -> None:
        """An element back from a silence longer than ``tau`` takes its reading as
        baseline if the change fits the drift allowed over the gap (``max_drift`` per
        second of it, every channel); otherwise nothing moves and the change is a touch.

        Without this the tracker's per-step clip (±max_drift·tau) would cap the
        catch-up after hours of silence at 10 fF, and an element's own drift over
        those hours came back as a touch held for ``max_touch``. A press that appeared
        during the gap and fits the allowance is absorbed, as one rising that slowly
        would be; each catch-up is counted (``health()["outage_catchups"]``).
        """
        gap = tt - self._last_t  # NaN or inf where not tracked: compares False / is masked
        back = trk & (gap > self.config.tau)
        if not back.any():
            return
        idx = np.nonzero(back)[0]  # tracked: sampled before, so the gap is finite
        fit = idx[rows_all(np.abs(delta[idx]) <= self._drift * gap[idx, None])]
        if fit.size:
            self._base[fit] += delta[fit]
            delta[fit] = 0.0
            self._catchups += int(fit.size)

    def _hysteresis(
        self, live: NDArray[np.bool_], tt: FloatArray, delta: FloatArray,
        enter: FloatArray, leave: FloatArray, contact: NDArray[np.bool_] | None,
    ) -> NDArray[np.bool_] | None:
        """Touch state changes; the elements re-baselined after ``max_touch`` (or None)."""
        cfg = self.config
        st = self._state
        up = live & (st != TOUCHED) & rows_any(delta > enter)
        if contact is not None:
            up &= contact  # above enter, but no contact's reading: drift, never a touch
        down = live & (st == TOUCHED) & rows_all(delta < leave)
        st[up] = TOUCHED
        self._since[up] = tt[up]
        st[down] = HOLDOFF
        self._since[down] = tt[down]
        back = (st == HOLDOFF) & (tt - self._since >= cfg.holdoff)
        st[back] = TRACKING
        if cfg.max_touch is None:
            return None
        stuck = (st == TOUCHED) & (tt - self._since >= cfg.max_touch)
        if contact is not None:
            # judged on a reading of its own: a silent element waits for its next one
            stuck &= live
            held = stuck & contact
            self._holds[held] += 1
            self._since[held] = tt[held]  # a press held this long: keep it, look again later
            stuck &= ~contact
        if not stuck.any():
            return None
        self._rebaselines[stuck] += 1
        self.tare(stuck)
        return stuck

    def _track(
        self, trk: NDArray[np.bool_], live: NDArray[np.bool_], tt: FloatArray,
        delta: FloatArray, enter: FloatArray, leave: FloatArray, contact: NDArray[np.bool_] | None,
    ) -> None:
        """Element drift: clipped exponential tracker, unclipped and faster on a
        channel that has stayed below −enter for ``negative_after`` seconds, and on
        every channel of an element that has read above ``enter`` what no contact
        gives for as long (a missing reading neither restarts nor ends either wait);
        followed so until it is back below ``leave`` (or reads a contact's reading), so
        a steady drift is followed closely, not held at ``enter``."""
        cfg = self.config
        # (An idle skin has no element below -enter nor drifting above enter: each rule's
        # arrays are then what the rule leaves, and are not built; the same numbers.)
        below = trk[:, None] & (delta < -enter)
        since = np.where(live[:, None], np.inf, self._below_since)
        fast: NDArray[np.bool_] | None = None  # None: no channel is followed fast
        if below.any():
            self._below_since = np.where(below, np.minimum(self._below_since, tt[:, None]), since)
            fast = below & (tt[:, None] - self._below_since >= cfg.negative_after)
        else:
            self._below_since = since
        if contact is not None:
            following = tt - self._off_since >= cfg.negative_after
            off = trk & ~contact & (rows_any(delta > enter) | (following & rows_any(delta > leave)))
            kept = np.where(live, np.inf, self._off_since)
            if off.any():
                self._off_since = np.where(off, np.minimum(self._off_since, tt), kept)
                drifted = (off & (tt - self._off_since >= cfg.negative_after))[:, None]
                fast = drifted if fast is None else fast | drifted
            else:
                self._off_since = kept
        if not trk.any():
            return
        dt = tt - self._last_t
        dt = np.where(trk & np.isfinite(dt), dt, 0.0)  # first tracked reading: no step
        clipped = np.minimum(np.maximum(delta, -self._clip), self._clip)  # (np.clip, unwrapped)
        if fast is None or not fast.any():
            alpha = -np.expm1(-dt[:, None] / cfg.tau)
            innov = clipped
        else:
            alpha = -np.expm1(-dt[:, None] / np.where(fast, cfg.tau_negative, cfg.tau))
            innov = np.where(fast, delta, clipped)
        self._base += np.where(trk[:, None], alpha * innov, 0.0)
