"""Contacts across frames: stable ids, a birth only after a contact persists.

A robot wants "finger 3 moved 2 mm", not a fresh list every frame. The tracker
associates each frame's contacts with the tracks of the previous frames, gives a
track an id only once it has been seen in ``birth_frames`` consecutive frames (a
noise spike on one frame is never a contact; a new contact on or next to the elements
of another waits ``split_frames``, and, when the frame says when each element was read,
until the elements between the two have been read since the press began, as long as one
disk could be both without those elements' readings: one press read as two, while one of
its elements' readings is late, is no second contact; nor is
a contact made only of readings a track already used: what a released press leaves
while one element's release reading is late), keeps it through ``max_missed`` frames
without a match (a reading that briefly falls under the touch threshold), and feeds
each track's last disk to the estimator as the start of the next fit.

Association: a contact and a track may match when they share an element, or when
their positions agree within ``gate`` standard deviations per axis, the variance
being both reported variances plus ``motion²`` (how far a contact may move between
frames). An axis the readings do not resolve carries an element-wide σ, so a disk
that slides from inside an element to across a seam (its reported x jumps from the
element's centre to the true position) keeps its id. Pairs are taken greedily:
first a confirmed contact and a contact on its elements, then closest first (a press
read in two for a while and then whole again continues its id, not the split-off's),
distances taken from each track's last fitted contact (a failed fit's centroid, e.g. two
fingers read as one for a frame, is no place of the track's).
Sans-I/O: frames and times go in, tracks come out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any, Mapping, Sequence

import numpy as np
from cellbridge.tactile.contact_result import Contact
from cellbridge.tactile.estimator import ContactEstimator
from cellbridge.tactile.two_disks import SPLIT_DCHI2
from numpy.typing import ArrayLike

__all__ = ["TrackedContact", "ContactTracker"]


@dataclass(frozen=True)
class TrackedContact:
    """One confirmed contact in the current frame.

    ``id`` is stable for the contact's life; ``age`` counts frames since it was
    first seen (including those before its birth), ``missed`` the consecutive frames
    it went unmatched (0: ``contact`` is from this frame; otherwise it is the last
    one seen), ``t`` the time given with the frame that last matched it.
    """

    id: int
    contact: Contact
    age: int
    missed: int
    t: float | None

    def to_dict(self) -> dict[str, object]:
        """Plain dict of Python scalars and lists (msgpack/JSON ready)."""
        return {"id": self.id, "age": self.age, "missed": self.missed, "t": self.t, **self.contact.to_dict()}


@dataclass
class _Track:
    contact: Contact
    first_frame: int
    hits: int = 1
    missed: int = 0
    id: int | None = None  # given at birth
    t: float | None = None
    elements: frozenset[int] = field(default_factory=frozenset)
    need: int = 1  # consecutive frames to be seen in before its birth
    since: float = -math.inf  # instant of its first frame (-inf: not known, e.g. carried over)
    read: dict[int, float] = field(default_factory=dict)  # element -> read time of the reading it last used
    # Its last contact a disk was fitted to (or that is a light touch; or its last contact,
    # if none was): where association looks for it. A failed fit (valid, fit_ok False: no
    # disk explains the cluster, e.g. two presses on one cluster with too few readings to
    # fit two) reports the cluster's centroid, which says nothing about where this is.
    anchor: Contact | None = None
    unseen: int = 0  # consecutive frames in which every element of it was unknown

    def __post_init__(self) -> None:
        if self.anchor is None:
            self.anchor = self.contact


class ContactTracker:
    """Tracks the contacts of successive frames of one skin.

    ``update(dC1, dC2, active, t)`` estimates and tracks one frame;
    ``step(contacts, t)`` tracks contacts estimated elsewhere. Both return the
    confirmed tracks, ordered by id. Counters: ``births``, ``deaths`` (confirmed
    tracks that ended), ``rejected`` (candidates that vanished before their birth,
    e.g. one-frame noise spikes) and ``remnants`` (contacts made only of readings a track
    had already used, taken as that track's: see :meth:`step`).
    """

    def __init__(
        self,
        estimator: ContactEstimator,
        *,
        birth_frames: int = 3,
        max_missed: int = 2,
        gate: float = 3.0,
        motion: float = 0.010,
        split_frames: int = 3,
    ):
        if int(birth_frames) != birth_frames or birth_frames < 1:
            raise ValueError(f"birth_frames must be an integer >= 1, got {birth_frames!r}")
        if int(split_frames) != split_frames or split_frames < 1:
            raise ValueError(f"split_frames must be an integer >= 1, got {split_frames!r}")
        if int(max_missed) != max_missed or max_missed < 0:
            raise ValueError(f"max_missed must be an integer >= 0, got {max_missed!r}")
        if not (math.isfinite(gate) and gate > 0):
            raise ValueError(f"gate must be > 0 standard deviations, got {gate!r}")
        if not (math.isfinite(motion) and motion >= 0):
            raise ValueError(f"motion must be >= 0 m, got {motion!r}")
        self.estimator = estimator
        self.birth_frames = int(birth_frames)
        self.split_frames = int(split_frames)
        lay = estimator.layout
        reach: dict[int, set[int]] = {int(i): {int(i)} for i in lay.ids}
        for a, b in lay.corner_edges.tolist():
            reach[int(lay.ids[a])].add(int(lay.ids[b]))
            reach[int(lay.ids[b])].add(int(lay.ids[a]))
        self._reach = {k: frozenset(v) for k, v in reach.items()}  # each element id and its neighbours
        self.max_missed = int(max_missed)
        self.gate = float(gate)
        self.motion = float(motion)
        self._tracks: list[_Track] = []
        self._next_id = 0
        self._last_t: float | None = None
        self.frame = 0
        self.births = 0
        self.deaths = 0
        self.rejected = 0
        self.remnants = 0
        self._row = {int(e): i for i, e in enumerate(lay.ids.tolist())}
        # the readings of the frame being tracked, when :meth:`update` has them: (ΔC1, ΔC2, active)
        self._frame: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None = None

    # -- public ---------------------------------------------------------------------------
    def ids_from(self, first: int) -> None:
        """Number contacts born from now on from ``first`` at least: a tracker built afresh
        (new layout, new worker process) must never hand out an id its owner already used."""
        self._next_id = max(self._next_id, int(first))

    def carry(self, contacts: Sequence[dict[str, Any]]) -> int:
        """Continue the confirmed contacts a tracker before this one published (``to_dict``
        of each): a tracker built afresh for a new layout, new estimation settings or in a
        replaced worker process takes them as its tracks, so a contact held across the
        rebuild is matched by position (or a shared element id) and keeps its id. Only a
        tracker with no tracks yet takes them; ids count on above every id carried.
        Returns how many were taken."""
        if self._tracks or self.frame:
            return 0
        for d in contacts:
            c = _contact_of(d)
            age = max(1, int(d.get("age", self.birth_frames)))
            self._tracks.append(_Track(c, 1 - age, hits=max(self.birth_frames, age), missed=int(d.get("missed", 0)),
                                       id=int(d["id"]), t=d.get("t"), elements=frozenset(c.elements)))
            self._next_id = max(self._next_id, int(d["id"]) + 1)
        return len(self._tracks)

    def update(
        self, dC1: ArrayLike, dC2: ArrayLike, active: ArrayLike | None = None, t: float | None = None, *,
        at: float | None = None, read_at: Mapping[int, float] | None = None,
    ) -> list[TrackedContact]:
        """Estimate one frame (warm-started from the tracks) and track its contacts
        (``at``, ``read_at``: see :meth:`step`; with the readings at hand, a new contact
        next to another is told from one press read in two by them too)."""
        contacts = self.estimator.estimate(dC1, dC2, active, hints=self.hints())
        self._frame = (np.asarray(dC1, dtype=np.float64), np.asarray(dC2, dtype=np.float64),
                       None if active is None else np.asarray(active, dtype=bool))
        try:
            return self.step(contacts, t, at=at, read_at=read_at)
        finally:
            self._frame = None

    def hints(self) -> np.ndarray:
        """``(x, y, diameter, force)`` of every track's last contact: next frame's starts
        where it is a fitted disk, and where the contacts were (diameter and force NaN for
        a light or unfitted one: the estimator keeps apart what lay apart, even across
        elements with no reading)."""
        rows = [
            (c.x, c.y, c.diameter, c.force)
            if c.valid and c.fit_ok and math.isfinite(c.diameter) and math.isfinite(c.force)
            else (c.x, c.y, math.nan, math.nan)
            for c in (tr.contact for tr in self._tracks)
            if math.isfinite(c.x) and math.isfinite(c.y)
        ]
        return np.array(rows, dtype=np.float64).reshape(-1, 4)

    def step(self, contacts: Sequence[Contact], t: float | None = None, *, at: float | None = None,
             read_at: Mapping[int, float] | None = None) -> list[TrackedContact]:
        """Associate one frame's contacts with the tracks; return the confirmed ones.

        ``t`` (s, optional) must be finite and never go back (as for the calibrator):
        a frame that breaks this is refused with ValueError and changes nothing.

        ``at`` (s, default ``t``): the instant the frame stands for; ``read_at``: when
        each element's reading in this frame was taken (element id → s, on the clock of
        ``at``; unknown elements left out or NaN). Given both, a new contact next to
        another is born only once every known element next to both (not on either) was
        read at or after the instant the earlier of the two was first seen (the earlier
        one is born as it would be alone; the later one waits): a reading
        from before says "untouched" without knowing, and a held reading whose change is
        still on its way (a loaded host, a bridge retried) splits one press in two for
        as long as it is late; from :meth:`update`, only while one disk explains the two
        with those elements' readings left out (two fingers are still two without them).
        Without ``read_at`` only ``split_frames`` applies. Given
        ``read_at``, a contact made only of readings a track already used (the same
        element readings, taken at the same instants) is no new contact either: it
        continues that track, or is dropped when the track matched another contact (a
        released press whose release reading is late on one element).
        """
        if t is not None:
            if not math.isfinite(t):
                raise ValueError(f"t must be a finite time in s, got {t!r}")
            if self._last_t is not None and t < self._last_t:
                raise ValueError(f"t went backwards: {t!r} after {self._last_t!r}")
            self._last_t = float(t)
        self.frame += 1
        pairs = self._associate(contacts)
        dropped = self._remnants(contacts, pairs, read_at)
        matched_t = set()
        matched_c = set(dropped)
        for ti, ci in pairs:
            tr = self._tracks[ti]
            c = contacts[ci]
            prev, tr.contact = tr.contact, c
            tr.hits += 1
            tr.missed = 0
            tr.t = t
            tr.elements = frozenset(c.elements)
            # A failed fit (a pressure, but no disk explains the cluster: two presses in one
            # cluster with too few readings to fit two, each finger's centroid between them)
            # is no place of this contact's, nor are its readings all this contact's: the
            # track is looked for where it was last fitted, and keeps its own readings.
            if _placed(c) or tr.anchor is None or not _placed(tr.anchor):
                tr.anchor = c
                if read_at is not None:
                    tr.read.update({e: read_at.get(e, math.nan) for e in tr.elements})
            elif not _placed(prev) and all(map(math.isfinite, (c.x, c.y, prev.x, prev.y))):
                # failed fits frame after frame (an edge, a palm, two fingers that stay one
                # cluster): the anchor moves as the cluster does, or a sliding one is lost
                # once it has left the elements of its last fit
                a = tr.anchor
                tr.anchor = replace(a, x=a.x + c.x - prev.x, y=a.y + c.y - prev.y)
            matched_t.add(ti)
            matched_c.add(ci)
        keep = []
        for i, tr in enumerate(self._tracks):
            if i not in matched_t:
                tr.missed += 1
                if tr.id is None:
                    self.rejected += 1  # a candidate must persist without a gap
                    continue
                if tr.missed > self.max_missed:
                    self.deaths += 1
                    continue
            keep.append(tr)
        held = frozenset().union(*(tr.elements for tr in keep))
        for ci, c in enumerate(contacts):
            if ci not in matched_c:
                els = frozenset(c.elements)
                # A new contact on or next to the elements of another contact of this frame
                # or of a kept track may be one press read in two: most often a frame with
                # one of its elements' readings late (a corner press on three of its four
                # elements fits no one disk). Such a contact needs ``split_frames`` frames,
                # however small ``birth_frames`` is; one far from the others does not.
                others = held.union(*(contacts[k].elements for k in range(len(contacts)) if k != ci))
                near = frozenset().union(*(self._reach.get(e, frozenset((e,))) for e in els)) & others
                need = max(self.birth_frames, self.split_frames) if near else self.birth_frames
                since = at if at is not None else (t if t is not None else -math.inf)
                read = {} if read_at is None else {e: read_at.get(e, math.nan) for e in els}
                keep.append(_Track(c, self.frame, t=t, elements=els, need=need, since=since, read=read))
        for tr in keep:
            if tr.id is None and tr.hits >= tr.need and not self._unread_between(tr, keep, read_at):
                tr.id = self._next_id
                self._next_id += 1
                self.births += 1
        self._tracks = keep
        out = [
            TrackedContact(tr.id, tr.contact, self.frame - tr.first_frame + 1, tr.missed, tr.t)
            for tr in keep
            if tr.id is not None
        ]
        return sorted(out, key=lambda tc: tc.id)

    def _remnants(self, contacts: Sequence[Contact], pairs: list[tuple[int, int]],
                  read_at: Mapping[int, float] | None) -> set[int]:
        """A contact no track matched, made only of readings one track already used (each
        element's reading taken at the very instant the track last used it), is what is
        left of that track, not a new contact: an element under a released press whose
        release reading is late still holds its touched reading. It continues the track
        when the track is unmatched (appended to ``pairs``), and is dropped when the track
        matched another contact (returned); either way it is counted in ``remnants``."""
        if read_at is None:
            return set()
        used_t = {ti for ti, _ in pairs}
        used_c = {ci for _, ci in pairs}
        dropped: set[int] = set()
        for ci, c in enumerate(contacts):
            if ci in used_c or not c.elements:
                continue
            mine = [
                ti for ti, tr in enumerate(self._tracks)
                if all(math.isfinite(read_at.get(e, math.nan)) and tr.read.get(e) == read_at.get(e) for e in c.elements)
            ]
            if not mine:
                continue
            mine.sort(key=lambda ti: (self._tracks[ti].id is None, ti))  # a confirmed track first
            free = [ti for ti in mine if ti not in used_t]
            if free:
                pairs.append((free[0], ci))
                used_t.add(free[0])
            else:
                dropped.add(ci)
            self.remnants += 1
        return dropped

    def _unread_between(self, tr: _Track, tracks: Sequence[_Track], read_at: Mapping[int, float] | None) -> bool:
        """Whether a known element next to both ``tr`` and another track near it (and on
        neither) was last read before the earlier of the two was first seen, and one press
        could be what the two are: nothing says the press did not reach that element.

        Only the later of the two waits: ``other`` counts when it is born (this frame's
        earlier births included) or a candidate seen before ``tr``. One of a press read in
        two is enough to be born; held back for each other, a first finger with a second
        landing diagonally next to it within its birth frames was no contact at all until
        the elements between were read again (a heartbeat: up to a second).

        With the frame's readings at hand (:meth:`update`), such elements hold the birth
        back only while one disk explains the two contacts' readings with those elements
        left out (:meth:`_one_press`). Two fingers sharing an element have that element's
        whole ring of neighbours "next to both", elements beside the pair as well as between
        them, and an idle element of an event-based skin is read once a heartbeat (1 s):
        the second finger waited for the last of up to six heartbeats, longer than a press."""
        if read_at is None:
            return False
        mine = frozenset().union(*(self._reach.get(e, frozenset((e,))) for e in tr.elements))
        for other in tracks:
            if other is tr or not (mine & other.elements):
                continue
            if other.id is None and other.first_frame >= tr.first_frame:
                continue  # a later (or as old) candidate waits for this one, not this for it
            onset = min(tr.since, other.since)
            if not math.isfinite(onset):
                continue
            theirs = frozenset().union(*(self._reach.get(e, frozenset((e,))) for e in other.elements))
            unread = set()
            for e in (mine & theirs) - tr.elements - other.elements:
                r = read_at.get(e, math.nan)
                if math.isfinite(r) and r < onset - 1e-9:
                    unread.add(e)
            if unread and self._one_press(tr, other, unread):
                return True
        return False

    def _one_press(self, tr: _Track, other: _Track, unread: set[int]) -> bool:
        """Whether one press could be what ``tr`` and ``other`` are, were the ``unread``
        elements' readings (taken before it began, so saying "untouched" without knowing)
        left out: the touched elements of both, estimated again without them, are one
        contact, and either the estimator weighed two disks against it and kept one, or
        (too few readings left for two disks) one disk explains them, its χ² counted with
        the model tolerance as the split test counts it within what that test leaves to
        noise. Without the frame's readings (:meth:`step` called alone), it could."""
        if self._frame is None:
            return True
        c1, c2, active = self._frame
        est = self.estimator
        gone = [self._row[e] for e in unread if e in self._row]
        d1, d2 = c1.copy(), c2.copy()
        d1[gone] = math.nan
        d2[gone] = math.nan
        keep = np.zeros(est.layout.n, dtype=bool)
        keep[[self._row[e] for e in tr.elements | other.elements if e in self._row]] = True
        touched = active if active is not None else (d1 > 3 * est.noise[0]) | (d2 > 3 * est.noise[1])
        keep &= touched & np.isfinite(d1) & np.isfinite(d2)
        if not keep.any():
            return True
        found = est.estimate(d1, d2, keep)
        if len(found) != 1:
            return not found  # still two (or more) contacts without them: no one press
        (c,) = found
        if not (c.valid and math.isfinite(c.chi2)) or (c.dof - 4 >= 2 and int(keep.sum()) >= 2):
            return True  # a touch without a pressure, or one the split test weighed and kept whole
        # χ² in units of the noise and of the model tolerance together, as the split test counts it
        tol = est.model_error * np.array([np.abs(d1[keep]).max(), np.abs(d2[keep]).max()])
        scale = 1.0 / (1.0 + float(np.max(tol / est.noise)) ** 2)
        return c.chi2 * scale <= max(c.dof, 0) + SPLIT_DCHI2

    @property
    def candidates(self) -> int:
        """Tracks seen but not yet born."""
        return sum(tr.id is None for tr in self._tracks)

    def end_unsupported(self, unknown: set[int], hold: int = 0) -> set[int]:
        """Tracks this frame did not match whose elements are all in ``unknown`` (elements
        the host has no reading of): the frame says nothing of them, so it is not counted
        as a miss, for up to ``hold`` such frames in a row (a record lost on its way must
        not end a press and give it a new id when its elements come back); after that
        nothing supports them any more and they end. Returns the ids of the confirmed
        contacts not seen in this frame for that reason, ended or held: neither is
        reported for this frame (ended ids are never given again)."""
        gone: set[int] = set()
        keep = []
        for tr in self._tracks:
            if tr.missed > 0 and tr.elements and tr.elements <= unknown:
                tr.unseen += 1
                if tr.unseen <= hold:
                    tr.missed -= 1  # not a miss: unseen
                    if tr.id is not None:
                        gone.add(tr.id)
                    keep.append(tr)
                    continue
                if tr.id is not None:
                    gone.add(tr.id)
                    self.deaths += 1
                continue
            tr.unseen = 0
            keep.append(tr)
        self._tracks = keep
        return gone

    def reset(self) -> None:
        """Forget every track (ids keep counting up, so an old id never comes back)."""
        self._tracks = []

    # -- association ----------------------------------------------------------------------
    def _distance(self, a: Contact, b: Contact) -> float:
        """Gate units between two positions; inf when either says nothing (a σ or a
        coordinate not finite), so such a contact matches only by a shared element.
        (The rule; :meth:`_associate` computes it for every pair of a frame at once.)"""
        m2 = self.motion * self.motion
        dx = (a.x - b.x) ** 2 / (a.sigma_x**2 + b.sigma_x**2 + m2 + 1e-18)
        dy = (a.y - b.y) ** 2 / (a.sigma_y**2 + b.sigma_y**2 + m2 + 1e-18)
        fin = math.isfinite
        if not (fin(a.sigma_x) and fin(a.sigma_y) and fin(b.sigma_x) and fin(b.sigma_y) and fin(dx) and fin(dy)):
            return math.inf
        return math.sqrt(max(dx, dy))

    def _associate(self, contacts: Sequence[Contact]) -> list[tuple[int, int]]:
        cand = []
        # (the contacts on each element, so a track's shared contacts are one look-up per
        # element of it, not a set intersection per pair)
        on: dict[int, list[int]] = {}
        for ci, c in enumerate(contacts):
            for e in c.elements:
                on.setdefault(e, []).append(ci)
        # (:meth:`_distance` of every pair, each contact's terms taken once: its arithmetic,
        # in its order, without a call and a dozen attribute reads per pair; ten tracks
        # against ten contacts are a hundred pairs a frame)
        m2 = self.motion * self.motion
        gate = self.gate
        fin = math.isfinite
        terms = [(c.x, c.y, c.sigma_x**2, c.sigma_y**2, fin(c.sigma_x) and fin(c.sigma_y)) for c in contacts]
        for ti, tr in enumerate(self._tracks):
            ref = tr.anchor if tr.anchor is not None else tr.contact
            ax, ay, asx, asy, afin = ref.x, ref.y, ref.sigma_x**2, ref.sigma_y**2, fin(ref.sigma_x) and fin(ref.sigma_y)
            sharing = {ci for e in tr.elements for ci in on.get(e, ())}
            unborn = tr.id is None
            for ci, (bx, by, bsx, bsy, bfin) in enumerate(terms):
                dx = (ax - bx) ** 2 / (asx + bsx + m2 + 1e-18)
                dy = (ay - by) ** 2 / (asy + bsy + m2 + 1e-18)
                d = math.sqrt(max(dx, dy)) if afin and bfin and fin(dx) and fin(dy) else math.inf
                shared = ci in sharing
                if d <= gate or shared:
                    # A contact on a confirmed track's elements continues it before any
                    # candidate (a press read in two for a while, then whole again, keeps
                    # its id rather than taking the split-off's); then closest first, and
                    # confirmed tracks first at equal distance.
                    cand.append((not (shared and not unborn), d, unborn, ti, ci))
        cand.sort()
        used_t, used_c, pairs = set(), set(), []
        for _, _, _, ti, ci in cand:
            if ti in used_t or ci in used_c:
                continue
            used_t.add(ti)
            used_c.add(ci)
            pairs.append((ti, ci))
        return pairs


def _placed(c: Contact) -> bool:
    """Whether ``c`` says where its contact is: a fitted disk, or a touch without a pressure
    (located as one); not a failed fit, reported at its cluster's centroid."""
    return c.fit_ok or not c.valid


_CONTACT_FIELDS = tuple(f.name for f in fields(Contact))


def _contact_of(d: dict[str, Any]) -> Contact:
    """The :class:`Contact` a ``to_dict`` (possibly through msgpack) was made of."""
    v = {k: d[k] for k in _CONTACT_FIELDS}
    v["cov"] = tuple(tuple(float(x) for x in row) for row in v["cov"])
    v["elements"] = tuple(int(e) for e in v["elements"])
    v["observable"] = tuple(bool(o) for o in v["observable"])
    return Contact(**v)
