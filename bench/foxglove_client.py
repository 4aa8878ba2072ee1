"""A client of the Foxglove WebSocket protocol v1 (``foxglove.websocket.v1``, now ``foxglove.sdk.v1``).

Enough of the protocol to check a server as Foxglove sees it: the server's ``serverInfo``
and ``advertise`` (JSON text frames), ``subscribe``, and binary ``messageData`` frames
(opcode 1, subscription id u32, log time u64 ns, payload, little-endian). Protobuf
channels are decoded with the schema the server advertised (a base64
FileDescriptorSet), not with a copy of Foxglove's ``.proto`` files.
"""

from __future__ import annotations

import base64
import json
import struct
import time
from contextlib import ExitStack
from typing import Any

# The protocol's v1 under both of its names: "foxglove.sdk.v1" (the SDK's) is
# "foxglove.websocket.v1" (the ws-protocol spec's) renamed; a client offers both and the
# server picks (cellbridge/views/subprotocol.py).
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


class FoxgloveClient:
    def __init__(self, url: str, subprotocols: list[str] | None = None) -> None:
        """``subprotocols``: what the client offers (default both names, as Foxglove's app does)."""
        from websockets.sync.client import connect

        self._stack = ExitStack()  # websockets wants its connections used as context managers
        self.ws = self._stack.enter_context(connect(url, subprotocols=subprotocols or SUBPROTOCOLS,  # type: ignore[arg-type]
                                                    max_size=64 * 1024 * 1024, open_timeout=10, compression=None))
        self.server_info: dict[str, Any] | None = None
        self.channels: dict[int, dict[str, Any]] = {}
        self.subs: dict[int, int] = {}  # subscription id -> channel id
        self.decoders: dict[int, Any] = {}

    @property
    def subprotocol(self) -> str | None:
        return self.ws.subprotocol

    def _handle_text(self, text: str) -> None:
        msg = json.loads(text)
        if msg.get("op") == "serverInfo":
            self.server_info = msg
        elif msg.get("op") == "advertise":
            for ch in msg["channels"]:
                self.channels[ch["id"]] = ch
        elif msg.get("op") == "unadvertise":
            for cid in msg["channelIds"]:
                self.channels.pop(cid, None)

    def by_topic(self, topic: str) -> dict[str, Any] | None:
        return next((c for c in self.channels.values() if c["topic"] == topic), None)

    def wait_channels(self, topics: list[str], timeout: float = 10.0) -> None:
        end = time.monotonic() + timeout
        while not all(self.by_topic(t) for t in topics):
            left = end - time.monotonic()
            if left <= 0:
                raise AssertionError(f"not advertised within {timeout} s: "
                                     f"{[t for t in topics if not self.by_topic(t)]} (have {self.channels})")
            msg = self.ws.recv(timeout=left)
            if isinstance(msg, str):
                self._handle_text(msg)

    def subscribe(self, topic: str) -> int:
        ch = self.by_topic(topic)
        assert ch is not None, topic
        sid = len(self.subs) + 1
        self.subs[sid] = ch["id"]
        self.ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": sid, "channelId": ch["id"]}]}))
        return sid

    def decoder(self, channel: dict[str, Any]) -> Any:
        """A function payload -> decoded message, from the channel's advertised schema."""
        if channel["encoding"] == "json":
            return lambda data: json.loads(data)
        assert channel["encoding"] == "protobuf" and channel["schemaEncoding"] == "protobuf", channel
        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

        fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
        pool = descriptor_pool.DescriptorPool()
        for fd in fds.file:
            pool.Add(fd)
        cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
        return cls.FromString

    def next_message(self, topic: str, timeout: float = 10.0, pred: Any = lambda m: True) -> tuple[int, Any]:
        """(log time ns, decoded message) of the next message on ``topic`` that satisfies ``pred``."""
        ch = self.by_topic(topic)
        assert ch is not None
        if ch["id"] not in self.decoders:
            self.decoders[ch["id"]] = self.decoder(ch)
        want = {sid for sid, cid in self.subs.items() if cid == ch["id"]}
        end = time.monotonic() + timeout
        while True:
            left = end - time.monotonic()
            if left <= 0:
                raise AssertionError(f"no matching message on {topic} within {timeout} s")
            msg = self.ws.recv(timeout=left)
            if isinstance(msg, str):
                self._handle_text(msg)
                continue
            if msg[0] != 1:
                continue
            sid, log_time = struct.unpack_from("<IQ", msg, 1)
            if sid in want:
                decoded = self.decoders[ch["id"]](msg[13:])
                if pred(decoded):
                    return log_time, decoded

    def close(self) -> None:
        self._stack.close()
