"""The skin's time domains: its parts that share one time root, each with its own frames.

Mesh time is the counter of one bridge, the time root, flooded over the cells
(docs/time.md). Parts of a robot that no cell joins (two limbs, each with its own
gateways) run two unrelated mesh times, each with its own root: frame ``k`` of one has
nothing to do with frame ``k`` of the other. Every READOUT record says whose mesh time
its index counts (its ``root``), so the host keeps, per root, one map of mesh time to host
time (:class:`~cellbridge.daemon.core.clock.SkinClock`) and one frame sequence
(:class:`~cellbridge.daemon.core.frames.SkinFrames`), and a frame speaks for its own root's
elements only (:meth:`~cellbridge.daemon.core.readings.ElementReadings.scheduled`).

A gateway follows one root at a time: a record of another root moves it (the root died
and another took over; frames of the old root no longer wait for it). A line that
carries DATA samples on mesh time teaches the map of the root its gateway's newest record
named (root 0 before any: a skin without the readout has one domain). At most
``max_domains`` roots are followed; a record of another root beyond them is refused
(counted), after forgetting the roots no gateway follows that are quiet (none of their
gateways delivered a record within ``active_for``); when there are none, the quiet roots
followed by a gateway are forgotten: else records corrupted past the
CRC, each naming a root of its own (and a gateway never heard again), filled the table
for as long as their phantom gateways were remembered, and the root a failover moved
to was refused. A domain forgotten keeps its counts in health and gives out the frames
still waiting in it; a gateway coming back to it starts a sequence of its own.

Sans-I/O: fed decoded records, global cycles and host times by the pipeline.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from cellbridge.daemon.core.clock import SkinClock
from cellbridge.daemon.core.frames import RecordPart, SkinFrame, SkinFrames
from numpy.typing import NDArray

#: Roots followed at once: a robot's limbs, with room for failovers and a corrupted root id.
MAX_DOMAINS = 64


#: s without a point of a record that said its age, after which such a point, following
#: points that did not say theirs, begins the map's envelope again (:meth:`SkinClock.anew`).
#: Points of both kinds taught together (a gateway that says its age beside one that does
#: not) leave the envelope to the quicker; a stretch of only the slower ones builds it up.
AGED_GAP = 0.25


class _Domain:
    __slots__ = ("clock", "frames", "aged_at", "unaged", "ages")

    def __init__(self, clock: SkinClock, frames: SkinFrames) -> None:
        self.clock = clock
        self.frames = frames
        self.aged_at = -math.inf  # arrival of the newest point of a record that said its age
        self.unaged = False  # a point that did not say its age was taught since then
        self.ages: dict[int, int] = {}  # gateway -> cycles of age its newest record taken said


class TimeDomains:
    """Per time root, a :class:`SkinClock` and a :class:`SkinFrames`; see the module.

    ``hz``: the bridges' clock rate (cycles of mesh time per second); ``margin``,
    ``active_for``, ``max_pending``: as :class:`SkinFrames` takes them."""

    def __init__(self, hz: float, margin: float = 0.02, active_for: float = 2.0, max_pending: int = 64,
                 max_domains: int = MAX_DOMAINS) -> None:
        self.hz = float(hz)
        self._hz_int = int(self.hz)
        self._settings = (float(margin), float(active_for), int(max_pending))
        self.max_domains = int(max_domains)
        self._domains: dict[int, _Domain] = {}
        self._root_of: dict[int, int] = {}  # gateway -> the root of its newest record
        self.refused = 0  # records of a root beyond max_domains
        self.moves = 0  # gateways that changed root
        self._newest: dict[str, int] | None = None  # the newest frame given out: index, rate, root
        self._retired: dict[str, int] = {}  # the counts of domains forgotten
        self._ready: list[SkinFrame] = []  # their frames still waiting, given out at the next take

    def configure(self, margin: float, active_for: float, max_pending: int) -> None:
        """A reload's settings, for every domain."""
        self._settings = (float(margin), float(active_for), int(max_pending))
        for d in self._domains.values():
            d.frames.configure(*self._settings)

    def _domain(self, root: int, now: float) -> _Domain | None:
        d = self._domains.get(root)
        if d is None:
            if len(self._domains) >= self.max_domains:
                followed = set(self._root_of.values())
                quiet = [r for r, o in self._domains.items() if not o.frames.active(now)]
                for r in [r for r in quiet if r not in followed] or quiet:  # those no gateway follows first
                    self._retire(self._domains.pop(r))
            if len(self._domains) >= self.max_domains:
                return None
            d = self._domains[root] = _Domain(SkinClock(self.hz), SkinFrames(*self._settings, root=root))
        return d

    def _retire(self, d: _Domain) -> None:
        """A domain forgotten: its frames waiting go out at the next take, its counts stay."""
        self._ready.extend(d.frames.take(math.inf))
        for k, v in d.frames.counts.items():
            self._retired[k] = self._retired.get(k, 0) + v

    def root_of(self, gateway: int) -> int:
        """The root of ``gateway``'s newest record (0: none yet)."""
        return self._root_of.get(gateway, 0)

    # -- in ------------------------------------------------------------------------------
    def teach(self, root: int, gateway: int, g: int, now: float) -> bool:
        """A point of ``gateway``'s own on ``root``'s mesh time (global cycle ``g`` reached the
        host at ``now``): :meth:`SkinClock.teach`. True when that map began again."""
        d = self._domain(root, now)
        if d is None:
            return False
        d.unaged = True
        return d.clock.teach(gateway, g, now)

    def record(self, gateway: int, rec: RecordPart, root: int, g: int, now: float,
               serial: float) -> tuple[float, bool]:
        """One record part of ``gateway`` of ``root``'s frame at global cycle ``g`` (-1: a
        nonsense index), arrived at ``now``; ``serial``: s it takes on the line. Its part 0
        teaches the map; the part joins its frame. Returns the frame's host time (NaN: not
        mapped, and the part refused) and whether the map began again (the skin's time
        jumped, confirmed)."""
        d = self._domain(root, now)
        if d is None:
            self.refused += 1
            return math.nan, False
        old = self._root_of.get(gateway)
        if old != root:
            if old is not None:
                if old in self._domains:
                    self._domains[old].frames.forget(gateway)
                d.frames.moved(gateway)  # what it said before is in the old root's frames
                self.moves += 1
            self._root_of[gateway] = root
        t, jumped = math.nan, False
        if g >= 0:
            # the point it teaches: the mesh time the gateway wrote it at, when it says (its
            # age, within its own schedule), else its frame's gate start. Records go as soon as
            # they are complete, so by their frames alone the map put every frame as late as
            # the skin's quickest whole readout (8-9 ms on a 4x4 at 100 Hz), and every
            # contact's time with it.
            w = g + rec.age_us * self._hz_int // 1_000_000 if 0 < rec.age_us <= rec.span_us else g
            if rec.part == 0:
                if w == g:
                    d.unaged = True
                else:  # after a stretch of points that did not say their age: begin again here
                    if d.unaged and now - d.aged_at > AGED_GAP:
                        d.clock.anew(w, now)
                    d.aged_at, d.unaged = now, False
                jumped = d.clock.teach(gateway, w, now, g)
                if jumped:  # the skin's time jumped: its frames start again
                    d.frames.restart()
            # a record whose point the map holds back (its frame after its arrival, unconfirmed)
            # is refused, every part of it (each says its own age: asked by its frame): a copy
            # of an older record under an index corrupted ahead was given out as that later
            # frame, whole, before the frame's own record came. Not when its age alone put the
            # point there: by the gateway's age before, its frame would have been taken (as
            # without ages), so the point stays held and the record is taken (refused, its
            # elements were unknown in that frame). An index corrupted ahead is still refused.
            held = d.clock.held(gateway, g)
            if held and w != g:
                before = d.ages.get(gateway)
                held = before is None or not d.clock.before(g + before, now)
            elif not held and rec.part == 0 and w != g:
                d.ages[gateway] = w - g
            t = math.nan if held else d.clock.frame_time(g, now)
        d.frames.add(gateway, rec, now, t, serial)
        return t, jumped

    def frame_times(self, root: int, g: NDArray[np.int64], now: float) -> NDArray[np.float64] | None:
        """:meth:`SkinClock.frame_times` on ``root``'s map; None while it has none."""
        d = self._domains.get(root)
        if d is None or not d.clock.synced:
            return None
        return d.clock.frame_times(g, now)

    def forget(self, gateway: int) -> None:
        """Stop following ``gateway`` (gone for good) in every domain."""
        for d in self._domains.values():
            d.frames.forget(gateway)
            d.ages.pop(gateway, None)
        self._root_of.pop(gateway, None)

    # -- out -----------------------------------------------------------------------------
    def take(self, now: float) -> list[SkinFrame]:
        """Every domain's frames ready by ``now``, by host time (each domain's in its order)."""
        out, self._ready = self._ready, []
        retired = bool(out)  # (frames of a domain forgotten: of another root than those that follow)
        for d in self._domains.values():
            out.extend(d.frames.take(now))
        if len(self._domains) > 1 or retired:  # (one domain's frames are in its order already)
            out.sort(key=lambda f: f.t)
        if out:
            self._newest = {"index": out[-1].index, "rate": out[-1].rate, "root": out[-1].root}
        return out

    def active(self, now: float) -> bool:
        """Whether some gateway is on the schedule, in any domain."""
        return any(d.frames.active(now) for d in self._domains.values())

    def due(self) -> float:
        """The earliest host time at which :meth:`take` gives a frame out with no new record."""
        return min((d.frames.due() for d in self._domains.values()), default=math.inf)

    def counters(self, now: float) -> dict[str, Any]:
        """The frames' health summed over the domains, with the domains followed."""
        out: dict[str, Any] = dict(self._retired)
        for d in self._domains.values():
            c = d.frames.counters(now)
            c.pop("newest")
            for k, v in c.items():
                out[k] = out.get(k, 0) + v
        if not self._domains:
            out = {**SkinFrames().counters(now), **self._retired}
            out.pop("newest")
        out["rejected_records"] = out.get("rejected_records", 0) + self.refused
        return {**out, "newest": self._newest, "time_roots": sorted(r for r in self._domains if r),
                "root_moves": self.moves}
