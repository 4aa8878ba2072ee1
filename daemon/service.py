"""The asyncio service: links, PUB, control, ticking, contacts and signals around one :class:`Pipeline`.

Everything here is a thin shell: each task moves bytes or messages between the
outside (serial lines, ZeroMQ sockets, signals) and the sans-I/O pipeline. Contact
estimation runs in one worker *process* on the newest snapshot whenever the worker is
free, so a slow estimate delays the next estimate, never ingest (a thread would hold
the interpreter lock for milliseconds at a time and stall the event loop).
"""

from __future__ import annotations

import asyncio
import gc
import logging
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
import zmq
import zmq.asyncio

from cellbridge._version import __version__
from cellbridge.config import load_layout
from cellbridge.daemon.config import SECTIONS, Config, ConfigError, load_config
from cellbridge.daemon.contact_worker import ContactWorker
from cellbridge.daemon.control_server import ControlServer
from cellbridge.daemon.links import Link, ReplayLink, SerialLink
from cellbridge.daemon.logs import event, setup
from cellbridge.daemon.ops import OpsHooks
from cellbridge.daemon.pipeline import Pipeline
from cellbridge.daemon.publisher import Publisher
from cellbridge.tactile import SkinLayout


def read_layout(config: Config) -> SkinLayout | None:
    path = config.layout_path()
    return None if path is None else load_layout(path)


