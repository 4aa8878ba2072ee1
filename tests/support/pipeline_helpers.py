"""Reading the sans-I/O pipeline's output in tests, through the production contact path."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator
from typing import Any

from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.contacts import ContactJob, ContactSnapshot
from cellbridge.daemon.core.messages import LogEvent, Message, Publish
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.daemon.shell.contact_worker import ContactWorker, InlineExecutor
from cellbridge.daemon.shell.offline import OfflineDaemon, Output


def published(messages: list[Message]) -> list[tuple[str, dict[str, Any]]]:
    """(topic, payload) of each message to publish, in order (log events and writes left out)."""
    return [(m.topic, m.payload) for m in messages if isinstance(m, Publish)]


def logged(messages: list[Message]) -> list[str]:
    """The text of each log event, in order."""
    return [m.text for m in messages if isinstance(m, LogEvent)]


def worker() -> ContactWorker:
    """The daemon's contact worker on an inline executor: production's path, in this process."""
    return ContactWorker(logging.getLogger("tests"), InlineExecutor)


def snapshot(p: Pipeline) -> ContactSnapshot | None:
    """The snapshot of the pipeline's next contact job, if there is one."""
    job = p.contact_job()
    return None if job is None else job.snapshot


def estimate(p: Pipeline, job: ContactJob, runs: int = 1) -> tuple[str, dict[str, Any]]:
    """Estimate ``job`` ``runs`` times (a contact is born after a few) on one inline worker;
    (topic, payload) of the last estimate's ``contact`` message."""
    w = worker()
    for _ in range(runs):
        contacts = w.estimate_now(job)
    m = p.contact_frame(job, contacts)
    return m.topic, m.payload


#: Host time of virtual time 0 in the virtual-mesh tests.
T0 = 1_800_000_000.0


def drive(reads: list[tuple[float, bytes]], until: float, stop_feeding_at: float = math.inf,
          wall_steps: dict[float, float] | None = None, sections: dict | None = None) -> Iterator[Output]:
    """The daemon offline on the gateway's reads (the service's schedule in virtual time:
    ticks, contact looks paced at ``[contact] rate``) from ``T0`` to ``T0 + until``; reads
    from ``stop_feeding_at`` s on are lost (the line went quiet); at each time of
    ``wall_steps`` the wall clock steps by its value (the next tick notices; the time base,
    the monotonic clock, does not move). ``sections``: more of the daemon's configuration.
    Yields (time, topic, payload)."""
    d = OfflineDaemon(parse_config({"link": [{"name": "gw", "url": "/dev/null"}], **(sections or {})}))
    fed = ((t, "gw", data) for t, data in reads if t < T0 + stop_feeding_at)
    steps = [(T0 + at, by) for at, by in (wall_steps or {}).items()]
    yield from d.run(fed, T0 + until, start=T0, wall_steps=steps)
