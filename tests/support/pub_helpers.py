"""A real PUB socket publishing daemon-shaped messages, and subscriber processes to read it.

Messages have the daemon's wire shape: multipart ``[topic, msgpack map]`` with at
least ``v`` and ``t_host``. The publisher repeats them until stopped, so a
subscriber that connects late (ZeroMQ's slow joiner) still gets them.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import msgpack
import zmq


def daemon_messages(seq: int) -> list[tuple[str, dict[str, Any]]]:
    """One round of messages as the daemon publishes them (topics contact, health, raw)."""
    now = time.time()
    return [
        ("contact", {"v": 1, "t_host": now, "seq": seq,
                     "contacts": [{"id": 3, "x": 12.5, "y": -3.25, "force": 0.75, "valid": True}]}),
        ("health", {"v": 1, "t_host": now, "seq": seq, "links": {"/dev/ttyUSB0": {"frames_ok": seq, "drops": 0}}}),
        ("raw", {"v": 1, "t_host": now, "seq": seq, "bridge": 7, "frame": b"\x01\xfe"}),
    ]


@contextlib.contextmanager
def publisher(setup: Callable[[zmq.Socket], None] | None = None, period: float = 0.02,
              extra: Sequence[list[bytes]] = (), context: zmq.Context | None = None) -> Iterator[str]:
    """Publish :func:`daemon_messages` (and ``extra`` raw multipart messages) every ``period``.

    Yields the bound endpoint (tcp://127.0.0.1:PORT). ``setup`` configures the socket
    before bind (e.g. ``CurveServer.apply``, whose context must then be passed: ZAP
    works per context). The socket lives on its own thread only.
    """
    stop, bound = threading.Event(), threading.Event()
    endpoint: list[str] = []
    own_context = context is None
    context = zmq.Context() if context is None else context

    def loop() -> None:
        sock = context.socket(zmq.PUB)
        sock.linger = 0
        try:
            if setup is not None:
                setup(sock)
            sock.bind("tcp://127.0.0.1:*")
            endpoint.append(sock.get_string(zmq.LAST_ENDPOINT))
            bound.set()
            seq = 0
            while not stop.wait(period):
                for topic, payload in daemon_messages(seq):
                    sock.send_multipart([topic.encode(), msgpack.packb(payload)])
                for parts in extra:
                    sock.send_multipart(parts)
                seq += 1
        finally:
            sock.close()
            bound.set()

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    try:
        assert bound.wait(10) and endpoint, "publisher did not bind"
        yield endpoint[0]
    finally:
        stop.set()
        thread.join(10)
        if own_context:
            context.term()


def run_subscriber(cmd: Sequence[str], timeout: float = 30, **kwargs: Any) -> subprocess.CompletedProcess[str]:
    """Run a subscriber process in its own process group; the group is killed however it ends."""
    proc = subprocess.Popen(list(cmd), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, **kwargs)
    try:
        out, err = proc.communicate(timeout=timeout)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def json_lines(text: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in text.splitlines() if line.strip()]
