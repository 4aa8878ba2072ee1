"""The daemon's one adapter to :mod:`cellbridge.tactile`: readings → capacitance → ΔC → (F, S) → contacts.

All uses of the tactile layer (transfer functions, Calibrator, the inverse, the contact
estimator, layouts) sit here, vectorised over the samples of a batch, so the rest of
the daemon never depends on that layer's internals and a change there stays local.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellbridge.tactile import (
    CalibrationConfig,
    Calibrator,
    ChipParams,
    ContactEstimator,
    ContactTracker,
    ElementParams,
    InverseStatus,
    SkinLayout,
    adc_mean_code,
    counts_to_capacitance,
    expected_counts,
    grid_layout,
    skin_response,
    solve,
    unwrap_counts,
)

FloatArray = NDArray[np.float64]
_OVERFLOW_C1, _OVERFLOW_C2 = 0x01, 0x02
ADC_MODE = 1  # protocol Mode.ADC; the daemon's wire adapter guarantees the numbering


class Frontend:
    """Counts (counter mode) or summed ADC codes (ADC mode) → capacitances in farads.

    The counter's gate may differ per bridge (SET_GATE): C ∝ gate/count, so a count at
    gate g is converted as the count ``n·g0/g`` at the reference gate g0. ADC means are
    inverted through a dense table of the exact dithered mean-code curve (the
    transfer function's own Newton inversion is exact but far too slow per sample).
    """

    def __init__(self, params: ElementParams, chip: ChipParams) -> None:
        self.chip = chip
        self.rest = np.array([params.C1_rest, params.C2_rest])
        self._nominal = expected_counts(self.rest, chip)  # counts at rest, reference gate
        caps = np.geomspace(0.5e-12, 1e-9, 6000)
        means = adc_mean_code(caps, chip)  # falls as C grows
        order = np.argsort(means, kind="stable")
        self._adc_means, self._adc_caps = means[order], caps[order]
        self._adc_top = chip.adc_levels - 1
        self._ov_bits = np.array([_OVERFLOW_C1, _OVERFLOW_C2])

    def capacitance(self, mode: NDArray[np.int64], over: NDArray[np.int64], raw: NDArray[np.int64],
                    flags: NDArray[np.int64], gate: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """(C in F, saturated), both (n, 2), from (n, 2) raw readings. Saturated: a dead
        oscillator or a counter value no counter can hold, an ADC mean at a rail (C is NaN
        for the impossible and the railed)."""
        adc = mode == ADC_MODE
        if not adc.any():
            return self._counter(raw, flags, gate)
        caps = np.empty(raw.shape)
        sat = np.empty(raw.shape, dtype=bool)
        cnt = ~adc
        if cnt.any():
            caps[cnt], sat[cnt] = self._counter(raw[cnt], flags[cnt], gate[cnt])
        mean = raw[adc] / over[adc][:, None]
        rail = (mean <= 0) | (mean >= self._adc_top)
        caps[adc] = np.where(rail, np.nan, np.interp(mean, self._adc_means, self._adc_caps))
        sat[adc] = rail
        return caps, sat

    def _counter(self, raw: NDArray[np.int64], flags: NDArray[np.int64], gate: FloatArray
                 ) -> tuple[FloatArray, NDArray[np.bool_]]:
        ratio = (self.chip.gate_cycles / gate)[:, None]
        bad = raw >= self.chip.counter_modulus  # only a corrupt reading: the counter has 16 bits
        if bad.any():
            raw = np.where(bad, 0, raw)
        ov = (flags[:, None] & self._ov_bits) != 0
        n = unwrap_counts(raw, self._nominal / ratio, self.chip, ov)
        caps = counts_to_capacitance(n * ratio, self.chip)
        sat = (n <= 0) | bad
        if bad.any():
            caps[bad] = np.nan
        return caps, sat


def calibration_config(section: dict[str, Any]) -> CalibrationConfig:
    keys = ("n_baseline", "enter", "leave", "k_enter", "k_leave", "holdoff", "tau", "tau_negative", "max_drift")
    return CalibrationConfig(**{k: section[k] for k in keys}, max_touch=section["max_touch"] or None)


class ElementStage:
    """Calibration and inverse for the elements of one layout, a batch at a time.

    The Calibrator's baseline, drift and touch state need one step per sampling period,
    not one per serial read: it steps at most ``max_step_rate`` times a second, each
    time on the newest reading of every element since the step before (so no element
    is left out however reads fall). A read holding several samples of an element (a
    backlog) steps on the first ones too: two steps at most, so a large read costs a
    bounded amount while baselines still collect from it. Every sample gets ΔC against
    the current baseline, and the inverse runs on all of a read's samples in one call.
    """

    def __init__(self, layout: SkinLayout, params: ElementParams, cal: CalibrationConfig, noise: float,
                 max_step_rate: float = 250.0) -> None:
        self.layout = layout
        self.params = params
        self.noise = noise
        self.calibrator = Calibrator(layout.n, 2, cal)
        self.min_step = 1.0 / max_step_rate
        self.touched = np.zeros(layout.n, dtype=bool)
        self._pending = np.full((layout.n, 2), np.nan)  # newest readings since the last step
        self._pending_rows = np.zeros(layout.n, dtype=bool)
        self.stepped = np.zeros(0, dtype=np.int64)  # rows the last step classified (their newest reading)
        self._last_step = -math.inf
        self._t = -math.inf

    def step(self, rows: NDArray[np.int64], caps: FloatArray, groups: tuple[NDArray[np.int64], NDArray[np.int64]],
             now: float) -> dict[str, FloatArray]:
        """``rows``: layout row of each sample; ``caps``: (n, 2) farads; ``groups``: the
        distinct rows and the index of each one's newest sample."""
        self._t = max(self._t, now)  # the Calibrator needs times that never go backwards
        uniq, newest = groups
        self._pending[uniq] = caps[newest]
        self._pending_rows[uniq] = True
        self.stepped = self.stepped[:0]
        if self._t - self._last_step >= self.min_step:
            early = None
            if uniq.shape[0] != rows.shape[0]:  # several samples per element: also step on the first ones
                first_rows, first = np.unique(rows, return_index=True)
                early = np.full((self.layout.n, 2), np.nan)
                early[first_rows] = caps[first]
            self._step(early)
        delta = caps - self.calibrator.baseline[rows]  # NaN while an element's baseline is being taken
        out = {"dc1": delta[:, 0], "dc2": delta[:, 1], "touched": self.touched[rows]}
        out.update(self._inverse(delta))
        return out

    def flush(self, now: float) -> NDArray[np.int64]:
        """Step on the readings still waiting for one, if the rate allows it now (the contact
        snapshot asks: their touch flags are then from them). The rows stepped."""
        self._t = max(self._t, now)
        self.stepped = self.stepped[:0]
        if self._pending_rows.any() and self._t - self._last_step >= self.min_step:
            self._step(None)
        return self.stepped

    def _step(self, early: FloatArray | None) -> None:
        for values in ([self._pending] if early is None else [early, self._pending]):
            st = self.calibrator.update(self._t, values)
        self.touched = st.touched
        self.stepped = np.flatnonzero(self._pending_rows)
        self._pending = np.full((self.layout.n, 2), np.nan)
        self._pending_rows[:] = False
        self._last_step = self._t

    def _inverse(self, delta: FloatArray) -> dict[str, FloatArray]:
        """The inverse on the rows that can pass its noise floor; the others are answered
        here as the inverse would (NaN, invalid, BELOW_NOISE or NONFINITE) — a quiet
        skin then costs no call at all, and the call has a large fixed cost."""
        n = delta.shape[0]
        force, area = np.full(n, np.nan), np.full(n, np.nan)
        valid = np.zeros(n, dtype=bool)
        finite = np.isfinite(delta).all(axis=1)
        status = np.where(finite, int(InverseStatus.BELOW_NOISE), int(InverseStatus.NONFINITE)).astype(np.uint8)
        with np.errstate(invalid="ignore"):
            signal = finite & (delta > self.noise).all(axis=1)  # the inverse asks for k_sigma (3) noise sigmas
        if signal.any():
            inv = solve(delta[signal, 0], delta[signal, 1], self.params, noise=self.noise)
            force[signal], area[signal], valid[signal], status[signal] = inv.force, inv.area, inv.valid, inv.status
        return {"force": force, "area": area, "valid": valid, "status": status}

    def adopt(self, old: ElementStage, rows: NDArray[np.int64], old_rows: NDArray[np.int64]) -> None:
        """Keep the calibration and touch state of elements carried over from ``old``'s layout."""
        self.calibrator.adopt(old.calibrator, rows, old_rows)
        self.touched[rows] = old.touched[old_rows]
        self._last_step, self._t = old._last_step, old._t

    def tare(self, rows: NDArray[np.int64] | None) -> None:
        self.calibrator.tare(rows)


@dataclass(frozen=True)
class ContactSnapshot:
    """What contact estimation needs of one moment; copied so the estimator may run in a thread."""

    dc: FloatArray  # (n, 2) each element's ΔC at the moment (see daemon.moment)
    touched: NDArray[np.bool_]
    t_host: float
    t_sample: FloatArray  # (n,) host time of each element's sample used (NaN: none)
    cycle: NDArray[np.uint64]  # (n,) its bridge cycle count
    ids: NDArray[np.int64]  # (n,) the layout's element (bridge) ids
    t_moment: float  # host time the skin is estimated at: every element's reading at or just before it
    unknown: NDArray[np.bool_] | None = None  # (n,) elements with no reading of this frame (None: all known)


@dataclass(frozen=True)
class ContactSpec:
    """Everything a contact estimator is built from: small, picklable and hashable, so a
    worker process can build (and keep) its own estimator for the current layout."""

    ids: tuple[int, ...]
    centres: tuple[tuple[float, float], ...]
    side: float
    neighbour_gap: float
    noise: float
    method: str
    birth_frames: int = 3
    max_missed: int = 2

    @classmethod
    def of(cls, layout: SkinLayout, noise: float, contact: dict[str, Any]) -> ContactSpec:
        return cls(tuple(int(i) for i in layout.ids), tuple((float(x), float(y)) for x, y in layout.centres),
                   layout.side, float(layout.neighbour_gap), noise, contact["method"],  # type: ignore[arg-type]
                   contact["birth_frames"], contact["max_missed"])

    def build(self) -> ContactStage:
        layout = SkinLayout(np.array(self.centres), side=self.side, ids=np.array(self.ids),
                            neighbour_gap=self.neighbour_gap)
        return ContactStage(layout, default_params(layout), self.noise, self.method, self.birth_frames,
                            self.max_missed)


@dataclass(frozen=True)
class ContactJob:
    """One contact estimate to run: the skin at one moment and what its estimator is built from.

    ``owner`` names the pipeline that made it: its contacts are tracked (ids, ages) apart
    from any other pipeline's, even when several share a process (tests, tools)."""

    owner: str
    spec: ContactSpec
    snapshot: ContactSnapshot


#: The estimator each owner's jobs run on, built once per spec: in the worker process (or
#: the caller's, with an inline executor). A few owners at most are kept.
_STAGES: OrderedDict[str, tuple[ContactSpec, ContactStage]] = OrderedDict()
_MAX_OWNERS = 8


def estimate(job: ContactJob) -> list[dict[str, Any]]:
    """The contacts of ``job`` (tracked across its owner's jobs): what the contact worker runs.

    The owner's estimator is rebuilt (its tracks restarted) only when the spec changed."""
    kept = _STAGES.get(job.owner)
    if kept is None or kept[0] != job.spec:
        kept = _STAGES[job.owner] = (job.spec, job.spec.build())
    _STAGES.move_to_end(job.owner)
    while len(_STAGES) > _MAX_OWNERS:
        _STAGES.popitem(last=False)
    return kept[1].run(job.snapshot)


def warm_up() -> None:
    """Run in the worker at start: imports, and the estimator's compiled kernels loaded by one
    estimate on a small skin, happen before the first touch instead of delaying it."""
    layout = grid_layout(2, 2)
    dc1, dc2 = skin_response(layout, [(0.02, 0.0, 1.0, 0.012)])
    touched = dc1 > 1e-13
    stage = ContactStage(layout, default_params(layout), 2e-15, "capacitance", birth_frames=1)
    stage.run(ContactSnapshot(np.stack([dc1, dc2], axis=1), touched, 0.0, np.zeros(layout.n),
                              np.zeros(layout.n, dtype=np.uint64), layout.ids, 0.0))


class ContactStage:
    """Contact estimation and tracking for one layout, one snapshot at a time.

    Contacts keep a stable ``id`` across estimates and are reported only once they have
    persisted ``birth_frames`` estimates (a one-frame spike is no contact); each track's
    last disk warm-starts the next fit.
    """

    def __init__(self, layout: SkinLayout, params: ElementParams, noise: float, method: str,
                 birth_frames: int = 3, max_missed: int = 2) -> None:
        self.layout = layout
        self.estimator = ContactEstimator(layout, params, noise=noise, method=method)  # type: ignore[arg-type]
        self.tracker = ContactTracker(self.estimator, birth_frames=birth_frames, max_missed=max_missed)

    def run(self, snap: ContactSnapshot) -> list[dict[str, Any]]:
        if snap.touched.any():
            tracks = self.tracker.update(snap.dc[:, 0], snap.dc[:, 1], snap.touched, snap.t_host)
        else:  # an empty frame still counts: tracks miss it and end
            tracks = self.tracker.step([], snap.t_host)
        if snap.unknown is not None and snap.unknown.any():
            # a contact that only unknown elements supported is no longer known: it ends
            # now, not after the frames a missed contact is kept through
            gone = self.tracker.end_unsupported({int(i) for i in snap.ids[snap.unknown]})
            if gone:
                tracks = [tc for tc in tracks if tc.id not in gone]
        return [_finite(tc.to_dict()) for tc in tracks]


def _finite(d: dict[str, Any]) -> dict[str, Any]:
    """Plain Python floats (msgpack-ready); numpy scalars converted."""
    out = {}
    for k, v in d.items():
        if isinstance(v, np.generic):
            v = v.item()
        out[k] = v
    return out


def layout_from_geometry(geometry: dict[int, tuple[float, float, float]]) -> tuple[SkinLayout | None, list[int]]:
    """A layout from the bridges' HELLO geometry {bridge: (x, y, side)}.

    Returns (layout, rejected bridges). Elements must share one side length (the layout
    model's); bridges announcing another side, or overlapping an earlier bridge, are
    rejected and reported rather than placed wrongly.
    """
    if not geometry:
        return None, []
    ids = sorted(geometry)
    sides = [geometry[i][2] for i in ids]
    side = max(set(sides), key=sides.count)
    kept: list[int] = []
    rejected = [i for i in ids if not math.isclose(geometry[i][2], side, rel_tol=1e-6)]
    for i in ids:
        if i in rejected:
            continue
        trial = kept + [i]
        try:
            SkinLayout(np.array([geometry[j][:2] for j in trial]), side=side, ids=np.array(trial))
        except ValueError:
            rejected.append(i)
            continue
        kept.append(i)
    if not kept:
        return None, sorted(rejected)
    layout = SkinLayout(np.array([geometry[j][:2] for j in kept]), side=side, ids=np.array(kept))
    return layout, sorted(rejected)


def layout_dict(layout: SkinLayout) -> dict[str, Any]:
    return {"side": layout.side, "ids": layout.ids.tolist(), "x": layout.centres[:, 0].tolist(),
            "y": layout.centres[:, 1].tolist()}


def default_params(layout: SkinLayout) -> ElementParams:
    return ElementParams(side=layout.side)


def chip_params(section: dict[str, Any]) -> ChipParams:
    return ChipParams(clock_hz=section["clock_hz"], gate_cycles=section["gate_cycles"])