class Service:
    TICK = 0.1  # s between pipeline ticks (health itself goes out every health.interval)
    HOST_STEP = 0.005  # s: a change of wall minus monotonic time beyond this is a clock step

    def __init__(self, config: Config, layout: SkinLayout | None = None, *, config_path: str | Path | None = None,
                 hooks: OpsHooks | None = None) -> None:
        self.config = config
        self.config_path = config_path
        self.log = setup(config["daemon"]["log_level"], config["daemon"]["log_format"])
        self.pipeline = Pipeline(config, layout)
        self._wall_offset = time.time() - time.monotonic()
        self.hooks = hooks if hooks is not None else OpsHooks(config)
        self.links: dict[str, Link] = {}
        self._fresh = asyncio.Event()
        self._stop = asyncio.Event()
        self._tasks: list[asyncio.Task[Any]] = []
        self.contacts = ContactWorker(self.log)
        self._contacts_shown = False
        self._feeds_since_snapshot = 0
        self.ingest_errors = 0
        self._busy = np.zeros(4096)  # s spent on each of the last reads, bytes to published messages
        self._n_reads = 0
        self._lag_max = 0.0  # s, since the last health message

    # -- ingest -------------------------------------------------------------------------
    def _on_data(self, link: str, data: bytes, now: float) -> None:
        t0 = time.perf_counter()
        self.pub.serial(link, data, now)
        p = self.pipeline
        publish = self.pub.publish
        try:
            for topic, payload in p.feed(link, data, now):
                publish(topic, payload)
        except Exception:  # a bug must cost one read, not the daemon
            self.ingest_errors += 1
            self.log.exception("ingest failed on one read", extra={"fields": {"link": link, "bytes": len(data)}})
        if len(p.commands):
            self.control.resolve(now)
        if p.events:
            self._log_events()
        self._feeds_since_snapshot += 1
        self._fresh.set()
        self._busy[self._n_reads % self._busy.shape[0]] = time.perf_counter() - t0
        self._n_reads += 1

    def _on_state(self, link: str, connected: bool, why: str) -> None:
        self.pipeline.link_state(link, connected, time.time(), why)
        if connected:
            event(self.log, "info", "link up", link=link, url=self.links[link].cfg.url)
        else:
            event(self.log, "warning", "link down", link=link, reason=why)

    def _log_events(self) -> None:
        for level, text in self.pipeline.events:
            event(self.log, level, text)
        self.pipeline.events.clear()

    def _make_link(self, cfg: Any) -> Link:
        if cfg.is_replay:
            gate = self._wait_subscriber if cfg.wait_for_subscriber else None
            return ReplayLink(cfg, self._on_data, self._on_state, gate, self._replay_done)
        return SerialLink(cfg, self._on_data, self._on_state)

    async def _wait_subscriber(self) -> None:
        await self.pub.subscribed.wait()

    def _replay_done(self, name: str) -> None:
        event(self.log, "info", "replay finished", link=name, records=self.links[name].stats()["replayed_records"])
        exits = [ln for ln in self.links.values() if ln.cfg.exit_when_done]
        if exits and all(isinstance(ln, ReplayLink) and ln.finished for ln in exits):
            self._stop.set()

    # -- periodic -----------------------------------------------------------------------
    async def _ticker(self) -> None:
        next_status = 0.0
        while True:
            try:
                next_status = self._tick_once(next_status)
            except Exception:  # a bug must cost one tick, not every health message from now on
                self.log.exception("tick failed")
            asked = time.perf_counter()
            await asyncio.sleep(self.TICK)
            # How late the loop woke us: time the loop spent on other work (or did not get the CPU).
            self._lag_max = max(self._lag_max, time.perf_counter() - asked - self.TICK)

    def _tick_once(self, next_status: float) -> float:
        """Health, command deadlines, logged events, and every 5 s sd_notify STATUS and
        capture flushes; returns when the next STATUS is due."""
        now = time.time()
        step = (now - time.monotonic()) - self._wall_offset
        if abs(step) > self.HOST_STEP:  # the wall clock stepped (NTP): the bridge clocks follow at once
            self._wall_offset += step
            self.pipeline.host_clock_step(step)
        self._link_stats()
        for topic, payload in self.pipeline.tick(now):
            if topic == "health":
                payload.update(self._shell_health())
                self._lag_max = 0.0  # each health message reports the lag since the one before
            self.pub.publish(topic, payload)
        self.control.resolve(now)
        self._log_events()
        if now >= next_status or next_status - now > 5.0:  # (the host clock may step back)
            next_status = now + 5.0
            self.hooks.status(self._summary(now))
            for link in self.links.values():
                cap = getattr(link, "capture", None)
                if cap is not None:
                    cap.flush()
        return next_status

    async def _watchdog(self, interval: float) -> None:
        while True:
            self.hooks.watchdog()
            await asyncio.sleep(interval)

    def _summary(self, now: float) -> str:
        bridges = self.pipeline.bridges
        alive = sum(1 for b in bridges.values() if not b.silent)
        up = sum(1 for h in self.pipeline.links.values() if h.connected)
        return f"{up}/{len(self.links)} links up, {alive}/{len(bridges)} bridges alive"

    def _link_stats(self) -> None:
        """The links' own counters into the pipeline's link health, before it builds health."""
        for name, link in self.links.items():
            lh = self.pipeline.links.get(name)
            if lh is not None:
                lh.extra = link.stats()

    def _shell_health(self) -> dict[str, Any]:
        recent = self._busy[:min(self._n_reads, self._busy.shape[0])]
        p50, p99 = (np.percentile(recent, [50, 99]) * 1e3).tolist() if recent.size else (None, None)
        ingest = {"reads": self._n_reads, "errors": self.ingest_errors, "ms_per_read_p50": p50,
                  "ms_per_read_p99": p99, "ms_per_read_max": float(recent.max() * 1e3) if recent.size else None,
                  "loop_lag_ms_max": self._lag_max * 1e3}
        out = {"pub": self.pub.stats(), "contact_estimation": dict(self.contacts.stats), "ingest": ingest}
        security = self.hooks.counters()
        if security:
            out["security"] = security
        return out

    def status_body(self, now: float) -> dict[str, Any]:
        self._link_stats()
        body = self.pipeline.health_body(now)
        body.update(self._shell_health(), version=__version__, t_host=now)
        return body

    # -- contacts -----------------------------------------------------------------------
    async def _contacts(self) -> None:
        while True:
            await self._fresh.wait()
            self._fresh.clear()
            started = time.perf_counter()
            await self._contact_once()
            rest = 1.0 / self.config["contact"]["rate"] - (time.perf_counter() - started)
            if rest > 0:
                await asyncio.sleep(rest)

    async def _contact_once(self) -> None:
        if "contact" not in self.pub.wanted:
            return
        snap = self.pipeline.contact_snapshot()
        spec = self.pipeline.skin.contact_spec
        if snap is None or spec is None:
            return
        self.contacts.stats["feeds_skipped"] += max(0, self._feeds_since_snapshot - 1)
        self._feeds_since_snapshot = 0
        contacts = await self.contacts.estimate(spec, snap, self.config["contact"]["worker_timeout"])
        if contacts is None:
            return
        if contacts or self._contacts_shown:  # publish every estimate with contacts, and the first without
            self.pub.publish(*self.pipeline.contact_message(snap, contacts))
        self._contacts_shown = bool(contacts)

    # -- reload -------------------------------------------------------------------------
    def reload(self) -> None:
        """SIGHUP: re-read the config file and apply what can change without a restart."""
        self.hooks.reloading()
        if self.config_path is None:
            event(self.log, "warning", "reload ignored: started without a config file")
            self.hooks.ready("reloaded (nothing to do)")
            return
        try:
            new = load_config(self.config_path)
            layout = read_layout(new)
        except (ConfigError, ValueError) as exc:
            event(self.log, "error", "reload rejected, keeping the running config", error=str(exc))
            self.hooks.ready("reload rejected")
            return
        fixed = [f"{s}.{k}" for s, keys in SECTIONS.items() for k, spec in keys.items()
                 if not spec.reloadable and new[s][k] != self.config[s][k]]
        if new.links != self.config.links:
            fixed.append("link")
        if fixed:
            event(self.log, "warning", "reload: these changes need a restart", keys=fixed)
        self.config = new
        self.log.setLevel(new["daemon"]["log_level"].upper())
        self.pipeline.reconfigure(new, layout)
        try:
            self.hooks.reload_keys()
        except ValueError as exc:
            event(self.log, "error", "allowed client keys not reloaded, keeping the previous ones", error=str(exc))
        event(self.log, "info", "config reloaded", source=new.source)
        self.hooks.ready("reloaded")

    # -- lifecycle ----------------------------------------------------------------------
    def _bind(self, ctx: zmq.asyncio.Context) -> None:
        c = self.config
        self.pub = Publisher(ctx, c["pub"]["endpoint"], c["pub"]["hwm"], c["pub"]["count_drops"], c["pub"]["source"])
        self.ctl = ctx.socket(zmq.ROUTER)
        self.ctl.setsockopt(zmq.LINGER, 500)
        self.control = ControlServer(self.ctl, self, self.log)
        for sock, endpoint in ((self.pub.sock, c["pub"]["endpoint"]), (self.ctl, c["control"]["endpoint"])):
            self.hooks.secure(ctx, sock, endpoint)  # OPS: security check and CURVE, before bind
            sock.bind(endpoint)
        self.pub.on_wanted = self._wanted_changed

    def _wanted_changed(self, wanted: set[str]) -> None:
        self.pipeline.wanted = wanted

    async def run(self) -> int:
        loop = asyncio.get_running_loop()
        ctx = zmq.asyncio.Context()
        try:
            self._bind(ctx)
        except (zmq.ZMQError, ValueError) as exc:
            event(self.log, "error", "cannot bind", error=str(exc))
            ctx.destroy(linger=0)
            return 1
        self.pipeline.wanted = set()
        for cfg in self.config.links:
            self.links[cfg.name] = self._make_link(cfg)
        loop.add_signal_handler(signal.SIGTERM, self._stop.set)
        loop.add_signal_handler(signal.SIGINT, self._stop.set)
        loop.add_signal_handler(signal.SIGHUP, self.reload)
        link_tasks = [asyncio.create_task(ln.run(), name=f"link {n}") for n, ln in self.links.items()]
        self._tasks = [asyncio.create_task(c) for c in (self._ticker(), self._contacts(), self.control.serve(),
                                                        self.pub.watch_subscriptions())]
        if self.config["contact"]["enabled"]:
            self.contacts.start()
        if self.hooks.watchdog_interval:
            self._tasks.append(asyncio.create_task(self._watchdog(self.hooks.watchdog_interval)))
        event(self.log, "info", "daemon started", version=__version__, pub=self.config["pub"]["endpoint"],
              control=self.config["control"]["endpoint"], links=list(self.links))
        # Start-up objects (numpy, zmq, the layout) never die: keep them out of the cyclic
        # collector's full passes, which pause the event loop for the time they take.
        gc.collect()
        gc.freeze()
        self.hooks.ready(self._summary(time.time()))  # OPS: READY=1 once links run and sockets are bound
        try:
            await self._stop.wait()
        finally:
            self.hooks.stopping()  # OPS: STOPPING=1
            event(self.log, "info", "stopping: draining")
            await self._drain(link_tasks)
            for s in (self.pub.sock, self.ctl):
                s.close()
            self.hooks.close()
            ctx.term()
            self.contacts.close()
            for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
                loop.remove_signal_handler(sig)
            event(self.log, "info", "stopped")
        return 0

    async def _drain(self, link_tasks: list[asyncio.Task[Any]]) -> None:
        """Stop reading, finish what was read (last contact estimate, pending replies), say goodbye."""
        for t in link_tasks:
            t.cancel()
        await asyncio.gather(*link_tasks, return_exceptions=True)
        await self.contacts.idle()  # a running estimate finishes and is published
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        await self.control.finish()
        await self._contact_once()  # the newest state, if the last estimate did not see it
        now = time.time()
        self._link_stats()
        for topic, payload in self.pipeline.tick(now, force=True):
            if topic == "health":
                payload.update(self._shell_health())
            self.pub.publish(topic, payload)
        self._log_events()


def run_service(config_path: str | Path | None, config: Config) -> int:
    layout = read_layout(config)
    service = Service(config, layout, config_path=config_path)
    return asyncio.run(service.run())


logging.getLogger("asyncio").setLevel(logging.WARNING)
