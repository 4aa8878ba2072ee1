"""The asyncio service: links, PUB, control, ticking, contacts and signals around one :class:`Pipeline`.

Everything here is a thin shell: each task moves bytes or messages between the
outside (serial lines, ZeroMQ sockets, signals) and the sans-I/O pipeline. Contact
estimation runs in one worker *process* on the newest snapshot whenever the worker is
free, so a slow estimate delays the next estimate, never ingest (a thread would hold
the interpreter lock for milliseconds at a time and stall the event loop).

Every outside part comes in through the constructor (the ZeroMQ context, the serial
opener, the clock the links stamp and wait with, the contact worker's executor), so
tests run a whole service in-process on fakes and ``inproc://`` endpoints.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import functools
import gc
import logging
import math
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zmq
import zmq.asyncio
from cellbridge.daemon.core import readout_columns
from cellbridge.daemon.core.commands import Pending
from cellbridge.daemon.core.config import Config, ConfigError, load_config
from cellbridge.daemon.core.contact_schedule import TICK as PIPELINE_TICK
from cellbridge.daemon.core.contact_schedule import ContactScheduler
from cellbridge.daemon.core.messages import Health, LinkWrite, LogEvent, Message
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.daemon.ops.ops import OpsHooks
from cellbridge.daemon.ops.security import endpoint_error
from cellbridge.daemon.shell import kernels
from cellbridge.daemon.shell.contact_worker import ContactWorker, ExecutorFactory, process_pool
from cellbridge.daemon.shell.control_server import ControlServer
from cellbridge.daemon.shell.layout_file import load_layout_file
from cellbridge.daemon.shell.links import (
    SYSTEM_CLOCK,
    Clock,
    Link,
    Opener,
    RecordedOrder,
    ReplayLink,
    ReplayPacer,
    SerialLink,
    open_serial,
)
from cellbridge.daemon.shell.logs import event, setup
from cellbridge.daemon.shell.publisher import Publisher
from cellbridge.tactile import SkinLayout
from cellbridge.tactile.skin_geometry import SkinGeometry

from cellbridge._version import __version__


def read_layout(config: Config) -> tuple[SkinLayout | None, SkinGeometry | None]:
    """The layout file's layout and skin description (None, None: no layout file; the
    description None: a plain layout)."""
    path = config.layout_path()
    return (None, None) if path is None else load_layout_file(path)


#: The most pipeline ticks a read of a replay in recorded time runs before it (10 s of
#: recording): over a longer gap, the last ones only (:meth:`Service._recorded_ticks`).
MAX_RECORDED_TICKS = 100


class Service:
    """The daemon around one :class:`Pipeline`: :meth:`run` until SIGTERM/SIGINT (or every
    replay with ``exit_when_done`` finished), :meth:`reload` on SIGHUP.

    ``ctx``: the ZeroMQ context to bind in (default: a new one, terminated at the end;
    a given one is left to its owner). ``opener``/``clock``: how serial links open their
    device and read the time; ``contact_executor``: makes the contact worker's executor.
    ``drain_limit``: seconds a stop may take from SIGTERM to the last message (under the
    unit's ``TimeoutStopSec``), whatever hangs."""

    TICK = PIPELINE_TICK  # s between pipeline ticks (health itself goes out every health.interval)
    HOST_STEP = 0.005  # s: a change of wall minus monotonic time beyond this is a clock step
    DRAIN_LIMIT = 10.0  # s: systemd's TimeoutStopSec=15 kills a daemon that takes longer
    REPLAY_WARM_LIMIT = 300.0  # s a replay waits at its start for the contact worker's warm-up
    #: s the start waits, before the links, for the calibrator's compiled step (loading it from
    #: the cache takes under a second; compiling it on a fresh installation, about 12 s, goes on
    #: in its thread past this while numpy steps the first frames)
    CALIBRATION_WARM_LIMIT = 5.0
    TASK_END_LIMIT = 1.0  # s a stop waits for the links' and the service's tasks to end once cancelled
    TERM_LIMIT = 2.0  # s a stop waits for its ZeroMQ context to terminate (PUB lingers 1 s)

    def __init__(self, config: Config, layout: SkinLayout | None = None, *, config_path: str | Path | None = None,
                 hooks: OpsHooks | None = None, ctx: zmq.asyncio.Context | None = None,
                 opener: Opener = open_serial, clock: Clock = SYSTEM_CLOCK,
                 contact_executor: ExecutorFactory = process_pool, drain_limit: float = DRAIN_LIMIT) -> None:
        self.config = config
        self._ctx = ctx
        self._opener = opener
        self._clock = clock
        self.drain_limit = drain_limit
        self.config_path = config_path
        self.log = setup(config.daemon.log_level, config.daemon.log_format)
        self.pipeline = Pipeline(config, layout)
        # The pipeline runs on the monotonic clock; a replay in recorded time feeds recorded
        # wall-clock times instead, and then nothing is added to them.
        self._recorded = any(ln.is_replay and ln.replay_clock == "recorded" for ln in config.links)
        self._wall_offset = clock.wall() - clock.time()
        self.pipeline.set_wall_offset(0.0 if self._recorded else self._wall_offset)
        # The reads' times as a recording keeps them for a replay: the wall clock's at the
        # start, then the time base's, so that a wall-clock step never enters a replay.
        self._read_offset = self.pipeline.wall_offset
        # A replay in recorded time runs on the recording's clock: the recorded time of the
        # last read fed (None until the first read; link states meanwhile wait for it). Ticked on today's
        # wall clock instead, every bridge of a recording made yesterday was a day silent.
        self._recorded_now: float | None = None
        # ... and ticked on it: every TICK of recorded time up to each read, as the offline
        # driver ticks (health, silence and deadlines at the recording's times). Ticked only
        # by the loop's timer, a replay the machine could not keep pace with came in bursts
        # between two ticks, and health went out seconds of recording apart.
        self._next_recorded_tick = math.inf
        self._states_before_data: list[tuple[str, bool, str]] = []
        # ... fed as one recording across links, from one origin and in one time order
        self._recorded_order = RecordedOrder([ln.name for ln in config.links
                                              if ln.is_replay and ln.replay_clock == "recorded"])
        # ... and those on shifted time at a recorded speed fed by one task, the records due
        # together at one wake (links.ReplayPacer; on the host's clock, as the replays pace)
        self._replay_pacer = ReplayPacer()
        self.hooks = hooks if hooks is not None else OpsHooks(config)
        self._binding = ("pub", config.pub.endpoint)  # the socket being bound (said when that fails)
        self.links: dict[str, Link] = {}
        self._fresh = asyncio.Event()
        # the contact loop rests after a look that ran no estimate, and a read completing a
        # frame worth a look ends that rest (ContactScheduler.wakes)
        self._resting = False
        self._woken = asyncio.Event()
        self._stop = asyncio.Event()
        self._tasks: list[asyncio.Task[Any]] = []
        self.contacts = ContactWorker(self.log, contact_executor)
        self.ingest_errors = 0
        self._busy = np.zeros(4096)  # s spent on each of the last reads, bytes to published messages
        self._n_reads = 0
        self._lag_max = 0.0  # s, since the last health message
        # the contact loop's policy (pacing, when a frame is due, what is published, skipped
        # reads); _contacts only waits and publishes
        self.schedule = ContactScheduler(self.pipeline, config.contact.rate)

    def now(self) -> float:
        """The pipeline's time base: the monotonic clock; while a replay feeds recorded
        wall-clock times, the last of them fed (the recording's clock stands still between
        its reads and after its end, and steps back where the recording does; before the first read it is the wall clock's
        time, which the pipeline is never ticked on: :meth:`_tick_once`)."""
        if self._recorded:
            return self._clock.wall() if self._recorded_now is None else self._recorded_now
        return self._clock.time()

    # -- ingest -------------------------------------------------------------------------
    def _on_data(self, link: str, data: bytes, now: float) -> None:
        t0 = time.perf_counter()
        if self._recorded:
            # (the replays feed in one time order across links, links.RecordedOrder: a read
            # before the last is the recording's own step back, e.g. two days' captures
            # concatenated, and the clock follows it as a host clock stepping back; held
            # at the newest time instead, it stood still for the whole rest of the
            # recording: no health, no silence, no command deadline)
            first = self._recorded_now is None
            self._recorded_ticks(now)
            self._recorded_now = now
            if first:  # the links came up on the recording's clock, at its first read
                for name, connected, why in self._states_before_data:
                    self.pipeline.link_state(name, connected, now, why)
                self._states_before_data.clear()
        self.pub.serial(link, data, now + self.pipeline.wall_offset, now + self._read_offset)
        p = self.pipeline
        try:
            self._act(p.feed(link, data, now))
        except Exception:  # a bug must cost one read, not the daemon
            self.ingest_errors += 1
            self.log.exception("ingest failed on one read", extra={"fields": {"link": link, "bytes": len(data)}})
        if p.commands_in_flight():
            self.control.resolve(now)
        framed = self.schedule.fed()
        if self._resting and self.schedule.wakes(now, False, framed, not self.contacts.last_ran()):
            self._woken.set()
        self._fresh.set()
        self._busy[self._n_reads % self._busy.shape[0]] = time.perf_counter() - t0
        self._n_reads += 1

    def _act(self, messages: list[Message]) -> None:
        """Do what the pipeline's messages say: publish, log, write on a link."""
        publish = self.pub.publish
        for m in messages:
            if isinstance(m, LogEvent):
                event(self.log, m.level, m.text, **m.fields)
            elif isinstance(m, LinkWrite):
                self._write(m)
            else:
                if isinstance(m, Health):
                    m = m.with_fields(self._shell_health())
                    self._lag_max = 0.0  # each health message reports the lag since the one before
                publish(m.topic, m.payload)

    def _write(self, w: LinkWrite) -> bool:
        """The one way bytes reach a link (the pipeline's messages and control's commands):
        True when the link took them."""
        link = self.links.get(w.link)
        return link is not None and link.write(w.data)

    # -- what the control server asks (control_server.Host) ------------------------------
    def send_command(self, op: int, value: int | None, target: int | None, now: float,
                     timeout: float) -> tuple[int, list[str]]:
        """Start a command to ``target`` (None: every bridge alive) and write it: its token
        and the links it went out on."""
        pending, writes = self.pipeline.command(op, value, target, now, timeout)
        return pending.token, [w.link for w in writes if self._write(w)]

    def finished_commands(self, now: float) -> list[Pending]:
        return self.pipeline.finished_commands(now)

    def expire_command(self, token: int) -> Pending | None:
        return self.pipeline.expire_command(token)

    def topology_body(self, now: float) -> dict[str, Any]:
        return self.pipeline.topology_body(now)

    def tare(self, bridges: list[int] | None) -> int:
        return self.pipeline.tare(bridges)

    def wall(self, now: float) -> float:
        return now + self.pipeline.wall_offset

    def _on_state(self, link: str, connected: bool, why: str) -> None:
        if self._recorded and self._recorded_now is None:
            self._states_before_data.append((link, connected, why))
        else:
            self.pipeline.link_state(link, connected, self.now(), why)
        if connected:
            event(self.log, "info", "link up", link=link, url=self.links[link].cfg.url)
        else:
            event(self.log, "warning", "link down", link=link, reason=why)

    def _make_link(self, cfg: Any) -> Link:
        if cfg.is_replay:
            gate = functools.partial(self._replay_gate, cfg.wait_for_subscriber)
            order = self._recorded_order if cfg.replay_clock == "recorded" else None
            return ReplayLink(cfg, self._on_data, self._on_state, gate, self._replay_done, order=order,
                              pacer=self._replay_pacer if order is None else None)
        return SerialLink(cfg, self._on_data, self._on_state, self._opener, self._clock)

    async def _replay_gate(self, subscriber: bool) -> None:
        """A replay starts once a subscriber is there (``wait_for_subscriber``) and the contact
        worker is warm: started before, a recording's first seconds were estimated late or
        not at all, by how long the warm-up took on this machine (on a fresh installation
        it compiles the kernels, about half a minute), where the daemon that recorded them
        had its worker warm long before: a replay must not depend on that."""
        if subscriber:
            await self.pub.subscribed.wait()
        if self.config.contact.enabled and not await self.contacts.warm(self.REPLAY_WARM_LIMIT):
            event(self.log, "error", "contact worker not started: the replay goes on without waiting",
                  waited=self.REPLAY_WARM_LIMIT)

    def _replay_done(self, name: str) -> None:
        event(self.log, "info", "replay finished", link=name, records=self.links[name].stats()["replayed_records"])
        exits = [ln for ln in self.links.values() if ln.cfg.exit_when_done]
        if exits and all(isinstance(ln, ReplayLink) and ln.finished for ln in exits):
            self._tasks.append(asyncio.create_task(self._finish_replay()))

    async def _finish_replay(self) -> None:
        """Stop once the contacts of what was replayed are estimated: a stop's drain gives
        the estimate under way a share of ``drain_limit`` (systemd's stop timeout), and a
        replay that ends is no such stop."""
        # (the replay began after the warm-up, or after its gate gave up on it: no second wait)
        if self.contacts.warmed():
            await self.contacts.idle(self.config.contact.worker_timeout)  # the estimate under way is published
        self._stop.set()

    def _recorded_ticks(self, t: float) -> None:
        """A replay in recorded time, about to feed a read of recorded time ``t``: the pipeline's
        ticks of the recording's clock before it (every :attr:`TICK` from the first read),
        in time order with the reads, whatever pace the loop keeps. A read before the last
        (the recording steps back) starts the ticks again from it: the loop's next tick
        takes the step as the host clock's. Over a gap of more than :data:`MAX_RECORDED_TICKS`
        ticks (a recording resumed an hour later) only the last of them run: each would find
        what the one before found, and a day's gap would stall the loop for seconds."""
        last = self._recorded_now
        if not math.isfinite(t):  # (a capture's corrupt time: no tick is due by it)
            return
        if last is None or not t >= last:
            self._next_recorded_tick = t
            return
        nxt = self._next_recorded_tick
        if t - nxt > MAX_RECORDED_TICKS * self.TICK:
            nxt = t - MAX_RECORDED_TICKS * self.TICK
        for _ in range(MAX_RECORDED_TICKS + 1):  # (bounded: at 1e308 s a TICK adds nothing)
            if not nxt < t:
                break
            self._act(self.pipeline.tick(nxt))
            self.control.resolve(nxt)
            nxt += self.TICK
        self._next_recorded_tick = max(nxt, t)

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
        now = self.now()
        step = (self._clock.wall() - self._clock.time()) - self._wall_offset
        if abs(step) > self.HOST_STEP and not self._recorded:  # the wall clock stepped (NTP)
            self._wall_offset += step
            self._act(self.pipeline.host_clock_step(step))
        if self._recorded and self._recorded_now is None:
            return next_status  # no recorded time yet: a tick now would be a clock stepping back later
        self._link_stats()
        self._act(self.pipeline.tick(now))
        self._fresh.set()  # contacts are looked at without new data too: silence ends them
        self.control.resolve(now)
        if now >= next_status or next_status - now > 5.0:  # (the host clock may step back)
            next_status = now + 5.0
            self.hooks.status(self.pipeline.summary())
            for link in self.links.values():
                cap = getattr(link, "capture", None)
                if cap is not None:
                    cap.flush()
        return next_status

    async def _watchdog(self, interval: float) -> None:
        while True:
            self.hooks.watchdog()
            await asyncio.sleep(interval)

    def _link_stats(self) -> None:
        """The links' own counters into the pipeline's link health, before it builds health."""
        for name, link in self.links.items():
            self.pipeline.link_stats(name, link.stats())

    def _shell_health(self) -> dict[str, Any]:
        recent = self._busy[:min(self._n_reads, self._busy.shape[0])]
        p50, p99 = (np.percentile(recent, [50, 99]) * 1e3).tolist() if recent.size else (None, None)
        ingest = {"reads": self._n_reads, "errors": self.ingest_errors, "ms_per_read_p50": p50,
                  "ms_per_read_p99": p99, "ms_per_read_max": float(recent.max() * 1e3) if recent.size else None,
                  "loop_lag_ms_max": self._lag_max * 1e3}
        out = {"pub": self.pub.stats(), "control": self.control.stats(), "contact_estimation": dict(self.contacts.stats),
               "ingest": ingest}
        security = self.hooks.counters()
        if security:
            out["security"] = security
        return out

    def status_body(self, now: float) -> dict[str, Any]:
        self._link_stats()
        body = self.pipeline.health_body(now)
        body.update(self._shell_health(), version=__version__, t_host=now + self.pipeline.wall_offset)
        return body

    # -- contacts -----------------------------------------------------------------------
    async def _contacts(self) -> None:
        """The contact loop's waiting: the policy is the scheduler's (daemon/core/contact_schedule.py)."""
        sched = self.schedule
        while True:
            # data came (a frame completed), the tick looked for silence, or a frame's
            # deadline passed with a gateway's record missing
            idle = not self.contacts.last_ran()
            due = sched.due(self.now(), idle) - self.now()
            if not self._fresh.is_set() and due < self.TICK:
                # asyncio.timeout, not wait_for: Python 3.11's wait_for returns the result of
                # a wait that ended in the step before its task was cancelled, and the cancel
                # is lost; this loop then went on, and a stop's drain waited for it for ever.
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(max(due, 0.0)):
                        await self._fresh.wait()
            else:
                await self._fresh.wait()
            self._fresh.clear()
            # ``rate`` bounds the estimates, not the looks, and a late estimate does not
            # make the next one late; a frame that came due while the look ran is looked
            # at again at once (daemon/core/pacing.py). The pacing runs on the host's
            # performance counter, the pipeline on its own time base: due is carried over.
            started = time.perf_counter()
            estimated = await self._contact_once()
            now = self.now()
            t = time.perf_counter()
            sched.set_rate(self.config.contact.rate)
            due_at = sched.due(now, not self.contacts.last_ran())
            rest = sched.rest_until(started, estimated, t + (due_at - now)) - t
            if rest > 0:
                await self._rest(rest, estimated)

    async def _rest(self, rest: float, estimated: bool) -> None:
        """The pacer's ``rest`` s before the next look. After a look that ran no estimate
        (``estimated`` False) a read that completes a skin frame worth a look ends it
        (:meth:`ContactScheduler.wakes`): the gap only spaces looks at reads that complete
        nothing, and a frame completed in it waited for the gap's end (up to a quarter of a
        period, 2.5 ms at 100 Hz, on every press's way to its contact)."""
        if estimated:
            await asyncio.sleep(rest)
            return
        self._woken.clear()
        self._resting = True
        try:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(rest):  # (not wait_for: see above)
                    await self._woken.wait()
        finally:
            self._resting = False

    async def _contact_once(self, limit: float = math.inf) -> bool:
        """Look at the skin once and estimate its newest frame if it moved on; whether a job
        ran in the worker (a frame taken with nothing touched and no track left is not
        shipped, and costs the estimate rate nothing: counted, idle frames kept the loop's
        token bucket empty and each frame of a press's onset was estimated up to a period
        after it was due). A failed estimate counts as one, and so does a look that raised:
        a bug costs that look (logged, counted in the estimates' errors), not the contact
        loop, whose task it ended (no contact published again, health going on, nothing
        logged)."""
        try:
            return await self._look(limit)
        except Exception:
            self.contacts.stats["errors"] += 1
            self.log.exception("contact look failed: this frame's contacts are not published")
            return True

    async def _look(self, limit: float) -> bool:
        """:meth:`_contact_once` without its guard."""
        # (a replay in recorded time: its data's own time, or the whole recording looks silent)
        look = self.schedule.look(None if self._recorded else self.now())
        self._act(list(look.messages))  # frames whose deadline passed, and their elements' messages
        if look.job is None:
            return False
        self.contacts.stats["feeds_skipped"] = self.schedule.feeds_skipped
        contacts = await self.contacts.estimate(look.job, min(limit, self.config.contact.worker_timeout))
        message = self.schedule.publish(look.job, contacts)
        if message is not None:
            self._act([message])
        return contacts is None or self.contacts.last_ran()

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
            layout, surface = read_layout(new)
        except (ConfigError, ValueError) as exc:
            event(self.log, "error", "reload rejected, keeping the running config", error=str(exc))
            self.hooks.ready("reload rejected")
            return
        fixed = self.config.needs_restart(new)
        if fixed:
            event(self.log, "warning", "reload: these changes need a restart", keys=fixed)
        self.config = new
        self.log.setLevel(new.daemon.log_level.upper())
        self.pipeline.reconfigure(new, layout, surface)
        try:
            self.hooks.reload_keys()
        except ValueError as exc:
            event(self.log, "error", "allowed client keys not reloaded, keeping the previous ones", error=str(exc))
        event(self.log, "info", "config reloaded", source=new.source)
        self.hooks.ready("reloaded")

    # -- lifecycle ----------------------------------------------------------------------
    def _bind(self, ctx: zmq.asyncio.Context) -> None:
        c = self.config
        self.pub = Publisher(ctx, c.pub.endpoint, c.pub.hwm, c.pub.count_drops, c.pub.source)
        self.ctl = ctx.socket(zmq.ROUTER)
        self.ctl.setsockopt(zmq.LINGER, 500)
        self.control = ControlServer(self.ctl, self, self.log)
        for section, sock, endpoint in (("pub", self.pub.sock, c.pub.endpoint),
                                        ("control", self.ctl, c.control.endpoint)):
            self._binding = (section, endpoint)
            self.hooks.secure(ctx, sock, endpoint)  # OPS: security check, CURVE and peer bounds, before bind
            sock.bind(endpoint)
            self.hooks.bound(sock, endpoint)  # OPS: an ipc:// socket file's mode and group
        self.pub.on_wanted = self.pipeline.want

    def _warm_calibration(self, done: threading.Event) -> None:
        """In a thread at the start: the READOUT reader (:mod:`cellbridge.daemon.core.readout_columns`)
        and the calibrator's compiled step loaded, or compiled on a fresh installation
        (:mod:`cellbridge.tactile.calibration_kernel`); frames before it is warm are stepped by
        numpy, with the same results, and so are all of them if it fails (and a reader that
        fails leaves every record to the plain decoder)."""
        t0 = time.monotonic()
        # (first the READOUT reader, a quarter of the calibrator's time: the ingest's, which
        # otherwise compiled at the first record, holding the loop; each compiled in a child
        # where the cache lacks it, see :mod:`cellbridge.daemon.shell.kernels`; the reader's kernels
        # are made at its first use, so made first here: asked for before, they were not missed;
        # records that come meanwhile are read by the plain decoder, see make_reader)
        with contextlib.suppress(Exception):  # (a reader that fails is the warm-up's to report)
            readout_columns.make_reader()
            if kernels.compile_apart("cellbridge.daemon.core.readout_columns:warm_up",
                                     modules=("cellbridge.daemon.core.readout_columns",)):
                event(self.log, "info", "READOUT reader compiled apart", seconds=round(time.monotonic() - t0, 3))
        if not readout_columns.warm_up():
            event(self.log, "warning", "compiled READOUT reader unavailable: records are read by the plain decoder")
        try:
            from cellbridge.tactile import calibration_kernel

            if kernels.compile_apart("cellbridge.tactile.calibration_kernel:warm_up",
                                     modules=("cellbridge.tactile.calibration_kernel",)):
                event(self.log, "info", "calibration kernel compiled apart", seconds=round(time.monotonic() - t0, 3))
            calibration_kernel.warm_up()
        except Exception as exc:  # any failure leaves the numpy step, which gives the same numbers
            event(self.log, "warning", "calibration kernel unavailable: numpy steps the calibrator",
                  error=f"{type(exc).__name__}: {exc}")
            return
        finally:
            done.set()
        event(self.log, "debug", "calibration kernel ready", seconds=round(time.monotonic() - t0, 3))

    async def _calibration_warm(self) -> None:
        """Start the calibrator's warm-up and wait for it up to :attr:`CALIBRATION_WARM_LIMIT`:
        loaded before the links, it neither holds the loop while frames come nor grows the
        process's memory (its JIT, about 50 MiB) after the start."""
        done = threading.Event()
        threading.Thread(target=self._warm_calibration, args=(done,), name="calibration kernel", daemon=True).start()
        end = time.monotonic() + self.CALIBRATION_WARM_LIMIT
        while not done.is_set() and time.monotonic() < end:
            await asyncio.sleep(0.02)

    async def run(self) -> int:
        loop = asyncio.get_running_loop()
        ctx = self._ctx if self._ctx is not None else zmq.asyncio.Context()
        try:
            self._bind(ctx)
        except (zmq.ZMQError, ValueError) as exc:
            event(self.log, "error", "cannot bind", error=str(exc))
            print(f"cellbridge daemon: {bind_problem(*self._binding, exc)}", file=sys.stderr, flush=True)
            self.hooks.close()
            if self._ctx is None:
                ctx.destroy(linger=0)
            return 1
        self.pipeline.want(set())
        for cfg in self.config.links:
            self.links[cfg.name] = self._make_link(cfg)
        loop.add_signal_handler(signal.SIGTERM, self._stop.set)
        loop.add_signal_handler(signal.SIGINT, self._stop.set)
        loop.add_signal_handler(signal.SIGHUP, self.reload)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGHUP})  # held back since the command began (cli.main)
        if self.config.contact.enabled:  # (before the links: a replay waits for its warm-up)
            self.contacts.start()
        await self._calibration_warm()
        link_tasks = [asyncio.create_task(ln.run(), name=f"link {n}") for n, ln in self.links.items()]
        self._tasks = [asyncio.create_task(c) for c in (self._ticker(), self._contacts(), self.control.serve(),
                                                        self.pub.watch_subscriptions())]
        if self.hooks.watchdog_interval:
            self._tasks.append(asyncio.create_task(self._watchdog(self.hooks.watchdog_interval)))
        event(self.log, "info", "daemon started", version=__version__, pub=self.config.pub.endpoint,
              control=self.config.control.endpoint, links=list(self.links))
        # Start-up objects (numpy, zmq, the layout) never die: keep them out of the cyclic
        # collector's full passes, which pause the event loop for the time they take.
        gc.collect()
        gc.freeze()
        self.hooks.ready(self.pipeline.summary())  # OPS: READY=1 once links run and sockets are bound
        try:
            await self._stop.wait()
        finally:
            self.hooks.stopping()  # OPS: STOPPING=1
            event(self.log, "info", "stopping: draining")
            try:
                await self._drain(link_tasks)
            finally:  # (also when the drain is cancelled: the sockets, the peer guard's thread
                # and the worker process would be left open, and a term() of the context hung)
                for t in (*link_tasks, *self._tasks):
                    t.cancel()
                for s in (self.pub.sock, self.ctl):
                    s.close()
                self.hooks.close()
                if self._ctx is None:
                    self._term(ctx, self.TERM_LIMIT)
                self.contacts.close()
                for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
                    loop.remove_signal_handler(sig)
                event(self.log, "info", "stopped")
        return 0

    async def _drain(self, link_tasks: list[asyncio.Task[Any]]) -> None:
        """Stop reading, finish what was read (last contact estimate, pending replies), say
        goodbye, all within ``drain_limit`` s of the stop whatever hangs: a contact worker
        still on an estimate when its share of the time is up is left to :meth:`run`,
        which kills it; none is started in its place."""
        end = time.monotonic() + self.drain_limit

        def left(share: float) -> float:
            return max(0.0, min(share, end - time.monotonic()))

        self.contacts.stop()
        await self._end(link_tasks, left(self.TASK_END_LIMIT))
        await self.contacts.idle(left(self.drain_limit / 2))  # a running estimate finishes and is published
        await self._end(self._tasks, left(self.TASK_END_LIMIT))
        await self.control.finish(left(1.0))
        if not self.contacts.working and left(math.inf) > 0:
            await self._contact_once(left(math.inf))  # the newest state, if the last estimate did not see it
        now = self.now()
        self._link_stats()
        self._act(self.pipeline.tick(now, force=True))

    async def _end(self, tasks: list[asyncio.Task[Any]], limit: float) -> None:
        """Cancel ``tasks`` and wait for them to end, at most ``limit`` s, cancelling those
        still running again every 0.1 s (a cancel can be lost: Python 3.11's wait_for took
        one in as the end of its wait). A task that outlives the bound is logged and left
        (:func:`run_service` gives it a last bounded chance); the stop goes on."""
        end = time.monotonic() + limit
        pending = {t for t in tasks if not t.done()}
        while pending:
            for t in pending:
                t.cancel()
            wait = min(end - time.monotonic(), 0.1)
            if wait <= 0:
                break
            _, pending = await asyncio.wait(pending, timeout=wait)
        for t in tasks:  # what they raised is theirs, not the stop's (as gather's return_exceptions)
            if t.done() and not t.cancelled():
                t.exception()
        if pending:
            event(self.log, "error", "tasks did not end when cancelled, left behind",
                  tasks=sorted(t.get_name() for t in pending), waited=limit)

    def _term(self, ctx: zmq.asyncio.Context, limit: float) -> None:
        """Terminate the service's own ZeroMQ context, waiting at most ``limit`` s. ``term()``
        waits for every socket of the context to be closed, without a bound: one left open
        (a helper thread that did not end in its time) held the daemon after its drain."""
        worker = threading.Thread(target=ctx.term, name="cellbridge zmq term", daemon=True)
        worker.start()
        worker.join(limit)
        if worker.is_alive():
            event(self.log, "error", "ZeroMQ context did not terminate: a socket is still open or still sending",
                  waited=limit)


