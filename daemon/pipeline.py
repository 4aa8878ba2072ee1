"""The daemon's sans-I/O core: (link, bytes, host time) in → messages to publish out;
commands in → CMD frames out.

No sockets, no asyncio, no clock: the shells pass the time, so the same object runs
under the service, in tests fed synthesized bytes, and on replayed captures with
their recorded times (which is what makes golden-output tests exact). One call of
:meth:`Pipeline.feed` handles one read of a link as a batch: frames are decoded, then
every later stage works on numpy columns of all the batch's samples.

Contact estimation is deliberately *not* in ``feed``: it is slow next to ingest, so
the shell asks :meth:`Pipeline.contact_snapshot` for the newest consistent state whenever
it is free and runs the estimator on that (one moment of the skin, never a backlog;
see :mod:`cellbridge.daemon.moment`).
"""

from __future__ import annotations

import math
from collections import Counter
from typing import Any

import numpy as np

from cellbridge.daemon.clock import BridgeClock, rows_to_host
from cellbridge.daemon.commands import CommandTracker, Pending
from cellbridge.daemon.config import Config
from cellbridge.daemon.health import BridgeHealth, LinkHealth, link_report
from cellbridge.daemon.physics import ContactSnapshot, Frontend, chip_params, default_params, layout_dict
from cellbridge.daemon.skin import Skin
from cellbridge.daemon.topology import Topology
from cellbridge.daemon.wire import ADDR_BROADCAST, OPS, Decoded, Ingress, SampleColumns, command_bytes
from cellbridge.tactile import ElementParams, SkinLayout

SCHEMA_VERSION = 1
Message = tuple[str, dict[str, Any]]
_GATE_OP = int(OPS["gate"])
_SKIN_SECTIONS = ("calibration", "inverse", "contact")  # what the element and contact stages are built from


