"""Control requests to a daemon replaying in recorded time, whose clock is the
recording's: it stands still between reads and after the last, and is not there at all
before the first. A command's timeout must still end it (a reply that says who did not
answer), before the first read, between reads and after the end of the recording."""

from __future__ import annotations

import asyncio
import time
from typing import Any

import msgpack
import zmq
import zmq.asyncio
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.shell.contact_worker import InlineExecutor
from cellbridge.daemon.shell.service import Service

from support.golden_corpus import BASE_CONFIG, DATA
from support.shell_fakes import RecordingHooks

RECORDING = DATA / "multihop_line.mcap"  # bridges 1-6 on link gw1, 2.5 s


def _config(endpoint: str, *, wait_for_subscriber: bool) -> Any:
    data: dict[str, Any] = {k: dict(v) for k, v in BASE_CONFIG.items()}
    data["pub"] = {"endpoint": endpoint}
    data["control"] = {"endpoint": endpoint + "-ctl"}
    data["link"] = [{"name": "gw1", "url": f"replay:{RECORDING}", "replay_speed": 4.0, "replay_clock": "recorded",
                     "wait_for_subscriber": wait_for_subscriber}]
    return parse_config(data, "test")


async def _ask(ctx: zmq.asyncio.Context, endpoint: str, request: dict[str, Any], limit: float) -> tuple[dict[str, Any], float]:
    """The reply to ``request`` and how long it took (s)."""
    sock = ctx.socket(zmq.DEALER)
    sock.connect(endpoint)
    try:
        t = time.monotonic()
        await sock.send(msgpack.packb({"v": 1, **request}))
        assert await sock.poll(int(limit * 1000)), f"no reply to {request} within {limit} s"
        rep = msgpack.unpackb(await sock.recv(), raw=False, strict_map_key=False)
        return rep, time.monotonic() - t
    finally:
        sock.close(linger=0)


def _with_service(endpoint: str, wait_for_subscriber: bool, body: Any) -> Any:
    async def run() -> Any:
        ctx = zmq.asyncio.Context()
        cfg = _config(endpoint, wait_for_subscriber=wait_for_subscriber)
        svc = Service(cfg, hooks=RecordingHooks(cfg), ctx=ctx, contact_executor=InlineExecutor)
        task = asyncio.create_task(svc.run())
        try:
            await asyncio.sleep(0.2)
            return await body(ctx, svc)
        finally:
            svc._stop.set()
            assert await asyncio.wait_for(task, 15) == 0
            ctx.destroy(linger=0)

    return asyncio.run(run())


def test_a_command_after_the_recording_ended_times_out_with_a_reply_that_says_so() -> None:
    """The recording's clock stands still after its last read: a command's deadline on it
    never came, and the request ended on the control server's own bound as
    'internal error: TimeoutError', its pending command left in the pipeline."""
    endpoint = "inproc://recorded-control-end"

    async def body(ctx: zmq.asyncio.Context, svc: Service) -> None:
        for _ in range(100):  # the replay: 2.5 s at 4x
            if svc.links["gw1"].stats()["replay_finished"]:
                break
            await asyncio.sleep(0.1)
        assert svc.links["gw1"].stats()["replay_finished"]
        rep, took = await _ask(ctx, endpoint + "-ctl", {"cmd": "ping", "bridge": 3, "timeout": 0.3}, 5.0)
        assert not rep["ok"]
        assert "no reply within the timeout from bridges [3]" in rep["error"], rep
        assert rep["missing"] == [3], rep
        assert took < 2.0, took
        assert not svc.pipeline.commands_in_flight()

    _with_service(endpoint, False, body)


def test_a_command_before_the_first_read_times_out_with_a_reply_that_says_so() -> None:
    """Before its first read a replay in recorded time has no clock and nothing ticks: a
    command's deadline (taken on the wall clock) was never looked at."""
    endpoint = "inproc://recorded-control-before"

    async def body(ctx: zmq.asyncio.Context, svc: Service) -> None:
        assert svc.links["gw1"].stats()["replayed_records"] == 0  # held: no subscriber yet
        rep, took = await _ask(ctx, endpoint + "-ctl", {"cmd": "ping", "bridge": 3, "timeout": 0.3}, 5.0)
        assert not rep["ok"]
        assert "internal error" not in rep["error"], rep
        assert took < 2.0, took
        status, _ = await _ask(ctx, endpoint + "-ctl", {"cmd": "status"}, 5.0)
        assert status["ok"], status
        assert not svc.pipeline.commands_in_flight()

    _with_service(endpoint, True, body)
