"""``cellbridge record OUT.mcap``: subscribe to a daemon, keep its messages in MCAP.

The shell around :class:`cellbridge.recording.recorder.Recorder`: one SUB socket, the
signals, and a line of counters at the end. SIGINT and SIGTERM finish the file (summary
and index) and exit 0; a failed write (disk full) is reported and exits 1.

A message's publish time in the file is when it left ZeroMQ here, and ``cellbridge
replay`` reproduces those intervals. It is read on :class:`EpochClock`: the wall clock's
time at the recorder's start, then the monotonic clock's, so that a wall-clock step (NTP,
an operator) while recording never becomes a pause, or a burst, in a replay. A thread of its own (:class:`Receiver`) takes
messages off the socket and stamps them, while the main thread encodes them and writes
chunks: a chunk's compression, write and fsync (milliseconds, tens of them on a busy disk)
no longer hold back the stamps of the messages that arrive meanwhile.
"""

from __future__ import annotations

import argparse
import glob
import json
import math
import os
import queue
import signal
import socket
import sys
import threading
import time
from pathlib import Path

import zmq

from cellbridge._version import __version__
from cellbridge.daemon.ops.security import apply_client, endpoint_error
from cellbridge.daemon.shell.subscribe import QUIET_S, health_probe
from cellbridge.recording.mcapfile import MAX_CHUNK_SIZE, RecordingWriter
from cellbridge.recording.recorder import Recorder
from cellbridge.ros2.record import add_profile_arguments

DEFAULT_PUB = "tcp://127.0.0.1:5560"
ALL_TOPICS = ("contact", "element", "raw", "health", "topology", "serial")
DEFAULT_TOPICS = ("contact", "element", "health", "topology")
#: Messages stamped but not yet written that the receiver holds before it leaves the rest in
#: ZeroMQ's queue (bounded by its high-water mark; what overflows shows as ``missed``).
BACKLOG = 100_000
#: ... and bytes of them: past this the receiver goes on taking messages off the socket but
#: keeps none (they show as ``missed``), so that neither its queue nor ZeroMQ's, bounded in
#: messages only, grows by the size of large ones (100 000 of 500 kB are 50 GB).
BACKLOG_BYTES = 256 << 20
#: Messages ZeroMQ itself queues for the receiver: the deep queue (a slow disk moment must
#: not cost messages) is the receiver's, bounded in bytes too; ZeroMQ's, bounded in messages
#: only, held 100 000 of any size whenever the receiver waited for a core (a loaded machine).
RCVHWM = 1000
#: The interpreter's thread switch interval while recording (default 5 ms): the receiver
#: gets the GIL within this while the writer encodes JSON, so a stamp is at most this late.
SWITCH_INTERVAL = 0.0005


class EpochClock:
    """Seconds since the epoch that a wall-clock step never moves: the wall clock's reading
    when made, advanced from then on by the monotonic clock."""

    def __init__(self) -> None:
        self._base = time.time() - time.monotonic()

    def __call__(self) -> float:
        return self._base + time.monotonic()


class Receiver(threading.Thread):
    """Takes messages off the SUB socket as they come and stamps them (``clock``).

    Hands ``(parts, time received)`` to :meth:`get`; the socket is this thread's alone once
    started. Holds at most :data:`BACKLOG` messages and :data:`BACKLOG_BYTES` bytes not yet
    taken. Stops when :attr:`stop` is set (within 0.1 s).
    """

    def __init__(self, sock: zmq.Socket, clock: EpochClock) -> None:
        super().__init__(name="record-receiver", daemon=True)
        self.sock = sock
        self.clock = clock
        self.messages: queue.SimpleQueue[tuple[list[bytes], float, int]] = queue.SimpleQueue()
        self.stop = threading.Event()
        self.error: zmq.ZMQError | None = None
        self._put_bytes = 0  # (this thread's)
        self._taken_bytes = 0  # (the taker's)
        self.discarded = 0  #: messages taken off the socket and not kept: over BACKLOG_BYTES

    @property
    def backlog_bytes(self) -> int:
        return self._put_bytes - self._taken_bytes

    def get(self, timeout: float | None = None) -> tuple[list[bytes], float]:
        """The next message and its time received (``queue.Empty`` after ``timeout``; 0: none waiting)."""
        parts, now, size = self.messages.get(timeout=timeout) if timeout != 0 else self.messages.get_nowait()
        self._taken_bytes += size
        return parts, now

    def run(self) -> None:
        try:
            while not self.stop.is_set():
                if self.messages.qsize() >= BACKLOG:  # the writer is behind: leave the rest to ZeroMQ's queue
                    time.sleep(0.01)
                    continue
                if not self.sock.poll(100):
                    continue
                while self.messages.qsize() < BACKLOG:
                    try:
                        parts = self.sock.recv_multipart(zmq.NOBLOCK)
                    except zmq.Again:
                        break
                    size = sum(len(p) for p in parts)
                    if self.backlog_bytes + size > BACKLOG_BYTES:  # far behind on large messages: not kept
                        self.discarded += 1
                        continue
                    self._put_bytes += size
                    self.messages.put((parts, self.clock(), size))
        except zmq.ZMQError as exc:
            self.error = exc