class Pipeline:
    def __init__(self, config: Config, layout: SkinLayout | None = None) -> None:
        self.config = config
        s = config.sections
        self.ingress = Ingress(s["protocol"]["dedupe_window"], s["protocol"]["reassembly_timeout"])
        self.chip = chip_params(s["chip"])
        self.frontend = Frontend(default_params(layout) if layout is not None else ElementParams(), self.chip)
        self.skin = Skin(s, layout)
        self.gate = np.full(0x10000, float(self.chip.gate_cycles))
        self._bits = s["chip"]["cycle_bits"]
        # Each bridge's clock parameters, indexed by bridge id, so a batch maps in one vector step.
        self._ref = np.zeros(0x10000, dtype=np.uint64)
        self._t_ref = np.full(0x10000, np.nan)
        self._k = np.ones(0x10000)
        self._hz = np.full(0x10000, float(self.chip.clock_hz))
        self.clocks: dict[int, BridgeClock] = {}
        self.bridges: dict[int, BridgeHealth] = {}
        self.links: dict[str, LinkHealth] = {ln.name: LinkHealth(ln.url) for ln in config.links}
        self.topology = Topology()
        self.commands = CommandTracker()
        self.wanted: set[str] | None = None  # topics with subscribers; None = build all
        self.seq: dict[str, int] = {}
        self.started: float | None = None
        self.last_feed = 0.0
        self._next_health = -math.inf
        self._last_tick = -math.inf
        self._last_health = -math.inf
        self.forgotten_bridges = 0
        self.announced_silent: set[int] = set()
        self.events: list[tuple[str, str]] = []  # (level, text) for the shell to log

    # -- helpers ------------------------------------------------------------------------
    def _message(self, topic: str, now: float, body: dict[str, Any]) -> Message:
        n = self.seq.get(topic, 0)
        self.seq[topic] = n + 1
        return topic, {"v": SCHEMA_VERSION, "seq": n, "t_host": now, **body}

    def _want(self, topic: str) -> bool:
        return self.wanted is None or topic in self.wanted

    def _bridge(self, bid: int, now: float) -> BridgeHealth:
        b = self.bridges.get(bid)
        if b is None:
            b = self.bridges[bid] = BridgeHealth(first_seen=now, clock_hz=self.chip.clock_hz)
        return b

    def _clock(self, bid: int) -> BridgeClock:
        c = self.clocks.get(bid)
        if c is None:
            hz = self.bridges[bid].clock_hz if bid in self.bridges else self.chip.clock_hz
            c = self.clocks[bid] = BridgeClock(hz, bits=self.config["chip"]["cycle_bits"])
        return c

    # -- ingest -------------------------------------------------------------------------
    def feed(self, link: str, data: bytes, now: float) -> list[Message]:
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
            out.extend(self._samples(link, dec.samples, now))
        return out

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
        for origin in dec.boots:  # its cycle counter restarted too, perhaps by less than the clock's jump limit
            if origin in self.clocks and self.clocks.pop(origin).synced:
                self._bridge(origin, now).clock_resets += 1
                self.events.append(("warning", f"bridge {origin}: restarted (HELLO 0), resynchronising its clock"))
        for origin, h in dec.hellos:
            b = self._bridge(origin, now)
            if b.clock_hz != h.clock_hz and h.clock_hz > 0:
                b.clock_hz = float(h.clock_hz)
                self.clocks.pop(origin, None)
        for origin, src, bc in dec.beacons:
            self.topology.beacon(origin, bc.parent, bc.path_etx, bc.hops)
        for origin, st in dec.statuses:
            self.topology.status(origin, st.parent, st.path_etx, {n.bridge: n.link_etx for n in st.neighbours},
                                 st.queue_drops, st.retries, st.resets)
        if dec.hellos and self.skin.hello({o: (h.x, h.y, h.side) for o, h in dec.hellos}):
            self.events.append(("info", f"layout from HELLO now has {self.skin.layout.n} elements"))  # type: ignore[union-attr]
            if self._want("topology"):
                out.append(self._message("topology", now, self._topology_body(now)))
        for origin, reply in dec.replies:
            p = self.commands.reply(origin, reply, now)
            if p is not None and p.op == _GATE_OP and reply.status.name == "OK":
                gate = reply.value if reply.value else p.value
                if gate:
                    self.gate[origin] = float(gate)

    def _sync_clocks(self, s: SampleColumns, now: float) -> tuple[np.ndarray, np.ndarray]:
        """Feed each bridge's clock its newest sample; (host time, bridge time) of every sample."""
        origin_list = s.origin.tolist()
        newest = {o: i for i, o in enumerate(origin_list)}  # each bridge's newest sample
        counts = Counter(origin_list)
        for o, i in newest.items():
            b = self._bridge(o, now)
            clk = self._clock(o)
            cyc = int(s.cycle[i])
            if clk.observe(cyc, now):
                b.clock_resets += 1
                self.events.append(("warning", f"bridge {o}: clock restarted (reset?), resynchronising"))
            b.samples += counts[o]
            b.last_cycle = cyc
            self._ref[o], self._t_ref[o], self._k[o], self._hz[o] = clk.params()
        o = s.origin
        hz = self._hz[o]
        t_sample = rows_to_host(s.cycle, self._ref[o], self._t_ref[o], self._k[o], hz, self._bits)
        return t_sample, s.cycle.astype(np.float64) / hz

    def _samples(self, link: str, s: SampleColumns, now: float) -> list[Message]:
        t_sample, t_bridge = self._sync_clocks(s, now)
        o = s.origin
        raw = np.stack([s.c1, s.c2], axis=1)
        caps_all, sat_all = self.frontend.capacitance(s.mode, s.oversampling, raw, s.flags, self.gate[o])
        rows = self.skin.rows_of(o, s.element)
        placed = rows >= 0
        all_placed = bool(placed.all())
        if not all_placed:
            for b_id, cnt in Counter(o[~placed].tolist()).items():
                self.bridges[b_id].unmapped_samples += cnt
        out: list[Message] = []
        if self._want("raw"):
            out.append(self._message("raw", now, {
                "link": link, "bridge": s.origin.tolist(), "element": s.element.tolist(),
                "cycle": s.cycle.tolist(), "t_bridge": t_bridge.tolist(), "c1": s.c1.tolist(),
                "c2": s.c2.tolist(), "flags": s.flags.tolist(), "mode": s.mode.tolist(),
                "oversampling": s.oversampling.tolist(),
            }))
        sk = self.skin
        if sk.elements is None or not placed.any():
            return out
        sel = slice(None) if all_placed else placed
        r = rows[sel]
        caps = caps_all[sel]
        last = {x: i for i, x in enumerate(r.tolist())}  # each element's newest sample
        groups = (np.fromiter(last, np.int64, len(last)), np.fromiter(last.values(), np.int64, len(last)))
        assert sk.channels is not None
        sk.channels.update(r, raw[sel], sat_all[sel], groups, now)
        res = sk.elements.step(r, caps, groups, now)
        sk.record(r, t_sample[sel], s.cycle[sel], res, groups[0].shape[0] == r.shape[0], now)
        if self._want("element"):
            out.append(self._message("element", now, {
                "bridge": o[sel].tolist(), "element": s.element[sel].tolist(),
                "cycle": s.cycle[sel].tolist(), "t_bridge": t_bridge[sel].tolist(),
                "t_sample": t_sample[sel].tolist(), "c1": caps[:, 0].tolist(), "c2": caps[:, 1].tolist(),
                "dc1": res["dc1"].tolist(), "dc2": res["dc2"].tolist(), "force": res["force"].tolist(),
                "area": res["area"].tolist(), "valid": res["valid"].tolist(), "status": res["status"].tolist(),
                "touched": res["touched"].tolist(),
            }))
        return out

    # -- contacts -----------------------------------------------------------------------
    def contact_snapshot(self) -> ContactSnapshot | None:
        """The skin at one moment, if that moment advanced since the last snapshot: each
        element's reading at or just before the newest time every live element has
        reported past (bridges silent for ``bridge_timeout`` hold nothing back), stamped
        with the arrival time of the newest data. Not the newest reading of each element:
        bridges' frames arrive staggered, and a skin half pressed, half not, gives ghosts."""
        if not self.config["contact"]["enabled"]:
            return None
        return self.skin.snapshot(self.last_feed, self.config["health"]["bridge_timeout"])

    def contact_message(self, snap: ContactSnapshot, contacts: list[dict[str, Any]]) -> Message:
        index = {int(b): i for i, b in enumerate(snap.ids)}
        for c in contacts:
            rows = [index[e] for e in c["elements"]]
            c["cycles"] = [int(snap.cycle[i]) for i in rows]
            ts = [float(snap.t_sample[i]) for i in rows if math.isfinite(snap.t_sample[i])]
            c["t_sample"] = max(ts) if ts else None
        t = snap.t_moment if math.isfinite(snap.t_moment) else None
        return self._message("contact", snap.t_host, {"t_sample": t, "t_bridge": None, "contacts": contacts})

    # -- periodic -----------------------------------------------------------------------
    def host_clock_step(self, delta: float) -> None:
        """The host's wall clock stepped by ``delta`` s (NTP): every bridge clock follows at once."""
        for clk in self.clocks.values():
            clk.host_step(delta)
        self.events.append(("warning", f"host clock stepped by {delta:+.3f} s; bridge clocks follow"))

    def tick(self, now: float, force: bool = False) -> list[Message]:
        """Health every ``health.interval`` (or now, if forced) and topology when it changed."""
        h = self.config["health"]
        if now < self._last_tick:
            self._clock_stepped_back(now)
        self._last_tick = now
        if now < self._next_health and not force:
            return []
        interval = h["interval"]
        self._next_health = now + interval
        # Over the time since the health before (often more than the interval), not the interval.
        elapsed = now - self._last_health if 0 < now - self._last_health < math.inf else interval
        self._last_health = now
        self.ingress.reassembler.expire(now)
        for bid, b in self.bridges.items():
            b.rate = (b.samples - b._samples_at_tick) / elapsed
            b._samples_at_tick = b.samples
            silent = now - b.last_seen > h["bridge_timeout"]
            if silent and not b.silent:
                self.events.append(("warning", f"no data from bridge {bid} for {now - b.last_seen:.1f} s"))
            elif b.silent and not silent:
                self.events.append(("info", f"bridge {bid} is back"))
            b.silent = silent
        self._forget(now - h["forget_after"])
        out = []
        if self._want("health"):
            out.append(self._message("health", now, self.health_body(now)))
        topo = self._topology_body(now)
        if self.topology.changed(topo) and self._want("topology"):
            out.append(self._message("topology", now, topo))
        return out

    def _forget(self, before: float) -> None:
        """Drop bridges the layout does not place that were last heard ``before``: phantoms
        of a noisy line or strangers would otherwise grow health and every tick forever."""
        gone = [bid for bid, b in self.bridges.items() if b.last_seen < before and not self.skin.placed(bid)]
        for bid in gone:
            del self.bridges[bid]
            self.clocks.pop(bid, None)
            self.topology.nodes.pop(bid, None)
            self.ingress.reassembly_drops.pop(bid, None)
        self.forgotten_bridges += len(gone)

    def _clock_stepped_back(self, now: float) -> None:
        """The host clock went back (NTP step, RTC set): times kept from before lie in the
        future and would hold back health, silence and command deadlines for as long as
        the step. They are taken as "now": a dead bridge is then reported silent
        ``bridge_timeout`` after the step, not hours later."""
        self._next_health = min(self._next_health, now)
        for b in self.bridges.values():
            b.last_seen = min(b.last_seen, now)
            b.first_seen = min(b.first_seen, now)
        self.topology.clock_stepped_back(now)
        self.commands.clock_stepped_back(now)
        self.events.append(("warning", "host clock stepped back; liveness and deadlines counted from now"))

    def health_body(self, now: float) -> dict[str, Any]:
        h = self.config["health"]
        layout_report = self.skin.report(now, h["stuck_after"])
        unplaced = sorted(b for b, bh in self.bridges.items() if bh.unmapped_samples and not self.skin.placed(b))
        return {
            "t_bridge": None,
            "uptime": 0.0 if self.started is None else now - self.started,
            "links": {name: link_report(lh, self.ingress.counters(name)) for name, lh in self.links.items()},
            "bridges": {str(b): {**bh.report(now), "reassembly_drops": self.ingress.reassembly_drops.get(b, 0)}
                        for b, bh in sorted(self.bridges.items())},
            "silent": sorted(b for b, bh in self.bridges.items() if bh.silent),
            "unplaced": unplaced,
            "forgotten_bridges": self.forgotten_bridges,
            "layout": layout_report,
            "reassembly": self.ingress.reassembler.counters(),
            "duplicates": self.ingress.dedupe.duplicates,
            "dedupe": self.ingress.dedupe.counters(),
            "commands": {"in_flight": len(self.commands), "unmatched_replies": self.commands.unmatched_replies},
        }

    def _topology_body(self, now: float) -> dict[str, Any]:
        body = self.topology.report(now, self.config["health"]["bridge_timeout"])
        body["t_bridge"] = None
        body["layout"] = self.skin.layout_report()
        return body

    def topology_body(self, now: float) -> dict[str, Any]:
        return self._topology_body(now)

    # -- commands -----------------------------------------------------------------------
    def command(self, op: int, value: int | None, target: int | None, now: float,
                timeout: float) -> tuple[Pending, list[tuple[str, bytes]]]:
        """Start a command to one bridge (``target``) or all (None); returns it and the
        (link, bytes) writes. Raises ValueError for a bridge never heard from."""
        if target is None:
            alive = {b for b, bh in self.bridges.items() if not bh.silent}
            pending = self.commands.start(op, value, alive, now, timeout)
            data = command_bytes(ADDR_BROADCAST, pending.token, op, value)  # type: ignore[arg-type]
            return pending, [(name, data) for name in self.links]
        links = self.topology.links_of(target)
        if not links:
            raise ValueError(f"bridge {target} has not been heard from on any link")
        pending = self.commands.start(op, value, {target}, now, timeout)
        data = command_bytes(target, pending.token, op, value)  # type: ignore[arg-type]
        return pending, [(name, data) for name in links]

    def tare(self, bridges: list[int] | None) -> int:
        return self.skin.tare(bridges)

    def reconfigure(self, config: Config, layout: SkinLayout | None) -> None:
        """SIGHUP: take the reloadable settings. The element stages are rebuilt (baselines
        re-taken) only when their settings or the layout changed: a SIGHUP that changes
        nothing of theirs (log rotation, client keys) must not erase a press being held."""
        old, self.config = self.config, config
        sk = self.skin
        same_layout = (layout is None and not sk.from_file) or (
            layout is not None and sk.from_file and sk.layout is not None and layout_dict(layout) == layout_dict(sk.layout))
        if same_layout and all(old[s] == config[s] for s in _SKIN_SECTIONS):
            sk.sections = config.sections
            return
        geometry = self.skin.geometry
        self.skin = Skin(config.sections, layout)
        self.skin.hello(geometry)

    # -- links ----------------------------------------------------------------------------
    def link_state(self, link: str, connected: bool, now: float, error: str = "") -> None:
        lh = self.links.get(link)
        if lh is None:
            lh = self.links[link] = LinkHealth(link)
        lh.set_state(connected, now, error)
        if connected:
            self.ingress.reset_link(link)
