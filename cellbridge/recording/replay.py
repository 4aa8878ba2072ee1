"""``cellbridge replay IN.mcap``: a recording back onto ZeroMQ, as the daemon published it.

Each recorded message is sent as the daemon sent it: multipart ``[topic, msgpack
payload]``, the very payload (:mod:`cellbridge.recording.codec` is lossless), in the
order it was received, at its recorded time offsets (publish times) scaled by ``--rate``,
or as fast as possible. A subscriber cannot tell the replay from the daemon, except by
the clock: the payloads' ``t_host`` are the recorded ones.

:class:`Pacer` is the timing core (recorded offsets in, due times out); the shell sleeps
until each due time and sends.
"""

from __future__ import annotations

import argparse
import gc
import json
import signal
import sys
import time
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import zmq

from cellbridge.recording import codec
from cellbridge.recording.mcapfile import ReadResult, read_messages

DEFAULT_PUB = "tcp://127.0.0.1:5560"
SPIN = 0.001  #: s before a message is due that the replay waits awake (timing within a millisecond)
WORK_SLACK = 0.003  #: s of slack before the next message is due in which the replay prepares later ones
AHEAD = 2000  #: most messages read and encoded ahead of their turn


class Ahead:
    """The recordings' messages read, decoded and encoded to msgpack ahead of their turn.

    Reading (a chunk's decompression) and encoding take time; done right after a send,
    they made the next message late when it was due soon after (a burst: ``element``,
    ``contact`` and ``raw`` of one moment). The sending loop calls :meth:`prepare` while it
    has slack, so that work falls into the gaps between messages."""

    def __init__(self, paths: list[Path], topics: set[str] | None) -> None:
        self.queue: deque[tuple[bytes, bytes, float]] = deque()  # (topic, payload, recorded publish time s)
        self.notes: list[str] = []  # why a file ended early
        self._files = iter(paths)
        self._topics = topics
        self._messages: Iterator[Any] | None = None
        self._result = ReadResult()

    def prepare(self) -> bool:
        """Read and encode one more message (False: none left, or :data:`AHEAD` are waiting)."""
        if len(self.queue) >= AHEAD:
            return False
        while True:
            if self._messages is None:
                path = next(self._files, None)
                if path is None:
                    return False
                self._result = ReadResult()
                self._messages = iter(read_messages(path, self._result, self._topics))
            m = next(self._messages, None)
            if m is not None:
                self.queue.append((m.topic.encode(), codec.to_msgpack(codec.decode(m.topic, m.data)),
                                   m.publish_ns * 1e-9))
                return True
            if not self._result.complete:
                self.notes.append(self._result.error)
            self._messages = None


class Pacer:
    """When to send each message: ``start + (t - t_first) / rate``; rate 0: at once."""

    def __init__(self, rate: float) -> None:
        if rate < 0:
            raise ValueError("rate must be >= 0 (0: as fast as possible)")
        self.rate = rate
        self._first: float | None = None
        self._start = 0.0

    def due(self, recorded: float, now: float) -> float:
        """Host time (monotonic) at which the message recorded at ``recorded`` (s) goes out."""
        if self._first is None:
            self._first, self._start = recorded, now
        if self.rate == 0:
            return now
        return self._start + (recorded - self._first) / self.rate


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Publish a recording (cellbridge record) on a ZeroMQ PUB socket exactly as the daemon\n"
        "published it: same topics, same payloads, same order, at the recorded timing (or\n"
        "--rate times it, or --fast). Subscribers (cellbridge sub, watch, the examples) connect\n"
        "to it as to a daemon.\n\n"
        "examples:\n"
        "  cellbridge replay skin.mcap                          # real time on tcp://127.0.0.1:5560\n"
        "  cellbridge replay skin.mcap --rate 10 --topics contact\n"
        "  cellbridge replay skin.mcap --fast --wait-subscriber # flat out, once someone listens"
    )
    parser.add_argument("inputs", type=Path, nargs="+", metavar="IN.mcap", help="recording(s), played in order")
    parser.add_argument("--endpoint", default=DEFAULT_PUB, help=f"PUB endpoint to bind (default: {DEFAULT_PUB})")
    parser.add_argument("--rate", type=float, default=1.0, help="speed factor (default 1: recorded timing)")
    parser.add_argument("--fast", action="store_true", help="as fast as possible (same as --rate 0)")
    parser.add_argument("--topics", default="", help="comma-separated topics to replay (default: all recorded)")
    parser.add_argument("--wait-subscriber", action="store_true",
                        help="start once a subscriber has subscribed (nothing is lost to a slow connect)")
    parser.add_argument("--hwm", type=int, default=100_000, help="messages queued per subscriber (default 100000)")


