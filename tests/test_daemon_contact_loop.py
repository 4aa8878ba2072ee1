"""The service's contact loop outlives a look that raises: that look is lost (logged,
counted as a failed estimate), the next frames are estimated and published.

A look runs the pipeline's frame stages, the estimate's message and the contact identity
on whatever the worker answered. An exception in any of them left ``Service._contacts``
with it: the loop's task ended, no contact was published again while health went on, and
nothing was logged (a layout reload under a held press did this, through a contact carried
onto the new layout with an element it no longer has). Ingest already costs a bug one read
(``Service._on_data``); a look now costs it one look."""

from __future__ import annotations

import asyncio
import time
from typing import Any

import pytest
import zmq.asyncio
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.shell.contact_worker import InlineExecutor
from cellbridge.daemon.shell.service import Service

from daemon_traffic import GridFrames
from support.shell_fakes import FakeClock, RecordingHooks

STRADDLE = (0.020, 0.006, 3.0, 0.012)  # on the seam of bridges 1 and 2
T0 = 1_800_000_000.0


def test_a_look_that_raises_costs_that_look_not_the_contact_loop(capfd: pytest.CaptureFixture[str]) -> None:
    sk = GridFrames()
    cfg = parse_config({"link": [{"name": "gw", "url": "/dev/null"}], "contact": {"birth_frames": 1},
                        "pub": {"endpoint": "inproc://loop-errors"}, "control": {"endpoint": "inproc://loop-errors-ctl"}})
    clock = FakeClock(T0)

    async def run() -> tuple[int, list[dict[str, Any]], bool, int]:
        ctx = zmq.asyncio.Context()
        svc = Service(cfg, sk.layout, hooks=RecordingHooks(cfg), ctx=ctx, clock=clock, contact_executor=InlineExecutor)
        task = None
        try:
            svc._bind(ctx)
            got: list[dict[str, Any]] = []
            publish = svc.pub.publish

            def recording(topic: str, payload: dict[str, Any]) -> None:
                if topic == "contact":
                    got.append(payload)
                publish(topic, payload)

            svc.pub.publish = recording  # type: ignore[method-assign]  # (the real publisher, its contact messages kept)
            real = svc.pipeline.contact_frame
            raised: list[Any] = []

            def raises_once(job: Any, contacts: Any) -> Any:
                if not raised:
                    raised.append(job)
                    raise RuntimeError("a bug in one look")
                return real(job, contacts)

            svc.pipeline.contact_frame = raises_once  # type: ignore[method-assign]  # the bug, in the first message of a press
            task = asyncio.create_task(svc._contacts())
            svc._on_data("gw", sk.hellos() + sk.beacons(), T0)
            for k, data in [*sk.stream(60), *sk.stream(40, STRADDLE, start=60)]:
                clock.t = T0 + k / sk.rate
                svc._on_data("gw", data, clock.t)
                await asyncio.sleep(0.002)  # (the loop looks and estimates between reads)
            end = time.monotonic() + 10.0
            while len(got) < 5 and not task.done() and time.monotonic() < end:
                await asyncio.sleep(0.01)
            return len(raised), got, task.done(), svc.contacts.stats["errors"]
        finally:
            if task is not None:
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)
            svc.pub.sock.close(0)
            svc.ctl.close(0)
            svc.hooks.close()  # (its peer guard's thread, before the context ends)
            ctx.term()

    raised, got, ended, errors = asyncio.run(run())
    assert raised == 1  # the bug ran, in a look of the press
    assert not ended  # the loop goes on
    assert got and all(m["contacts"] for m in got)  # the press, estimated and published after it
    assert errors == 1 and "contact look failed" in capfd.readouterr().err  # (the daemon's log: stderr)
