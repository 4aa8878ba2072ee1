"""A stand-in for the daemon's two sockets, for the views' tests: a PUB the test publishes
any payload on (well-formed or not) and a control socket that answers ``topology``.

The views are real processes connected over loopback ZeroMQ, as to a daemon; what they
are sent is entirely the test's (the fuzz test's random and mistyped messages, two
sources on one endpoint). :meth:`FakeDaemon.publish` packs with msgpack as the daemon
does; :meth:`FakeDaemon.publish_raw` sends frames as given.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import msgpack
import zmq

from daemon_harness import free_port

SIDE = 0.04


def grid_layout(rows: int = 3, cols: int = 3, side: float = SIDE) -> dict[str, Any]:
    """A ``topology``-shaped layout: bridge ids 1.. along rows from the corner."""
    ids = list(range(1, rows * cols + 1))
    return {"side": side, "ids": ids, "x": [side / 2 + side * ((i - 1) % cols) for i in ids],
            "y": [side / 2 + side * ((i - 1) // cols) for i in ids]}


class FakeDaemon:
    """PUB and control (ROUTER) sockets bound on loopback; :attr:`endpoints` as the
    daemon's config would give them. ``reply(request) -> reply`` answers control requests
    (default: ``topology`` with :attr:`layout`, ``ok`` for anything else). Always
    :meth:`close` it (a context manager)."""

    def __init__(self, layout: dict[str, Any] | None = None,
                 reply: Callable[[Any], Any] | None = None, sndhwm: int = 1000) -> None:
        self.layout = layout if layout is not None else grid_layout()
        self.reply = reply or self._reply
        self.ctx = zmq.Context()
        self.pub = self.ctx.socket(zmq.PUB)
        self.pub.linger = 0
        self.pub.sndhwm = sndhwm  # per subscriber: a large one holds a burst for a slow view instead of dropping it
        self.endpoints = {"pub": f"tcp://127.0.0.1:{free_port()}", "control": f"tcp://127.0.0.1:{free_port()}"}
        self.pub.bind(self.endpoints["pub"])
        self.requests = 0
        self._stop = threading.Event()
        self._control = threading.Thread(target=self._serve, name="fake control", daemon=True)
        self._control.start()

    def _reply(self, request: Any) -> Any:
        rid = request.get("id") if isinstance(request, dict) else None
        if isinstance(request, dict) and request.get("cmd") == "topology":
            return {"v": 1, "id": rid, "ok": True, "layout": self.layout}
        return {"v": 1, "id": rid, "ok": True}

    def _serve(self) -> None:
        sock = self.ctx.socket(zmq.ROUTER)
        sock.linger = 0
        sock.bind(self.endpoints["control"])
        try:
            while not self._stop.is_set():
                if not sock.poll(100):
                    continue
                frames = sock.recv_multipart()
                self.requests += 1
                try:
                    request = msgpack.unpackb(frames[-1], raw=False, strict_map_key=False)
                except ValueError:
                    continue
                sock.send_multipart([*frames[:-1], msgpack.packb(self.reply(request), use_bin_type=True)])
        finally:
            sock.close()

    def publish(self, topic: str, payload: Any) -> None:
        self.pub.send_multipart([topic.encode(), msgpack.packb(payload, use_bin_type=True)])

    def publish_raw(self, frames: list[bytes]) -> None:
        self.pub.send_multipart(frames)

    def close(self) -> None:
        self._stop.set()
        self._control.join(5)
        self.ctx.destroy(linger=0)

    def __enter__(self) -> FakeDaemon:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
