"""Contacts from the skin at one moment: what a contact estimate needs (snapshot, spec,
job), and the estimator and tracker it runs, in the contact worker's process or inline.

The worker builds its estimator from a small :class:`ContactSpec` and keeps it (with its
tracks) per owner while the spec stays the same, so the estimate itself only ships the
readings of one moment."""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from cellbridge.daemon.config import ContactSection
from cellbridge.daemon.elements import default_params
from cellbridge.tactile import (
    ContactEstimator,
    ContactTracker,
    ElementParams,
    SkinLayout,
    grid_layout,
    skin_response,
)
from cellbridge.tactile.arrays import FloatArray
from cellbridge.tactile.seam_estimator import SeamEstimator
from cellbridge.tactile.skin_geometry import Band
from numpy.typing import NDArray


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
    again: bool = False  # the frame estimated last, taken again (a late onset of it came: Moments.take)


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
    birth_frames: int = 1
    max_missed: int = 2
    bands: tuple[Band, ...] = ()  # the layout's bands that close on themselves (a skin description's)

    @classmethod
    def of(cls, layout: SkinLayout, noise: float, contact: ContactSection) -> ContactSpec:
        return cls(tuple(int(i) for i in layout.ids), tuple((float(x), float(y)) for x, y in layout.centres),
                   layout.side, float(layout.neighbour_gap), noise, contact.method,  # type: ignore[arg-type]  # one of the estimator's methods: the config checks it
                   contact.birth_frames, contact.max_missed)

    def build(self) -> ContactStage:
        layout = SkinLayout(np.array(self.centres), side=self.side, ids=np.array(self.ids),
                            neighbour_gap=self.neighbour_gap)
        return ContactStage(layout, default_params(layout), self.noise, self.method, self.birth_frames,
                            self.max_missed, self.bands)


@dataclass(frozen=True)
class ContactJob:
    """One contact estimate to run: the skin at one moment and what its estimator is built from.

    ``owner`` names the pipeline that made it: its contacts are tracked (ids, ages) apart
    from any other pipeline's, even when several share a process (tests, tools)."""

    owner: str
    spec: ContactSpec
    snapshot: ContactSnapshot
    first_id: int = 0  # the owner's lowest id never used: a rebuilt tracker numbers from here
    # The owner's contacts last published (as the worker gave them): a tracker built afresh
    # (new layout or settings, a replaced worker) continues them, so a held contact keeps its id.
    carry: tuple[dict[str, Any], ...] = ()


#: The estimator each owner's jobs run on, built once per spec: in the worker process (or
#: the caller's, with an inline executor). A few owners at most are kept.
_STAGES: OrderedDict[str, tuple[ContactSpec, ContactStage]] = OrderedDict()
_MAX_OWNERS = 8


def estimate(job: ContactJob) -> list[dict[str, Any]]:
    """The contacts of ``job`` (tracked across its owner's jobs): what the contact worker runs.

    The owner's estimator is rebuilt only when the spec changed (or this process has none:
    a replaced worker); the rebuilt tracker continues the contacts the job carries."""
    kept = _STAGES.get(job.owner)
    if kept is None or kept[0] != job.spec:
        kept = _STAGES[job.owner] = (job.spec, job.spec.build())
        kept[1].tracker.carry(job.carry)
    _STAGES.move_to_end(job.owner)
    while len(_STAGES) > _MAX_OWNERS:
        _STAGES.popitem(last=False)
    kept[1].tracker.ids_from(job.first_id)
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
                 birth_frames: int = 1, max_missed: int = 2, bands: tuple[Band, ...] = ()) -> None:
        self.layout = layout
        if bands:  # a press across a wrap seam is one contact
            self.estimator: ContactEstimator = SeamEstimator(layout, params, bands=bands, noise=noise, method=method)
        else:
            self.estimator = ContactEstimator(layout, params, noise=noise, method=method)  # type: ignore[arg-type]  # one of the estimator's methods: the config checks it
        self.tracker = ContactTracker(self.estimator, birth_frames=birth_frames, max_missed=max_missed)
        self._row = {int(e): i for i, e in enumerate(layout.ids.tolist())}

    def run(self, snap: ContactSnapshot) -> list[dict[str, Any]]:
        if snap.touched.any():
            # When each known element's reading was taken: a new contact next to another
            # waits until the elements between them were read since the press began (one
            # of them late splits one press in two), while one disk could be both without
            # those readings (see ContactTracker.step)
            read_at = _ReadTimes(self._row, snap.t_sample if snap.unknown is None
                                 else np.where(snap.unknown, np.nan, snap.t_sample))
            tracks = self.tracker.update(snap.dc[:, 0], snap.dc[:, 1], snap.touched, snap.t_host,
                                         at=snap.t_moment, read_at=read_at, again=snap.again)
        else:  # an empty frame still counts: tracks miss it and end (no contact to be born)
            tracks = self.tracker.step([], snap.t_host, at=snap.t_moment, again=snap.again)
        if snap.unknown is not None and snap.unknown.any():
            # a contact that only unknown elements supported is no longer known: it ends
            # now, not after the frames a missed contact is kept through
            gone = self.tracker.end_unsupported({int(i) for i in snap.ids[snap.unknown]})
            if gone:
                tracks = [tc for tc in tracks if tc.id not in gone]
        return [_finite(tc.to_dict()) for tc in tracks]


class _ReadTimes(Mapping[int, float]):
    """Element id → sample time of its reading in a snapshot (NaN: unknown), looked up in
    the snapshot's array: the tracker asks only about the few elements around a new
    contact, so a skin of thousands of elements builds no table per frame."""

    def __init__(self, row: dict[int, int], t: FloatArray) -> None:
        self._row, self._t = row, t

    def __getitem__(self, element: int) -> float:
        return float(self._t[self._row[element]])

    def __iter__(self) -> Iterator[int]:
        return iter(self._row)

    def __len__(self) -> int:
        return len(self._row)


def _finite(d: dict[str, Any]) -> dict[str, Any]:
    """Plain Python floats (msgpack-ready); numpy scalars converted."""
    out = {}
    for k, v in d.items():
        if isinstance(v, np.generic):
            v = v.item()
        out[k] = v
    return out