def add_curve_client_arguments(parser: argparse.ArgumentParser, what: str = "the daemon") -> None:
    parser.add_argument("--server-key", type=Path, metavar="FILE",
                        help=f"{what}'s public key file (NAME.key) when it runs with CURVE")
    parser.add_argument("--client-key", type=Path, metavar="FILE",
                        help=f"this client's secret key file (NAME.key_secret); its NAME.key must be allowed by {what}")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.description = (
        "Subscribe to a daemon and write what it publishes into an MCAP file (JSON messages\n"
        "with JSON Schemas: Foxglove opens it), chunked and zstd-compressed. Log time is each\n"
        "message's t_host, publish time when it was received. Ctrl-C or SIGTERM finish the file;\n"
        "a recorder killed outright leaves a file readable up to its last whole chunk\n"
        "(chunks are finished every --chunk-seconds). A full disk stops the recording with a\n"
        "message and exit status 1; the daemon is not affected. Publish times follow the\n"
        "monotonic clock from the wall clock's time at the start: a clock step while\n"
        "recording does not show in a replay. The line of counters at the end counts what\n"
        "was not recorded as received: malformed (not [topic, msgpack map]), bad_time\n"
        "(t_host no time: recorded with its receive time), oversized (not written), dropped,\n"
        "unconfirmed, missed (gaps in seq), restarts (the daemon's), behind (received while the writer was over 256 MB\n"
        "behind: not kept, and missed). The file is made with the first message recorded: with none\n"
        "(no daemon there?) nothing is written, a line says so, and the exit status is 1.\n\n"
        "Topics: contact, element, raw, health, topology, and serial (each gateway read's bytes:\n"
        "a daemon can later be run on them, link url replay:FILE.mcap). Default: all but raw\n"
        "and serial.\n\n"
        "examples:\n"
        "  cellbridge record skin.mcap                       # contact, element, health, topology\n"
        "  cellbridge record skin.mcap --serial              # ... and the gateway lines' bytes\n"
        "  cellbridge record skin.mcap --topics contact      # contacts only\n"
        "  cellbridge record skin.mcap --rotate-size 500     # skin-0000.mcap, skin-0001.mcap, ... of 500 MB\n"
        "  cellbridge record skin.mcap --rotate-minutes 60   # a file an hour\n"
        "  cellbridge record skin --profile ros2             # a ROS 2 bag, the directory skin/ (docs/ros2.md)"
    )
    parser.add_argument("out", type=Path, metavar="OUT.mcap", help="file to write (with rotation: OUT-NNNN.mcap)")
    parser.add_argument("--endpoint", default=DEFAULT_PUB, help=f"daemon's PUB endpoint (default: {DEFAULT_PUB})")
    parser.add_argument("--topics", default=",".join(DEFAULT_TOPICS),
                        help=f"comma-separated topics, or 'all' (default: {','.join(DEFAULT_TOPICS)})")
    parser.add_argument("--raw", action="store_true", help="also record the raw topic")
    parser.add_argument("--serial", action="store_true", help="also record the gateway lines' bytes (serial)")
    parser.add_argument("--rotate-size", type=float, default=0.0, metavar="MB",
                        help="start a new file when the current one reaches this size (default: never)")
    parser.add_argument("--rotate-minutes", type=float, default=0.0, metavar="MIN",
                        help="start a new file after this many minutes (default: never)")
    parser.add_argument("--chunk-size", type=float, default=1.0, metavar="MB",
                        help=f"uncompressed chunk size (default: 1 MB, at most {MAX_CHUNK_SIZE / 1e6:g}: "
                             "readers bound the chunks they decompress)")
    parser.add_argument("--chunk-seconds", type=float, default=1.0, metavar="S",
                        help="finish a chunk at least this often: the most a kill can lose (default: 1 s)")
    parser.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd",
                        help="chunk compression (default: zstd)")
    parser.add_argument("--no-fsync", action="store_true",
                        help="do not fsync on each chunk (faster; a power loss may lose more than a chunk)")
    parser.add_argument("--force", action="store_true",
                        help="replace an earlier recording of that name (with rotation: OUT-NNNN.mcap); "
                             "without it, one is refused (a ROS 2 bag is always a new directory)")
    parser.add_argument("--count", type=int, default=None, metavar="N",
                        help="stop after N messages (default: until Ctrl-C)")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="stop after S seconds (default: until Ctrl-C)")
    add_curve_client_arguments(parser)
    add_profile_arguments(parser)


