"""``cellbridge replay IN.mcap``: a recording back onto ZeroMQ, as the daemon published it.

Each recorded message is sent as the daemon sent it: multipart ``[topic, msgpack
payload]``, the very payload (:mod:`cellbridge.recording.codec` is lossless), in the
order it was received, at its recorded time offsets (publish times) scaled by ``--rate``,
or as fast as possible. A subscriber cannot tell the replay from the daemon, except by
the clock: the payloads' ``t_host`` are the recorded ones.

A pause in the recording longer than ``--max-gap`` (the daemon was stopped, or, in a
recording made before publish times were monotonic, the recorder's wall clock stepped
forward) is shortened to it, and a step back in publish times is not waited out; both
are announced on stderr, so a replay is never silent for long without saying why.

A damaged recording is replayed from every part that can be read (the messages of a
damaged chunk, and messages that do not decode, are skipped); one line on stderr per
file says what was skipped, and the exit status is 1.

:class:`Pacer` is the timing core (recorded offsets in, due times out); the shell sleeps
until each due time and sends.
"""

from __future__ import annotations

import argparse
import gc
import json
import math
import random
import signal
import sys
import time
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import zmq

from cellbridge.daemon.ops.security import endpoint_error
from cellbridge.recording import codec
from cellbridge.recording.mcapfile import NotARecording, ReadResult, read_payloads
from cellbridge.recording.schemas import SCHEMAS

DEFAULT_PUB = "tcp://127.0.0.1:5560"
SPIN = 0.001  #: s before a message is due that the replay waits awake (timing within a millisecond)
WORK_SLACK = 0.003  #: s of slack before the next message is due in which the replay prepares later ones
AHEAD = 2000  #: most messages read and encoded ahead of their turn
AHEAD_BYTES = 16 << 20  #: ... and most bytes of them (a few large messages fill it before AHEAD small ones)
DEFAULT_MAX_GAP = 10.0  #: s of recording: a longer pause is shortened to this (--max-gap)
BACK_STEP = 1.0  #: s: publish times going back more than this is a clock step, announced
NOTICES = 10  #: gap notices printed per replay (the rest counted in the final line)


class Ahead:
    """The recordings' messages read, decoded and encoded to msgpack ahead of their turn.

    Reading (a chunk's decompression) and encoding take time; done right after a send,
    they made the next message late when it was due soon after (a burst: ``element``,
    ``contact`` and ``raw`` of one moment). The sending loop calls :meth:`prepare` while it
    has slack, so that work falls into the gaps between messages."""

    def __init__(self, paths: list[Path], topics: set[str] | None) -> None:
        #: (topic, payload, recorded publish time s, file)
        self.queue: deque[tuple[bytes, bytes, float, Path]] = deque()
        self.queued_bytes = 0
        self.notes: list[str] = []  # why a file ended early
        self.problems: list[str] = []  # one line per file that was damaged or is not a recording
        self.skipped = 0  # messages and damaged parts skipped, over all files
        self._files = iter(paths)
        self._topics = topics
        self._messages: Iterator[Any] | None = None
        self._result = ReadResult()
        self._path = Path()

    def popleft(self) -> tuple[bytes, bytes, float, Path]:
        item = self.queue.popleft()
        self.queued_bytes -= len(item[1])
        return item

    def prepare(self) -> bool:
        """Read and encode one more message (False: none left, or :data:`AHEAD` (or
        :data:`AHEAD_BYTES`) are waiting)."""
        if len(self.queue) >= AHEAD or self.queued_bytes >= AHEAD_BYTES:
            return False
        while True:
            if self._messages is None:
                path = next(self._files, None)
                if path is None:
                    return False
                self._result, self._path = ReadResult(), path
                self._messages = iter(read_payloads(path, self._result, self._topics))
            try:
                item = next(self._messages, None)
            except NotARecording as exc:
                self.problems.append(str(exc))
                item = None
            except OSError as exc:
                self.problems.append(f"{self._path}: {exc.strerror or exc}")
                item = None
            if item is not None:
                m, payload = item
                try:
                    data = codec.to_msgpack_checked(payload)
                except codec.PayloadError as exc:
                    self._result.add_bad_message(f"a message on {m.topic[:40]!r} (chunk at byte {m.offset}): {exc}")
                    continue
                self.queue.append((m.topic.encode(), data, m.publish_ns * 1e-9, self._path))
                self.queued_bytes += len(data)
                return True
            if not self._result.complete and self._result.error:
                self.notes.append(self._result.error)
            if not self._result.ok:
                self.problems.append(self._result.problem(self._path))
                self.skipped += self._result.damaged + self._result.bad_messages
            self._messages = None


