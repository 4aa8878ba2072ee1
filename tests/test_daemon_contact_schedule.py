"""The contact loop's one policy (daemon/core/contact_schedule.py) and the daemon offline
(daemon/shell/offline.py) that runs it in virtual time: what is published, what is counted, and
that the pacing production runs is the pacing every offline user gets."""

from __future__ import annotations

import math
from typing import Any

import pytest
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.core.contact_schedule import TICK, ContactScheduler
from cellbridge.daemon.core.pipeline import Pipeline
from cellbridge.daemon.shell.capture import read_capture
from cellbridge.daemon.shell.offline import OfflineDaemon

from support.golden_corpus import DATA
from support.pipeline_helpers import worker

CAPTURE = DATA / "daemon_press.cbcap"  # the golden corpus's capture scenario
READS = [(t, "gw", data) for t, data in read_capture(CAPTURE)]  # a 3x3 skin at 100 Hz, two presses


def config(**contact: Any) -> Any:
    return parse_config({"calibration": {"n_baseline": 10}, "contact": {"birth_frames": 1, **contact},
                         "link": [{"name": "gw", "url": "/dev/null"}]})


def pressed_scheduler() -> tuple[ContactScheduler, Pipeline]:
    """A scheduler on a pipeline fed the capture up to its first press."""
    p = Pipeline(config())
    sched = ContactScheduler(p, 100.0)
    for t, link, data in READS[:30]:
        p.feed(link, data, t)
        sched.fed()
    return sched, p


def test_every_estimate_with_contacts_is_published_and_the_first_without_then_none() -> None:
    sched, p = pressed_scheduler()
    job = sched.look(None).job
    assert job is not None
    touch = worker().estimate_now(job)
    assert len(touch) == 1  # the press on the corner of four elements
    assert sched.publish(job, None) is None  # a failed estimate: nothing, and nothing changes
    assert sched.publish(job, []) is None  # nothing shown yet: an empty estimate says nothing new
    first = sched.publish(job, touch)
    assert first is not None and [c["id"] for c in first.payload["contacts"]] == [touch[0]["id"]]
    assert sched.publish(job, touch) is not None
    assert sched.publish(job, None) is None  # a failure between does not count as "ended"
    ended = sched.publish(job, [])
    assert ended is not None and ended.payload["contacts"] == []  # the end of the contacts is said
    assert sched.publish(job, []) is None
    assert sched.publish(job, []) is None


def test_reads_no_estimate_saw_are_counted_when_a_job_is_taken() -> None:
    p = Pipeline(config())
    sched = ContactScheduler(p, 100.0)
    skipped: list[int] = []
    for t, link, data in READS:
        p.feed(link, data, t)
        sched.fed()
        if len(skipped) < 40 and (t - READS[0][0]) % 0.05 < 0.011:  # a look now and then: the loop behind
            found = sched.look(t)
            if found.job is not None:
                skipped.append(found.skipped)
    assert sum(skipped) == sched.feeds_skipped > 0
    assert max(skipped) >= 3  # several reads between two looks: all but the last one's frame lost


def test_a_look_without_a_new_frame_takes_no_job_and_counts_nothing() -> None:
    sched, _ = pressed_scheduler()
    assert sched.look(None).job is not None
    again = sched.look(None)
    assert again.job is None and again.skipped == 0 and sched.feeds_skipped == 29


@pytest.mark.parametrize("rate", [5.0, 20.0, 100.0])
def test_the_offline_daemon_estimates_at_most_at_the_configured_rate(rate: float) -> None:
    """The pacer runs offline as in the service: at most ``rate`` estimates a second plus
    the bucket's burst (and a stop's last look). A fixed-step driver (every 10 ms, the tests'
    and tools' loop before) estimated 100 a second whatever the rate said."""
    d = OfflineDaemon(config(rate=rate), topics={"element", "contact"})
    out = list(d.run(READS))
    span = READS[-1][0] - READS[0][0]
    assert d.estimates <= math.floor(2 + rate * span) + 1
    if rate == 100.0:  # frames come at 100 Hz: more estimates than a slower rate allows
        assert d.estimates > math.floor(2 + 20.0 * span) + 1
    contacts = [o for o in out if o.topic == "contact"]
    assert contacts and contacts[-1].payload["contacts"], "the held press ends the run as a contact"


def test_the_offline_daemon_ticks_and_publishes_in_time_order() -> None:
    d = OfflineDaemon(config())
    out = list(d.run(READS))
    times = [o.t for o in out]
    assert times == sorted(times)
    health = [o.t for o in out if o.topic == "health"]
    assert health and health[0] == READS[0][0]  # the first tick at the first read
    assert all(math.isclose((t - READS[0][0]) / TICK, round((t - READS[0][0]) / TICK)) for t in health)
    assert READS[0][0] <= times[0] and times[-1] <= READS[-1][0]  # (default: until the last read)


def test_the_offline_daemon_notices_a_wall_clock_step_at_the_next_tick() -> None:
    step_at = READS[0][0] + 0.15
    plain = [o for o in OfflineDaemon(config()).run(READS) if o.topic == "contact"]
    stepped = [o for o in OfflineDaemon(config()).run(READS, wall_steps=[(step_at, 2.0)]) if o.topic == "contact"]
    assert [o.t for o in plain] == [o.t for o in stepped]  # the schedule does not move
    for a, b in zip(plain, stepped):
        moved = b.payload["t_host"] - a.payload["t_host"]
        assert moved == pytest.approx(2.0 if a.t >= READS[0][0] + 0.2 else 0.0)  # from the tick at 0.2 s


def test_reads_out_of_time_order_are_refused() -> None:
    d = OfflineDaemon(config())
    with pytest.raises(ValueError, match="out of time order"):
        list(d.run([READS[1], READS[0]]))
