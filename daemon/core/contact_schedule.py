"""The contact loop's policy, without its waiting: when to look at the skin, what a look
takes, which estimates are published, and what is counted.

Sans-I/O: a :class:`ContactScheduler` wraps one :class:`~cellbridge.daemon.core.pipeline.Pipeline`
and is fed the loop's times and the worker's answers. The service's asyncio loop
(``Service._contacts``) only waits (for data, a tick or :meth:`ContactScheduler.due`, and
the rest :meth:`ContactScheduler.rest_until` returns) and publishes; the offline driver
(:mod:`cellbridge.daemon.shell.offline`) runs the very same policy in virtual time, so golden
files, tests, benchmarks and tools see the pacing production runs.

The policy, in one place:

- **when**: a look when data came (a read), at each tick (silence ends contacts), or when
  :meth:`Pipeline.contact_due` says a frame is complete or its deadline passed; never
  sooner than the :class:`~cellbridge.daemon.core.pacing.Pacer` allows after the last look
  (``[contact] rate`` estimates a second on average, a token bucket), except that the rest
  after a look that estimated nothing ends at the read that completes a skin frame worth a
  look (:meth:`ContactScheduler.fed`, :meth:`ContactScheduler.wakes`): that read is what
  the rest waited for, and the rest's gap (a quarter of a period) would only delay it;
- **what a look takes**: the frames whose deadline passed (their elements' messages, to
  publish first) and the newest complete skin frame as a contact job, or none;
- **which estimates are published**: every estimate with contacts, and the first without
  (the one that says they ended), none of a failed estimate;
- **counted**: reads whose frame was never estimated because a newer one was taken
  (``feeds_skipped``: several reads between two looks is the loop falling behind, or a
  frame split over reads).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from cellbridge.daemon.core.contacts import ContactJob
from cellbridge.daemon.core.messages import ContactFrame, Message
from cellbridge.daemon.core.pacing import Pacer
from cellbridge.daemon.core.pipeline import Pipeline

#: s between the service's pipeline ticks (health goes out every ``health.interval``); each
#: tick is also a look at the skin, so that silence ends contacts.
TICK = 0.1


@dataclass(frozen=True)
class Look:
    """What one look at the skin found.

    ``messages``: the elements' messages of frames whose deadline passed (publish them
    before the estimate's). ``job``: the newest complete skin frame to estimate, or None
    (nothing new). ``skipped``: reads since the last job beyond the one that brought it
    (also added to :attr:`ContactScheduler.feeds_skipped`)."""

    messages: Sequence[Message]
    job: ContactJob | None
    skipped: int = 0


class ContactScheduler:
    """The contact loop's policy around ``pipeline`` at ``rate`` estimates a second (see the
    module). Not thread-safe: one loop drives it.

    The loop, in any time base the pacing is given in (the service: the host's monotonic
    counter; the offline driver: the reads' times)::

        framed = sched.fed()                         # on every read
        at = sched.due(now, idle=not worker.last_ran())   # wait until then, data, or a tick
        look = sched.look(now)                       # publish look.messages
        contacts = worker.estimate(look.job)         # when look.job is not None
        message = sched.publish(look.job, contacts)  # publish it when not None
        rest = sched.rest_until(t0, ran, sched.due(...))  # no look before then, except:
        sched.wakes(now, ran, framed, idle)          # a read in the rest after a look that ran nothing
    """

    def __init__(self, pipeline: Pipeline, rate: float) -> None:
        self.pipeline = pipeline
        self.pacer = Pacer(rate)
        #: reads whose frame no estimate saw (a newer frame was taken first)
        self.feeds_skipped = 0
        self._feeds = 0  # reads since the last job was taken
        self._shown = False  # the last published contact message had contacts
        self._given = pipeline.frames_given()  # skin frames given out as of the last read

    def set_rate(self, rate: float) -> None:
        """``[contact] rate`` changed (a reload): this many estimates a second from now on."""
        self.pacer.set_rate(rate)

    def fed(self) -> bool:
        """A read was fed to the pipeline (counted against the next job: skipped feeds).
        True when it gave out a skin frame (complete by its records, or the read came past
        a deadline; see :meth:`wakes`)."""
        self._feeds += 1
        given = self.pipeline.frames_given()
        framed, self._given = given != self._given, given
        return framed

    def wakes(self, now: float, estimated: bool, framed: bool, idle: bool) -> bool:
        """Whether a read at ``now`` ends the loop's rest early: the look before the rest
        ran no estimate (``estimated`` False: the rest is the pacer's gap after a look that
        found nothing, not the token bucket's bound on estimates), the read completed a skin
        frame (``framed``, from :meth:`fed`) and a look now finds it (:meth:`due`, ``idle``
        as there: a frame that only repeats an idle skin's does not wake it)."""
        return framed and not estimated and self.due(now, idle) <= now

    def due(self, now: float, idle: bool) -> float:
        """The pipeline's time at which a look finds a new frame without new data
        (:meth:`Pipeline.contact_due`; ``inf``: only data brings one). ``idle``: the last
        estimate had nothing to track (the worker skipped it)."""
        return self.pipeline.contact_due(now, idle)

    def look(self, now: float | None) -> Look:
        """Look at the skin at pipeline time ``now`` (None: the last read's time, as a replay
        in recorded time does): the frames whose deadline passed go out, and the newest
        complete frame becomes the job."""
        messages = self.pipeline.advance(now)
        job = self.pipeline.contact_job(now)
        self._given = self.pipeline.frames_given()  # (frames a look gave out at their deadline: no read's)
        if job is None:
            return Look(messages, None)
        skipped = max(0, self._feeds - 1)
        self._feeds = 0
        self.feeds_skipped += skipped
        return Look(messages, job, skipped)

    def publish(self, job: ContactJob, contacts: list[dict[str, Any]] | None) -> ContactFrame | None:
        """The ``contact`` message of ``job``'s estimate, or None: every estimate with
        contacts is published, and the first without (it says they ended); a failed
        estimate (``contacts`` None) publishes nothing and changes nothing."""
        if contacts is None:
            return None
        message = self.pipeline.contact_frame(job, contacts) if contacts or self._shown else None
        self._shown = bool(contacts)
        return message

    def rest_until(self, began: float, estimated: bool, due: float) -> float:
        """After a look that began at ``began`` and ran an estimate (``estimated``: the
        worker ran it, not skipped) or not; ``due``: :meth:`due` asked after the look, in
        the time base of ``began``. The earliest time of the next look
        (:meth:`Pacer.after_look`)."""
        return self.pacer.after_look(began, estimated, due)