def topics_of(args: argparse.Namespace) -> list[str]:
    names = ALL_TOPICS if args.topics == "all" else [t.strip() for t in args.topics.split(",") if t.strip()]
    unknown = [t for t in names if t not in ALL_TOPICS]
    if unknown:
        raise ValueError(f"unknown topic {unknown[0]!r} (known: {', '.join(ALL_TOPICS)}, or all)")
    out = list(dict.fromkeys([*names, *(["raw"] if args.raw else []), *(["serial"] if args.serial else [])]))
    if not out:
        raise ValueError("no topic to record")
    return out


def limits_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with ``--count`` and ``--duration``, or None. Left out, each means no
    limit; 0 is refused, as ``cellbridge sub --count 0`` is (it ran until Ctrl-C, silently)."""
    if args.count is not None and args.count < 1:
        return f"--count must be at least 1, got {args.count} (leave it out to record until Ctrl-C)"
    if args.duration is not None and not 0 < args.duration < float("inf"):  # (False for NaN)
        return f"--duration must be more than 0 seconds, got {args.duration:g} (leave it out to record until Ctrl-C)"
    return None


def earlier_recording(out: Path, rotating: bool) -> Path | None:
    """A file a recording to ``out`` would replace: ``out`` itself, or with rotation the
    first ``OUT-NNNN.mcap`` there is; None when there is none."""
    if not rotating:
        return out if os.path.lexists(out) else None
    pattern = f"{glob.escape(out.stem)}-[0-9][0-9][0-9][0-9]{glob.escape(out.suffix or '.mcap')}"
    return next(iter(sorted(out.parent.glob(pattern))), None)


def numbers_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with the sizes and times of ``args`` (both profiles; the limits are
    :func:`limits_problem`'s), or None. Each is a finite number (``nan`` passed a check of
    ``< 0`` and then stopped nothing: ``--chunk-seconds nan`` never finished a chunk on time)."""
    for option, value in (("--rotate-size", args.rotate_size), ("--rotate-minutes", args.rotate_minutes),
                          ("--chunk-size", args.chunk_size), ("--chunk-seconds", args.chunk_seconds)):
        if not math.isfinite(value) or value < 0:
            return f"{option} {value:g}: not a number of 0 or more"
    if args.chunk_size <= 0:
        return "--chunk-size must be more than 0"
    if args.chunk_size * 1e6 > MAX_CHUNK_SIZE:
        return (f"--chunk-size {args.chunk_size:g} MB: at most {MAX_CHUNK_SIZE / 1e6:g} MB "
                "(readers bound the chunks they decompress)")
    return None


