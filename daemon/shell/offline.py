"""The daemon offline: a configuration and timed reads in, what the service would publish out.

:class:`OfflineDaemon` runs the service's schedule in virtual time on the reads' own clock:
each read is fed at its time, the pipeline ticks every :data:`~cellbridge.daemon.core.contact_schedule.TICK`
s from the first read (health, topology, wall-clock steps noticed), and the contact loop
looks at the skin when the service's would, by the one policy both use
(:class:`~cellbridge.daemon.core.contact_schedule.ContactScheduler`: data or a tick wakes it, a
frame's due time wakes it, the pacer holds it back to ``[contact] rate``, the first
estimate without contacts is published and the rest are not). Contacts are estimated
inline by the production worker code (:class:`~cellbridge.daemon.shell.contact_worker.ContactWorker`
on an :class:`~cellbridge.daemon.shell.contact_worker.InlineExecutor`), taking no virtual time.
A run ends as a stopped service does: one last look at ``until``.

What it leaves out is the machine: an estimate takes no time, reads are never late, the
loop never lags. The same reads give the same messages on any machine, which is what the
golden files, the tests, the benchmarks and ``cellbridge`` tools replaying a capture need.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Generator, Iterable, Iterator
from typing import Any, NamedTuple

from cellbridge.daemon.core.config import Config
from cellbridge.daemon.core.contact_schedule import TICK, ContactScheduler
from cellbridge.daemon.core.messages import Message, Publish
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.daemon.shell.contact_worker import ContactWorker, InlineExecutor
from cellbridge.tactile import SkinLayout

__all__ = ["OfflineDaemon", "Output", "Read"]


class Read(NamedTuple):
    """One read of a link: its host time (the pipeline's time base), the link's name, the bytes."""

    t: float
    link: str
    data: bytes


class Output(NamedTuple):
    """One published message: when the service would publish it, its topic and payload."""

    t: float
    topic: str
    payload: dict[str, Any]


class OfflineDaemon:
    """The daemon's core and its contact loop's policy, driven in virtual time (see the module).

    ``topics``: the topics subscribed to (None: every topic is built, as with no
    subscription filter; the service builds only what its subscribers want).
    ``surface``: the skin's 3-D surface for contact fields (a skin description's geometry),
    as ``cellbridge daemon`` sets it from the layout file. ``recorded``: the reads are a
    replay in recorded time (``replay_clock = "recorded"``): each look takes the last read's
    time, as the service's does then, not the loop's. :attr:`pipeline`,
    :attr:`worker` and :attr:`schedule` stay readable after (and during) a run."""

    def __init__(self, config: Config, layout: SkinLayout | None = None, *, topics: set[str] | None = None,
                 surface: Any = None, recorded: bool = False, log: logging.Logger | None = None) -> None:
        self.config = config
        self.recorded = recorded
        self.pipeline = Pipeline(config, layout)
        if surface is not None:
            self.pipeline.surface = surface
        self.pipeline.want(topics)
        self.worker = ContactWorker(log or logging.getLogger("cellbridge.offline"), InlineExecutor)
        self.schedule = ContactScheduler(self.pipeline, config.contact.rate)
        #: looks at the skin so far (with or without a job), and estimates that ran
        self.looks = 0
        self.estimates = 0

    def run(self, reads: Iterable[tuple[float, str, bytes]], until: float | None = None, *,
            start: float | None = None, wall_steps: Iterable[tuple[float, float]] = ()) -> Iterator[Output]:
        """Feed ``reads`` ((time, link, bytes), in time order; an iterator is read lazily, one
        read ahead) and yield every published message in the order the service publishes
        them. ``until``: the host time the run stops at (default: the last read's);
        ``start``: the first tick's time (default: the first read's). ``wall_steps``:
        (time, seconds) the host's wall clock steps by (the next tick notices, as the
        service's does). Raises :class:`ValueError` for reads out of time order."""
        it = iter(reads)
        pending = _next_read(it, -math.inf)
        if start is None:
            start = pending.t if pending is not None else (until if until is not None else 0.0)
        steps = sorted(wall_steps)
        p, sched, w = self.pipeline, self.schedule, self.worker
        now = start
        next_tick = start
        last_read = start
        rest_until = -math.inf
        ran = False  # the last look ran an estimate (its rest is the token bucket's, not cut short)
        fresh = False

        def end() -> float:
            if until is not None:
                return until
            return last_read if pending is None else math.inf

        def publish(t: float, messages: Iterable[Message]) -> Iterator[Output]:
            for m in messages:
                if isinstance(m, Publish):
                    yield Output(t, m.topic, m.payload)

        def advance_to(t: float, resting: bool = False) -> Generator[Output, None, float | None]:
            """Reads and ticks up to ``t``, in time order (a read before a tick at one time).
            ``resting``: the loop's rest, which a read may end (``ContactScheduler.wakes``):
            then the time of that read, else None."""
            nonlocal pending, next_tick, last_read, fresh
            while True:
                t_read = pending.t if pending is not None else math.inf
                if min(t_read, next_tick) > t:
                    return None
                if pending is not None and t_read <= next_tick:
                    yield from publish(t_read, p.feed(pending.link, pending.data, t_read))
                    framed = sched.fed()
                    last_read = t_read
                    pending = _next_read(it, t_read)
                    if resting and sched.wakes(t_read, ran, framed, not w.last_ran()):
                        fresh = True
                        return t_read
                else:
                    while steps and steps[0][0] <= next_tick:
                        yield from publish(next_tick, p.host_clock_step(steps.pop(0)[1]))
                    yield from publish(next_tick, p.tick(next_tick))
                    next_tick += TICK
                fresh = True

        def look(t: float) -> Iterator[Output]:
            nonlocal rest_until, ran
            self.looks += 1
            found = sched.look(None if self.recorded else t)
            yield from publish(t, found.messages)
            ran = False
            if found.job is not None:
                contacts = w.estimate_now(found.job)
                ran = w.last_ran()
                self.estimates += ran
                message = sched.publish(found.job, contacts)
                if message is not None:
                    yield Output(t, message.topic, message.payload)
            rest_until = sched.rest_until(t, ran, sched.due(t, not w.last_ran()))

        while True:
            if rest_until > now:  # the loop rests; reads and ticks go on (a read may end it)
                stop = min(rest_until, end())
                woke = yield from advance_to(stop, resting=True)
                now = max(now, stop if woke is None else woke)
                if now >= end():
                    break
            if not fresh:  # wait for data, a tick, or a frame's due time
                t_read = pending.t if pending is not None else math.inf
                wake = max(min(t_read, next_tick, sched.due(now, not w.last_ran())), now)
                if wake > end() or (wake == end() and not math.isfinite(wake)):
                    break
                yield from advance_to(wake)
                now = wake
            fresh = False
            yield from look(now)
        stop = end()
        if math.isfinite(stop):
            yield from advance_to(stop)
            now = max(now, stop)
        yield from look(now)  # a stop's last look: the newest state, if no estimate saw it yet


def _next_read(it: Iterator[tuple[float, str, bytes]], after: float) -> Read | None:
    got = next(it, None)
    if got is None:
        return None
    read = Read(float(got[0]), str(got[1]), bytes(got[2]))
    if read.t < after:
        raise ValueError(f"reads out of time order: {read.t!r} after {after!r}")
    return read
