"""Contacts from one skin frame: what a contact estimate needs (snapshot, spec, job),
and the estimator and tracker it runs, in the contact worker's process or inline.

The worker builds its estimator from a :class:`ContactSpec` and keeps it (with its
tracks) per owner while the spec stays the same. What crosses to the worker is an
:class:`EstimateRequest`: the readings of one frame the estimator reads, and the spec only
while the worker has not built it (else its digest alone): on a humanoid's 1 144 elements a
whole job pickled to about 80 kB, more than a pipe holds, and the request to about 21 kB.

**Never a confident wrong contact.** Where a contact's elements or their neighbours are
unknown in the frame, the contact lists them (``unknown_near``), and where the known
readings do not pin it, its uncertainty covers every position and force the unknown ones
leave open (:func:`bound_by_unknown`), instead of reporting the fit of the known share
alone (a seam press with one side unknown was reported at the other side's centre with
half its force, σ_F 4 mN)."""

from __future__ import annotations

import gc
import hashlib
import itertools
import math
import os
import pickle
from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from cellbridge.daemon.core.config import ContactSection
from cellbridge.daemon.core.elements import default_params
from cellbridge.tactile import (
    ContactEstimator,
    ContactTracker,
    ElementParams,
    SkinLayout,
    grid_layout,
    skin_response,
)
from cellbridge.tactile.arrays import FloatArray
from cellbridge.tactile.disk_model import element_vector, sensitivity_slope
from cellbridge.tactile.seam_estimator import SeamEstimator
from cellbridge.tactile.skin_geometry import Band, SkinGeometry
from numpy.typing import NDArray


@dataclass(frozen=True)
class ContactSnapshot:
    """What contact estimation needs of one moment; copied so the estimator may run in a thread."""

    dc: FloatArray  # (n, 2) each element's ΔC in the frame (see daemon.readings)
    touched: NDArray[np.bool_]
    t_host: float
    t_sample: FloatArray  # (n,) host time of each element's sample used (NaN: none)
    cycle: NDArray[np.uint64]  # (n,) its cycle count (a scheduled sample's: its frame's global cycle)
    ids: NDArray[np.int64]  # (n,) the layout's element (bridge) ids
    t_frame: float  # host time of the skin frame estimated (its gates' start)
    unknown: NDArray[np.bool_] | None = None  # (n,) elements with no reading of this frame (None: all known)


