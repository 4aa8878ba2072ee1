"""Reading the sans-I/O pipeline's output in tests, through the production contact path."""

from __future__ import annotations

import logging
from typing import Any

from cellbridge.daemon.contact_worker import ContactWorker, InlineExecutor
from cellbridge.daemon.messages import LogEvent, Message, Publish
from cellbridge.daemon.contacts import ContactJob, ContactSnapshot
from cellbridge.daemon.pipeline import Pipeline


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
