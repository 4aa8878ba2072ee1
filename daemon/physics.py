"""The daemon's one adapter to :mod:`cellbridge.tactile`: readings → capacitance → ΔC → (F, S) → contacts.

All uses of the tactile layer (transfer functions, Calibrator, the inverse, the contact
estimator, layouts) sit here, vectorised over the samples of a batch, so the rest of
the daemon never depends on that layer's internals and a change there stays local.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cellbridge.tactile import (
    CalibrationConfig,
    Calibrator,
    ChipParams,
    ContactEstimator,
    ElementParams,
    SkinLayout,
    adc_mean_code,
    counts_to_capacitance,
    expected_counts,
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

    def capacitance(self, mode: NDArray[np.int64], over: NDArray[np.int64], raw: NDArray[np.int64],
                    flags: NDArray[np.int64], channel: int, gate: FloatArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """(C in F, saturated) of one channel for every row. Saturated: counter overflow
        with no plausible unwrap, a dead oscillator, or an ADC mean at a rail."""
        out = np.empty(raw.shape)
        sat = np.zeros(raw.shape, dtype=bool)
        adc = mode == ADC_MODE
        cnt = ~adc
        if cnt.any():
            ratio = self.chip.gate_cycles / gate[cnt]
            r = raw[cnt]
            r = np.clip(r, 0, self.chip.counter_modulus - 1)
            ov = (flags[cnt] & (_OVERFLOW_C1 if channel == 0 else _OVERFLOW_C2)) != 0
            n = unwrap_counts(r, self._nominal[channel] / ratio, self.chip, ov)
            out[cnt] = counts_to_capacitance(n * ratio, self.chip)
            sat[cnt] = n <= 0
        if adc.any():
            mean = raw[adc] / over[adc]
            c = np.interp(mean, self._adc_means, self._adc_caps)
            rail = (mean <= 0) | (mean >= self._adc_top)
            out[adc] = np.where(rail, np.nan, c)
            sat[adc] = rail
        return out, sat


def calibration_config(section: dict[str, Any]) -> CalibrationConfig:
    keys = ("n_baseline", "enter", "leave", "k_enter", "k_leave", "holdoff", "tau", "tau_negative")
    return CalibrationConfig(**{k: section[k] for k in keys})


class ElementStage:
    """Calibration and inverse for the elements of one layout, a batch at a time.

    The Calibrator steps once per sampling slot in the batch (at most ``MAX_STEPS``
    times); every sample of the batch gets ΔC against the baseline after the last
    step, and the inverse runs on all of them in one call.
    """

    MAX_STEPS = 8

    def __init__(self, layout: SkinLayout, params: ElementParams, cal: CalibrationConfig, noise: float) -> None:
        self.layout = layout
        self.params = params
        self.noise = noise
        self.calibrator = Calibrator(layout.n, 2, cal)
        self.latest = np.full((layout.n, 2), np.nan)  # newest ΔC per element, for contact estimation
        self.touched = np.zeros(layout.n, dtype=bool)
        self._t = -math.inf

    def step(self, rows: NDArray[np.int64], caps: FloatArray, now: float) -> dict[str, FloatArray]:
        """``rows``: layout row of each sample (all valid); ``caps``: (n, 2) farads."""
        self._t = max(self._t, now)  # the Calibrator needs times that never go backwards
        for values in self._sub_steps(rows, caps):
            st = self.calibrator.update(self._t, values)
            fresh = np.all(np.isfinite(st.delta), axis=1)
            self.latest[fresh] = st.delta[fresh]
        self.latest[~st.ready] = np.nan
        base = self.calibrator.baseline
        delta = caps - base[rows]
        self.touched = st.touched
        inv = solve(delta[:, 0], delta[:, 1], self.params, noise=self.noise)
        return {
            "dc1": delta[:, 0], "dc2": delta[:, 1], "force": inv.force, "area": inv.area,
            "valid": inv.valid, "status": inv.status, "touched": st.touched[rows],
        }

    def _sub_steps(self, rows: NDArray[np.int64], caps: FloatArray) -> list[FloatArray]:
        """(n, 2) readings per Calibrator step: the k-th step holds each element's k-th
        sample of the batch. A batch that holds many samples per element (a backlog)
        is thinned to ``MAX_STEPS`` evenly spaced steps, so its cost stays bounded while
        baselines still collect several readings from it."""
        order = np.argsort(rows, kind="stable")
        r = rows[order]
        starts = np.r_[0, np.nonzero(r[1:] != r[:-1])[0] + 1]
        lengths = np.diff(np.r_[starts, r.size])
        occ = np.empty(rows.size, dtype=np.int64)
        occ[order] = np.arange(r.size) - np.repeat(starts, lengths)
        top = int(lengths.max())
        ks = np.arange(top) if top <= self.MAX_STEPS else np.unique(np.linspace(0, top - 1, self.MAX_STEPS).round())
        out = []
        for k in ks.astype(np.int64):
            sel = occ == k
            values = np.full((self.layout.n, 2), np.nan)
            values[rows[sel]] = caps[sel]
            out.append(values)
        return out

    def tare(self, rows: NDArray[np.int64] | None) -> None:
        self.calibrator.tare(rows)
        sel = slice(None) if rows is None else rows
        self.latest[sel] = np.nan


@dataclass(frozen=True)
class ContactSnapshot:
    """What contact estimation needs of one moment; copied so the estimator may run in a thread."""

    dc: FloatArray  # (n, 2)
    touched: NDArray[np.bool_]
    t_host: float
    t_sample: FloatArray  # (n,) host time of each element's newest sample (NaN: none)
    cycle: NDArray[np.uint64]  # (n,) its bridge cycle count
    ids: NDArray[np.int64]  # (n,) the layout's element (bridge) ids


class ContactStage:
    """The contact estimator for one layout; ``run`` is thread-safe on its snapshot."""

    def __init__(self, layout: SkinLayout, params: ElementParams, noise: float, method: str) -> None:
        self.layout = layout
        self.estimator = ContactEstimator(layout, params, noise=noise, method=method)  # type: ignore[arg-type]

    def run(self, snap: ContactSnapshot) -> list[dict[str, Any]]:
        if not snap.touched.any():
            return []
        contacts = self.estimator.estimate(snap.dc[:, 0], snap.dc[:, 1], active=snap.touched)
        return [_finite(c.to_dict()) for c in contacts]


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