#: s a thread may hold the GIL while another waits for it (Python's default: 5 ms). A
#: contact estimate's result reaches the loop through the worker's result thread
#: (daemon/shell/worker_process.py), and ZeroMQ's authenticator answers from its own; with the
#: loop busy on reads (1-5 ms of numpy work each, back to back around a press) such a
#: thread waited up to a whole interval for its turn. Measured with the process pool the
#: daemon used before, press to contact (bench/bench_press_latency.py --trace): submitted
#: -> worker began 3.9 / 5.4 ms (p90/p99) with the default, 2.2 / 3.8 ms with this one.
GIL_SWITCH_INTERVAL = 0.0005


#: s the event loop's close gives tasks left after the service stopped, and the default executor
LEFTOVER_LIMIT = 1.0


def build_service(config: Config, config_path: str | Path | None, **kwargs: Any) -> Service:
    """The service ``cellbridge daemon`` runs for ``config`` (read from ``config_path``), its
    layout file read; ``kwargs``: the rest of :class:`Service`'s arguments (tests)."""
    layout, surface = read_layout(config)
    service = Service(config, layout, config_path=config_path, **kwargs)
    service.pipeline.surface = surface
    return service


def bind_problem(section: str, endpoint: str, exc: Exception) -> str:
    """A bind that failed as one sentence for a person: the endpoint, its config key, and
    for one in use the likely cause (the log line gives libzmq's words to a machine)."""
    where = f"{endpoint} ([{section}] endpoint)"
    if isinstance(exc, zmq.ZMQError) and exc.errno == errno.EADDRINUSE:
        return (f"{where} is in use: another daemon is probably running on it (the same config started "
                "twice?); stop that one, or give this one other endpoints")
    if isinstance(exc, zmq.ZMQError):
        return f"{where} cannot be bound: {endpoint_error(endpoint, exc).removeprefix(endpoint + ': ')}"
    return f"{where}: {exc}"


