"""The daemon's sans-I/O core: (link, bytes, host time) in → frozen messages out.

No sockets, no asyncio, no clock: the shells pass the time, so the same object runs
under the service, in tests fed synthesized bytes, and on replayed captures with
their recorded times (which is what makes golden-output tests exact). One call of
:meth:`Pipeline.feed` handles one read of a link as a batch: frames are decoded, then
every later stage works on numpy columns of all the batch's samples. What comes back
is a list of :mod:`cellbridge.daemon.messages`: messages to publish, log events, bytes
to write on a link; the shell does what each says and never reads the pipeline's
attributes.

Skin frames come from the gateways' readout records (:mod:`cellbridge.daemon.frames`):
a frame is complete when every active gateway's record of it came, or at its deadline,
and each element of it is a new reading, its previous one (its bridge said unchanged)
or unknown (:mod:`cellbridge.daemon.readings`). Bridges on no schedule send DATA, read
by a minimal fallback rule.

Contact estimation is deliberately *not* in ``feed``: it is slow next to ingest, so
the shell asks :meth:`Pipeline.contact_job` for the newest complete frame whenever its
worker is free (:meth:`Pipeline.contact_due` says when one is there), runs it
(:mod:`cellbridge.daemon.contact_worker`) and hands the contacts back to
:meth:`Pipeline.contact_frame` (one frame of the skin, never a backlog).
"""

from __future__ import annotations

import itertools
import math
import os
from collections import Counter
from collections.abc import Iterable
from dataclasses import replace
from typing import Any, TypeVar

import numpy as np
from cellbridge.daemon.clock import BridgeClock, rows_to_host
from cellbridge.daemon.commands import CommandTracker, Pending
from cellbridge.daemon.config import Config
from cellbridge.daemon.contacts import ContactJob, ContactSpec
from cellbridge.daemon.surface import contact_fields, skin_report
from cellbridge.daemon.elements import default_params
from cellbridge.daemon.domains import TimeDomains
from cellbridge.daemon.frames import SkinFrame
from cellbridge.daemon.frontend import Frontend, chip_params
from cellbridge.daemon.health import BridgeHealth, LinkHealth, link_report
from cellbridge.daemon.layout import LayoutStages, layout_dict, skin_settings
from cellbridge.daemon.messages import (
    ContactFrame,
    ElementBatch,
    Health,
    LinkWrite,
    LogEvent,
    Message,
    Publish,
    RawBatch,
    Topology,
)
from cellbridge.daemon.topology import Topology as Routes
from cellbridge.daemon.wire import (
    ADDR_BROADCAST,
    HELD,
    NO_MESH_TIME,
    OPS,
    Decoded,
    PART_BYTES,
    Ingress,
    Readout,
    SampleColumns,
    command_bytes,
)
from cellbridge.tactile import ElementParams, SkinLayout
from cellbridge.tactile.skin_geometry import SkinGeometry

SCHEMA_VERSION = 2  # 2: contacts in link frames (link, position, normal, force_vector), topology.skin
_GATE_OP = int(OPS["gate"])
_NO_MESH_TIME = np.int64(NO_MESH_TIME)
_HELD = np.int64(HELD)
# Unplaced bridges health lists one by one: beyond this, only their count. One corrupt frame in
# ~65 536 passes CRC-16 with a random origin, so a noisy line makes thousands of phantoms; each
# would cost ~240 bytes in every health message (15 MB at 65 530) until forgotten.
_UNPLACED_SHOWN = 64
_OWNERS = itertools.count()
_P = TypeVar("_P", bound=Publish)


