"""The PUB side: multipart ``[topic, msgpack payload]`` that never blocks the daemon.

An XPUB socket behaves exactly like PUB for subscribers, and also tells the daemon
which topics anyone subscribed to, so nothing is built for a topic nobody reads (the
``raw`` columns cost as much as the ``element`` ones). Sends are non-blocking: a
subscriber that stops reading fills its own queue (``hwm`` messages) and then loses
messages — libzmq drops them for that subscriber alone, silently; every payload has a
per-topic ``seq`` so each subscriber can count its own gaps. What the daemon itself
could not hand to ZeroMQ is counted here (``dropped``): with ``strict`` (config
``pub.count_drops``) a message is refused when *any* subscriber's queue is full, so
every drop is counted exactly, at the price of that message missing for everyone.

Every payload names its daemon (``source``, config ``pub.source``, default the host
name and the PUB endpoint's port), added here where messages are serialised, so that several daemons behind one
``cellbridge proxy`` read as one stream a subscriber can still tell apart. The
``serial`` topic carries each link read's bytes exactly as read (the daemon's capture
stream), so a recorder can keep them and the whole pipeline can be re-run later; like
every topic it costs nothing while nobody subscribes to it.
"""

from __future__ import annotations

import asyncio
import socket
from collections import Counter
from collections.abc import Callable
from typing import Any

import msgpack
import numpy as np
import zmq
import zmq.asyncio

TOPICS = ("contact", "element", "raw", "health", "topology", "serial")


_TOPIC_BYTES = tuple(t.encode() for t in TOPICS)


def _can_match(prefix: bytes) -> bool:
    """A subscription matches a topic frame when it is a prefix of it ("" matches all)."""
    return any(t.startswith(prefix) for t in _TOPIC_BYTES)


def _default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"cannot pack {type(obj).__name__}")


def default_source(endpoint: str) -> str:
    """What ``source`` says when the config does not name the daemon: ``HOST:PORT`` (the
    host name and the PUB endpoint's port; ``HOST:ipc:///path`` for another transport).
    Unique per daemon on a host, as two daemons cannot bind one endpoint."""
    return f"{socket.gethostname()}:{endpoint.rpartition(':')[2] if endpoint.startswith('tcp://') else endpoint}"


def pack(payload: dict[str, Any]) -> bytes:
    return msgpack.packb(payload, use_bin_type=True, default=_default)


class Publisher:
    def __init__(self, ctx: zmq.asyncio.Context, endpoint: str, hwm: int, strict: bool = False,
                 source: str = "") -> None:
        self.endpoint = endpoint
        self.source = source or default_source(endpoint)
        self.sock = ctx.socket(zmq.XPUB)
        self.sock.setsockopt(zmq.SNDHWM, hwm)
        if strict:
            self.sock.setsockopt(zmq.XPUB_NODROP, 1)
        self.subscriptions_unmatched = 0  # (first) subscriptions to a prefix that matches no topic
        self.sock.setsockopt(zmq.LINGER, 1000)  # on shutdown, 1 s to flush what is queued
        self._raw: zmq.Socket[bytes] = zmq.Socket.shadow(self.sock.underlying)  # plain non-blocking sends: no futures
        self._prefixes: Counter[bytes] = Counter()
        self.wanted: set[str] = set()
        self.subscribed = asyncio.Event()
        self.sent: Counter[str] = Counter()
        self.dropped: Counter[str] = Counter()
        self.on_wanted: Callable[[set[str]], None] | None = None
        self._serial_seq = 0

    def bind(self) -> None:
        self.sock.bind(self.endpoint)

    def publish(self, topic: str, payload: dict[str, Any]) -> None:
        payload["source"] = self.source
        try:
            self._raw.send_multipart([topic.encode(), pack(payload)], zmq.NOBLOCK)
            self.sent[topic] += 1
        except zmq.Again:
            self.dropped[topic] += 1

    def serial(self, link: str, data: bytes, now: float, t_read: float) -> None:
        """One link read on topic ``serial`` (``link``, ``t_host`` = its arrival on the wall
        clock, ``t_read`` = on the clock a replay runs on, ``data``), if wanted."""
        if "serial" in self.wanted:
            self.publish("serial", {"v": 2, "seq": self._serial_seq, "t_host": now, "t_read": t_read,
                                    "t_bridge": None, "link": link, "data": data})
            self._serial_seq += 1

    async def watch_subscriptions(self) -> None:
        """Keep :attr:`wanted` (topics some subscriber asked for) up to date; count the
        subscriptions that can match no topic (``subscriptions_unmatched``: a client's bug)
        without keeping them here."""
        while True:
            msg = await self.sock.recv()
            if not msg:
                continue
            prefix = bytes(msg[1:])
            if not _can_match(prefix):
                self.subscriptions_unmatched += msg[0] == 1
                continue
            if msg[0] == 1:
                self._prefixes[prefix] += 1
            elif msg[0] == 0 and self._prefixes[prefix] > 0:
                self._prefixes[prefix] -= 1
                if not self._prefixes[prefix]:
                    del self._prefixes[prefix]
            self.wanted = {t for t in TOPICS if any(t.encode().startswith(p) for p in self._prefixes)}
            if self.on_wanted is not None:
                self.on_wanted(self.wanted)
            if self.wanted:
                self.subscribed.set()

    def stats(self) -> dict[str, Any]:
        return {"endpoint": self.endpoint, "sent": dict(self.sent), "dropped": dict(self.dropped),
                "subscribed_topics": sorted(self.wanted), "subscriptions_unmatched": self.subscriptions_unmatched}

    def close(self) -> None:
        self.sock.close()