def run(args: argparse.Namespace) -> int:
    problem = limits_problem(args)
    if args.force and args.profile == "ros2":
        problem = "--force replaces an MCAP recording; a ROS 2 bag is always a new directory (remove the old one)"
    if problem:
        print(f"cellbridge record: {problem}", file=sys.stderr)
        return 2
    if args.profile == "ros2":
        from cellbridge.ros2 import record as ros2_record
        return ros2_record.run(args)
    if (args.server_key is None) != (args.client_key is None):
        print("cellbridge record: --server-key and --client-key go together (CURVE needs both)", file=sys.stderr)
        return 2
    try:
        topics = topics_of(args)
    except ValueError as exc:
        print(f"cellbridge record: {exc}", file=sys.stderr)
        return 2
    problem = numbers_problem(args)
    if problem:
        print(f"cellbridge record: {problem}", file=sys.stderr)
        return 2
    earlier = None if args.force else earlier_recording(args.out, int(args.rotate_size * 1e6) > 0 or args.rotate_minutes > 0)
    if earlier is not None:
        print(f"cellbridge record: {earlier} exists (an earlier recording?): choose another name, or add --force "
              "to replace it", file=sys.stderr)
        return 2
    meta = {"endpoint": args.endpoint, "topics": ",".join(topics), "recorder_host": socket.gethostname(),
            "cellbridge_version": __version__, "started": f"{time.time():.6f}"}

    def opener(path: Path) -> RecordingWriter:
        return RecordingWriter(path, chunk_size=int(args.chunk_size * 1e6), compression=args.compression,
                               fsync=not args.no_fsync, metadata=meta)

    rec = Recorder(args.out, opener, rotate_bytes=int(args.rotate_size * 1e6),
                   rotate_seconds=args.rotate_minutes * 60, chunk_seconds=args.chunk_seconds, topics=set(topics))
    clock = EpochClock()
    stop = []
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.append(True))
    ctx = zmq.Context()
    sock = ctx.socket(zmq.SUB)
    sock.linger = 0
    sock.rcvhwm = RCVHWM
    # Retry a daemon not yet bound every 10 ms, not ZeroMQ's 100: a recorder started first
    # then has the daemon's first messages too (the first read's serial bytes among them).
    sock.reconnect_ivl = 10
    receiver: Receiver | None = None
    probe: zmq.Socket | None = None
    switch = sys.getswitchinterval()
    total = 0
    try:
        if args.server_key is not None:
            apply_client(sock, args.server_key, args.client_key)
        for t in topics:
            sock.subscribe(t)
        sock.connect(args.endpoint)
        probe = health_probe(ctx, args)  # (a daemon runs when its health comes, whatever the topics recorded)
        sys.setswitchinterval(SWITCH_INTERVAL)
        receiver = Receiver(sock, clock)
        receiver.start()
        started = time.monotonic()
        end = None if args.duration is None else started + args.duration

        def take(parts: list[bytes], now: float) -> None:
            if len(parts) != 2:
                rec.malformed += 1
            else:
                rec.feed(parts[0].decode("ascii", "replace"), parts[1], now)

        while not stop and not rec.stopped and (args.count is None or total < args.count):
            if end is not None and time.monotonic() >= end:
                break
            if receiver.error is not None:
                raise receiver.error
            try:
                parts, now = receiver.get(timeout=0.1)
            except queue.Empty:
                rec.tick(clock())
                if probe is not None and time.monotonic() - started >= QUIET_S:
                    if not total and not probe.poll(0):  # (a recorder started before its daemon is right: it waits on)
                        print(f"cellbridge record: nothing in {QUIET_S:g} s from {args.endpoint}, not even its "
                              "health: is the daemon running? (waiting on: the file is made with the first "
                              "message; Ctrl-C stops)", file=sys.stderr, flush=True)
                    probe.close()
                    probe = None
                continue
            total += 1
            take(parts, now)
            if probe is not None:  # a message came: the daemon is there
                probe.close()
                probe = None
        receiver.stop.set()
        receiver.join()
        if stop and not rec.stopped:  # what was received before the signal goes into the file too
            while args.count is None or total < args.count:
                try:
                    parts, now = receiver.get(timeout=0)
                except queue.Empty:
                    break
                total += 1
                take(parts, now)
        if rec.stopped:  # received, never written: counted with the recorder's drops
            rec.dropped += receiver.messages.qsize()
    except ValueError as exc:
        print(f"cellbridge record: {exc}", file=sys.stderr)
        return 2
    except zmq.ZMQError as exc:
        print(f"cellbridge record: {endpoint_error(args.endpoint, exc)}", file=sys.stderr)
        return 2
    finally:
        if receiver is not None:
            receiver.stop.set()
            receiver.join()
        sys.setswitchinterval(switch)
        if probe is not None:
            probe.close()
        sock.close()
        ctx.term()
        rec.close()
        print(json.dumps({**rec.stats(), "behind": receiver.discarded if receiver is not None else 0}),
              file=sys.stderr)
    if rec.error:
        print(f"cellbridge record: {rec.error}", file=sys.stderr)
        return 1
    if not rec.files:  # the file is made with the first message recorded
        what = (f"nothing received from {args.endpoint}" if not total else
                f"none of the {total} messages received could be recorded")
        print(f"cellbridge record: {what}: {args.out} not written", file=sys.stderr)
        return 1
    return 0