class Pipeline:
    """Everything the daemon knows, fed by the shell; the shell's whole interface is methods.

    - :meth:`feed` (one read of a link) and :meth:`tick` (time passing) return the
      messages to act on, in order; :meth:`link_state`, :meth:`host_clock_step` likewise.
    - :meth:`contact_job` / :meth:`contact_frame`: the next contact estimate and its message.
    - :meth:`command` / :meth:`finished_commands`: commands to bridges and their outcome.
    - :meth:`want` (topics with subscribers), :meth:`link_stats` (the shell's own link
      counters), :meth:`health_body`, :meth:`topology_body`, :meth:`summary`,
      :meth:`tare`, :meth:`reconfigure`.

    ``config`` is a validated :class:`~cellbridge.daemon.config.Config`; ``layout`` the
    layout file's, or None to place bridges by their HELLO geometry. Every time argument
    is host time in seconds and must come from one clock (a step back is handled, see
    :meth:`tick`). Nothing here raises on what arrives on a link: bad bytes are counted.
    The attributes are for tests and tools to inspect; a shell does not use them.
    """

    def __init__(self, config: Config, layout: SkinLayout | None = None) -> None:
        self.config = config
        self._owner = f"{os.getpid()}.{next(_OWNERS)}"  # whose tracks a contact job continues
        self.ingress = Ingress(config.protocol.dedupe_window, config.protocol.reassembly_timeout)
        self.chip = chip_params(config.chip)
        self.frontend = Frontend(default_params(layout) if layout is not None else ElementParams(), self.chip)
        self.skin = LayoutStages(config, layout)
        self.gate = np.full(0x10000, float(self.chip.gate_cycles))
        self._bits = config.chip.cycle_bits
        # Each bridge's clock parameters, indexed by bridge id, so a batch maps in one vector step.
        self._ref = np.zeros(0x10000, dtype=np.uint64)
        self._t_ref = np.full(0x10000, np.nan)
        self._k = np.ones(0x10000)
        self._hz = np.full(0x10000, float(self.chip.clock_hz))
        self.clocks: dict[int, BridgeClock] = {}
        # Per time root (docs/time.md): mesh time -> host time, taught by the gateways' own
        # samples and readout records, and the skin frames of the records
        f = config.frames
        self.times = TimeDomains(self.chip.clock_hz, f.margin, config.health.bridge_timeout, f.max_pending)
        self._link_root: dict[str, int] = {}  # link -> the root of its newest record (DATA samples' mesh time)
        self.unknown_element_frames = 0  # placed elements unknown in the scheduled frames given out
        self._baud = {ln.name: ln.baudrate for ln in config.links}  # s a record takes on its line: bytes x 10 / baud
        # bridges the readout records spoke for (a sample or unchanged): when, on which link, how
        # many samples; folded into their health when it is read (_fold_heard)
        self._heard = np.full(0x10000, -math.inf)
        self._heard_via = np.zeros(0x10000, dtype=np.int64)
        self._heard_new = np.zeros(0x10000, dtype=bool)
        self._heard_samples = np.zeros(0x10000, dtype=np.int64)
        self._link_index: dict[str, int] = {}
        self.bridges: dict[int, BridgeHealth] = {}
        self.links: dict[str, LinkHealth] = {ln.name: LinkHealth(ln.url) for ln in config.links}
        self.topology = Routes()
        self.commands = CommandTracker()
        self.wanted: set[str] | None = None  # topics with subscribers; None = build all
        self.seq: dict[str, int] = {}
        self.started: float | None = None
        self.last_feed = 0.0
        self._next_health = -math.inf
        self._last_tick = -math.inf
        self._last_health = -math.inf
        self.forgotten_bridges = 0
        # Bridges whose rate or silence a health tick must look at: heard since, or not yet
        # silent with a rate of 0. A silent bridge costs the tick nothing (65 530 phantoms).
        self._awake: set[int] = set()
        self._forget_floor = -math.inf  # no bridge nor gateway id _forget could drop was last heard before this
        self._next_contact_id = 0  # lowest contact id never published (see contact_job)
        self._carry: tuple[dict[str, Any], ...] = ()  # the contacts last published, as the worker gave them
        self.announced_silent: set[int] = set()
        self._queue: list[Message] = []  # log events (and the messages of frames contact_job gave out), handed out next
        # The pipeline runs on one time base, the host's monotonic clock as the shell passes
        # it: silence, frames and deadlines never see the wall clock step. Wall-clock time
        # is only stamped on what is published: monotonic time + this offset.
        self.wall_offset = 0.0
        #: the skin description (links, patches) the layout is the atlas of; set by the shell
        self.surface: SkinGeometry | None = None
        self._spec_memo: tuple[ContactSpec, ContactSpec] | None = None

    # -- helpers ------------------------------------------------------------------------
    def _message(self, kind: type[_P], now: float, body: dict[str, Any]) -> _P:
        n = self.seq.get(kind.topic, 0)
        self.seq[kind.topic] = n + 1
        return kind({"v": SCHEMA_VERSION, "seq": n, "t_host": now + self.wall_offset, **body})

    def _wall(self, t: float | None) -> float | None:
        return None if t is None else t + self.wall_offset

    def set_wall_offset(self, offset: float) -> None:
        """Wall-clock minus the time base the shell feeds (``time.time() - time.monotonic()``
        for a service on the monotonic clock; 0 when fed wall-clock or recorded times).
        Only published stamps use it."""
        self.wall_offset = float(offset)

    def _event(self, level: str, text: str) -> None:
        self._queue.append(LogEvent(level, text))

    def _drain(self, out: list[Message]) -> list[Message]:
        if self._queue:
            out.extend(self._queue)
            self._queue.clear()
        return out

    def _want(self, topic: str) -> bool:
        return self.wanted is None or topic in self.wanted

    def _bridge(self, bid: int, now: float) -> BridgeHealth:
        b = self.bridges.get(bid)
        if b is None:
            b = self.bridges[bid] = BridgeHealth(first_seen=now, clock_hz=self.chip.clock_hz)
            self._forget_floor = min(self._forget_floor, now)  # it may be due to be forgotten some day
        self._awake.add(bid)
        return b

    def _clock(self, bid: int) -> BridgeClock:
        c = self.clocks.get(bid)
        if c is None:
            hz = self.bridges[bid].clock_hz if bid in self.bridges else self.chip.clock_hz
            c = self.clocks[bid] = BridgeClock(hz, bits=self.config.chip.cycle_bits)
        return c

    # -- ingest -------------------------------------------------------------------------
    def feed(self, link: str, data: bytes, now: float) -> list[Message]:
        """One read of ``link`` (a configured link's name; another name is taken as a new
        link), ``data`` as it came off the line (any split of the stream), arriving at
        host time ``now``. Returns, in order, the messages the read produced: ``topology``
        when HELLOs changed the layout, ``raw`` and ``element`` for its samples (each
        only while :meth:`want` asks for its topic), and log events. Never raises for
        bad bytes (they are counted in health)."""
        if self.started is None:
            self.started = now
        self.last_feed = now
        dec = self.ingress.feed(link, data, now)
        lh = self.links.get(link)
        if lh is None:
            lh = self.links[link] = LinkHealth(link)
        lh.last_data = now
        out: list[Message] = []
        self._routing(link, dec, now, out)
        if dec.samples is not None:
            self._samples(link, dec.samples, now, out, dec.gateways)
        if dec.readouts:
            self._readouts(link, dec.readouts, now)
            self._frames_out(self.times.take(now), now, out)
        return self._drain(out)

    def advance(self, now: float | None = None) -> list[Message]:
        """Time passing to ``now`` (default: the last read's time): the skin frames whose
        deadline passed go out (their elements' ``raw`` and ``element`` messages are
        returned). :meth:`contact_job` does this too; a shell calls it first, to publish
        what it returns."""
        now = self.last_feed if now is None else now
        out: list[Message] = []
        self._frames_out(self.times.take(now), now, out)
        return self._drain(out)

    def _routing(self, link: str, dec: Decoded, now: float, out: list[Message]) -> None:
        window = self.ingress.dedupe.window
        for origin, seqs in dec.frames_by_origin.items():
            b = self._bridge(origin, now)
            restarts = b.seq_restarts
            b.frames_seen(seqs, window, origin in dec.boots)
            if b.seq_restarts != restarts and origin in self.clocks and origin not in dec.boots:
                self.clocks[origin].suspect_reset()  # numbering restarted without a HELLO: perhaps a reset
            b.last_seen, b.link = now, link
            self.topology.heard(origin, link, dec.gateways, now)
        if self.topology.gateways_heard(link, dec.gateways, now):
            self._forget_floor = min(self._forget_floor, now)
        for origin in dec.boots:  # its cycle counter restarted too, perhaps by less than the clock's jump limit
            if origin in self.clocks and self.clocks.pop(origin).synced:
                self._bridge(origin, now).clock_resets += 1
                self._event("warning", f"bridge {origin}: restarted (HELLO 0), resynchronising its clock")
        for origin, h in dec.hellos:
            b = self._bridge(origin, now)
            if b.clock_hz != h.clock_hz and h.clock_hz > 0:
                b.clock_hz = float(h.clock_hz)
                self.clocks.pop(origin, None)
        for origin, _src, bc in dec.beacons:
            self.topology.beacon(origin, bc.parent, bc.path_etx, bc.hops)
        for origin, st in dec.statuses:
            self.topology.status(origin, st.parent, st.path_etx, {n.bridge: n.link_etx for n in st.neighbours},
                                 st.queue_drops, st.retries, st.resets)
        if dec.hellos and self.skin.hello({o: (h.x, h.y, h.side) for o, h in dec.hellos}):
            self._forget_floor = -math.inf  # a bridge the layout no longer places may be due
            self._event("info", f"layout from HELLO now has {self.skin.layout.n} elements")  # type: ignore[union-attr]  # hello() returned True: a layout is in place
            if self._want("topology"):
                out.append(self._message(Topology, now, self.topology_body(now)))
        for origin, reply in dec.replies:
            p = self.commands.reply(origin, reply, now)
            if p is not None and p.op == _GATE_OP and reply.status.name == "OK":
                gate = reply.value if reply.value else p.value
                if gate:
                    self.gate[origin] = float(gate)

    def _sync_clocks(self, s: SampleColumns, now: float, gateways: set[int],
                     root: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Feed the clocks; (host time, bridge time, global cycle or -1) of every sample.

        A sample on mesh time (no ``NO_MESH_TIME`` flag, a rate) started its C1 gate at
        global time ``index / rate``: its host time comes from the skin's one map, so two
        bridges' samples of one index get one host time. Other samples (a bridge booting
        or cut off, protocol version 1) are timed from their bridge's own arrival fit."""
        on_time = ((s.flags & _NO_MESH_TIME) == 0) & (s.rate > 0)
        with np.errstate(divide="ignore"):  # an index whose instant does not fit 63 bits is nonsense
            on_time &= s.index.astype(np.float64) * self.chip.clock_hz / np.maximum(s.rate, 1) < 2.0**62
        g = np.full(s.origin.shape[0], -1, dtype=np.int64)
        if on_time.any():
            rate = np.where(on_time, s.rate, 1).astype(np.uint64)
            cps = np.uint64(int(self.chip.clock_hz))
            # index · clock_hz // rate without index · clock_hz, which wraps in uint64 below the check above
            # (at a high rate): a corrupted index was put on some frame of the last 65 days
            g = np.where(on_time, (s.index // rate * cps + s.index % rate * cps // rate).astype(np.int64), -1)
            own = np.flatnonzero(on_time & np.isin(s.origin, np.fromiter(gateways, np.int64, len(gateways))))
            if own.size:
                newest = own[np.argmax(g[own])]
                self._teach(root, int(s.origin[newest]), int(g[newest]), now)
        origin_list = s.origin.tolist()
        newest = {o: i for i, o in enumerate(origin_list)}  # each bridge's newest sample
        counts = Counter(origin_list)
        for o, i in newest.items():
            b = self._bridge(o, now)
            clk = self._clock(o)
            cyc = int(s.cycle[i])
            if clk.observe(cyc, now):
                b.clock_resets += 1
                self._event("warning", f"bridge {o}: clock restarted (reset?), resynchronising")
            b.samples += counts[o]
            b.last_cycle = cyc
            self._ref[o], self._t_ref[o], self._k[o], self._hz[o] = clk.params()
        o = s.origin
        hz = self._hz[o]
        t_sample = rows_to_host(s.cycle, self._ref[o], self._t_ref[o], self._k[o], hz, self._bits)
        frame_t = self.times.frame_times(root, np.where(on_time, g, -1), now) if on_time.any() else None
        if frame_t is not None:
            # A frame the map puts after the sample's own arrival was never taken: its index is
            # wrong (a frame corrupted past the CRC, a bridge on some other time); so is one
            # behind a jump back of the skin's time not confirmed yet. Believed, it would move
            # the skin frame that far and stop every estimate until then.
            wrong = on_time & np.isnan(frame_t)
            if wrong.any():
                for b_id, cnt in Counter(o[wrong].tolist()).items():
                    self.bridges[b_id].index_rejected += cnt
                g = np.where(wrong, -1, g)
                on_time &= ~wrong
            t_sample = np.where(on_time, frame_t, t_sample)
        return t_sample, s.cycle.astype(np.float64) / hz, g

    def _teach(self, root: int, gateway: int, g: int, now: float) -> None:
        """A gateway's own point of ``root``'s mesh time (global cycle ``g``) reached the host at ``now``."""
        if self.times.teach(root, gateway, g, now):
            self._event("warning", "mesh time jumped (a new time root?): mapping it to host time again")

    def _cycle_of(self, index: int, rate: int) -> int:
        """The global cycle of frame ``index`` at ``rate`` (-1: its instant does not fit 62 bits:
        a nonsense index)."""
        g = index * int(self.chip.clock_hz) // rate
        return g if 0 <= g < 1 << 62 else -1

    def _readouts(self, link: str, records: list[tuple[int, Readout]], now: float) -> None:
        """READOUT record parts a gateway wrote (:mod:`cellbridge.daemon.frames`): each record
        teaches the skin clock (it cannot reach the host before its frame's gates opened: a
        gateway sends it as soon as it is complete, the schedule's end being only the latest)
        and joins its frame; the bridges it accounts for with a sample or unchanged were heard
        (:meth:`_fold_heard`)."""
        part_s = PART_BYTES * 10 / self._baud.get(link, 1_000_000)  # s a part takes on the line, at most
        via = self._link_index.setdefault(link, len(self._link_index))
        for gw, rec in records:
            g = self._cycle_of(rec.index, rec.rate)  # (-1, a nonsense index: the record is refused, and counted)
            self._link_root[link] = rec.root
            t, jumped = self.times.record(gw, rec, rec.root, g, now, rec.parts * part_s)
            if jumped:
                self._event("warning", "mesh time jumped (a new time root?): mapping it to host time again")
            if math.isfinite(t):
                n = len(rec.samples)
                said = np.array([s[0] for s in rec.samples] + list(rec.unchanged), dtype=np.int64)
                self._heard[said], self._heard_via[said], self._heard_new[said] = now, via, True
                self._heard_samples[said[:n]] += 1

    def _fold_heard(self) -> None:
        """The bridges readout records spoke for since the last fold into their health: heard
        then, on that link, their samples counted. (Done when health is read, not per record:
        a thousand bridges a frame, a hundred frames a second.)"""
        ids = np.flatnonzero(self._heard_new)
        if not ids.size:
            return
        names = list(self._link_index)
        for bid, at, via, n in zip(ids.tolist(), self._heard[ids].tolist(), self._heard_via[ids].tolist(),
                                   self._heard_samples[ids].tolist()):
            b = self._bridge(bid, at)
            if at > b.last_seen:
                b.last_seen, b.link = at, names[via]
            b.samples += n
        self._heard_new[ids] = False
        self._heard_samples[ids] = 0

    def _frames_out(self, frames: list[SkinFrame], now: float, out: list[Message]) -> None:
        """Complete skin frames into the element stages and the readings contacts are
        estimated on; ``raw`` and ``element`` messages for their samples."""
        for f in frames:
            g = self._cycle_of(f.index, f.rate)
            link = self.bridges[f.gateways[0]].link if f.gateways and f.gateways[0] in self.bridges else ""
            raw = np.stack([f.c1, f.c2], axis=1)
            if self._want("raw") and f.bridges.size:
                cyc = [g] * f.bridges.size
                out.append(self._message(RawBatch, now, {
                    "link": link, "bridge": f.bridges.tolist(), "element": [0] * f.bridges.size, "cycle": cyc,
                    "t_bridge": [g / self.chip.clock_hz] * f.bridges.size, "c1": f.c1.tolist(), "c2": f.c2.tolist(),
                    "flags": f.flags.tolist(), "mode": f.mode.tolist(), "oversampling": f.oversampling.tolist(),
                }))
            if not self.skin.ready:
                continue
            zero = np.zeros(f.bridges.size, dtype=np.int64)
            rows = self.skin.rows_of(f.bridges, zero)
            placed = rows >= 0
            if not placed.all():
                for b_id, cnt in Counter(f.bridges[~placed].tolist()).items():
                    self.bridges[b_id].unmapped_samples += cnt
            caps, sat = self.frontend.capacitance(f.mode, f.oversampling, raw, f.flags, self.gate[f.bridges])
            unchanged = self.skin.rows_of(f.unchanged, np.zeros(f.unchanged.size, dtype=np.int64))
            missing = self.skin.rows_of(f.missing, np.zeros(f.missing.size, dtype=np.int64))
            res, unknown = self.skin.frame(f.t, g, rows[placed], raw[placed], sat[placed], caps[placed],
                                           unchanged[unchanged >= 0], now, inverse=self._want("element"),
                                           root=f.root, missing=missing[missing >= 0])
            self.unknown_element_frames += unknown
            if self._want("element") and placed.any():
                n = int(placed.sum())
                out.append(self._message(ElementBatch, now, {
                    "bridge": f.bridges[placed].tolist(), "element": [0] * n, "cycle": [g] * n,
                    "t_bridge": [g / self.chip.clock_hz] * n, "t_sample": [f.t + self.wall_offset] * n,
                    "index": [f.index] * n, "on_time": [True] * n,
                    "c1": caps[placed, 0].tolist(), "c2": caps[placed, 1].tolist(),
                    "dc1": res["dc1"].tolist(), "dc2": res["dc2"].tolist(), "force": res["force"].tolist(),
                    "area": res["area"].tolist(), "valid": res["valid"].tolist(), "status": res["status"].tolist(),
                    "touched": res["touched"].tolist(),
                }))

    def _samples(self, link: str, s: SampleColumns, now: float, out: list[Message], gateways: set[int]) -> None:
        t_sample, t_bridge, g = self._sync_clocks(s, now, gateways, self._link_root.get(link, 0))
        o = s.origin
        raw = np.stack([s.c1, s.c2], axis=1)
        caps_all, sat_all = self.frontend.capacitance(s.mode, s.oversampling, raw, s.flags, self.gate[o])
        rows = self.skin.rows_of(o, s.element)
        placed = rows >= 0
        all_placed = bool(placed.all())
        if not all_placed:
            for b_id, cnt in Counter(o[~placed].tolist()).items():
                self.bridges[b_id].unmapped_samples += cnt
        if self._want("raw"):
            out.append(self._message(RawBatch, now, {
                "link": link, "bridge": s.origin.tolist(), "element": s.element.tolist(),
                "cycle": s.cycle.tolist(), "t_bridge": t_bridge.tolist(), "c1": s.c1.tolist(),
                "c2": s.c2.tolist(), "flags": s.flags.tolist(), "mode": s.mode.tolist(),
                "oversampling": s.oversampling.tolist(),
            }))
        if not self.skin.ready or not placed.any():
            return
        sel = slice(None) if all_placed else placed
        caps = caps_all[sel]
        flags = s.flags[sel]
        rate = s.rate[sel]
        with np.errstate(divide="ignore"):
            period = np.where(rate > 0, 1.0 / rate, np.nan)
        res = self.skin.step(rows[sel], raw[sel], sat_all[sel], caps, t_sample[sel], s.cycle[sel], now,
                             (flags & _HELD) != 0, g[sel] >= 0, period, inverse=self._want("element"))
        if self._want("element"):
            out.append(self._message(ElementBatch, now, {
                "bridge": o[sel].tolist(), "element": s.element[sel].tolist(),
                "cycle": s.cycle[sel].tolist(), "t_bridge": t_bridge[sel].tolist(),
                "t_sample": (t_sample[sel] + self.wall_offset).tolist(), "index": s.index[sel].tolist(), "on_time": (g[sel] >= 0).tolist(),
                "c1": caps[:, 0].tolist(), "c2": caps[:, 1].tolist(),
                "dc1": res["dc1"].tolist(), "dc2": res["dc2"].tolist(), "force": res["force"].tolist(),
                "area": res["area"].tolist(), "valid": res["valid"].tolist(), "status": res["status"].tolist(),
                "touched": res["touched"].tolist(),
            }))

    # -- contacts -----------------------------------------------------------------------
    def contact_job(self, now: float | None = None) -> ContactJob | None:
        """The next contact estimate to run, or None: estimation off, nobody subscribed
        to ``contact``, no layout, or no skin frame came since the last job.

        The job holds the newest complete skin frame (frames whose deadline passed by
        ``now`` go out first: :meth:`advance`; their messages come with the next call that
        returns messages): each element's reading of it, or unknown (see
        :mod:`cellbridge.daemon.readings`). Never an older frame left behind: one frame
        of the skin, never a backlog. Run it with
        :class:`~cellbridge.daemon.contact_worker.ContactWorker` (any executor) and pass
        the contacts to :meth:`contact_frame`. ``now``: the host time (default: the last
        read's); a shell passes it also when no data comes, so that silence is noticed."""
        if not self.config.contact.enabled or not self._want("contact"):
            return None
        now = self.last_feed if now is None else now
        self._frames_out(self.times.take(now), now, self._queue)
        snap = self.skin.snapshot(now, self.config.health.bridge_timeout, self.times.active(now))
        if snap is None or self.skin.contact_spec is None:
            return None
        return ContactJob(self._owner, self._surface_spec(self.skin.contact_spec), snap, self._next_contact_id,
                          self._carry)

    def contact_due(self, now: float, idle: bool = False) -> float:
        """The host time at which :meth:`contact_job` has a new frame: ``now`` when one is
        complete and not estimated yet, else the deadline of the oldest frame waiting for a
        record, ``inf`` when only new data brings one. A shell asks for a job when data comes
        or at this time, whichever is first (at most ``contact.rate`` a second); the periodic
        tick notices silence. ``idle``: the last estimate had nothing to track (the worker
        skipped it): a frame after it is worth a look only if it says something new (an
        idle event-based skin's frames say "unchanged" a hundred times a second)."""
        if not self.config.contact.enabled or not self._want("contact"):
            return math.inf
        scheduled = self.times.active(now)
        return max(min(self.skin.snapshot_due(now, idle, scheduled), self.times.due()), now)

    def contact_frame(self, job: ContactJob, contacts: Iterable[dict[str, Any]]) -> ContactFrame:
        """The ``contact`` message of ``job``'s estimate: each contact (as the worker gave
        it, copied) with the cycle count of each of its elements' readings and the newest
        of their sample times."""
        snap = job.snapshot
        index = dict(zip(snap.ids.tolist(), range(len(snap.ids))))  # (one C pass: a thousand ids a frame)
        out = []
        contacts = list(contacts)
        self._carry = tuple(contacts)
        for c in contacts:
            if isinstance(c.get("id"), int):  # ids never go back, whatever rebuilt the tracker
                self._next_contact_id = max(self._next_contact_id, c["id"] + 1)
            rows = [index[e] for e in c["elements"]]
            ts = [float(snap.t_sample[i]) for i in rows if math.isfinite(snap.t_sample[i])]
            out.append({**c, "t": self._wall(c.get("t")), "cycles": [int(snap.cycle[i]) for i in rows],
                        "t_sample": self._wall(max(ts)) if ts else None})
        out = contact_fields(self.surface, out)  # link, 3-D position, normal, force vector
        t = self._wall(snap.t_frame) if math.isfinite(snap.t_frame) else None
        unknown = [] if snap.unknown is None else snap.ids[snap.unknown].tolist()
        return self._message(ContactFrame, snap.t_host, {"t_sample": t, "t_bridge": None, "contacts": out,
                                                         "unknown": unknown, "rebaselined": self._rebaselined()})

    def _rebaselined(self) -> list[int]:
        """Bridge ids of the elements re-baselined under a touch (after ``max_touch``, their
        reading no contact's) since the last ``contact`` message, each once."""
        stage, layout = self.skin.elements, self.skin.layout
        if stage is None or layout is None:
            return []
        return [int(b) for b in layout.ids[stage.take_rebaselined()]]

    # -- periodic -----------------------------------------------------------------------
    def host_clock_step(self, delta: float) -> list[Message]:
        """The host's wall clock stepped by ``delta`` s (NTP, chrony ``makestep``): the stamps
        published from now on move by it, and nothing else does (the pipeline runs on the
        monotonic time base). Returns the log event saying so."""
        self.wall_offset += delta
        self._event("warning", f"host wall clock stepped by {delta:+.3f} s; published times follow, "
                               "the skin is not affected")
        return self._drain([])

    def tick(self, now: float, force: bool = False) -> list[Message]:
        """Time passes (the shell calls this often, ~10 Hz): ``health`` every
        ``health.interval`` (or now, if ``force``), ``topology`` when it changed, and log
        events (bridges gone silent or back, the host clock stepping back: a ``now``
        before the last tick's is taken as such a step)."""
        self._fold_heard()
        h = self.config.health
        if now < self._last_tick:
            self._clock_stepped_back(now)
        self._last_tick = now
        if now < self._next_health and not force:
            return self._drain([])
        interval = h.interval
        self._next_health = now + interval
        # Over the time since the health before (often more than the interval), not the interval.
        elapsed = now - self._last_health if 0 < now - self._last_health < math.inf else interval
        self._last_health = now
        self.ingress.reassembler.expire(now)
        went_silent: list[int] = []
        came_back: list[int] = []
        for bid in list(self._awake):
            b = self.bridges[bid]
            b.rate = (b.samples - b._samples_at_tick) / elapsed
            b._samples_at_tick = b.samples
            silent = now - b.last_seen > h.bridge_timeout
            if silent != b.silent:
                (went_silent if silent else came_back).append(bid)
            b.silent = silent
            if silent and not b.rate:
                self._awake.discard(bid)
        self._silence_events(went_silent, came_back, now)
        self._forget(now - h.forget_after)
        out: list[Message] = []
        if self._want("health"):
            out.append(self._message(Health, now, self.health_body(now)))
        topo = self.topology_body(now)
        if self.topology.changed(topo) and self._want("topology"):
            out.append(self._message(Topology, now, topo))
        return self._drain(out)

    def _silence_events(self, went_silent: list[int], came_back: list[int], now: float) -> None:
        """Log bridges gone silent or back: each placed bridge by itself, of the others
        (phantom origins of a noisy line, strangers) the first ``_UNPLACED_SHOWN`` and
        one summary with the count: 65 530 phantoms going quiet at once must not make
        65 530 log events in one tick."""
        for bids, level, what in ((went_silent, "warning", "went silent"), (came_back, "info", "are back")):
            placed, others = self.skin.split_placed(bids)
            for b in placed + others[:_UNPLACED_SHOWN]:
                self._event(level, f"no data from bridge {b} for {now - self.bridges[b].last_seen:.1f} s"
                            if bids is went_silent else f"bridge {b} is back")
            if len(others) > _UNPLACED_SHOWN:
                self._event(level, f"{len(others) - _UNPLACED_SHOWN} more bridges the layout does not place "
                                   f"{what} (not logged one by one)")

    def _forget(self, before: float) -> None:
        """Drop bridges the layout does not place that were last heard ``before``: phantoms
        of a noisy line or strangers would otherwise grow health and every tick forever."""
        if before < self._forget_floor:  # nothing can be due: no scan of every origin per tick
            return
        gone = [b for b in self.skin.split_placed(self.bridges)[1] if self.bridges[b].last_seen < before]
        for bid in gone:
            del self.bridges[bid]
            self.clocks.pop(bid, None)
            self.times.forget(bid)
            self.topology.nodes.pop(bid, None)
            self.ingress.reassembly_drops.pop(bid, None)
            self._awake.discard(bid)
        self.forgotten_bridges += len(gone)
        self.topology.forget_gateways(before)
        # Last-heard times only grow (a step back resets this), and a bridge or gateway id heard
        # later is newer: until the oldest one left is due, a scan forgets nothing. A new one
        # (heard for the first time, or again after it was forgotten) lowers this again.
        _, others = self.skin.split_placed(self.bridges)
        oldest = min((self.bridges[b].last_seen for b in others), default=math.inf)
        self._forget_floor = min(oldest, self.topology.oldest_gateway())

    def _clock_stepped_back(self, now: float) -> None:
        """The host clock went back (NTP step, RTC set): times kept from before lie in the
        future and would hold back health, silence and command deadlines for as long as
        the step. They are taken as "now": a dead bridge is then reported silent
        ``bridge_timeout`` after the step, not hours later."""
        self._next_health = min(self._next_health, now)
        self._awake.update(self.bridges)
        self._forget_floor = -math.inf
        for b in self.bridges.values():
            b.last_seen = min(b.last_seen, now)
            b.first_seen = min(b.first_seen, now)
        self.topology.clock_stepped_back(now)
        self.commands.clock_stepped_back(now)
        self._event("warning", "host clock stepped back; liveness and deadlines counted from now")

    def health_body(self, now: float) -> dict[str, Any]:
        """The fields of a ``health`` message at ``now`` (control's ``status`` answers with them)."""
        self._fold_heard()
        h = self.config.health
        layout_report = self.skin.report(now, h.stuck_after)
        placed, others = self.skin.split_placed(self.bridges)
        others.sort()
        unplaced = [b for b in others if self.bridges[b].unmapped_samples]
        # Every placed bridge is reported; of the others (phantoms, strangers, bridges not yet
        # placed by a HELLO) the lowest ids up to _UNPLACED_SHOWN, the rest only counted.
        shown = sorted(placed + others[:_UNPLACED_SHOWN])
        return {
            "t_bridge": None,
            "uptime": 0.0 if self.started is None else now - self.started,
            "links": {name: self._wall_link(link_report(lh, self.ingress.counters(name)))
                      for name, lh in self.links.items()},
            "bridges": {str(b): self._wall_bridge(self.bridges[b].report(now), self.ingress.reassembly_drops.get(b, 0))
                        for b in shown},
            "bridges_not_shown": len(self.bridges) - len(shown),
            "silent": sorted(b for b in shown if self.bridges[b].silent),
            # a bridge not awake is silent: counted without walking every origin
            "silent_count": len(self.bridges) - sum(1 for b in self._awake if not self.bridges[b].silent),
            "unplaced": unplaced[:_UNPLACED_SHOWN],
            "unplaced_count": len(unplaced),
            "forgotten_bridges": self.forgotten_bridges,
            "layout": layout_report,
            "reassembly": self.ingress.reassembler.counters(),
            "duplicates": self.ingress.dedupe.duplicates,
            "dedupe": self.ingress.dedupe.counters(),
            "commands": {"in_flight": len(self.commands), "unmatched_replies": self.commands.unmatched_replies},
            "frames": {**self.times.counters(now), "unknown_element_frames": self.unknown_element_frames},
        }

    def _wall_bridge(self, report: dict[str, Any], reassembly_drops: int) -> dict[str, Any]:
        for key in ("first_seen", "last_seen"):
            report[key] = self._wall(report[key])
        report["reassembly_drops"] = reassembly_drops
        return report

    def _wall_link(self, report: dict[str, Any]) -> dict[str, Any]:
        for key in ("connected_since", "last_data"):
            report[key] = self._wall(report[key])
        return report

    def topology_body(self, now: float) -> dict[str, Any]:
        """The fields of a ``topology`` message at ``now`` (control's ``topology`` answers with them)."""
        body = self.topology.report(now, self.config.health.bridge_timeout, self.skin.split_placed,
                                    _UNPLACED_SHOWN)
        for node in body["bridges"].values():
            node["last_seen"] = self._wall(node["last_seen"])
        body["t_bridge"] = None
        body["layout"] = self.skin.layout_report()
        body["skin"] = skin_report(self.surface)
        return body

    # -- the skin description (links, patches; see daemon/surface.py) --------------------
    def _surface_spec(self, spec: ContactSpec) -> ContactSpec:
        """The contact spec with the description's bands (contacts across wrap seams), when
        there is a description and its atlas is the layout."""
        bands = self.surface.bands if self.surface is not None else ()
        if not bands or spec.bands == bands:
            return spec
        memo = self._spec_memo
        if memo is None or memo[0] is not spec:
            self._spec_memo = memo = (spec, replace(spec, bands=bands))
        return memo[1]

    # -- commands -----------------------------------------------------------------------
    def command(self, op: int, value: int | None, target: int | None, now: float,
                timeout: float) -> tuple[Pending, list[LinkWrite]]:
        """Start a command to one bridge (``target``) or all alive (None): returns it (its
        ``token`` names it in :meth:`finished_commands`) and the link writes that send it.
        Raises ValueError for a bridge never heard from."""
        if target is None:
            self._fold_heard()
            alive = {b for b, bh in self.bridges.items() if not bh.silent}
            pending = self.commands.start(op, value, alive, now, timeout)
            data = command_bytes(ADDR_BROADCAST, pending.token, op, value)  # type: ignore[arg-type]  # an Op value: the control layer checks it
            return pending, [LinkWrite(name, data) for name in self.links]
        links = self.topology.links_of(target)
        if not links:
            raise ValueError(f"bridge {target} has not been heard from on any link")
        pending = self.commands.start(op, value, {target}, now, timeout)
        data = command_bytes(target, pending.token, op, value)  # type: ignore[arg-type]  # an Op value: the control layer checks it
        return pending, [LinkWrite(name, data) for name in links]

    def finished_commands(self, now: float) -> list[Pending]:
        """Commands whose bridges all answered, or whose time ran out by ``now`` (each once)."""
        return self.commands.done(now) if len(self.commands) else []

    def commands_in_flight(self) -> int:
        return len(self.commands)

    def tare(self, bridges: list[int] | None) -> int:
        """Re-take the baselines of ``bridges``' elements (None: all) now; the next
        :meth:`contact_job` comes at once. Returns how many elements were tared."""
        return self.skin.tare(bridges)

    def reconfigure(self, config: Config, layout: SkinLayout | None) -> None:
        """SIGHUP: take the reloadable settings. The element stages are rebuilt only when
        their settings or the layout changed: a SIGHUP that changes nothing of theirs (log
        rotation, client keys) must not erase a press being held. Baselines are re-taken
        only when calibration or inverse settings changed, and then only for every element;
        a new layout or new contact settings keep those of elements that kept their place."""
        old, self.config = self.config, config
        self.times.configure(config.frames.margin, config.health.bridge_timeout, config.frames.max_pending)
        sk = self.skin
        same_layout = (layout is None and not sk.from_file) or (
            layout is not None and sk.from_file and sk.layout is not None and layout_dict(layout) == layout_dict(sk.layout))
        if same_layout and skin_settings(old) == skin_settings(config):
            sk.config = config
            return
        geometry = self.skin.geometry
        # Calibration and inverse unchanged: elements that keep their place keep their
        # baselines (a press held across the reload goes on, and so does its contact's id).
        same_elements = (old.calibration, old.inverse) == (config.calibration, config.inverse)
        self.skin = LayoutStages(config, layout, sk if same_elements else None)
        self.skin.hello(geometry)
        self._forget_floor = -math.inf

    # -- links and subscribers --------------------------------------------------------------
    def link_state(self, link: str, connected: bool, now: float, error: str = "") -> None:
        """``link`` came up (its stream decoder starts afresh) or went down (``error``: why)."""
        lh = self.links.get(link)
        if lh is None:
            lh = self.links[link] = LinkHealth(link)
        lh.set_state(connected, now, error)
        if connected:
            self.ingress.reset_link(link)

    def link_stats(self, link: str, stats: dict[str, Any]) -> None:
        """The shell's own counters of ``link`` (writes dropped, capture): shown in its health."""
        lh = self.links.get(link)
        if lh is not None:
            lh.extra = stats

    def want(self, topics: set[str] | None) -> None:
        """Build only messages of ``topics`` (those with subscribers); None: every topic."""
        self.wanted = None if topics is None else set(topics)

    def summary(self) -> str:
        """One line for the service manager's status: links up, bridges alive."""
        self._fold_heard()
        alive = sum(1 for b in self.bridges.values() if not b.silent)
        up = sum(1 for h in self.links.values() if h.connected)
        return f"{up}/{len(self.links)} links up, {alive}/{len(self.bridges)} bridges alive"
