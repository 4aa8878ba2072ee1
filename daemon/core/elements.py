"""Per element, a batch at a time: capacitance → ΔC against a tracked baseline (the
Calibrator), touch state, and (F, S) with a validity flag (the inverse)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from cellbridge.daemon.core.config import CalibrationSection
from cellbridge.tactile import (
    CalibrationConfig,
    Calibrator,
    ContactSurface,
    ElementParams,
    InverseStatus,
    SkinLayout,
    solve,
)
from cellbridge.tactile.arrays import FloatArray, rows_all, rows_any
from numpy.typing import NDArray


def calibration_config(s: CalibrationSection) -> CalibrationConfig:
    return CalibrationConfig(n_baseline=s.n_baseline, enter=s.enter, leave=s.leave, k_enter=s.k_enter,
                             k_leave=s.k_leave, holdoff=s.holdoff, tau=s.tau, tau_negative=s.tau_negative,
                             max_drift=s.max_drift, max_touch=s.max_touch or None)


def default_params(layout: SkinLayout) -> ElementParams:
    return ElementParams(side=layout.side)


@dataclass(frozen=True, slots=True)
class Stepped:
    """What a call's calibrator step decided: the layout rows it classified by their newest
    reading (none when the rate allowed no step), and every element's touch state after it."""

    rows: NDArray[np.int64]
    touched: NDArray[np.bool_]


@dataclass(frozen=True, slots=True)
class Calibrated:
    """One batch through the element stage: per-sample ``columns`` (:meth:`ElementStage.step`),
    what its calibrator step decided, and each sample's ΔC (n, 2) (``columns``' ``dc1`` and
    ``dc2`` are its columns)."""

    columns: dict[str, FloatArray]
    stepped: Stepped
    dc: FloatArray