def run_service(config_path: str | Path | None, config: Config) -> int:
    """The daemon's process: the service on a new event loop until it stops; its exit status.

    Not ``asyncio.run``: its close cancels the tasks left and waits for them without a
    bound; a task that does not end when cancelled (the service logged it) would keep the
    daemon from exiting after it said "stopped". Here they get ``LEFTOVER_LIMIT``."""
    sys.setswitchinterval(GIL_SWITCH_INTERVAL)
    service = build_service(config, config_path)
    loop = asyncio.new_event_loop()
    asyncio.set_event_loop(loop)
    try:
        return loop.run_until_complete(service.run())
    finally:
        try:
            close_loop(loop, LEFTOVER_LIMIT)
        finally:
            asyncio.set_event_loop(None)
            loop.close()


def close_loop(loop: asyncio.AbstractEventLoop, limit: float) -> None:
    """What ``asyncio.run`` does after its coroutine, each wait bounded by ``limit`` s:
    cancel the tasks left and wait for them, close async generators, shut the default
    executor down."""
    left = asyncio.all_tasks(loop)
    for t in left:
        t.cancel()
    if left:
        loop.run_until_complete(asyncio.wait(left, timeout=limit))
        for t in left:
            if t.done() and not t.cancelled():
                t.exception()  # retrieved: a task's error at exit is not the daemon's to print
    loop.run_until_complete(loop.shutdown_asyncgens())
    loop.run_until_complete(asyncio.wait([loop.create_task(loop.shutdown_default_executor())], timeout=limit))


logging.getLogger("asyncio").setLevel(logging.WARNING)
