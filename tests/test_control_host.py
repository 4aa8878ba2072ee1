"""The control server needs only its narrow ``Host``: no pipeline, no links.

A host that has nothing but :class:`~cellbridge.daemon.shell.control_server.Host`'s members
answers every request over a real ROUTER socket on loopback; a bridge command goes out
through ``Host.send_command`` (the service's one road to the links) and its reply comes
back through ``Host.finished_commands``.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

import msgpack
import zmq
import zmq.asyncio
from cellbridge.daemon.core.commands import CommandTracker, Pending
from cellbridge.daemon.core.config import parse_config
from cellbridge.daemon.shell.control_server import ControlServer
from cellbridge.protocol import CommandReply, Op, Status


class NarrowHost:
    """Only what ``Host`` lists; it writes commands on its 'links' (a list) itself."""

    def __init__(self) -> None:
        self.config = parse_config({})
        self.t = 100.0
        self.commands = CommandTracker()
        self.written: list[tuple[str, int]] = []  # (link, token)
        self.tared: list[list[int] | None] = []

    def now(self) -> float:
        return self.t

    def wall(self, now: float) -> float:
        return now + 1000.0

    def status_body(self, now: float) -> dict[str, Any]:
        return {"uptime": now}

    def topology_body(self, now: float) -> dict[str, Any]:
        return {"bridges": {}, "t": now}

    def tare(self, bridges: list[int] | None) -> int:
        self.tared.append(bridges)
        return 3

    def send_command(self, op: int, value: int | None, target: int | None, now: float,
                     timeout: float) -> tuple[int, list[str]]:
        if target != 7:
            raise ValueError(f"bridge {target} has not been heard from on any link")
        p = self.commands.start(op, value, {7}, now, timeout)
        self.written.append(("gw", p.token))
        return p.token, ["gw"]

    def finished_commands(self, now: float) -> list[Pending]:
        return self.commands.done(now)

    def expire_command(self, token: int) -> Pending | None:
        return self.commands.expire(token)


async def _session(host: NarrowHost) -> list[dict[str, Any]]:
    ctx = zmq.asyncio.Context()
    server_sock = ctx.socket(zmq.ROUTER)
    client = ctx.socket(zmq.DEALER)
    try:
        for s in (server_sock, client):
            s.setsockopt(zmq.LINGER, 0)
        port = server_sock.bind_to_random_port("tcp://127.0.0.1")
        client.connect(f"tcp://127.0.0.1:{port}")
        server = ControlServer(server_sock, host, logging.getLogger("test.control"))
        serving = asyncio.create_task(server.serve())
        requests = [{"cmd": "status", "id": 1}, {"cmd": "topology", "id": 2}, {"cmd": "tare", "bridges": [4, 5], "id": 3},
                    {"cmd": "ping", "id": 4}, {"cmd": "ping", "bridge": 9, "id": 5}, {"cmd": "ping", "bridge": 7, "id": 6}]
        for r in requests:
            await client.send_multipart([b"", msgpack.packb(r)])
        replies: list[dict[str, Any]] = []
        async with asyncio.timeout(10.0):
            while len(replies) < 5:
                replies.append(msgpack.unpackb((await client.recv_multipart())[-1]))
            while not host.written:  # the ping to bridge 7 went out: its bridge answers
                await asyncio.sleep(0.01)
            host.t += 0.004
            (link, token), = host.written
            host.commands.reply(7, CommandReply(token, Op.PING, Status.OK), host.t)
            server.resolve(host.t)
            replies.append(msgpack.unpackb((await client.recv_multipart())[-1]))
        serving.cancel()
        await asyncio.gather(serving, return_exceptions=True)
        return sorted(replies, key=lambda r: r["id"])
    finally:
        client.close()
        server_sock.close()
        ctx.term()


def test_the_control_server_answers_through_the_narrow_host_alone() -> None:
    host = NarrowHost()
    status, topo, tare, alive, unknown, ping = asyncio.run(_session(host))
    assert status["ok"] and status["uptime"] == 100.0
    assert topo["ok"] and topo["t"] == 100.0
    assert tare["ok"] and tare["tared_elements"] == 3 and host.tared == [[4, 5]]
    assert alive["ok"] and alive["pong"] and alive["t_host"] == 1100.0  # the host's wall clock, not the pipeline's
    assert not unknown["ok"] and "bridge 9 has not been heard from" in unknown["error"]
    assert ping["ok"] and ping["sent_on"] == ["gw"] and set(ping["replies"]) == {"7"}
    assert abs(ping["replies"]["7"]["rtt"] - 0.004) < 1e-9
