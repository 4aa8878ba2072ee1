"""Downlink commands in flight: tokens, expected repliers, deadlines (sans-I/O).

A command to one bridge completes at its reply; a broadcast completes when every
bridge alive at sending time has replied, or at the deadline with the silent ones
listed. The shell awaits completion; this object only keeps the books.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from cellbridge.daemon.core.messages import LinkWrite
from cellbridge.daemon.core.wire import ADDR_BROADCAST, command_bytes, reply_fields


@dataclass(slots=True)
class Pending:
    token: int
    op: int
    value: int | None
    expected: set[int]
    sent_at: float
    deadline: float
    replies: dict[int, Any] = field(default_factory=dict)  # bridge -> CommandReply
    reply_at: dict[int, float] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        return self.expected <= set(self.replies)

    def result(self) -> dict[str, Any]:
        return {
            "replies": {str(b): {**reply_fields(r), "rtt": self.reply_at[b] - self.sent_at}
                        for b, r in sorted(self.replies.items())},
            "missing": sorted(self.expected - set(self.replies)),
        }


class CommandTracker:
    def __init__(self) -> None:
        self._pending: dict[int, Pending] = {}
        self._next = 1
        self.unmatched_replies = 0

    def start(self, op: int, value: int | None, expected: set[int], now: float, timeout: float) -> Pending:
        for _ in range(0x10000):
            token, self._next = self._next, (self._next % 0xFFFF) + 1
            if token not in self._pending:
                break
        else:  # pragma: no cover - 65535 commands in flight
            raise RuntimeError("no free command token")
        p = self._pending[token] = Pending(token, op, value, set(expected), now, now + timeout)
        return p

    def send(self, op: int, value: int | None, target: int | None, expected: set[int], links: Iterable[str],
             now: float, timeout: float) -> tuple[Pending, list[LinkWrite]]:
        """Start a command to ``target`` (None: a broadcast) awaiting replies of ``expected``:
        the command and the writes that send it on ``links``."""
        p = self.start(op, value, expected, now, timeout)
        data = command_bytes(ADDR_BROADCAST if target is None else target, p.token, op, value)  # type: ignore[arg-type]  # an Op value: the control layer checks it
        return p, [LinkWrite(name, data) for name in links]

    def reply(self, bridge: int, reply: Any, now: float) -> Pending | None:
        """Record a reply; returns its command (None when no command waits for it)."""
        p = self._pending.get(reply.token)
        if p is None or int(reply.op) != p.op:
            self.unmatched_replies += 1
            return None
        if bridge not in p.replies:
            p.replies[bridge] = reply
            p.reply_at[bridge] = now
        return p

    def done(self, now: float) -> list[Pending]:
        """Commands complete or past their deadline (removed from the books)."""
        out = [p for p in self._pending.values() if p.complete or now >= p.deadline]
        for p in out:
            del self._pending[p.token]
        return out

    def expire(self, token: int) -> Pending | None:
        """Take command ``token`` off the books as timed out, whatever its deadline (None:
        it already finished)."""
        return self._pending.pop(token, None)

    def clock_stepped_back(self, now: float) -> None:
        """Keep each command's full timeout from now instead of waiting out the step."""
        for p in self._pending.values():
            if p.sent_at > now:
                p.deadline = now + (p.deadline - p.sent_at)
                p.sent_at = now

    def __len__(self) -> int:
        return len(self._pending)

    def counters(self) -> dict[str, int]:
        """For ``health``: commands in flight, replies no command waited for."""
        return {"in_flight": len(self._pending), "unmatched_replies": self.unmatched_replies}