class Pacer:
    """When to send each message: ``start + (t - t_first - cut) / rate``; rate 0: at once.

    ``cut`` is the recorded time left out: of a pause longer than ``max_gap`` (s of
    recording) all but ``max_gap``; of a step back in publish times of more than
    :data:`BACK_STEP`, the step (the message goes out at once, and the ones after keep
    their intervals). After each :meth:`due`, :attr:`notice` says whether that message
    followed such a pause or step: ``(recorded interval s, wait s)``, else None.
    """

    def __init__(self, rate: float, max_gap: float = DEFAULT_MAX_GAP) -> None:
        if not rate >= 0:
            raise ValueError("rate must be >= 0 (0: as fast as possible)")
        if not max_gap > 0:
            raise ValueError("max gap must be > 0 s (inf: keep every pause)")
        self.rate = rate
        self.max_gap = max_gap
        self._first: float | None = None
        self._last = 0.0
        self._start = 0.0
        self._cut = 0.0
        self.notice: tuple[float, float] | None = None

    def due(self, recorded: float, now: float) -> float:
        """Host time (monotonic) at which the message recorded at ``recorded`` (s) goes out."""
        self.notice = None
        if self._first is None:
            self._first = self._last = recorded
            self._start = now
        step = recorded - self._last
        self._last = recorded
        if step > self.max_gap:
            self._cut += step - self.max_gap
            if self.rate:
                self.notice = (step, self.max_gap / self.rate)
        elif step < -BACK_STEP:
            self._cut += step
            if self.rate:
                self.notice = (step, 0.0)
        if self.rate == 0:
            return now
        return self._start + (recorded - self._first - self._cut) / self.rate


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Publish a recording (cellbridge record) on a ZeroMQ PUB socket exactly as the daemon\n"
        "published it: same topics, same payloads, same order, at the recorded timing (or\n"
        "--rate times it, or --fast). Subscribers (cellbridge sub, watch, the examples) connect\n"
        "to it as to a daemon. A pause longer than --max-gap is shortened and said on stderr.\n"
        "A damaged recording is replayed from every part that can be read; a line on stderr\n"
        "names the file and what was skipped (exit status 1).\n\n"
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
    parser.add_argument("--hwm", type=int, default=100_000, help="messages queued per subscriber, at least 1 (default 100000)")
    parser.add_argument("--max-gap", type=float, default=DEFAULT_MAX_GAP, metavar="S",
                        help=f"shorten a pause in the recording longer than S s to S s, and say so on stderr "
                             f"(default {DEFAULT_MAX_GAP:g}; inf keeps every pause)")


def _gap_notice(path: Path, n: int, step: float, wait: float) -> str:
    if step < 0:
        return (f"cellbridge replay: {path}: publish times go back {-step:.1f} s after message {n} "
                f"(the clock stepped while recording): going on at once")
    return (f"cellbridge replay: {path}: no message for {step:.1f} s of the recording after message {n} "
            f"(the daemon stopped, or the clock stepped while recording): waiting {wait:.1f} s (--max-gap)")


