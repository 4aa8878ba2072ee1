"""The daemon's sans-I/O core: (link, bytes, host time) in → frozen messages out.

No sockets, no asyncio, no clock: the shells pass the time, so the same object runs under
the service, in tests and on replayed recordings with their recorded times (which makes
golden output exact). :meth:`Pipeline.feed` takes one read as a batch (numpy columns of
all its samples) and returns :mod:`cellbridge.daemon.core.messages` for the shell to act on.

The pipeline orchestrates, and only that: each concept has one owner (``core/``: ``wire``
the receive path, ``clock`` and ``domains`` time, ``health``, ``topology``, ``batches`` and
``layout`` the element stages, ``commands``, ``contacts`` contact identity), which returns
its results; a bridge forgotten is forgotten by each. Skin frames come from the gateways'
readout records (``frames``), complete when every active gateway's record came or at
their deadline; bridges on no schedule send DATA, read by a minimal fallback rule.
Contact estimation is not in ``feed``: the shell asks :meth:`Pipeline.contact_job` for the
newest complete frame whenever its worker is free, runs it and hands the contacts to
:meth:`Pipeline.contact_frame` (one frame of the skin, never a backlog).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np
from cellbridge.daemon.core.batches import Batch, Batches
from cellbridge.daemon.core.clock import HostTimes
from cellbridge.daemon.core.commands import CommandTracker, Pending
from cellbridge.daemon.core.config import Config
from cellbridge.daemon.core.contacts import ContactIdentity, ContactJob
from cellbridge.daemon.core.domains import TimeDomains
from cellbridge.daemon.core.elements import default_params
from cellbridge.daemon.core.frames import SkinFrame
from cellbridge.daemon.core.frontend import Frontend, chip_params
from cellbridge.daemon.core.health import UNPLACED_SHOWN, HealthBook
from cellbridge.daemon.core.layout import LayoutStages
from cellbridge.daemon.core.messages import (
    SCHEMA_VERSION,
    ContactFrame,
    ElementBatch,
    Health,
    LinkWrite,
    LogEvent,
    Message,
    RawBatch,
    Stamps,
    Topology,
)
from cellbridge.daemon.core.surface import contact_fields, skin_report
from cellbridge.daemon.core.topology import Topology as Routes
from cellbridge.daemon.core.wire import NO_MESH_TIME, OPS, Decoded, Ingress, ReadoutColumns, SampleColumns
from cellbridge.tactile import ElementParams, SkinLayout
from cellbridge.tactile.skin_geometry import SkinGeometry

__all__ = ["SCHEMA_VERSION", "Pipeline"]  # the schema version of what it publishes (daemon/core/messages.py)

_GATE_OP = int(OPS["gate"])
_NO_MESH_TIME = np.int64(NO_MESH_TIME)
_JUMPED = "mesh time jumped (a new time root?): mapping it to host time again"


class Pipeline:
    """Everything the daemon knows, fed by the shell; the shell's whole interface is methods:
    :meth:`feed` (a read), :meth:`tick` (time passing), :meth:`advance` and
    :meth:`host_clock_step` return the messages to act on, in order; :meth:`contact_job` /
    :meth:`contact_frame` the next contact estimate and its message; :meth:`command` /
    :meth:`finished_commands` commands to bridges; :meth:`want`, :meth:`link_state`,
    :meth:`link_stats`, :meth:`health_body`, :meth:`topology_body`, :meth:`summary`,
    :meth:`tare`, :meth:`reconfigure`.

    ``config`` is a validated :class:`~cellbridge.daemon.core.config.Config`; ``layout`` the
    layout file's, or None to place bridges by their HELLO geometry. Every time argument
    is host time in seconds and must come from one clock (a step back is handled, see
    :meth:`tick`). Nothing here raises on what arrives on a link: bad bytes are counted.
    The attributes are for tests and tools to inspect; a shell does not use them.
    """

    def __init__(self, config: Config, layout: SkinLayout | None = None) -> None:
        self.config = config
        self.ingress = Ingress(config.protocol.dedupe_window, config.protocol.reassembly_timeout)
        self.chip = chip_params(config.chip)
        self.skin = LayoutStages(config, layout)
        self.batches = Batches(Frontend(default_params(layout) if layout is not None else ElementParams(), self.chip),
                               self.chip.clock_hz, self.chip.gate_cycles)
        # Per time root (docs/time.md): mesh time -> host time, taught by the gateways' own
        # samples and readout records, and the skin frames of the records
        f = config.frames
        self.domains = TimeDomains(self.chip.clock_hz, f.margin, config.health.bridge_timeout, f.max_pending)
        self.clock = HostTimes(self.domains, self.chip.clock_hz, config.chip.cycle_bits,
                               {ln.name: ln.baudrate for ln in config.links})
        self.unknown_element_frames = 0  # placed elements unknown in the scheduled frames given out
        self._frames_given = 0  # skin frames given to the element stages (complete or at their deadline)
        self.health = HealthBook(self.chip.clock_hz, ((ln.name, ln.url) for ln in config.links))
        self.topology = Routes()
        self.commands = CommandTracker()
        self.contacts = ContactIdentity()
        self.stamps = Stamps()
        self.wanted: set[str] | None = None  # topics with subscribers; None = build all
        self.last_feed = 0.0
        self._next_health = -math.inf
        self._last_tick = -math.inf
        self._last_health = -math.inf
        self._queue: list[Message] = []  # log events (and the messages of frames contact_job gave out), handed out next
        #: the skin description (links, patches) the layout is the atlas of; set by the shell
        self.surface: SkinGeometry | None = None
        self._topology_due = False  # a reload changed the layout or the description: topology is news
        self._skin_reported: tuple[SkinGeometry | None, dict[str, Any] | None] | None = None

    @property
    def wall_offset(self) -> float:
        """Wall-clock minus the time base fed (:class:`~cellbridge.daemon.core.messages.Stamps`)."""
        return self.stamps.wall_offset

    def set_wall_offset(self, offset: float) -> None:
        """Wall-clock minus the time base fed (0 for wall-clock or recorded times): stamps only."""
        self.stamps.wall_offset = float(offset)

    def _event(self, level: str, text: str) -> None:
        self._queue.append(LogEvent(level, text))  # handed out with the next messages (_drain)

    def _drain(self, out: list[Message]) -> list[Message]:
        if self._queue:
            out.extend(self._queue)
            self._queue.clear()
        return out

    def _want(self, topic: str) -> bool:
        return self.wanted is None or topic in self.wanted

    # -- ingest -------------------------------------------------------------------------
    def feed(self, link: str, data: bytes, now: float) -> list[Message]:
        """One read of ``link`` (a configured link's name; another name is taken as a new
        link), ``data`` as it came off the line (any split of the stream), arriving at
        host time ``now``. Returns, in order, the messages the read produced: ``topology``
        when HELLOs changed the layout, ``raw`` and ``element`` for its samples (each
        only while :meth:`want` asks for its topic), and log events. Never raises for
        bad bytes (they are counted in health)."""
        self.last_feed = now
        self.health.link_data(link, now)
        dec = self.ingress.feed(link, data, now)
        out: list[Message] = []
        self._routing(link, dec, now, out)
        if dec.samples is not None:
            self._samples(link, dec.samples, now, out, dec.gateways)
        if dec.readouts:
            self._readouts(link, dec.readouts, now)
            self._frames_out(self.domains.take(now), now, out)
        return self._drain(out)

    def advance(self, now: float | None = None) -> list[Message]:
        """Time passing to ``now`` (default: the last read's time): the skin frames whose
        deadline passed go out, their ``raw`` and ``element`` messages returned
        (:meth:`contact_job` does this too; a shell calls this first, to publish them)."""
        now = self.last_feed if now is None else now
        out: list[Message] = []
        self._frames_out(self.domains.take(now), now, out)
        return self._drain(out)

    def _routing(self, link: str, dec: Decoded, now: float, out: list[Message]) -> None:
        window, health = self.ingress.dedupe_window(), self.health
        for origin, seqs in dec.frames_by_origin.items():
            boot = origin in dec.boots
            if health.frames_seen(origin, seqs, window, boot, link, now) and not boot:
                self.clock.suspect_reset(origin)  # numbering restarted without a HELLO: perhaps a reset
            self.topology.heard(origin, link, dec.gateways, now)
        if self.topology.gateways_heard(link, dec.gateways, now):
            health.may_forget_from(now)
        if not (dec.boots or dec.hellos or dec.beacons or dec.statuses or dec.replies):
            return  # (a read of readout records or samples alone: most reads)
        for origin in dec.boots:  # its cycle counter restarted too, perhaps by less than the clock's jump limit
            if self.clock.booted(origin):
                health.clock_reset(origin, now)
                self._event("warning", f"bridge {origin}: restarted (HELLO 0), resynchronising its clock")
        for origin, h in dec.hellos:
            if health.clock_rate(origin, h.clock_hz, now):
                self.clock.rate(origin, h.clock_hz)
        for origin, _src, bc in dec.beacons:
            self.topology.beacon(origin, bc.parent, bc.path_etx, bc.hops)
        for origin, st in dec.statuses:
            self.topology.status(origin, st.parent, st.path_etx, {n.bridge: n.link_etx for n in st.neighbours},
                                 st.queue_drops, st.retries, st.resets)
        if dec.hellos and self.skin.hello({o: (h.x, h.y, h.side) for o, h in dec.hellos}):
            health.may_forget_from(-math.inf)  # a bridge the layout no longer places may be due
            self._event("info", f"layout from HELLO now has {self.skin.layout.n} elements")  # type: ignore[union-attr]  # hello() returned True: a layout is in place
            if self._want("topology"):
                out.append(self.stamps.message(Topology, now, self.topology_body(now)))
        for origin, reply in dec.replies:
            p = self.commands.reply(origin, reply, now)
            if p is not None and p.op == _GATE_OP and reply.status.name == "OK":
                gate = reply.value if reply.value else p.value
                if gate:
                    self.batches.set_gate(origin, gate)

    def _readouts(self, link: str, records: list[tuple[int, ReadoutColumns]], now: float) -> None:
        """READOUT record parts teach the skin's time and join their frames
        (:meth:`HostTimes.records`); the bridges each accounts for were heard."""
        for r in self.clock.records(link, records, now):
            if r.jumped:
                self._event("warning", _JUMPED)
            if r.sampled is not None and r.unchanged is not None:
                self.health.spoken_for(link, r.sampled, r.unchanged, now)

    def _frames_out(self, frames: list[SkinFrame], now: float, out: list[Message]) -> None:
        """Complete skin frames into the element stages and the readings contacts are
        estimated on; ``raw`` and ``element`` messages for their samples."""
        self._frames_given += len(frames)
        for f in frames:
            link = self.health.link_of(f.gateways[0]) if f.gateways else ""
            b = self.batches.frame(self.skin, link, f, now, self.wall_offset, self._want("raw"), self._want("element"))
            self.unknown_element_frames += b.unknown
            self._batch(b, now, out)

    def _samples(self, link: str, s: SampleColumns, now: float, out: list[Message], gateways: set[int]) -> None:
        st = self.clock.samples(link, s.origin, s.cycle, s.index, s.rate, (s.flags & _NO_MESH_TIME) == 0, gateways, now)
        if st.jumped:
            self._event("warning", _JUMPED)
        self.health.sampled(st.newest, s.origin, s.cycle, now)
        for o in st.resets:
            self.health.clock_reset(o, now)
            self._event("warning", f"bridge {o}: clock restarted (reset?), resynchronising")
        if st.rejected.size:
            self.health.rejected(st.rejected, now)
        self._batch(self.batches.samples(self.skin, link, s, st.t_host, st.t_bridge, st.cycle, now, self.wall_offset,
                                         self._want("raw"), self._want("element")), now, out)

    def _batch(self, b: Batch, now: float, out: list[Message]) -> None:
        if b.unplaced.size:
            self.health.unmapped(b.unplaced, now)
        if b.raw is not None:
            out.append(self.stamps.message(RawBatch, now, b.raw))
        if b.element is not None:
            out.append(self.stamps.message(ElementBatch, now, b.element))

    # -- contacts -----------------------------------------------------------------------
    def contact_job(self, now: float | None = None) -> ContactJob | None:
        """The next contact estimate to run, or None: estimation off, nobody subscribed
        to ``contact``, no layout, or no skin frame came since the last job. The job holds
        the newest complete skin frame (frames whose deadline passed by ``now`` go out
        first, their messages with the next call that returns any): each element's reading
        of it, or unknown (:mod:`cellbridge.daemon.core.readings`); one frame, never a backlog.
        Run it with :class:`~cellbridge.daemon.shell.contact_worker.ContactWorker` and pass the
        contacts to :meth:`contact_frame`. ``now``: default the last read's time; a shell
        passes it also when no data comes, so that silence is noticed."""
        if not self.config.contact.enabled or not self._want("contact"):
            return None
        now = self.last_feed if now is None else now
        self._frames_out(self.domains.take(now), now, self._queue)
        snap = self.skin.snapshot(now, self.config.health.bridge_timeout, self.domains.active(now))
        if snap is None:  # (most calls: the spec is built only for a frame to estimate)
            return None
        spec = self.skin.spec(self.surface.bands if self.surface is not None else ())
        return None if spec is None else self.contacts.job(spec, snap, self.surface)

    def contact_due(self, now: float, idle: bool = False) -> float:
        """When :meth:`contact_job` has a new frame: ``now`` when one is complete and not
        estimated yet, else the deadline of the oldest frame waiting for a record, ``inf``
        when only new data brings one (a shell asks when data comes or then, whichever is
        first). ``idle``: the last estimate had nothing to track: a frame after it is worth
        a look only if it says something new (an idle skin's frames say "unchanged")."""
        if not self.config.contact.enabled or not self._want("contact"):
            return math.inf
        scheduled = self.domains.active(now)
        return max(min(self.skin.snapshot_due(now, idle, scheduled), self.domains.due()), now)

    def frames_given(self) -> int:
        """Skin frames given to the element stages so far (complete, or at their deadline): a
        read that raises it completed one (the contact loop need not wait out a rest)."""
        return self._frames_given

    def contact_frame(self, job: ContactJob, contacts: Iterable[dict[str, Any]]) -> ContactFrame:
        """The ``contact`` message of ``job``'s estimate (:meth:`ContactIdentity.published`),
        with each contact's place on the robot (:func:`~cellbridge.daemon.core.surface.contact_fields`)
        on the description the job was made with (a reload may have installed another since)."""
        snap, wall = job.snapshot, self.stamps.wall
        out = contact_fields(job.surface, self.contacts.published(job, contacts, wall))
        return self.stamps.message(ContactFrame, snap.t_host, {
            "t_sample": wall(snap.t_frame) if math.isfinite(snap.t_frame) else None, "t_bridge": None,
            "contacts": out, "unknown": [] if snap.unknown is None else snap.ids[snap.unknown].tolist(),
            "rebaselined": self.skin.take_rebaselined()})

    # -- periodic -----------------------------------------------------------------------
    def host_clock_step(self, delta: float) -> list[Message]:
        """The host's wall clock stepped by ``delta`` s (NTP, chrony ``makestep``): the stamps
        published from now on move by it, and nothing else does (the pipeline runs on the
        monotonic time base). Returns the log event saying so."""
        self.stamps.wall_offset += delta
        self._event("warning", f"host wall clock stepped by {delta:+.3f} s; published times follow, "
                               "the skin is not affected")
        return self._drain([])

    def tick(self, now: float, force: bool = False) -> list[Message]:
        """Time passes (the shell calls this often, ~10 Hz): ``health`` every
        ``health.interval`` (or now, if ``force``), ``topology`` when it changed, and log
        events (bridges gone silent or back, the host clock stepping back: a ``now``
        before the last tick's is taken as such a step)."""
        self.health.fold()
        h = self.config.health
        if now < self._last_tick:
            self._clock_stepped_back(now)
        self._last_tick = now
        if now < self._next_health and not force:
            return self._drain([])
        self._next_health = now + h.interval
        # Over the time since the health before (often more than the interval), not the interval.
        elapsed = now - self._last_health if 0 < now - self._last_health < math.inf else h.interval
        self._last_health = now
        self.ingress.expire(now)
        self._queue.extend(self.health.tick(now, elapsed, h.bridge_timeout, self.skin.split_placed))
        self._forget(now - h.forget_after)
        out: list[Message] = []
        if self._want("health"):
            out.append(self.stamps.message(Health, now, self.health_body(now)))
        topo = self.topology_body(now)
        if (self.topology.changed(topo) or self._topology_due) and self._want("topology"):
            out.append(self.stamps.message(Topology, now, topo))
            self._topology_due = False
        return self._drain(out)

    def _forget(self, before: float) -> None:
        """Bridges health forgets (:meth:`HealthBook.forget`) every owner forgets; gateway ids as old too."""
        gone = self.health.forget(before, self.skin.split_placed)
        if gone is None:
            return
        for bid in gone:
            self.clock.forget(bid)
            self.domains.forget(bid)
            self.topology.forget(bid)
            self.ingress.forget(bid)
        self.topology.forget_gateways(before)
        self.health.may_forget_from(self.topology.oldest_gateway())

    def _clock_stepped_back(self, now: float) -> None:
        """The host clock went back (NTP step, RTC set): times kept from before lie in the
        future and would hold back health, silence and command deadlines for as long as
        the step. They are taken as "now": a dead bridge is then reported silent
        ``bridge_timeout`` after the step, not hours later."""
        self._next_health = min(self._next_health, now)
        self.health.clock_stepped_back(now)
        self.topology.clock_stepped_back(now)
        self.commands.clock_stepped_back(now)
        self._event("warning", "host clock stepped back; liveness and deadlines counted from now")

    def health_body(self, now: float) -> dict[str, Any]:
        """The fields of a ``health`` message at ``now`` (control's ``status`` answers with them)."""
        layout_report, w = self.skin.report(now, self.config.health.stuck_after), self.wall_offset
        jump = layout_report.get("calibration", {}).get("last_common_jump")
        if jump is not None:  # (the calibrator is fed the time base; health speaks the wall clock)
            jump["t"] = self.stamps.wall(jump["t"])
        return {
            "t_bridge": None, "uptime": self.health.uptime(now),
            "links": self.health.links_report(self.ingress.counters, w),
            **self.health.bridges_report(now, self.skin.split_placed, self.ingress.drops_of, w),
            "layout": layout_report, **self.ingress.totals(),
            "commands": self.commands.counters(),
            "frames": {**self.domains.counters(now), "unknown_element_frames": self.unknown_element_frames},
        }

    def topology_body(self, now: float) -> dict[str, Any]:
        """The fields of a ``topology`` message at ``now`` (control's ``topology`` answers with them)."""
        body = self.topology.report(now, self.config.health.bridge_timeout, self.skin.split_placed, UNPLACED_SHOWN)
        for node in body["bridges"].values():
            node["last_seen"] = self.stamps.wall(node["last_seen"])
        body.update(t_bridge=None, layout=self.skin.layout_report(), skin=self._skin_report())
        return body

    def _skin_report(self) -> dict[str, Any] | None:
        """``topology``'s ``skin``: built once per description (it lists every element, a
        tenth of a second on the largest skin, and the body is built at every health
        interval to see whether the routes changed). Read only: published as it is."""
        if self._skin_reported is None or self._skin_reported[0] is not self.surface:
            self._skin_reported = (self.surface, skin_report(self.surface))
        return self._skin_reported[1]

    # -- commands -----------------------------------------------------------------------
    def command(self, op: int, value: int | None, target: int | None, now: float,
                timeout: float) -> tuple[Pending, list[LinkWrite]]:
        """Start a command to one bridge (``target``) or all alive (None): returns it (its
        ``token`` names it in :meth:`finished_commands`) and the link writes that send it.
        Raises ValueError for a bridge never heard from."""
        if target is None:
            return self.commands.send(op, value, None, self.health.alive(), self.health.link_names(), now, timeout)
        links = self.topology.links_of(target)
        if not links:
            raise ValueError(f"bridge {target} has not been heard from on any link")
        return self.commands.send(op, value, target, {target}, links, now, timeout)

    def finished_commands(self, now: float) -> list[Pending]:
        """Commands whose bridges all answered, or whose time ran out by ``now`` (each once)."""
        return self.commands.done(now) if len(self.commands) else []

    def expire_command(self, token: int) -> Pending | None:
        """Command ``token`` ended as timed out now (None: it already finished): for a time
        base that never reaches its deadline (a replay's recorded clock stands still)."""
        return self.commands.expire(token)

    def commands_in_flight(self) -> int:
        return len(self.commands)

    def tare(self, bridges: list[int] | None) -> int:
        """Re-take the baselines of ``bridges``' elements (None: all) now; the next
        :meth:`contact_job` comes at once. Returns how many elements were tared."""
        return self.skin.tare(bridges)

    def reconfigure(self, config: Config, layout: SkinLayout | None, surface: SkinGeometry | None = None) -> None:
        """SIGHUP: take the reloadable settings (the element stages:
        :meth:`~cellbridge.daemon.core.layout.LayoutStages.reconfigured`) and the layout
        file's skin description (``surface``: the next contacts are placed on its links, and
        ``topology`` says it at the next health interval)."""
        self.config = config
        described = surface is not self.surface
        self.surface = surface
        self.domains.configure(config.frames.margin, config.health.bridge_timeout, config.frames.max_pending)
        self.skin, rebuilt = self.skin.reconfigured(config, layout)
        if rebuilt:
            self.health.may_forget_from(-math.inf)
        # A new layout or description is news to every view (the mesh's routes alone decide
        # whether topology changed): the next tick publishes it.
        self._topology_due = self._topology_due or rebuilt or described

    # -- links and subscribers --------------------------------------------------------------
    def link_state(self, link: str, connected: bool, now: float, error: str = "") -> None:
        """``link`` came up (its stream decoder starts afresh) or went down (``error``: why)."""
        self.health.link_state(link, connected, now, error)
        if connected:
            self.ingress.reset_link(link)

    def link_stats(self, link: str, stats: dict[str, Any]) -> None:
        """The shell's own counters of ``link`` (writes dropped, capture): shown in its health."""
        self.health.link_stats(link, stats)

    def want(self, topics: set[str] | None) -> None:
        """Build only messages of ``topics`` (those with subscribers); None: every topic."""
        self.wanted = None if topics is None else set(topics)

    def summary(self) -> str:
        """One line for the service manager's status: links up, bridges alive."""
        return self.health.summary()

