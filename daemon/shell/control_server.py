"""The control socket's shell: receive requests, run each in its own task, send the replies.

Parsing and validation are sans-I/O (:mod:`cellbridge.daemon.core.control`); commands that
travel to bridges wait here on a future the service resolves as replies come in, so a
client waiting for a slow bridge holds up no other client and no ingest.
"""

from __future__ import annotations

import asyncio
import logging
from collections import Counter
from typing import Any, Protocol

import zmq
import zmq.asyncio
from cellbridge.daemon.core.commands import Pending
from cellbridge.daemon.core.config import Config
from cellbridge.daemon.core.control import COMMANDS, Request, RequestError, error, parse_request, reply, too_large
from cellbridge.daemon.core.wire import PING
from cellbridge.daemon.shell.logs import event
from cellbridge.daemon.shell.publisher import pack

from cellbridge._version import __version__

#: Frames one request may have (routing envelope, delimiter, body); more make it oversize.
MAX_FRAMES = 16


class Host(Protocol):
    """What the control server needs of the service, and all it may do: it never holds
    the pipeline or the links. Writes on a link go the service's one way (the same as
    the pipeline's own messages take)."""

    config: Config

    def now(self) -> float:
        """The pipeline's time base (command deadlines are kept on it)."""
        ...

    def wall(self, now: float) -> float:
        """``now`` on the wall clock, as published stamps are."""
        ...

    def status_body(self, now: float) -> dict[str, Any]: ...

    def topology_body(self, now: float) -> dict[str, Any]: ...

    def tare(self, bridges: list[int] | None) -> int: ...

    def send_command(self, op: int, value: int | None, target: int | None, now: float,
                     timeout: float) -> tuple[int, list[str]]:
        """Start a command and write it on its links: its token and the links it went out
        on. ValueError for a bridge never heard from."""
        ...

    def finished_commands(self, now: float) -> list[Pending]: ...

    def expire_command(self, token: int) -> Pending | None:
        """End command ``token`` as timed out now (None: it already finished)."""
        ...


class ControlServer:
    def __init__(self, sock: zmq.asyncio.Socket, host: Host, log: logging.Logger) -> None:
        self.sock = sock
        self.host = host
        self.log = log
        self._waiting: dict[int, asyncio.Future[dict[str, Any]]] = {}
        self._answers: set[asyncio.Task[Any]] = set()
        self.counts: Counter[str] = Counter({"requests": 0, "errors": 0, "oversize": 0, "busy": 0})

    async def serve(self) -> None:
        limits = self.host.config.control
        while True:
            envelope, body, size = await self._receive(limits.max_request_bytes)
            self.counts["requests"] += 1
            if body is None:
                self.counts["oversize"] += 1
                event(self.log, "info", "control request too large", bytes=size)
                await self._send(envelope, too_large(size, limits.max_request_bytes))
            elif len(self._answers) >= limits.max_pending:
                self.counts["busy"] += 1
                await self._send(envelope, _busy(body, len(self._answers)))
            else:
                task = asyncio.create_task(self._answer(envelope, body))  # a slow command never holds up others
                self._answers.add(task)
                task.add_done_callback(self._answers.discard)

    async def _receive(self, limit: int) -> tuple[list[bytes], bytes | None, int]:
        """One request: (envelope, body, size in bytes). Its frames are read one at a time;
        past ``limit`` bytes (or ``MAX_FRAMES`` frames) the rest is read and dropped and the
        body is None, so no client can make the daemon hold more than ``limit`` for it."""
        frames: list[bytes] = []
        size, whole = 0, True
        more = True
        while more:
            part = await self.sock.recv()
            more = bool(self.sock.getsockopt(zmq.RCVMORE))
            size += len(part)
            if whole and (size > limit or len(frames) >= MAX_FRAMES):
                whole = False
            if whole:
                frames.append(part)
            elif len(frames) < 2 and not part:
                frames.append(part)  # the REQ delimiter still belongs to the envelope
        if not whole:
            envelope = frames[:1] + [f for f in frames[1:2] if not f]
            return envelope, None, size
        return frames[:-1], frames[-1], size

    async def _send(self, envelope: list[bytes], rep: dict[str, Any]) -> None:
        if not rep.get("ok"):
            self.counts["errors"] += 1
        await self.sock.send_multipart([*envelope, pack(rep)])

    def stats(self) -> dict[str, int]:
        """Requests read, answered with an error, refused as too large, refused as busy; in progress."""
        return {**self.counts, "in_progress": len(self._answers)}

    async def finish(self, limit: float = 1.0) -> None:
        """Let requests in progress answer (commands still waiting get their timeout reply)."""
        self.resolve(self.host.now() + 3600.0)
        if self._answers:
            await asyncio.wait(self._answers, timeout=limit)

    def resolve(self, now: float) -> None:
        """Complete the commands whose bridges all answered or whose time ran out."""
        for p in self.host.finished_commands(now):
            fut = self._waiting.pop(p.token, None)
            if fut is not None and not fut.done():
                fut.set_result(p.result())

    async def command(self, op: int, value: int | None, target: int | None, timeout: float) -> dict[str, Any]:
        now = self.host.now()
        token, sent = self.host.send_command(op, value, target, now, timeout)
        fut: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._waiting[token] = fut
        self.resolve(now)  # a broadcast with nobody alive completes at once
        try:
            async with asyncio.timeout(timeout + 1.0):  # (not wait_for: it can lose a cancel, see the service)
                result = await fut
        except TimeoutError:
            # The time base never reached the deadline: a replay's recorded clock stands still
            # between its reads and after its last (or has not started). The command ends as
            # timed out on the host's clock, with the reply a timeout gives: who did not answer.
            self._waiting.pop(token, None)
            pending = self.host.expire_command(token)
            if pending is None:  # finished meanwhile: resolved, or about to be
                if not fut.done():
                    raise
                result = fut.result()
            else:
                result = pending.result()
        result["sent_on"] = sent
        return result

    async def _answer(self, envelope: list[bytes], body: bytes) -> None:
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
        await self._send(envelope, rep)

    async def _execute(self, req: Request) -> dict[str, Any]:
        now = self.host.now()
        timeout = req.timeout or self.host.config.control.command_timeout
        if req.cmd == "status":
            return reply(True, req.id, **self.host.status_body(now))
        if req.cmd == "topology":
            return reply(True, req.id, **self.host.topology_body(now))
        if req.cmd == "tare":
            n = self.host.tare(None if req.bridges is None else list(req.bridges))
            return reply(True, req.id, tared_elements=n)
        if req.cmd == "ping" and req.bridge is None:
            return reply(True, req.id, pong=True, version=__version__, t_host=self.host.wall(now),
                         commands=COMMANDS)
        op, value = (int(PING), None) if req.cmd == "ping" else (req.op, req.value)
        result = await self.command(op, value, req.bridge, timeout)  # type: ignore[arg-type]  # a bridge command's op and value, checked by parse_request
        replies = result["replies"]
        ok = bool(replies) and not result["missing"] and all(r["status"] == "OK" for r in replies.values())
        if not ok:
            result["error"] = _command_error(result)
        return reply(ok, req.id, **result)


def _busy(body: bytes, in_progress: int) -> dict[str, Any]:
    """The reply when ``control.max_pending`` requests are in progress (with the request's
    id, so a client pipelining over DEALER knows which one to send again)."""
    try:
        rid = parse_request(body).id
    except RequestError as exc:
        return error(str(exc))
    return error(f"busy: {in_progress} requests in progress (control.max_pending); send it again later", rid)


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