def run(args: argparse.Namespace) -> int:
    rate = 0.0 if args.fast else args.rate
    try:
        pacer = Pacer(rate, args.max_gap)
    except ValueError as exc:
        print(f"cellbridge replay: {exc}", file=sys.stderr)
        return 2
    if args.hwm < 1:  # libzmq reads 0 as no limit: a subscriber that stops reading would grow the replay for ever
        print(f"cellbridge replay: --hwm must be at least 1, got {args.hwm}", file=sys.stderr)
        return 2
    for p in args.inputs:
        if not p.is_file():
            what = "not a regular file (a FIFO, a device or a directory)" if p.exists() else "no such file"
            print(f"cellbridge replay: {p}: {what}", file=sys.stderr)
            return 2
    topics = {t.strip() for t in args.topics.split(",") if t.strip()} or None
    unknown = sorted((topics or set()) - set(SCHEMAS))
    if unknown:  # a typo ('contacts') replayed nothing, exit 0 (a newer daemon's topic: replayed by default)
        print(f"cellbridge replay: --topics: the daemon has no topic {unknown[0]!r} (topics: "
              f"{', '.join(sorted(SCHEMAS))})", file=sys.stderr)
        return 2
    stop: list[bool] = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(True))
    ctx = zmq.Context()
    sock = ctx.socket(zmq.XPUB)
    sock.sndhwm = args.hwm
    sock.linger = 2000
    sent = 0
    late = Lateness()  # how late each paced message went out after it was due (what the replay adds to timing)
    notes: list[str] = []
    gaps = 0
    ahead = Ahead(args.inputs, topics)
    problems = 0  # of ahead.problems, printed
    try:
        sock.bind(args.endpoint)
        if args.wait_subscriber:
            while not stop:
                if sock.poll(100) and sock.recv()[:1] == b"\x01":
                    break
        gc.disable()  # decoded payloads hold no cycles; a collection would only delay a message
        t0 = time.monotonic()
        while not stop:
            if not ahead.queue and not ahead.prepare():
                break
            topic, payload, recorded, path = ahead.popleft()
            due = pacer.due(recorded, time.monotonic())
            if pacer.notice is not None:
                gaps += 1
                if gaps <= NOTICES:
                    print(_gap_notice(path, sent, *pacer.notice), file=sys.stderr, flush=True)
            for line in ahead.problems[problems:]:  # a file that ended damaged, as soon as it is known
                print(f"cellbridge replay: {line}", file=sys.stderr, flush=True)
            problems = len(ahead.problems)
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
                late.add(time.monotonic() - due)
            sent += 1
        notes += ahead.notes
        elapsed = time.monotonic() - t0
    except zmq.ZMQError as exc:
        print(f"cellbridge replay: {endpoint_error(args.endpoint, exc)}", file=sys.stderr)
        return 2
    finally:
        sock.close()
        ctx.term()
    gc.enable()
    for line in ahead.problems[problems:]:
        print(f"cellbridge replay: {line}", file=sys.stderr)
    print(json.dumps({"sent": sent, "seconds": round(elapsed, 3), "incomplete": notes, "skipped": ahead.skipped,
                      "damaged": len(ahead.problems), "gaps": gaps, "late_ms": late.summary()}),
          file=sys.stderr)
    return 1 if ahead.problems else 0


class Lateness:
    """How late paced messages went out, in bounded memory whatever the recording's length
    (a value per message was ~1.6 GB over a 3-day recording): the exact maximum, and p50
    and p99 from a uniform sample of at most :data:`SAMPLE` of them (reservoir sampling)."""

    SAMPLE = 100_000

    def __init__(self) -> None:
        self.n = 0
        self.max = -math.inf
        self.sample: list[float] = []
        self._random = random.Random(0)

    def add(self, late: float) -> None:
        self.n += 1
        self.max = max(self.max, late)
        if len(self.sample) < self.SAMPLE:
            self.sample.append(late)
        else:
            k = self._random.randrange(self.n)
            if k < self.SAMPLE:
                self.sample[k] = late

    def summary(self) -> dict[str, float]:
        """p50, p99 and max (ms); empty when no message was paced."""
        if not self.n:
            return {}
        xs = sorted(self.sample)
        q = (lambda f: round(xs[min(len(xs) - 1, int(f * len(xs)))] * 1e3, 3))
        return {"p50": q(0.5), "p99": q(0.99), "max": round(self.max * 1e3, 3)}


def _drain_subscriptions(sock: zmq.Socket) -> None:
    """An XPUB reports (un)subscriptions; read them so they never pile up."""
    try:
        while True:
            sock.recv(zmq.NOBLOCK)
    except zmq.Again:
        pass