class ElementStage:
    """Calibration and inverse for the elements of one layout, a batch at a time.

    The Calibrator's baseline, drift and touch state need one step per sampling period,
    not one per serial read: it steps at most ``max_step_rate`` times a second, each
    time on the newest reading of every element since the step before (so no element
    is left out however reads fall). A read holding several samples of an element (a
    backlog) steps on the first ones too: two steps at most, so a large read costs a
    bounded amount while baselines still collect from it. Every sample gets ΔC against
    the current baseline, and the inverse runs on all of a read's samples in one call.

    The calibrator tells a held press from a drifting element by the element's (F, S)
    surface (:class:`ContactSurface` at the inverse's noise): a touch reaching
    ``max_touch`` with a contact's reading is kept; the elements it does re-baseline are
    collected for the next ``contact`` message (:meth:`take_rebaselined`).

    A held reading (event-based reporting, flag ``HELD``) stands for the frames after it:
    its bridge sends again as soon as the element changes. Each step gives the Calibrator
    the newest reading of every element, so a ready element whose newest reading is held
    takes part with that reading while its bridge is live (:meth:`hold_for`: the daemon
    sets the longer of ``tau`` and ``bridge_timeout``; a bridge silent that long is treated
    as silent). A bridge's heartbeat may be longer than ``tau`` (SET_REPORTING allows
    600 s), and ``tau`` shorter than the heartbeat: a reading standing for ``tau`` alone
    lapsed between heartbeats, and the first elements of a press stepped alone again. Without it a step held only the elements
    that changed, the ones under a press, and the Calibrator took their rise, alike on
    all of them, for a common step of the whole skin: the press was cut to a sliver and
    every other element went negative (one came back as a ghost contact).
    """

    def __init__(self, layout: SkinLayout, params: ElementParams, cal: CalibrationConfig, noise: float,
                 max_step_rate: float = 250.0) -> None:
        self.layout = layout
        self.params = params
        self.noise = noise
        self.calibrator = Calibrator(layout.n, 2, cal, is_contact=ContactSurface(params, noise), compiled=True)
        self.rebaselined = np.zeros(layout.n, dtype=bool)  # re-baselined since take_rebaselined()
        self.min_step = 1.0 / max_step_rate
        self.touched = np.zeros(layout.n, dtype=bool)
        self._pending = np.full((layout.n, 2), np.nan)  # newest readings since the last step
        self._pending_rows = np.zeros(layout.n, dtype=bool)
        self._waiting = False  # any of _pending_rows (flush asks with every read)
        self._held = np.full((layout.n, 2), np.nan)  # newest reading of each element, if held
        self._held_at = np.full(layout.n, -math.inf)  # when it came
        self._any_held = False  # a held reading ever came (else none stands: _standing has nothing to do)
        # s a held reading stands after it came (the bridge is live that long): hold_for
        self._hold = cal.tau
        self._none = np.zeros(0, dtype=np.int64)
        self._last_step = -math.inf
        self._t = -math.inf

    def step(self, rows: NDArray[np.int64], caps: FloatArray, groups: tuple[NDArray[np.int64], NDArray[np.int64]],
             now: float, held: NDArray[np.bool_] | None = None, inverse: bool = True) -> Calibrated:
        """``rows``: layout row of each sample; ``caps``: (n, 2) farads; ``groups``: the
        distinct rows and the index of each one's newest sample; ``held``: each sample's
        ``HELD`` flag (None: none is held). Returns the columns ΔC (``dc1``, ``dc2``) and
        ``touched`` of each sample, and with ``inverse`` its force and area (``force``,
        ``area``, ``valid``, ``status``), with what the step (if the rate allowed one)
        decided. Force and area are for ``element`` messages only: a read with touched
        samples spends a third of its time on them (0.4 of 1.2 ms, in-process), and a
        press's contact waits behind the read."""
        self._t = max(self._t, now)  # the Calibrator needs times that never go backwards
        uniq, newest = groups
        # each row once (a skin frame): uniq is rows, and each sample its row's newest
        latest = caps if uniq.shape[0] == rows.shape[0] else caps[newest]
        self._pending[uniq] = latest
        self._pending_rows[uniq] = True
        self._waiting = self._waiting or bool(uniq.shape[0])
        if held is None:
            self._held[uniq] = np.nan
        else:
            self._held[uniq] = np.where(held[newest, None], latest, np.nan)
            self._any_held = self._any_held or bool(held.any())
        self._held_at[uniq] = self._t
        stepped = self._none
        if self._t - self._last_step >= self.min_step:
            early = None
            if uniq.shape[0] != rows.shape[0]:  # several samples per element: also step on the first ones
                first_rows, first = np.unique(rows, return_index=True)
                early = np.full((self.layout.n, 2), np.nan)
                early[first_rows] = caps[first]
            stepped = self._step(early)
        delta = caps - self.calibrator.baseline[rows]  # NaN while an element's baseline is being taken
        out = {"dc1": delta[:, 0], "dc2": delta[:, 1], "touched": self.touched[rows]}
        if inverse:
            out.update(self._inverse(delta))
        return Calibrated(out, Stepped(stepped, self.touched), delta)

    def flush(self, now: float) -> Stepped:
        """Step on the readings still waiting for one, if the rate allows it now (the contact
        snapshot asks: their touch flags are then from them)."""
        self._t = max(self._t, now)
        stepped = self._none
        if self._waiting and self._t - self._last_step >= self.min_step:
            stepped = self._step(None)
        return Stepped(stepped, self.touched)

    def hold_for(self, seconds: float) -> None:
        """How long a held reading stands after it came: as long as its bridge counts as live."""
        self._hold = seconds

    def touched_rows(self) -> NDArray[np.int64]:
        """The layout rows touched as of the last step."""
        return np.flatnonzero(self.touched)

    def thresholds(self) -> tuple[FloatArray, FloatArray]:
        """The calibrator's touch thresholds (:meth:`Calibrator.thresholds`)."""
        return self.calibrator.thresholds()

    def calibration_health(self) -> dict[str, Any]:
        """The calibrator's counters for ``health`` (:meth:`Calibrator.health`)."""
        return self.calibrator.health()

    def not_ready_rows(self) -> NDArray[np.int64]:
        """The layout rows whose baseline is still being taken."""
        return np.flatnonzero(~self.calibrator.ready)

    def _standing(self, values: FloatArray) -> FloatArray:
        """``values`` with the held readings that still stand filled in where an element
        has no new reading (a ready element's only: a baseline is taken from readings)."""
        if not self._any_held:
            return values
        fill = (rows_any(np.isnan(values)) & rows_all(np.isfinite(self._held))
                & (self._t - self._held_at <= self._hold) & self.calibrator.ready)
        if not fill.any():
            return values
        out = values.copy()
        out[fill] = self._held[fill]
        return out

    def _step(self, early: FloatArray | None) -> NDArray[np.int64]:
        """One calibrator step (two with ``early``); the rows it classified."""
        for values in ([self._pending] if early is None else [early, self._pending]):
            values = self._standing(values)
            st = self.calibrator.update(self._t, values)
            if st.rebaselined is not None:
                self.rebaselined |= st.rebaselined
        self.touched = st.touched
        stepped = np.flatnonzero(self._pending_rows)
        self._pending = np.full((self.layout.n, 2), np.nan)
        self._pending_rows[:] = False
        self._waiting = False
        self._last_step = self._t
        return stepped

    def take_rebaselined(self) -> NDArray[np.int64]:
        """Layout rows re-baselined after ``max_touch`` since the last call (each once)."""
        rows = np.flatnonzero(self.rebaselined)
        self.rebaselined[:] = False
        return rows

    def _inverse(self, delta: FloatArray) -> dict[str, FloatArray]:
        """The inverse on the rows that can pass its noise floor; the others are answered
        here as the inverse would (NaN, invalid, BELOW_NOISE or NONFINITE) — a quiet
        skin then costs no call at all, and the call has a large fixed cost."""
        n = delta.shape[0]
        force, area = np.full(n, np.nan), np.full(n, np.nan)
        valid = np.zeros(n, dtype=bool)
        finite = rows_all(np.isfinite(delta))
        status = np.where(finite, int(InverseStatus.BELOW_NOISE), int(InverseStatus.NONFINITE)).astype(np.uint8)
        with np.errstate(invalid="ignore"):
            signal = finite & rows_all(delta > self.noise)  # the inverse asks for k_sigma (3) noise sigmas
        if signal.any():
            inv = solve(delta[signal, 0], delta[signal, 1], self.params, noise=self.noise)
            force[signal], area[signal], valid[signal], status[signal] = inv.force, inv.area, inv.valid, inv.status
        return {"force": force, "area": area, "valid": valid, "status": status}

    def adopt(self, old: ElementStage, rows: NDArray[np.int64], old_rows: NDArray[np.int64]) -> None:
        """Keep the calibration and touch state of elements carried over from ``old``'s layout,
        and their held readings (lost, a press's first elements stepped alone until every
        other element sent again, and were a common step)."""
        self.calibrator.adopt(old.calibrator, rows, old_rows)
        self.touched[rows] = old.touched[old_rows]
        self.rebaselined[rows] = old.rebaselined[old_rows]
        for name in ("_held", "_held_at"):
            getattr(self, name)[rows] = getattr(old, name)[old_rows]
        self._any_held = self._any_held or old._any_held
        self._hold = old._hold
        self._last_step, self._t = old._last_step, old._t

    def tare(self, rows: NDArray[np.int64] | None) -> None:
        self.calibrator.tare(rows)
