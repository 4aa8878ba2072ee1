"""The asyncio service: links, PUB, control, ticking, contacts and signals around one :class:`Pipeline`.

Everything here is a thin shell: each task moves bytes or messages between the
outside (serial lines, ZeroMQ sockets, signals) and the sans-I/O pipeline. Contact
estimation runs in one worker *process* on the newest snapshot whenever the worker is
free, so a slow estimate delays the next estimate, never ingest (a thread would hold
the interpreter lock for milliseconds at a time and stall the event loop).
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import concurrent.futures.process
import gc
import logging
import multiprocessing
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
from cellbridge.daemon.control import COMMANDS, Request, RequestError, error, parse_request, reply
from cellbridge.daemon.links import Link, ReplayLink, SerialLink
from cellbridge.daemon.logs import event, setup
from cellbridge.daemon.physics import estimate_in_worker, warm_up
from cellbridge.daemon.pipeline import Pipeline
from cellbridge.daemon.publisher import Publisher, pack
from cellbridge.daemon.wire import PING
from cellbridge.tactile import SkinLayout


class OpsHooks:
    """Where the operations pieces plug in (see DAEMON_OPS_API.md); no-ops here.

    On merge the lead wires ``cellbridge.daemon.security`` into :meth:`secure`
    (``check_bind`` for every endpoint, ``CurveServer.apply`` when CURVE is configured)
    and ``cellbridge.daemon.notify.Notifier`` into the lifecycle methods. The service
    calls them at exactly the points the agreed interface names.
    """

    watchdog_interval: float | None = None  # s; Notifier.watchdog_interval

    def __init__(self, config: Config) -> None:
        self.config = config

    def secure(self, ctx: zmq.asyncio.Context, socket: zmq.Socket, endpoint: str) -> None:  # BINDING
        """Before binding ``socket`` to ``endpoint``: refuse a non-loopback bind without CURVE keys."""

    def ready(self, status: str) -> None:  # READINESS: links and sockets are up
        pass

    def status(self, text: str) -> None:  # one-line summary every few seconds
        pass

    def watchdog(self) -> None:  # WATCHDOG: from the event loop, every watchdog_interval
        pass

    def reloading(self) -> None:  # SIGHUP
        pass

    def stopping(self) -> None:  # SIGTERM
        pass

    def close(self) -> None:  # after the sockets are closed (stop the ZAP authenticator)
        pass


def read_layout(config: Config) -> SkinLayout | None:
    path = config.layout_path()
    return None if path is None else load_layout(path)


class Service:
    TICK = 0.1  # s between pipeline ticks (health itself goes out every health.interval)

    def __init__(self, config: Config, layout: SkinLayout | None = None, *, config_path: str | Path | None = None,
                 hooks: OpsHooks | None = None) -> None:
        self.config = config
        self.config_path = config_path
        self.log = setup(config["daemon"]["log_level"], config["daemon"]["log_format"])
        self.pipeline = Pipeline(config, layout)
        self.hooks = hooks if hooks is not None else OpsHooks(config)
        self.links: dict[str, Link] = {}
        self._waiting: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self._fresh = asyncio.Event()
        self._stop = asyncio.Event()
        self._tasks: list[asyncio.Task[Any]] = []
        self._answers: set[asyncio.Task[Any]] = set()
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self._contact_busy = False
        self._contacts_shown = False
        self.contact_stats = {"runs": 0, "errors": 0, "last_ms": 0.0, "max_ms": 0.0, "feeds_skipped": 0}
        self._feeds_since_snapshot = 0
        self.ingest_errors = 0
        self._busy = np.zeros(4096)  # s spent on each of the last reads, bytes to published messages
        self._n_reads = 0

    # -- ingest -------------------------------------------------------------------------
    def _on_data(self, link: str, data: bytes, now: float) -> None:
        t0 = time.perf_counter()
        p = self.pipeline
        publish = self.pub.publish
        try:
            for topic, payload in p.feed(link, data, now):
                publish(topic, payload)
        except Exception:  # a bug must cost one read, not the daemon
            self.ingest_errors += 1
            self.log.exception("ingest failed on one read", extra={"fields": {"link": link, "bytes": len(data)}})
        if len(p.commands):
            self._resolve(now)
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
            now = time.time()
            for topic, payload in self.pipeline.tick(now):
                if topic == "health":
                    payload.update(self._shell_health())
                self.pub.publish(topic, payload)
            self._resolve(now)
            self._log_events()
            if now >= next_status:
                next_status = now + 5.0
                self.hooks.status(self._summary(now))
                for link in self.links.values():
                    cap = getattr(link, "capture", None)
                    if cap is not None:
                        cap.flush()
            await asyncio.sleep(self.TICK)

    async def _watchdog(self, interval: float) -> None:
        while True:
            self.hooks.watchdog()
            await asyncio.sleep(interval)

    def _summary(self, now: float) -> str:
        bridges = self.pipeline.bridges
        alive = sum(1 for b in bridges.values() if not b.silent)
        up = sum(1 for h in self.pipeline.links.values() if h.connected)
        return f"{up}/{len(self.links)} links up, {alive}/{len(bridges)} bridges alive"

    def _shell_health(self) -> dict[str, Any]:
        for name, link in self.links.items():
            lh = self.pipeline.links.get(name)
            if lh is not None:
                lh.extra = link.stats()
        recent = self._busy[:min(self._n_reads, self._busy.shape[0])]
        p50, p99 = (np.percentile(recent, [50, 99]) * 1e3).tolist() if recent.size else (None, None)
        ingest = {"reads": self._n_reads, "errors": self.ingest_errors, "ms_per_read_p50": p50,
                  "ms_per_read_p99": p99, "ms_per_read_max": float(recent.max() * 1e3) if recent.size else None}
        return {"pub": self.pub.stats(), "contact_estimation": dict(self.contact_stats), "ingest": ingest}

    def status_body(self, now: float) -> dict[str, Any]:
        body = self.pipeline.health_body(now)
        body.update(self._shell_health(), version=__version__, t_host=now)
        return body

    # -- contacts -----------------------------------------------------------------------
    async def _contacts(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await self._fresh.wait()
            self._fresh.clear()
            started = time.perf_counter()
            await self._contact_once(loop)
            rest = 1.0 / self.config["contact"]["rate"] - (time.perf_counter() - started)
            if rest > 0:
                await asyncio.sleep(rest)

    async def _contact_once(self, loop: asyncio.AbstractEventLoop) -> None:
        wanted = self.pub.wanted
        if "contact" not in wanted:
            return
        snap = self.pipeline.contact_snapshot()
        spec = self.pipeline.skin.contact_spec
        if snap is None or spec is None:
            return
        self.contact_stats["feeds_skipped"] += max(0, self._feeds_since_snapshot - 1)
        self._feeds_since_snapshot = 0
        t0 = time.perf_counter()
        if not snap.touched.any():
            contacts: list[dict[str, Any]] = []  # nothing touched: no need to ask the worker
        else:
            self._contact_busy = True
            try:
                contacts = await loop.run_in_executor(self._worker(), estimate_in_worker, spec, snap)
            except Exception as exc:  # a bad estimate (or a dead worker) must not end contact publishing
                self.contact_stats["errors"] += 1
                event(self.log, "error", "contact estimation failed", error=f"{type(exc).__name__}: {exc}")
                if isinstance(exc, concurrent.futures.process.BrokenProcessPool):
                    self._pool = None  # a new worker on the next estimate
                return
            finally:
                self._contact_busy = False
        ms = (time.perf_counter() - t0) * 1e3
        st = self.contact_stats
        st["runs"] += 1
        st["last_ms"], st["max_ms"] = ms, max(st["max_ms"], ms)
        if contacts or self._contacts_shown:  # publish every estimate with contacts, and the first without
            self.pub.publish(*self.pipeline.contact_message(snap, contacts))
        self._contacts_shown = bool(contacts)

    def _worker(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            self._pool = concurrent.futures.ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"))
        return self._pool

    # -- commands -----------------------------------------------------------------------
    def _resolve(self, now: float) -> None:
        for p in self.pipeline.commands.done(now):
            fut = self._waiting.pop(p.token, None)
            if fut is not None and not fut.done():
                fut.set_result(p.result())

    async def command(self, op: int, value: int | None, target: int | None, timeout: float) -> dict[str, Any]:
        now = time.time()
        pending, writes = self.pipeline.command(op, value, target, now, timeout)
        fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._waiting[pending.token] = fut
        sent = [name for name, data in writes if name in self.links and self.links[name].write(data)]
        self._resolve(now)  # a broadcast with nobody alive completes at once
        result = await asyncio.wait_for(fut, timeout + 1.0)
        result["sent_on"] = sent
        return result

    # -- control ------------------------------------------------------------------------
    async def _control(self) -> None:
        while True:
            frames = await self.ctl.recv_multipart()
            task = asyncio.create_task(self._answer(frames))  # a slow command never holds up others
            self._answers.add(task)
            task.add_done_callback(self._answers.discard)

    async def _answer(self, frames: list[bytes]) -> None:
        envelope, body = frames[:-1], frames[-1]
        try:
            req = parse_request(body)
        except RequestError as exc:
            event(self.log, "info", "bad control request", error=str(exc))
            rep = error(str(exc))
        else:
            try:
                rep = await self._execute(req)
            except ValueError as exc:
                rep = error(str(exc), req.id)
            except Exception as exc:  # never let one request take the daemon down
                self.log.exception("control request failed")
                rep = error(f"internal error: {type(exc).__name__}: {exc}", req.id)
        await self.ctl.send_multipart([*envelope, pack(rep)])

    async def _execute(self, req: Request) -> dict[str, Any]:
        now = time.time()
        timeout = req.timeout or self.config["control"]["command_timeout"]
        if req.cmd == "status":
            return reply(True, req.id, **self.status_body(now))
        if req.cmd == "topology":
            return reply(True, req.id, **self.pipeline.topology_body(now))
        if req.cmd == "tare":
            n = self.pipeline.tare(None if req.bridges is None else list(req.bridges))
            return reply(True, req.id, tared_elements=n)
        if req.cmd == "ping" and req.bridge is None:
            return reply(True, req.id, pong=True, version=__version__, t_host=now, commands=COMMANDS)
        op, value = (int(PING), None) if req.cmd == "ping" else (req.op, req.value)
        result = await self.command(op, value, req.bridge, timeout)  # type: ignore[arg-type]
        replies = result["replies"]
        ok = bool(replies) and not result["missing"] and all(r["status"] == "OK" for r in replies.values())
        if not ok and not result.get("error"):
            result["error"] = self._command_error(result)
        return reply(ok, req.id, **result)

    @staticmethod
    def _command_error(result: dict[str, Any]) -> str:
        if not result["replies"] and not result["missing"]:
            return "no bridge is alive to receive the command"
        bad = {b: r["status"] for b, r in result["replies"].items() if r["status"] != "OK"}
        parts = []
        if result["missing"]:
            parts.append(f"no reply within the timeout from bridges {result['missing']}")
        if bad:
            parts.append(f"refused: {bad}")
        return "; ".join(parts)

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
                 if not spec.reloadable and s != "layout" and new[s][k] != self.config[s][k]]
        if new.links != self.config.links:
            fixed.append("link")
        if fixed:
            event(self.log, "warning", "reload: these changes need a restart", keys=fixed)
        self.config = new
        self.log.setLevel(new["daemon"]["log_level"].upper())
        self.pipeline.reconfigure(new, layout)
        event(self.log, "info", "config reloaded", source=new.source)
        self.hooks.ready("reloaded")

    # -- lifecycle ----------------------------------------------------------------------
    def _bind(self, ctx: zmq.asyncio.Context) -> None:
        c = self.config
        self.pub = Publisher(ctx, c["pub"]["endpoint"], c["pub"]["hwm"], c["pub"]["count_drops"])
        self.ctl = ctx.socket(zmq.ROUTER)
        self.ctl.setsockopt(zmq.LINGER, 500)
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
        self._tasks = [asyncio.create_task(c) for c in (self._ticker(), self._contacts(), self._control(),
                                                        self.pub.watch_subscriptions())]
        if self.config["contact"]["enabled"]:
            self._worker().submit(warm_up)  # the worker starts now, not at the first touch
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
            await self._drain(loop, link_tasks)
            for s in (self.pub.sock, self.ctl):
                s.close()
            self.hooks.close()
            ctx.term()
            if self._pool is not None:
                self._pool.shutdown(wait=True)
            for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
                loop.remove_signal_handler(sig)
            event(self.log, "info", "stopped")
        return 0

    async def _drain(self, loop: asyncio.AbstractEventLoop, link_tasks: list[asyncio.Task[Any]]) -> None:
        """Stop reading, finish what was read (last contact estimate, pending replies), say goodbye."""
        for t in link_tasks:
            t.cancel()
        await asyncio.gather(*link_tasks, return_exceptions=True)
        for _ in range(500):  # let a running contact estimate finish and publish (at most 5 s)
            if not self._contact_busy:
                break
            await asyncio.sleep(0.01)
        for t in self._tasks:
            t.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._answers:
            await asyncio.wait(self._answers, timeout=1.0)
        await self._contact_once(loop)
        now = time.time()
        self._resolve(now + 3600.0)  # anything still waiting gets its timeout answer
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