@dataclass(frozen=True)
class ContactSpec:
    """Everything a contact estimator is built from: small, picklable and hashable, so a
    worker process can build (and keep) its own estimator for the current layout.

    ``ids`` and ``centres`` are the layout's element ids and centres as the bytes of int64
    and (n, 2) float64 arrays: every job carries the spec, and a humanoid's 1 144 centres
    as tuples of Python floats took 0.2 ms a job to pickle, unpickle and compare (as bytes,
    microseconds)."""

    ids: bytes
    centres: bytes
    side: float
    neighbour_gap: float
    noise: float
    method: str
    birth_frames: int = 1
    max_missed: int = 2
    bands: tuple[Band, ...] = ()  # the layout's bands that close on themselves (a skin description's)

    @classmethod
    def of(cls, layout: SkinLayout, noise: float, contact: ContactSection) -> ContactSpec:
        return cls(np.ascontiguousarray(layout.ids, dtype=np.int64).tobytes(),
                   np.ascontiguousarray(layout.centres[:, :2], dtype=np.float64).tobytes(),
                   layout.side, float(layout.neighbour_gap), noise, contact.method,  # type: ignore[arg-type]  # one of the estimator's methods: the config checks it
                   contact.birth_frames, contact.max_missed)

    def digest(self) -> bytes:
        """16 bytes that name this spec across processes: an estimate request whose worker
        has built the spec carries them instead of the spec (:class:`EstimateRequest`)."""
        return hashlib.blake2b(pickle.dumps((self.ids, self.centres, self.side, self.neighbour_gap, self.noise,
                                             self.method, self.birth_frames, self.max_missed, self.bands)),
                               digest_size=16).digest()

    def check(self) -> int:
        """The count of elements. Raises ValueError, saying which, for bytes that are not
        whole int64 ids and (x, y) float64 centres, one centre an id (a truncated spec, or
        arrays of another dtype read as these)."""
        if not isinstance(self.ids, bytes) or not isinstance(self.centres, bytes):
            raise ValueError(f"contact spec: ids and centres must be bytes, got {type(self.ids).__name__} "
                             f"and {type(self.centres).__name__}")
        if len(self.ids) % 8:
            raise ValueError(f"contact spec: ids are {len(self.ids)} bytes, not whole int64 ids")
        if len(self.centres) % 16:
            raise ValueError(f"contact spec: centres are {len(self.centres)} bytes, not whole (x, y) float64 pairs")
        n, m = len(self.ids) // 8, len(self.centres) // 16
        if n != m:
            raise ValueError(f"contact spec: {n} ids and {m} centres")
        return n

    def build(self) -> ContactStage:
        """The estimator of this spec. Raises ValueError, saying which, for bytes that
        :meth:`check` refuses or that make no layout (SkinLayout's checks)."""
        self.check()
        layout = SkinLayout(np.frombuffer(self.centres, dtype=np.float64).reshape(-1, 2).copy(), side=self.side,
                            ids=np.frombuffer(self.ids, dtype=np.int64).copy(),
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
    # The skin description the spec's layout is the atlas of (None: a flat layout): its
    # contacts are placed on it, whatever a reload installed while they were estimated.
    surface: SkinGeometry | None = None

    def request(self, key: bytes, ship: bool) -> EstimateRequest:
        """What the worker needs of this job: ``key`` is the spec's :meth:`ContactSpec.digest`,
        and the spec itself goes along when ``ship`` (the worker may not have built it).
        Raises ValueError when the snapshot is of other elements than the spec's (contacts are
        named by the spec's ids, and the host looks them up in the snapshot's), or a spec
        that :meth:`ContactSpec.check` refuses."""
        snap = self.snapshot
        n = self.spec.check()
        ids = np.ascontiguousarray(snap.ids, dtype=np.int64)
        if ids.size != n or ids.tobytes() != self.spec.ids:
            raise ValueError(f"contact job: the snapshot's {ids.size} elements are not its spec's {n}")
        return EstimateRequest(self.owner, key, self.spec if ship else None, snap.dc, snap.touched, snap.t_host,
                               snap.t_frame, snap.unknown, self.first_id, self.carry)


@dataclass(frozen=True)
class EstimateRequest:
    """One estimate, as it crosses to the contact worker: the readings of one frame that the
    estimator reads (not the sample times, cycle counts and ids the host keeps to publish
    the contacts), and its estimator's spec by ``key`` (its digest), with the spec itself
    only when the worker may not have built it (``spec`` None: the worker's own)."""

    owner: str
    key: bytes
    spec: ContactSpec | None
    dc: FloatArray  # (n, 2) as ContactSnapshot
    touched: NDArray[np.bool_]
    t_host: float
    t_frame: float
    unknown: NDArray[np.bool_] | None
    first_id: int
    carry: tuple[dict[str, Any], ...]


class SpecNeeded(LookupError):
    """The worker has no estimator under a request's key (a replaced worker, or one that
    dropped the owner's): the request is to be sent again with its spec."""


_OWNERS = itertools.count()


class ContactIdentity:
    """The host's side of contact identity: the ids the worker's tracker gives are kept here.

    The tracker (in the worker, :func:`estimate`) numbers contacts and follows them from
    frame to frame; it may be built afresh (a new layout or settings, a replaced worker
    process), and then it continues from what this holds: the lowest id never published
    (ids never go back) and the contacts last published (a held press keeps its id).
    ``owner`` names this pipeline's tracks apart from any other's in the same worker."""

    def __init__(self) -> None:
        self.owner = f"{os.getpid()}.{next(_OWNERS)}"
        self._first_id = 0
        self._carry: tuple[dict[str, Any], ...] = ()
        self._index: tuple[object, dict[int, int]] = (None, {})  # (a layout's ids, id -> row): kept while they are

    def job(self, spec: ContactSpec, snapshot: ContactSnapshot, surface: SkinGeometry | None = None) -> ContactJob:
        """The estimate of ``snapshot`` on ``spec`` (the atlas of ``surface``, when it is a
        skin description's), continuing the contacts published."""
        return ContactJob(self.owner, spec, snapshot, self._first_id, self._carry, surface)

    def published(self, job: ContactJob, contacts: Iterable[dict[str, Any]],
                  wall: Callable[[float | None], float | None]) -> list[dict[str, Any]]:
        """The worker's ``contacts`` of ``job`` are published: they are the ones to continue.
        Returns each (copied) with the cycle count of each of its elements' readings
        (``cycles``) and the newest of their sample times (``t_sample``), its times moved to
        the wall clock by ``wall``."""
        snap = job.snapshot
        contacts = list(contacts)
        self._carry = tuple(contacts)
        if contacts and self._index[0] is not snap.ids:  # (the layout's ids: one array while it stands)
            self._index = (snap.ids, dict(zip(snap.ids.tolist(), range(len(snap.ids)))))
        index = self._index[1]
        out = []
        for c in contacts:
            if isinstance(c.get("id"), int):  # ids never go back, whatever rebuilt the tracker
                self._first_id = max(self._first_id, c["id"] + 1)
            rows = [index[e] for e in c["elements"]]
            ts = [float(snap.t_sample[i]) for i in rows if math.isfinite(snap.t_sample[i])]
            out.append({**c, "t": wall(c.get("t")), "cycles": [int(snap.cycle[i]) for i in rows],
                        "t_sample": wall(max(ts)) if ts else None})
        return out


#: The estimator each owner's requests run on, with its spec and the spec's digest, built
#: once per spec: in the worker process (or the caller's, with an inline executor). A few
#: owners at most are kept.
_STAGES: OrderedDict[str, tuple[ContactSpec, bytes, ContactStage]] = OrderedDict()
_MAX_OWNERS = 8
#: This process is the contact worker's (:func:`in_worker`): only there does building an
#: estimator end in :func:`_settle` (a test or tool estimating inline keeps its collector as it is).
_SETTLE = False


def in_worker() -> None:
    """The contact worker process's first job (``contact_worker.process_pool``): from now on
    the warm-up and every estimator built are kept out of the cyclic collector's full passes."""
    global _SETTLE
    _SETTLE = True


def _settle() -> None:
    """Everything alive now (modules, compiled kernels, the estimators kept) out of the cyclic
    collector's full passes. Over the humanoid's estimator one such pass took about 60 ms of
    the worker's CPU, and one came every several seconds as the tracks' objects aged into
    the oldest generation: a frame's whole latency budget, several times over, stalled. The
    objects are unfrozen and collected first, so what a rebuild left behind (the estimator
    before) is freed, not kept for ever; that one pass is paid once per build."""
    gc.unfreeze()
    gc.collect()
    gc.freeze()


def estimate(req: EstimateRequest) -> list[dict[str, Any]]:
    """The contacts of ``req`` (tracked across its owner's requests): what the contact worker runs.

    The owner's estimator is rebuilt only when the request ships a spec other than the one
    built (or this process has none); the rebuilt tracker continues the contacts the request
    carries. Raises :class:`SpecNeeded` for a request without its spec whose key is not the
    estimator's here; ValueError for a spec that makes no layout (:meth:`ContactSpec.build`)
    or readings of another count of elements than the spec's, or of another shape or dtype
    than the host's (:func:`_check_readings`): refused, not estimated on whatever the bytes
    made."""
    kept = _STAGES.get(req.owner)
    if req.spec is not None:
        if kept is None or kept[0] != req.spec:
            stage = req.spec.build()
            stage.carry(req.carry)
            kept = _STAGES[req.owner] = (req.spec, req.spec.digest(), stage)
            if _SETTLE:
                _settle()
        elif req.key != kept[1] and (digest := req.spec.digest()) != kept[1]:
            # an equal spec of another digest (-0.0 for 0.0): the host asks by that digest from
            # now on, and the one kept refused each of its requests (its own, computed here)
            kept = _STAGES[req.owner] = (req.spec, digest, kept[2])
    elif kept is None or kept[1] != req.key:
        raise SpecNeeded(f"contact worker: no estimator of spec {req.key.hex()} for {req.owner}")
    _STAGES.move_to_end(req.owner)
    while len(_STAGES) > _MAX_OWNERS:
        _STAGES.popitem(last=False)
    stage = kept[2]
    _check_readings(req, stage.layout.n)
    stage.tracker.ids_from(req.first_id)
    return stage.run(req)


def _check_readings(req: EstimateRequest, n: int) -> None:
    """Raises ValueError, saying which, for readings that are not the host's: ``dc`` (n, 2)
    float64, ``touched`` and ``unknown`` (n,) bool. Others were estimated as whatever they
    made (int64 ``unknown`` taken as indices: contacts bounded by other elements than the
    frame's unknown ones; a third column of ΔC ignored); NaN readings are the host's own
    (an element without a reading), and the estimator's to handle."""
    dc = req.dc
    if not isinstance(dc, np.ndarray) or dc.dtype != np.float64 or dc.ndim != 2 or dc.shape[1] != 2:
        raise ValueError(f"contact job: dc must be (n, 2) float64, got {_shape(dc)}")
    if dc.shape[0] != n:
        raise ValueError(f"contact job: the snapshot's {dc.shape[0]} elements are not its spec's {n}")
    for name, flags in (("touched", req.touched), ("unknown", req.unknown)):
        if (flags is not None or name == "touched") and (
                not isinstance(flags, np.ndarray) or flags.dtype != np.bool_ or flags.shape != (n,)):
            raise ValueError(f"contact job: {name} must be ({n},) bool, got {_shape(flags)}")


def _shape(a: object) -> str:
    """``a``'s shape and dtype, or its type: what a refused reading was."""
    return f"{a.shape} {a.dtype}" if isinstance(a, np.ndarray) else type(a).__name__


def warm_up() -> None:
    """Run in the worker at start: imports, and the estimator's compiled kernels loaded by one
    estimate on a small skin, happen before the first touch instead of delaying it."""
    layout = grid_layout(2, 2)
    dc1, dc2 = skin_response(layout, [(0.02, 0.0, 1.0, 0.012)])
    touched = dc1 > 1e-13
    stage = ContactStage(layout, default_params(layout), 2e-15, "capacitance", birth_frames=1)
    stage.run(EstimateRequest("warm-up", b"", None, np.stack([dc1, dc2], axis=1), touched, 0.0, 0.0, None, 0, ()))
    # The one kernel Python calls by itself, which this press does not reach: an element's
    # sensitivity at a pressure, for each disk's share when two disks in one cluster are
    # split in two contacts, and for every cluster's weight with the area method. Loaded
    # by the first such estimate, it cost it 5-6 ms of CPU (a cache load; 5-69 ms wall).
    par = element_vector(default_params(layout))
    sensitivity_slope(1.0, *par[:4])  # (float64 x 5: as FitRunner.g calls it)
    if _SETTLE:
        _settle()


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
        self._ring = corner_rings(layout)

    def carry(self, contacts: Iterable[dict[str, Any]]) -> int:
        """Continue the contacts a tracker before this one published (a new layout or
        settings, a replaced worker: :meth:`ContactTracker.carry`), each with the elements of
        this layout only; one with none left ended with its layout. Carried whole, a contact
        missed in the next frame was reported with an element the layout no longer has (a
        SIGHUP's layout file without it), and the host, which looks up each element's row
        in the frame, raised in its contact loop and ended it. Returns how many were taken."""
        kept = []
        for c in contacts:
            elements = [e for e in c["elements"] if e in self._row]
            if elements:
                kept.append(c if len(elements) == len(c["elements"]) else {**c, "elements": elements})
        return self.tracker.carry(kept)

    def run(self, snap: EstimateRequest) -> list[dict[str, Any]]:
        if snap.touched.any():
            tracks = self.tracker.update(snap.dc[:, 0], snap.dc[:, 1], snap.touched, snap.t_host, at=snap.t_frame)
        else:  # an empty frame still counts: tracks miss it and end (no contact to be born)
            tracks = self.tracker.step([], snap.t_host, at=snap.t_frame)
        unknown = snap.unknown if snap.unknown is not None else np.zeros(self.layout.n, dtype=bool)
        if unknown.any():
            # a contact that only unknown elements supported is not seen in this frame (not
            # reported), and not missed either: it goes on under its id when they come back,
            # within UNSEEN_FRAMES frames in a row, and ends after that
            gone = self.tracker.end_unsupported({int(i) for i in self.layout.ids[unknown]}, UNSEEN_FRAMES)
            if gone:
                tracks = [tc for tc in tracks if tc.id not in gone]
        if not unknown.any():  # (every reading known: nothing bounds a contact; bound_by_unknown's own answer)
            out = [_finite(tc.to_dict()) for tc in tracks]
            for d in out:
                d["unknown_near"] = []
            return out
        return [bound_by_unknown(_finite(tc.to_dict()), self.layout, self._row, self._ring, unknown)
                for tc in tracks]


def corner_rings(layout: SkinLayout) -> list[NDArray[np.int64]]:
    """Each element's neighbours, corners included: row ``i``'s are the other ends of the
    corner edges ``(i, j)`` in edge order, then of the edges ``(j, i)`` in edge order (what
    ``np.concatenate([e[e[:, 0] == i, 1], e[e[:, 1] == i, 0]])`` gives per row). One stable
    sort of the edges' ends, not two passes over every edge per element: on a humanoid's
    1 144 elements those took 25 ms of the worker's each time it built its estimator (at
    start, at a new layout), and the first press after that waited behind them."""
    e = np.asarray(layout.corner_edges, dtype=np.int64)
    src = np.concatenate([e[:, 0], e[:, 1]])
    dst = np.concatenate([e[:, 1], e[:, 0]])
    order = np.argsort(src, kind="stable")  # (a row's first-half ends before its second half's, each in edge order)
    return np.split(dst[order], np.cumsum(np.bincount(src, minlength=layout.n))[:-1])


#: Frames in a row a contact whose elements are all unknown is held (not reported, not
#: missed) before it ends: 0.25 s at 100 Hz, longer than a lost record or a late gateway.
UNSEEN_FRAMES = 25


def bound_by_unknown(c: dict[str, Any], layout: SkinLayout, row: Mapping[int, int], ring: list[NDArray[np.int64]],
                     unknown: NDArray[np.bool_]) -> dict[str, Any]:
    """``c`` (a contact's ``to_dict``) with ``unknown_near``: the ids of the unknown elements
    among its elements and their neighbours (corners included), sorted. The fit leaves them
    out; where it still pins a coordinate (``observable``: the known readings' cost rises
    either side), the disk is what the known readings say, whatever the unknown ones read.
    Along an axis it does not pin (or with no fitted disk) the press may reach into the
    unknown elements by any amount, so there:

    * the contact may lie anywhere in the bounding box of its elements and those: its
      position is the box's middle along that axis (``observable`` stays False) and σ
      reaches the box's far edges (every position in it within one σ);
    * the force may be larger by the pressure over the unknown elements' whole area, and
      the diameter by as much: σ of each covers that.

    Without unknown neighbours ``c`` is returned as it is (with ``unknown_near`` empty)."""
    rows = np.array([row[e] for e in c["elements"] if e in row], dtype=np.int64)
    if rows.size == 0 or not unknown.any():
        return {**c, "unknown_near": []}
    near = np.unique(np.concatenate([rows, *(ring[r] for r in rows.tolist())]))
    near = near[unknown[near]]
    out = {**c, "unknown_near": [int(layout.ids[i]) for i in near.tolist()]}
    if near.size == 0:
        return out
    b = layout.bounds
    own_lo, own_hi = b[rows, :2].min(axis=0), b[rows, 2:].max(axis=0)
    every = np.concatenate([rows, near])
    lo, hi = b[every, :2].min(axis=0), b[every, 2:].max(axis=0)
    fitted = bool(c.get("valid")) and bool(c.get("fit_ok"))
    seen = [bool(v) for v in c["observable"]]
    pos = [float(c["x"]), float(c["y"])]
    sig = [float(c["sigma_x"]), float(c["sigma_y"])]
    widened = False
    for a in range(2):
        reaches = lo[a] < own_lo[a] - 1e-12 or hi[a] > own_hi[a] + 1e-12  # an unknown element out along a
        if not reaches or (fitted and seen[a] and math.isfinite(pos[a])):
            continue
        pos[a], seen[a], widened = 0.5 * float(lo[a] + hi[a]), False, True
        cover = max(pos[a] - float(lo[a]), float(hi[a]) - pos[a])
        sig[a] = cover if not math.isfinite(sig[a]) else max(sig[a], cover)
    if not widened:
        return out
    out.update(x=pos[0], y=pos[1], sigma_x=sig[0], sigma_y=sig[1], observable=seen, sigma_xy=max(sig),
               cov=[[sig[0] ** 2, 0.0], [0.0, sig[1] ** 2]])
    extra = float(np.prod(b[near, 2:] - b[near, :2], axis=1).sum())  # m² the press may also cover
    pressure, force, diam = c.get("pressure"), c.get("force"), c.get("diameter")
    if isinstance(pressure, float) and math.isfinite(pressure) and isinstance(force, float) and math.isfinite(force):
        s = c.get("sigma_force")
        out["sigma_force"] = max(s, pressure * extra) if isinstance(s, float) and math.isfinite(s) else pressure * extra
    if isinstance(diam, float) and math.isfinite(diam):
        wider = math.sqrt(diam * diam + 4.0 * extra / math.pi) - diam
        s = c.get("sigma_diameter")
        out["sigma_diameter"] = max(s, wider) if isinstance(s, float) and math.isfinite(s) else wider
    return out


def _finite(d: dict[str, Any]) -> dict[str, Any]:
    """``d`` (a fresh ``to_dict``, changed in place) with plain Python floats (msgpack-ready):
    numpy scalars converted. In place, not copied: ten contacts a frame, each copied twice
    more on its way out, were a few per cent of a humanoid frame's estimate."""
    for k, v in d.items():
        if isinstance(v, np.generic):
            d[k] = v.item()  # (a value replaced, no key added: the iteration stays valid)
    return d