def run(args: argparse.Namespace) -> int:
    rate = 0.0 if args.fast else args.rate
    try:
        pacer = Pacer(rate)
    except ValueError as exc:
        print(f"cellbridge replay: {exc}", file=sys.stderr)
        return 2
    for p in args.inputs:
        if not p.is_file():
            print(f"cellbridge replay: {p}: no such file", file=sys.stderr)
            return 2
    topics = {t.strip() for t in args.topics.split(",") if t.strip()} or None
    stop: list[bool] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(True))
    ctx = zmq.Context()
    sock = ctx.socket(zmq.XPUB)
    sock.sndhwm = args.hwm
    sock.linger = 2000
    sent = 0
    late: list[float] = []  # s each paced message went out after it was due (what the replay adds to timing)
    notes: list[str] = []
    try:
        sock.bind(args.endpoint)
        if args.wait_subscriber:
            while not stop:
                if sock.poll(100) and sock.recv()[:1] == b"\x01":
                    break
        gc.disable()  # decoded payloads hold no cycles; a collection would only delay a message
        t0 = time.monotonic()
        ahead = Ahead(args.inputs, topics)
        while not stop:
            if not ahead.queue and not ahead.prepare():
                break
            topic, payload, recorded = ahead.queue.popleft()
            due = pacer.due(recorded, time.monotonic())
            while not stop:
                wait = due - time.monotonic()
                if wait <= 0:
                    break
                if wait > SPIN + WORK_SLACK and ahead.prepare():  # idle: read and encode the next ones now
                    continue
                if wait > SPIN:  # sleep to just before it is due, then spin: wake-ups are late
                    time.sleep(min(wait - SPIN, 0.1))
                    _drain_subscriptions(sock)
            if stop:
                break
            sock.send_multipart([topic, payload])
            if rate:
                late.append(time.monotonic() - due)
            sent += 1
        notes += ahead.notes
        elapsed = time.monotonic() - t0
    except ValueError as exc:
        print(f"cellbridge replay: {exc}", file=sys.stderr)
        return 2
    except zmq.ZMQError as exc:
        print(f"cellbridge replay: {args.endpoint}: {exc}", file=sys.stderr)
        return 2
    finally:
        sock.close()
        ctx.term()
    print(json.dumps({"sent": sent, "seconds": round(elapsed, 3), "incomplete": notes, "late_ms": lateness(late)}),
          file=sys.stderr)
    return 0


def lateness(late: list[float]) -> dict[str, float]:
    """p50, p99 and max (ms) of how late paced messages went out; empty when none was paced."""
    if not late:
        return {}
    xs = sorted(late)
    q = (lambda f: round(xs[min(len(xs) - 1, int(f * len(xs)))] * 1e3, 3))
    return {"p50": q(0.5), "p99": q(0.99), "max": round(xs[-1] * 1e3, 3)}


def _drain_subscriptions(sock: zmq.Socket) -> None:
    """An XPUB reports (un)subscriptions; read them so they never pile up."""
    try:
        while True:
            sock.recv(zmq.NOBLOCK)
    except zmq.Again:
        pass
