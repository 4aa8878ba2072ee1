"""An in-process daemon service run to its end, with what it published.

The service (:class:`cellbridge.daemon.shell.service.Service`) runs on its own event loop
with replay links that end when done; a SUB socket of the same ZeroMQ context reads its
topics on an inproc endpoint. ``on_message`` sees every message as it comes (a test that
reloads the service at its first contact, say) and may return extra entries to record.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from typing import Any

import msgpack
import zmq
import zmq.asyncio

Got = list[tuple[str, dict[str, Any]]]


def service_messages(make: Callable[[zmq.asyncio.Context], Any], endpoint: str, topics: tuple[str, ...],
                     on_message: Callable[[Any, Got], None] | None = None, timeout: float = 60.0) -> Got:
    """(topic, payload) of everything the service ``make(ctx)`` published on ``topics`` at
    ``endpoint`` until it exited (it must exit with status 0), in order; ``on_message(svc,
    got)`` after each message received while it runs."""

    async def run() -> Got:
        ctx = zmq.asyncio.Context()
        svc = make(ctx)
        sub = ctx.socket(zmq.SUB)
        got: Got = []
        try:
            for topic in topics:
                sub.setsockopt(zmq.SUBSCRIBE, topic.encode())
            task = asyncio.create_task(svc.run())
            for _ in range(500):  # the service binds first (inproc: connect after bind)
                await asyncio.sleep(0.01)
                try:
                    sub.connect(endpoint)
                    break
                except zmq.ZMQError:
                    continue
            while not task.done():
                # poll, then receive: a receive cancelled by a timeout could take a message
                # with it on a loaded machine (the last health, the one a test looks for)
                if await sub.poll(200):
                    parts = await sub.recv_multipart()
                    got.append((parts[0].decode(), msgpack.unpackb(parts[1])))
                    if on_message is not None:
                        on_message(svc, got)
            assert await asyncio.wait_for(task, 30) == 0
            while await sub.poll(100):
                parts = await sub.recv_multipart()
                got.append((parts[0].decode(), msgpack.unpackb(parts[1])))
        finally:
            sub.close(linger=0)
            ctx.destroy(linger=0)
        return got

    return asyncio.run(asyncio.wait_for(run(), timeout))
